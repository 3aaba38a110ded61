"""Surfaces that cut through each other (hemirad.scene.intersections): cut where they meet, so
no element straddles another surface, and what a closed solid holds dropped, so no light is
lost to back faces inside it; scenes where nothing cuts through anything meshed as before."""
from __future__ import annotations

import numpy as np
import pytest
import shapely
import torch
import trimesh
import yaml

import hemirad
from hemirad.core.errors import SceneError
from hemirad.geometry.crossings import crossing_segments
from hemirad.geometry.footprints import PlaneFrame
from hemirad.geometry.patches import plane_axes
from hemirad.geometry.solids import closed_solids
from hemirad.scene.loader import parse_scene
from hemirad.scene.meshing import box_face_corners, build_mesh
from hemirad.scene.model import Box, Camera, Material, Quad, Room, Scene

from patches import assert_same_mesh

TOLERANCE = 1e-9


def surface_area(mesh, name: str) -> float:
    return float(mesh.areas[mesh.surface == mesh.surface_names.index(name)].sum())


def area_of(mesh, prefix: str) -> float:
    keep = [i for i, n in enumerate(mesh.surface_names) if n == prefix or n.startswith(prefix + ".")]
    return float(mesh.areas[torch.isin(mesh.surface, torch.tensor(keep))].sum())


def straddling(mesh, tolerance: float = 1e-7) -> list[tuple[str, str]]:
    """(element's surface, other surface) for every element that another surface's triangle
    passes through: the element has corners beyond ``tolerance`` on both sides of the other
    triangle's plane where that plane meets the other triangle's inside."""
    corners = mesh.corners.numpy()
    surface = mesh.surface.numpy()
    low, high = corners.min(axis=1), corners.max(axis=1)
    found = []
    for b in range(len(corners)):
        near = (low <= high[b] + tolerance).all(axis=1) & (high >= low[b] - tolerance).all(axis=1)
        near &= surface != surface[b]
        rows = np.flatnonzero(near)
        if not len(rows):
            continue
        e1, e2 = corners[b, 1] - corners[b, 0], corners[b, 2] - corners[b, 0]
        normal = np.cross(e1, e2) / np.linalg.norm(np.cross(e1, e2))
        crossing, segments = crossing_segments(corners[b, 0], normal, corners[rows], tolerance, along_edges=False)
        u, v = plane_axes(normal)
        frame = PlaneFrame(corners[b, 0], normal, u, v)
        other = shapely.Polygon(frame.to_plane(corners[b])).buffer(-tolerance)
        for a, segment in zip(rows[crossing], segments):  # each passes through the plane
            if shapely.LineString(frame.to_plane(segment)).intersection(other).length > tolerance:
                found.append((mesh.surface_names[surface[a]], mesh.surface_names[surface[b]]))
    return found


def room_scene(*objects, element_size: float = 0.25, intersections: bool = True) -> Scene:
    materials = [Material("white", (0.5, 0.5, 0.5)), Material("lamp", (0.0, 0.0, 0.0), (10.0, 10.0, 10.0))]
    room = Room((0.0, 0.0, 0.0), (4.0, 3.0, 4.0), "white", element_size, name="room")
    scene = Scene(materials, [room, *objects], Camera((2.0, 1.5, -1.0), (2.0, 1.0, 2.0)))
    scene.meshing.intersections = intersections
    return scene


def horizontal_quad(y: float, low, high, material: str, name: str, up: bool = True, size: float = 0.25) -> Quad:
    (x0, z0), (x1, z1) = low, high
    corners = [(x0, y, z0), (x0, y, z1), (x1, y, z1), (x1, y, z0)]  # counter-clockwise from above
    return Quad(tuple(corners if up else corners[::-1]), material, size, name=name)


# ----------------------------------------------------------------------------------------
# a plane through a closed box


