"""Where other triangles touch a plane: the footprints they cover and the lines they stand on.

A planar surface is touched in two ways (the zero-order discontinuities of discontinuity
meshing, Heckbert 1992; Lischinski, Tampieri & Greenberg 1992):

* a triangle lying in the plane and facing it (a box's bottom on the floor) covers its own
  area: nothing can see or light what lies under it. So does a triangle parallel to the
  plane hovering within a thin ``gap`` in front of it, whichever way it faces (a lamp panel
  hung 5 mm under a ceiling, its back to it; a desk top 1 mm above its legs): light reaches
  under it only through a slit, a band of about the gap's width inside its outline, and a
  ceiling element there, dark, would pull the lit ceiling beside the lamp down in every
  reconstruction that spans the outline (measured in a room with 0.5 m ceiling elements:
  22-51% dark 2-25 cm outside a lamp hung 5 mm under it). Only a cover much wider than its
  gap (``HOVER_ASPECT``) counts;
* a triangle meeting the plane along an edge and rising on the plane's front (a block's
  side standing on the floor) marks a *contact line*. Where contact lines close a polygon
  and every edge of it has a face standing on it whose normal points out of the polygon
  (the Cornell blocks' sides, which have no bottom face), the polygon is a footprint and
  is covered too. Walls standing around a floor face into it, so the floor is not covered.

Everything works in the plane's own 2D frame (``PlaneFrame``) with shapely geometry;
``tolerance`` is the distance (scene units) within which a point counts as on the plane.
A triangle exactly on the plane facing the way it does is its twin (a decal), not a cover.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import LineString, Polygon
from shapely.geometry.base import BaseGeometry

from hemirad.core.fastops import cross3
from hemirad.geometry.patches import plane_axes

#: A triangle faces the plane when its normal is within 60 degrees of the plane's reversed normal.
FACING_COSINE = 0.5
#: A hovering cover counts only where it is at least this many times wider (twice its area
#: over its perimeter) than its gap: under it the slit is then dark but for a rim about the
#: gap wide. A 10 cm tile 7 mm off a ceiling lets light under it; a 1 m lamp 5 mm off does not.
HOVER_ASPECT = 10.0


@dataclass(frozen=True)
class PlaneFrame:
    """A plane and a 2D frame in it: a point ``origin`` (3,), the unit ``normal`` (3,) and
    in-plane unit axes ``u``, ``v`` (3,) with u x v = normal, so a counter-clockwise polygon
    in (u, v) runs counter-clockwise seen from the plane's front."""

    origin: np.ndarray
    normal: np.ndarray
    u: np.ndarray
    v: np.ndarray

    def height(self, points: np.ndarray) -> np.ndarray:
        """(...,) signed distances of ``points`` (..., 3) above the plane (front positive)."""
        return (points - self.origin) @ self.normal

    def to_plane(self, points: np.ndarray) -> np.ndarray:
        """(..., 2) the in-plane coordinates of ``points`` (..., 3)."""
        d = points - self.origin
        return np.stack([d @ self.u, d @ self.v], axis=-1)

    def in_plane(self, directions: np.ndarray) -> np.ndarray:
        """(..., 2) the in-plane components of ``directions`` (..., 3)."""
        return np.stack([directions @ self.u, directions @ self.v], axis=-1)

    def lift(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) the points of the plane at in-plane coordinates ``points`` (N, 2)."""
        return self.origin + points[:, :1] * self.u + points[:, 1:] * self.v


def planar_frame(vertices: np.ndarray, triangles: np.ndarray, tolerance: float) -> PlaneFrame | None:
    """The plane of a surface (V, 3) vertices and (T, 3) triangles, or None when it is not
    planar: a vertex further than ``tolerance`` off the plane, or a triangle folded back."""
    corners = vertices[triangles]  # (T, 3, 3)
    cross = cross3(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    total = cross.sum(0)
    length = float(np.linalg.norm(total))
    if not length > 0:
        return None
    normal = total / length
    lengths = np.linalg.norm(cross, axis=1)
    if ((cross @ normal) < (1 - 1e-9) * lengths).any():  # a triangle turned away from the plane
        return None
    origin = vertices[triangles[0, 0]]
    if np.abs((vertices - origin) @ normal).max() > tolerance:
        return None
    u, v = plane_axes(normal)
    return PlaneFrame(origin, normal, u, v)


def surface_region(frame: PlaneFrame, vertices: np.ndarray, triangles: np.ndarray, tolerance: float) -> BaseGeometry:
    """The area a planar surface covers in its frame: the union of its triangles (a Polygon
    or MultiPolygon), vertices in line to within ``tolerance`` dropped (a grid's edge
    points)."""
    flat = frame.to_plane(vertices)
    return _union_of_triangles(flat[triangles], tolerance)


def _union_of_triangles(corners: np.ndarray, tolerance: float) -> BaseGeometry:
    """The union of (K, 3, 2) triangles, simplified to within ``tolerance``."""
    polygons = shapely.polygons(np.concatenate([corners, corners[:, :1]], axis=1))
    union = shapely.unary_union(polygons)
    return shapely.simplify(union, tolerance, preserve_topology=True)


@dataclass(frozen=True)
class Contacts:
    """What touches one plane.

    Attributes:
        covered: the polygonal area hidden by what touches it (possibly empty).
        segments: (L, 2, 2) the contact lines, in-plane, each a triangle's edge lying in
            the plane whose triangle rises on its front.
        outward: (L, 2) unit in-plane direction of each contact line's triangle's normal.
    """

    covered: BaseGeometry
    segments: np.ndarray
    outward: np.ndarray

    @property
    def empty(self) -> bool:
        return self.covered.is_empty and len(self.segments) == 0


def contacts(frame: PlaneFrame, corners: np.ndarray, normals: np.ndarray, tolerance: float,
             gap: float = 0.0) -> Contacts:
    """What the triangles (K, 3, 3) ``corners`` with unit ``normals`` (K, 3) do to the plane
    of ``frame``: the area they cover (lying on it facing it, or hovering within ``gap`` in
    front of it) and the contact lines they stand on (see the module)."""
    heights = frame.height(corners)  # (K, 3)
    on = np.abs(heights) <= tolerance
    facing = normals @ frame.normal < -FACING_COSINE
    parallel = np.abs(normals @ frame.normal) > FACING_COSINE
    hovering = (heights.min(axis=1) > tolerance) & (heights.max(axis=1) <= gap) & parallel
    lying = on.all(axis=1) & facing
    standing = (on.sum(axis=1) == 2) & (heights.max(axis=1) > tolerance)

    covered = [_union_of_triangles(frame.to_plane(corners[lying]), tolerance)] if lying.any() else []
    if hovering.any():
        covered += _hovering_covers(frame.to_plane(corners[hovering]), heights[hovering].max(axis=1), tolerance)
    rows = np.flatnonzero(standing)
    # each standing triangle's two corners on the plane, in their cyclic order
    off = np.argmin(on[rows], axis=1)  # the corner above the plane
    first = corners[rows, (off + 1) % 3]
    second = corners[rows, (off + 2) % 3]
    segments = np.stack([frame.to_plane(first), frame.to_plane(second)], axis=1)  # (L, 2, 2)
    outward = frame.in_plane(normals[rows])
    outward /= np.maximum(np.linalg.norm(outward, axis=1, keepdims=True), 1e-300)
    if len(rows):
        covered += _footprints(segments, outward, tolerance)
    area = shapely.unary_union(covered) if covered else Polygon()
    return Contacts(shapely.simplify(area, tolerance, preserve_topology=True), segments, outward)


def _hovering_covers(corners: np.ndarray, heights: np.ndarray, tolerance: float) -> list[BaseGeometry]:
    """The parts of the union of the hovering triangles (K, 3, 2) ``corners``, each at most
    ``heights`` (K,) off the plane, that are ``HOVER_ASPECT`` times wider than their gap."""
    union = _union_of_triangles(corners, tolerance)
    centroids = corners.mean(axis=1)
    kept = []
    for part in shapely.get_parts(union):
        inside = shapely.contains_xy(part, centroids[:, 0], centroids[:, 1])
        gap = heights[inside].max() if inside.any() else heights.max()
        if 2.0 * part.area >= HOVER_ASPECT * gap * part.length:
            kept.append(part)
    return kept


def _footprints(segments: np.ndarray, outward: np.ndarray, tolerance: float) -> list[BaseGeometry]:
    """The polygons the contact lines (L, 2, 2) close whose every edge has a standing
    triangle facing out of the polygon (``outward`` (L, 2) its in-plane normal)."""
    lines = shapely.unary_union(shapely.linestrings(segments))
    found = []
    for face in shapely.get_parts(shapely.polygonize(shapely.get_parts(lines))):
        ring = np.asarray(shapely.orient_polygons(face).exterior.coords)  # counter-clockwise
        a, b = ring[:-1], ring[1:]
        edge = b - a
        length = np.linalg.norm(edge, axis=1)
        keep = length > tolerance
        a, edge, length = a[keep], edge[keep], length[keep]
        out = np.stack([edge[:, 1], -edge[:, 0]], axis=1) / length[:, None]  # right of a CCW ring: outside
        middle = a + 0.5 * edge
        near = point_segment_distances(middle, segments) <= tolerance  # (E, L)
        agrees = (out @ outward.T) > FACING_COSINE  # (E, L)
        if (near & agrees).any(axis=1).all():
            found.append(face)
    return found


def point_segment_distances(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """(P, L) distances of (P, d) points from (L, 2, d) segments (in the plane, d = 2, or in space)."""
    a, b = segments[None, :, 0], segments[None, :, 1]
    ab = b - a
    t = ((points[:, None] - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-300)
    closest = a + np.clip(t, 0.0, 1.0)[..., None] * ab
    return np.linalg.norm(points[:, None] - closest, axis=-1)


def inner_lines(segments: np.ndarray, region: BaseGeometry, tolerance: float) -> list[np.ndarray]:
    """The parts of the contact lines (L, 2, 2) inside ``region`` and not on its boundary:
    (2, 2) pieces, noded where they cross. Pieces shorter than ``tolerance`` are dropped."""
    if not len(segments) or region.is_empty:
        return []
    inside = shapely.intersection(shapely.unary_union(shapely.linestrings(segments)), region)
    boundary = region.boundary
    pieces = []
    for part in shapely.get_parts(shapely.unary_union(inside)):
        if not isinstance(part, LineString):
            continue
        coords = np.asarray(part.coords)
        for p, q in zip(coords[:-1], coords[1:]):
            if np.linalg.norm(q - p) <= tolerance:
                continue
            probes = shapely.points(np.stack([p, q, 0.5 * (p + q)]))
            if (shapely.distance(probes, boundary) <= tolerance).all():
                continue  # along the boundary: already an edge
            pieces.append(np.stack([p, q]))
    return pieces
