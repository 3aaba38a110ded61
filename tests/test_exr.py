"""The HDR output: image.exr holds the camera view's linear radiance B / pi as 32-bit floats,
written atomically; a run writes it beside the false-colour luminance.png."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
from matplotlib import colormaps
from PIL import Image

import hemirad
from hemirad.cli import main
from hemirad.core.colour import LUMENS_PER_WATT
from hemirad.core.errors import HemiradInputError
from hemirad.output import display
from hemirad.output.export import read_exr, write_exr
from hemirad.output.falsecolour import COLOUR_MAP, luminance_values
from hemirad.output.render import render_view

DATA = Path(__file__).parent / "data"
LAMP_EMISSION = 20.0  # small_room.yaml's lamp: emission 20, reflectance 0


def test_exr_round_trip_keeps_every_float(tmp_path):
    rng = np.random.default_rng(7)
    image = (rng.random((5, 7, 3)) * 10.0 ** rng.integers(-6, 7, (5, 7, 3))).astype(np.float32)
    image[0, 0] = [3e38, 1e-38, 0.0]  # beyond what half floats or 8 bits hold
    path = tmp_path / "image.exr"
    write_exr(path, image)
    back, types = read_exr(path)
    assert back.dtype == np.float32 and np.array_equal(back, image)  # first row at the top, no curve
    assert types == {"R": OpenEXR.FLOAT, "G": OpenEXR.FLOAT, "B": OpenEXR.FLOAT}
    assert OpenEXR.isOpenExrFile(str(path))
    assert not list(tmp_path.glob(".*.tmp"))  # the temporary file was moved into place


def test_exr_that_cannot_be_written_is_an_input_error_and_keeps_the_old_file(tmp_path, monkeypatch):
    path = tmp_path / "image.exr"
    write_exr(path, np.ones((2, 2, 3), np.float32))
    before = path.read_bytes()

    def fail(self, name):
        Path(name).write_bytes(b"half")  # a write that fails part way
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(OpenEXR.File, "write", fail)
    with pytest.raises(HemiradInputError, match="image.exr: No space left on device"):
        write_exr(path, np.zeros((2, 2, 3), np.float32))
    assert path.read_bytes() == before and not list(tmp_path.glob(".*.tmp"))
    with pytest.raises(ValueError):
        write_exr(tmp_path / "flat.exr", np.zeros((2, 2), np.float32))


@pytest.fixture(scope="module")
def solved(tmp_path_factory):
    scene = hemirad.load_scene(DATA / "small_room.yaml")
    scene.solver = dataclasses.replace(scene.solver, max_shots=10)
    result = hemirad.solve(scene)
    return result, result.write(tmp_path_factory.mktemp("out"))


def test_written_exr_is_the_linear_view_over_pi(solved):
    result, paths = solved
    assert paths["HDR image"].name == "image.exr"
    back, types = read_exr(paths["HDR image"])
    assert set(types.values()) == {OpenEXR.FLOAT}
    camera = result.scene.camera
    shading = result.shading()
    linear = render_view(result.mesh, shading.values, camera, triangles=shading.triangles, positions=shading.positions)
    assert back.shape == (camera.height, camera.width, 3)
    assert np.allclose(back, linear / math.pi, rtol=1e-6, atol=0)
    # the lamp reflects nothing: where the camera sees it whole, its radiance is E / pi exactly
    lamp = np.isclose(back, LAMP_EMISSION / math.pi, rtol=1e-6).all(axis=2)
    assert 20 < lamp.sum() < back.shape[0] * back.shape[1] / 4
    assert back.max() == pytest.approx(LAMP_EMISSION / math.pi, rel=1e-6)  # no exposure, no clipping
    # the walls: far below the lamp, not black
    assert 0.01 < np.median(back[~lamp]) < LAMP_EMISSION / math.pi / 4


def test_the_tone_mapped_image_is_the_same_view(solved):
    result, paths = solved
    back, _ = read_exr(paths["HDR image"])
    png = np.asarray(Image.open(paths["image"])).astype(int)
    # the same pixels, up to the rounding of dividing by pi in 32 bits
    assert np.abs(png - display.to_srgb8(back * math.pi, result.exposure())).max() <= 1


def test_luminance_of_the_view_is_683_b_over_pi(solved):
    result, _ = solved
    coverage = result.coverage_image()
    assert np.allclose(coverage, 1.0)  # a closed room: every pixel sees a surface
    lum = luminance_values(result.linear_image(), coverage, LUMENS_PER_WATT)
    assert np.nanmax(lum) == pytest.approx(683.0 * LAMP_EMISSION / math.pi, rel=1e-6)  # the lamp, 4348 cd/m^2


def test_cli_writes_the_exr_and_the_luminance_picture(tmp_path, capsys):
    assert main([str(DATA / "small_room.yaml"), "-o", str(tmp_path), "-q", "--shots", "3"]) == 0
    back, types = read_exr(tmp_path / "image.exr")
    assert back.shape == (72, 96, 3) and set(types.values()) == {OpenEXR.FLOAT}
    assert back.max() == pytest.approx(LAMP_EMISSION / math.pi, rel=1e-6)
    picture = np.asarray(Image.open(tmp_path / "luminance.png").convert("RGB"))
    assert picture.ndim == 3 and picture.shape[1] > 96  # a picture with its colour bar, not the bare view
    top = np.rint(255 * np.asarray(colormaps[COLOUR_MAP](1.0)[:3]))
    # the lamp, the brightest in view, takes the top of the scale over a patch of the picture
    assert (np.abs(picture.astype(int) - top).max(axis=2) <= 1).sum() > 500