def test_a_plane_through_a_box_is_cut_at_its_sides_and_its_inside_dropped():
    shelf = horizontal_quad(1.3, (0.6, 0.6), (3.4, 3.4), "white", "shelf")
    box = Box((1.2, 0.5, 1.5), (2.7, 2.0, 2.6), "white", 0.25, name="box")
    assert straddling(build_mesh(room_scene(shelf, box, intersections=False)))  # the check sees it
    mesh = build_mesh(room_scene(shelf, box))
    assert straddling(mesh) == []
    # the shelf: no element inside the box or straddling its outline; its area less the box's section
    s = mesh.surface_names.index("shelf")
    xz = mesh.corners[mesh.surface == s].numpy()[:, :, [0, 2]]
    inside = ((xz > [1.2 + TOLERANCE, 1.5 + TOLERANCE]) & (xz < [2.7 - TOLERANCE, 2.6 - TOLERANCE])).all(axis=2)
    assert not inside.any(axis=1).any()
    assert surface_area(mesh, "shelf") == pytest.approx(2.8 * 2.8 - 1.5 * 1.1, rel=1e-9)
    # the box is whole (the shelf is no solid), its sides cut at the shelf's height
    assert area_of(mesh, "box") == pytest.approx(2 * (1.5 * 1.5 + 1.5 * 1.1 + 1.5 * 1.1), rel=1e-9)
    for side in ("x_min", "x_max", "z_min", "z_max"):
        y = mesh.corners[mesh.surface == mesh.surface_names.index(f"box.{side}")].numpy()[:, :, 1]
        assert ((y >= 1.3 - TOLERANCE).all(axis=1) | (y <= 1.3 + TOLERANCE).all(axis=1)).all()
    # surfaces nothing crosses keep their grids
    plain = build_mesh(room_scene(shelf, box, intersections=False))
    for name in ("room.floor", "room.ceiling", "box.top", "box.bottom"):
        a, b = (m.surface_names.index(name) for m in (mesh, plain))
        assert torch.equal(mesh.corners[mesh.surface == a], plain.corners[plain.surface == b])


def test_two_boxes_into_each_other_keep_only_their_union_outline():
    first = Box((0.5, 0.5, 0.5), (1.5, 1.5, 1.5), "white", 0.25, name="first")
    second = Box((1.1, 0.7, 0.8), (2.0, 1.3, 1.2), "white", 0.25, name="second")  # off the first's grid
    assert straddling(build_mesh(room_scene(first, second, intersections=False)))
    mesh = build_mesh(room_scene(first, second))
    assert straddling(mesh) == []
    assert area_of(mesh, "first") == pytest.approx(6.0 - 0.6 * 0.4, rel=1e-9)  # less where the second enters
    # the second's part outside the first, x from 1.5 to 2
    assert area_of(mesh, "second") == pytest.approx(2 * 0.5 * 0.4 + 2 * 0.5 * 0.6 + 0.6 * 0.4, rel=1e-9)
    assert "second.x_min" not in mesh.surface_names  # wholly inside the first


def test_a_sphere_through_a_plane_is_cut_in_place(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.6)
    sphere.export(tmp_path / "sphere.ply")
    plane = {"type": "quad", "material": "white", "name": "plate",
             "corners": [[1.0, 1.2, 1.0], [1.0, 1.2, 3.0], [3.0, 1.2, 3.0], [3.0, 1.2, 1.0]]}
    scene = {"element_size": 0.25,
             "materials": {"white": {"reflectance": 0.5}, "lamp": {"reflectance": 0.0, "emission": 5.0}},
             "objects": [{"type": "room", "name": "room", "min": [0, 0, 0], "max": [4, 3, 4], "material": "white"},
                         {"type": "mesh", "name": "ball", "file": "sphere.ply", "material": "lamp",
                          "transform": {"translate": [2.0, 1.4, 2.0]}}, plane],
             "camera": {"position": [2, 1.5, -1], "look_at": [2, 1, 2]}}
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(scene))
    loaded = hemirad.load_scene(path)
    mesh = build_mesh(loaded)
    assert straddling(mesh) == []
    # the ball's triangles each lie on one side of the plate, and the ball keeps its area
    ball = mesh.corners[mesh.surface == mesh.surface_names.index("ball")].numpy()
    y = ball[:, :, 1]
    assert ((y >= 1.2 - 1e-7).all(axis=1) | (y <= 1.2 + 1e-7).all(axis=1)).all()
    loaded.meshing.intersections = False
    assert surface_area(mesh, "ball") == pytest.approx(surface_area(build_mesh(loaded), "ball"), rel=1e-9)
    # the plate loses the ball's section: a polygon inscribed in the circle of radius sqrt(0.6^2 - 0.2^2)
    section = np.pi * (0.6 ** 2 - 0.2 ** 2)
    lost = 4.0 - surface_area(mesh, "plate")
    assert 0.85 * section < lost < section
    centroids = mesh.centroids[mesh.surface == mesh.surface_names.index("plate")].numpy()
    assert (np.linalg.norm(centroids - [2.0, 1.4, 2.0], axis=1) > 0.5).all()
    # the ball's vertices are shared across the cut: no crack, no vertex left unused
    s = mesh.surface_names.index("ball")
    used = torch.unique(mesh.triangles[mesh.surface == s])
    positions = mesh.vertices[used].numpy()
    assert len(np.unique(positions.round(9), axis=0)) == len(positions)


# ----------------------------------------------------------------------------------------
# light


def escaped_share(scene: Scene) -> float:
    scene.solver.resolution, scene.solver.max_shots, scene.solver.unshot_fraction = 32, 40, 0.0
    stats = hemirad.solve(scene, progress=None).stats
    return float(np.sum(stats["escaped_power"]) / np.sum(stats["emitted_power"]))


