"""The paper-reproduction script, in its quick mode: every figure written, and the paper's
two qualitative results (pattern 2 keeps triangle shape, refinement follows shadows)."""
import importlib.util
import json
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parent.parent / "scripts" / "reproduce_figures.py"


@pytest.fixture(scope="module")
def figures(tmp_path_factory):
    out = tmp_path_factory.mktemp("figures")
    spec = importlib.util.spec_from_file_location("reproduce_figures", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.main(["--quick", "--out", str(out)]) == 0
    return out, json.loads((out / "summary.json").read_text())


def test_every_figure_file_is_written(figures):
    out, _ = figures
    for scene in ("office", "floating", "floating_coarse"):
        for run in "abc":
            for suffix in ("", "_mesh"):
                path = out / f"{scene}_{run}{suffix}.png"
                assert path.stat().st_size > 500, path
        assert (out / f"{scene}.png").stat().st_size > 1000
    for name in ("table1.md", "mesh_quality.md"):
        text = (out / name).read_text()
        assert "Fig. 6(c)" in text and "Fig. 7(b)" in text


def test_pattern_2_keeps_the_largest_angle_variance_below_pattern_1(figures):
    _, summary = figures
    runs = {(r["scene"], r["run"]): r for r in summary["runs"]}
    for scene in ("office", "floating", "floating_coarse"):
        b, c = runs[scene, "b"], runs[scene, "c"]
        assert b["elements"] > b["initial_elements"] and c["elements"] > c["initial_elements"]
        assert c["angle"]["variance"] < b["angle"]["variance"]


def test_refined_floors_are_denser_near_the_shadow_than_far_from_it(figures):
    _, summary = figures
    for run in summary["runs"]:
        shadow = run["shadow"]
        if run["pattern"] == "none":
            assert shadow["density_ratio"] == pytest.approx(1.0, abs=0.25)  # a uniform grid
        else:
            assert shadow["density_near_per_m2"] > 1.5 * shadow["density_far_per_m2"], run["figure"]
