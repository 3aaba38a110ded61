"""A solved scene's sensors and calculation grids, read by one final gather.

``measure`` renders a hemicube at every sensor and grid point of the scene (one renderer,
one GL context) and gives each its irradiance, its illuminance in lux and, per grid,
EN 12464-1's statistics; ``blind_grids`` finds, before a solve, grids that see no surface.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch

from hemirad.core.colour import luminance
from hemirad.core.errors import HemiradWarning
from hemirad.geometry.mesh import Mesh
from hemirad.lighting.grids import GridLayout, grid_layout, grid_statistics
from hemirad.lighting.photometry import illuminance
from hemirad.lighting.sensors import SENSOR_RESOLUTION, final_gather, sensor_renderer, unit_normals
from hemirad.scene.model import Grid, Scene
from hemirad.transport.hemicube import OFF_AXIS_TANGENT

#: The columns of ``sensors.csv`` (E: the luminance of E_r, E_g, E_b in the scene's unit).
SENSOR_COLUMNS = ("name", "x", "y", "z", "nx", "ny", "nz", "E_r", "E_g", "E_b", "E", "lux")
#: The columns of ``grid_<name>.csv``: row j and column i count along v and u from the origin.
GRID_COLUMNS = ("row", "column", "x", "y", "z", "nx", "ny", "nz", "E_r", "E_g", "E_b", "E", "lux")


def _number(x: float) -> str:
    return repr(float(x))  # the shortest text that reads back as the same float


@dataclass(frozen=True)
class SensorReadings:
    """N sensors' values: ``names``; ``points``, ``normals`` (unit), ``irradiance`` (N, 3)
    float64; ``lux`` (N,) their illuminance; ``coverage``, ``front_coverage`` (N,) as in
    ``sensors.Gather``."""

    names: list[str]
    points: torch.Tensor
    normals: torch.Tensor
    irradiance: torch.Tensor
    lux: torch.Tensor
    coverage: torch.Tensor
    front_coverage: torch.Tensor

    def table(self) -> tuple[tuple[str, ...], list[list[str]]]:
        """(header, rows) of ``sensors.csv``."""
        rows = []
        for i, name in enumerate(self.names):
            numbers = [*self.points[i].tolist(), *self.normals[i].tolist(), *self.irradiance[i].tolist(),
                       float(luminance(self.irradiance[i])), float(self.lux[i])]
            rows.append([name, *map(_number, numbers)])
        return SENSOR_COLUMNS, rows


@dataclass(frozen=True)
class GridReadings:
    """One grid's values: ``layout`` (its points, (rows, columns, 3)), ``irradiance``
    (rows, columns, 3), ``lux`` (rows, columns), ``coverage`` and ``front_coverage``
    (rows, columns), and ``statistics`` (``grid_statistics`` of the lux)."""

    grid: Grid
    layout: GridLayout
    irradiance: torch.Tensor
    lux: torch.Tensor
    coverage: torch.Tensor
    front_coverage: torch.Tensor
    statistics: dict

    @property
    def file_name(self) -> str:
        return grid_file_name(self.grid.name)

    def stats(self, metres_per_unit: float) -> dict:
        """What stats.json says of the grid: its size, spacing and statistics (in lux)."""
        rows, columns = self.layout.shape
        return {"points": rows * columns, "rows": rows, "columns": columns, "spacing": self.layout.spacing,
                "spacing_m": self.layout.spacing * metres_per_unit, "cell": list(self.layout.cell),
                "normal": self.layout.normal.tolist(), "unit": "lx", **self.statistics,
                "points_seeing_nothing": int((self.front_coverage == 0).sum()), "file": self.file_name}

    def table(self) -> tuple[tuple[str, ...], list[list[str]]]:
        """(header, rows) of ``grid_<name>.csv``, row by row along v, column by column along u."""
        rows, columns = self.layout.shape
        normal = self.layout.normal.tolist()
        out = []
        for j in range(rows):
            for i in range(columns):
                e = self.irradiance[j, i]
                numbers = [*self.layout.points[j, i].tolist(), *normal, *e.tolist(), float(luminance(e)),
                           float(self.lux[j, i])]
                out.append([str(j), str(i), *map(_number, numbers)])
        return GRID_COLUMNS, out


def grid_file_name(name: str, suffix: str = ".csv") -> str:
    """A grid's file: its table (``.csv``), or its false-colour picture (``.png``)."""
    return f"grid_{name}{suffix}"


