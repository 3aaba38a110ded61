"""Initial meshes: grids over quads, orientation of rooms and boxes, imported meshes."""
from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from hemirad.core.errors import HemiradWarning
from hemirad.geometry.mesh import Mesh
from hemirad.scene.loader import load_scene
from hemirad.scene.meshing import box_face_corners, build_mesh, grid_quad, smooth_patches
from hemirad.scene.model import Box, Camera, Material, MeshFile, Quad, Room, Scene

from patches import assert_same_mesh

DATA = Path(__file__).parent / "data"
TETRA = np.array([(1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1)], dtype=np.float64)


def areas_and_normals(vertices: torch.Tensor, triangles: torch.Tensor):
    c = vertices[triangles]
    cross = torch.linalg.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
    return 0.5 * cross.norm(dim=1), cross / cross.norm(dim=1, keepdim=True)


def scene_of(*objects) -> Scene:
    materials = [Material("white", (0.5, 0.5, 0.5)), Material("lamp", (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))]
    return Scene(materials, list(objects), Camera((0.0, 0.0, -5.0), (0.0, 0.0, 0.0)))


def polygon_area(corners: np.ndarray) -> float:
    """Area of a planar polygon (N, 3): half the norm of its vector area."""
    return 0.5 * float(np.linalg.norm(np.cross(corners, np.roll(corners, -1, axis=0)).sum(axis=0)))


def assert_surfaces_share_no_vertex(mesh: Mesh):
    owner = torch.full((len(mesh.vertices),), -1, dtype=torch.int64)
    for s in range(len(mesh.surface_names)):
        used = mesh.triangles[mesh.surface == s].unique()
        assert (owner[used] == -1).all(), f"surface {mesh.surface_names[s]} shares vertices"
        owner[used] = s


# ---------------------------------------------------------------------------------------
# grid_quad


def test_grid_quad_rectangle():
    corners = torch.tensor([[0, 0, 0], [1, 0, 0], [1, 0.5, 0], [0, 0.5, 0]], dtype=torch.float64)
    v, t = grid_quad(corners, 0.25)
    assert v.shape == (5 * 3, 3) and t.shape == (16, 3)  # 4 x 2 cells
    area, normal = areas_and_normals(v, t)
    assert float(area.sum()) == pytest.approx(0.5, rel=1e-12)
    assert torch.allclose(area, torch.full_like(area, 0.5 / 16))
    assert torch.allclose(normal, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(normal))
    # the corners are reproduced exactly
    for c in corners:
        assert (v == c).all(dim=1).any()


def test_grid_quad_winding_follows_the_corners():
    corners = torch.tensor([[0, 0, 0], [0, 0.5, 0], [1, 0.5, 0], [1, 0, 0]], dtype=torch.float64)
    _, normal = areas_and_normals(*grid_quad(corners, 0.25))
    assert torch.allclose(normal[:, 2], torch.full((len(normal),), -1.0, dtype=torch.float64))


def test_grid_quad_rounding_does_not_add_a_cell():
    corners = torch.tensor([[0, 0, 0], [0.9, 0, 0], [0.9, 0.3, 0], [0, 0.3, 0]], dtype=torch.float64)
    _, t = grid_quad(corners, 0.3)  # 0.9 / 0.3 is 3.0000000000000004 in floating point
    assert len(t) == 2 * 3 * 1


def test_grid_quad_splits_cells_along_the_shorter_diagonal():
    # one sheared cell: diagonal 0-2 is 1.90 long, diagonal 1-3 only 0.63
    corners = torch.tensor([[0, 0, 0], [1, 0, 0], [1.8, 0.6, 0], [0.8, 0.6, 0]], dtype=torch.float64)
    v, t = grid_quad(corners, 1.0)
    assert t.shape == (2, 3)
    c = v[t]
    assert float((c - c.roll(1, dims=1)).norm(dim=2).max()) == pytest.approx(1.0)  # no long diagonal
    area, normal = areas_and_normals(v, t)
    assert float(area.sum()) == pytest.approx(0.6, rel=1e-12)
    assert (normal[:, 2] > 0.999).all()


