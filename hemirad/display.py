"""From element radiosity to displayable values: vertex averaging, exposure and sRGB encoding.

Element values are constant over each triangle. For display they are averaged to the
vertices and interpolated (Gouraud). Vertices are shared only inside one surface, so the
averaging never blends across a crease or between objects, and a T-vertex (a vertex of a
split neighbour lying on an unsplit element's edge) simply gets the value of the elements
it belongs to.

Everything here is pure torch/numpy; nothing touches OpenGL.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from .mesh import Mesh

# Rec. 709 / sRGB primaries: relative luminance of linear RGB.
REC709_LUMINANCE = (0.2126, 0.7152, 0.0722)

# Linear display value that the mean scene luminance is mapped to by automatic exposure.
MIDDLE_GREY = 0.18


def vertex_values(mesh: Mesh, element_values: torch.Tensor) -> torch.Tensor:
    """Area-weighted mean of the values of the elements incident to each vertex.

    Args:
        mesh: the mesh; its triangles index its vertices.
        element_values: (T, C) or (T,) one value per element.

    Returns:
        (V, C) or (V,) matching ``element_values``. A vertex whose incident elements all
        have zero area gets their plain mean; a vertex no triangle uses gets 0.
    """
    values = torch.as_tensor(element_values)
    if not values.is_floating_point():
        values = values.to(torch.float64)
    squeeze = values.dim() == 1
    if squeeze:
        values = values[:, None]
    if values.shape[0] != mesh.num_elements:
        raise ValueError(f"need one value per element ({mesh.num_elements}), got {values.shape[0]}")

    num_vertices = len(mesh.vertices)
    corner_vertex = mesh.triangles.reshape(-1)  # (3T,) vertex of each triangle corner
    areas = mesh.areas.to(values.dtype)
    # Every corner contributes its triangle's value, weighted by the triangle's area.
    corner_weight = areas.repeat_interleave(3)  # (3T,)
    corner_value = values.repeat_interleave(3, dim=0)  # (3T, C)

    weighted_sum = values.new_zeros(num_vertices, values.shape[1]).index_add_(
        0, corner_vertex, corner_weight[:, None] * corner_value)
    weight_sum = values.new_zeros(num_vertices).index_add_(0, corner_vertex, corner_weight)
    # Fallback for vertices whose elements are all degenerate: the unweighted mean.
    plain_sum = values.new_zeros(num_vertices, values.shape[1]).index_add_(0, corner_vertex, corner_value)
    count = values.new_zeros(num_vertices).index_add_(0, corner_vertex, torch.ones_like(corner_weight))

    has_area = weight_sum > 0
    result = torch.where(
        has_area[:, None],
        weighted_sum / torch.where(has_area, weight_sum, 1.0)[:, None],
        plain_sum / count.clamp_min(1.0)[:, None],
    )
    return result[:, 0] if squeeze else result


def luminance(rgb: torch.Tensor) -> torch.Tensor:
    """(..., 3) linear RGB -> (...) relative luminance (Rec. 709 weights)."""
    rgb = torch.as_tensor(rgb)
    weights = torch.tensor(REC709_LUMINANCE, dtype=rgb.dtype if rgb.is_floating_point() else torch.float64)
    return rgb.to(weights.dtype) @ weights


def auto_exposure(element_values: torch.Tensor, areas: torch.Tensor, emitting: torch.Tensor) -> float:
    """A display scale that maps the scene's mean luminance to middle grey (0.18, linear).

    The mean is area-weighted over the non-emitting elements: light sources are far
    brighter than what they light and would otherwise darken the whole image. If every
    element emits, all of them are used.

    Args:
        element_values: (T, 3) linear radiosity per element.
        areas: (T,) element areas.
        emitting: (T,) bool, True where the element has non-zero emission.

    Returns:
        The exposure (display value per unit radiosity); 1.0 when the mean is zero or not
        finite, so that a black scene stays black instead of producing inf or nan.
    """
    lum = luminance(torch.as_tensor(element_values, dtype=torch.float64))
    areas = torch.as_tensor(areas, dtype=torch.float64)
    mask = ~torch.as_tensor(emitting, dtype=torch.bool)
    if not bool(mask.any()):
        mask = torch.ones_like(mask)
    total_area = float(areas[mask].sum())
    if not total_area > 0:
        return 1.0
    mean = float((lum[mask] * areas[mask]).sum()) / total_area
    if not (math.isfinite(mean) and mean > 0):
        return 1.0
    return MIDDLE_GREY / mean


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """The exact sRGB transfer function (IEC 61966-2-1) on values in [0, 1]; same shape."""
    linear = np.asarray(linear, dtype=np.float64)
    # np.where evaluates both branches; the clamp keeps the power away from negative inputs.
    return np.where(
        linear <= 0.0031308,
        12.92 * linear,
        1.055 * np.power(np.maximum(linear, 0.0031308), 1.0 / 2.4) - 0.055,
    )


def to_srgb8(linear, exposure: float) -> np.ndarray:
    """Linear values -> 8-bit sRGB for display or export.

    Args:
        linear: (H, W, 3) or (N, 3) linear RGB, torch or numpy.
        exposure: display value per unit of ``linear`` (finite, >= 0).

    Returns:
        uint8 numpy array of the same shape: ``round(255 * srgb(clip(exposure * linear, 0, 1)))``.
        NaN inputs display as black.
    """
    if not (math.isfinite(exposure) and exposure >= 0):
        raise ValueError(f"exposure must be finite and >= 0, got {exposure!r}")
    if isinstance(linear, torch.Tensor):
        linear = linear.detach().cpu().numpy()
    scaled = np.asarray(linear, dtype=np.float64) * exposure
    scaled = np.clip(np.nan_to_num(scaled, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    return np.rint(255.0 * srgb_encode(scaled)).astype(np.uint8)
