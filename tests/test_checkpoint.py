"""Checkpoints: a run killed and resumed gives the same result, bit for bit, as one never
interrupted; checkpoints are written atomically and refused for a different run."""
from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

import hemirad
from hemirad import checkpoint as checkpoints
from hemirad.cli import main
from hemirad.core.errors import HemiradInputError
from hemirad.output.export import read_ply_radiosity
from hemirad.transport import solver as solver_module
from hemirad.transport.solver import ProgressiveSolver

SMALL_ROOM = Path(__file__).parent / "data" / "small_room.yaml"
REFINE = {"pattern": "pattern2", "criterion": "gradient", "threshold": 1e-3, "max_depth": 2}


def scene(shots: int = 24, refine: bool = False, **solver):
    """The small room for ``shots`` shots; one patch a shot unless ``sweeps=True`` is passed,
    so that a run can stop at any shot."""
    s = hemirad.load_scene(SMALL_ROOM)  # hemicube resolution 32
    s.solver = dataclasses.replace(s.solver, **{"max_shots": shots, "unshot_fraction": 0.0, "sweeps": False, **solver})
    if refine:
        s.refine = dataclasses.replace(s.refine, **REFINE)
    return s


def stop_after(k: int):
    def progress(report):
        if report.shots == k:
            raise KeyboardInterrupt  # what Ctrl-C raises in the middle of a solve
    return progress


def assert_identical(a: hemirad.Result, b: hemirad.Result):
    for field in ("vertices", "triangles", "surface", "material", "level", "edge_parents"):
        assert torch.equal(getattr(a.mesh, field), getattr(b.mesh, field)), field
    assert a.mesh.surface_names == b.mesh.surface_names
    for field in ("radiosity", "unshot", "reflectance", "emission"):
        assert torch.equal(getattr(a, field), getattr(b, field)), field
    for key in ("shots", "elements", "unshot_fraction", "emitted_power", "absorbed_power", "escaped_power"):
        assert a.stats[key] == b.stats[key], key
    assert a.stats["refine"]["splits"] == b.stats["refine"]["splits"]


@pytest.fixture(scope="module")
def uninterrupted():
    """Reference runs, one per refinement setting, computed once."""
    return {refine: hemirad.solve(scene(refine=refine)) for refine in (False, True)}


@pytest.mark.parametrize("refine", [False, True], ids=["fixed mesh", "pattern2"])
def test_killed_and_resumed_run_equals_an_uninterrupted_one(refine, uninterrupted, tmp_path):
    path = tmp_path / checkpoints.FILENAME
    # killed at shot 10, between checkpoints: the resumed run redoes shots 9 and 10
    with pytest.raises(KeyboardInterrupt):
        hemirad.solve(scene(refine=refine), progress=stop_after(10), checkpoint=path, checkpoint_every=4)
    assert checkpoints.saved_shots(path) == 8
    assert [p.name for p in tmp_path.iterdir()] == [checkpoints.FILENAME]  # no temporary files left
    resumed = hemirad.solve(scene(refine=refine), checkpoint=path, checkpoint_every=4, resume=True)
    assert resumed.stats["resumed_from_shot"] == 8
    full = uninterrupted[refine]
    if refine:
        assert full.stats["refine"]["splits"] > 0 and full.stats["elements"] > full.stats["initial_elements"]
    assert_identical(resumed, full)
    assert checkpoints.saved_shots(path) == 24  # the end of the run is saved too


def test_a_run_of_sweeps_killed_and_resumed_equals_an_uninterrupted_one(tmp_path):
    def sweeping():
        return scene(shots=100000, sweeps=True, unshot_fraction=1e-3)

    reports = []
    full = hemirad.solve(sweeping(), progress=reports.append)
    assert len(reports) > 6 and full.stats["sweeps"] == len(reports)
    assert reports[2].shots - reports[1].shots > 10  # a sweep is many patches' shots
    path = tmp_path / checkpoints.FILENAME
    # saved after the 5th sweep (its shots pass the cadence, the 6th's do not), killed after
    # the 6th: the resumed run redoes the 6th
    every = reports[4].shots
    with pytest.raises(KeyboardInterrupt):
        hemirad.solve(sweeping(), progress=stop_after(reports[5].shots), checkpoint=path, checkpoint_every=every)
    assert checkpoints.saved_shots(path) == reports[4].shots
    resumed = hemirad.solve(sweeping(), checkpoint=path, checkpoint_every=every, resume=True)
    assert resumed.stats["resumed_from_shot"] == reports[4].shots
    assert_identical(resumed, full)


def test_a_resumed_run_is_finished_by_the_same_final_gathers(uninterrupted, tmp_path):
    """The gathers come after the checkpoint's last write, from the solution it holds: a
    resumed run makes them again, the same to the bit."""
    full = hemirad.solve(scene(final_gather="all"))
    assert not torch.equal(full.radiosity, uninterrupted[False].radiosity)  # the gathers changed it
    path = tmp_path / checkpoints.FILENAME
    with pytest.raises(KeyboardInterrupt):
        hemirad.solve(scene(final_gather="all"), progress=stop_after(10), checkpoint=path, checkpoint_every=4)
    resumed = hemirad.solve(scene(final_gather="all"), checkpoint=path, checkpoint_every=4, resume=True)
    assert_identical(resumed, full)
    assert resumed.stats["final_gather"] == full.stats["final_gather"]


