"""Colour conventions shared by the solver, the refinement criteria and the display."""
from __future__ import annotations

import torch

from hemirad.core.device import as_tensor

# Rec. 709 / sRGB primaries: relative luminance of linear RGB.
REC709_LUMINANCE = (0.2126, 0.7152, 0.0722)
LUMENS_PER_WATT = 683.0

#: Luminous efficacy at 555 nm (lm/W), the SI definition of the candela: a radiometric
#: quantity (W/m^2, or W/(m^2 sr)) times this, with its colour weighted by ``luminance``,
#: is the photometric one (lx, or cd/m^2).
LUMENS_PER_WATT = 683.0


def luminance(rgb: torch.Tensor) -> torch.Tensor:
    """(..., 3) linear RGB -> (...) relative luminance (Rec. 709 weights)."""
    rgb = as_tensor(rgb)
    weights = torch.tensor(REC709_LUMINANCE, dtype=rgb.dtype if rgb.is_floating_point() else torch.float64,
                           device=rgb.device)
    return rgb.to(weights.dtype) @ weights
