"""Form factors of receivers that cover few hemicube pixels, without pixel luck
(docs/DESIGN.md §1.5).

A hemicube gives element j the delta form factors of the pixels whose centres fall on it. For
an element a few pixels wide that sum depends on where the centres happen to fall: a
triangle a fraction of a pixel's footprint gets nothing or a whole pixel, one of a few
pixels anything within about a pixel of its true value. Refined elements in a penumbra are
that small, and the grain shows.

For such receivers (an unoccluded footprint estimated below ``MAX_PIXELS`` pixels) the
factor is instead that of the part of the triangle the eye sees, found with the hemicube as a
shadow map: the centroids of its level^2 equal sub-triangles (about one a pixel) are
projected into the atlas, and a point is hidden when the element its pixel sees, another
one, is crossed by the point's own ray before the point (the ray meets that element's
plane first) and lies, where the pixel sees it, on the eye's side of the receiver's plane.
Both conditions are needed: the first alone would hide points beside a convex edge (a box's
underside seen past its side face), the second alone points beside a concave one (a
ceiling seen past the wall it meets). The visible points' kernel cos_s cos_j / (pi r^2),
each standing for its sub-triangle, sums to the factor; near the eye, where that sum is too
coarse (``NEAR``), Lambert's closed form times the visible share of the sum is used. An
unoccluded receiver so gets its exact factor (to about 1e-3) wherever it lies under the
pixels; a partly hidden one a visibility resolved to the shadow map's pixels, as the
pixel sum resolves it, but without the luck of where the centres fall on the receiver.

The row keeps the hemicube's total: it is scaled by the hemicube's sum over the new one, so
a closed scene's row still sums to 1 and power is conserved exactly. The scale differs from
1 by the small receivers' pixel luck summed, a fraction of a pixel's weight over the row's
total when a few are corrected.
"""
from __future__ import annotations

import math
from typing import Callable, Sequence

import torch

from hemirad.core.device import cached_per_device
from hemirad.core.fastops import flatnonzero, row_sums
from hemirad.core.scripted import scripted
from hemirad.geometry.analytic import point_to_triangles
from hemirad.transport.formfactor import sum_by_index
from hemirad.transport.hemicube import FACES, face_viewports
from hemirad.transport.view import HemicubeView, pixel_directions

#: The receivers whose unoccluded footprint on the hemicube is estimated below this many
#: pixels get their factor from samples. Measured (a right triangle, legs along the pixel
#: rows, over 7 x 7 offsets within a pixel): a pixel sum's worst error is 106% at half a
#: pixel, 55% at 2, 38% at 4.5, 29% at 8, 21% at 18 and 64, 10% at 128.
MAX_PIXELS = 16.0
#: The same for a shooter that only reflects (``ProgressiveSolver.shot_row``): its receivers'
#: reflected light comes from hundreds of such shooters, whose pixel luck averages out, except
#: under a pixel, where a receiver gets nothing or a whole pixel, ten times its share at a
#: tenth of a pixel. Measured (converged, floating refined by the answer from x2 in three
#: rounds to 11,000 elements; relMSE): every receiver under 16 pixels corrected 0.00003 in 22 s,
#: those under one 0.00004 in 16 s, none 0.00014 in 16 s; on the uniform meshes of 10,000-11,000
#: elements all three give the same error.
BOUNCE_MAX_PIXELS = 1.0
#: Visibility samples per receiver: about one a pixel of its footprint, at most SAMPLE_LEVEL^2.
SAMPLE_LEVEL = 4
#: Samples made in one pass at most (``visible_form_factors``; runs of whole receivers): each
#: holds about 400 bytes of temporaries while it is made, and a sweep group of a furnished
#: room's lamp elements sends half a million and more.
SAMPLE_CHUNK = 1 << 17
#: A receiver whose sub-triangles are longer than this fraction of its distance from the eye
#: gets the closed form times its visible share rather than the sampled sum (the sum's
#: relative error is about the square of that ratio: under 0.3% where it is used).
NEAR = 0.05
# A point is hidden only by what its ray crosses this fraction of its length short of it,
# and what lies this fraction of the eye's height off the receiver's plane (rounding; the
# receiver's coplanar neighbours are not occluders).
_TOLERANCE = 1e-6


