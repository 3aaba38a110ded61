"""Every mistake a user can make in a scene file or on the command line: exit code 2 and one
paragraph naming the file, the key and what was expected; never a traceback.

The scene files are in ``bad_inputs/``, each ``base.yaml`` broken in one place, with what
the message must say in ``bad_inputs/expected.yaml``.
"""
from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from hemirad.cli import main

BAD = Path(__file__).parent / "bad_inputs"
DATA = Path(__file__).parent / "data"
EXPECTED = yaml.safe_load((BAD / "expected.yaml").read_text())


def one_paragraph_error(capsys, argv: list[str]) -> str:
    """Run the command; it must fail with code 2 and a single ``hemirad: error:`` line."""
    code = main(argv)
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert err.startswith("hemirad: error: "), err
    assert "Traceback" not in err and "\n" not in err, err
    return err


def test_every_bad_scene_has_an_expectation_and_the_corpus_is_large():
    files = {p.stem for p in BAD.glob("*.yaml")} - {"expected", "base"}
    assert files == set(EXPECTED)
    assert len(files) >= 30


def test_the_base_scene_solves(tmp_path, capsys):
    # so each bad file fails because of its own edit, not something they share
    assert main([str(BAD / "base.yaml"), "-o", str(tmp_path), "-q"]) == 0


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_bad_scene_is_refused_with_the_key_named(name, tmp_path, capsys):
    err = one_paragraph_error(capsys, [str(BAD / f"{name}.yaml"), "-o", str(tmp_path / "out")])
    expected = EXPECTED[name]
    assert f"{name}.yaml: {expected['key']}{': ' if expected['key'] else ''}" in err
    assert expected["says"] in err
    assert not (tmp_path / "out" / "stats.json").exists()


def test_a_folder_given_as_the_scene(tmp_path, capsys):
    folder = tmp_path / "scene.yaml"
    folder.mkdir()
    err = one_paragraph_error(capsys, [str(folder), "-o", str(tmp_path / "out")])
    assert "scene.yaml" in err and "not a regular file" in err


def test_a_misspelt_bundled_scene_name(capsys):
    err = one_paragraph_error(capsys, ["cornel_box"])
    assert "Did you mean the bundled scene 'cornell_box'?" in err


def test_an_output_path_that_is_a_file(tmp_path, capsys):
    blocker = tmp_path / "taken"
    blocker.write_text("")
    err = one_paragraph_error(capsys, [str(BAD / "base.yaml"), "-o", str(blocker)])
    assert "output folder" in err and "taken" in err


@pytest.mark.parametrize("option, value, says", [
    ("--shots", "0", "positive integer"),
    ("--shots", "ten", "expected an integer, got 'ten'"),
    ("--resolution", "30.5", "expected an integer"),
    ("--resolution", "7", "even integer >= 8"),
    ("--unshot-fraction", "1", "[0, 1)"),
    ("--unshot-fraction", "nan", "[0, 1)"),
    ("--threshold", "-1", "positive number"),
    ("--threshold", "inf", "positive number"),
    ("--max-depth", "17", "0 to 16"),
    ("--max-elements", "6000000", "5,000,000"),
    ("--checkpoint-every", "-3", ">= 0"),
    ("--cache-mb", "-1", "megabytes from 0 to 1e7"),
    ("--round-growth", "1", "above 1 and at most 100"),
    ("--refine", "pattern3", "invalid choice"),
    ("--criterion", "gradient2", "invalid choice"),
    ("--importance", "view", "invalid choice"),
    ("--final-gather", "everywhere", "invalid choice"),
    ("--device", "gpu", "expected one of cpu, cuda, cuda:N, auto"),
])
def test_bad_option_value_is_one_paragraph_with_exit_code_2(option, value, says, capsys):
    with pytest.raises(SystemExit) as exit_:
        main([str(BAD / "base.yaml"), option, value])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("hemirad: error: ") and "\n" not in err
    assert option in err and says in err


def test_unknown_option_is_one_paragraph(capsys):
    with pytest.raises(SystemExit) as exit_:
        main([str(BAD / "base.yaml"), "--most-shots", "3"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip()
    assert "unrecognized arguments: --most-shots 3" in err and "\n" not in err


def test_a_mesh_with_some_degenerate_triangles_is_solved_with_a_counted_warning(tmp_path, capsys):
    mesh = tmp_path / "tetra.obj"
    # the tetrahedron plus a zero-area triangle (a repeated corner) and one with a NaN corner
    mesh.write_text((DATA / "tetra.obj").read_text() + "v nan 0 0\nf 1 1 2\nf 1 2 5\n")
    scene = tmp_path / "scene.yaml"
    scene.write_text((BAD / "base.yaml").read_text())
    assert main([str(scene), "-o", str(tmp_path / "out"), "-q"]) == 0
    err = capsys.readouterr().err.strip()
    assert err == "hemirad: warning: tetra: dropped 2 of 6 triangles of tetra.obj (1 non-finite, 1 zero-area)"
