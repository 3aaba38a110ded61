"""From element radiosity to displayable values: vertex averaging, exposure and sRGB encoding.

Element values are constant over each triangle. For display they are averaged to the
vertices and interpolated (Gouraud). Vertices are shared only inside one surface, so the
averaging never blends across a crease or between objects.

Edge splitting leaves T-vertices: a midpoint made by splitting one element that lies on the
still unsplit edge of its neighbour. ``conforming_vertex_values`` gives them the value the
neighbour's edge interpolates (no shading seam) and ``conforming_triangles`` re-triangulates
the neighbour to include them (no rasterisation cracks).

Everything here is pure torch/numpy; nothing touches OpenGL.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from hemirad.core.colour import luminance
from hemirad.geometry.edges import contains, edge_keys, midpoint_lookup, triangle_edges, unique_edge_keys
from hemirad.geometry.mesh import Mesh

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


# ----------------------------------------------------------------------------------------
# T-vertices


def _t_vertex_depth(mesh: Mesh) -> torch.Tensor:
    """(V,) int64: 0 for a vertex that is not a T-vertex; otherwise 1 + the larger depth of
    the two ends of its edge, so the ends of a depth-d T-vertex all have depth < d.

    A midpoint m of (a, b) is a T-vertex when the segment (a, b) lies inside an edge some
    triangle still has: the edge (a, b) itself, or, when (a, b) is half of the edge that a
    (or b) is the midpoint of, whatever edge that end vertex hangs on. The second case is a
    midpoint of a midpoint: both sides of (a, b) can be split while the coarse edge that
    holds all of them is still whole on the far side.
    """
    num_vertices = len(mesh.vertices)
    depth = torch.zeros(num_vertices, dtype=torch.int64)
    parents = mesh.edge_parents
    mids = torch.nonzero(parents[:, 0] >= 0).reshape(-1)
    if len(mids) == 0 or mesh.num_elements == 0:
        return depth
    a, b = parents[mids, 0], parents[mids, 1]
    direct = contains(unique_edge_keys(mesh.triangles), edge_keys(a, b))
    # (a, b) is half of a's own parent edge when b is one of a's edge_parents.
    half_of_a = (parents[a] == b[:, None]).any(dim=1)
    half_of_b = (parents[b] == a[:, None]).any(dim=1)

    # Fixed-point iteration over the midpoint hierarchy: each pass settles one more level,
    # so the loop runs as many times as the deepest nesting (a handful), not per vertex.
    hanging = torch.zeros(num_vertices, dtype=torch.bool)
    for _ in range(len(mids) + 1):
        new = direct | (half_of_a & hanging[a]) | (half_of_b & hanging[b])
        new_depth = torch.where(new, 1 + torch.maximum(depth[a], depth[b]), 0)
        if torch.equal(new, hanging[mids]) and torch.equal(new_depth, depth[mids]):
            break
        hanging[mids] = new
        depth[mids] = new_depth
    return depth


def t_vertex_mask(mesh: Mesh) -> torch.Tensor:
    """(V,) bool: True for the split-made vertices lying inside an edge that some triangle
    of the mesh still has (directly or as a midpoint of a midpoint on it)."""
    return _t_vertex_depth(mesh) > 0


def conforming_vertex_values(mesh: Mesh, vertex_vals: torch.Tensor) -> torch.Tensor:
    """Give every T-vertex the value its unsplit neighbour's edge interpolates.

    ``vertex_values`` gives a T-vertex the mean of the elements around it, but the unsplit
    neighbour only sees the edge's two ends, so Gouraud shading would jump across the edge.
    Replacing the T-vertex by the mean of its edge's ends makes both sides agree. A
    T-vertex on a T-vertex's half edge uses the already corrected value, so values along
    the coarse edge are exactly linear: the triangulation of a coarse element then does
    not matter for shading.

    Args:
        mesh: the mesh whose ``edge_parents`` define the midpoints.
        vertex_vals: (V, C) or (V,) values per vertex.

    Returns:
        Same shape and dtype; a new tensor, equal to the input except at T-vertices.
    """
    values = torch.as_tensor(vertex_vals).clone()
    if values.shape[0] != len(mesh.vertices):
        raise ValueError(f"need one value per vertex ({len(mesh.vertices)}), got {values.shape[0]}")
    depth = _t_vertex_depth(mesh)
    parents = mesh.edge_parents
    # Shallow first: the ends of a depth-d vertex have depth < d and are already final.
    for d in range(1, int(depth.max()) + 1 if len(depth) else 1):
        v = torch.nonzero(depth == d).reshape(-1)
        a, b = parents[v, 0], parents[v, 1]
        values[v] = 0.5 * (values[a] + values[b])
    return values


def _edge_points(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The split-made vertices lying inside each directed triangle edge, in order.

    Edge ``3 t + e`` of triangle t runs from corner e to corner e + 1. The points on it are
    its midpoint (if that edge was ever split), then recursively the midpoints of the two
    halves, which is a breadth-first walk down the midpoint hierarchy; the parameter of each
    point along the edge is a dyadic fraction, exact in float64.

    Returns:
        counts: (T, 3) int64 number of points on each edge.
        offsets: (3T + 1,) int64 start of each edge's run in ``points``.
        points: (P,) int64 vertex indices, grouped by edge and ordered from start to end.
    """
    tri = mesh.triangles
    find = midpoint_lookup(mesh)
    start, end = triangle_edges(tri)
    edge_id = torch.arange(len(start), dtype=torch.int64)
    mid = find(start, end)
    hit = mid >= 0
    seg_edge, seg_a, seg_b, seg_mid = edge_id[hit], start[hit], end[hit], mid[hit]
    seg_lo = torch.zeros(len(seg_edge), dtype=torch.float64)
    seg_hi = torch.ones(len(seg_edge), dtype=torch.float64)

    out_edge, out_t, out_vertex = [], [], []
    while len(seg_edge):  # one pass per level of midpoint nesting
        seg_t = 0.5 * (seg_lo + seg_hi)
        out_edge.append(seg_edge)
        out_t.append(seg_t)
        out_vertex.append(seg_mid)
        seg_edge = torch.cat([seg_edge, seg_edge])
        seg_a, seg_b = torch.cat([seg_a, seg_mid]), torch.cat([seg_mid, seg_b])
        seg_lo, seg_hi = torch.cat([seg_lo, seg_t]), torch.cat([seg_t, seg_hi])
        seg_mid = find(seg_a, seg_b)
        hit = seg_mid >= 0
        seg_edge, seg_a, seg_b = seg_edge[hit], seg_a[hit], seg_b[hit]
        seg_lo, seg_hi, seg_mid = seg_lo[hit], seg_hi[hit], seg_mid[hit]

    if out_edge:
        edges = torch.cat(out_edge).numpy()
        params = torch.cat(out_t).numpy()
        vertices = torch.cat(out_vertex).numpy()
        order = np.lexsort((params, edges))
        edges, points = edges[order], vertices[order]
    else:
        edges = points = np.zeros(0, dtype=np.int64)
    counts = np.bincount(edges, minlength=len(start)).astype(np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    return counts.reshape(-1, 3), offsets, points


def _triangulate_with_edge_points(corners, edge0, edge1, edge2) -> list[tuple[int, int, int]]:
    """Triangulate a triangle with extra points on its edges, adding no vertex.

    The polygon is v0, edge0..., v1, edge1..., v2, edge2... (counter-clockwise). edge0 must
    be non-empty. Two chains leave v0: A runs along edge 0 to v1; B runs the other way round,
    along edge 2 to v2 and along edge 1 to v1. After the ear at v0, a strip zig-zags between
    the chains and an ear at v1 closes it. Every triangle is proper: a strip triangle takes
    two consecutive points of one chain (collinear on one side of the triangle) and one
    point of the other chain that is not on that side, because the strip stays strictly
    between the two ears, away from v0 (on sides 0 and 2) and v1 (on sides 0 and 1).
    Winding follows the input.
    """
    v0, v1, v2 = corners
    chain_a = [v0, *edge0, v1]
    chain_b = [v0, *edge2[::-1], v2, *edge1[::-1], v1]
    n, m = len(chain_a) - 1, len(chain_b) - 1  # n >= 2, m >= 2
    out = [(v0, chain_a[1], chain_b[1])]
    i = j = 1
    while i < n - 1 or j < m - 1:
        # Advance the chain that is proportionally behind, for less skinny strip triangles.
        if j == m - 1 or (i < n - 1 and i * (m - 1) <= j * (n - 1)):
            out.append((chain_a[i], chain_a[i + 1], chain_b[j]))
            i += 1
        else:
            out.append((chain_a[i], chain_b[j + 1], chain_b[j]))
            j += 1
    out.append((chain_a[n - 1], v1, chain_b[m - 1]))
    return out


def conforming_triangles(mesh: Mesh, return_source: bool = False):
    """A display triangulation without T-vertices, for crack-free rasterisation.

    Every triangle with split-made vertices inside its edges (the midpoint of an edge, the
    midpoints of its halves, and so on) is replaced by a triangulation of the polygon made of
    its corners and those points; no vertex is added and no triangle has zero area. The
    others are kept as they are. With ``conforming_vertex_values`` the shading is the same
    linear function over the replaced triangle as over the original.

    Args:
        mesh: the mesh.
        return_source: also return which element each display triangle belongs to.

    Returns:
        triangles: (T'', 3) int64 indices into ``mesh.vertices``, wound like their element:
            the unaffected elements in order, then the pieces of the affected ones.
        source: (T'',) int64 element index of each display triangle (only if
            ``return_source``).
    """
    num = mesh.num_elements
    counts, offsets, points = _edge_points(mesh)
    affected = np.flatnonzero(counts.sum(axis=1) > 0)
    if len(affected) == 0:
        triangles, source = mesh.triangles.clone(), torch.arange(num, dtype=torch.int64)
        return (triangles, source) if return_source else triangles

    keep = np.ones(num, dtype=bool)
    keep[affected] = False
    tri = mesh.triangles.numpy()
    points = points.tolist()
    offsets = offsets.tolist()
    pieces: list[tuple[int, int, int]] = []
    piece_source: list[int] = []
    # Python over the affected elements only, a few microseconds each: this runs once per
    # displayed image, not per shot.
    for t, corners, c in zip(affected.tolist(), tri[affected].tolist(), counts[affected].tolist()):
        runs = [points[offsets[3 * t + e]:offsets[3 * t + e + 1]] for e in range(3)]
        r = 0 if c[0] else (1 if c[1] else 2)  # rotate so that edge 0 carries points
        rotated = [corners[(r + k) % 3] for k in range(3)]
        new = _triangulate_with_edge_points(rotated, runs[r], runs[(r + 1) % 3], runs[(r + 2) % 3])
        pieces.extend(new)
        piece_source.extend([t] * len(new))

    kept = np.flatnonzero(keep)
    triangles = torch.cat([mesh.triangles[torch.from_numpy(kept)],
                           torch.tensor(pieces, dtype=torch.int64).reshape(-1, 3)])
    if not return_source:
        return triangles
    source = torch.cat([torch.from_numpy(kept).to(torch.int64), torch.tensor(piece_source, dtype=torch.int64)])
    return triangles, source
