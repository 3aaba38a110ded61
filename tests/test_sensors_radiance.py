"""Sensor irradiance against RADIANCE's ``rtrace -I``, and the reference data themselves.

The references in ``tests/references/radiance_<scene>.json`` were made by
``scripts/make_radiance_references.py`` (RADIANCE through pyradiance: the scene's own
triangles, unbiased settings, 32 independent evaluations per point); these tests need no
RADIANCE, except the one that checks the translation, skipped without pyradiance.

RADIANCE's ``light`` does not reflect, hemirad's emitters do: the Cornell box's light has
reflectance 0.78, and the light it reflects raises the whole box by about 0.85%
(measured by the script's ``--gather``). The comparison solves the scenes as RADIANCE saw
them, emitters not reflecting; the office's lamp reflects nothing anyway.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import hemirad
from hemirad.evaluation import irradiance_reference as ir
from hemirad.evaluation.metrics import luminance
from hemirad.evaluation.reference import geometry_summary
from hemirad.geometry.analytic import point_to_polygon
from hemirad.scene.meshing import build_mesh
from hemirad.scene.model import Camera, Material, Quad, Scene

REFERENCES = Path(__file__).resolve().parent / "references"
SCENES = ("cornell_box", "office")
#: The issue's tolerance: every point, luminance and each channel.
TOLERANCE = 0.02


@pytest.mark.parametrize("name", SCENES)
def test_reference_files_are_well_formed(name):
    reference = ir.IrradianceReference.load(REFERENCES, name)
    n = len(reference.names)
    assert n >= 12 and len(set(reference.names)) == n
    for array in (reference.points, reference.normals, reference.irradiance, reference.direct,
                  reference.standard_error):
        assert array.shape == (n, 3) and np.isfinite(array).all()
    np.testing.assert_allclose(np.linalg.norm(reference.normals, axis=1), 1.0, atol=1e-8)
    assert (reference.irradiance > 0).all(), "every point must see some light in every channel"
    assert (reference.direct >= 0).all() and (reference.standard_error > 0).all()
    # Indirect light only adds: the total is at least the direct part, beyond the noise.
    assert (reference.irradiance + 4 * reference.standard_error >= reference.direct).all()
    # The reference's own noise is far below the tolerance it is used with.
    assert (reference.standard_error / reference.irradiance).max() < TOLERANCE / 4
    info = reference.info
    assert info["scene"] == name and info["repeats"] >= 8
    assert info["renderer"]["radiance"].startswith("RADIANCE")
    options = info["renderer"]["options"].split()
    for flag in ("-ab", "-aa", "-ad", "-lw", "-lr", "-ds", "-u+"):
        assert flag in options, f"setting {flag} not recorded"
    assert options[options.index("-aa") + 1] == "0", "the irradiance cache must be off (no interpolation bias)"
    assert int(options[options.index("-ab") + 1]) >= 10
    assert info["renderer"]["direct_options"].split()[:2] == ["-ab", "0"]
    # Made from the scene as it is now: same triangles, area, materials and camera.
    scene = hemirad.load_scene(name)
    assert info["geometry"] == geometry_summary(scene), "the scene changed since the reference was made"


def test_direct_light_at_the_cornell_floor_matches_lamberts_closed_form():
    """RADIANCE's -ab 0 value at an open floor point, which sees the whole light, is the
    light's emission times Lambert's point-to-polygon form factor, per channel."""
    reference = ir.IrradianceReference.load(REFERENCES, "cornell_box")
    i = reference.names.index("floor_open")
    point, normal = torch.tensor(reference.points[i]), torch.tensor(reference.normals[i])
    assert float(normal[1]) == pytest.approx(1.0) and float(point[1]) < 0.2  # on the floor, facing up
    scene = hemirad.load_scene("cornell_box")
    light = next(o for o in scene.objects if o.name == "light")
    emission = next(m for m in scene.materials if m.name == "light").emission
    form_factor = float(point_to_polygon(point, normal, torch.tensor(light.corners, dtype=torch.float64)))
    assert 0.01 < form_factor < 0.02  # 130 x 105 mm at 548 mm: about 0.0117
    expected = form_factor * np.array(emission)
    np.testing.assert_allclose(reference.direct[i], expected, rtol=2e-3)


def test_radiance_scene_translates_materials_and_triangles():
    scene = Scene(
        materials=[Material("grey", (0.5, 0.25, 0.125)), Material("lamp", (0.7, 0.7, 0.7), (math.pi, 2 * math.pi, 0.0))],
        objects=[Quad(name="floor", material="grey", element_size=1.0,
                      corners=((1, 0, -1), (-1, 0, -1), (-1, 0, 1), (1, 0, 1))),
                 Quad(name="lamp", material="lamp", element_size=2.0,
                      corners=((1, 1, -1), (1, 1, 1), (-1, 1, 1), (-1, 1, -1)))],
        camera=Camera(position=(0, 0.5, -3), look_at=(0, 0.5, 0)))
    mesh = build_mesh(scene)
    words = ir.radiance_scene(scene, mesh, emitter_splits=1).split()
    assert "void plastic m0 0 0 5 0.5 0.25 0.125 0 0" in " ".join(words)
    assert "void light m1 0 0 3 1 2 0" in " ".join(words)  # radiance = exitance / pi
    lamp = int((mesh.material == 1).sum())
    pieces = 4  # one split
    assert words.count("polygon") == mesh.num_elements - lamp + pieces * lamp
    assert words.count("m1") == 1 + pieces * lamp
    # The first polygon is the first triangle, corners in the same (counter-clockwise) order.
    first = words.index("polygon")
    assert words[first - 1] == f"m{int(mesh.material[0])}"
    numbers = np.array([float(x) for x in words[first + 5:first + 14]]).reshape(3, 3)
    np.testing.assert_allclose(numbers, mesh.corners[0].numpy())


def test_split_triangles_keep_area_normal_and_surface():
    triangle = np.array([[[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.5, 1.5, 0.3]]])
    pieces = ir.split_triangles(triangle, 2)
    assert pieces.shape == (16, 3, 3)

    def cross(t):
        return np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    whole = cross(triangle)[0]
    np.testing.assert_allclose(cross(pieces), np.tile(whole / 16, (16, 1)), atol=1e-12)  # same area, same facing
    # every corner lies in the parent (barycentric coordinates in [0, 1])
    basis = np.stack([triangle[0, 1] - triangle[0, 0], triangle[0, 2] - triangle[0, 0]], axis=1)
    coords = np.linalg.lstsq(basis, (pieces.reshape(-1, 3) - triangle[0, 0]).T, rcond=None)[0]
    assert (coords > -1e-12).all() and (coords.sum(axis=0) < 1 + 1e-12).all()


def test_rtrace_gives_lamberts_closed_form_for_an_open_square_light():
    """Needs pyradiance: the translation and rtrace's units (-I is irradiance), against the
    closed form at three tilted sensors under a 2 x 2 square light one unit up and closer
    (nothing else to see). Its elements are 0.125, each a RADIANCE source, whose bias is
    about 0.05% here; as one source the whole square is 1.3% too bright under its centre
    and 6.8% at the second sensor."""
    pytest.importorskip("pyradiance")
    corners = ((1, 1, -1), (1, 1, 1), (-1, 1, 1), (-1, 1, -1))  # faces down
    scene = Scene(materials=[Material("lamp", (0.0, 0.0, 0.0), (10.0, 20.0, 5.0))],
                  objects=[Quad(name="lamp", material="lamp", element_size=0.125, corners=corners)],
                  camera=Camera(position=(0, 0.5, -3), look_at=(0, 0.5, 0)))
    mesh = build_mesh(scene)
    # (the light lies wholly above each sensor's plane, as Lambert's formula needs)
    points = np.array([[0.0, 0.0, 0.0], [0.5, 0.2, -0.3], [0.1, 0.5, 0.2]])
    normals = np.array([[0.0, 1.0, 0.0], [0.3, 1.0, 0.1], [-0.1, 1.0, 0.1]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    values = ir.rtrace_irradiance(scene, mesh, points, normals, ir.RTRACE_DIRECT_OPTIONS, repeats=2).mean(axis=0)
    polygon = torch.tensor(corners, dtype=torch.float64)
    for point, normal, value in zip(points, normals, values):
        F = float(point_to_polygon(torch.tensor(point), torch.tensor(normal), polygon))
        np.testing.assert_allclose(value, F * np.array([10.0, 20.0, 5.0]), rtol=2e-3)


def solved_as_radiance_sees_it(name: str):
    """The scene converged to 1e-4 unshot, its emitters not reflecting (as RADIANCE's
    ``light``), on its own mesh and hemicube."""
    scene = hemirad.load_scene(name)
    scene.solver.unshot_fraction = 1e-4
    scene.materials = [dataclasses.replace(m, reflectance=(0.0, 0.0, 0.0)) if max(m.emission) > 0 else m
                       for m in scene.materials]
    return hemirad.solve(scene)


def office_lamp_direct(point, normal, samples=(1200, 600)) -> float:
    """The office lamp's direct irradiance at ``point`` (grey: its emission is grey), by
    quadrature over the lamp (``samples`` cells), each cell's ray tested against every box of
    the scene: independent of hemicubes and of RADIANCE's source sampling."""
    scene = hemirad.load_scene("office")
    lamp = next(o for o in scene.objects if o.name == "lamp")
    emission = next(m for m in scene.materials if m.name == lamp.material).emission[0]
    c = np.asarray(lamp.corners, dtype=np.float64)
    a = (np.arange(samples[0]) + 0.5) / samples[0]
    b = (np.arange(samples[1]) + 0.5) / samples[1]
    A, B = np.meshgrid(a, b)
    u, v = c[1] - c[0], c[3] - c[0]
    cells = c[0] + A.reshape(-1, 1) * u + B.reshape(-1, 1) * v  # (n, 3)
    lamp_normal = np.cross(u, v) / np.linalg.norm(np.cross(u, v))
    d = cells - np.asarray(point)
    r2 = (d * d).sum(1)
    cos_here = np.clip(d @ np.asarray(normal), 0, None) / np.sqrt(r2)
    cos_there = np.clip(-(d @ lamp_normal), 0, None) / np.sqrt(r2)
    weight = cos_here * cos_there / (np.pi * r2) * np.linalg.norm(np.cross(u, v)) / len(cells)
    seen = np.ones(len(cells), dtype=bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        for box in (o for o in scene.objects if type(o).__name__ == "Box"):
            t0, t1 = (np.asarray(box.min) - point) / d, (np.asarray(box.max) - point) / d
            near = np.nanmax(np.minimum(t0, t1), axis=1)
            far = np.nanmin(np.maximum(t0, t1), axis=1)
            seen &= ~((far >= np.maximum(near, 0.0)) & (near <= 1.0))
    return float(emission * (weight * seen).sum())


#: Points whose RADIANCE direct light is wrong, by this much (see the test below): there the
#: comparison takes RADIANCE's indirect light plus the lamp's direct light by quadrature.
DIRECT_OFF = {("office", "floor_by_chair"): 0.05}


def test_the_office_reference_overestimates_the_lamp_beside_the_chair():
    # At floor_by_chair the chair's back hides the far 40% of the lamp. RADIANCE's direct
    # light there (-ab 0, every source shadow-tested) is 5% above the lamp's visible part
    # integrated cell by cell, while hemirad's gather of the lamp alone is within 0.5% of it.
    from hemirad.lighting.sensors import irradiance_at

    reference = ir.IrradianceReference.load(REFERENCES, "office")
    i = reference.names.index("floor_by_chair")
    point, normal = reference.points[i], reference.normals[i]
    exact = office_lamp_direct(point, normal)
    assert exact == pytest.approx(office_lamp_direct(point, normal, (600, 300)), rel=2e-3)  # converged
    assert reference.direct[i][0] / exact - 1 > 0.04
    scene = hemirad.load_scene("office")
    mesh = build_mesh(scene)
    emission = scene.emission_table()[mesh.material]  # the lamp alone, as its own radiosity
    ours = irradiance_at(mesh, emission, torch.tensor(point[None]), torch.tensor(normal[None]))
    assert float(ours[0, 0]) == pytest.approx(exact, rel=5e-3)


def expected_irradiance(name: str, reference) -> np.ndarray:
    """(N, 3) what each point should read: RADIANCE's, but at the points of ``DIRECT_OFF``
    its indirect light plus the direct light by quadrature."""
    expected = np.array(reference.irradiance, dtype=np.float64)
    for (scene, point_name), _ in DIRECT_OFF.items():
        if scene == name:
            i = reference.names.index(point_name)
            expected[i] += office_lamp_direct(reference.points[i], reference.normals[i]) - reference.direct[i]
    return expected


@pytest.mark.parametrize("name", SCENES)
def test_sensor_irradiance_matches_radiance(name):
    from hemirad.lighting.sensors import irradiance_at

    reference = ir.IrradianceReference.load(REFERENCES, name)
    result = solved_as_radiance_sees_it(name)
    ours = np.asarray(irradiance_at(result.mesh, result.display_radiosity, torch.tensor(reference.points),
                                    torch.tensor(reference.normals), resolution=256), dtype=np.float64)
    assert ours.shape == reference.irradiance.shape
    failures = []
    for point_name, mine, theirs, noise in zip(reference.names, ours, expected_irradiance(name, reference),
                                               reference.standard_error):
        lum = luminance(mine) / luminance(theirs) - 1
        channel = mine / theirs - 1
        if abs(lum) > TOLERANCE or (np.abs(channel) > TOLERANCE).any():
            failures.append(f"{point_name}: luminance {100 * lum:+.2f}%, RGB "
                            f"{', '.join(f'{100 * c:+.2f}%' for c in channel)} "
                            f"(ours {mine.round(5).tolist()}, RADIANCE {theirs.round(5).tolist()} "
                            f"+- {(100 * noise / theirs).round(2).tolist()}%)")
    assert not failures, f"{name}: sensors more than {TOLERANCE:.0%} off RADIANCE at:\n" + "\n".join(failures)
