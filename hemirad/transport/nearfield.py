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
  (``analytic.triangle_to_triangles``, a contour integral) for pairs closer than
  ``CONTOUR_GAP`` source sides; beyond, Lambert's factor from G times the ratio of the
  point-to-point kernels cos cos / r^2 from the source's centroid and from G (Lambert's from
  the source's centroid, to second order in the receiver's size, without its cost). A
  centroid's Lambert factor alone, as an earlier version used, leaves the 7% above: the
  error is in the pairs that touch.
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
  right beyond the near field (0.9% per element where ``hemicube`` leaves 5.4%), but against
  the path-traced references it is worse (Cornell box relative MSE 0.0029 against 0.0025):
  a source under an object standing on it (a floor element straddling a block's footprint)
  counts as wholly exposed, and the pictures' Gouraud shading at a surface's border prefers
  the old values (docs/DESIGN.md §1.4).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from hemirad.core.fastops import flatnonzero
from hemirad.geometry.analytic import point_to_triangles, triangle_to_triangles
from hemirad.geometry.mesh import Mesh
from hemirad.transport.smallreceivers import visible_form_factors
from hemirad.transport.view import HemicubeView

#: How a source's light is split between its near receivers and the rest (module docstring).
TOTALS = ("hemicube", "area")
#: Pairs closer than this many source sides (their gap: the centroids' distance less both
#: radii) get the contour integral.
CONTOUR_GAP = 1.0
#: Gauss points along a source edge (``triangle_to_triangles``: about 0.2% of the factor for
#: triangles that touch, 0.01% for those apart by half a side).
GAUSS_POINTS = 4
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


def _sides_centroids_radii(corners: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(m,) sides sqrt(2 A), (m, 3) centroids and (m,) radii (the farthest corner from the
    centroid) of (m, 3, 3) triangles."""
    centroid = corners.mean(1)
    area = 0.5 * torch.linalg.vector_norm(
        torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), dim=1)
    return (2.0 * area).sqrt(), centroid, torch.linalg.vector_norm(corners - centroid[:, None], dim=2).amax(1)


def area_factors(sources: torch.Tensor, normal: torch.Tensor, receivers: torch.Tensor,
                 receiver_normals: torch.Tensor, point: torch.Tensor, from_point: torch.Tensor) -> torch.Tensor:
    """(k, n) the unoccluded form factors from the (k, 3, 3) ``sources``, shooting along unit
    ``normal`` (3,), to the (n, 3, 3) ``receivers`` of (n, 3) unit ``receiver_normals``, given
    Lambert's factors ``from_point`` (n,) from ``point`` (3,), G.

    Pairs closer than ``CONTOUR_GAP`` source sides get the area-to-area factor. The others
    get G's factor times the ratio of the kernels cos_s cos_j / r^2 from the source's
    centroid and from G to the receiver's centroid, where both cosines seen from G exceed
    0.1; where they do not (a receiver near G's horizon, or seen edge-on), the area-to-area
    factor too."""
    k, n = len(sources), len(receivers)
    if k == 0 or n == 0:
        return sources.new_zeros(k, n)
    side, centre, radius = _sides_centroids_radii(sources)
    _, receiver_centre, receiver_radius = _sides_centroids_radii(receivers)
    gap = (torch.cdist(centre, receiver_centre) - radius[:, None] - receiver_radius[None, :]).clamp(min=0.0)
    to_receiver = receiver_centre - point  # (n, 3)
    distance = torch.linalg.vector_norm(to_receiver, dim=1)
    cos_g = to_receiver @ normal / distance
    cos_j = -(to_receiver * receiver_normals).sum(1) / distance
    steady = (cos_g > 0.1) & (cos_j > 0.1)  # (n,)
    d = receiver_centre[None] - centre[:, None]  # (k, n, 3) from each source's centroid
    d2 = d.square().sum(-1)
    kernel = (d @ normal).clamp(min=0.0) * (-(d * receiver_normals[None]).sum(-1)).clamp(min=0.0) / d2.square()
    kernel_g = torch.where(steady, cos_g * cos_j / distance.square(), 1.0)
    out = from_point[None] * kernel / kernel_g[None]
    s, r = torch.nonzero((gap < CONTOUR_GAP * side[:, None]) | ~steady[None], as_tuple=True)
    if len(s):
        out[s, r] = triangle_to_triangles(sources.index_select(0, s), receivers.index_select(0, r), GAUSS_POINTS)
    return out


def visibility(view: HemicubeView, rows: torch.Tensor, corners: torch.Tensor, areas: torch.Tensor,
               form_factors: torch.Tensor, from_point: torch.Tensor) -> torch.Tensor:
    """(n,) the share of each receiver ``rows`` (n,), of (n, 3, 3) ``corners`` and (n,)
    ``areas``, that the eye of ``view`` sees: 1 where all its samples are visible, else its
    ``form_factors`` (n,) over Lambert's ``from_point`` (n,), at most 1."""
    ratio = torch.where(from_point > 0, form_factors / from_point.clamp(min=1e-300), 0.0).clamp(max=1.0)
    doubtful = flatnonzero(ratio < 1.0)  # the others are 1 either way
    if len(doubtful) == 0:
        return ratio
    levels = torch.full((len(doubtful),), VISIBILITY_LEVEL, dtype=torch.int64, device=rows.device)
    visible, unoccluded = visible_form_factors(view, rows.index_select(0, doubtful), corners.index_select(0, doubtful),
                                               areas.index_select(0, doubtful), levels)
    # equal sums: no sample hidden
    return ratio.index_copy(0, doubtful, torch.where(visible >= unoccluded, 1.0, ratio.index_select(0, doubtful)))


def near_receivers(mesh: Mesh, members: torch.Tensor, sources: torch.Tensor, point: torch.Tensor,
                   normal: torch.Tensor, view: HemicubeView, form_factors: torch.Tensor, reach: float,
                   totals: str = "hemicube", among: torch.Tensor | None = None) -> NearReceivers:
    """The near receivers of the shooter whose (K,) ``members`` shoot from ``point`` (3,)
    along ``normal`` (3,), and the weights of its (k, 3, 3) ``sources`` (the triangles its
    power is spread over: its initial elements), given what its hemicube saw, ``view``, the
    row it shoots with, ``form_factors`` (T,), and how the totals are found (``TOTALS``).
    With ``among`` (R,), only those among these elements, unscaled (``far_scale`` 1: the
    caller scales what it needs)."""
    radius = float(torch.linalg.vector_norm(mesh.corners_of(members).reshape(-1, 3) - point, dim=1).max())
    centroids, seen_from_g = mesh.centroids, form_factors > 0  # what G does not see stays unseen (occluded, or behind)
    if among is not None:
        centroids, seen_from_g = centroids.index_select(0, among), seen_from_g.index_select(0, among)
    near = (torch.linalg.vector_norm(centroids - point, dim=1) < reach * radius) & seen_from_g
    rows = flatnonzero(near) if among is None else among[near]
    rows = rows[~torch.isin(rows, members)]
    corners = mesh.corners_of(rows)  # (n, 3, 3)
    F = form_factors.index_select(0, rows)
    from_point = point_to_triangles(point, normal, corners)  # (n,) Lambert's from G
    seen = visibility(view, rows, corners, mesh.areas.index_select(0, rows), F, from_point)
    weights = area_factors(sources, normal, corners, mesh.normals.index_select(0, rows), point,
                           from_point) * seen[None, :]
    far_scale = weights.new_ones(len(sources))
    if among is not None or len(rows) == 0:
        return NearReceivers(rows, weights, far_scale)
    near_sums = weights.sum(1)  # (k,)
    if totals == "hemicube":
        # G's total over the near receivers, shared as the source sends it (a source that
        # reaches none of them: G's numbers)
        lit = near_sums > 0
        weights = torch.where(lit[:, None], weights * (F.sum() / torch.where(lit, near_sums, 1.0))[:, None],
                              F[None, :].expand_as(weights))
        return NearReceivers(rows, weights, far_scale)
    if totals != "area":
        raise ValueError(f"totals must be one of {', '.join(TOTALS)}, not {totals!r}")
    far = form_factors.index_fill(0, rows, 0.0).sum()  # G's factors to the others (a sum: no rounding)
    rest = far + (1.0 - form_factors.sum()).clamp(min=0.0)  # and what G's hemicube sees nothing in
    if float(rest) > REST_FLOOR:
        wanted = (1.0 - near_sums).clamp(min=0.0) / rest
        # what the source sees and G does not is in no receiver's row: would it land on a few
        # far receivers, the near ones take the excess
        far_scale = wanted.clamp(max=FAR_SCALE_MAX)
        extra = (wanted - far_scale) * far
        weights = weights * (1.0 + extra / near_sums.clamp(min=1e-300))[:, None]
        near_sums = near_sums + extra
    weights = weights / near_sums.clamp(min=1.0)[:, None]  # at most the whole hemisphere (rounding)
    return NearReceivers(rows, weights, far_scale)


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