def test_an_emitter_partly_inside_a_solid_loses_no_light_to_its_back_faces():
    """A lamp panel pushed through a closed box: the part inside shines on the box's back
    faces, and that light leaves a closed room. Cut, the part inside is gone, and nothing
    escapes."""
    def scene(intersections: bool) -> Scene:
        lamp = horizontal_quad(1.5, (1.0, 1.0), (3.0, 3.0), "lamp", "lamp", up=False)
        box = Box((1.5, 1.0, 1.5), (2.5, 2.0, 2.5), "white", 0.25, name="box")
        cut = room_scene(lamp, box, element_size=0.5, intersections=intersections)
        cut.meshing.contacts = False  # the box's sides close round the panel's part inside too
        return cut
    assert escaped_share(scene(False)) > 0.15  # a quarter of the panel is inside
    assert escaped_share(scene(True)) < 0.005


# ----------------------------------------------------------------------------------------
# solids


def quad_shell(corners) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(corners, dtype=np.float64), np.array([[0, 1, 2], [0, 2, 3]])


def box_shells(low, high, inward: bool = False):
    return [quad_shell(box_face_corners(torch.tensor(low, dtype=torch.float64), torch.tensor(high, dtype=torch.float64),
                                        face, inward).numpy())
            for face in ("floor", "ceiling", "x_min", "x_max", "z_min", "z_max")]


def test_which_surfaces_make_solids():
    box = box_shells((0, 0, 0), (1, 1, 1))
    room = box_shells((-5, -5, -5), (5, 5, 5), inward=True)
    solids = closed_solids(box + room, 1e-9)
    assert [sorted(s.members) for s in solids] == [list(range(6))]  # the room faces in: no solid
    assert closed_solids(box[:5], 1e-9) == []  # a box without its bottom does not close
    # a tube of quads closed by a mesh of its caps given in 32-bit floats is one solid
    ring = np.array([[np.cos(a), 0.0, np.sin(a)] for a in np.linspace(0, 2 * np.pi, 9)[:-1]])
    top = ring + [0, 1, 0]
    tube = [quad_shell([ring[i], top[i], top[(i + 1) % 8], ring[(i + 1) % 8]]) for i in range(8)]
    caps = np.concatenate([ring, top, [[0, 0, 0], [0, 1, 0]]]).astype(np.float32).astype(np.float64)
    fans = [[i, (i + 1) % 8, 16] for i in range(8)] + [[8 + (i + 1) % 8, 8 + i, 17] for i in range(8)]
    solids = closed_solids(tube + [(caps, np.array(fans))], 1e-6)
    assert len(solids) == 1 and solids[0].members == frozenset(range(9))
    inside = solids[0].contains(np.array([[0, 0.5, 0], [2, 0.5, 0], [1.0, 0.5, 0.0], [0, 1.0, 0]]), 1e-6)
    assert inside.tolist() == [True, False, False, False]  # on the surface counts as outside


def ell_prism():
    """(vertices, faces) of an L-shaped prism 1 high, faces outwards, triangulated by hand
    (trimesh's extrusion needs a triangulation engine the test environment need not have)."""
    outline = np.array([(0, 0), (2, 0), (2, 1), (1, 1), (1, 2), (0, 2)], dtype=np.float64)  # counter-clockwise
    n = len(outline)
    vertices = np.concatenate([np.c_[outline, np.zeros(n)], np.c_[outline, np.ones(n)]])
    cap = [(0, 1, 2), (0, 2, 3), (0, 3, 4), (0, 4, 5)]  # a fan from the corner that sees the whole L
    faces = [(a + n, b + n, c + n) for a, b, c in cap] + [(a, c, b) for a, b, c in cap]
    for a in range(n):
        b = (a + 1) % n
        faces += [(a, b, b + n), (a, b + n, a + n)]
    return vertices, np.asarray(faces, dtype=np.int64)


def test_what_a_solid_holds():
    """Inside a box, an L of two boxes (concave: a ray from its inner corner crosses it
    three times) and a sphere of 1,280 triangles; on the surface is outside."""
    box = closed_solids(box_shells((0, 0, 0), (1, 1, 1)), 1e-9)[0]
    points = np.array([[0.5, 0.5, 0.5], [0.01, 0.99, 0.5], [1.5, 0.5, 0.5], [-3, 7, 2], [1.0, 0.5, 0.5], [0, 0, 0]])
    assert box.contains(points, 1e-9).tolist() == [True, True, False, False, False, False]
    # an L: [0, 2] x [0, 1] and [0, 1] x [1, 2] in (x, y), from z = 0 to 1
    solid = closed_solids([ell_prism()], 1e-9)[0]
    points = np.array([[0.5, 1.5, 0.5], [1.5, 0.5, 0.5], [1.5, 1.5, 0.5], [1.2, 1.2, 0.5], [0.9, 1.1, 0.5]])
    assert solid.contains(points, 1e-9).tolist() == [True, True, False, False, True]
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    solid = closed_solids([(np.asarray(sphere.vertices), np.asarray(sphere.faces))], 1e-9)[0]
    rng = np.random.default_rng(1)
    points = rng.uniform(-1.2, 1.2, (4000, 3))
    radius = np.linalg.norm(points, axis=1)
    clear = np.abs(radius - 0.99) > 0.02  # the facets lie between radius 0.98 and 1
    held = solid.contains(points, 1e-9)
    assert (held[clear] == (radius[clear] < 0.99)).all()


