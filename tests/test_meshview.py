import dataclasses
import math

import numpy as np
import pytest
import torch

from hemirad.output.display import (conforming_triangles, conforming_vertex_values, t_vertex_mask,
                             vertex_values)
from hemirad.core.errors import HemiradInputError
from hemirad.geometry.mesh import Mesh
from hemirad.geometry.split import split_triangles
from hemirad.output.meshview import pick_surface, surface_view, view_basis
from hemirad.output.render import render_view
from hemirad.scene.meshing import grid_quad
from hemirad.scene.model import Camera

UNIT_SQUARE = torch.tensor([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=torch.float64)


def _grid(corners, element_size, surface=0, names=None) -> Mesh:
    v, t = grid_quad(torch.as_tensor(corners, dtype=torch.float64), element_size)
    n = len(t)
    return Mesh(v, t, torch.full((n,), surface), torch.zeros(n), names or [])


def _refined(depth: int, seed: int = 0, patterns=("pattern2",)) -> Mesh:
    """The unit square (8 triangles) after ``depth`` rounds of splitting a random 35%."""
    mesh = _grid(UNIT_SQUARE, 0.5)
    g = torch.Generator().manual_seed(seed)
    for r in range(depth):
        selected = torch.rand(mesh.num_elements, generator=g) < 0.35
        mesh, _ = split_triangles(mesh, selected, patterns[r % len(patterns)])
    return mesh


def _points_inside_edges(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(V,) bool, brute force: the vertex lies strictly inside some edge of the triangles."""
    edges = np.unique(np.sort(np.concatenate(
        [triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1), axis=0)
    a, b = vertices[edges[:, 0]], vertices[edges[:, 1]]
    ab = b - a
    out = np.zeros(len(vertices), dtype=bool)
    for v in np.unique(triangles):
        t = ((vertices[v] - a) * ab).sum(1) / (ab * ab).sum(1)
        off = np.linalg.norm(a + t[:, None] * ab - vertices[v], axis=1)
        out[v] = bool(((t > 1e-9) & (t < 1 - 1e-9) & (off < 1e-12)).any())
    return out


def _areas(vertices: torch.Tensor, triangles: torch.Tensor) -> torch.Tensor:
    c = vertices[triangles]
    return 0.5 * torch.linalg.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]).norm(dim=1)


# ----------------------------------------------------------------------------------------
# T-vertices


def test_t_vertex_on_diagonal_gets_mean_of_its_ends():
    square = Mesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]], [0, 0], [0, 0])
    mesh, parent = split_triangles(square, torch.tensor([True, False]), "pattern2")
    diagonal_mid = int(torch.nonzero((mesh.edge_parents == torch.tensor([0, 2])).all(dim=1)))
    assert t_vertex_mask(mesh).tolist() == [False] * 4 + [v == diagonal_mid for v in range(4, 7)]

    element = torch.tensor([[1.0, 10.0], [3.0, 30.0]], dtype=torch.float64)[parent]
    raw = vertex_values(mesh, element)
    fixed = conforming_vertex_values(mesh, raw)
    expected = raw.clone()
    expected[diagonal_mid] = 0.5 * (raw[0] + raw[2])
    torch.testing.assert_close(fixed, expected, rtol=0, atol=0)
    assert not torch.equal(raw[diagonal_mid], fixed[diagonal_mid])  # it did change something
    # One-dimensional values work the same way.
    torch.testing.assert_close(conforming_vertex_values(mesh, raw[:, 0]), expected[:, 0])


def test_nested_t_vertices_are_linear_along_the_coarse_edge():
    square = Mesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]], [0, 0], [0, 0])
    mesh = square
    # Split the corner-0 child on the diagonal twice more: points at 1/2, 1/4, 1/8 of the
    # diagonal hang on the unsplit triangle (0, 2, 3).
    for _ in range(3):
        corner0 = torch.nonzero((mesh.triangles == 0).any(dim=1) & (mesh.level == mesh.level.max())
                                & ~(mesh.triangles == 3).any(dim=1)).reshape(-1)
        selected = torch.zeros(mesh.num_elements, dtype=torch.bool)
        selected[corner0] = True
        mesh, _ = split_triangles(mesh, selected, "pattern2")
    hanging = t_vertex_mask(mesh)
    assert torch.equal(hanging, torch.from_numpy(_points_inside_edges(mesh.vertices.numpy(), mesh.triangles.numpy())))
    on_diagonal = hanging & (mesh.vertices[:, 0] == mesh.vertices[:, 1])
    assert sorted(mesh.vertices[on_diagonal, 0].tolist()) == [0.125, 0.25, 0.5]
    values = torch.full((len(mesh.vertices),), 7.0, dtype=torch.float64)
    values[0], values[2] = 1.0, 3.0
    fixed = conforming_vertex_values(mesh, values)
    # Along the diagonal the value is linear in x: 1 + 2x.
    x = mesh.vertices[on_diagonal, 0]
    torch.testing.assert_close(fixed[on_diagonal], 1.0 + 2.0 * x, rtol=0, atol=1e-15)


@pytest.mark.parametrize("patterns", [("pattern2",), ("pattern2", "pattern1")])
def test_t_vertex_mask_matches_geometry(patterns):
    for depth in range(1, 6):
        mesh = _refined(depth, seed=depth, patterns=patterns)
        expected = _points_inside_edges(mesh.vertices.numpy(), mesh.triangles.numpy())
        assert t_vertex_mask(mesh).numpy().tolist() == expected.tolist()


@pytest.mark.parametrize("patterns", [("pattern2",), ("pattern2", "pattern1")])
def test_conforming_triangles_tile_without_t_vertices(patterns):
    for depth in (1, 3, 5):
        mesh = _refined(depth, seed=10 + depth, patterns=patterns)
        triangles, source = conforming_triangles(mesh, return_source=True)
        assert triangles.dtype == torch.int64 and triangles.shape[1] == 3
        areas = _areas(mesh.vertices, triangles)
        assert abs(float(areas.sum()) / float(mesh.areas.sum()) - 1) < 1e-9
        # Each element is tiled exactly by its pieces, none degenerate, all wound like it.
        per_element = torch.zeros(mesh.num_elements, dtype=torch.float64).index_add_(0, source, areas)
        torch.testing.assert_close(per_element, mesh.areas, rtol=1e-12, atol=0)
        assert (areas > 1e-6 * mesh.areas[source]).all()
        c = mesh.vertices[triangles]
        normals = torch.linalg.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
        assert ((normals * mesh.normals[source]).sum(dim=1) > 0).all()
        # Every T-vertex is used, and none is left inside a display edge.
        hanging = t_vertex_mask(mesh)
        assert hanging.any()
        assert set(torch.nonzero(hanging).reshape(-1).tolist()) <= set(triangles.unique().tolist())
        assert not _points_inside_edges(mesh.vertices.numpy(), triangles.numpy()).any()
        assert torch.equal(conforming_triangles(mesh), triangles)


def test_conforming_triangles_leave_a_conforming_mesh_alone():
    mesh = _refined(3, patterns=("pattern1",))
    assert not t_vertex_mask(mesh).any()
    assert torch.equal(conforming_triangles(mesh), mesh.triangles)


def test_rendered_ramp_has_no_seams_and_no_cracks():
    """Red is a ramp in x, green is 1 everywhere: a seam shows in red, a crack in green."""
    width = height = 96
    half_fov = math.radians(20.0)
    camera = Camera(position=(0.5, 0.5, 2.0), look_at=(0.5, 0.5, 0.0), up=(0.0, 1.0, 0.0),
                    fov=40.0, width=width, height=height, supersample=1)
    # World position at each pixel centre of the plane z = 0.
    pixel = 2 * 2.0 * math.tan(half_fov) / width
    world_x = 0.5 + (np.arange(width) + 0.5 - width / 2) * pixel
    world_y = 0.5 - (np.arange(height) + 0.5 - height / 2) * pixel
    margin = 1.5 * pixel
    inside_x = (world_x > margin) & (world_x < 1 - margin)
    inside_y = (world_y > margin) & (world_y < 1 - margin)
    inside = inside_y[:, None] & inside_x[None, :]
    ramp = np.broadcast_to(world_x[None, :], (height, width))

    for depth in (1, 2, 4):
        mesh = _refined(depth, seed=20 + depth)
        hanging = torch.from_numpy(_points_inside_edges(mesh.vertices.numpy(), mesh.triangles.numpy()))
        assert hanging.any()
        x = mesh.vertices[:, 0]
        colors = torch.stack([x, torch.ones_like(x), torch.full_like(x, 0.25)], dim=1)
        # What averaging element values may give a T-vertex: anything but the edge's value.
        colors[hanging, 0] = 5.0
        fixed = conforming_vertex_values(mesh, colors)
        torch.testing.assert_close(fixed[:, 0], x, rtol=0, atol=1e-15)

        image = render_view(mesh, fixed, camera, triangles=conforming_triangles(mesh))
        assert np.abs(image[..., 1][inside] - 1.0).max() < 1e-5, f"crack at depth {depth}"
        assert np.abs(image[..., 0][inside] - ramp[inside]).max() < 2e-3, f"seam at depth {depth}"
        # The check has teeth: without the fix the T-vertices' values show.
        broken = render_view(mesh, colors, camera, triangles=conforming_triangles(mesh))
        assert np.abs(broken[..., 0][inside] - ramp[inside]).max() > 0.1


# ----------------------------------------------------------------------------------------
# surface views


def _floor_blocks(colors: dict, surface: int = 0, name: str = "room.floor") -> tuple[Mesh, torch.Tensor]:
    """The floor y = 0, x in [0, 2], z in [0, 1], facing +y, as four 1 x 0.5 blocks with
    their own vertices (so each shows its colour flat). ``colors[(ix, iz)]`` is the RGB of
    the block x in [ix, ix + 1], z in [iz / 2, (iz + 1) / 2]."""
    parts, vertex_colors = [], []
    for (ix, iz), rgb in sorted(colors.items()):
        x0, x1, z0, z1 = ix, ix + 1.0, iz / 2, (iz + 1) / 2
        corners = [[x0, 0, z0], [x0, 0, z1], [x1, 0, z1], [x1, 0, z0]]  # normal +y
        part = _grid(corners, 10.0, surface=0, names=[name])
        parts.append(part)
        vertex_colors.append(torch.tensor(rgb, dtype=torch.float64).expand(len(part.vertices), 3))
    joined = Mesh.concatenate(parts)
    mesh = dataclasses.replace(joined, surface=torch.full_like(joined.surface, surface),
                               surface_names=[f"s{i}" for i in range(surface)] + [name])
    return mesh, torch.cat(vertex_colors)


BLOCKS = {(0, 0): (1.0, 0.0, 0.0), (1, 0): (0.0, 1.0, 0.0), (0, 1): (0.0, 0.0, 1.0), (1, 1): (1.0, 1.0, 0.0)}
MAGENTA = (1.0, 0.0, 1.0)


def test_floor_view_orientation_and_colours():
    mesh, colors = _floor_blocks(BLOCKS)
    assert (mesh.normals[:, 1] > 0.99).all()
    image = surface_view(mesh, colors, 0, size=64, edges=False)
    assert image.shape == (32, 64, 3) and image.dtype == np.float32
    # Seen from above: +x to the right, -z at the top.
    np.testing.assert_array_equal(image[:16, :32], np.broadcast_to(BLOCKS[(0, 0)], (16, 32, 3)))
    np.testing.assert_array_equal(image[:16, 32:], np.broadcast_to(BLOCKS[(1, 0)], (16, 32, 3)))
    np.testing.assert_array_equal(image[16:, :32], np.broadcast_to(BLOCKS[(0, 1)], (16, 32, 3)))
    np.testing.assert_array_equal(image[16:, 32:], np.broadcast_to(BLOCKS[(1, 1)], (16, 32, 3)))


def test_floor_view_edges():
    mesh, colors = _floor_blocks(BLOCKS)
    image = surface_view(mesh, colors, 0, size=64, edge_color=MAGENTA)
    is_edge = (image == np.asarray(MAGENTA, dtype=np.float32)).all(axis=2)
    # Outline on the outermost pixels, block borders near the middle column and row.
    assert is_edge[0].all() and is_edge[-1].all() and is_edge[:, 0].all() and is_edge[:, -1].all()
    assert is_edge[:, 31:33].any(axis=1).all()
    assert is_edge[15:17].any(axis=0).all()
    # Each block's diagonal is drawn too, but most of a block is its own colour.
    for (ix, iz), rgb in BLOCKS.items():
        region = image[16 * iz + 2: 16 * iz + 14, 32 * ix + 2: 32 * ix + 30]
        own = (region == np.asarray(rgb, dtype=np.float32)).all(axis=2)
        edge = is_edge[16 * iz + 2: 16 * iz + 14, 32 * ix + 2: 32 * ix + 30]
        assert (own | edge).all() and own.mean() > 0.7 and edge.any()
    without = surface_view(mesh, colors, 0, size=64, edges=False, edge_color=MAGENTA)
    assert not (without == np.asarray(MAGENTA, dtype=np.float32)).all(axis=2).any()


def test_wall_view_is_upright():
    # A wall z = 0 facing +z: x in [0, 1], y in [0, 2]; red below y = 1, green above.
    low = _grid([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], 10.0)
    high = _grid([[0, 1, 0], [1, 1, 0], [1, 2, 0], [0, 2, 0]], 10.0)
    joined = Mesh.concatenate([low, high])
    mesh = dataclasses.replace(joined, surface=torch.zeros_like(joined.surface))
    colors = torch.cat([torch.tensor([1.0, 0, 0]).expand(4, 3), torch.tensor([0, 1.0, 0]).expand(4, 3)])
    image = surface_view(mesh, colors, 0, size=40, edges=False)
    assert image.shape == (40, 20, 3)
    np.testing.assert_array_equal(image[:20], np.broadcast_to((0.0, 1.0, 0.0), (20, 20, 3)))
    np.testing.assert_array_equal(image[20:], np.broadcast_to((1.0, 0.0, 0.0), (20, 20, 3)))


def test_view_basis_is_right_handed_facing_the_normal():
    for normal in ([0, 1, 0], [0, -1, 0], [1, 0, 0], [0.3, -0.2, 0.9], [0.01, 1, 0.02]):
        basis = view_basis(np.asarray(normal, dtype=np.float64))
        np.testing.assert_allclose(basis @ basis.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(basis) == pytest.approx(1.0)
        np.testing.assert_allclose(basis[2], np.asarray(normal) / np.linalg.norm(normal), atol=1e-12)
    np.testing.assert_allclose(view_basis(np.array([0.0, 1.0, 0.0]))[:2], [[1, 0, 0], [0, 0, -1]], atol=1e-12)


def test_only_the_chosen_surface_is_drawn_and_framed():
    floor, floor_colors = _floor_blocks(BLOCKS)
    wall = _grid([[0, 0, 0], [3, 0, 0], [3, 2, 0], [0, 2, 0]], 0.5, surface=1)
    mesh = Mesh.concatenate([floor, wall])
    colors = torch.cat([floor_colors, torch.full((len(wall.vertices), 3), 0.5, dtype=torch.float64)])
    alone = surface_view(floor, floor_colors, 0, size=64)
    np.testing.assert_array_equal(surface_view(mesh, colors, 0, size=64), alone)
    np.testing.assert_array_equal(surface_view(mesh, colors, [0], size=64), alone)
    with pytest.raises(HemiradInputError, match="no elements"):
        surface_view(mesh, colors, 5)


def test_refined_floor_view_has_no_cracks():
    corners = [[0, 0, 0], [0, 0, 1], [2, 0, 1], [2, 0, 0]]
    mesh = _grid(corners, 0.25)
    g = torch.Generator().manual_seed(3)
    for _ in range(4):
        mesh, _ = split_triangles(mesh, torch.rand(mesh.num_elements, generator=g) < 0.3, "pattern2")
    assert t_vertex_mask(mesh).any()
    colors = torch.full((len(mesh.vertices), 3), 0.5, dtype=torch.float64)
    image = surface_view(mesh, colors, 0, size=200, edges=False, background=MAGENTA)
    assert image.shape == (100, 200, 3)
    np.testing.assert_array_equal(image, np.full(image.shape, 0.5, dtype=np.float32))
    edged = surface_view(mesh, colors, 0, size=200, background=MAGENTA)
    assert not (edged == np.asarray(MAGENTA, dtype=np.float32)).all(axis=2).any()
    assert (edged == 0).all(axis=2).mean() > 0.05  # black edges over a grey floor


def test_pick_surface():
    parts = [_grid([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], 1.0),  # area 1
             _grid([[0, 0, 0], [3, 0, 0], [3, 3, 0], [0, 3, 0]], 1.0),  # area 9
             _grid([[0, 0, 0], [2, 0, 0], [2, 2, 0], [0, 2, 0]], 1.0),  # area 4
             _grid([[0, 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0]], 1.0)]  # area 2
    mesh = Mesh.concatenate(parts)
    mesh = dataclasses.replace(mesh, surface_names=["room.floor", "room.ceiling", "desk.top", "mat.floor"])
    assert pick_surface(mesh, "room.ceiling") == 1
    assert pick_surface(mesh, "ceiling") == 1
    assert pick_surface(mesh, "top") == 2
    assert pick_surface(mesh, None) == 3  # the larger of the two floors
    with pytest.raises(HemiradInputError, match="ambiguous") as err:
        pick_surface(mesh, "floor")
    assert "room.floor" in str(err.value) and "mat.floor" in str(err.value)
    with pytest.raises(HemiradInputError, match="no surface named 'wall'") as err:
        pick_surface(mesh, "wall")
    assert "room.floor, room.ceiling, desk.top, mat.floor" in str(err.value)
    with pytest.raises(HemiradInputError):
        pick_surface(mesh, "oor")  # a suffix is a whole dotted component, not any tail

    mesh = dataclasses.replace(mesh, surface_names=["a", "b", "c", "d"])
    assert pick_surface(mesh, None) == 1  # no floor: the largest surface


def test_views_over_the_opengl_size_limit_are_refused(monkeypatch):
    # The one limit both pictures check (GLContext.max_image_size), lowered to 48 pixels a side.
    from hemirad.transport.gl import GLContext

    monkeypatch.setattr(GLContext, "max_image_size", classmethod(lambda cls, gpu=False: 48))
    mesh, colors = _floor_blocks(BLOCKS)
    with pytest.raises(HemiradInputError, match="view size 64 exceeds the OpenGL framebuffer limit of 48 pixels"):
        surface_view(mesh, colors, 0, size=64)
    assert surface_view(mesh, colors, 0, size=48).shape == (24, 48, 3)
    camera = Camera((1.0, 2.0, 0.5), (1.0, 0.0, 0.5), (0.0, 0.0, -1.0), width=24, height=16, supersample=3)
    with pytest.raises(HemiradInputError, match="camera size 24 x 16 with supersample 3 exceeds the OpenGL "
                                                "framebuffer limit of 48 pixels"):
        render_view(mesh, colors, camera)
    camera.supersample = 2
    assert render_view(mesh, colors, camera).shape == (16, 24, 3)