def test_a_finished_run_continues_with_more_shots(uninterrupted, tmp_path):
    path = tmp_path / checkpoints.FILENAME
    hemirad.solve(scene(shots=15), checkpoint=path)  # no cadence: saved once, at the end
    assert checkpoints.saved_shots(path) == 15
    longer = hemirad.solve(scene(shots=24), checkpoint=path, resume=True)
    assert_identical(longer, uninterrupted[False])


def test_the_checkpoint_holds_the_whole_state_and_loads_without_pickled_code(tmp_path):
    path = tmp_path / checkpoints.FILENAME
    hemirad.solve(scene(shots=3, refine=True), checkpoint=path)
    payload = torch.load(path, weights_only=True)
    assert payload["format"] == checkpoints.FORMAT
    state = payload["solver"]
    assert set(state["mesh"]) == {"vertices", "triangles", "surface", "material", "surface_names", "level",
                                  "edge_parents"}
    assert {"radiosity", "unshot", "shots", "absorbed", "escaped", "reflectance", "emission", "refiner",
            "timings", "emitted_power"} <= set(state)
    assert state["refiner"]["splits"] > 0 and state["shots"] == 3
    assert payload["fingerprint"] == checkpoints.fingerprint(scene(refine=True))


def test_an_interrupted_write_leaves_the_previous_checkpoint(tmp_path, monkeypatch):
    path = tmp_path / checkpoints.FILENAME
    hemirad.solve(scene(shots=4), checkpoint=path)
    before = path.read_bytes()

    def torn_save(obj, f):
        f.write(b"PK\x03\x04 half a zip")
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", torn_save)
    with pytest.raises(KeyboardInterrupt):
        hemirad.solve(scene(shots=6), checkpoint=path, checkpoint_every=1)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == [checkpoints.FILENAME]


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    path = tmp_path_factory.mktemp("saved") / checkpoints.FILENAME
    hemirad.solve(scene(shots=2), checkpoint=path)
    return path


@pytest.mark.parametrize("change, says", [
    (lambda s: setattr(s, "solver", dataclasses.replace(s.solver, resolution=16)),
     "solver.resolution: 32 there, 16 here"),
    (lambda s: setattr(s, "refine", dataclasses.replace(s.refine, pattern="pattern1")),
     "refine.pattern: 'none' there, 'pattern1' here"),
    (lambda s: setattr(s.materials[0], "reflectance", (0.6, 0.7, 0.7)), "the scene's materials differ"),
    (lambda s: setattr(s.objects[0], "element_size", 0.4), "the scene's objects differ"),
])
def test_resuming_a_different_run_is_refused(saved, change, says):
    s = scene(shots=4)
    change(s)
    with pytest.raises(HemiradInputError, match="written for a different run") as error:
        hemirad.solve(s, checkpoint=saved, resume=True)
    assert says in str(error.value)


def test_the_answers_importance_is_part_of_the_fingerprint_only_where_it_ranks():
    # a run refined by the answer and resumed with the other importance would split its later
    # rounds otherwise than the run it continues
    refined = scene(shots=4)
    refined.refine = dataclasses.replace(refined.refine, pattern="pattern2", criterion="answer")
    other = copy.deepcopy(refined)
    other.refine = dataclasses.replace(other.refine, importance="surfaces")
    assert checkpoints.fingerprint(refined)["refine.importance"] == "camera"
    assert checkpoints.fingerprint(other)["refine.importance"] == "surfaces"
    plain = scene(shots=4)
    changed = copy.deepcopy(plain)
    changed.refine = dataclasses.replace(changed.refine, importance="surfaces")
    assert checkpoints.fingerprint(plain) == checkpoints.fingerprint(changed)


@pytest.mark.parametrize("module, constant, key, says", [
    (solver_module, "ARITHMETIC", "solver arithmetic",
     "written for a different run (solver arithmetic: {old} there, {new} here)"),
    (checkpoints, "FORMAT", "checkpoint format", "not a hemirad checkpoint of format {new} (found {old})"),
], ids=["arithmetic", "format"])
def test_a_checkpoint_of_another_arithmetic_or_format_is_refused(saved, monkeypatch, module, constant, key, says):
    # As code whose solves give other numbers, or that stores checkpoints otherwise, would see it.
    old = getattr(module, constant)
    assert checkpoints.fingerprint(scene())[key] == old
    monkeypatch.setattr(module, constant, old + 1)
    with pytest.raises(HemiradInputError) as error:
        hemirad.solve(scene(shots=4), checkpoint=saved, resume=True)
    assert says.format(old=old, new=old + 1) in str(error.value)