# ----------------------------------------------------------------------------------------
# nothing to cut; the option


@pytest.mark.parametrize("name", ["cornell_box", "office"])
def test_a_scene_where_nothing_cuts_through_anything_is_meshed_as_before(name):
    scene = hemirad.load_scene(name)
    assert scene.meshing.intersections is True  # the default
    cut = build_mesh(scene)
    scene.meshing.intersections = False
    plain = build_mesh(scene)
    assert_same_mesh(cut, plain)


def test_the_order_of_the_objects_does_not_matter():
    shelf = horizontal_quad(1.3, (0.6, 0.6), (3.4, 3.4), "white", "shelf")
    box = Box((1.2, 0.5, 1.5), (2.7, 2.0, 2.6), "white", 0.25, name="box")
    one, other = build_mesh(room_scene(shelf, box)), build_mesh(room_scene(box, shelf))
    assert sorted(one.surface_names) == sorted(other.surface_names)
    for name in one.surface_names:
        assert surface_area(one, name) == pytest.approx(surface_area(other, name), rel=1e-12)


def test_the_scene_key():
    base = {"materials": {"lamp": {"reflectance": 0.0, "emission": 1.0}},
            "objects": [{"type": "quad", "material": "lamp", "element_size": 1.0,
                         "corners": [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]}],
            "camera": {"position": [0, 0, 3], "look_at": [0, 0, 0]}}
    assert parse_scene(base).meshing.intersections is True
    assert parse_scene({**base, "meshing": {"intersections": False}}).meshing.intersections is False
    with pytest.raises(SceneError, match=r"meshing\.intersections"):
        parse_scene({**base, "meshing": {"intersections": "off"}})
    with pytest.raises(SceneError, match="intersections"):
        parse_scene({**base, "meshing": {"intersection": True}})


def test_no_cut_leaves_a_needle(tmp_path):
    # A lamp's barrel (20 quads, corners to 5 decimals) pushed into its globe down to the
    # globe's centre, as in the furnished room whose barrels were cut into needles (a cut's
    # end within rounding of an edge, not on it: 5 units long, 6e-7 high) that a hemicube
    # pixel over-counts by orders of magnitude. Every triangle is now thicker than the cut's
    # tolerance; before, this globe left one needle, the room's own 64.
    globe = trimesh.creation.icosphere(subdivisions=2, radius=2.5)
    globe.vertices = np.round(globe.vertices + [-5.0, 5.0, 5.0], 5)
    globe.export(tmp_path / "globe.ply")
    angle = np.linspace(0.0, 2 * np.pi, 21)
    rim = np.round(np.stack([-5 + 1.25 * np.cos(angle), 5 + 1.25 * np.sin(angle)], 1), 5).tolist()
    barrel = [{"type": "quad", "material": "white", "name": f"barrel.q{k}",
               "corners": [[x0, 10.0, z0], [x0, 5.0, z0], [x1, 5.0, z1], [x1, 10.0, z1]]}
              for k, ((x1, z1), (x0, z0)) in enumerate(zip(rim[:-1], rim[1:]))]
    scene = {"element_size": 1.0,
             "materials": {"white": {"reflectance": 0.5}, "lamp": {"reflectance": 0.0, "emission": 5.0}},
             "objects": [{"type": "room", "name": "room", "min": [-9, 0, 0], "max": [-1, 11, 10], "material": "white"},
                         {"type": "mesh", "name": "globe", "file": "globe.ply", "material": "lamp"}, *barrel],
             "camera": {"position": [-5, 5, 0.5], "look_at": [-5, 5, 5]}}
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(scene))
    mesh = build_mesh(hemirad.load_scene(path))
    edges = mesh.corners - mesh.corners.roll(1, dims=1)
    height = 2 * mesh.areas / edges.norm(dim=2).amax(1)
    assert float(height.min()) > 1e-6 * 11.0  # CONTACT_TOLERANCE times the scene's size
    assert sum(name.startswith("barrel") for name in mesh.surface_names) == 20
