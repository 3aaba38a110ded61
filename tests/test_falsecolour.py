"""False-colour pictures: the colour of a pixel encodes the value there, iso-lines lie where
the field crosses their level, no-data is grey; a surface's map shows the irradiance
(B - E) / rho falling on it, and the camera's the luminance B / pi."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from matplotlib import colormaps
from PIL import Image

from hemirad.cli import main
from hemirad.core.colour import LUMENS_PER_WATT, REC709_LUMINANCE, luminance
from hemirad.geometry.mesh import Mesh
from hemirad.output import falsecolour
from hemirad.output.falsecolour import (element_irradiance, luminance_values, nice_levels, plane_figure,
                                        plane_picture, render, surface_values, vertex_values_with_gaps)
from hemirad.scene.meshing import grid_quad

DATA = Path(__file__).parent / "data"
LUT = np.rint(255 * colormaps[falsecolour.COLOUR_MAP](np.linspace(0, 1, 256))[:, :3]).astype(np.float64)


def lut_of(t: float) -> int:
    """The colour-map entry a normalised value t in [0, 1] takes (matplotlib's 256 bins)."""
    return int(min(math.floor(256 * t), 255))


def lut_index(pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For (..., 3) uint8 pixels: the index of the nearest colour-map entry (0..255) and the
    distance to it (0 for a pixel of the map's own colours)."""
    d = np.linalg.norm(pixels[..., None, :].astype(np.float64) - LUT, axis=-1)
    return d.argmin(axis=-1), d.min(axis=-1)


def to_pixel(fig, ax, x: float, y: float) -> tuple[int, int]:
    """(row, column) of a data point in the rendered picture (rows from the top)."""
    height = int(round(fig.figure.bbox.height))
    px, py = ax.transData.transform((x, y))
    return int(height - py), int(px)


# ----------------------------------------------------------------------------------------
# plane pictures


def test_nice_levels_are_round_numbers_inside_the_range():
    for lo, hi in [(0.0, 1000.0), (113.0, 487.0), (0.0031, 0.0047), (-20.0, 35.0), (1e4, 6e4)]:
        levels = nice_levels(lo, hi)
        assert 3 <= len(levels) <= 9 and np.all((levels > lo) & (levels < hi))
        steps = np.diff(levels)
        assert np.allclose(steps, steps[0])
        mantissa = steps[0] / 10 ** math.floor(math.log10(steps[0]))
        assert min(abs(mantissa - m) for m in (1, 2, 2.5, 5)) < 1e-9
        assert np.allclose(levels / steps[0], np.round(levels / steps[0]))  # multiples of the step
    assert len(nice_levels(5.0, 5.0)) == 0 and len(nice_levels(0.0, math.nan)) == 0


@pytest.fixture(scope="module")
def ramp():
    """A linear ramp v = 100 + 200 x over [0, 4] x [0, 2], 80 x 40 cells, a no-data block
    over x in [0.6, 0.9] (220 to 280: no level crosses it), y in [0.5, 1.0]."""
    nx, ny = 80, 40
    x = (np.arange(nx) + 0.5) * 4.0 / nx
    values = np.tile(100.0 + 200.0 * x, (ny, 1))
    values[10:20, 12:18] = np.nan
    fig = plane_figure(values, (0.0, 4.0, 0.0, 2.0), "lx", "ramp")
    return fig, render(fig)


def test_the_picture_is_the_figure_rendered(ramp):
    fig, pixels = ramp
    assert pixels.dtype == np.uint8 and pixels.ndim == 3 and pixels.shape[2] == 3
    nx_values = np.tile(100.0 + 200.0 * (np.arange(80) + 0.5) * 0.05, (40, 1))
    nx_values[10:20, 12:18] = np.nan
    assert np.array_equal(plane_picture(nx_values, (0.0, 4.0, 0.0, 2.0), "lx", "ramp"), pixels)


def test_map_colours_follow_the_ramp(ramp):
    fig, pixels = ramp
    norm = fig.axes.images[0].norm
    # along y = 1.5 (above the no-data block), pixel by pixel between the left and right edges
    r0, c0 = to_pixel(fig, fig.axes, 0.0, 1.5)
    _, c1 = to_pixel(fig, fig.axes, 4.0, 1.5)
    columns = np.arange(c0 + 2, c1 - 2)
    index, distance = lut_index(pixels[r0, columns])
    clean = distance < 3  # the map's own colours, not an iso-line or its label
    assert clean.mean() > 0.8
    def expected(shift: float) -> np.ndarray:
        """the colour index of the cell under the pixel's centre moved by ``shift`` pixels"""
        x = (columns + 0.5 + shift - c0) / (c1 - c0) * 4.0
        cell_x = (np.floor(x / 0.05) + 0.5) * 0.05
        return np.minimum(np.floor(256 * np.ma.getdata(norm(100.0 + 200.0 * cell_x))), 255)

    # a pixel within a pixel of a cell boundary may show either cell (1/80 of the range apart)
    low, high = expected(-1.0), expected(1.0)
    assert np.all((index[clean] >= low[clean] - 1) & (index[clean] <= high[clean] + 1))
    assert np.all(np.diff(index[clean]) >= 0)  # monotonic along the ramp
    assert index[clean][0] <= 4 and index[clean][-1] >= 251  # the whole map is used


def test_no_data_cells_are_neutral_grey(ramp):
    fig, pixels = ramp
    top, left = to_pixel(fig, fig.axes, 0.6, 1.0)
    bottom, right = to_pixel(fig, fig.axes, 0.9, 0.5)
    block = pixels[top + 3:bottom - 3, left + 3:right - 3].reshape(-1, 3).astype(int)
    assert len(block) > 50
    assert np.all(np.abs(block - 128) <= 1)
    assert lut_index(pixels[top - 6, left + 5])[1] < 3  # just above it, the map


def _line_share(pixels, fig, x: float, ys: np.ndarray, expected_colour) -> float:
    """Share of the rows at ``ys`` with a pixel within 2 columns of ``x`` far (> 60) from
    the map's colour there."""
    hits = []
    for y in ys:
        row, col = to_pixel(fig, fig.axes, x, y)
        near = pixels[row, col - 2:col + 3].astype(np.float64)
        hits.append(bool((np.linalg.norm(near - expected_colour, axis=1) > 60).any()))
    return float(np.mean(hits))


def test_iso_lines_lie_at_their_levels_and_only_there(ramp):
    fig, pixels = ramp
    norm = fig.axes.images[0].norm
    levels = nice_levels(100.0 + 200.0 * 0.025, 100.0 + 200.0 * 3.975)
    assert list(levels) == [200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0]
    ys = np.linspace(1.05, 1.95, 40)  # above the no-data block
    for level in levels:
        x = (level - 100.0) / 200.0
        colour = LUT[lut_of(float(norm(level)))]
        assert _line_share(pixels, fig, x, ys, colour) > 0.8, level  # a line (or its label) there
        x_between = x + 0.25  # halfway to the next level
        colour = LUT[lut_of(float(norm(level + 50.0)))]
        assert _line_share(pixels, fig, x_between, ys, colour) < 0.05, level
    # the colour bar carries the levels as ticks and the unit as its label
    assert list(fig.colorbar.get_ticks()) == list(levels) and fig.colorbar.ax.get_ylabel() == "lx"


def test_chosen_levels_draw_those_lines():
    values = np.tile(np.linspace(0.0, 10.0, 50), (20, 1))
    fig = plane_figure(values, (0.0, 10.0, 0.0, 4.0), "W/m^2", "chosen", levels=[2.5, 7.0])
    pixels = render(fig)
    norm = fig.axes.images[0].norm
    ys = np.linspace(0.5, 3.5, 30)
    for x in (2.5, 7.0):  # the ramp's value is x
        assert _line_share(pixels, fig, x, ys, LUT[lut_of(float(norm(x)))]) > 0.8
    assert _line_share(pixels, fig, 5.0, ys, LUT[lut_of(float(norm(5.0)))]) < 0.05


def test_the_colour_bar_runs_through_the_colour_map(ramp):
    fig, pixels = ramp
    bar = fig.colorbar.ax.get_window_extent()
    height = pixels.shape[0]
    column = int((bar.x0 + bar.x1) / 2)
    rows = np.arange(int(height - bar.y1) + 2, int(height - bar.y0) - 2)
    index, distance = lut_index(pixels[rows, column])
    clean = distance < 3  # not the level marks drawn across it
    assert clean.mean() > 0.9
    assert np.all(np.diff(index[clean]) <= 0)  # top row brightest
    assert index[clean][0] >= 250 and index[clean][-1] <= 5


def test_a_reversed_axis_runs_the_map_the_other_way():
    # a floor seen from above: z grows downwards; the value is z (row j at z = 2 - 0.1 (j + 0.5))
    values = np.tile((2.0 - 0.1 * (np.arange(20) + 0.5))[:, None], (1, 10))
    fig = plane_figure(values, (0.0, 1.0, 2.0, 0.0), "lx", "floor", levels=(), xlabel="x", ylabel="z")
    pixels = render(fig)
    top, col = to_pixel(fig, fig.axes, 0.5, 0.1)
    bottom, _ = to_pixel(fig, fig.axes, 0.5, 1.9)
    assert top < bottom
    assert lut_index(pixels[top, col])[0] < 20 and lut_index(pixels[bottom, col])[0] > 235


def test_flat_and_empty_fields_are_drawn():
    flat = plane_figure(np.full((5, 5), 300.0), (0, 1, 0, 1), "lx", "flat")
    assert len(flat.axes.collections) == 0  # no iso-line: nothing crosses a level
    render(flat)
    empty = plane_figure(np.full((6, 6), np.nan), (0, 1, 0, 1), "lx", "no data")
    pixels = render(empty)
    row, col = to_pixel(empty, empty.axes, 0.5, 0.5)
    assert np.all(np.abs(pixels[row - 20:row + 20, col - 20:col + 20].astype(int) - 128) <= 1)


# ----------------------------------------------------------------------------------------
# surfaces: the irradiance falling on them


def test_irradiance_is_radiosity_less_emission_over_reflectance():
    b = torch.tensor([[0.5, 0.3, 0.2], [20.0, 20.0, 20.0], [0.3, 0.2, 0.1]], dtype=torch.float64)
    e = torch.tensor([[0.1, 0.0, 0.0], [20.0, 20.0, 20.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    rho = torch.tensor([[0.5, 0.6, 0.4], [0.0, 0.0, 0.0], [0.6, 0.0, 0.25]], dtype=torch.float64)
    h = element_irradiance(b, e, rho)
    assert torch.allclose(h[0], torch.tensor([0.8, 0.5, 0.5], dtype=torch.float64), rtol=1e-15)
    assert torch.isnan(h[1]).all()  # a lamp that reflects nothing: no data
    assert h[2, 0] == pytest.approx(0.5) and torch.isnan(h[2, 1]) and h[2, 2] == pytest.approx(0.4)


def floor_mesh(size: float = 2.0, element: float = 0.25) -> Mesh:
    """A floor over [0, size] x [0, size] in x and z at y = 0, facing up, one surface."""
    corners = torch.tensor([[0, 0, 0], [0, 0, size], [size, 0, size], [size, 0, 0]], dtype=torch.float64)
    v, t = grid_quad(corners, element)
    c = v[t]
    if float(torch.linalg.cross(c[0, 1] - c[0, 0], c[0, 2] - c[0, 0])[1]) < 0:
        t = t[:, [0, 2, 1]]
    n = len(t)
    return Mesh(v, t, torch.zeros(n, dtype=torch.int64), torch.zeros(n, dtype=torch.int64), ["room.floor"])


def test_surface_values_interpolate_vertices_on_the_scene_axes():
    mesh = floor_mesh()
    x, z = mesh.vertices[:, 0], mesh.vertices[:, 2]
    seen = surface_values(mesh, 100.0 + 40.0 * x - 15.0 * z, 0, size=200)
    x0, x1, z0, z1 = seen.extent
    assert (x0, x1, z0, z1) == pytest.approx((0.0, 2.0, 2.0, 0.0)) and (seen.xlabel, seen.ylabel) == ("x", "z")
    assert seen.values.shape == (200, 200) and np.isfinite(seen.values).all()
    ny, nx = seen.values.shape
    px = x0 + (np.arange(nx) + 0.5) * (x1 - x0) / nx
    pz = z0 + (np.arange(ny) + 0.5) * (z1 - z0) / ny
    expected = 100.0 + 40.0 * px[None, :] - 15.0 * pz[:, None]  # linear: interpolation is exact
    assert np.allclose(seen.values, expected, rtol=1e-5)


def test_surface_map_of_a_uniformly_lit_floor_is_the_closed_form():
    mesh = floor_mesh()
    t = mesh.num_elements
    rho = torch.tensor([0.6, 0.5, 0.25], dtype=torch.float64).expand(t, 3)
    emission = torch.tensor([0.05, 0.05, 0.05], dtype=torch.float64).expand(t, 3)
    h = torch.tensor([0.5, 0.4, 0.4], dtype=torch.float64)
    b = emission + rho * h  # B = E + rho H
    element = luminance(element_irradiance(b, emission, rho)) * LUMENS_PER_WATT
    expected = LUMENS_PER_WATT * float(np.dot(REC709_LUMINANCE, [0.5, 0.4, 0.4]))  # 287.75 lx by hand
    assert expected == pytest.approx(683 * (0.2126 * 0.5 + 0.7152 * 0.4 + 0.0722 * 0.4))
    seen = surface_values(mesh, vertex_values_with_gaps(mesh, element), 0, size=64)
    assert np.allclose(seen.values, expected, rtol=1e-6)


def test_elements_without_reflectance_are_no_data():
    mesh = floor_mesh(element=0.5)
    centre_x = mesh.corners[:, :, 0].mean(dim=1)
    values = torch.where(centre_x < 1.0, 300.0, torch.nan)  # the half x > 1 reflects nothing
    vertex = vertex_values_with_gaps(mesh, values)
    on_left = mesh.vertices[:, 0] <= 1.0
    assert torch.all(vertex[on_left] == 300.0)  # shared vertices keep the known side's value
    assert torch.isnan(vertex[~on_left]).all()
    seen = surface_values(mesh, vertex, 0, size=100)
    assert np.allclose(seen.values[:, :48], 300.0) and np.isnan(seen.values[:, 52:]).all()


# ----------------------------------------------------------------------------------------
# the camera view


def test_luminance_is_radiosity_over_pi_times_683():
    linear = np.zeros((2, 3, 3))
    linear[0, 0] = [math.pi, math.pi, math.pi]  # B = pi: luminance 1 (x 683)
    linear[0, 1] = [1.0, 0.0, 0.0]
    linear[0, 2] = [0.5 * math.pi, 0.5 * math.pi, 0.5 * math.pi]  # half covered: the covered half is pi
    coverage = np.ones((2, 3))
    coverage[0, 2] = 0.5
    coverage[1, :] = [0.0, 0.2, 1.0]
    lum = luminance_values(linear, coverage, LUMENS_PER_WATT)
    assert lum[0, 0] == pytest.approx(683.0) and lum[0, 2] == pytest.approx(683.0)
    assert lum[0, 1] == pytest.approx(683.0 * 0.2126 / math.pi)
    assert np.isnan(lum[1, 0]) and np.isnan(lum[1, 1]) and lum[1, 2] == 0.0  # seen, and black


# ----------------------------------------------------------------------------------------
# the command


def test_cli_writes_the_surface_pictures(tmp_path, capsys):
    assert main([str(DATA / "small_room.yaml"), "-o", str(tmp_path), "-q", "--shots", "5",
                 "--falsecolour", "floor", "--falsecolour", "box.top", "--falsecolour", "lamp"]) == 0
    floor = np.asarray(Image.open(tmp_path / "falsecolour_floor.png").convert("RGB"))
    _, distance = lut_index(floor[::4, ::4])
    assert (distance < 3).mean() > 0.3  # mostly the map's colours
    lamp = np.asarray(Image.open(tmp_path / "falsecolour_lamp.png").convert("RGB")).astype(int)
    assert (np.abs(lamp - 128) <= 1).all(axis=2).mean() > 0.3  # the lamp reflects nothing: grey
    assert (tmp_path / "falsecolour_box.top.png").is_file()


def test_cli_refuses_an_unknown_surface_naming_close_ones(tmp_path, capsys):
    assert main([str(DATA / "small_room.yaml"), "-o", str(tmp_path / "out"), "--falsecolour", "room.flor"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("hemirad: error: --falsecolour (given on the command line, for falsecolour[0])")
    assert "No surface named 'room.flor'. The closest names: room.floor" in err and "\n" not in err
    assert not (tmp_path / "out" / "stats.json").exists()


def test_scene_key_falsecolour(tmp_path, capsys):
    (tmp_path / "tetra.obj").write_bytes((DATA / "tetra.obj").read_bytes())
    text = (DATA / "small_room.yaml").read_text()
    scene = tmp_path / "scene.yaml"
    scene.write_text(text + "\nfalsecolour: [room.floor, celing]\n")
    assert main([str(scene), "-o", str(tmp_path / "out"), "-q", "--shots", "2"]) == 2
    err = capsys.readouterr().err
    assert "scene.yaml: falsecolour[1]: expected the name of a surface" in err and "room.ceiling" in err
    scene.write_text(text + "\nfalsecolour: room.floor\n")
    assert main([str(scene), "-o", str(tmp_path / "out"), "-q"]) == 2
    assert "falsecolour: expected a list of surface names" in capsys.readouterr().err
