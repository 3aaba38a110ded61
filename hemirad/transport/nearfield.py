"""The light a shooter sends to the receivers close to it, as its extent sends it
(docs/DESIGN.md §1.4).

A shooter (a node of a patch; with a near field when elements shoot alone, an element)
shoots from one hemicube at its centroid G. For a receiver many shooter sizes away that
point stands in well for the shooter's area; for one beside it (the floor along a wall
patch) it does not. Nor does a triangle's centroid for the triangles beside it: the
area-to-area factor F(e -> j) = (1/A_e) int_e F^L(x -> j) dx grows steeply where two
surfaces meet, and a centroid's value falls short of it. In a closed box that left the light
along the edges too low and the faces' middles too high: 7% per element at reflectance 0.7
with every element shooting, 6-9% with patches.

For the receivers within ``reach`` shooter radii of G, each source triangle (the shooter's
initial elements, whose power it shoots) gets its own factor to each receiver, times the
receiver's visibility from G:

- the factor is the triangles' unoccluded area-to-area form factor
  (``analytic.triangle_to_triangles``, a contour integral; for a receiver far smaller than
  the source, ``analytic.small_triangle_factors``, by reciprocity from points of the
  receiver) for pairs closer than ``CONTOUR_GAP`` source sides; beyond, Lambert's factor
  from G times the ratio of the point-to-point kernels cos cos / r^2 from the source's
  centroid and from G (Lambert's from the source's centroid, to second order in the
  receiver's size, without its cost). A centroid's Lambert factor alone, as an earlier
  version used, leaves the 7% above: the error is in the pairs that touch.
- the visibility is 1 where all ``VISIBILITY_LEVEL``^2 samples of the receiver are visible
  in G's hemicube (the shadow-map test of ``smallreceivers``), else the hemicube's factor
  over Lambert's from G, at most 1. The pixels' ratio alone carries their luck (a few per
  cent for a receiver of a few hundred pixels), which reached the answer.

How much of a source's light its near receivers take (``TOTALS``):

- ``hemicube`` (the default): what G's hemicube gives them, shared among them by the
  source's own factors; the other receivers get G's factors. Each source's row sums to the
  hemicube's, so power is conserved exactly. The point's error stays in that total (a wall
  patch's centroid sees less of the floor beside it than the patch's edge does), so the near
  field must reach far: in a closed 1 m box of 0.25 m cells, 3 patch radii leave up to 4%
  per element, 4 (the whole box) 0.5%.
- ``area``: the source's own factors, whose total is right; the rest of its hemisphere (far
  receivers, and what G sees nothing in) is G's, scaled by what the near ones leave,
  (1 - near) / (1 - G's near), the far receivers taking at most ``FAR_SCALE_MAX`` times G's
  numbers (the excess then goes to the near ones: what the source sees and G does not is
  in no receiver's row). Rows sum to at most 1, so nothing is created. It keeps a closed box
  right beyond the near field (0.9% per element where ``hemicube`` leaves 5.4%), and keeps
  the floor at a wall's foot as bright as the wall's edge makes it. But a source under an
  object standing on it (a floor element straddling a block's footprint) counts as wholly
  exposed: it is the choice where contacts are meshed (``assembly.near_totals``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch

from hemirad.core.fastops import flatnonzero, row_sums, segments
from hemirad.core.scripted import scripted
from hemirad.geometry.analytic import point_to_triangles, small_triangle_factors, triangle_to_triangles
from hemirad.geometry.mesh import Mesh
from hemirad.transport.smallreceivers import visible_form_factors
from hemirad.transport.view import HemicubeView

#: How a source's light is split between its near receivers and the rest (module docstring).
TOTALS = ("hemicube", "area")
#: Pairs closer than this many source sides (their gap: the centroids' distance less both
#: radii) get the contour integral.
CONTOUR_GAP = 1.0
#: Gauss points along each piece of a source edge (``triangle_to_triangles``: at most about 1%
#: of the factor for triangles that touch, 0.01% for those apart by half a side).
GAUSS_POINTS = 4
#: Pairs at least this many source sides apart (three in four of the contour integrals of a
#: furnished room: those near a shooter's horizon or seen edge-on) have no kink for the pieces
#: to resolve, and get ``APART_POINTS`` along each whole source edge instead: against 8 points
#: a piece, over the room's 331,000 such pairs, median / 99th percentile / largest error
#: 5e-11 / 5e-6 / 0.2% where 4 points a piece read 6e-9 / 2e-4 / 4%, in half the time.
PIECES_GAP = 0.5
APART_POINTS = 5
#: Close pairs whose receiver's radius is at most this share of the source's side, in front
#: of the source's plane (touching it at most), get their factor from points of the receiver
#: (``analytic.small_triangle_factors``): three, or its centroid where it lies at least
#: ``CENTROID_APART`` receiver radii from the source (the gap between their bounding
#: spheres). A refined mesh's receivers beside a patch's sources are a hundredth of their
#: side, where the contour integral loses its digits.
SMALL_RECEIVER = 0.1
CENTROID_APART = 32.0
# A receiver's corner this share of the source's side off its plane lies on it (rounding).
_ON_PLANE = 1e-9
#: Contour integrals done in one pass of the vectorised kernels.
CONTOUR_CHUNK = 1024
#: Source-receiver pairs that ``near_fields`` takes in one pass, at most (a shooter with
#: more takes them alone).
PAIR_CHUNK = 1 << 16
#: A near receiver counts as wholly visible from G when all its level^2 samples are.
VISIBILITY_LEVEL = 4
#: With ``area`` totals, the most G's factors to the far receivers are scaled by for a source.
FAR_SCALE_MAX = 2.0
#: Below this share of G's hemisphere beyond its near receivers, there is nothing to scale.
REST_FLOOR = 1e-9


@dataclass(frozen=True)
class NearReceivers:
    """How a shooter's source triangles reach the receivers near it, and the others.

    Attributes:
        rows: (n,) the near receivers (not the shooter's own elements).
        weights: (k, n) per source triangle (k), its form factor to each near receiver;
            zero for a receiver G does not see.
        far_scale: (k,) per source, the scale of G's factors to the other receivers.
    """

    rows: torch.Tensor
    weights: torch.Tensor
    far_scale: torch.Tensor


@dataclass(frozen=True)
class NearShooter:
    """A shooter whose near field is wanted: its (K,) ``members`` (elements), (k, 3, 3)
    ``sources`` (the triangles its power is spread over: its initial elements), the ``point``
    G (3,) it shoots from along unit ``normal`` (3,), what its hemicube there saw, ``view``,
    and the row it shoots with, ``form_factors`` (T,)."""

    members: torch.Tensor
    sources: torch.Tensor
    point: torch.Tensor
    normal: torch.Tensor
    view: HemicubeView
    form_factors: torch.Tensor


def _sides_centroids_radii(corners: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(m,) sides sqrt(2 A), (m, 3) centroids and (m,) radii (the farthest corner from the
    centroid) of (m, 3, 3) triangles."""
    centroid = corners.mean(1)
    area = 0.5 * torch.linalg.vector_norm(
        torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), dim=1)
    return (2.0 * area).sqrt(), centroid, torch.linalg.vector_norm(corners - centroid[:, None], dim=2).amax(1)


