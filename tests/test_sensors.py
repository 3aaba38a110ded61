"""Sensors: irradiance at points by a final gather, against closed forms; sensor files and
``sensors.csv`` through the command."""
import csv
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import hemirad
from hemirad.cli import main
from hemirad.core.colour import REC709_LUMINANCE
from hemirad.geometry.analytic import point_to_polygon, point_to_triangles
from hemirad.geometry.mesh import Mesh
from hemirad.lighting import sensors
from hemirad.lighting.sensors import final_gather, irradiance_at
from hemirad.scene.loader import parse_scene
from hemirad.scene.meshing import box_face_corners, grid_quad
from hemirad.scene.sensorfile import read_sensor_file
from hemirad.transport.formfactor import delta_form_factors, hemicube_directions

SMALL_ROOM = Path(__file__).parent / "data" / "small_room.yaml"

# A 1 x 0.6 lamp at y = 1 facing down (corners counter-clockwise seen from below), meshed
# into 0.25 cells: alone in the scene, so its hemicube factor is Lambert's, unoccluded.
LAMP = torch.tensor([[-0.5, 1.0, -0.3], [0.5, 1.0, -0.3], [0.5, 1.0, 0.3], [-0.5, 1.0, 0.3]], dtype=torch.float64)
LAMP_RADIOSITY = torch.tensor([2.0, 3.0, 5.0], dtype=torch.float64)


def quads_mesh(quads: list[torch.Tensor], size: float) -> Mesh:
    """One surface per quad (4, 3), gridded at ``size``."""
    parts = []
    for q in quads:
        v, t = grid_quad(q, size)
        parts.append(Mesh(v, t, torch.zeros(len(t)), torch.zeros(len(t)), ["quad"]))
    return Mesh.concatenate(parts)


def room_mesh(lo=(0.0, 0.0, 0.0), hi=(2.0, 1.5, 1.0), size: float = 0.25) -> tuple[Mesh, list[str]]:
    """A closed room facing inward, its faces in ``Room.FACE_NAMES`` order."""
    faces = ("floor", "ceiling", "x_min", "x_max", "z_min", "z_max")
    return quads_mesh([box_face_corners(lo, hi, f, inward=True) for f in faces], size), list(faces)


def rotation(axis, degrees: float) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = math.radians(degrees)
    return np.eye(3) + math.sin(t) * k + (1 - math.cos(t)) * k @ k


def lambert(mesh: Mesh, point, normal) -> float:
    """The unoccluded factor from a point to all of ``mesh``, each triangle clipped to the
    point's upper half-space (Lambert's formula, summed)."""
    return float(point_to_triangles(torch.tensor(point, dtype=torch.float64),
                                    torch.tensor(normal, dtype=torch.float64), mesh.corners).sum())


# ----------------------------------------------------------------------------------------
# against closed forms

OFFSETS = [(0.0, 0.5, 0.0), (0.2, 0.3, 0.1), (0.3, 0.0, 0.2), (1.0, 0.2, -0.5), (0.0, -1.0, 0.0),
           (0.45, 0.8, 0.25), (1.2, -0.4, 0.7)]
TILTS = [((1, 0, 0), 0.0), ((1, 0, 0), 30.0), ((0, 0, 1), -45.0), ((1, 0, 1), 60.0), ((0, 0, 1), 80.0)]


def test_a_sensor_under_a_lamp_reads_lamberts_closed_form_within_half_a_percent():
    """Points at offsets from 0.2 to 2 below the lamp and beside it, tilted up to 80
    degrees (the lamp partly behind some of them: the closed form is clipped to the
    point's half-space too), most outside the lamp's bounding box, which is flat: the
    clip planes must reach them."""
    mesh = quads_mesh([LAMP], 0.25)
    radiosity = LAMP_RADIOSITY.expand(mesh.num_elements, 3)
    points = np.array([offset for offset in OFFSETS for _ in TILTS], dtype=np.float64)
    normals = np.array([rotation(axis, angle) @ [0.0, 1.0, 0.0] for _ in OFFSETS for axis, angle in TILTS])
    measured = irradiance_at(mesh, radiosity, points, normals, resolution=256)
    errors = []
    for point, normal, e in zip(points, normals, measured):
        factor = lambert(mesh, point, normal)
        assert factor > 1e-3  # each configuration sees a fair part of the lamp
        errors.append(float(((e / (factor * LAMP_RADIOSITY)) - 1).abs().max()))
    assert max(errors) < 0.005, f"worst {max(errors):.4%} at {points[int(np.argmax(errors))]}"
    assert np.mean(errors) < 0.001  # 0.05% measured


