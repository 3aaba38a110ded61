"""Hostile and unusual input, by class: nothing crashes, nothing silently wrong is written,
no output is left half-written.

- every broken scene in ``bad_inputs/`` is refused in bounded time and memory;
- non-finite results are never written; outputs are written atomically, and a killed
  run's temporary files are removed;
- what can be checked before the solve is (an output file that is a folder);
- a checkpoint's content is checked after unpickling;
- legal input the formats allow is accepted (YAML merge keys, a Latin-1 byte in an OBJ);
- messages name the command-line option when a value came from there;
- two runs cannot write one output folder; ``--resume`` never reports more shots than asked.
"""
from __future__ import annotations

import dataclasses
import errno
import fcntl
import json
import math
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import pytest
import torch

import hemirad
from hemirad import checkpoint as checkpoints
from hemirad.cli import main
from hemirad.core import atomic
from hemirad.core.errors import MAX_MESSAGE, HemiradInputError, SceneError, bounded_repr
from hemirad.scene.loader import load_scene

BAD = Path(__file__).parent / "bad_inputs"
EXPECTED = BAD / "expected.yaml"
OUTPUTS = ("image.png", "image.exr", "luminance.png", "mesh.png", "mesh.ply", "mesh.glb", "stats.json")


def refused(capsys, argv: list[str]) -> str:
    code = main(argv)
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert err.startswith("hemirad: error: ") and "\n" not in err and "Traceback" not in err, err
    return err


def scene_copy(tmp_path: Path, text: str | None = None) -> Path:
    """base.yaml (or ``text``) beside a copy of its mesh file."""
    (tmp_path / "tetra.obj").write_bytes((BAD / "tetra.obj").read_bytes())
    path = tmp_path / "scene.yaml"
    path.write_text((BAD / "base.yaml").read_text() if text is None else text)
    return path


# ----------------------------------------------------------------------------------------
# 1. resource exhaustion


