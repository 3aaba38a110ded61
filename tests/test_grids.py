"""Calculation grids: EN 12464-1's spacing, where the points lie, statistics computed by
hand, the scene keys, and the grid files and table of a run."""
import csv
import json
import math

import numpy as np
from pathlib import Path

import pytest
import torch
import yaml

from hemirad.cli import main
from hemirad.core.errors import SceneError
from hemirad.lighting.grids import (grid_counts, grid_layout, grid_statistics, points_per_side,
                                    standard_spacing)
from hemirad.scene.loader import parse_scene
from hemirad.scene.model import Grid

SMALL_ROOM = Path(__file__).parent / "data" / "small_room.yaml"


# ----------------------------------------------------------------------------------------
# spacing and points


@pytest.mark.parametrize("side, spacing", [
    (1.0, 0.2),                              # 0.2 x 5^0
    (10.0, 1.0),                             # 0.2 x 5^1
    (100.0, 5.0),                            # 0.2 x 5^2
    (50.0, 0.2 * 5 ** 1.6989700043360187),   # 3.08 m (2.64 m is d = 40)
    (40.0, 2.6352503200506234),
    (1000.0, 10.0),                          # 25 m by the formula, capped at 10
    (269.0, 0.2 * 5 ** math.log10(269.0)),   # just under the cap: 9.99 m
])
def test_en12464_spacing(side, spacing):
    assert standard_spacing(side) == pytest.approx(spacing, rel=1e-12)


def test_points_per_side_is_the_fewest_that_keep_cells_within_the_spacing():
    assert points_per_side(1.0, 0.2) == 5          # 1 / 5 = 0.2 exactly: no sixth point
    assert points_per_side(1.0, 0.19999) == 6
    assert points_per_side(0.9, 0.3) == 3          # 0.9 / 0.3 = 3.0000000000000004 in floats
    assert points_per_side(0.1, 0.2) == 1
    assert points_per_side(1.6, standard_spacing(1.6)) == 6  # p = 0.278 m: 1.6 / 0.278 = 5.76


def test_a_work_plane_grid_puts_its_points_at_cell_centres():
    """A 2 x 1 m desk at 0.75 m: d = 2 m, p = 0.2 x 5^0.301 = 0.325 m, so 7 columns
    (2 / 7 = 0.286 m) and 4 rows (1 / 4 = 0.25 m), half a cell in from the border."""
    scene = parse_scene(yaml.safe_load(SCENE_WITH("grids: [{name: desk, work_plane: {height: 0.75, min: [1, 2], "
                                                  "max: [3, 3]}}]")), folder=SMALL_ROOM.parent)
    grid = scene.grids[0]
    assert grid.normal == (0.0, 1.0, 0.0)
    layout = grid_layout(grid, scene.metres_per_unit)
    assert layout.shape == (4, 7) and layout.spacing == pytest.approx(0.2 * 5 ** math.log10(2.0))
    assert layout.cell == pytest.approx((2 / 7, 0.25))
    x, y, z = layout.points[..., 0], layout.points[..., 1], layout.points[..., 2]
    assert torch.equal(y, torch.full((4, 7), 0.75, dtype=torch.float64))
    torch.testing.assert_close(x[0], 1 + (torch.arange(7, dtype=torch.float64) + 0.5) * 2 / 7)
    torch.testing.assert_close(z[:, 0], 2 + (torch.arange(4, dtype=torch.float64) + 0.5) * 0.25)


def test_the_spacing_is_in_metres_whatever_the_scene_unit():
    """The same 5 x 3 m area in metres and in centimetres: the same points, scaled. Its
    centimetres read as metres would make a 500 x 300 m hall: p capped at 10 m, 50 x 30 points."""
    grid_m = Grid("a", (0, 0, 0), (5, 0, 0), (0, 0, 3), (0, 1, 0))
    grid_cm = Grid("a", (0, 0, 0), (500, 0, 0), (0, 0, 300), (0, 1, 0))
    assert grid_counts(grid_m, 1.0) == grid_counts(grid_cm, 0.01) == (9, 5)  # p = 0.2 x 5^0.699 = 0.617 m
    torch.testing.assert_close(grid_layout(grid_cm, 0.01).points, 100 * grid_layout(grid_m, 1.0).points)
    assert grid_counts(grid_cm, 1.0) == (50, 30)


def test_a_grid_with_its_own_spacing_and_a_tilted_rectangle():
    """A wall grid from a corner and two edges: u x v is its default normal; with spacing 0.5
    on a 2 x 1.5 rectangle, 4 x 3 points."""
    grid = Grid("wall", (0.0, 0.0, 2.0), (2.0, 0.0, 0.0), (0.0, 1.5, 0.0), (0.0, 0.0, 1.0), spacing=0.5)
    layout = grid_layout(grid)
    assert layout.shape == (3, 4)
    torch.testing.assert_close(layout.points[2, 3], torch.tensor([1.75, 1.25, 2.0], dtype=torch.float64))


