"""Concave creases (hemirad.geometry.creases): the sides of quads where another surface
stands facing them are found from the geometry, their grids get a strip of thin elements
there, and the picture beside the crease follows the light falling into it."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import hemirad
from hemirad.evaluation.surface_points import elements_at
from hemirad.geometry.creases import CREASE_STRIP, crease_sides
from hemirad.geometry.mesh import barycentric
from hemirad.lighting.sensors import final_gather
from hemirad.scene.meshing import box_face_corners, build_mesh, grid_quad
from hemirad.scene.model import Camera, Material, Quad, Room, Scene

TOLERANCE = 1e-9


def triangles_of(*quads: np.ndarray, size: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """The grids of (4, 3) quads as (K, 3, 3) triangles and their (K, 3) unit normals."""
    corners = []
    for quad in quads:
        v, t = grid_quad(torch.as_tensor(quad, dtype=torch.float64), size)
        corners.append(v.numpy()[t.numpy()])
    corners = np.concatenate(corners)
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return corners, normals / np.linalg.norm(normals, axis=1, keepdims=True)


FLOOR = box_face_corners((0, 0, 0), (2, 2, 2), "floor", inward=True).numpy()  # normal +y


def test_a_wall_standing_on_a_floor_is_a_crease_of_both():
    wall = box_face_corners((0, 0, 0), (2, 2, 2), "x_min", inward=True).numpy()  # x = 0, facing +x
    floor_sides = crease_sides(FLOOR, *triangles_of(wall), TOLERANCE)
    wall_sides = crease_sides(wall, *triangles_of(FLOOR), TOLERANCE)
    assert floor_sides.sum() == 1 and wall_sides.sum() == 1
    for quad, sides in ((FLOOR, floor_sides), (wall, wall_sides)):
        k = int(np.flatnonzero(sides)[0])
        assert np.abs(quad[[k, (k + 1) % 4], 0]).max() < TOLERANCE and np.abs(quad[[k, (k + 1) % 4], 1]).max() < TOLERANCE
    # a wall facing away from the floor's front (the outside of a room) is no crease
    outside = box_face_corners((0, 0, 0), (2, 2, 2), "x_min", inward=False).numpy()
    assert not crease_sides(FLOOR, *triangles_of(outside), TOLERANCE).any()


@pytest.mark.parametrize("lift, creases", [(0.0, 1), (1e-3, 0)], ids=["standing", "a millimetre up"])
def test_a_box_on_a_floor(lift, creases):
    """A box's sides meet the floor at a concave crease (inside the floor's outline, where
    no floor triangle has an edge), but not its top, whose sides are convex edges; a box a
    millimetre up touches nothing."""
    low, high = (0.7, lift, 0.7), (1.3, 0.6 + lift, 1.3)
    faces = {f: box_face_corners(low, high, f, inward=False).numpy() for f in ("x_min", "x_max", "z_min", "z_max", "ceiling")}
    floor = triangles_of(FLOOR)
    for name, quad in faces.items():
        others = triangles_of(FLOOR, *[q for f, q in faces.items() if f != name])
        assert crease_sides(quad, *others, TOLERANCE).sum() == (0 if name == "ceiling" else creases), name
        assert crease_sides(quad, *floor, TOLERANCE).sum() == (0 if name == "ceiling" else creases), name


def test_a_graded_grid_puts_a_strip_along_its_graded_sides():
    quad = torch.as_tensor(FLOOR)
    plain = grid_quad(quad, 0.5)
    graded = grid_quad(quad, 0.5, (True, False, True, False))  # sides 01 and 23
    areas = [torch.linalg.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]).norm(dim=1) / 2 for v, t in (plain, graded)]
    assert float(areas[1].sum()) == pytest.approx(float(areas[0].sum()), rel=1e-12)
    assert len(graded[1]) == len(plain[1]) + 2 * 2 * 4  # two strips of four cells, two triangles each
    along = torch.as_tensor(FLOOR[1] - FLOOR[0]).abs().argmax()  # the axis sides 01 and 23 run along
    across = 2 - along  # x or z: the floor is y = 0
    lines = torch.unique(graded[0][:, across])
    assert torch.allclose(lines[[1, -2]], torch.tensor([CREASE_STRIP * 0.5, 2 - CREASE_STRIP * 0.5], dtype=torch.float64))
    assert torch.equal(torch.unique(graded[0][:, along]), torch.unique(plain[0][:, along]))


def cornell(creases) -> Scene:
    scene = hemirad.load_scene("cornell_box")
    scene.refine.pattern = "pattern2"  # judged on the answer: creases on by default
    scene.meshing.creases = creases
    return scene


def outline_distances(mesh, name: str, corners) -> np.ndarray:
    """(T,) the distances of surface ``name``'s element centroids from its quad's outline."""
    centroids = mesh.corners[mesh.surface == mesh.surface_names.index(name)].mean(dim=1).numpy()
    a = np.asarray(corners, dtype=np.float64)
    b = np.roll(a, -1, axis=0)
    t = np.clip(((centroids[:, None] - a) * (b - a)).sum(-1) / ((b - a) ** 2).sum(-1), 0, 1)
    return np.linalg.norm(centroids[:, None] - (a + t[..., None] * (b - a)), axis=-1).min(axis=1)


def test_the_cornell_box_answer_grades_its_room_and_blocks_but_not_the_lamp_or_the_tops():
    """Its room's faces and its blocks' sides (where they stand on the floor) get strips of
    elements a quarter of their 40 mm wide along their concave creases, within the same area."""
    assert cornell("auto").meshes_creases and not hemirad.load_scene("cornell_box").meshes_creases
    scene = cornell("auto")
    graded, plain = build_mesh(scene), build_mesh(cornell(False))
    quads = {obj.name: obj.corners for obj in scene.objects}
    strip = CREASE_STRIP * 40.0
    for name in ("floor", "ceiling", "back_wall", "green_wall", "red_wall", "short_block.side0", "tall_block.side2"):
        s = [m.surface_names.index(name) for m in (graded, plain)]
        areas = [m.areas[m.surface == i] for m, i in zip((graded, plain), s)]
        assert float(areas[0].sum()) == pytest.approx(float(areas[1].sum()), rel=1e-8), name  # the red wall is twisted
        inside = [(outline_distances(m, name, quads[name]) < strip).sum() for m in (graded, plain)]
        assert inside[0] >= 8 and inside[1] == 0, (name, inside)  # the strips' thin elements
    for name in ("light", "short_block.top", "tall_block.top"):
        s = [m.surface_names.index(name) for m in (graded, plain)]
        assert torch.equal(*[m.corners[m.surface == i] for m, i in zip((graded, plain), s)]), name


def test_office_answer_grades_its_room_but_not_short_sides():
    """Sides a single cell long (a desk leg's foot, 5 cm) get no strip; the room's do."""
    scene = hemirad.load_scene("office")
    scene.refine.pattern = "pattern2"
    graded = build_mesh(scene)
    scene.meshing.creases = False
    plain = build_mesh(scene)
    def surface(mesh, name):
        return mesh.corners[mesh.surface == mesh.surface_names.index(name)]
    for name in ("room.floor", "room.ceiling", "room.x_min", "pc.tower.x_max"):
        assert len(surface(graded, name)) > len(surface(plain, name)), name
    for name in ("desk.leg1.x_min", "desk.leg4.z_max", "chair.leg2.x_max"):
        assert torch.equal(surface(graded, name), surface(plain, name)), name


def crease_room(creases: bool) -> Scene:
    """A 2 m cube of 0.5 m elements (reflectance 0.7) lit by a 0.6 m lamp 5 mm under its ceiling."""
    materials = [Material("wall", (0.7,) * 3), Material("lamp", (0.0,) * 3, (30.0,) * 3)]
    lamp = ((0.7, 1.995, 0.7), (1.3, 1.995, 0.7), (1.3, 1.995, 1.3), (0.7, 1.995, 1.3))
    scene = Scene(materials, [Room((0.0, 0.0, 0.0), (2.0, 2.0, 2.0), "wall", 0.5, name="room"), Quad(lamp, "lamp", 0.3)],
                  Camera((1.0, 1.0, 0.1), (1.0, 1.0, 1.0), width=32, height=32))
    scene.meshing.creases = creases
    scene.solver.resolution, scene.solver.unshot_fraction = 128, 1e-3
    return scene


def test_the_picture_beside_a_crease_follows_the_light_into_it():
    """Within 12 cm of the room's concave edges (the wall under the ceiling, the ceiling
    beside the wall, the wall over the floor), the picture as drawn against final gathers
    of the same solution at the same points, which see the light arrive whatever the mesh:
    with the strips the wall under the ceiling reads about 5% bright, without them 13%."""
    d = np.array([0.005, 0.01, 0.02, 0.04, 0.08, 0.12])
    lines = [(np.stack([0 * d, 2 - d, 0 * d + 1.03], 1), (1.0, 0.0, 0.0)),  # the wall under the ceiling
             (np.stack([d, 0 * d + 2, 0 * d + 0.53], 1), (0.0, -1.0, 0.0)),  # the ceiling beside the wall
             (np.stack([0 * d, d, 0 * d + 1.03], 1), (1.0, 0.0, 0.0))]  # the wall over the floor
    points = torch.as_tensor(np.concatenate([p for p, _ in lines]))
    normals = torch.as_tensor(np.concatenate([np.tile(n, (len(d), 1)) for _, n in lines]))
    worst = {}
    for creases in (True, False):
        result = hemirad.solve(crease_room(creases), progress=None)
        element = elements_at(result.mesh, points, normals)
        shown = result.shading().at(result.mesh, element, barycentric(result.mesh.corners[element], points))[:, 0]
        gathered = 0.7 * final_gather(result.mesh, result.radiosity, points.numpy(), normals.numpy(), 128).irradiance[:, 0]
        error = (shown / torch.as_tensor(gathered) - 1).abs().numpy()
        worst[creases] = error.reshape(len(lines), -1).max(axis=1)
    assert (worst[True] < 0.07).all(), worst
    assert (worst[True] < 0.6 * worst[False]).all(), worst
    assert worst[False][0] > 0.1, worst  # the control: what the strips mend

