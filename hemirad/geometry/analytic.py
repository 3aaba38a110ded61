"""Closed-form form factors (Howell's catalog, Lambert's polygon formula) as torch functions.

They are the ground truth the hemicube is tested against, and, being torch expressions,
differentiable: the derivative of the point-to-polygon factor with respect to the point is
the reference for the gradients of the adaptive mesher.
"""
from __future__ import annotations

import math

import torch

from hemirad.core.device import as_tensor


def _t(x) -> torch.Tensor:
    return as_tensor(x, dtype=torch.float64)


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


def point_to_triangles(point: torch.Tensor, normal: torch.Tensor, triangles: torch.Tensor) -> torch.Tensor:
    """Unoccluded form factors from a differential area to many triangles at once.

    Each triangle is first clipped to the half-space above the point's tangent plane (what a
    hemicube can see), then Lambert's formula is summed over the clipped polygon's edges.

    Args:
        point: (3,), or (T, 1, 3) a point per triangle; normal: (3,) unit; triangles: (T, 3, 3).
    Returns:
        (T,) form factors, >= 0.
    """
    T = len(triangles)
    d = (triangles - point) @ normal  # (T, 3) heights above the tangent plane
    nxt = torch.tensor([1, 2, 0], device=triangles.device)
    d0, d1 = d, d[:, nxt]
    v0, v1 = triangles, triangles[:, nxt]
    crossing = (d0 > 0) != (d1 > 0)
    s = torch.where(crossing, d0 / torch.where(crossing, d0 - d1, torch.ones_like(d0)), torch.zeros_like(d0))
    cut = v0 + s[..., None] * (v1 - v0)
    # Sutherland-Hodgman in fixed slots: [v0, cut01, v1, cut12, v2, cut20], kept in order.
    candidates = torch.stack([v0, cut], dim=2).reshape(T, 6, 3)
    valid = torch.stack([d0 > 0, crossing], dim=2).reshape(T, 6)
    slot = torch.arange(6, device=triangles.device).expand(T, 6)
    order = torch.argsort(torch.where(valid, slot, slot + 6), dim=1, stable=True)
    polygon = torch.gather(candidates, 1, order[..., None].expand(T, 6, 3))
    count = valid.sum(1, keepdim=True)  # (T, 1) vertices of the clipped polygon, 0 to 4
    following = torch.gather(polygon, 1, ((slot + 1) % count.clamp(min=1))[..., None].expand(T, 6, 3))
    R, R_next = polygon - point, following - point
    cross = torch.linalg.cross(R, R_next)
    cross_norm = cross.norm(dim=-1)
    theta = torch.atan2(cross_norm, (R * R_next).sum(-1))
    edge = (slot < count) & (cross_norm > 0)
    term = torch.where(edge, theta * (cross @ normal) / torch.where(edge, cross_norm, torch.ones_like(cross_norm)),
                       torch.zeros_like(theta))
    return (term.sum(1) / (2 * math.pi)).abs()
