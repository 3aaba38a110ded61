"""Photometric units: the 683 lm/W and Rec. 709 conventions, a flux made an exitance, and
the lux under a lamp given by its flux against the closed form."""
import math
from pathlib import Path

import pytest
import torch
import yaml

import hemirad
from hemirad.core.colour import LUMENS_PER_WATT
from hemirad.core.errors import SceneError
from hemirad.geometry.analytic import point_to_polygon
from hemirad.lighting.photometry import flux_exitance, illuminance, luminance_cd
from hemirad.scene.loader import parse_scene

SMALL_ROOM = Path(__file__).parent / "data" / "small_room.yaml"


def test_lux_of_radiometric_and_photometric_irradiance():
    """Radiometric: 683 lm/W times the Rec. 709 luminance; photometric: the luminance itself."""
    assert LUMENS_PER_WATT == 683.0
    e = torch.tensor([[1.0, 1.0, 1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 2.0]], dtype=torch.float64)
    assert illuminance(e, "radiometric").tolist() == pytest.approx([683.0, 683 * 0.7152, 683 * 0.2126, 683 * 0.1444])
    assert illuminance(e, "photometric").tolist() == pytest.approx([1.0, 0.7152, 0.2126, 0.1444])
    # a Lambertian surface of exitance B: luminance B / pi
    assert luminance_cd(torch.tensor([100.0, 100.0, 100.0]), "photometric").item() == pytest.approx(100 / math.pi)
    with pytest.raises(ValueError, match="units"):
        illuminance(e, "lumens")


def test_a_flux_becomes_an_exitance_of_its_colour():
    """1,000 lm over 0.5 m^2: 2,000 lm/m^2 of luminance, the colour's ratios kept; as watts,
    2,000 / 683 W/m^2 of luminance."""
    e = flux_exitance(1000.0, 0.5, (1.0, 0.5, 0.25), "photometric")
    assert float(e @ torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64)) == pytest.approx(2000.0)
    assert (e[1] / e[0]).item() == pytest.approx(0.5) and (e[2] / e[0]).item() == pytest.approx(0.25)
    torch.testing.assert_close(flux_exitance(1000.0, 0.5, (1, 1, 1), "radiometric"),
                               torch.full((3,), 2000.0 / 683, dtype=torch.float64))


# A 100 x 60 cm lamp at 100 cm, facing down, alone: no surface reflects anything back.
LAMP_ALONE = """
units: {units}
unit: cm
materials:
  lamp: {{reflectance: 0.0, flux: 600, colour: [1.0, 0.9, 0.8]}}
objects:
  - {{type: quad, name: lamp, material: lamp, element_size: 20,
     corners: [[-50, 100, -30], [50, 100, -30], [50, 100, 30], [-50, 100, 30]]}}
camera: {{position: [0, 0, -200], look_at: [0, 100, 0], width: 16, height: 12, supersample: 1}}
solver: {{resolution: 16}}
sensors:
  - {{name: under, position: [0, 0, 0], normal: [0, 1, 0]}}
  - {{name: aside, position: [80, 30, 40], normal: [-0.3, 1, 0]}}
"""


@pytest.mark.parametrize("units", ["photometric", "radiometric"])
def test_lux_under_a_lamp_given_by_its_flux_is_flux_over_area_times_the_form_factor(units):
    """600 lm over 0.6 m^2 (its corners in cm): 1,000 lm/m^2, so E = 1000 F lux, F
    Lambert's factor from the point to the lamp, within the sensors' 0.5%; as watts (a
    radiometric scene) the same lux, through 683 lm/W both ways."""
    scene = parse_scene(yaml.safe_load(LAMP_ALONE.format(units=units)))
    assert scene.metres_per_unit == 0.01
    result = hemirad.solve(scene)
    flux = result.stats["flux"]["lamp"]
    assert flux["area_m2"] == pytest.approx(0.6) and flux["flux_lm"] == 600
    exitance = torch.tensor(flux["exitance"], dtype=torch.float64)
    assert illuminance(exitance, units).item() == pytest.approx(1000.0, rel=1e-12)
    assert float(exitance[1] / exitance[0]) == pytest.approx(0.9) and float(exitance[2] / exitance[0]) == pytest.approx(0.8)
    torch.testing.assert_close(result.emission[0], exitance)  # what the solver emitted
    lamp = torch.tensor([[-50, 100, -30], [50, 100, -30], [50, 100, 30], [-50, 100, 30]], dtype=torch.float64)
    for i, (point, normal) in enumerate([((0, 0, 0), (0, 1, 0)), ((80, 30, 40), (-0.3, 1, 0))]):
        n = torch.tensor(normal, dtype=torch.float64)
        factor = float(point_to_polygon(torch.tensor(point, dtype=torch.float64), n / n.norm(), lamp))
        assert result.sensors.lux[i].item() == pytest.approx(1000.0 * factor, rel=0.005)
        assert result.sensors.irradiance[i, 0].item() == pytest.approx(
            exitance[0].item() * factor, rel=0.005)
    assert result.stats["units"] == units
    # the emitted power: 1,000 lm/m^2 over 6,000 cm^2, luminance in scene units (cm^2)
    emitted = torch.tensor(result.stats["emitted_power"], dtype=torch.float64)
    assert illuminance(emitted, units).item() * scene.metres_per_unit ** 2 == pytest.approx(600.0, rel=1e-9)