def test_grid_statistics_by_hand():
    stats = grid_statistics(torch.tensor([[100.0, 200.0], [300.0, 400.0]]))
    assert stats == {"Em": 250.0, "Emin": 100.0, "Emax": 400.0, "U0": 0.4, "Emin_Emax": 0.25}
    stats = grid_statistics([0.0, 0.0, 30.0])
    assert stats["Em"] == 10.0 and stats["U0"] == 0.0 and stats["Emin_Emax"] == 0.0
    assert grid_statistics([0.0, 0.0]) == {"Em": 0.0, "Emin": 0.0, "Emax": 0.0, "U0": None, "Emin_Emax": None}


# ----------------------------------------------------------------------------------------
# scene keys

BASE = SMALL_ROOM.read_text()


def SCENE_WITH(extra: str) -> str:
    return BASE + "\n" + extra + "\n"


def test_a_rectangle_grid_defaults_its_normal_to_u_cross_v():
    scene = parse_scene(yaml.safe_load(SCENE_WITH(
        "grids: [{origin: [0, 0.5, 2], u: [0, 1, 0], v: [2, 0, 0]}]")), folder=SMALL_ROOM.parent)
    assert scene.grids[0].name == "grid0" and scene.grids[0].normal == (0.0, 0.0, -1.0)


@pytest.mark.parametrize("grids, key, says", [
    ("[{name: a, work_plane: {height: 1, min: [0, 0], max: [1, 1]}, normal: [0, 0, 0]}]", "grids[0].normal",
     "non-zero"),
    ("[{name: a, origin: [0, 0, 0], u: [1, 0, 0], v: [1, 1, 0]}]", "grids[0].v", "perpendicular to u"),
    ("[{name: a, origin: [0, 0, 0], u: [0, 0, 0], v: [0, 1, 0]}]", "grids[0].u", "non-zero"),
    ("[{name: a, origin: [0, 0, 0], u: [1, 0, 0]}]", "grids[0].v", "The key is missing"),
    ("[{name: a, work_plane: {height: 1, min: [0, 0], max: [1, 1]}, origin: [0, 0, 0]}]", "grids[0].origin",
     "not both"),
    ("[{name: a, work_plane: {height: 1, min: [0, 2], max: [1, 1]}}]", "grids[0].work_plane.max", "On axis z"),
    ("[{name: a, work_plane: {height: 1, min: [0, 0, 0], max: [1, 1]}}]", "grids[0].work_plane.min", "[x, z]"),
    ("[{name: a/b, work_plane: {height: 1, min: [0, 0], max: [1, 1]}}]", "grids[0].name", "grid_<name>.csv"),
    ("[{name: a, work_plane: {height: 1, min: [0, 0], max: [1, 1]}, spacing: 0}]", "grids[0].spacing", "> 0"),
    ("[{name: a, work_plane: {height: 1, min: [0, 0], max: [1, 1]}}, "
     "{name: a, work_plane: {height: 1, min: [0, 0], max: [1, 1]}}]", "grids[1].name", "no other grid"),
    ("[{name: a, work_plane: {hieght: 1, min: [0, 0], max: [1, 1]}}]", "grids[0].work_plane.hieght",
     "Did you mean 'height'?"),
    ("{a: 1}", "grids", "a list of grids"),
])
def test_bad_grid_keys_name_the_key(grids, key, says):
    with pytest.raises(SceneError) as raised:
        parse_scene(yaml.safe_load(SCENE_WITH(f"grids: {grids}")), file="room.yaml", folder=SMALL_ROOM.parent)
    assert raised.value.key == key and says in str(raised.value)


def one_paragraph_error(capsys, argv) -> str:
    code = main(argv)
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert err.startswith("hemirad: error: ") and "\n" not in err and "Traceback" not in err
    return err


def scene_file(tmp_path, extra: str) -> Path:
    path = tmp_path / "room.yaml"
    path.write_text(SCENE_WITH(extra))
    (tmp_path / "tetra.obj").write_bytes((SMALL_ROOM.parent / "tetra.obj").read_bytes())
    return path


