"""Surfaces that cut through each other: each is cut along where the others pass through
it, and what lies inside a closed solid is dropped.

A lamp's barrel pushed into its glass globe, a pipe through a wall, a box sunk into a
floor: an element straddling the other surface is lit (and shoots) as one value for both
sides, and one whose centroid lies inside a closed solid sees the solid's back faces from
its hemicube, so its light escapes the scene (measured on a furnished room whose globes
are pierced by their barrels: 9.3% of the emitted power lost that way). So before the
solve every surface is cut where other surfaces' triangles cross it (``geometry.crossings``;
only triangles with corners on both sides of it: what merely touches it is contact
meshing's business) and the pieces inside a closed solid (``geometry.solids``) that the
surface is not part of are dropped: nothing outside can see or light them, and what they
would emit stays inside the solid.

A planar surface (a quad, a face of a room or box, a flat patch of a mesh file) is meshed
anew with the cut lines as element edges (``geometry.conforming``, as contact meshing
does, its grid away from the cuts kept). A curved patch of a mesh file is cut triangle by
triangle, each crossed triangle triangulated in its own plane with no point added on its
edges, so it meets its neighbours where they meet it. Surfaces nothing crosses and no
solid holds keep their meshes exactly.

Cuts are found on the surfaces as first meshed, so the result does not depend on the
order of the objects.
"""
from __future__ import annotations

import numpy as np
import shapely
from scipy.spatial import cKDTree

from hemirad.core.fastops import cross3
from hemirad.geometry.conforming import MIN_ANGLE, min_angles, triangulate
from hemirad.geometry.crossings import crossing_segments
from hemirad.geometry.footprints import PlaneFrame, inner_lines, planar_frame, surface_region
from hemirad.geometry.patches import plane_axes
from hemirad.geometry.solids import Solid, closed_solids
from hemirad.scene.contacts import CONTACT_TOLERANCE, SurfaceGeometry, bounding_boxes, overlapping, scene_size

Meshed = tuple[np.ndarray, np.ndarray]


def cut_at_intersections(surfaces: list[SurfaceGeometry], shells: list[Meshed]) -> list[Meshed | None]:
    """For each surface, its new (vertices (V', 3), triangles (T', 3)) where others cut it or
    a solid holds part of it (T' may be 0: a solid holds all of it), or None where its mesh
    stays as it is. ``shells[i]`` is surface i's outline triangles (vertices (V, 3),
    triangles (T, 3): a quad's two, a mesh patch's own before subdivision), from which the
    closed solids are found."""
    if not surfaces:
        return []
    tolerance = CONTACT_TOLERANCE * scene_size(surfaces)
    solids = closed_solids(shells, tolerance)
    corners = [s.vertices[s.triangles] for s in surfaces]
    low, high = bounding_boxes(corners)
    out = []
    for i, surface in enumerate(surfaces):
        overlap = overlapping(low, high, i, tolerance)
        cutting = _near_box(np.concatenate([corners[j] for j in np.flatnonzero(overlap)] or [np.zeros((0, 3, 3))]),
                            low[i], high[i], tolerance)
        around = [s for s in solids if i not in s.members
                  and (s.low <= high[i] + tolerance).all() and (s.high >= low[i] - tolerance).all()]
        frame = planar_frame(surface.vertices, surface.triangles, tolerance)
        if frame is not None:
            out.append(_cut_plane(surface, frame, cutting, around, tolerance))
        else:
            out.append(_cut_in_place(surface, corners[i], cutting, around, tolerance))
    return out