def test_grid_quad_rejects_bad_size():
    with pytest.raises(ValueError):
        grid_quad(torch.eye(4, 3, dtype=torch.float64), 0.0)


# ---------------------------------------------------------------------------------------
# rooms, boxes, quads


@pytest.mark.parametrize("inward", [True, False])
@pytest.mark.parametrize("face", Room.FACE_NAMES)
def test_box_face_corners_orientation(face, inward):
    lo, hi = (0.0, 1.0, 2.0), (3.0, 5.0, 4.0)
    corners = box_face_corners(lo, hi, face, inward)
    normal = torch.linalg.cross(corners[1] - corners[0], corners[2] - corners[0])
    to_centre = torch.tensor(lo, dtype=torch.float64) / 2 + torch.tensor(hi, dtype=torch.float64) / 2 - corners.mean(0)
    assert (float(normal @ to_centre) > 0) == inward


def test_room_normals_point_inward_and_box_normals_outward():
    room = Room((0.0, 0.0, 0.0), (4.0, 2.5, 3.0), "white", 0.5, name="room")
    box = Box((1.0, 0.0, 1.0), (2.0, 0.5, 1.5), "white", 0.25, name="box")
    scene = scene_of(room, box)
    scene.meshing.contacts = False  # every face meshed, the box's bottom on the floor too
    mesh = build_mesh(scene)
    assert mesh.surface_names[:6] == [f"room.{f}" for f in Room.FACE_NAMES]
    assert mesh.surface_names[6:] == ["box.bottom", "box.top", "box.x_min", "box.x_max", "box.z_min", "box.z_max"]
    in_room = mesh.surface < 6
    room_c = torch.tensor([2.0, 1.25, 1.5], dtype=torch.float64)
    box_c = torch.tensor([1.5, 0.25, 1.25], dtype=torch.float64)
    d_room = ((mesh.centroids - room_c) * mesh.normals).sum(1)
    d_box = ((mesh.centroids - box_c) * mesh.normals).sum(1)
    assert (d_room[in_room] < 0).all()
    assert (d_box[~in_room] > 0).all()
    # total areas: room 2 (4*2.5 + 4*3 + 2.5*3), box 2 (1*0.5 + 1*0.5 + 0.5*0.5)
    assert float(mesh.areas[in_room].sum()) == pytest.approx(2 * (10 + 12 + 7.5), rel=1e-12)
    assert float(mesh.areas[~in_room].sum()) == pytest.approx(2 * (0.5 + 0.5 + 0.25), rel=1e-12)
    assert_surfaces_share_no_vertex(mesh)


def test_room_face_overrides():
    from hemirad.scene.model import FaceOverride

    room = Room((0.0, 0.0, 0.0), (2.0, 2.0, 2.0), "white", 1.0,
                faces={"floor": FaceOverride(material="lamp", element_size=0.5)}, name="room")
    mesh = build_mesh(scene_of(room))
    floor = mesh.surface == 0
    assert int(floor.sum()) == 2 * 4 * 4 and int((~floor).sum()) == 5 * 2 * 2 * 2
    assert (mesh.material[floor] == 1).all() and (mesh.material[~floor] == 0).all()


def test_duplicate_names_fall_back_to_key_paths():
    quad = ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (1.0, 1.0, 0.0), (0.0, 1.0, 0.0))
    mesh = build_mesh(scene_of(Quad(quad, "lamp", 1.0), Quad(quad, "white", 1.0), Quad(quad, "white", 1.0, name="q")))
    assert mesh.surface_names == ["objects[0]", "objects[1]", "q"]


CORNELL_INTO_BOX = {"floor": (0, 1, 0), "ceiling": (0, -1, 0), "light": (0, -1, 0), "back_wall": (0, 0, -1),
                    "green_wall": (1, 0, 0), "red_wall": (-1, 0, 0)}


