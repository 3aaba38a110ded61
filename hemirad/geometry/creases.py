"""Concave creases: the sides of a quad along which another surface stands facing it.

Where two surfaces meet at a concave edge (a wall on a floor, a ceiling on a wall, a box's
side on the floor) each sees the other over half its hemisphere right at the edge, and the
other's radiosity, changing across the edge, arrives through a kernel that grows without
bound there: the received radiosity at a distance d from the edge goes as d ln d, its slope
unbounded (for perpendicular planes, a gradient g across the other surface adds about
rho g d ln(h / d) / 2). No quadratic over an element beside the edge follows that, and a
picture drawn from element means stays a few percent bright along every concave edge of a
room. An element a quarter as wide there (``hemirad.scene.meshing``) follows it.
"""
from __future__ import annotations

import numpy as np
import shapely
import torch
from shapely.geometry.base import BaseGeometry

from hemirad.core.fastops import cross3
from hemirad.geometry.mesh import barycentric

#: The width of the strip of elements along a concave crease, in elements: measured on the
#: bundled scenes' answers (docs/MEASUREMENTS.md, Concave creases).
CREASE_STRIP = 0.25
#: A triangle faces into the quad when its normal is within 60 degrees of the side's
#: inward direction.
FACING_COSINE = 0.5
#: A side is a crease when another surface stands on at least this share of it.
COVERED_SHARE = 0.5
#: Points along a side at which that is asked.
SIDE_SAMPLES = 16
#: How far in front of the quad (in ``tolerance``) a standing surface must reach.
RISE = 10.0


def crease_sides(corners: np.ndarray, triangles: np.ndarray, normals: np.ndarray, tolerance: float,
                 asked: np.ndarray | None = None) -> np.ndarray:
    """(4,) bool: which sides of the quad (4, 3) ``corners`` (side k runs from corner k to
    k + 1; the front by the right-hand rule over corners 0, 1, 2), of those ``asked`` (4,)
    bool (default all), are concave creases: at
    ``COVERED_SHARE`` of ``SIDE_SAMPLES`` points along the side, one of the triangles
    (K, 3, 3) of the other surfaces, unit ``normals`` (K, 3), holds both the point and the
    point ``RISE`` tolerances in front of the quad, and faces into the quad. A wall on a
    floor is found from either, a box's side standing inside a floor's outline too;
    surfaces ``tolerance`` apart or more (a desk top a millimetre over its legs) are not."""
    sides = np.zeros(4, dtype=bool)
    t = (np.arange(SIDE_SAMPLES) + 0.5) / SIDE_SAMPLES
    for k in range(4) if asked is None else np.flatnonzero(asked):
        a, b, d = corners[k], corners[(k + 1) % 4], corners[(k + 3) % 4]
        normal = cross3(b - a, d - a)
        length = float(np.linalg.norm(b - a))
        if not length > tolerance:
            continue
        normal = normal / max(float(np.linalg.norm(normal)), 1e-300)
        inward = np.cross(normal, (b - a) / length)  # in the quad's plane, away from the side
        facing = normals @ inward > FACING_COSINE
        if not facing.any():
            continue
        points = a + t[:, None] * (b - a)  # (P, 3)
        held = _holds(triangles[facing], points, tolerance) & _holds(triangles[facing], points + RISE * tolerance * normal,
                                                                       tolerance)
        sides[k] = held.any(axis=0).mean() >= COVERED_SHARE
    return sides


def _holds(triangles: np.ndarray, points: np.ndarray, tolerance: float) -> np.ndarray:
    """(K, P) whether each triangle (K, 3, 3) holds each point (P, 3): within ``tolerance``
    of its plane and of its outline or inside."""
    K, P = len(triangles), len(points)
    e1, e2 = triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]
    normal = cross3(e1, e2)
    area2 = np.linalg.norm(normal, axis=1)
    ok = area2 > 0
    normal = normal / np.maximum(area2, 1e-300)[:, None]
    height = np.abs(np.einsum("kpc,kc->kp", points[None] - triangles[:, None, 0], normal))
    lam = barycentric(torch.from_numpy(np.repeat(triangles, P, axis=0)),
                      torch.from_numpy(np.tile(points, (K, 1)))).numpy().reshape(K, P, 3)
    # the tolerance in barycentric units, by the shorter of the two edges
    slack = tolerance / np.sqrt(np.maximum(np.minimum((e1 * e1).sum(1), (e2 * e2).sum(1)), 1e-300))[:, None, None]
    return ok[:, None] & (height <= tolerance) & (lam >= -slack).all(axis=2)


def crease_strips(creases: np.ndarray, region: BaseGeometry, width: float) -> tuple[BaseGeometry, np.ndarray]:
    """The strips of ``width`` inside a planar ``region`` along its (C, 2, 2) ``creases``
    (in-plane segments on its outline): their area, and its outline's (E, 2, 2) segments
    (the pieces inside the region are the strips' inner edges)."""
    bands = shapely.buffer(shapely.linestrings(creases), width, cap_style="flat")
    area = shapely.intersection(shapely.unary_union(bands), region)
    rings = [np.asarray(ring.coords) for polygon in shapely.get_parts(area) if not polygon.is_empty
             for ring in (polygon.exterior, *polygon.interiors)]
    edges = [np.stack([ring[:-1], ring[1:]], axis=1) for ring in rings]
    return area, np.concatenate(edges) if edges else np.zeros((0, 2, 2))

