"""Refinement criteria: per receiver, how wrong one shot's constant-per-element answer is.

Every criterion scores the elements at once from what a shot computed (``ShotContext``):
all of them, a (T,) tensor, or the rows asked for; the refiner splits the elements whose
score exceeds the threshold.
Scores are luminances of radiosity (Rec. 709 weights over RGB), except ``uniform``'s,
which is an edge length.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch

from hemirad.geometry.analytic import point_to_triangles
from hemirad.geometry.mesh import Mesh
from hemirad.scene.model import SHOT_CRITERION_NAMES


@dataclass
class ShotContext:
    """One shot, before it is committed.

    Attributes:
        mesh: the current mesh (T elements).
        shooter: the shooter (an element's index, or a patch tree's node: ``transport.shooters``).
        eye: (3,) the hemicube's centre; normal: (3,) the shooter's normal.
        form_factors: (T,) F_sj.
        luminance_per_form_factor: (T,) d(luminance of received)/dF_sj: the luminance of
            the radiosity this shot gives element j is F_sj times it.
        jacobian: (T, 3) dF_sj/dc (interior and/or shadow-edge terms), when the criterion
            needs it; zero outside ``candidates``.
        candidates: (T,) bool, the receivers this pass of the shot judges; None for all.
        shooter_offsets: (K, 3) the shooter's corners P_k less the point G it shoots from;
            None: the corners of element ``shooter`` less their mean. A patch shooting from
            its centroid (``transport.shooters``) gives its elements' corners.
    """

    mesh: Mesh
    shooter: int
    eye: torch.Tensor
    normal: torch.Tensor
    form_factors: torch.Tensor
    luminance_per_form_factor: torch.Tensor
    jacobian: torch.Tensor | None = None
    candidates: torch.Tensor | None = None
    shooter_offsets: torch.Tensor | None = None

    def __post_init__(self):
        if self.shooter_offsets is None:
            corners = self.mesh.corners_of(self.shooter)
            self.shooter_offsets = corners - corners.mean(0)  # (3, 3)


def _rows(values: torch.Tensor, rows: torch.Tensor | None) -> torch.Tensor:
    return values if rows is None else values.index_select(0, rows)


def _corners(ctx: ShotContext, rows: torch.Tensor | None) -> torch.Tensor:
    return ctx.mesh.corners if rows is None else ctx.mesh.corners_of(rows)


def gradient_score(ctx: ShotContext, rows: torch.Tensor | None = None) -> torch.Tensor:
    """The paper's eq. 7: max over the shooter's vertices P_k of |grad B_j . (P_k - G)|.

    The first-order change of what receiver j gets had the shooter's energy left from one
    of its corners instead of its centroid: large where a point source is a poor stand-in.
    """
    grad = _rows(ctx.luminance_per_form_factor, rows)[:, None] * _rows(ctx.jacobian, rows)  # (R, 3)
    return (grad @ ctx.shooter_offsets.T).abs().amax(dim=1)


def gradient_score_bound(ctx: ShotContext, rows: torch.Tensor, distance: torch.Tensor,
                         sine_sums: torch.Tensor) -> torch.Tensor:
    """(R,) an upper bound of the interior (frozen-visibility) part of ``gradient_score`` for
    the receivers ``rows``, from what the render gave without any hit point: where it is
    under the threshold, that part's Jacobian need not be computed.

    Each pixel's kernel K_q = w_q A B / (A0 B0) (r0 / r)^4, with A = n_s . (y - c) its height
    above the shooter's plane, B = n_j . (c - y) the eye's height above the receiver's plane
    and r = |y - c|, has the gradient K_q (-n_s / A + n_j / B + 4 (y - c) / r^2); at c0,
    K_q = w_q. The score dots the gradient with the shooter's corner offsets P_k - G, which
    lie in its plane, so only the gradient's part in that plane counts: n_s drops out, n_j
    leaves sin(alpha_j) (alpha_j between n_j and n_s) and y - c leaves r sin(theta_q)
    (theta_q the pixel ray's angle from n_s). Over a receiver B is one number and r >= B, so
    |P dF_sj/dc| <= (sin(alpha_j) F_sj + 4 sum_q w_q sin(theta_q)) / B.

    Args:
        rows: (R,) receivers; distance: (R,) their n_j . (p_j - eye) (``ShotView.distance_of``);
        sine_sums: (R,) their sum_q w_q sin(theta_q) (``ShotView.sine_sums``).
    """
    normals = ctx.mesh.normals.index_select(0, rows)  # (R, 3)
    sin_alpha = torch.linalg.cross(normals, ctx.normal.expand_as(normals), dim=1).norm(dim=1)
    in_plane = (sin_alpha * _rows(ctx.form_factors, rows) + 4.0 * sine_sums) / distance.abs()
    reach = ctx.shooter_offsets.norm(dim=1).max()  # max_k |P_k - G|
    return _rows(ctx.luminance_per_form_factor, rows) * in_plane * reach


def receiver_score(ctx: ShotContext, rows: torch.Tensor | None = None) -> torch.Tensor:
    """The first-order variation of received radiosity across each receiver itself.

    Translating the receiver by t changes the frozen-visibility kernel as translating the
    shooter by -t does, so its gradient is minus the interior Jacobian; it is dotted with
    the receiver's own vertex offsets.
    """
    grad = -_rows(ctx.luminance_per_form_factor, rows)[:, None] * _rows(ctx.jacobian, rows)  # (R, 3)
    corners = _corners(ctx, rows)
    offsets = corners - corners.mean(dim=1, keepdim=True)  # (R, 3, 3)
    return torch.einsum("tc,tkc->tk", grad, offsets).abs().amax(dim=1)


def partial_visibility_score(ctx: ShotContext, rows: torch.Tensor | None = None) -> torch.Tensor:
    """Radiosity a partly visible receiver misses: (unoccluded F - hemicube F) in luminance.

    Zero for receivers the shooter does not see at all; these are not on a shadow edge
    (or are wholly inside a shadow, where a finer mesh would not help).
    """
    unoccluded = point_to_triangles(ctx.eye, ctx.normal, _corners(ctx, rows))
    form_factors = _rows(ctx.form_factors, rows)
    missing = (unoccluded - form_factors).clamp(min=0)
    luminance_per_form_factor = _rows(ctx.luminance_per_form_factor, rows)
    return torch.where(form_factors > 0, luminance_per_form_factor * missing, torch.zeros_like(missing))


def neighbor_difference_score(ctx: ShotContext, rows: torch.Tensor | None = None) -> torch.Tensor:
    """The classic baseline: the largest difference in received luminance to any element
    sharing a vertex (vertices are shared within a surface only)."""
    value = ctx.luminance_per_form_factor * ctx.form_factors  # (T,) luminance of the received radiosity
    triangles = ctx.mesh.triangles
    V = len(ctx.mesh.vertices)
    spread = value[:, None].expand(-1, 3).reshape(-1)
    at = triangles.reshape(-1)
    high = torch.full((V,), -torch.inf, dtype=value.dtype, device=value.device).scatter_reduce(0, at, spread, "amax")
    low = torch.full((V,), torch.inf, dtype=value.dtype, device=value.device).scatter_reduce(0, at, spread, "amin")
    return _rows(torch.maximum(high[triangles] - value[:, None], value[:, None] - low[triangles]).amax(dim=1), rows)


def uniform_score(ctx: ShotContext, rows: torch.Tensor | None = None) -> torch.Tensor:
    """Each element's longest edge: with the threshold as a target size, splits everything
    down to it (the brute-force reference)."""
    corners = _corners(ctx, rows)
    return (corners - corners.roll(1, dims=1)).norm(dim=-1).amax(dim=1)


@dataclass(frozen=True)
class Criterion:
    # (ctx, rows or None) -> the (R,) scores of those receivers, or (T,) of all of them
    score: Callable[[ShotContext, torch.Tensor | None], torch.Tensor]
    jacobian: str | None  # "full", "interior" or None: which form-factor gradient it reads
    radiosity_units: bool = True  # False: the threshold is a length
    # (ctx without its jacobian, rows, ShotView.distance_of(rows), ShotView.sine_sums rows) ->
    # (rows,) an upper bound of the score's interior part, for leaving receivers out of the
    # interior Jacobian; None: none
    interior_bound: Callable[[ShotContext, torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor] | None = None


CRITERIA: dict[str, Criterion] = {
    "gradient": Criterion(gradient_score, "full", interior_bound=gradient_score_bound),
    "receiver": Criterion(receiver_score, "interior"),
    "partial_visibility": Criterion(partial_visibility_score, None),
    "neighbor_difference": Criterion(neighbor_difference_score, None),
    "uniform": Criterion(uniform_score, None, radiosity_units=False),
}
if tuple(CRITERIA) != SHOT_CRITERION_NAMES:  # the scene's vocabulary and the registry are one list
    raise RuntimeError(f"hemirad.scene.model.SHOT_CRITERION_NAMES {SHOT_CRITERION_NAMES} and the criteria defined here "
                       f"{tuple(CRITERIA)} differ; a criterion is named in both, in the same order")