def test_the_remaining_error_is_the_lamps_outline_rounded_to_pixel_centres(monkeypatch):
    """Straight under the lamp, 2 away, with the hemicube's rows along the lamp's edges (the
    frame's x along the lamp's x): the lamp spans x in +-0.25 and y in +-0.15 of the top
    face, 32 x 19.2 pixels a side at R = 256. A pixel counts whole where its centre is
    inside, so 19 rows count of 19.2: the hemicube gives exactly the delta form factors of
    the pixels whose centres fall inside, 1% short of Lambert, and as much at R = 512
    (38 rows of 38.4: the edge falls at the same fraction of a pixel). Turned off the
    axes (the default frame), the edges cross the rows, the roundings cancel along them,
    and the same point is within 0.1%."""
    mesh = quads_mesh([LAMP], 0.25)
    radiosity = torch.ones(mesh.num_elements, 3, dtype=torch.float64)
    point, normal = np.array([[0.0, -1.0, 0.0]]), np.array([[0.0, 1.0, 0.0]])
    exact = lambert(mesh, point[0], normal[0])

    def hemicube(resolution: int) -> float:
        return float(irradiance_at(mesh, radiosity, point, normal, resolution)[0, 0])

    def centres_inside(resolution: int) -> float:
        d = hemicube_directions(resolution)[:resolution]  # the top face: (x, y, 1)
        inside = (d[..., 0].abs() < 0.25) & (d[..., 1].abs() < 0.15)
        return float(delta_form_factors(resolution)[:resolution][inside].sum())

    turned = hemicube(256)
    monkeypatch.setattr(sensors, "OFF_AXIS_TANGENT", np.array([1.0, 0.0, 0.0]))
    for resolution in (256, 512):
        along = hemicube(resolution)
        assert along == pytest.approx(centres_inside(resolution), rel=1e-9)
        assert along / exact - 1 == pytest.approx(-0.2 / 19.2, rel=0.05)
    assert abs(turned / exact - 1) < 0.001


def test_in_a_uniformly_bright_closed_room_every_sensor_reads_that_radiosity():
    """Every pixel sees some wall's front, and the delta form factors sum to 1: E = B
    exactly, in mid-air, lying on a wall, in a corner, facing any way."""
    mesh, _ = room_mesh()
    radiosity = torch.tensor([1.5, 2.0, 0.25], dtype=torch.float64).expand(mesh.num_elements, 3)
    points = [(1.0, 0.75, 0.5), (0.3, 1.2, 0.8), (1.0, 0.0, 0.5), (0.0, 0.7, 0.3), (1.99, 0.01, 0.99)]
    normals = [(0, 1, 0), (0.3, -0.2, 0.9), (0, 1, 0), (1, 0, 0), (-1, 1, -1)]
    gather = final_gather(mesh, radiosity, points, normals, resolution=64)
    torch.testing.assert_close(gather.irradiance, radiosity[:len(points)], rtol=1e-12, atol=0)
    torch.testing.assert_close(gather.coverage, torch.ones(len(points), dtype=torch.float64), rtol=1e-12, atol=0)


def test_a_sensor_measures_only_the_side_its_normal_faces():
    """Only the floor is bright. In mid-air, facing up, a sensor reads nothing; facing down,
    the floor's closed form. Lying on the floor facing up it reads nothing (the floor is
    below its horizon, not seen through); on the ceiling facing down, the floor's factor."""
    mesh, faces = room_mesh(size=0.2)
    radiosity = torch.zeros(mesh.num_elements, 3, dtype=torch.float64)
    radiosity[mesh.surface == faces.index("floor")] = 1.0
    floor = box_face_corners((0.0, 0.0, 0.0), (2.0, 1.5, 1.0), "floor", inward=True)
    cases = [((1.0, 0.6, 0.5), (0, 1, 0), 0.0), ((1.0, 0.6, 0.5), (0, -1, 0), None),
             ((0.7, 0.0, 0.4), (0, 1, 0), 0.0), ((0.7, 1.5, 0.4), (0, -1, 0), None),
             ((1.3, 0.9, 0.2), (0.3, -1, 0.2), None)]
    points, normals = [c[0] for c in cases], [c[1] for c in cases]
    measured = irradiance_at(mesh, radiosity, points, normals)[:, 0]
    for (point, normal, expected), e in zip(cases, measured.tolist()):
        if expected is not None:
            assert e == expected, (point, normal)
        else:
            n = torch.tensor(normal, dtype=torch.float64)
            exact = float(point_to_polygon(torch.tensor(point, dtype=torch.float64), n / n.norm(), floor))
            assert e == pytest.approx(exact, rel=0.005), (point, normal)