def test_cornell_box_mesh():
    scene = load_scene("cornell_box")
    scene.meshing.contacts = False  # every quad meshed whole, as the paper's figures are
    mesh = build_mesh(scene)
    assert len(mesh.surface_names) == len(scene.objects) == 16
    assert 1000 < mesh.num_elements < 10000
    quads = {o.name: np.array(o.corners) for o in scene.objects}
    areas, normals = mesh.areas, mesh.normals
    total_expected = 0.0
    for s, name in enumerate(mesh.surface_names):
        mine = mesh.surface == s
        corners = quads[name]
        planar = abs(np.dot(np.cross(corners[1] - corners[0], corners[2] - corners[0]), corners[3] - corners[0]))
        expected = polygon_area(corners)
        total_expected += expected
        # the published red wall is twisted by ~3 mm: its grid follows the bilinear patch,
        # whose area differs from the flat polygon's by O(twist^2)
        rel = 1e-9 if planar < 1e-6 else 1e-4
        assert float(areas[mine].sum()) == pytest.approx(expected, rel=rel), name
        if name in CORNELL_INTO_BOX:
            want = torch.tensor(CORNELL_INTO_BOX[name], dtype=torch.float64)
            assert (normals[mine] @ want > 0.999).all(), name
    assert float(areas.sum()) == pytest.approx(total_expected, rel=1e-6)
    # block sides and tops face away from their block's axis
    for block, height in (("short_block", 165.0), ("tall_block", 330.0)):
        pick = torch.tensor([n.startswith(block) for n in mesh.surface_names])[mesh.surface]
        centre = torch.tensor(quads[f"{block}.top"].mean(0), dtype=torch.float64) - torch.tensor([0, height / 2, 0])
        assert (((mesh.centroids[pick] - centre) * normals[pick]).sum(1) > 0).all(), block
    # the light hangs below the ceiling, never in its plane
    light = mesh.vertices[mesh.triangles[mesh.surface == mesh.surface_names.index("light")]]
    assert float(light[..., 1].max()) < 548.8
    assert_surfaces_share_no_vertex(mesh)


@pytest.mark.parametrize("name", ["floating", "cornell_box"])
def test_bundled_scenes_mesh_deterministically(name):
    scene = load_scene(name)
    a, b = build_mesh(scene), build_mesh(load_scene(name))
    assert_same_mesh(a, b)
    assert a.vertices.dtype == torch.float64 and a.triangles.dtype == torch.int64


# ---------------------------------------------------------------------------------------
# imported meshes


def test_small_room_mesh():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = load_scene(DATA / "small_room.yaml")
        mesh = build_mesh(scene)
    assert 150 <= mesh.num_elements <= 250
    tetra = [n for n in mesh.surface_names if n.startswith("tetra")]
    assert tetra == [f"tetra.patch{k}" for k in range(4)]  # four faces, all creases sharper than 30 degrees
    assert_surfaces_share_no_vertex(mesh)
    a, b = build_mesh(scene), build_mesh(scene)
    assert torch.equal(a.vertices, b.vertices) and torch.equal(a.triangles, b.triangles)