def _cut_plane(surface: SurfaceGeometry, frame: PlaneFrame, cutting: np.ndarray, around: list[Solid],
               tolerance: float) -> Meshed | None:
    """A planar surface meshed anew along the lines (K, 3, 3) ``cutting`` cuts in it, the
    parts inside the solids ``around`` dropped; None when that changes nothing."""
    _, segments = crossing_segments(frame.origin, frame.normal, cutting, tolerance)
    region = surface_region(frame, surface.vertices, surface.triangles, tolerance) if len(segments) else None
    lines = _straightened(inner_lines(frame.to_plane(segments), region, tolerance), tolerance)
    if not lines:
        return _without_inside_or_needles(surface.vertices, surface.triangles, around, tolerance,
                                          unchanged_is_none=True)
    grid = frame.to_plane(surface.vertices)
    # a narrow quad's grid is thinner than the mesher's 28 degrees: ask no better of its cuts,
    # or the refinement chases the grid's own triangles through the whole surface
    own = min_angles(grid[surface.triangles]).min() * (1 - 1e-6)
    points, triangles = triangulate(region, lines, grid, surface.element_size, tolerance,
                                    min_angle=min(MIN_ANGLE, own))
    return _without_inside_or_needles(frame.lift(points), triangles, around, tolerance)