@cached_per_device
def sample_barycentrics(level: int) -> torch.Tensor:
    """(level^2, 3) float64 barycentric coordinates of the centroids of the level^2 congruent
    triangles a triangle splits into when each edge is cut into ``level`` equal parts."""
    points = []
    for i in range(level):
        for j in range(level - i):
            points.append(((3 * i + 1) / (3 * level), (3 * j + 1) / (3 * level)))  # pointing up
            if i + j < level - 1:
                points.append(((3 * i + 2) / (3 * level), (3 * j + 2) / (3 * level)))  # pointing down
    ab = torch.tensor(points, dtype=torch.float64)
    return torch.cat([ab, 1.0 - ab.sum(1, keepdim=True)], dim=1)


@cached_per_device
def _sample_table(max_level: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``sample_barycentrics`` of levels 1 to ``max_level`` one after another, (S, 3), and
    (max_level + 1,) int64 where each level's begin (indexed by the level)."""
    levels = range(1, max_level + 1)
    sizes = [level * level for level in levels]
    begin = torch.tensor([0, 0, *sizes[:-1]]).cumsum(0)  # level 1 begins at 0, level k after k-1's
    return torch.cat([sample_barycentrics(level) for level in levels]), begin


def sample_levels(footprint: torch.Tensor, max_level: int = SAMPLE_LEVEL) -> torch.Tensor:
    """(n,) int64 the level of each receiver's samples for its (n,) ``footprint`` in pixels:
    the least with level^2 >= footprint (a sample a pixel: what a pixel sees is one answer
    for all the points in it), from 1 to ``max_level``."""
    return torch.ceil(torch.sqrt(footprint)).long().clamp(1, max_level)


@cached_per_device
def _face_table(resolution: int) -> tuple[torch.Tensor, ...]:
    """Per face (5): the local axis (5, 3) int64 and its sign (5, 3) float64 that forward, right
    and up each lie along (every one is a signed axis); the lowest up-coordinate, first atlas
    row and rows (5,)."""
    vectors = torch.tensor([f[:3] for f in FACES], dtype=torch.float64)  # (5, 3 vectors, 3)
    axis = vectors.abs().argmax(2)
    sign = vectors.gather(2, axis[:, :, None])[:, :, 0]
    bottom = torch.tensor([f[3] for f in FACES], dtype=torch.float64)
    y0 = torch.tensor([v[1] for v in face_viewports(resolution)], dtype=torch.int64)
    height = torch.tensor([v[3] for v in face_viewports(resolution)], dtype=torch.int64)
    return axis, sign, bottom, y0, height


def atlas_pixels(local: torch.Tensor, resolution: int) -> torch.Tensor:
    """(N,) int64 the flattened atlas pixel each (N, 3) direction in the hemicube's local frame
    falls in (``formfactor.hemicube_directions``' layout); a direction below the horizon
    gets the side face's lowest row."""
    axis, sign, bottom, y0, height = _face_table(resolution, local.device)
    return _atlas_pixels(local, axis, sign, bottom, y0, height, resolution)


@scripted
def _atlas_pixels(local: torch.Tensor, axis: torch.Tensor, sign: torch.Tensor, bottom: torch.Tensor, y0: torch.Tensor,
                  height: torch.Tensor, resolution: int) -> torch.Tensor:
    """``atlas_pixels`` given the ``_face_table``: one kernel (``core.scripted``)."""
    x, y, z = local.unbind(1)
    ax, ay = x.abs(), y.abs()
    side = torch.where(ax >= ay, torch.where(x > 0, 1, 2), torch.where(y > 0, 3, 4))
    face = torch.where(z >= torch.maximum(ax, ay), 0, side)  # (N,)
    # each direction's coordinates along its face's forward, right and up: signed components
    along, sx, sy = (local.gather(1, axis.index_select(0, face)) * sign.index_select(0, face)).unbind(1)
    sx, sy = sx / along, sy / along
    half = 0.5 * resolution
    col = torch.floor((sx + 1.0) * half).long().clamp(0, resolution - 1)
    row = torch.minimum(torch.floor((sy - bottom.index_select(0, face)) * half).long().clamp(min=0),
                        height.index_select(0, face) - 1)
    return (y0.index_select(0, face) + row) * resolution + col


def footprint_pixels(view: HemicubeView, corners: torch.Tensor, areas: torch.Tensor) -> torch.Tensor:
    """(T,) about how many hemicube pixels each element would cover unoccluded: its solid
    angle over a pixel's in its direction, A_j cos_j |d|^3 / (r^2 (2/R)^2) for d the
    direction scaled onto the unit cube, which is A_j h_j R^2 / (4 m^3) with h_j the eye's
    height above its plane and m the largest of the local |x|, |y| and z of its centroid;
    0 for an element that faces away or lies wholly below the horizon.

    Args:
        corners: (T, 3, 3) the elements' corners; areas: (T,).
    """
    footprint = _facing_footprint(view, areas)
    return torch.where(_above_horizon(view, corners), footprint, 0.0)


def small_receivers(view: HemicubeView, corners: torch.Tensor, areas: torch.Tensor, max_pixels: float,
                    among: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(n,) the elements (of ``among`` (T,) bool, when given) whose ``footprint_pixels`` lies
    in (0, ``max_pixels``), and (n,) those footprints; the horizon is tested on these only
    (the corners' test is most of the cost, and few elements are small)."""
    footprint = _facing_footprint(view, areas)
    small = (footprint > 0) & (footprint < max_pixels)
    candidates = flatnonzero(small if among is None else small & among)
    rows = candidates.index_select(0, flatnonzero(_above_horizon(view, corners.index_select(0, candidates))))
    return rows, footprint.index_select(0, rows)


def _facing_footprint(view: HemicubeView, areas: torch.Tensor) -> torch.Tensor:
    """(T,) ``footprint_pixels`` without the horizon test (0 for an element that faces away)."""
    return _footprints(view.distance, view.points, view.eye, view.frame, areas, 0.25 * view.resolution ** 2)


@scripted
def _footprints(distance: torch.Tensor, points: torch.Tensor, eye: torch.Tensor, frame: torch.Tensor,
                areas: torch.Tensor, scale: float) -> torch.Tensor:
    """``_facing_footprint`` of the view's (T,) ``distance`` and (T, 3) ``points``, its ``eye``
    (3,) and ``frame`` (3, 3), ``scale`` = R^2 / 4: one kernel (``core.scripted``)."""
    height = -distance  # n_j . (eye - p_j): > 0 where the eye sees the front
    local = (points - eye) @ frame.T  # (T, 3)
    m = torch.maximum(local[:, :2].abs().amax(1), local[:, 2])
    seen = (height > 0) & (m > 0)
    return torch.where(seen, areas * height * scale / torch.where(seen, m, 1.0) ** 3, 0.0)


def _above_horizon(view: HemicubeView, corners: torch.Tensor) -> torch.Tensor:
    """(n,) bool: whether any of each element's (n, 3, 3) corners lies above the eye's tangent plane."""
    return (((corners - view.eye) @ view.frame[2]) > 0).any(1)


def visible_form_factors(views: Sequence[HemicubeView], view_of: torch.Tensor, rows: torch.Tensor,
                         corners: torch.Tensor, areas: torch.Tensor, levels: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """(n,) the form factor from the eye of its view to the part of each receiver ``rows`` (n,)
    the eye sees, and (n,) the same unoccluded: the kernel cos_s cos_j / (pi r^2) = z h_j /
    (pi r^4) (z a point's height above the eye's tangent plane, h_j the eye's height above
    the receiver's plane) summed over the centroids of the receiver's level^2 equal
    sub-triangles that the hemicube, as a shadow map, finds visible, each standing for A_j /
    level^2.

    The midpoint rule's relative error falls like the square of a sub-triangle's size over
    its distance (``NEAR``). Every view's samples go through one pass (a reflecting
    shooter's few receivers under a pixel cost the torch calls, not the arithmetic), each in
    its own view's frame.

    Args:
        views: the hemicubes, of one mesh; view_of: (n,) the one each receiver is seen from,
            non-decreasing (a sweep group's shooters, or a shooter's near receivers).
        rows: (n,) front-facing receivers; corners: (n, 3, 3) theirs; areas: (n,) theirs.
        levels: (n,) int64 each one's samples: the level^2 points of ``sample_barycentrics``.
    """
    n = len(rows)
    if n > 1 and bool((view_of[1:] < view_of[:-1]).any()):
        raise ValueError("visible_form_factors: view_of must be non-decreasing (receivers grouped by view)")
    ends = (levels * levels).cumsum(0)  # (n,) where each receiver's samples end
    if n == 0 or int(ends[-1]) <= SAMPLE_CHUNK:
        return _visible_form_factors(views, view_of, rows, corners, areas, levels)
    parts, start = [], 0
    while start < n:  # runs of whole receivers, each of at most SAMPLE_CHUNK samples (or one receiver)
        done = int(ends[start - 1]) if start else 0
        end = max(start + 1, int(torch.searchsorted(ends, done + SAMPLE_CHUNK, right=True)))
        parts.append(_visible_form_factors(views, view_of[start:end], rows[start:end], corners[start:end],
                                           areas[start:end], levels[start:end]))
        start = end
    return torch.cat([sampled for sampled, _ in parts]), torch.cat([unoccluded for _, unoccluded in parts])


def _visible_form_factors(views: Sequence[HemicubeView], view_of: torch.Tensor, rows: torch.Tensor,
                          corners: torch.Tensor, areas: torch.Tensor, levels: torch.Tensor
                          ) -> tuple[torch.Tensor, torch.Tensor]:
    """``visible_form_factors`` of receivers whose samples are made in one pass."""
    n, device = len(rows), corners.device
    # every receiver's level^2 samples in turn: sample i of receiver p is row begin[level_p] + i
    # of the table (one gather for all levels)
    table, begin = _sample_table(int(levels.max()), device)
    counts = levels * levels
    position = torch.repeat_interleave(counts)  # (N,) the receiver of each
    first = counts.cumsum(0) - counts  # (n,) where each receiver's samples start
    index = (begin.index_select(0, levels) - first).index_select(0, position) + torch.arange(len(position), device=device)
    points = torch.einsum("nk,nkc->nc", table.index_select(0, index), corners.index_select(0, position))  # (N, 3)
    eyes = torch.stack([view.eye for view in views]).index_select(0, view_of)  # (n, 3)
    weight, visible = _sample_weights(views, view_of.index_select(0, position), points, rows.index_select(0, position))
    first = views[0]
    height = -row_sums((first.points.index_select(0, rows) - eyes) * first.normals.index_select(0, rows))
    scale = height * areas / (math.pi * levels * levels)  # h_j A_j / (pi S)
    return sum_by_index(position, visible, n) * scale, sum_by_index(position, weight, n) * scale


def _sample_weights(views: Sequence[HemicubeView], view_of: torch.Tensor, points: torch.Tensor, owner: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """(N,) the kernel z / r^4 of each sample (N, 3) of a receiver ``owner`` (N,) seen from the
    eye of its view ``views[view_of]`` (N,, non-decreasing), and (N,) the same with 0 where
    that view, as a shadow map, hides it. Per sample, in the same arithmetic whichever
    views share the pass."""
    first = views[0]
    eyes = torch.stack([view.eye for view in views]).index_select(0, view_of)  # (N, 3)
    frames = torch.stack([view.frame for view in views]).index_select(0, view_of)  # (N, 3, 3)
    ray, local, weight = _sample_kernels(points, eyes, frames)
    resolutions = [view.resolution for view in views]  # a sweep group's lamps and reflectors may differ
    pixels = _per_resolution(view_of, resolutions, lambda R, rows: atlas_pixels(_rows(local, rows), R),
                             (len(local),), torch.int64)
    # what each sample's pixel sees, view by view (the atlases stay where they are)
    parts = pixels.split(torch.bincount(view_of, minlength=len(views)).tolist())
    seen = torch.cat([view.element.index_select(0, part) for view, part in zip(views, parts)])
    other = flatnonzero((seen >= 0) & (seen != owner))  # samples whose pixel sees another element
    if len(other) == 0:
        return weight, weight
    pixels = pixels.index_select(0, other)
    direction = _per_resolution(view_of.index_select(0, other), resolutions, lambda R, rows: pixel_directions(
        R, points.device).index_select(1, _rows(pixels, rows)).T, (len(other), 3), points.dtype)
    hidden = _hidden_samples(other, seen.index_select(0, other), owner.index_select(0, other),
                             eyes.index_select(0, other), ray.index_select(0, other), frames.index_select(0, other),
                             direction, first.points, first.normals, _TOLERANCE)
    return weight, weight.index_fill(0, hidden, 0.0)


@scripted
def _sample_kernels(points: torch.Tensor, eyes: torch.Tensor, frames: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(N, 3) the rays from the ``eyes`` (N, 3) to the ``points`` (N, 3), (N, 3) the same in
    their eyes' ``frames`` (N, 3, 3: rows t, b, n), and (N,) the kernels z / r^4."""
    ray = points - eyes
    local = row_sums(ray[:, None, :] * frames)  # (N, 3) along t, b and n
    r2 = row_sums(ray * ray)
    return ray, local, local[:, 2].clamp(min=0.0) / (r2 * r2)


@scripted
def _hidden_samples(other: torch.Tensor, k: torch.Tensor, j: torch.Tensor, eye: torch.Tensor, ray: torch.Tensor,
                    axes: torch.Tensor, direction: torch.Tensor, points: torch.Tensor, normals: torch.Tensor,
                    tolerance: float) -> torch.Tensor:
    """(h,) those of the samples ``other`` (M,) that the shadow map hides: each a sample of
    receiver ``j`` (M,) whose pixel sees element ``k`` (M,), along ``ray`` (M, 3) from ``eye``
    (M, 3), the pixel's centre in the ``direction`` (M, 3) of the eye's frame ``axes`` (M, 3,
    3: rows t, b, n in the world); ``points`` and ``normals`` (T, 3) the elements';
    ``tolerance``, ``_TOLERANCE`` (a kernel takes no globals)."""
    normal_k = normals.index_select(0, k)
    toward = row_sums(normal_k * ray)  # n_k . ray
    # the ray meets k's plane at d_k / toward of its length
    d_k = row_sums((points.index_select(0, k) - eye) * normal_k)
    crosses = (d_k * toward > 0) & (d_k.abs() < (1.0 - tolerance) * toward.abs())
    normal_j = normals.index_select(0, j)
    d_j = row_sums((points.index_select(0, j) - eye) * normal_j)  # < 0: the eye is in front of j
    # where the pixel's own ray (its centre's direction, in the world) meets k's plane,
    # along n_j from the eye
    direction = direction[:, 0:1] * axes[:, 0] + direction[:, 1:2] * axes[:, 1] + direction[:, 2:3] * axes[:, 2]
    seen_at = d_k / row_sums(direction * normal_k) * row_sums(direction * normal_j)
    in_front = seen_at - d_j > tolerance * d_j.abs()
    return other.index_select(0, torch.nonzero(crosses & in_front).reshape(-1))


def _per_resolution(view_of: torch.Tensor, resolutions: Sequence[int], make: Callable, shape: tuple,
                    dtype: torch.dtype) -> torch.Tensor:
    """``make(R, rows)`` for the samples (``view_of`` (N,): each one's view) of the views of
    each resolution R in ``resolutions`` (one per view), ``rows`` (n,) those samples, put
    together into a tensor of ``shape`` (N, ...); one call, ``rows`` None, where the views
    share one resolution."""
    distinct = sorted(set(resolutions))
    if len(distinct) == 1:
        return make(distinct[0], None)
    of = torch.tensor(resolutions, device=view_of.device).index_select(0, view_of)
    out = torch.empty(shape, dtype=dtype, device=view_of.device)
    for R in distinct:
        rows = flatnonzero(of == R)
        out.index_copy_(0, rows, make(R, rows))
    return out


def _rows(x: torch.Tensor, rows: torch.Tensor | None) -> torch.Tensor:
    return x if rows is None else x.index_select(0, rows)


def small_receiver_rows(views: Sequence[HemicubeView], corners: torch.Tensor, areas: torch.Tensor,
                        max_pixels: Sequence[float], max_level: int = SAMPLE_LEVEL) -> list[torch.Tensor]:
    """``small_receiver_form_factors`` of each of ``views`` (of one mesh), each with its own
    ``max_pixels``: the rows F_sj (T,) of a sweep group's shooters, made in one pass; each
    the same as made alone to the last bits that the vectorised ``atan2`` of the closed
    forms near the eye rounds by its place in the batch."""
    found = [small_receivers(view, corners, areas, limit) for view, limit in zip(views, max_pixels)]
    rows = torch.cat([r for r, _ in found])
    if len(rows) == 0:
        return [view.form_factors for view in views]
    counts = [len(r) for r, _ in found]
    view_of = torch.repeat_interleave(torch.arange(len(views), device=rows.device),
                                      torch.tensor(counts, device=rows.device))
    sampled = _visible_part_factors(views, view_of, rows, torch.cat([f for _, f in found]), corners, areas, max_level)
    out = []
    for view, part, mine in zip(views, rows.split(counts), sampled.split(counts)):
        pixel_sums = view.form_factors
        if len(part) == 0:
            out.append(pixel_sums)
            continue
        F = pixel_sums.index_copy(0, part, mine)
        hemicube_total, total = pixel_sums.sum(), F.sum()
        out.append(pixel_sums if float(total) <= 0.0 else F * (hemicube_total / total))
    return out


def small_receiver_form_factors(view: HemicubeView, corners: torch.Tensor, areas: torch.Tensor,
                                max_pixels: float = MAX_PIXELS, max_level: int = SAMPLE_LEVEL,
                                among: torch.Tensor | None = None) -> torch.Tensor:
    """(T,) the row F_sj of ``view`` (its ``form_factors`` being the pixel sums) with every
    receiver of an estimated footprint below ``max_pixels`` pixels given the form factor of
    its visible part (``visible_form_factors``, ``sample_levels`` up to ``max_level``), and
    the row then scaled to the hemicube's total.

    Args:
        corners: (T, 3, 3) the corners of the view's elements; areas: (T,) theirs.
        among: (T,) bool, optional: correct only these receivers, and leave the row unscaled
            (the caller scales what it needs; ``adaptive.answer`` per split element).
    """
    if among is None:
        return small_receiver_rows([view], corners, areas, [max_pixels], max_level)[0]
    rows, footprint = small_receivers(view, corners, areas, max_pixels, among)
    if len(rows) == 0:
        return view.form_factors
    sampled = _visible_part_factors([view], torch.zeros_like(rows), rows, footprint, corners, areas, max_level)
    return view.form_factors.index_copy(0, rows, sampled)


def _visible_part_factors(views: Sequence[HemicubeView], view_of: torch.Tensor, rows: torch.Tensor,
                          footprint: torch.Tensor, corners: torch.Tensor, areas: torch.Tensor,
                          max_level: int) -> torch.Tensor:
    """(n,) the factor from its view's eye to the visible part of each receiver ``rows`` (n,)
    of ``footprint`` (n,) pixels (``view_of`` as ``visible_form_factors`` takes it): the
    sampled sum, or near the eye, where that sum is too coarse, Lambert's closed form times
    the visible share of the sum."""
    levels = sample_levels(footprint, max_level)
    row_corners = corners.index_select(0, rows)
    sampled, unoccluded = visible_form_factors(views, view_of, rows, row_corners, areas.index_select(0, rows), levels)
    eyes = torch.stack([view.eye for view in views]).index_select(0, view_of)  # (n, 3)
    edges = row_corners - row_corners.roll(1, dims=1)
    size = edges.norm(dim=2).amax(1) / levels  # (n,) a sub-triangle's longest edge
    near = flatnonzero(size > NEAR * (views[0].points.index_select(0, rows) - eyes).norm(dim=1))
    if len(near) == 0:
        return sampled
    normals = torch.stack([view.frame[2] for view in views]).index_select(0, view_of.index_select(0, near))
    closed = point_to_triangles(eyes.index_select(0, near)[:, None], normals[:, None], row_corners.index_select(0, near))
    total = unoccluded.index_select(0, near)
    share = torch.where(total > 0, sampled.index_select(0, near) / torch.where(total > 0, total, 1.0), 0.0)
    return sampled.index_copy(0, near, closed * share)