def test_coverage_tells_outside_and_inside_from_in_the_open():
    """A point outside a closed box looking away sees nothing (coverage 0); inside the box
    it sees fronts all round; inside a box seen from outside (outward faces) it sees only
    back faces: coverage 1, front coverage 0, irradiance 0."""
    room, _ = room_mesh()  # inward faces
    faces = ("floor", "ceiling", "x_min", "x_max", "z_min", "z_max")
    box = quads_mesh([box_face_corners((3.0, 0.0, 0.0), (3.5, 0.5, 0.5), f, inward=False) for f in faces], 0.25)
    mesh = Mesh.concatenate([room, box])
    radiosity = torch.ones(mesh.num_elements, 3, dtype=torch.float64)
    gather = final_gather(mesh, radiosity, [(-1.0, 0.5, 0.5), (1.0, 0.5, 0.5), (3.25, 0.25, 0.25)],
                          [(-1, 0, 0), (0, 1, 0), (0, 1, 0)], resolution=32)
    assert gather.coverage.tolist() == pytest.approx([0.0, 1.0, 1.0], abs=1e-12)
    assert gather.front_coverage.tolist() == pytest.approx([0.0, 1.0, 0.0], abs=1e-12)
    assert gather.irradiance[[0, 2]].abs().max() == 0


