import json

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from hemirad.geometry.mesh import Mesh
from hemirad.output.export import read_ply_radiosity, write_ply, write_png, write_stats


def _two_surfaces() -> Mesh:
    """Two unit squares meeting at a crease, with duplicate positions along it."""
    floor = Mesh([[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1]], [[0, 2, 1], [0, 3, 2]], [0, 0], [0, 0])
    wall = Mesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]], [0, 0], [1, 1])
    return Mesh.concatenate([floor, wall])


def test_ply_round_trip(tmp_path):
    mesh = _two_surfaces()
    radiosity = torch.linspace(0.0, 5.5, 24, dtype=torch.float64).reshape(8, 3)
    rgb8 = (np.arange(24, dtype=np.uint8) * 10).reshape(8, 3)
    path = tmp_path / "out" / "mesh.ply"
    write_ply(path, mesh, radiosity, rgb8)

    assert path.read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")
    loaded = trimesh.load(path, file_type="ply", process=False)
    # Duplicate positions along the crease stay separate vertices, in the same order.
    assert len(loaded.vertices) == 8
    np.testing.assert_allclose(loaded.vertices, mesh.vertices.numpy(), atol=1e-6)
    assert loaded.faces.tolist() == mesh.triangles.tolist()
    assert loaded.visual.kind == "vertex"
    colors = loaded.visual.vertex_colors
    assert colors.dtype == np.uint8
    assert colors[:, :3].tolist() == rgb8.tolist()
    assert (colors[:, 3] == 255).all()
    # trimesh keeps the extra float properties in the raw PLY records.
    np.testing.assert_allclose(read_ply_radiosity(path), radiosity.numpy(), rtol=1e-6)


def test_ply_rejects_mismatched_lengths(tmp_path):
    with pytest.raises(ValueError):
        write_ply(tmp_path / "x.ply", _two_surfaces(), torch.zeros(7, 3), np.zeros((8, 3), np.uint8))
    with pytest.raises(ValueError):
        write_ply(tmp_path / "x.ply", _two_surfaces(), torch.zeros(8, 3), np.zeros((8, 3), np.float32))


def test_png_round_trip(tmp_path):
    image = np.random.default_rng(0).integers(0, 256, size=(5, 7, 3), dtype=np.uint8)
    path = tmp_path / "image.png"
    write_png(path, image)
    with Image.open(path) as loaded:
        assert loaded.mode == "RGB" and loaded.size == (7, 5)
        assert np.array_equal(np.asarray(loaded), image)


def test_png_rejects_float_image(tmp_path):
    with pytest.raises(ValueError):
        write_png(tmp_path / "image.png", np.zeros((2, 2, 3), np.float32))


def test_stats_round_trip(tmp_path):
    stats = {
        "shots": np.int64(100),
        "time_s": np.float32(1.5),
        "elements": torch.tensor(2148),
        "unshot_fraction": torch.tensor(1e-3, dtype=torch.float64),
        "per_shot": np.array([1.0, 2.0]),
        "converged": np.bool_(True),
        "renderer": "llvmpipe",
        "nested": {"b": 2, "a": (1, 2)},
    }
    path = tmp_path / "stats.json"
    write_stats(path, stats)
    text = path.read_text()
    assert text.endswith("\n") and text.startswith("{\n  \"converged\": true")
    assert json.loads(text) == {
        "shots": 100, "time_s": 1.5, "elements": 2148, "unshot_fraction": 1e-3,
        "per_shot": [1.0, 2.0], "converged": True, "renderer": "llvmpipe",
        "nested": {"a": [1, 2], "b": 2},
    }
    assert list(json.loads(text)) == sorted(stats)


@pytest.mark.parametrize("bad", [float("nan"), np.float64("inf"), torch.tensor(float("-inf"))])
def test_stats_refuse_non_finite(tmp_path, bad):
    with pytest.raises(ValueError, match="nested.x"):
        write_stats(tmp_path / "stats.json", {"nested": {"x": bad}})
