"""Irradiance at arbitrary points by a final gather: a hemicube rendered at each point,
every pixel's delta form factor times the radiosity of the element it sees.

A sensor is a small area at a point facing its normal: E = sum_j F_j B_j over the elements
whose front a pixel sees (``HemicubeView.form_factors`` @ B). Its accuracy is the
hemicube's, not the mesh's: the point need not be an element's, and values between
elements' centroids come from what the point itself sees.

A sensor on a surface works as a shooter does: the eye sits a hair (the renderer's near
distance) off the point along its normal, so the surface under it falls below the
horizon. A sensor in mid-air (a work plane) needs no surface under it: its hemicube sees
the half-space its normal faces, so it measures the irradiance on that side only.
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Iterator

import numpy as np
import torch

from hemirad.core.runtime import torch_threads
from hemirad.geometry.mesh import Mesh
from hemirad.transport.gl import GLContext
from hemirad.transport.hemicube import OFF_AXIS_TANGENT
from hemirad.transport.renderer import HemicubeRenderer, clip_planes

#: The hemicube resolution of a sensor: at 256 a point under a rectangular lamp is within
#: 0.5% of Lambert's closed form (0.07% on average; tests/test_sensors.py).
SENSOR_RESOLUTION = 256


@dataclass(frozen=True)
class Gather:
    """What the hemicubes of N sensors saw.

    Attributes:
        irradiance: (N, 3) float64, sum over pixels of delta form factor x radiosity of
            the element whose front the pixel sees.
        coverage: (N,) float64 the share of the hemisphere (cosine-weighted, 0 to 1) in
            which the sensor sees any surface, front or back: 0 where it sees nothing.
        front_coverage: (N,) float64 the same for surfaces' fronts only (what receives):
            0 where it sees only back faces (a point inside an object).
    """

    irradiance: torch.Tensor
    coverage: torch.Tensor
    front_coverage: torch.Tensor


def unit_normals(normals) -> np.ndarray:
    """(N, 3) float64 the normals scaled to length 1; ValueError for a zero or non-finite one."""
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    scale = np.abs(normals).max(axis=1, keepdims=True)  # first, so that 1e-200 does not underflow
    if not (np.isfinite(normals).all() and (scale > 0).all()):
        raise ValueError("every sensor needs a finite, non-zero normal")
    normals = normals / scale
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


@contextlib.contextmanager
def sensor_renderer(mesh: Mesh, points, resolution: int = SENSOR_RESOLUTION) -> Iterator[HemicubeRenderer]:
    """A renderer of ``mesh`` whose clip planes reach from any of ``points`` (N, 3) across
    the mesh (in the process's one GL context), released on exit."""
    mesh = mesh.to("cpu")
    points = torch.as_tensor(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    renderer = HemicubeRenderer(mesh, resolution, clip=clip_planes(mesh, points))
    try:
        yield renderer
    finally:
        renderer.close()


def final_gather(mesh: Mesh, radiosity: torch.Tensor, points, normals, resolution: int = SENSOR_RESOLUTION,
                 renderer: HemicubeRenderer | None = None) -> Gather:
    """Irradiance at N points, and how much of their hemisphere sees a surface.

    Args:
        mesh: the solved mesh (T elements).
        radiosity: (T, 3) the radiosity to gather (``Result.display_radiosity``).
        points: (N, 3) positions; normals: (N, 3) the directions they face (any length > 0).
        resolution: the hemicube's, when no ``renderer`` is given.
        renderer: one made by ``sensor_renderer`` for these points (or a ``HemicubeRenderer``
            of ``mesh`` whose clip planes reach them); one GL context serves every point.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    normals = unit_normals(normals)
    if len(points) != len(normals):
        raise ValueError(f"need one normal per point, got {len(points)} points and {len(normals)} normals")
    if renderer is None:
        with sensor_renderer(mesh, points, resolution) as renderer:
            return final_gather(mesh, radiosity, points, normals, renderer=renderer)
    radiosity = torch.as_tensor(radiosity, dtype=torch.float64).to(renderer.device)
    if radiosity.shape != (renderer.mesh.num_elements, 3):
        raise ValueError(f"radiosity must be ({renderer.mesh.num_elements}, 3), got {tuple(radiosity.shape)}")
    irradiance = torch.zeros(len(points), 3, dtype=torch.float64)
    coverage = torch.zeros(len(points), dtype=torch.float64)
    front_coverage = torch.zeros(len(points), dtype=torch.float64)
    # as in a solve: beside a software renderer, a second torch thread only fights it for the cores
    with torch_threads(1 if GLContext.is_software() else torch.get_num_threads()):
        for i, view in enumerate(renderer.views_at(points, normals, OFF_AXIS_TANGENT)):
            irradiance[i] = (view.form_factors @ radiosity).cpu()
            front_coverage[i] = float(view.form_factors.sum())
            coverage[i] = front_coverage[i] + float(view.back_share)  # every pixel that sees a face
    return Gather(irradiance, coverage, front_coverage)


def irradiance_at(mesh: Mesh, radiosity: torch.Tensor, points, normals, resolution: int = SENSOR_RESOLUTION,
                  renderer: HemicubeRenderer | None = None) -> torch.Tensor:
    """(N, 3) float64 the irradiance at ``points`` (N, 3) on small areas facing ``normals``
    (N, 3): the sum over hemicube pixels of delta form factor x ``radiosity`` (T, 3) of
    the element whose front the pixel sees. See ``final_gather``."""
    return final_gather(mesh, radiosity, points, normals, resolution, renderer).irradiance