def area_factors(sources: torch.Tensor, receivers: torch.Tensor, receiver_normals: torch.Tensor,
                 points: torch.Tensor, normals: torch.Tensor, from_point: torch.Tensor, source: torch.Tensor,
                 receiver: torch.Tensor, one_shooter: bool = False) -> torch.Tensor:
    """(C,) per pair of a source (``source`` (C,) into the (K, 3, 3) ``sources``) and a
    receiver (``receiver`` (C,) into the (N, 3, 3) ``receivers`` of unit ``receiver_normals``
    (N, 3)), the unoccluded form factor from the source, shooting along its shooter's unit
    ``normals`` (N, 3), to the receiver, given the receiver's Lambert factor ``from_point``
    (N,) from its shooter's point G, ``points`` (N, 3) (per receiver: a receiver near two
    shooters comes twice). With ``one_shooter``, the pairs are every source with every
    receiver, source by source (then found by broadcasting, not gathered: a refined mesh's
    shooter has thousands of receivers). Contour integrals are made ``CONTOUR_CHUNK`` at a time.

    Pairs closer than ``CONTOUR_GAP`` source sides get the area-to-area factor. The others
    get G's factor times the ratio of the kernels cos_s cos_j / r^2 from the source's
    centroid and from G to the receiver's centroid, where both cosines seen from G exceed
    0.1; where they do not (a receiver near G's horizon, or seen edge-on), the area-to-area
    factor too (``SMALL_RECEIVER``: or its reciprocal, from points of a small receiver)."""
    if len(source) == 0:
        return from_point.new_zeros(0)
    out, touching, apart, by_points, by_centroid = _pair_factors(
        sources, receivers, receiver_normals, points, normals, from_point, source, receiver, one_shooter,
        (CONTOUR_GAP, SMALL_RECEIVER, CENTROID_APART, PIECES_GAP, _ON_PLANE))
    for pairs, factors, chunk_size in (
            (touching, lambda s, r: triangle_to_triangles(s, r, GAUSS_POINTS), CONTOUR_CHUNK),
            (apart, lambda s, r: triangle_to_triangles(s, r, APART_POINTS, pieces=False), CONTOUR_CHUNK),
            (by_points, lambda s, r: small_triangle_factors(s, r, 3), CONTOUR_CHUNK),
            (by_centroid, lambda s, r: small_triangle_factors(s, r, 1), 3 * CONTOUR_CHUNK)):
        for chunk in pairs.split(chunk_size) if len(pairs) else ():  # (an empty tensor splits into one empty part)
            out.index_copy_(0, chunk, factors(sources.index_select(0, source.index_select(0, chunk)),
                                              receivers.index_select(0, receiver.index_select(0, chunk))))
    return out


