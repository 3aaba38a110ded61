import numpy as np
import pytest
import torch

from hemirad.core.colour import luminance
from hemirad.geometry.mesh import Mesh
from hemirad.output.display import auto_exposure, to_srgb8, vertex_values


def _srgb(x: float) -> float:
    return 12.92 * x if x <= 0.0031308 else 1.055 * x ** (1 / 2.4) - 0.055


def _square() -> Mesh:
    """Unit square in z = 0 split along the diagonal 0-2: two triangles of equal area."""
    vertices = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]
    return Mesh(vertices, [[0, 1, 2], [0, 2, 3]], [0, 0], [0, 0])


def test_vertex_values_equal_areas():
    out = vertex_values(_square(), torch.tensor([[1.0], [3.0]]))
    assert out.shape == (4, 1)
    torch.testing.assert_close(out[:, 0], torch.tensor([2.0, 1.0, 2.0, 3.0]))
    assert out.dtype == torch.float32  # follows the values, not the float64 geometry


def test_vertex_values_one_dimensional_input():
    out = vertex_values(_square(), torch.tensor([1.0, 3.0]))
    assert out.shape == (4,)
    torch.testing.assert_close(out, torch.tensor([2.0, 1.0, 2.0, 3.0]))


def test_vertex_values_area_weighted():
    # Triangle 0: (0,0),(1,0),(1,1), area 1/2. Triangle 1: (0,0),(1,1),(-2,1), area 3/2.
    mesh = Mesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [-2, 1, 0]], [[0, 1, 2], [0, 2, 3]], [0, 0], [0, 0])
    torch.testing.assert_close(mesh.areas, torch.tensor([0.5, 1.5], dtype=torch.float64))
    out = vertex_values(mesh, torch.tensor([[1.0, 0.0], [3.0, 4.0]], dtype=torch.float64))
    shared = (0.5 * torch.tensor([1.0, 0.0]) + 1.5 * torch.tensor([3.0, 4.0])) / 2.0
    expected = torch.stack([shared, torch.tensor([1.0, 0.0]), shared, torch.tensor([3.0, 4.0])]).double()
    torch.testing.assert_close(out, expected)


def test_vertex_values_do_not_mix_surfaces():
    # Two surfaces meeting at a crease along x = 0..1, y = 0: same positions, own vertices.
    floor = Mesh([[0, 0, 0], [1, 0, 0], [1, 0, 1]], [[0, 2, 1]], [0], [0])
    wall = Mesh([[0, 0, 0], [1, 0, 0], [1, 1, 0]], [[0, 1, 2]], [0], [0])
    mesh = Mesh.concatenate([floor, wall])
    out = vertex_values(mesh, torch.tensor([[10.0], [2.0]]))
    torch.testing.assert_close(out[:, 0], torch.tensor([10.0, 10.0, 10.0, 2.0, 2.0, 2.0]))


def test_vertex_values_unused_vertex_is_zero():
    mesh = Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]], [[0, 1, 2]], [0], [0])
    out = vertex_values(mesh, torch.tensor([[4.0]]))
    torch.testing.assert_close(out[:, 0], torch.tensor([4.0, 4.0, 4.0, 0.0]))


def test_auto_exposure_maps_mean_to_middle_grey():
    values = torch.tensor([[1.0, 1.0, 1.0], [3.0, 3.0, 3.0], [100.0, 100.0, 100.0]])
    areas = torch.tensor([1.0, 1.0, 5.0])
    emitting = torch.tensor([False, False, True])
    assert auto_exposure(values, areas, emitting) == pytest.approx(0.18 / 2.0)


def test_auto_exposure_uses_luminance_weights_and_areas():
    values = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    areas = torch.tensor([3.0, 1.0])
    mean = (3.0 * 0.2126 + 1.0 * 0.7152) / 4.0
    assert auto_exposure(values, areas, torch.tensor([False, False])) == pytest.approx(0.18 / mean)


def test_auto_exposure_fallbacks():
    values = torch.tensor([[2.0, 2.0, 2.0]])
    # Everything emits: use everything.
    assert auto_exposure(values, torch.tensor([1.0]), torch.tensor([True])) == pytest.approx(0.09)
    # A black scene: no division by zero.
    assert auto_exposure(torch.zeros(2, 3), torch.ones(2), torch.zeros(2, dtype=torch.bool)) == 1.0


def test_luminance_of_white_is_one():
    assert float(luminance(torch.ones(3))) == pytest.approx(1.0)


@pytest.mark.parametrize("x", [0.0, 0.0031308, 0.0031, 0.18, 0.5, 1.0])
def test_to_srgb8_matches_formula(x):
    got = to_srgb8(np.full((1, 3), x), 1.0)
    assert got.dtype == np.uint8
    assert (got == round(255 * _srgb(x))).all()


def test_to_srgb8_known_values_and_clipping():
    linear = np.array([[0.0, 0.18, 1.0], [2.0, -1.0, np.nan]])
    assert to_srgb8(linear, 1.0).tolist() == [[0, 118, 255], [255, 0, 0]]


def test_to_srgb8_applies_exposure_and_keeps_image_shape():
    image = torch.full((2, 4, 3), 0.09)
    out = to_srgb8(image, 2.0)
    assert out.shape == (2, 4, 3)
    assert (out == 118).all()


def test_to_srgb8_rejects_bad_exposure():
    with pytest.raises(ValueError):
        to_srgb8(np.zeros((1, 3)), float("nan"))
