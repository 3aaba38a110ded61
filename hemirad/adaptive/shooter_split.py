"""Whether a shooter's centroid is a poor stand-in for its extent: the paper's eq. 7 turned
from the receivers onto the shooter (docs/DESIGN.md §3.7).

B_jk = grad B_j . (P_k - G) is how much receiver j's radiosity would change had the
shooter's power left from its corner P_k instead of its centroid G. Where that change is a
large share of what j receives from the shot, one hemicube at G misplaces the light (a
penumbra drawn as a hard shadow, a floor beside a wall lit as if by a point), and the
shooter should shoot from its parts instead (``transport.shooters``).
"""
from __future__ import annotations

import torch

from hemirad.adaptive.gradient import form_factor_gradient
from hemirad.transport.view import HemicubeView


def point_source_error(view: HemicubeView, corners: torch.Tensor, significant: float = 1e-3) -> torch.Tensor:
    """(T,) per receiver, max_k |dF_sj/dc . (P_k - G)| / F_sj: the first-order change of its
    form factor, as a share of it, had the shooter shot from one of its corners; 0 where
    F_sj is under ``significant`` times the largest F_sj (what it gets hardly matters).

    Args:
        view: the shooter's render at its centroid G (its eye just off G).
        corners: (K, 3) the corners P_k of the shooter's elements.
    """
    F = view.form_factors
    counted = F > significant * float(F.max()) if len(F) else F > 0
    J = form_factor_gradient(view, wanted=counted)  # (T, 3), interior and shadow-edge terms
    offsets = corners - view.eye  # (K, 3); the eye's offset off the plane is ~1e-6 of the scene
    change = (J @ offsets.T).abs().amax(dim=1)  # (T,)
    return torch.where(counted, change / F.clamp(min=1e-300), torch.zeros_like(F))


def point_source_test(threshold: float):
    """A ``transport.shooters.ShooterTest``: shoot from the parts where some receiver's
    ``point_source_error`` exceeds ``threshold``."""
    def test(view: HemicubeView, corners: torch.Tensor) -> bool:
        return bool((point_source_error(view, corners) > threshold).any())

    return test
