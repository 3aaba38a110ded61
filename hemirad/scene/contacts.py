"""Meshes that respect contact lines: each planar surface that other surfaces touch is
meshed anew so that no element straddles where they touch, and what they cover is dropped.

Where a block stands on a floor the shadow is sharp along its footprint, and a floor
element straddling the footprint gives lit, shadowed and hidden floor one value (measured on
the Cornell box: -38% to +157% 0.5-2 cm outside the blocks at every uniform element size
tried). So before the solve, for every planar surface (a quad, a face of a room or box, a
planar patch of a mesh file), ``geometry.footprints`` finds from the geometry alone what
touches it: faces lying in its plane facing it or hovering a hair in front of it (a lamp
hung just under a ceiling), and faces standing on it. The touched surface is then
triangulated afresh (``geometry.conforming``) with the footprints' outlines and the contact
lines as element edges and the covered part left out: nothing can see or light it.
Surfaces nothing touches (or touches only along their outline, as walls meet a floor) keep
their meshes exactly.

Contacts are found on the surfaces as first meshed, so the result does not depend on the
order of the objects.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hemirad.core.fastops import cross3
from hemirad.geometry.conforming import triangulate
from hemirad.geometry.creases import CREASE_STRIP, crease_strips
from hemirad.geometry.footprints import PlaneFrame, contacts, inner_lines, planar_frame, surface_region

#: Points within this fraction of the scene's size of a plane touch it. The bundled scenes'
#: parts meant not to touch keep 1e-4 or more of their size apart (a lamp under a
#: ceiling, a desk top on its legs), and a contact is exact in a scene file's numbers.
CONTACT_TOLERANCE = 1e-6
#: A face parallel to a plane and within this fraction of the scene's size in front of it
#: covers the plane as if it lay on it (``footprints.contacts``): a lamp hung 5 mm under
#: the ceiling of a 4-5 m room (1.0-1.3e-3), the Cornell light 0.5 mm under its ceiling
#: (9e-4), a desk top 1 mm above its legs. Light enters such a slit only along its rim.
HOVER_GAP = 2e-3


@dataclass(frozen=True)
class SurfaceGeometry:
    """One surface as first meshed: (V, 3) float64 ``vertices``, (T, 3) int64 ``triangles``,
    the ``element_size`` it was meshed at and the (C, 2, 3) ``creases`` its mesh is graded
    toward (``hemirad.geometry.creases``), which a new mesh keeps."""

    vertices: np.ndarray
    triangles: np.ndarray
    element_size: float
    creases: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))


def scene_size(surfaces: list[SurfaceGeometry]) -> float:
    """The largest side of the bounding box of all the ``surfaces``' vertices: what
    ``CONTACT_TOLERANCE`` and ``HOVER_GAP`` are fractions of."""
    return float(np.ptp(np.concatenate([s.vertices for s in surfaces]), axis=0).max())


def bounding_boxes(corners: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(S, 3) lows and highs of each surface's triangles (K, 3, 3) in ``corners``."""
    return (np.stack([c.reshape(-1, 3).min(axis=0) for c in corners]),
            np.stack([c.reshape(-1, 3).max(axis=0) for c in corners]))


def overlapping(low: np.ndarray, high: np.ndarray, own: int, margin: float) -> np.ndarray:
    """(S,) bool: the boxes (S, 3) ``low``/``high`` within ``margin`` of box ``own``'s, itself left out."""
    near = ((low <= high[own] + margin) & (high >= low[own] - margin)).all(axis=1)
    near[own] = False
    return near


def conform_to_contacts(surfaces: list[SurfaceGeometry]) -> list[tuple[np.ndarray, np.ndarray] | None]:
    """For each surface, its new (vertices (V', 3), triangles (T', 3)) where others touch it
    (T' may be 0: all of it is covered), or None where its mesh stays as it is."""
    if not surfaces:
        return []
    size = scene_size(surfaces)
    tolerance, gap = CONTACT_TOLERANCE * size, HOVER_GAP * size
    corners = [s.vertices[s.triangles] for s in surfaces]
    normals = [unit_normals(c) for c in corners]
    low, high = bounding_boxes(corners)
    out = []
    for i, surface in enumerate(surfaces):
        frame = planar_frame(surface.vertices, surface.triangles, tolerance)
        if frame is None:
            out.append(None)
            continue
        near = _touching(frame, i, low, high, tolerance, gap)
        touching = [(corners[j][rows], normals[j][rows]) for j in near
                    for rows in [_rows_on_plane(frame, corners[j], low[i], high[i], tolerance, gap)] if len(rows)]
        if not touching:
            out.append(None)
            continue
        found = contacts(frame, np.concatenate([c for c, _ in touching]),
                         np.concatenate([n for _, n in touching]), tolerance, gap)
        out.append(None if found.empty else _remesh(surface, frame, found, tolerance))
    return out


def _remesh(surface: SurfaceGeometry, frame: PlaneFrame, found, tolerance: float):
    """The surface meshed around its contacts, or None when they change nothing (they lie
    along its outline, or outside it)."""
    region = surface_region(frame, surface.vertices, surface.triangles, tolerance)
    covered = found.covered.intersection(region)
    sliver = tolerance * region.length  # the area of a band of the tolerance's width along the outline
    remaining = region.difference(covered) if covered.area > sliver else region
    if remaining.area <= sliver:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    lines = inner_lines(found.segments, remaining, tolerance)
    if remaining is region and not lines:
        return None
    strips = None
    if len(surface.creases):  # the grid's strips along concave creases, kept as element edges
        strips, edges = crease_strips(frame.to_plane(surface.creases), region, CREASE_STRIP * surface.element_size)
        lines = inner_lines(np.concatenate([found.segments, edges]), remaining, tolerance)
    grid = frame.to_plane(surface.vertices)  # the Steiner points away from the contacts
    points, triangles = triangulate(remaining, lines, grid, surface.element_size, tolerance, thin=strips)
    return frame.lift(points), triangles


def unit_normals(corners: np.ndarray) -> np.ndarray:
    cross = cross3(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return cross / np.maximum(np.linalg.norm(cross, axis=1, keepdims=True), 1e-300)


def _touching(frame: PlaneFrame, own: int, low: np.ndarray, high: np.ndarray, tolerance: float,
              gap: float) -> list[int]:
    """The surfaces (other than ``own``) whose bounding boxes (S, 3) ``low``/``high`` overlap
    ``own``'s and reach the plane or the ``gap`` in front of it (within ``tolerance`` behind)."""
    centre, half = 0.5 * (low + high), 0.5 * (high - low)
    height = frame.height(centre)
    reach = half @ np.abs(frame.normal)
    crosses = (height - reach <= gap) & (height + reach >= -tolerance)
    return np.flatnonzero(overlapping(low, high, own, gap) & crosses).tolist()


def _rows_on_plane(frame: PlaneFrame, corners: np.ndarray, low: np.ndarray, high: np.ndarray,
                   tolerance: float, gap: float) -> np.ndarray:
    """The triangles of (K, 3, 3) ``corners`` with two or more corners on the plane, or all
    three on it or within ``gap`` in front of it, within ``gap`` of the touched surface's
    bounding box (3,) ``low``/``high`` (what lies beyond its outline is cut off later)."""
    height = frame.height(corners)
    on = np.abs(height) <= tolerance
    close = (height >= -tolerance) & (height <= gap)
    near = (corners.min(axis=1) <= high + gap).all(axis=1) & (corners.max(axis=1) >= low - gap).all(axis=1)
    return np.flatnonzero(((on.sum(axis=1) >= 2) | close.all(axis=1)) & near)
