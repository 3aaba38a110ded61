"""Delta form factors of the hemicube and their sums per element (pure torch).

The atlas layout is ``hemicube.py``'s: a (3R, R) image holding the top face and the four
half-height side faces, rows bottom-up inside each face.
"""
from __future__ import annotations

import math

import torch

from hemirad.core.device import cached_per_device
from hemirad.core.fastops import on_host
from hemirad.transport.hemicube import FACES, face_viewports


@cached_per_device
def hemicube_directions(resolution: int) -> torch.Tensor:
    """Unnormalised directions through every pixel centre, in the hemicube's local frame.

    A pixel of a face with axes (forward f, right r, up u) at image coordinates (sx, sy)
    lies at f + sx r + sy u, on the unit cube around the eye.

    Returns:
        (3R, R, 3) float64 (on ``device``, the second argument); do not modify (cached).
    """
    R = resolution
    out = torch.empty(3 * R, R, 3, dtype=torch.float64)
    sx = -1 + (torch.arange(R, dtype=torch.float64) + 0.5) * (2.0 / R)  # pixel centres
    for (forward, right, up, bottom), (_, y0, _, height) in zip(FACES, face_viewports(R)):
        sy = bottom + (torch.arange(height, dtype=torch.float64) + 0.5) * (2.0 / R)
        f, r, u = (torch.tensor(v, dtype=torch.float64) for v in (forward, right, up))
        out[y0:y0 + height] = f + sx[None, :, None] * r + sy[:, None, None] * u
    return out


def raw_delta_form_factors(resolution: int) -> torch.Tensor:
    """The textbook point-sampled weights of every pixel (docs/DESIGN.md §1).

    For the pixel at d = (x, y, z) on the unit cube, cos at the eye is z / |d| and cos at the
    pixel's face is 1 / |d|, so dF = z dA / (pi |d|^4) with dA = (2/R)^2: this is
    dA / (pi (x^2 + y^2 + 1)^2) on the top face and z dA / (pi (x^2 + z^2 + 1)^2) on a side.
    Their sum differs from 1 by the midpoint rule's O(1/R^2) error.

    Returns:
        (3R, R) float64.
    """
    d = hemicube_directions(resolution)
    r2 = (d * d).sum(dim=-1)
    return d[..., 2] * (2.0 / resolution) ** 2 / (math.pi * r2 * r2)


@cached_per_device
def delta_form_factors(resolution: int) -> torch.Tensor:
    """The raw weights scaled to sum to exactly 1, so a closed scene conserves energy to rounding.

    Returns:
        (3R, R) float64 (on ``device``, the second argument: the same numbers on every
        device); do not modify (cached).
    """
    w = raw_delta_form_factors(resolution)
    return w / w.sum()


def element_form_factors(element: torch.Tensor, front: torch.Tensor, weights: torch.Tensor,
                         num_elements: int) -> torch.Tensor:
    """F_sj: the sum of the delta form factors of the pixels that see the front of element j.

    Args:
        element: (P,) or (3R, R) int32 or int64 element index per pixel.
        front: same shape, bool, pixel sees a front face.
        weights: same shape, float64 delta form factors.
    Returns:
        (num_elements,) float64.
    """
    return form_factors_and_back_share(element, front, weights, num_elements)[0]


def form_factors_and_back_share(element: torch.Tensor, front: torch.Tensor, weights: torch.Tensor,
                                num_elements: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``element_form_factors``, and () the share of the weights whose pixels see a back face,
    from one sum over the pixels: every pixel in it, those that see no front summed into one
    more bin (``num_elements``), those that see nothing with weight zero. A front's sum adds
    the same pixels in the same order as its own would (x + 0 = x: bit for bit), without
    compacting the atlas by a mask (several times slower)."""
    element, front, weights = element.reshape(-1), front.reshape(-1), weights.reshape(-1)
    sums = sum_by_index(torch.where(front, element, num_elements), torch.where(element >= 0, weights, 0.0),
                        num_elements + 1)
    return sums[:num_elements], sums[num_elements]


def sum_by_index(index: torch.Tensor, values: torch.Tensor, size: int) -> torch.Tensor:
    """(size,) the sum of the (N,) ``values`` at each of their (N,) ``index``.

    On the CPU a bincount (a sequential sum in pixel order); on CUDA an index_add, which
    ``runtime.deterministic`` makes sum in a fixed order (bincount has no such mode).
    """
    if on_host(index):
        return torch.bincount(index, weights=values, minlength=size)
    return torch.zeros(size, dtype=values.dtype, device=values.device).index_add_(0, index, values)