def test_a_flux_shared_by_two_lamps_is_their_total():
    """Two lamps of one material with flux 900: 900 lm in all, spread by area (a 1 x 1 and
    a 1 x 2 lamp: 300 and 600 lm), one exitance."""
    scene = parse_scene(yaml.safe_load("""
units: photometric
materials:
  white: {reflectance: 0.5}
  lamp: {reflectance: 0.0, flux: 900}
objects:
  - {type: room, min: [0, 0, 0], max: [4, 3, 4], material: white, element_size: 1}
  - {type: quad, name: a, material: lamp, element_size: 1,
     corners: [[0.5, 2.99, 0.5], [1.5, 2.99, 0.5], [1.5, 2.99, 1.5], [0.5, 2.99, 1.5]]}
  - {type: quad, name: b, material: lamp, element_size: 1,
     corners: [[2, 2.99, 1], [3, 2.99, 1], [3, 2.99, 3], [2, 2.99, 3]]}
camera: {position: [2, 1.5, 0.1], look_at: [2, 1.5, 4], width: 16, height: 12, supersample: 1}
solver: {resolution: 16, max_shots: 1}
"""))
    result = hemirad.solve(scene)
    lamps = result.emission.max(dim=1).values > 0
    areas = result.mesh.areas[lamps]
    assert float(areas.sum()) == pytest.approx(3.0)
    torch.testing.assert_close(result.emission[lamps], torch.full((int(lamps.sum()), 3), 300.0, dtype=torch.float64))
    assert float((areas[:, None] * result.emission[lamps]).sum(0)[0]) == pytest.approx(900.0)


def test_an_office_lit_in_lumens():
    """The bundled office_lighting scene: its panel's 6,000 lm over 0.72 m^2, a desk grid and
    the room's working plane at EN 12464-1's spacing; solved, the desk centre is brighter
    than the floor under the desk, and the grid's mean lies between its extremes."""
    scene = hemirad.load_scene("office_lighting")
    assert scene.units == "photometric" and [g.name for g in scene.grids] == ["desk", "room"]
    scene.solver.unshot_fraction = 0.02  # quick: the check is of the plumbing, not convergence
    result = hemirad.solve(scene)
    assert result.stats["flux"]["lamp"]["exitance"][0] == pytest.approx(6000 / 0.72)
    desk = result.grids["desk"]
    assert desk.layout.shape == (3, 6)
    assert result.grids["room"].layout.shape == (6, 8)  # 4 x 3 m: p = 0.2 x 5^log10(4) = 0.526 m
    lux = dict(zip(result.sensors.names, result.sensors.lux.tolist()))
    assert lux["desk centre"] > 5 * lux["floor under desk"] > 0
    figures = desk.statistics
    assert figures["Emin"] < figures["Em"] < figures["Emax"]


@pytest.mark.parametrize("text, key, says", [
    ("{reflectance: 0.0, emission: 20, flux: 500}", "materials.lamp.flux", "not both"),
    ("{reflectance: 0.0, flux: -5}", "materials.lamp.flux", "lumens, > 0"),
    ("{reflectance: 0.0, flux: 500, colour: [0, 0, 0]}", "materials.lamp.colour", "some luminance"),
    ("{reflectance: 0.0, emission: 20, colour: [1, 0, 0]}", "materials.lamp.colour", "only beside flux"),
])
def test_bad_flux_keys(text, key, says):
    source = SMALL_ROOM.read_text().replace("{reflectance: 0.0, emission: [20.0, 20.0, 20.0]}", text)
    with pytest.raises(SceneError) as raised:
        parse_scene(yaml.safe_load(source), folder=SMALL_ROOM.parent)
    assert raised.value.key == key and says in str(raised.value)


@pytest.mark.parametrize("text, key, says", [
    ("units: photometrik", "units", "Did you mean 'photometric'?"),
    ("unit: inch", "unit", "a length unit"),
    ("unit: -1", "unit", "metres in one scene unit"),
])
def test_bad_unit_keys(text, key, says):
    with pytest.raises(SceneError) as raised:
        parse_scene(yaml.safe_load(SMALL_ROOM.read_text() + "\n" + text + "\n"), folder=SMALL_ROOM.parent)
    assert raised.value.key == key and says in str(raised.value)


def test_a_scene_lit_only_by_a_flux_is_lit():
    source = SMALL_ROOM.read_text().replace("{reflectance: 0.0, emission: [20.0, 20.0, 20.0]}",
                                            "{reflectance: 0.0, flux: 500}")
    scene = parse_scene(yaml.safe_load(source), folder=SMALL_ROOM.parent)
    assert scene.units == "radiometric" and scene.metres_per_unit == 1.0
    assert next(m for m in scene.materials if m.name == "lamp").flux == 500


def test_checkpoints_see_a_flux_and_its_units_and_no_more():
    """A scene without a flux hashes its materials as before flux existed (name, reflectance,
    emission), so earlier checkpoints still resume; a flux's exitance depends on the length
    unit and on lumens or watts, so changing either refuses its checkpoint."""
    import hashlib
    import json

    from hemirad import checkpoint

    scene = hemirad.load_scene("office")
    before = [{"name": m.name, "reflectance": list(m.reflectance), "emission": list(m.emission)}
              for m in scene.materials]
    digest = hashlib.sha256(json.dumps(before, sort_keys=True).encode()).hexdigest()
    assert checkpoint.fingerprint(scene)["materials"] == digest
    scene.units, scene.metres_per_unit = "photometric", 0.01  # no flux: nothing the solve uses changed
    assert checkpoint.fingerprint(scene)["materials"] == digest

    lit = hemirad.load_scene("office_lighting")
    prints = [checkpoint.fingerprint(lit)["materials"]]
    lit.metres_per_unit = 0.01
    prints.append(checkpoint.fingerprint(lit)["materials"])
    lit.units = "radiometric"
    prints.append(checkpoint.fingerprint(lit)["materials"])
    assert len(set(prints)) == 3