def output_names(scene: Scene) -> list[str]:
    """The files a run of ``scene`` writes for its sensors and grids."""
    return (["sensors.csv"] if scene.sensors else []) + [grid_file_name(g.name, suffix) for g in scene.grids
                                                          for suffix in (".csv", ".png")]


def blind_grids(scene: Scene, mesh: Mesh, resolution: int = SENSOR_RESOLUTION) -> list[Grid]:
    """The grids of ``scene`` none of whose points sees any surface of ``mesh`` (a grid
    outside the scene). A grid that sees something is usually known from its first point,
    so this costs about a hemicube per grid."""
    layouts = [grid_layout(grid, scene.metres_per_unit) for grid in scene.grids]
    if not layouts:
        return []
    points = torch.cat([layout.points.reshape(-1, 3) for layout in layouts])
    blind = []
    with sensor_renderer(mesh, points, resolution) as renderer:
        for grid, layout in zip(scene.grids, layouts):
            normal = layout.normal.numpy()
            if not any(bool((renderer.render_at(point, normal, OFF_AXIS_TANGENT).element >= 0).any())
                       for point in layout.points.reshape(-1, 3).numpy()):
                blind.append(grid)
    return blind


def measure(scene: Scene, mesh: Mesh, radiosity: torch.Tensor, resolution: int = SENSOR_RESOLUTION
            ) -> tuple[SensorReadings | None, dict[str, GridReadings]]:
    """Every sensor's and grid point's irradiance and illuminance on the solved ``mesh``,
    from ``radiosity`` (T, 3) (the display radiosity), with a hemicube of ``resolution``.
    Warns (``HemiradWarning``) of sensors and grid points that see no surface's front.

    Returns:
        The sensors' readings (None when the scene has none), and the grids' by name.
    """
    layouts = [grid_layout(grid, scene.metres_per_unit) for grid in scene.grids]
    sensor_points = np.array([s.position for s in scene.sensors], dtype=np.float64).reshape(-1, 3)
    sensor_normals = np.array([s.normal for s in scene.sensors], dtype=np.float64).reshape(-1, 3)
    points = np.concatenate([sensor_points, *(layout.points.reshape(-1, 3).numpy() for layout in layouts)])
    normals = np.concatenate([sensor_normals, *(layout.normal.expand(layout.points.shape[:2] + (3,)).reshape(-1, 3)
                                                .numpy() for layout in layouts)])
    if not len(points):
        return None, {}
    with sensor_renderer(mesh, points, resolution) as renderer:
        gather = final_gather(mesh, radiosity, points, normals, renderer=renderer)
    lux = illuminance(gather.irradiance, scene.units)
    sensors = None
    n = len(scene.sensors)
    if n:
        sensors = SensorReadings([s.name for s in scene.sensors], torch.from_numpy(sensor_points),
                                 torch.from_numpy(unit_normals(sensor_normals)), gather.irradiance[:n], lux[:n],
                                 gather.coverage[:n], gather.front_coverage[:n])
        for name, seen in zip(sensors.names, sensors.front_coverage.tolist()):
            if seen == 0:
                warnings.warn(f"sensor {name!r} sees no surface's front (it is outside the scene, or inside an "
                              f"object, or faces away from everything): its irradiance is 0", HemiradWarning)
    grids, start = {}, n
    for grid, layout in zip(scene.grids, layouts):
        rows, columns = layout.shape
        part = slice(start, start + rows * columns)
        start += rows * columns
        readings = GridReadings(grid, layout, gather.irradiance[part].reshape(rows, columns, 3),
                                lux[part].reshape(rows, columns), gather.coverage[part].reshape(rows, columns),
                                gather.front_coverage[part].reshape(rows, columns), grid_statistics(lux[part]))
        blind = int((readings.front_coverage == 0).sum())
        if blind:
            warnings.warn(f"{blind} of the {rows * columns} points of grid {grid.name!r} see no surface's front "
                          f"(outside the scene or inside an object): their illuminance is 0", HemiradWarning)
        grids[grid.name] = readings
    return sensors, grids