@pytest.mark.parametrize("grids, key, says", [
    # above the room, facing up: every point sees nothing at all
    ("[{name: sky, work_plane: {height: 5, min: [0, 0], max: [2, 2]}}]", "grids[0]", "No point of grid 'sky'"),
    # in the room but facing away from it, beside it: nothing either
    ("[{name: out, origin: [3, 0, 0], u: [0, 0, 2], v: [0, 1.5, 0], normal: [1, 0, 0]}]", "grids[0]",
     "sees any surface"),
    ("[{name: zero, work_plane: {height: 1, min: [0, 0], max: [1, 1]}, normal: [0, 0, 0]}]", "grids[0].normal",
     "non-zero direction"),
    ("[{name: dense, work_plane: {height: 1, min: [0, 0], max: [2, 2]}, spacing: 0.001}]", "grids[0].spacing",
     "at most 10,000 points"),
])
def test_a_bad_grid_stops_the_command_with_the_key_named(tmp_path, capsys, grids, key, says):
    path = scene_file(tmp_path, f"grids: {grids}")
    err = one_paragraph_error(capsys, [str(path), "-o", str(tmp_path / "out")])
    assert f"room.yaml: {key}: " in err and says in err
    assert not (tmp_path / "out" / "stats.json").exists()


# ----------------------------------------------------------------------------------------
# a run


def test_a_run_writes_the_grid_files_stats_and_table(tmp_path, capsys):
    """The floor (2 x 2 m: 7 x 7 points) and a wall grid (spacing 0.5: 4 x 3): each file
    holds its points in order, stats.json's figures are those of the file's lux column, and
    the printed table shows them. The floor grid has points inside the box standing on it:
    they see only its insides (illuminance 0), and the run warns of them."""
    path = scene_file(tmp_path, "grids:\n"
                      "  - {name: floor, work_plane: {height: 0.0, min: [0, 0], max: [2, 2]}}\n"
                      "  - {name: wall, origin: [0, 0, 2], u: [2, 0, 0], v: [0, 1.5, 0], normal: [0, 0, -1],"
                      " spacing: 0.5}")
    out = tmp_path / "out"
    assert main([str(path), "-o", str(out)]) == 0
    err = capsys.readouterr().err
    stats = json.loads((out / "stats.json").read_text())
    for name, (rows, columns) in {"floor": (7, 7), "wall": (3, 4)}.items():
        with open(out / f"grid_{name}.csv", newline="") as f:
            table = list(csv.DictReader(f))
        assert len(table) == rows * columns
        assert [(int(r["row"]), int(r["column"])) for r in table] == [(j, i) for j in range(rows) for i in range(columns)]
        lux = [float(r["lux"]) for r in table]
        figures = stats["grids"][name]
        assert (figures["rows"], figures["columns"], figures["points"]) == (rows, columns, rows * columns)
        assert figures["Em"] == pytest.approx(sum(lux) / len(lux), rel=1e-12)
        assert (figures["Emin"], figures["Emax"]) == (min(lux), max(lux))
        assert figures["U0"] == pytest.approx(min(lux) / figures["Em"], rel=1e-12)
        line = next(line for line in err.splitlines() if line.strip().startswith(name + " "))
        assert f"{columns}x{rows}" in line and f"{figures['Em']:.4g}" in line
    wall = list(csv.DictReader(open(out / "grid_wall.csv", newline="")))
    assert [float(wall[0][k]) for k in ("x", "y", "z", "nz")] == [0.25, 0.25, 2.0, -1.0]
    # the box stands on [0.3, 0.7]^2 of the floor: the point (3/7, 0, 3/7) is inside it
    floor = {(int(r["row"]), int(r["column"])): float(r["lux"]) for r in
             csv.DictReader(open(out / "grid_floor.csv", newline=""))}
    assert floor[(1, 1)] == 0 and min(v for k, v in floor.items() if k != (1, 1)) > 0
    assert stats["grids"]["floor"]["points_seeing_nothing"] == 1 and "1 of the 49 points" in err
    # and each grid's false-colour picture
    from PIL import Image
    for name in ("floor", "wall"):
        picture = np.asarray(Image.open(out / f"grid_{name}.png").convert("RGB"))
        assert picture.shape[0] > 100 and picture.shape[1] > 100


def test_a_grid_picture_is_drawn_in_scene_coordinates_where_its_edges_run_along_axes():
    from hemirad.output.falsecolour import grid_extent

    # a work plane: u along x, v along z
    assert grid_extent([1.0, 0.75, 2.0], [3.0, 0, 0], [0, 0, 1.5]) == ((1.0, 4.0, 2.0, 3.5), "x", "z")
    # a slanted rectangle: distances along its edges
    extent, xlabel, ylabel = grid_extent([0, 0, 0], [3.0, 4.0, 0], [0, 0, 2.0])
    assert extent == (0.0, 5.0, 0.0, 2.0) and (xlabel, ylabel) == ("along u", "z")