@scripted
def _pair_factors(sources: torch.Tensor, receivers: torch.Tensor, receiver_normals: torch.Tensor, points: torch.Tensor,
                  normals: torch.Tensor, from_point: torch.Tensor, source: torch.Tensor, receiver: torch.Tensor,
                  one_shooter: bool, limits: tuple[float, float, float, float, float]
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``area_factors``' pairs (same arguments) as one kernel (``core.scripted``): (C,) every
    pair's factor from G's, and the pairs (into C) whose factor must be made otherwise: (a)
    close ones by the contour integral in pieces, (b) by it over whole edges, (c) from three
    points of a small receiver, (d) from its centroid. ``limits``: ``CONTOUR_GAP``,
    ``SMALL_RECEIVER``, ``CENTROID_APART``, ``PIECES_GAP`` and ``_ON_PLANE`` (a kernel takes
    no globals)."""
    contour_gap, small_receiver, centroid_apart, pieces_gap, on_plane = limits
    side, centre, radius = _sides_centroids_radii(sources)  # (K,) ...
    _, receiver_centre, receiver_radius = _sides_centroids_radii(receivers)  # (N,) ...
    to_receiver = receiver_centre - points  # (N, 3) from G
    distance = torch.linalg.vector_norm(to_receiver, dim=1)
    cos_g = row_sums(to_receiver * normals) / distance
    cos_j = -row_sums(to_receiver * receiver_normals) / distance
    steady = (cos_g > 0.1) & (cos_j > 0.1)  # (N,)
    kernel_g = torch.where(steady, cos_g * cos_j / distance.square(), 1.0)
    d = _by_receiver(receiver_centre, receiver, one_shooter) - _by_source(centre, source, one_shooter)  # (C, 3)
    d2 = row_sums(d * d)
    gap = (d2.sqrt() - _by_source(radius, source, one_shooter)
           - _by_receiver(receiver_radius, receiver, one_shooter)).clamp(min=0.0).reshape(-1)
    kernel = (row_sums(d * _by_receiver(normals, receiver, one_shooter)).clamp(min=0.0)
              * (-row_sums(d * _by_receiver(receiver_normals, receiver, one_shooter))).clamp(min=0.0) / d2.square())
    out = (_by_receiver(from_point / kernel_g, receiver, one_shooter) * kernel).reshape(-1)
    side = _by_source(side, source, one_shooter).expand(d2.shape).reshape(-1)
    steady = _by_receiver(steady, receiver, one_shooter).expand(d2.shape).reshape(-1)
    close = torch.nonzero((gap < contour_gap * side) | ~steady).reshape(-1)
    # a receiver far smaller than its source, in front of the source's plane (touching it at
    # most): by reciprocity from points of the receiver
    close_source, close_receiver = source.index_select(0, close), receiver.index_select(0, close)
    source_normals = torch.nn.functional.normalize(
        torch.linalg.cross(sources[:, 1] - sources[:, 0], sources[:, 2] - sources[:, 0]), dim=1)
    heights = ((receivers.index_select(0, close_receiver) - sources.index_select(0, close_source)[:, :1])
               * source_normals.index_select(0, close_source)[:, None]).sum(-1)  # (c, 3)
    close_radius, close_side = receiver_radius.index_select(0, close_receiver), side.index_select(0, close)
    plane = on_plane * close_side[:, None]
    small = (heights >= -plane).all(1) & (heights > plane).any(1) & (close_radius <= small_receiver * close_side)
    by_centroid = small & (gap.index_select(0, close) >= centroid_apart * close_radius)
    by_points = small & ~by_centroid
    apart = gap.index_select(0, close) >= pieces_gap * close_side
    return out, close[~small & ~apart], close[~small & apart], close[by_points], close[by_centroid]


def _by_receiver(x: torch.Tensor, receiver: torch.Tensor, one_shooter: bool) -> torch.Tensor:
    """``x`` (N, ...) per receiver, per pair: broadcast over the sources (1, N, ...) with
    ``one_shooter``, else gathered by ``receiver``."""
    return x[None] if one_shooter else x.index_select(0, receiver)


def _by_source(x: torch.Tensor, source: torch.Tensor, one_shooter: bool) -> torch.Tensor:
    """``x`` (K, ...) per source, per pair: (K, 1, ...) with ``one_shooter``, else gathered by ``source``."""
    return x[:, None] if one_shooter else x.index_select(0, source)


def visibility(views: Sequence[HemicubeView], view_of: torch.Tensor, rows: torch.Tensor, corners: torch.Tensor,
               areas: torch.Tensor, ratio: torch.Tensor) -> torch.Tensor:
    """(n,) the share of each receiver ``rows`` (n,), of (n, 3, 3) ``corners`` and (n,)
    ``areas``, that the eye of its view ``views[view_of]`` sees: 1 where all its samples are
    visible, else ``ratio`` (n,), its hemicube factor over Lambert's from the eye, at most 1."""
    doubtful = flatnonzero(ratio < 1.0)  # the others are 1 either way
    if len(doubtful) == 0:
        return ratio
    levels = torch.full((len(doubtful),), VISIBILITY_LEVEL, dtype=torch.int64, device=rows.device)
    visible, unoccluded = visible_form_factors(views, view_of.index_select(0, doubtful), rows.index_select(0, doubtful),
                                               corners.index_select(0, doubtful), areas.index_select(0, doubtful), levels)
    # equal sums: no sample hidden
    return ratio.index_copy(0, doubtful, torch.where(visible >= unoccluded, 1.0, ratio.index_select(0, doubtful)))


def near_fields(mesh: Mesh, shooters: Sequence[NearShooter], reach: float, totals: str = "hemicube",
                among: torch.Tensor | None = None) -> list[NearReceivers]:
    """The near receivers of each of the B ``shooters`` (those within ``reach`` times its
    radius of its point that its hemicube sees, not its own members) and its sources'
    weights to them, with the totals found as ``totals`` says (``TOTALS``).

    All B are found together: a shooter's near field is a few hundred small pairs, whose
    cost one at a time was the torch calls' (about 120 a shooter), not their arithmetic
    (furnished room, hemicube 128: 3.0 ms a shooter alone, 1.7 in eights, 1.4 in 32s).

    With ``among`` (R,), only receivers among these elements, unscaled (``far_scale`` 1: the
    caller scales what it needs). The numbers do not depend on which shooters come together
    but in the last bits (vectorised ``log`` and ``atan2`` round otherwise than the scalar
    ones a batch's tail gets)."""
    if totals not in TOTALS:
        raise ValueError(f"totals must be one of {', '.join(TOTALS)}, not {totals!r}")
    device, B = mesh.centroids.device, len(shooters)
    points = torch.stack([s.point for s in shooters])  # (B, 3)
    normals = torch.stack([s.normal for s in shooters])
    form_factors = torch.stack([s.form_factors for s in shooters])  # (B, T)
    members = torch.cat([s.members for s in shooters])
    member_of = torch.repeat_interleave(torch.arange(B, device=device),
                                        torch.tensor([len(s.members) for s in shooters], device=device))
    reached = torch.linalg.vector_norm(mesh.corners_of(members) - points.index_select(0, member_of)[:, None], dim=2)
    radius = points.new_zeros(B).scatter_reduce_(0, member_of, reached.amax(1), "amax")
    # what G does not see stays unseen (occluded, or behind)
    near = (torch.linalg.vector_norm(mesh.centroids[None] - points[:, None], dim=2) < reach * radius[:, None]) & (
        form_factors > 0)  # (B, T)
    near[member_of, members] = False
    if among is not None:
        near &= torch.zeros_like(near[0]).index_fill_(0, among, True)[None]
    shooter_of, rows = torch.nonzero(near, as_tuple=True)  # (N,) each, shooter by shooter
    counts = torch.bincount(shooter_of, minlength=B)  # (B,) n_b
    # the rest by runs of shooters of at most PAIR_CHUNK source-receiver pairs (a refined
    # mesh's shooter can have thousands of near receivers: one pass over all of a group's
    # pairs, millions, ran at half the speed)
    pairs = (torch.tensor([len(s.sources) for s in shooters]) * counts.cpu()).tolist()
    starts = [0, *torch.cumsum(counts, 0).tolist()]
    made, first = [], 0
    while first < B:
        last, total = first + 1, pairs[first]
        while last < B and total + pairs[last] <= PAIR_CHUNK:
            total, last = total + pairs[last], last + 1
        part = slice(starts[first], starts[last])
        made += _near_run(mesh, shooters[first:last], shooter_of[part] - first, rows[part], counts[first:last],
                          points[first:last], normals[first:last], form_factors[first:last], near[first:last], totals,
                          among)
        first = last
    return made


def _near_run(mesh: Mesh, shooters: Sequence[NearShooter], shooter_of: torch.Tensor, rows: torch.Tensor,
              counts: torch.Tensor, points: torch.Tensor, normals: torch.Tensor, form_factors: torch.Tensor,
              near: torch.Tensor, totals: str, among: torch.Tensor | None) -> list[NearReceivers]:
    """``near_fields`` for a run of B ``shooters`` whose near receivers were found: (N,)
    ``rows``, shooter by shooter (``shooter_of`` (N,), ``counts`` (B,)), given their (B, 3)
    ``points`` and ``normals``, (B, T) rows ``form_factors`` and ``near`` masks."""
    device, B = rows.device, len(shooters)
    corners = mesh.corners_of(rows)  # (N, 3, 3)
    point_of, normal_of = points.index_select(0, shooter_of), normals.index_select(0, shooter_of)
    F = form_factors[shooter_of, rows]  # (N,)
    # Lambert's from G (one shooter's: its point and normal, which the products take faster)
    from_point = (point_to_triangles(points[0], normals[0], corners) if B == 1 else
                  point_to_triangles(point_of[:, None], normal_of[:, None], corners))
    seen = torch.where(from_point > 0, F / from_point.clamp(min=1e-300), 0.0).clamp(max=1.0)
    seen = visibility([s.view for s in shooters], shooter_of, rows, corners, mesh.areas.index_select(0, rows), seen)

    # Every shooter's sources with every one of its near receivers, source by source.
    sources = torch.cat([s.sources for s in shooters])  # (K, 3, 3)
    k = torch.tensor([len(s.sources) for s in shooters], device=device)  # (B,)
    source_of = torch.repeat_interleave(torch.arange(B, device=device), k)  # (K,)
    pair_of, position = segments(k * counts)  # the shooter of each pair
    receiver_start = torch.cumsum(counts, 0) - counts
    n_of = counts.index_select(0, pair_of)
    pair_source = (torch.cumsum(k, 0) - k).index_select(0, pair_of) + position // n_of.clamp(min=1)  # (C,)
    pair_receiver = receiver_start.index_select(0, pair_of) + position % n_of.clamp(min=1)  # (C,) a near pair
    weights = area_factors(sources, corners, mesh.normals.index_select(0, rows), point_of, normal_of, from_point,
                           pair_source, pair_receiver, one_shooter=B == 1) * seen.index_select(0, pair_receiver)
    far_scale = sources.new_ones(len(sources))
    if among is None:
        weights, far_scale = _totals(weights, pair_source, pair_receiver, source_of, shooter_of, F, form_factors,
                                     near, totals)
    sizes = counts.tolist()
    return [NearReceivers(row, w.reshape(len(f), n), f) for row, w, f, n in zip(
        rows.split(sizes), weights.split((k * counts).tolist()), far_scale.split(k.tolist()), sizes)]


def _totals(weights: torch.Tensor, pair_source: torch.Tensor, pair_receiver: torch.Tensor, source_of: torch.Tensor,
            shooter_of: torch.Tensor, F: torch.Tensor, form_factors: torch.Tensor, near: torch.Tensor,
            totals: str) -> tuple[torch.Tensor, torch.Tensor]:
    """The (C,) source-receiver ``weights`` (of each pair, its source (C,) and near pair (C,))
    scaled to the totals ``totals`` asks for, and (K,) each source's ``far_scale``; per near
    pair (N,) its shooter and G's factor ``F``; per source (K,) its shooter; per shooter the
    (B, T) rows ``form_factors`` and ``near`` mask."""
    K, B = len(source_of), len(form_factors)
    near_sums = weights.new_zeros(K).index_add_(0, pair_source, weights)  # (K,) a source's total
    far_scale = weights.new_ones(K)
    if totals == "hemicube":
        # G's total over the near receivers, shared as the source sends it (a source that
        # reaches none of them: G's numbers)
        near_total = F.new_zeros(B).index_add_(0, shooter_of, F).index_select(0, source_of)
        lit = near_sums > 0
        scale = (near_total / torch.where(lit, near_sums, 1.0)).index_select(0, pair_source)
        return torch.where(lit.index_select(0, pair_source), weights * scale, F.index_select(0, pair_receiver)), far_scale
    far = torch.where(near, 0.0, form_factors).sum(1)  # G's factors to the others (a sum: no rounding)
    rest = (far + (1.0 - form_factors.sum(1)).clamp(min=0.0)).index_select(0, source_of)  # and what G sees nothing in
    far = far.index_select(0, source_of)
    # a shooter with no near receivers keeps G's row as it is
    scaled = (rest > REST_FLOOR) & near.any(1).index_select(0, source_of)
    wanted = torch.where(scaled, (1.0 - near_sums).clamp(min=0.0) / torch.where(scaled, rest, 1.0), 1.0)
    # what the source sees and G does not is in no receiver's row: would it land on a few far
    # receivers, the near ones take the excess
    far_scale = wanted.clamp(max=FAR_SCALE_MAX)
    extra = (wanted - far_scale) * far
    weights = weights * (1.0 + extra / near_sums.clamp(min=1e-300)).index_select(0, pair_source)
    near_sums = near_sums + extra
    return weights / near_sums.clamp(min=1.0).index_select(0, pair_source), far_scale  # at most the hemisphere (rounding)


def incident_power(form_factors: torch.Tensor, shot_power: torch.Tensor, near: NearReceivers | None,
                   source_power: torch.Tensor | None) -> torch.Tensor:
    """(T, 3) the power reaching every receiver's front from a shot of ``shot_power`` (3,)
    whose source triangles hold (k, 3) ``source_power`` of it: F_sj times the power, but the
    ``near`` receivers get the sources' own factors, and the others G's scaled per source
    (``NearReceivers.far_scale``)."""
    if near is None or len(near.rows) == 0:
        return form_factors[:, None] * shot_power[None, :]
    incident = form_factors[:, None] * (near.far_scale @ source_power)[None, :]
    return incident.index_copy(0, near.rows, near.weights.T @ source_power)
