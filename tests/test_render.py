import numpy as np
import pytest
import torch

from hemirad.geometry.mesh import Mesh
from hemirad.output.render import depth_range, render_view
from hemirad.scene.model import Camera

RED = (1.0, 0.0, 0.0)
GREEN = (0.0, 1.0, 0.0)
BLUE = (0.0, 0.0, 1.0)


def _quad(x0, x1, y0, y1, z=0.0, surface=0):
    """Axis-aligned rectangle in the plane z, facing +z (CCW seen from +z)."""
    vertices = [[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]]
    return Mesh(vertices, [[0, 1, 2], [0, 2, 3]], [surface] * 2, [0, 0])


def _colored(parts):
    """Concatenate (mesh, rgb) pairs; returns the mesh and (V, 3) vertex colours."""
    mesh = Mesh.concatenate([m for m, _ in parts])
    colors = torch.cat([torch.tensor(c, dtype=torch.float64).expand(len(m.vertices), 3) for m, c in parts])
    return mesh, colors


def _camera(**kw):
    args = dict(position=(0.0, 0.0, 2.0), look_at=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0),
                fov=40.0, width=32, height=24, exposure=None, supersample=1)
    args.update(kw)
    return Camera(**args)


def test_constant_colour_fills_view():
    mesh = _quad(-10, 10, -10, 10)
    c = (0.25, 0.5, 0.125)
    colors = torch.tensor(c).expand(4, 3)
    image = render_view(mesh, colors, _camera(supersample=2))
    assert image.shape == (24, 32, 3) and image.dtype == np.float32
    np.testing.assert_allclose(image, np.broadcast_to(c, image.shape), atol=1e-5)


def test_back_faces_are_drawn():
    mesh = _quad(-10, 10, -10, 10)
    image = render_view(mesh, torch.ones(4, 3), _camera(position=(0.0, 0.0, -2.0)))
    np.testing.assert_allclose(image, 1.0, atol=1e-5)


def test_orientation_left_is_minus_x_top_is_plus_y():
    # Left half (x < 0) red; right half split: top (y > 0) green, bottom blue.
    mesh, colors = _colored([
        (_quad(-10, 0, -10, 10), RED),
        (_quad(0, 10, 0, 10), GREEN),
        (_quad(0, 10, -10, 0), BLUE),
    ])
    image = render_view(mesh, colors, _camera(width=40, height=30))
    h, w = image.shape[:2]
    np.testing.assert_allclose(image[:, : w // 2 - 1], np.broadcast_to(RED, (h, w // 2 - 1, 3)), atol=1e-5)
    np.testing.assert_allclose(image[: h // 2 - 1, w // 2 + 1:], np.broadcast_to(GREEN, (h // 2 - 1, w // 2 - 1, 3)), atol=1e-5)
    np.testing.assert_allclose(image[h // 2 + 1:, w // 2 + 1:], np.broadcast_to(BLUE, (h // 2 - 1, w // 2 - 1, 3)), atol=1e-5)


def test_gouraud_interpolation_between_vertices():
    # Colour ramps with x: 0 at x = -1, 1 at x = +1; seen head-on, the middle column is ~0.5.
    mesh = _quad(-1, 1, -10, 10)
    colors = torch.tensor([[0.0] * 3, [1.0] * 3, [1.0] * 3, [0.0] * 3])
    image = render_view(mesh, colors, _camera(fov=90.0, width=64, height=64, position=(0.0, 0.0, 1.0)))
    row = image[32, :, 0]
    assert np.all(np.diff(row) >= -1e-6)
    assert row[31:33].mean() == pytest.approx(0.5, abs=0.02)


def test_depth_test_keeps_nearer_surface():
    # Far quad white and large; near quad red and small, drawn first in index order.
    mesh, colors = _colored([(_quad(-0.2, 0.2, -0.2, 0.2, z=0.5), RED), (_quad(-10, 10, -10, 10, z=0.0), (1.0, 1.0, 1.0))])
    image = render_view(mesh, colors, _camera(width=31, height=31))
    np.testing.assert_allclose(image[15, 15], RED, atol=1e-5)
    np.testing.assert_allclose(image[0, 0], (1.0, 1.0, 1.0), atol=1e-5)


def test_background_is_black():
    mesh = _quad(-0.1, 0.1, -0.1, 0.1)
    image = render_view(mesh, torch.ones(4, 3), _camera())
    assert image[0, 0].tolist() == [0.0, 0.0, 0.0]
    assert image[12, 16].tolist() == [1.0, 1.0, 1.0]


def test_antialiasing_gives_intermediate_values_on_edges():
    # A white quad covering the right part of the view with an edge at a slant.
    mesh = Mesh([[0.0, -10, 0], [10, -10, 0], [10, 10, 0], [0.7, 10, 0]], [[0, 1, 2], [0, 2, 3]], [0, 0], [0, 0])
    white = torch.ones(4, 3)
    hard = render_view(mesh, white, _camera(supersample=1))
    soft = render_view(mesh, white, _camera(supersample=3))
    assert set(np.unique(hard).tolist()) <= {0.0, 1.0}
    partial = (soft > 0.01) & (soft < 0.99)
    assert partial[..., 0].sum() >= soft.shape[0] // 2  # about one partial pixel per row
    # Box filtering conserves coverage: both images hold about the same amount of white.
    assert abs(hard.mean() - soft.mean()) < 0.02


def test_deterministic():
    mesh, colors = _colored([(_quad(-1, 0, -1, 1), RED), (_quad(0, 1, -1, 0.5), GREEN)])
    camera = _camera(position=(0.3, 0.4, 2.0), supersample=2)
    a = render_view(mesh, colors, camera)
    b = render_view(mesh, colors, camera)
    assert np.array_equal(a, b)


def test_near_plane_does_not_clip_close_geometry():
    # A wall 0.05 in front of the camera hides a far one; the near plane must lie closer.
    near_wall = _quad(-1, 1, -1, 1, z=0.45)
    far_wall = _quad(-1, 1, -1, 1, z=-1.0)
    mesh, colors = _colored([(far_wall, RED), (near_wall, GREEN)])
    camera = _camera(position=(0.0, 0.0, 0.5), look_at=(0.0, 0.0, -1.0))
    near, far = depth_range(mesh, camera)
    assert 0 < near < 0.05 and far >= 1.5
    image = render_view(mesh, colors, camera)
    np.testing.assert_allclose(image, np.broadcast_to(GREEN, image.shape), atol=1e-5)


def test_everything_behind_camera_gives_black():
    mesh = _quad(-1, 1, -1, 1, z=5.0)
    image = render_view(mesh, torch.ones(4, 3), _camera())
    assert not image.any()


def test_rejects_wrong_colour_count():
    with pytest.raises(ValueError):
        render_view(_quad(-1, 1, -1, 1), torch.ones(3, 3), _camera())