def _cut_in_place(surface: SurfaceGeometry, corners: np.ndarray, cutting: np.ndarray, around: list[Solid],
                  tolerance: float) -> Meshed | None:
    """A curved surface (its triangles (T, 3, 3) ``corners``) with each triangle that
    ``cutting`` (K, 3, 3) crosses triangulated in its own plane along the cuts, the parts
    inside the solids ``around`` dropped; None when that changes nothing."""
    pairs = _box_pairs(corners, cutting, tolerance)
    normals = cross3(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    rows, segments = crossing_segments(corners[pairs[:, 0], 0], normals[pairs[:, 0]], cutting[pairs[:, 1]],
                                       tolerance, planes=pairs[:, 0])
    facet_of = pairs[rows, 0]
    vertices, kept = surface.vertices, np.ones(len(corners), dtype=bool)
    added_points, added_triangles, count = [], [], len(vertices)
    facets = np.unique(facet_of)
    for t, u, v in zip(facets, *plane_axes(normals[facets])):
        frame = PlaneFrame(corners[t, 0], normals[t], u, v)
        outline = shapely.Polygon(frame.to_plane(corners[t]))
        lines = _straightened(inner_lines(frame.to_plane(segments[facet_of == t]), outline, tolerance), tolerance)
        if not lines:
            continue
        points, triangles = triangulate(outline, lines, np.zeros((0, 2)), surface.element_size, tolerance,
                                        quality_rounds=0)
        kept[t] = False
        added_points.append(frame.lift(points))
        added_triangles.append(triangles + count)
        count += len(points)
    if not added_points:
        return _without_inside_or_needles(vertices, surface.triangles, around, tolerance, unchanged_is_none=True)
    vertices = np.concatenate([vertices, *added_points])
    triangles = np.concatenate([surface.triangles[kept], *added_triangles])
    return _without_inside_or_needles(*_weld(vertices, triangles, len(surface.vertices), tolerance), around,
                                      tolerance)


def _straightened(lines: list[np.ndarray], tolerance: float) -> list[np.ndarray]:
    """The (2, 2) pieces of ``lines`` joined where they continue one another in a straight
    line (within ``tolerance``): a cut comes in pieces, one per triangle of the other
    surface, and their ends (two close together where a grid's diagonal crosses) would
    otherwise all become vertices, with small triangles around them."""
    if not lines:
        return []
    merged = shapely.simplify(shapely.line_merge(shapely.multilinestrings(np.asarray(lines))), tolerance)
    pieces = []
    for part in shapely.get_parts(merged):
        coords = np.asarray(part.coords)
        pieces += [np.stack([p, q]) for p, q in zip(coords[:-1], coords[1:]) if np.linalg.norm(q - p) > tolerance]
    return pieces


def _without_inside_or_needles(vertices: np.ndarray, triangles: np.ndarray, around: list[Solid], tolerance: float,
                    unchanged_is_none: bool = False) -> Meshed | None:
    """The triangles whose centroids no solid of ``around`` holds, and that are not needles,
    with the vertices they use; None when ``unchanged_is_none`` and every triangle stays.

    A needle, a triangle thinner than ``tolerance`` (its height over its longest side), is
    what a cut's end found within rounding of an edge, not on it, leaves between them (the
    furnished room's barrels: 80 of them, 5 units long and 6e-7 high). Nothing can see one,
    and a hemicube pixel that happens to fall on it gives it thousands of times its share
    (7 to 75 times the lamps' own radiosity, before); the crack it leaves is narrower than
    the tolerance."""
    corners = vertices[triangles]
    edges = corners - np.roll(corners, 1, axis=1)
    longest = np.linalg.norm(edges, axis=2).max(axis=1)
    needle = np.linalg.norm(cross3(edges[:, 0], edges[:, 1]), axis=1) <= tolerance * longest  # 2 A / side
    inside = np.zeros(len(triangles), dtype=bool)
    if len(triangles):
        centroids = corners.mean(axis=1)
        for solid in around:
            inside |= solid.contains(centroids, tolerance)
    if unchanged_is_none and not (inside | needle).any():
        return None
    triangles = triangles[~(inside | needle)]
    used, index = np.unique(triangles, return_inverse=True)
    return vertices[used], index.reshape(-1, 3).astype(np.int64)


def _weld(vertices: np.ndarray, triangles: np.ndarray, first_added: int, tolerance: float) -> Meshed:
    """Vertices from index ``first_added`` on merged into any vertex within ``tolerance``
    that comes before them: a cut's end on an edge two cut triangles share is found from
    each (in its own plane) to within rounding, and must be one vertex of the surface.
    Triangles left with a corner twice are dropped (``_without_inside_or_needles`` drops them as needles)."""
    target = np.arange(len(vertices))
    for i, j in sorted(cKDTree(vertices).query_pairs(tolerance)):  # i < j
        if j >= first_added:
            target[j] = min(target[j], target[i])
    target = target[target]  # a chain of merges ends at its first vertex
    triangles = target[triangles]
    return vertices, triangles


def _near_box(corners: np.ndarray, low: np.ndarray, high: np.ndarray, tolerance: float) -> np.ndarray:
    """The triangles of (K, 3, 3) ``corners`` whose bounding boxes meet the box ``low``, ``high`` (3,)."""
    near = (corners.min(axis=1) <= high + tolerance).all(axis=1) & (corners.max(axis=1) >= low - tolerance).all(axis=1)
    return corners[near]


def _box_pairs(first: np.ndarray, second: np.ndarray, tolerance: float) -> np.ndarray:
    """(N, 2) the index pairs (into (A, 3, 3) ``first``, (B, 3, 3) ``second``) of triangles
    whose bounding boxes meet (within ``tolerance``), sorted.

    Boxes are centres and half-sizes: they meet where the centres are no farther apart on
    any axis than the half-sizes together. A k-d tree of the centres of ``second`` (in the
    max norm) finds the candidates, one tree per size class (half-sizes within a factor of
    2), so a wall's large triangles do not make every query reach over the whole scene."""
    if not len(first) or not len(second):
        return np.zeros((0, 2), dtype=np.int64)
    centre_a, half_a = 0.5 * (first.max(axis=1) + first.min(axis=1)), 0.5 * np.ptp(first, axis=1) + tolerance
    centre_b, half_b = 0.5 * (second.max(axis=1) + second.min(axis=1)), 0.5 * np.ptp(second, axis=1)
    reach_b = half_b.max(axis=1)
    size_class = np.floor(np.log2(np.maximum(reach_b, 1e-300))).astype(np.int64)
    found = []
    for k in np.unique(size_class):
        members = np.flatnonzero(size_class == k)
        near = cKDTree(centre_b[members]).query_ball_point(centre_a, half_a.max(axis=1) + reach_b[members].max(),
                                                           p=np.inf)
        counts = np.fromiter((len(n) for n in near), dtype=np.int64, count=len(near))
        if not counts.sum():
            continue
        a = np.repeat(np.arange(len(first)), counts)
        b = members[np.concatenate([n for n in near if n]).astype(np.int64)]
        meet = (np.abs(centre_a[a] - centre_b[b]) <= half_a[a] + half_b[b]).all(axis=1)
        found.append(np.stack([a[meet], b[meet]], axis=1))
    if not found:
        return np.zeros((0, 2), dtype=np.int64)
    pairs = np.concatenate(found)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
