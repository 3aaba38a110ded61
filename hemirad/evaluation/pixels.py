"""A solution against a path-traced reference image at chosen surface points: the pixel
each point projects into, kept where the camera sees the point and the pixel shows nothing
but its surface (so the pixel's radiance is that point's neighbourhood, not a blend)."""
from __future__ import annotations

import math

import numpy as np

from hemirad.evaluation.reference import Reference, coverage, radiance_view
from hemirad.output.render import camera_basis
from hemirad.scene.model import Camera

#: A pixel counts as showing only the surface when this share of it does.
WHOLE_SURFACE = 0.99


def pixel_of(point: np.ndarray, camera: Camera, width: int, height: int) -> tuple[int, int]:
    """(row, column) of the pixel ``point`` (3,) projects into (top row first, as images are)."""
    e = camera_basis(camera) @ (point - np.asarray(camera.position))
    f = 1.0 / math.tan(math.radians(camera.fov) / 2)
    x, y = f * height / width * e[0] / -e[2], f * e[1] / -e[2]
    return int((1 - y) / 2 * height), int((x + 1) / 2 * width)


def unoccluded(point: np.ndarray, eye: np.ndarray, corners: np.ndarray) -> bool:
    """Whether the segment from ``point`` (3,) to ``eye`` (3,) misses every triangle of
    ``corners`` (K, 3, 3) (Moller-Trumbore; the point's own surface, at t = 0, does not count)."""
    d = eye - point
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    h = np.cross(d, e2)
    a = (e1 * h).sum(1)
    ok = np.abs(a) > 1e-12
    f = 1.0 / np.where(ok, a, 1.0)
    s = point - corners[:, 0]
    u = f * (s * h).sum(1)
    q = np.cross(s, e1)
    v = f * (q @ d)
    t = f * (e2 * q).sum(1)
    return not (ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9) & (t < 1)).any()


def errors_at_points(result, points: np.ndarray, surface: int, reference: Reference) -> np.ndarray:
    """Relative errors of ``result``'s view (as its picture shades it) against
    ``reference`` at the pixels of ``points`` (N, 3) on the mesh's ``surface`` that the
    camera sees and that show only that surface; (M,) for the M <= N points kept."""
    camera, mesh = reference.camera, result.mesh
    view = radiance_view(mesh, result.shading(), camera)
    _, share = coverage(mesh, mesh.surface == surface, camera)
    height, width = reference.radiance.shape[:2]
    corners, eye = mesh.corners.numpy(), np.asarray(camera.position, dtype=np.float64)
    errors = []
    for point in points:
        row, col = pixel_of(point, camera, width, height)
        if not (0 <= row < height and 0 <= col < width) or share[row, col] <= WHOLE_SURFACE:
            continue
        if unoccluded(point, eye, corners):
            errors.append(view[row, col].mean() / reference.radiance[row, col].mean() - 1)
    return np.asarray(errors)