def rotation_y(degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def test_mesh_import_applies_the_transform():
    scene = load_scene(DATA / "small_room.yaml")
    tetra_obj = next(o for o in scene.objects if isinstance(o, MeshFile))
    mesh = build_mesh(scene_of(tetra_obj))
    expected = (0.15 * TETRA) @ rotation_y(30).T + np.array([1.4, 0.3, 1.2])
    lo, hi = mesh.bounding_box()
    assert np.allclose(lo.numpy(), expected.min(0), atol=1e-12)
    assert np.allclose(hi.numpy(), expected.max(0), atol=1e-12)
    # every edge was subdivided to at most the element size, and the area is kept
    c = mesh.corners
    assert float((c - c.roll(1, dims=1)).norm(dim=2).max()) <= tetra_obj.element_size
    edge = 0.15 * 2 * math.sqrt(2)
    assert float(mesh.areas.sum()) == pytest.approx(4 * math.sqrt(3) / 4 * edge**2, rel=1e-12)
    # faces still point out of the tetrahedron
    centre = torch.tensor(expected.mean(0))
    assert (((mesh.centroids - centre) * mesh.normals).sum(1) > 0).all()


def write_obj(path: Path, vertices, faces):
    lines = [f"v {float(x)!r} {float(y)!r} {float(z)!r}" for x, y, z in vertices] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


TETRA_FACES = [(1, 3, 2), (0, 2, 3), (0, 3, 1), (0, 1, 2)]


def test_mirroring_transform_keeps_faces_outward(tmp_path):
    write_obj(tmp_path / "t.obj", TETRA, TETRA_FACES)
    mirror = ((-1.0, 0, 0, 0), (0, 1.0, 0, 0), (0, 0, 1.0, 0), (0, 0, 0, 1.0))
    mesh = build_mesh(scene_of(MeshFile(tmp_path / "t.obj", "white", 10.0, mirror)))
    assert (((mesh.centroids) * mesh.normals).sum(1) > 0).all()


def test_degenerate_triangles_are_dropped_with_a_warning(tmp_path):
    vertices = np.vstack([TETRA, [(0.0, 0.0, 0.0), (2.0, 2.0, 2.0), (5.0, 5.0, 5.0)]])
    faces = TETRA_FACES + [(4, 5, 6), (0, 0, 1)]  # collinear corners; a repeated corner
    write_obj(tmp_path / "bad.obj", vertices, faces)
    write_obj(tmp_path / "good.obj", TETRA, TETRA_FACES)
    bad = scene_of(MeshFile(tmp_path / "bad.obj", "white", 10.0, name="bad"))
    with pytest.warns(HemiradWarning, match=r"dropped 2 of 6 triangles .*2 zero-area"):
        mesh = build_mesh(bad)
    good = build_mesh(scene_of(MeshFile(tmp_path / "good.obj", "white", 10.0, name="bad")))
    assert mesh.num_elements == good.num_elements == 4
    assert torch.allclose(mesh.areas.sort().values, good.areas.sort().values)


def test_smooth_patches_follow_the_crease_angle(tmp_path):
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces, dtype=np.int64)
    assert len(smooth_patches(v, f, 30.0)) == 1
    assert len(smooth_patches(v, f, 1.0)) == len(f)
    cube = trimesh.creation.box()
    patches = smooth_patches(np.asarray(cube.vertices), np.asarray(cube.faces, dtype=np.int64), 30.0)
    assert len(patches) == 6 and sorted(np.concatenate(patches).tolist()) == list(range(12))
    # through the mesher: a PLY sphere is one surface whose vertices its triangles share
    sphere.export(tmp_path / "sphere.ply")
    mesh = build_mesh(scene_of(MeshFile(tmp_path / "sphere.ply", "white", 10.0, name="ball")))
    assert mesh.surface_names == ["ball"] and len(mesh.vertices) == len(v)


def test_a_mesh_file_is_parsed_once_per_load(monkeypatch):
    import hashlib

    import trimesh

    from hemirad import checkpoint
    from hemirad.scene.meshfile import read_mesh_file

    parsed = []
    load = trimesh.load_scene
    monkeypatch.setattr(trimesh, "load_scene", lambda path, **kw: parsed.append(path) or load(path, **kw))
    scene = load_scene(DATA / "small_room.yaml")
    build_mesh(scene)
    build_mesh(scene.with_element_sizes_scaled(0.5))
    assert parsed == [DATA.absolute() / "tetra.obj"]
    # The same triangles as a fresh read; the checkpoint hashes the content as read.
    tetra = next(o for o in scene.objects if isinstance(o, MeshFile))
    fresh = read_mesh_file(tetra.path)
    assert np.array_equal(tetra.contents.vertices, fresh.vertices) and np.array_equal(tetra.contents.faces, fresh.faces)
    assert tetra.contents.sha256 == hashlib.sha256(tetra.path.read_bytes()).hexdigest()
    assert checkpoint.fingerprint(scene) == checkpoint.fingerprint(load_scene(DATA / "small_room.yaml"))
    # A MeshFile made by hand (no contents) is read when meshed.
    by_hand, before = MeshFile(tetra.path, "white", 0.5), len(parsed)
    assert by_hand.contents is None and len(build_mesh(scene_of(by_hand)).triangles) > 0
    assert len(parsed) == before + 1
