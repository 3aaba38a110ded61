"""Closed-form form factors (Howell's catalog, Lambert's polygon formula) as torch functions.

They are the ground truth the hemicube is tested against, and, being torch expressions,
differentiable: the derivative of the point-to-polygon factor with respect to the point is
the reference for the gradients of the adaptive mesher.
"""
from __future__ import annotations

import math

import torch


def _t(x) -> torch.Tensor:
    return torch.as_tensor(x, dtype=torch.float64)


def parallel_rectangles(a, b, c) -> torch.Tensor:
    """Form factor between directly opposed, parallel a x b rectangles at distance c."""
    X, Y = _t(a) / c, _t(b) / c
    one = torch.ones_like(X)
    sx, sy = torch.sqrt(one + X**2), torch.sqrt(one + Y**2)
    return 2.0 / (math.pi * X * Y) * (
        torch.log(torch.sqrt((1 + X**2) * (1 + Y**2) / (1 + X**2 + Y**2)))
        + X * sy * torch.atan(X / sy)
        + Y * sx * torch.atan(Y / sx)
        - X * torch.atan(X)
        - Y * torch.atan(Y)
    )


def perpendicular_rectangles(h, w, l) -> torch.Tensor:
    """Form factor from a w x l rectangle to an h x l one at right angles, sharing the edge l."""
    H, W = _t(h) / l, _t(w) / l
    A = (1 + W**2) * (1 + H**2) / (1 + W**2 + H**2)
    B = W**2 * (1 + W**2 + H**2) / ((1 + W**2) * (W**2 + H**2))
    C = H**2 * (1 + W**2 + H**2) / ((1 + H**2) * (W**2 + H**2))
    r = torch.sqrt(H**2 + W**2)
    return (1.0 / (math.pi * W)) * (
        W * torch.atan(1 / W) + H * torch.atan(1 / H) - r * torch.atan(1 / r)
        + 0.25 * (torch.log(A) + W**2 * torch.log(B) + H**2 * torch.log(C))
    )


def point_to_polygon(point: torch.Tensor, normal: torch.Tensor, polygon: torch.Tensor) -> torch.Tensor:
    """Lambert's differential-area-to-polygon form factor.

    Args:
        point: (3,) the differential area's position.
        normal: (3,) its unit normal.
        polygon: (N, 3) the polygon's vertices in order (either winding), wholly above the
            point's tangent plane.
    Returns:
        () the form factor; differentiable in all inputs.
    """
    R = polygon - point  # (N, 3)
    R_next = torch.roll(R, shifts=-1, dims=0)
    cross = torch.linalg.cross(R, R_next)  # (N, 3)
    cross_norm = cross.norm(dim=1)
    theta = torch.atan2(cross_norm, (R * R_next).sum(dim=1))
    return ((theta * (cross @ normal) / cross_norm).sum() / (2 * math.pi)).abs()