def test_the_fingerprint_does_not_hold_the_package_version(monkeypatch):
    before = checkpoints.fingerprint(scene())
    monkeypatch.setattr(hemirad, "__version__", "99.0.0")
    assert checkpoints.fingerprint(scene()) == before and "99.0.0" not in str(before)


def test_stopping_rules_and_display_may_change_on_resume(saved):
    s = scene(shots=3)
    s.camera.width = 40
    s.solver = dataclasses.replace(s.solver, unshot_fraction=1e-6, ambient=False)
    assert hemirad.solve(s, checkpoint=saved, resume=True).stats["shots"] == 3


def test_a_mesh_file_changed_since_the_checkpoint_is_refused(tmp_path):
    folder = tmp_path / "project"
    folder.mkdir()
    for name in ("small_room.yaml", "tetra.obj"):
        (folder / name).write_bytes((SMALL_ROOM.parent / name).read_bytes())
    path = tmp_path / checkpoints.FILENAME
    first = hemirad.load_scene(folder / "small_room.yaml")
    first.solver = dataclasses.replace(first.solver, max_shots=1)
    hemirad.solve(first, checkpoint=path)
    (folder / "tetra.obj").write_text((folder / "tetra.obj").read_text().replace("v 1.0 1.0 1.0", "v 1.0 1.1 1.0"))
    with pytest.raises(HemiradInputError, match="the scene's objects differ"):
        hemirad.solve(hemirad.load_scene(folder / "small_room.yaml"), checkpoint=path, resume=True)


@pytest.mark.parametrize("content, says", [
    (None, "there is no checkpoint"),
    (b"not a checkpoint", "not a readable hemirad checkpoint"),
    ("a dict", "not a hemirad checkpoint of format 1"),
])
def test_a_missing_or_foreign_checkpoint_is_refused(tmp_path, content, says):
    path = tmp_path / checkpoints.FILENAME
    if isinstance(content, bytes):
        path.write_bytes(content)
    elif content is not None:
        torch.save({"weights": torch.zeros(3)}, path)
    with pytest.raises(HemiradInputError, match=says):
        hemirad.solve(scene(shots=2), checkpoint=path, resume=True)


def test_a_checkpoint_whose_state_does_not_fit_is_refused(tmp_path):
    path = tmp_path / checkpoints.FILENAME
    hemirad.solve(scene(shots=2), checkpoint=path)
    payload = torch.load(path, weights_only=True)
    payload["solver"]["radiosity"] = payload["solver"]["radiosity"][:-1]  # one element short
    torch.save(payload, path)
    with pytest.raises(HemiradInputError, match=r"content is damaged \(radiosity is a \(\d+, 3\) torch.float64"):
        hemirad.solve(scene(shots=3), checkpoint=path, resume=True)


def test_solve_needs_a_path_to_checkpoint():
    with pytest.raises(ValueError):
        hemirad.solve(scene(shots=1), checkpoint_every=5)


# ---------------------------------------------------------------------------------------
# the command line


def interrupt_at(monkeypatch, k: int):
    """Make the solver raise KeyboardInterrupt in the middle of shot k (or of the sweep that
    would pass it), as Ctrl-C would."""
    shoot = ProgressiveSolver.shoot

    def shoot_until(self, limit=None):
        if self.state.shots + 1 >= k:
            raise KeyboardInterrupt
        return shoot(self, limit)

    monkeypatch.setattr(ProgressiveSolver, "shoot", shoot_until)


def test_ctrl_c_keeps_the_checkpoint_and_says_how_to_resume(tmp_path, monkeypatch, capsys):
    argv = [str(SMALL_ROOM), "-o", str(tmp_path / "out"), "-q", "--shots", "12", "--refine", "pattern2",
            "--criterion", "gradient", "--threshold", "1e-3", "--max-depth", "2", "--checkpoint-every", "5"]
    with monkeypatch.context() as m:
        interrupt_at(m, 8)
        assert main(argv) == 130
    err = capsys.readouterr().err.strip()
    assert "holds the run up to shot 5" in err and err.endswith(" ".join(argv[1:]) + " --resume")
    assert main(argv + ["--resume"]) == 0
    assert main(argv[:2] + [str(tmp_path / "direct")] + argv[3:]) == 0
    resumed, direct = (read_ply_radiosity(tmp_path / d / "mesh.ply") for d in ("out", "direct"))
    assert np.array_equal(resumed, direct)


def test_ctrl_c_without_checkpoints_says_nothing_was_saved(tmp_path, monkeypatch, capsys):
    interrupt_at(monkeypatch, 3)
    assert main([str(SMALL_ROOM), "-o", str(tmp_path), "-q"]) == 130
    assert "nothing was saved (--checkpoint-every N" in capsys.readouterr().err


def test_resume_without_a_checkpoint_is_an_input_error(tmp_path, capsys):
    assert main([str(SMALL_ROOM), "-o", str(tmp_path), "-q", "--resume"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("hemirad: error: cannot resume: there is no checkpoint") and "\n" not in err
