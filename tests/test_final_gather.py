"""The solution finished by final gathers (``solver.final_gather``, ``lighting.gathered``)."""
import numpy as np
import pytest
import torch
import yaml

import hemirad
from hemirad.geometry.split import split_triangles
from hemirad.lighting import gathered as gathered_module
from hemirad.lighting.gathered import CONTACT_BAND, GatherReport, contact_band, gathered_radiosity
from hemirad.scene.loader import parse_scene
from hemirad.scene.meshing import build_mesh
from test_contacts import CORNELL_FOOTPRINTS, CORNELL_LIGHT, _distance_to_outline
from test_gathered_error import exact, lamp_over_floor


def test_a_gathered_element_reads_the_closed_form_at_its_centroid():
    """Under a square lamp, every floor element gathers rho E F(centroid -> lamp) (Lambert's
    closed form) to 1%, where its shot value, the mean over its extent, is farther off."""
    scene = lamp_over_floor(0.25, samples=0)
    shot = hemirad.solve(scene)
    scene.solver.final_gather = "all"
    gathered = hemirad.solve(scene)
    mesh = gathered.mesh
    floor = torch.nonzero(mesh.surface == mesh.surface_names.index("floor")).flatten()
    truth = exact(mesh.centroids[floor])
    error = gathered.radiosity[floor, 0] / truth - 1
    assert float(error.abs().max()) < 0.01
    assert float((shot.radiosity[floor, 0] / truth - 1).abs().max()) > 3 * float(error.abs().max())
    lamp = mesh.surface == mesh.surface_names.index("lamp")
    assert torch.equal(gathered.radiosity[lamp], shot.radiosity[lamp])  # reflectance 0: its emission
    assert gathered.stats["final_gather"]["elements"] == mesh.num_elements
    assert gathered.stats["absorbed_power"] == shot.stats["absorbed_power"]  # the shots' bookkeeping


def test_the_exact_solution_of_a_glowing_closed_room_is_its_own_gather():
    """Every wall emits E and reflects rho: B = E / (1 - rho) everywhere, which a gather over
    the closed room returns (its hemicube's factors sum to 1)."""
    scene = parse_scene(yaml.safe_load("""
materials:
  glow: {reflectance: 0.5, emission: 1.0}
objects:
  - {name: room, type: room, min: [0, 0, 0], max: [2, 1.5, 1], material: glow, element_size: 0.5}
camera: {position: [1, 0.75, 0.1], look_at: [1, 0.75, 1]}
"""))
    mesh = build_mesh(scene)
    count = mesh.num_elements
    exact_radiosity = torch.full((count, 3), 2.0, dtype=torch.float64)
    gathered = gathered_radiosity(mesh, exact_radiosity, torch.ones(count, 3, dtype=torch.float64),
                                  torch.full((count, 3), 0.5, dtype=torch.float64), torch.zeros(3, dtype=torch.float64),
                                  torch.arange(count), 128)
    assert torch.allclose(gathered, exact_radiosity, rtol=2e-3)
    half = torch.arange(0, count, 2)  # only those named change
    partly = gathered_radiosity(mesh, exact_radiosity * 1.5, torch.ones(count, 3, dtype=torch.float64),
                                torch.full((count, 3), 0.5, dtype=torch.float64), torch.zeros(3, dtype=torch.float64),
                                half, 128)
    assert torch.allclose(partly[half], torch.full((len(half), 3), 2.5, dtype=torch.float64), rtol=2e-3)
    rest = torch.ones(count, dtype=torch.bool)
    rest[half] = False
    assert torch.equal(partly[rest], exact_radiosity[rest] * 1.5)


def test_the_contact_band_lies_along_the_footprints_and_the_light():
    """On the Cornell box (contacts meshed), the band is the floor round the blocks'
    footprints and the ceiling round the light hung under it: every element within a quarter
    of the rim elements' side is in it, none beyond their side, none on another surface."""
    scene = hemirad.load_scene("cornell_box")
    mesh = build_mesh(scene)
    band = contact_band(mesh, mesh).numpy()
    names = np.asarray(mesh.surface_names)[mesh.surface.numpy()]
    assert set(names[band]) == {"floor", "ceiling"}
    centroids = mesh.centroids.numpy()[:, [0, 2]]
    sides = np.sqrt(2 * mesh.areas.numpy())
    for surface, outlines in (("floor", CORNELL_FOOTPRINTS.values()), ("ceiling", [CORNELL_LIGHT])):
        on = names == surface
        distance = np.min([_distance_to_outline(centroids, outline) for outline in outlines], axis=0)
        rim = on & (distance < 0.5 * sides)  # elements with the rim within reach: about its side
        assert rim.sum() >= 8
        side = np.median(sides[rim])
        assert band[on & (distance < 0.5 * CONTACT_BAND * side)].all()
        assert not band[on & (distance > 2 * CONTACT_BAND * side)].any()


def test_a_refined_mesh_is_banded_by_its_initial_rims(monkeypatch):
    """Refined with hanging vertices, a mesh's split edges read as boundaries; the band is
    measured from the initial mesh's rims, so it is the same region, finer (and the same
    taken a few distances at a time)."""
    scene = hemirad.load_scene("cornell_box").with_element_sizes_scaled(2.0)
    initial = build_mesh(scene)
    floor = initial.surface == initial.surface_names.index("floor")
    refined, _ = split_triangles(initial, floor, "pattern2")
    coarse = contact_band(initial, initial)
    fine = contact_band(initial, refined)
    area = [float(m.areas[b].sum()) for m, b in ((initial, coarse), (refined, fine))]
    assert fine.sum() > coarse.sum()
    assert area[1] == pytest.approx(area[0], rel=0.25)
    monkeypatch.setattr(gathered_module, "_PAIRS_AT_ONCE", 1000)
    assert torch.equal(contact_band(initial, refined), fine)


def test_contacts_gather_only_the_band_and_say_so():
    scene = hemirad.load_scene("cornell_box").with_element_sizes_scaled(2.0)
    scene.solver.error_samples = 0
    shot = hemirad.solve(scene)
    scene.solver.final_gather = "contacts"
    reports = []
    gathered = hemirad.solve(scene, progress=reports.append)
    band = contact_band(build_mesh(scene), gathered.mesh)
    gathers = [r for r in reports if isinstance(r, GatherReport)]  # after every shot's report
    assert gathers and reports[-len(gathers):] == gathers
    assert gathers[-1].gathered == gathers[-1].elements == int(band.sum())
    changed = (gathered.radiosity != shot.radiosity).any(1)
    assert changed.any() and not changed[~band].any()
    said = gathered.stats["final_gather"]
    assert said["mode"] == "contacts" and said["elements"] == int(band.sum())
    assert abs(said["luminance_change"]) < 0.2 and gathered.stats["seconds"]["final_gather"] > 0
    assert gathered.stats["escaped_power"] == shot.stats["escaped_power"]