def test_every_bad_scene_is_refused_in_bounded_time_and_memory(tmp_path):
    """Each corpus case in one process limited to 4 GiB of address space (torch and the GL
    driver need about 3); each must exit 2 with one line within 10 s."""
    script = textwrap.dedent(f"""
        import contextlib, io, json, resource, sys, time
        resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))
        import yaml
        from hemirad.cli import main
        names = sorted(yaml.safe_load(open({str(EXPECTED)!r})))
        out = {{}}
        for name in names:
            err = io.StringIO()
            start = time.perf_counter()
            with contextlib.redirect_stderr(err):
                code = main([{str(BAD)!r} + "/" + name + ".yaml", "-o", {str(tmp_path)!r} + "/" + name, "-q"])
            out[name] = [code, time.perf_counter() - start, err.getvalue()]
        print(json.dumps(out))
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    results = json.loads(done.stdout.strip().splitlines()[-1])
    assert len(results) >= 70
    for name, (code, seconds, err) in results.items():
        assert code == 2 and seconds < 10, (name, code, seconds, err)
        assert err.count("\n") == 1 and err.startswith("hemirad: error: ") and f"{name}.yaml" in err, (name, err)


def test_messages_show_values_at_a_bounded_length_and_cost():
    looped: list = []
    looped.append(looped)
    bomb: list = ["x"] * 10
    for _ in range(8):
        bomb = [bomb] * 10  # 10^9 leaves when expanded
    for value in (10**5000, "y" * 10**6, looped, bomb, {str(i): i for i in range(10**4)}):
        assert len(bounded_repr(value)) <= 80
    assert bounded_repr(10**5000) == "<an integer of about 5,000 digits>"
    message = str(SceneError("s.yaml", "k", "x", bomb, hint="a\nb\n" + "z" * 10**5))
    assert "\n" not in message and len(message) <= MAX_MESSAGE
    assert str(HemiradInputError("line one\nline two")) == "line one line two"


# ----------------------------------------------------------------------------------------
# 2. non-finite results; 4. half-written outputs


@pytest.fixture(scope="module")
def solved():
    scene = load_scene(BAD / "base.yaml")
    return hemirad.solve(scene)


@pytest.mark.parametrize("value", [math.nan, math.inf, 1e39])
def test_a_result_that_is_not_finite_is_never_written(solved, tmp_path, value):
    radiosity = solved.radiosity.clone()
    radiosity[3, 1] = value
    broken = dataclasses.replace(solved, radiosity=radiosity, stats=dict(solved.stats))
    with pytest.raises(HemiradInputError, match="not finite, or too large for a 32-bit float, at 1 of"):
        broken.write(tmp_path)
    assert not any((tmp_path / name).exists() for name in OUTPUTS)


def test_a_full_disk_leaves_the_previous_outputs_whole(solved, tmp_path, monkeypatch):
    solved.write(tmp_path)
    before = {name: (tmp_path / name).read_bytes() for name in OUTPUTS}
    real_fsync = atomic.os.fsync

    def full(fd):
        if Path(f"/proc/self/fd/{fd}").resolve().name.startswith(".mesh.ply."):
            raise OSError(errno.ENOSPC, "No space left on device")
        real_fsync(fd)

    monkeypatch.setattr(atomic.os, "fsync", full)
    with pytest.raises(HemiradInputError, match="mesh.ply: No space left on device"):
        solved.write(tmp_path)
    assert (tmp_path / "mesh.ply").read_bytes() == before["mesh.ply"]  # not truncated
    assert not list(tmp_path.glob(".*.tmp"))  # the failed write's temporary file is gone


def test_a_killed_runs_temporary_files_are_removed(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    stale = [out / ".mesh.ply.4242.tmp", out / ".checkpoint.pt.17.tmp"]
    for path in stale:
        path.write_bytes(b"half")
    keep = out / ".notes.1.tmp"  # not a name hemirad writes
    keep.write_bytes(b"mine")
    assert main([str(scene_copy(tmp_path)), "-o", str(out), "-q"]) == 0
    assert not any(p.exists() for p in stale) and keep.exists()
    assert all((out / name).stat().st_size > 0 for name in OUTPUTS)


# ----------------------------------------------------------------------------------------
# 3. errors found before the work


@pytest.mark.parametrize("name", ["mesh.ply", "stats.json", "checkpoint.pt"])
def test_an_output_file_that_is_a_folder_is_refused_before_solving(tmp_path, capsys, name):
    out = tmp_path / "out"
    (out / name).mkdir(parents=True)
    err = refused(capsys, [str(scene_copy(tmp_path)), "-o", str(out)])
    assert f"cannot write {out / name}: it exists and is not a regular file (a folder)" in err
    assert not any((out / n).is_file() for n in OUTPUTS)


# ----------------------------------------------------------------------------------------
# 5. checkpoint content


def _damage(payload: dict, how: str) -> None:
    solver = payload["solver"]
    if how == "list for the mesh":
        solver["mesh"] = [solver["mesh"]]
    elif how == "list for a tensor":
        solver["radiosity"] = solver["radiosity"].tolist()
    elif how == "negative level":
        solver["mesh"]["level"][0] = -1
    elif how == "triangle past the vertices":
        solver["mesh"]["triangles"][0, 0] = len(solver["mesh"]["vertices"])
    elif how == "NaN radiosity":
        solver["radiosity"][2, 0] = math.nan
    elif how == "zero emitted power":
        solver["emitted_power"] = torch.zeros(3, dtype=torch.float64)
    elif how == "reflectance of 1":
        solver["reflectance"][0] = 1.0
    elif how == "negative shots":
        solver["shots"] = -4
    elif how == "shots as text":
        solver["shots"] = "2"
    elif how == "run as a list":
        payload["run"]["seconds"] = [1.0, 2.0]


@pytest.mark.parametrize("how, says", [
    ("list for the mesh", "the mesh is missing"),
    ("list for a tensor", "radiosity is a list, not a tensor"),
    ("negative level", "mesh.level holds values outside [0, 16]"),
    ("triangle past the vertices", "mesh.triangles holds values outside [0, "),
    ("NaN radiosity", "radiosity holds NaN or infinite values"),
    ("zero emitted power", "emitted_power is zero"),
    ("reflectance of 1", "reflectance holds values outside [0, 1)"),
    ("negative shots", "shots is -4, not an integer >= 0"),
    ("shots as text", "shots is '2', not an integer >= 0"),
    ("run as a list", "run.seconds is not a mapping"),
])
def test_a_checkpoint_with_damaged_content_is_refused(tmp_path, capsys, how, says):
    scene = scene_copy(tmp_path)
    out = tmp_path / "out"
    assert main([str(scene), "-o", str(out), "-q", "--checkpoint-every", "1"]) == 0
    path = out / checkpoints.FILENAME
    payload = torch.load(path, weights_only=True)
    _damage(payload, how)
    torch.save(payload, path)
    err = refused(capsys, [str(scene), "-o", str(out), "-q", "--resume", "--shots", "3"])
    assert f"its content is damaged ({says}" in err


# ----------------------------------------------------------------------------------------
# 6. legal input accepted


def test_yaml_merge_keys_are_accepted_and_may_be_overridden(tmp_path):
    plain = load_scene(scene_copy(tmp_path))
    text = (BAD / "base.yaml").read_text()
    text = text.replace("white: {reflectance: 0.7}", "white: &white {reflectance: 0.7}").replace(
        "lamp: {reflectance: 0.0, emission: [20, 20, 20]}", "lamp: {<<: *white, reflectance: 0.0, emission: 20}")
    merged = load_scene(scene_copy(tmp_path, text))
    assert "<<: *white" in text and merged.materials == plain.materials


def test_a_key_repeated_beside_a_merge_key_is_still_refused(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text("base: &b {x: 1}\nother: {<<: *b, y: 1, y: 2}\n")
    with pytest.raises(SceneError, match="found the key 'y' twice"):
        load_scene(path)


def test_an_obj_with_a_latin1_byte_in_a_comment_is_read(tmp_path):
    scene = scene_copy(tmp_path)
    (tmp_path / "tetra.obj").write_bytes(b"# mod\xe8le d'essai\n" + (BAD / "tetra.obj").read_bytes())
    mesh = load_scene(scene).objects[2]
    assert mesh.contents.faces.shape == (4, 3)


# ----------------------------------------------------------------------------------------
# 7. messages


def test_a_command_line_value_is_blamed_on_the_option(tmp_path, capsys):
    err = refused(capsys, [str(scene_copy(tmp_path)), "-o", str(tmp_path / "out"), "--resolution", "100000"])
    assert "--resolution (given on the command line, for solver.resolution): expected at most" in err
    assert "scene.yaml: solver.resolution" not in err


def test_extreme_scenes_load_without_numpy_warnings(tmp_path):
    names = ["camera_far_away", "corner_far_away", "quad_tiny_bow_tie", "emission_largest_float", "quad_sliver"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for name in names:
            with pytest.raises(SceneError):
                load_scene(BAD / f"{name}.yaml")


# ----------------------------------------------------------------------------------------
# 8. concurrency


def test_a_second_run_writing_the_same_folder_is_refused(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    with open(out / ".hemirad.lock", "a") as held:  # as a run in another process holds it
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        err = refused(capsys, [str(scene_copy(tmp_path)), "-o", str(out)])
    assert "another hemirad run is writing to the output folder" in err
    assert not any((out / name).exists() for name in OUTPUTS)
    assert main([str(scene_copy(tmp_path)), "-o", str(out), "-q"]) == 0  # free once released


def test_resuming_with_fewer_shots_than_the_checkpoint_holds_is_refused(tmp_path, capsys):
    scene = scene_copy(tmp_path)
    out = tmp_path / "out"
    assert main([str(scene), "-o", str(out), "-q", "--checkpoint-every", "1", "--shots", "3"]) == 0
    err = refused(capsys, [str(scene), "-o", str(out), "-q", "--resume", "--shots", "2"])
    assert "--shots (given on the command line, for solver.max_shots): expected at least the 3 shots" in err
    assert json.loads((out / "stats.json").read_text())["shots"] == 3  # the earlier outputs are kept
    assert main([str(scene), "-o", str(out), "-q", "--resume", "--shots", "3"]) == 0  # equal is fine