def test_points_gathered_together_read_what_each_reads_alone():
    """``final_gather`` draws the next point's hemicube while it sums one: every point still
    reads its own view, bit for bit, repeated and neighbouring points included."""
    mesh, faces = room_mesh(size=0.2)
    radiosity = torch.rand(mesh.num_elements, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    points = [(1.0, 0.6, 0.5), (1.0, 0.6, 0.5), (0.3, 1.2, 0.8), (0.7, 0.0, 0.4), (1.0, 0.6, 0.5), (0.31, 1.2, 0.8)]
    normals = [(0, 1, 0), (0, 1, 0), (0.3, -0.2, 0.9), (0, 1, 0), (0, -1, 0), (0.3, -0.2, 0.9)]
    together = final_gather(mesh, radiosity, points, normals, resolution=32)
    alone = [final_gather(mesh, radiosity, [p], [n], resolution=32) for p, n in zip(points, normals)]
    for name in ("irradiance", "coverage", "front_coverage"):
        assert torch.equal(getattr(together, name), torch.cat([getattr(a, name) for a in alone])), name
    assert not torch.equal(together.irradiance[0], together.irradiance[4])  # the views differ


def test_a_sensor_needs_a_normal():
    mesh = quads_mesh([LAMP], 0.5)
    with pytest.raises(ValueError, match="non-zero normal"):
        irradiance_at(mesh, torch.ones(mesh.num_elements, 3), [(0, 0, 0)], [(0, 0, 0)])


# ----------------------------------------------------------------------------------------
# a solved scene

FURNACE = """
materials:
  glow: {reflectance: 0.5, emission: 1.0}
objects:
  - {type: room, min: [0, 0, 0], max: [2, 1.5, 1], material: glow, element_size: 0.25}
camera: {position: [1, 0.7, 0.1], look_at: [1, 0.7, 1], width: 16, height: 12, supersample: 1}
solver: {resolution: 32, unshot_fraction: 1.0e-6}
sensors:
  - {position: [1, 0.75, 0.5], normal: [0, 1, 0], name: middle}
  - {position: [0.2, 0, 0.3], normal: [0.2, 1, -0.3]}
  - {position: [2, 1.2, 0.5], normal: [-1, 0, 0], name: on a wall}
"""


def test_in_a_glowing_closed_room_sensors_read_e_over_one_minus_rho():
    """Every surface emits 1 and reflects half: radiosity is 1 / (1 - 0.5) = 2 everywhere,
    and so is the irradiance at any sensor, whatever way it faces (within the solve's own
    per-element accuracy at hemicube 32, 1%: 0.24% measured); the helper for other points
    gives the same numbers as the scene's sensors."""
    import yaml

    scene = parse_scene(yaml.safe_load(FURNACE))
    result = hemirad.solve(scene)
    readings = result.sensors
    assert readings.names == ["middle", "sensor1", "on a wall"]
    torch.testing.assert_close(readings.irradiance, torch.full((3, 3), 2.0, dtype=torch.float64), rtol=0.01, atol=0)
    assert readings.lux.tolist() == pytest.approx((683 * readings.irradiance[:, 0]).tolist(), rel=1e-12)  # grey light
    again = result.irradiance_at(readings.points, readings.normals)
    torch.testing.assert_close(again, readings.irradiance, rtol=0, atol=0)
    assert result.stats["sensors"] == 3 and result.stats["units"] == "radiometric"


# ----------------------------------------------------------------------------------------
# sensor files


def test_a_sensor_file_with_a_header_comments_and_names(tmp_path):
    path = tmp_path / "s.csv"
    path.write_text("\ufeff# desks\nx, y, z, nx, ny, nz, name\n\n1, 0.75, 2.5, 0, 1, 0, desk A  # by the window\n"
                    "2,0.75,2.5,0,2,0\n-1e-3,1,1,1,0,0,\"wall, left\"\n", encoding="utf-8")
    read = read_sensor_file(path, {"sensor0"}, first_index=3)
    assert [s.name for s in read] == ["desk A", "sensor4", "wall, left"]
    assert read[0].position == (1.0, 0.75, 2.5) and read[1].normal == (0.0, 2.0, 0.0)
    assert read[2].position == (-1e-3, 1.0, 1.0)


BAD_FILES = [
    ("1,2,3,0,1\n", "line 1", "got 5"),
    ("x,y,z,nx,ny,nz\n1,2,3,0,1,0\n1,2,3,0,1,0,a,b\n", "line 3", "got 8"),
    ("# c\n1,2,3,0,1,0\n1,two,3,0,1,0\n", "line 3", "for y (column 2)"),
    ("1,2,3,0,0,0,flat\n", "line 1", "non-zero normal"),
    ("1,nan,3,0,1,0\n", "line 1", "finite number"),
    ("1,2,3,0,1,0,a\n4,5,6,0,1,0,a\n", "line 2", "no other sensor"),
    ("# nothing\n\n", "holds no sensor", ""),
    ("1e16,0,0,0,1,0\n", "line 1", "within +-1e+15"),
]


@pytest.mark.parametrize("text, where, says", BAD_FILES)
def test_a_bad_sensor_file_is_one_paragraph_naming_the_line(tmp_path, capsys, text, where, says):
    path = tmp_path / "sensors.csv"
    path.write_text(text)
    code = main([str(SMALL_ROOM), "-o", str(tmp_path / "out"), "--sensors", str(path), "-q"])
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert err.startswith("hemirad: error: ") and "\n" not in err and "Traceback" not in err
    assert str(path) in err and where in err and says in err
    assert not (tmp_path / "out" / "stats.json").exists()


def test_a_missing_sensor_file(tmp_path, capsys):
    assert main([str(SMALL_ROOM), "-o", str(tmp_path / "out"), "--sensors", str(tmp_path / "none.csv")]) == 2
    err = capsys.readouterr().err
    assert f"the sensor file {tmp_path / 'none.csv'} does not exist" in err


# ----------------------------------------------------------------------------------------
# sensors.csv


def test_the_command_writes_sensors_csv(tmp_path, capsys):
    """Radiometric scene: lux = 683 x the Rec. 709 luminance of E; the sensors are printed,
    and not in quiet mode."""
    path = tmp_path / "s.csv"
    path.write_text("x,y,z,nx,ny,nz,name\n1.0,0.0,1.6,0,1,0,floor\n1,1.2,1,0,-1,0,under lamp facing down\n"
                    "1.0,0.75,1.0,0,1,0\n")
    out = tmp_path / "out"
    assert main([str(SMALL_ROOM), "-o", str(out), "--sensors", str(path), "--shots", "400"]) == 0
    err = capsys.readouterr().err
    with open(out / "sensors.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["name", "x", "y", "z", "nx", "ny", "nz", "E_r", "E_g", "E_b", "E", "lux"]
    assert [r["name"] for r in rows] == ["floor", "under lamp facing down", "sensor2"]
    for r in rows:
        e = [float(r[k]) for k in ("E_r", "E_g", "E_b")]
        luminance = sum(w * x for w, x in zip(REC709_LUMINANCE, e))
        assert float(r["E"]) == pytest.approx(luminance, rel=1e-12)
        assert float(r["lux"]) == pytest.approx(683.0 * luminance, rel=1e-12)
        assert f"{r['name']}" in err
    # facing down under the lamp it sees no lamp, only the dimmer floor: less than facing up
    assert float(rows[1]["E"]) < float(rows[2]["E"])
    assert float(rows[0]["nx"]) == 0 and float(rows[0]["ny"]) == 1.0

    assert main([str(SMALL_ROOM), "-o", str(tmp_path / "quiet"), "--sensors", str(path), "--shots", "5", "-q"]) == 0
    assert capsys.readouterr().err == ""
    assert (tmp_path / "quiet" / "sensors.csv").exists()
