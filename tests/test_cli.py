"""End to end: the command line on a small scene, and on bad input."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from hemirad.cli import main

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def solved(tmp_path_factory):
    out = tmp_path_factory.mktemp("small_room")
    run = subprocess.run([sys.executable, "-m", "hemirad", str(DATA / "small_room.yaml"), "-o", str(out)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    return out, run


def test_cli_writes_a_nonconstant_image(solved):
    out, _ = solved
    image = np.asarray(Image.open(out / "image.png"))
    assert image.shape == (72, 96, 3) and image.dtype == np.uint8
    assert image.std() > 5  # lit walls, a lamp and shadows, not a flat field
    assert image.max() == 255  # the lamp is in view


def test_cli_writes_a_ply_with_one_colour_per_vertex(solved):
    out, _ = solved
    mesh = trimesh.load(out / "mesh.ply", process=False)
    stats = json.loads((out / "stats.json").read_text())
    assert len(mesh.faces) == stats["elements"]
    assert mesh.visual.kind == "vertex"
    assert mesh.visual.vertex_colors.shape == (len(mesh.vertices), 4)
    assert len(np.unique(mesh.visual.vertex_colors[:, :3], axis=0)) > 10


def test_cli_writes_stats_and_reports_progress(solved):
    out, run = solved
    stats = json.loads((out / "stats.json").read_text())
    assert stats["shots"] == 40 and 0 < stats["unshot_fraction"] < 1
    assert set(stats["seconds"]["solve_phases"]) == {"raster", "readback", "form_factors", "gradient", "refine", "update"}
    emitted, absorbed, escaped, unshot = (np.array(stats[k]) for k in
                                          ("emitted_power", "absorbed_power", "escaped_power", "unshot_power"))
    # A closed room: what was emitted is absorbed, still unshot, or fell on a back face.
    assert absorbed + escaped + unshot == pytest.approx(emitted, rel=1e-9)
    assert stats["unshot_fraction"] >= abs(unshot.sum()) / emitted.sum() * (1 - 1e-12)  # the magnitude
    assert stats["patches"] > 0 and stats["hemicubes_rendered"] > 0
    assert "40/40" in run.stderr and "unshot=" in run.stderr and "elements=" in run.stderr


def test_quiet_mode_prints_nothing(tmp_path):
    run = subprocess.run([sys.executable, "-m", "hemirad", str(DATA / "small_room.yaml"), "-o", str(tmp_path),
                          "--shots", "3", "-q"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0 and run.stdout == "" and run.stderr == ""


def test_a_solve_that_outgrows_cache_mb_says_so_and_which_option_keeps_its_sweeps(tmp_path, capsys):
    assert main([str(DATA / "small_room.yaml"), "-o", str(tmp_path), "--cache-mb", "0.01", "--error-samples", "0", "--shots", "100000",
                 "--unshot-fraction", "0.01"]) == 0
    err = capsys.readouterr().err
    assert "outgrew solver.cache_mb" in err and "--cache-mb" in err and "Traceback" not in err
    stats = json.loads((tmp_path / "stats.json").read_text())
    assert stats["unshot_fraction"] < 0.01


def one_paragraph_error(capsys, argv):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("hemirad: error: ") and "Traceback" not in err
    assert "\n\n" not in err
    return err


@pytest.mark.parametrize("good, bad, key", [
    ("white: {reflectance: 0.7}", "white: {reflectance: 0.7", "line"),
    ("white: {reflectance: 0.7}", "white: {reflectence: 0.7}", "materials.white.reflectence"),
    ("white: {reflectance: 0.7}", "white: {reflectance: 1.5}", "materials.white.reflectance"),
    ("material: red", "material: blue", "objects[2].material"),
])
def test_malformed_scene_gives_exit_code_2_and_one_paragraph(tmp_path, capsys, good, bad, key):
    text = (DATA / "small_room.yaml").read_text()
    assert good in text
    scene = tmp_path / "bad.yaml"
    scene.write_text(text.replace(good, bad))
    (tmp_path / "tetra.obj").write_bytes((DATA / "tetra.obj").read_bytes())
    err = one_paragraph_error(capsys, [str(scene), "-o", str(tmp_path / "out")])
    assert "bad.yaml" in err and key in err


def test_malformed_scene_through_the_real_command(tmp_path):
    scene = tmp_path / "bad.yaml"
    scene.write_text("objects: 3\n")
    run = subprocess.run([sys.executable, "-m", "hemirad", str(scene)], capture_output=True, text=True,
                         timeout=300, cwd=tmp_path)
    assert run.returncode == 2
    assert "Traceback" not in run.stderr and "bad.yaml" in run.stderr
    assert not list(tmp_path.glob("*_out"))  # nothing half-written


def test_missing_scene_and_unwritable_output(tmp_path, capsys):
    err = one_paragraph_error(capsys, [str(tmp_path / "nowhere.yaml")])
    assert "nowhere.yaml" in err
    blocker = tmp_path / "file"
    blocker.write_text("")
    err = one_paragraph_error(capsys, [str(DATA / "small_room.yaml"), "-o", str(blocker / "out")])
    assert "output folder" in err


def test_bad_option_gives_exit_code_2(capsys):
    with pytest.raises(SystemExit) as exit_:
        main([str(DATA / "small_room.yaml"), "--resolution", "7"])
    assert exit_.value.code == 2
    assert "even integer" in capsys.readouterr().err


def test_cli_refines_and_writes_the_mesh_view(tmp_path, capsys):
    assert main([str(DATA / "small_room.yaml"), "-o", str(tmp_path), "-q", "--shots", "10",
                 "--refine", "pattern2", "--criterion", "gradient", "--threshold", "1e-3", "--max-depth", "2"]) == 0
    stats = json.loads((tmp_path / "stats.json").read_text())
    assert stats["refine"]["pattern"] == "pattern2" and stats["refine"]["splits"] > 0
    assert len(stats["elements_per_level"]) == 3 and sum(stats["elements_per_level"]) == stats["elements"]
    assert stats["elements"] > stats["initial_elements"]
    view = np.asarray(Image.open(tmp_path / "mesh.png"))
    assert view.ndim == 3 and view.std() > 5
    mesh = trimesh.load(tmp_path / "mesh.ply", process=False)
    assert len(mesh.faces) == stats["elements"]


def test_refine_block_in_the_scene_file_is_checked(tmp_path, capsys):
    text = (DATA / "small_room.yaml").read_text() + "\nrefine:\n  pattern: patern2\n"
    (tmp_path / "tetra.obj").write_bytes((DATA / "tetra.obj").read_bytes())
    scene = tmp_path / "bad.yaml"
    scene.write_text(text)
    err = one_paragraph_error(capsys, [str(scene), "-o", str(tmp_path / "out")])
    assert "refine.pattern" in err and "pattern2" in err
