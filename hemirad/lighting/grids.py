"""Calculation grids: where their points lie (EN 12464-1's spacing) and their statistics.

EN 12464-1:2021 (as its 2011 edition, section 4.4) sizes a grid from the longer side d of
the area, in metres: the points are at most p = 0.2 x 5^log10(d) m apart (p at most 10 m).
Each side of length l gets the fewest points n with l / n <= p, at the centres of the n
equal cells, so that the outer points lie half a cell in from the border.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from hemirad.scene.model import Grid

#: The largest spacing the standard's formula gives, in metres (reached at d = 269 m).
MAX_STANDARD_SPACING = 10.0

#: The most points one grid may have: each is a hemicube rendered after the solve.
MAX_GRID_POINTS = 10_000

# l / n <= p with a little slack, so that 1 / 0.2 = 5.000000000000001 gives 5 points.
_SLACK = 1e-9


def standard_spacing(longer_side_m: float) -> float:
    """EN 12464-1's largest grid spacing p (m) for an area whose longer side is ``longer_side_m``."""
    if not longer_side_m > 0:
        raise ValueError(f"the side must be positive, got {longer_side_m}")
    return min(0.2 * 5.0 ** math.log10(longer_side_m), MAX_STANDARD_SPACING)


def points_per_side(length: float, spacing: float) -> int:
    """The fewest points n >= 1 on a side of ``length`` with ``length / n <= spacing``."""
    ratio = length / spacing
    if not math.isfinite(ratio) or ratio > 1e15:  # only ever to be refused as too many
        return 10**15
    return max(1, math.ceil(ratio * (1 - _SLACK)))


def grid_spacing(grid: Grid, metres_per_unit: float) -> float:
    """The grid's largest spacing in scene units: its own, else the standard's."""
    if grid.spacing is not None:
        return grid.spacing
    longer = max(float(np.linalg.norm(grid.u)), float(np.linalg.norm(grid.v)))
    return standard_spacing(longer * metres_per_unit) / metres_per_unit


def grid_counts(grid: Grid, metres_per_unit: float) -> tuple[int, int]:
    """(columns along u, rows along v) of the grid's points."""
    spacing = grid_spacing(grid, metres_per_unit)
    return (points_per_side(float(np.linalg.norm(grid.u)), spacing),
            points_per_side(float(np.linalg.norm(grid.v)), spacing))


@dataclass(frozen=True)
class GridLayout:
    """Where a grid's points are.

    Attributes:
        points: (rows, columns, 3) float64, row j column i at
            origin + (i + 1/2)/columns u + (j + 1/2)/rows v.
        normal: (3,) float64 unit, the way every point faces.
        spacing: the largest spacing allowed (scene units); cell: (2,) the cells' sides
            along u and v (each at most ``spacing``).
    """

    points: torch.Tensor
    normal: torch.Tensor
    spacing: float
    cell: tuple[float, float]

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, columns)"""
        return tuple(self.points.shape[:2])


def grid_layout(grid: Grid, metres_per_unit: float = 1.0) -> GridLayout:
    """The points of ``grid`` (ValueError past ``MAX_GRID_POINTS``)."""
    columns, rows = grid_counts(grid, metres_per_unit)
    if columns * rows > MAX_GRID_POINTS:
        raise ValueError(f"grid {grid.name} would have {columns * rows:,} points, more than {MAX_GRID_POINTS:,}")
    origin, u, v = (torch.tensor(x, dtype=torch.float64) for x in (grid.origin, grid.u, grid.v))
    a = (torch.arange(columns, dtype=torch.float64) + 0.5) / columns
    b = (torch.arange(rows, dtype=torch.float64) + 0.5) / rows
    points = origin + b[:, None, None] * v + a[None, :, None] * u
    normal = torch.tensor(grid.normal, dtype=torch.float64)
    normal = normal / normal.abs().max()
    return GridLayout(points, normal / normal.norm(), grid_spacing(grid, metres_per_unit),
                      (float(u.norm()) / columns, float(v.norm()) / rows))


def grid_statistics(values) -> dict[str, float | None]:
    """EN 12464-1's figures of a grid's values (equal cells, so plain means): ``Em`` the mean,
    ``Emin``, ``Emax``, ``U0`` = Emin / Em (uniformity) and ``Emin_Emax`` = Emin / Emax;
    a ratio whose divisor is 0 is None."""
    values = torch.as_tensor(values, dtype=torch.float64).reshape(-1)
    if not len(values):
        raise ValueError("a grid has at least one point")
    mean, low, high = float(values.mean()), float(values.min()), float(values.max())
    return {"Em": mean, "Emin": low, "Emax": high, "U0": low / mean if mean > 0 else None,
            "Emin_Emax": low / high if high > 0 else None}
