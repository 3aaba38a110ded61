"""Scene files: the bundled scenes load, and every kind of mistake names its key."""
from __future__ import annotations

import copy
from pathlib import Path

import pytest
import yaml

from hemirad.core.device import DEVICE_NAMES
from hemirad.core.errors import HemiradInputError, SceneError
from hemirad.geometry.patterns import PATTERN_CHOICES
from hemirad.scene.loader import MAX_TRIANGLES, bundled_scenes, load_scene, parse_scene
from hemirad.scene.model import CRITERION_NAMES, Box, MeshFile, Quad, Room, Scene

DATA = Path(__file__).parent / "data"

BASE = {
    "element_size": 0.5,
    "materials": {
        "white": {"reflectance": [0.7, 0.7, 0.7]},
        "lamp": {"reflectance": 0.0, "emission": [10, 10, 10]},
    },
    "objects": [
        {"type": "room", "min": [0, 0, 0], "max": [4, 2.5, 4], "material": "white"},
        {"type": "quad", "material": "lamp",
         "corners": [[1, 2.49, 1], [2, 2.49, 1], [2, 2.49, 2], [1, 2.49, 2]]},
    ],
    "camera": {"position": [2, 1.5, 0.2], "look_at": [2, 1, 4]},
}


def write(tmp_path: Path, doc) -> Path:
    path = tmp_path / "scene.yaml"
    path.write_text(doc if isinstance(doc, str) else yaml.safe_dump(doc, sort_keys=False))
    return path


def edited(edit):
    doc = copy.deepcopy(BASE)
    edit(doc)
    return doc


def set_key(doc, path: str, value):
    *parents, last = path.split(".")
    for p in parents:
        doc = doc[int(p)] if p.isdigit() else doc[p]
    doc[int(last) if last.isdigit() else last] = value


def del_key(doc, path: str):
    *parents, last = path.split(".")
    for p in parents:
        doc = doc[int(p)] if p.isdigit() else doc[p]
    del doc[last]


# ---------------------------------------------------------------------------------------
# good scenes


@pytest.mark.parametrize("name", ["cornell_box", "floating"])
def test_bundled_scenes_load(name):
    assert name in bundled_scenes()
    scene = load_scene(name)
    assert isinstance(scene, Scene) and scene.objects
    assert scene.source is not None and scene.source.name == f"{name}.yaml"
    assert any(max(m.emission) > 0 for m in scene.materials)


def test_cornell_box_follows_the_published_camera_and_light():
    scene = load_scene("cornell_box")
    assert scene.camera.position == (278.0, 273.0, -800.0)
    assert scene.camera.fov == pytest.approx(39.3)
    assert scene.camera.look_at[2] > scene.camera.position[2]  # looking along +z, into the box
    light = scene.materials[scene.material_index("light")]
    assert light.emission == pytest.approx([3.141592653589793 * x for x in (18.387, 13.987, 6.754)], rel=1e-5)


def test_small_room_loads_with_its_mesh_file():
    scene = load_scene(DATA / "small_room.yaml")
    kinds = [type(o) for o in scene.objects]
    assert kinds == [Room, Quad, Box, MeshFile]
    mesh = scene.objects[3]
    assert mesh.path.is_absolute() and mesh.path.name == "tetra.obj"
    assert (scene.camera.width, scene.camera.height) == (96, 72)
    assert (scene.solver.resolution, scene.solver.max_shots) == (32, 40)


def test_defaults_names_and_yaml12_floats(tmp_path):
    doc = edited(lambda d: d.update(solver={"unshot_fraction": "PLACEHOLDER"}))
    text = yaml.safe_dump(doc, sort_keys=False).replace("PLACEHOLDER", "1e-4")
    scene = load_scene(write(tmp_path, text))
    assert scene.solver.unshot_fraction == 1e-4  # YAML 1.1 would read 1e-4 as a string
    assert [o.name for o in scene.objects] == ["objects[0]", "objects[1]"]
    assert scene.objects[0].element_size == 0.5  # the scene-wide default
    assert scene.materials[0].reflectance == (0.7, 0.7, 0.7)
    assert scene.materials[1].reflectance == (0.0, 0.0, 0.0)  # one number means grey
    assert scene.camera.up == (0.0, 1.0, 0.0) and scene.camera.exposure is None


def test_room_face_overrides_and_mesh_transform(tmp_path):
    (tmp_path / "tetra.obj").write_text((DATA / "tetra.obj").read_text())
    doc = edited(lambda d: None)
    doc["materials"]["grey"] = {"reflectance": 0.5}
    doc["objects"][0]["faces"] = {"floor": {"material": "grey", "element_size": 0.25}}
    doc["objects"].append({"type": "mesh", "file": "tetra.obj", "material": "white",
                           "transform": {"scale": 2, "translate": [1, 2, 3]}, "crease_angle": 45})
    scene = load_scene(write(tmp_path, doc))
    face = scene.objects[0].faces["floor"]
    assert (face.material, face.element_size) == ("grey", 0.25)
    mesh = scene.objects[2]
    assert mesh.transform[0] == (2.0, 0.0, 0.0, 1.0) and mesh.transform[2][3] == 3.0
    assert mesh.crease_angle == 45.0


# ---------------------------------------------------------------------------------------
# bad scenes: (edit of BASE, substrings the message must contain)

BAD = {
    "misspelt key": (lambda d: d["materials"]["white"].update(reflectence=d["materials"]["white"].pop("reflectance")),
                     ["materials.white.reflectence", "reflectance"]),
    "unknown top-level key": (lambda d: d.update(objets=d.pop("objects")), ["objets", "objects"]),
    "reflectance of 1": (lambda d: set_key(d, "materials.white.reflectance", 1.0), ["materials.white.reflectance", "[0, 1)"]),
    "two reflectances": (lambda d: set_key(d, "materials.white.reflectance", [0.5, 0.5]), ["materials.white.reflectance"]),
    "negative emission": (lambda d: set_key(d, "materials.lamp.emission", [1, -1, 1]), ["materials.lamp.emission", ">= 0"]),
    "unknown material": (lambda d: set_key(d, "objects.0.material", "whte"), ["objects[0].material", "'white'"]),
    "unknown object type": (lambda d: set_key(d, "objects.1.type", "quadd"), ["objects[1].type", "'quad'"]),
    "missing type": (lambda d: del_key(d, "objects.1.type"), ["objects[1].type", "missing"]),
    "missing material": (lambda d: del_key(d, "objects.0.material"), ["objects[0].material", "missing"]),
    "key of another type": (lambda d: set_key(d, "objects.1.min", [0, 0, 0]), ["objects[1].min", "room and box"]),
    "room min >= max": (lambda d: set_key(d, "objects.0.max", [4, 0, 4]), ["objects[0].max", "axis y"]),
    "coincident corners": (lambda d: set_key(d, "objects.1.corners.2", [1, 2.49, 1]), ["objects[1].corners", "coincide"]),
    "bow-tie quad": (lambda d: set_key(d, "objects.1.corners", [[1, 2.49, 1], [2, 2.49, 1], [1, 2.49, 2], [2, 2.49, 2]]),
                     ["objects[1].corners", "bow-tie"]),
    "concave quad": (lambda d: set_key(d, "objects.1.corners", [[1, 2.49, 1], [2, 2.49, 1], [1.2, 2.49, 1.2], [1, 2.49, 2]]),
                     ["objects[1].corners", "concave"]),
    "collinear corners": (lambda d: set_key(d, "objects.1.corners", [[1, 2.49, 1], [2, 2.49, 1], [3, 2.49, 1], [1, 2.49, 2]]),
                          ["objects[1].corners", "collinear"]),
    "three corners": (lambda d: d["objects"][1]["corners"].pop(), ["objects[1].corners"]),
    "zero element size": (lambda d: set_key(d, "objects.0.element_size", 0), ["objects[0].element_size", "positive"]),
    "no element size": (lambda d: d.pop("element_size"), ["objects[0].element_size", "default"]),
    "unknown face": (lambda d: set_key(d, "objects.0.faces", {"flor": {"element_size": 0.1}}),
                     ["objects[0].faces.flor", "'floor'"]),
    "fov of 180": (lambda d: set_key(d, "camera.fov", 180), ["camera.fov", "0 < fov < 180"]),
    "no camera position": (lambda d: del_key(d, "camera.position"), ["camera.position", "missing"]),
    "eye at the target": (lambda d: set_key(d, "camera.look_at", [2, 1.5, 0.2]), ["camera.look_at"]),
    "up along the view": (lambda d: set_key(d, "camera.up", [0, 0, 1]) or set_key(d, "camera.look_at", [2, 1.5, 3]),
                          ["camera.up"]),
    "fractional width": (lambda d: set_key(d, "camera.width", 12.5), ["camera.width"]),
    "supersample 9": (lambda d: set_key(d, "camera.supersample", 9), ["camera.supersample"]),
    "exposure word": (lambda d: set_key(d, "camera.exposure", "bright"), ["camera.exposure", "auto"]),
    "odd resolution": (lambda d: d.update(solver={"resolution": 33}), ["solver.resolution", "even"]),
    "unknown solver key": (lambda d: d.update(solver={"max_shot": 3}), ["solver.max_shot", "max_shots"]),
    "too many eyes": (lambda d: d.update(solver={"emitter_eyes": 5}), ["solver.emitter_eyes", "auto", "0 to 4"]),
    "no light": (lambda d: set_key(d, "materials.lamp.emission", 0), ["no light"]),
    "light unused": (lambda d: set_key(d, "objects.1.material", "white"), ["no light", "lamp"]),
    "duplicate names": (lambda d: [o.update(name="wall") for o in d["objects"]], ["objects[1].name", "wall"]),
    "objects not a list": (lambda d: d.update(objects={"type": "room"}), ["objects", "list"]),
    "material not a mapping": (lambda d: set_key(d, "materials.white", 0.5), ["materials.white"]),
    "too many triangles": (lambda d: set_key(d, "objects.0.element_size", 1e-3),
                           ["objects[0].element_size", f"{MAX_TRIANGLES:,}", "about", "0.001"]),
    "nan": (lambda d: set_key(d, "camera.position", [float("nan"), 1, 1]), ["camera.position[0]", "finite"]),
    "infinite size": (lambda d: set_key(d, "element_size", float("inf")), ["element_size", "finite"]),
    "missing mesh file": (lambda d: d["objects"].append({"type": "mesh", "file": "chair.obj", "material": "white"}),
                          ["objects[2].file", "chair.obj"]),
    "unsupported mesh format": (lambda d: d["objects"].append({"type": "mesh", "file": "chair.blend", "material": "white"}),
                                ["objects[2].file", ".blend"]),
    "zero scale": (lambda d: d["objects"].append({"type": "mesh", "file": "tetra.obj", "material": "white",
                                                  "transform": {"scale": [1, 0, 1]}}), ["objects[2].transform"]),
    "matrix and scale": (lambda d: d["objects"].append({"type": "mesh", "file": "tetra.obj", "material": "white",
                                                        "transform": {"scale": 2, "matrix": [[1, 0, 0, 0]] * 4}}),
                         ["objects[2].transform"]),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_scene_names_the_key(tmp_path, case):
    edit, needles = BAD[case]
    (tmp_path / "tetra.obj").write_text((DATA / "tetra.obj").read_text())
    path = write(tmp_path, edited(edit))
    with pytest.raises(SceneError) as info:
        load_scene(path)
    message = str(info.value)
    assert str(path) in message
    for needle in needles:
        assert needle in message, f"{needle!r} not in: {message}"
    assert "\n" not in message


@pytest.mark.parametrize("path, value, key", [
    ("materials.white.reflectance", True, "materials.white.reflectance"),
    ("materials.lamp.emission", [True, 1, 1], "materials.lamp.emission"),
    ("camera.fov", True, "camera.fov"),
    ("camera.width", True, "camera.width"),
    ("objects.0.element_size", False, "objects[0].element_size"),
])
def test_bool_is_not_a_number(tmp_path, path, value, key):
    with pytest.raises(SceneError) as info:
        load_scene(write(tmp_path, edited(lambda d: set_key(d, path, value))))
    assert info.value.key == key
    assert key in str(info.value)


def test_ambient_must_be_bool(tmp_path):
    with pytest.raises(SceneError, match=r"solver\.ambient"):
        load_scene(write(tmp_path, edited(lambda d: d.update(solver={"ambient": "yes please"}))))


def test_missing_file_mentions_bundled_scenes(tmp_path):
    with pytest.raises(SceneError) as info:
        load_scene("cornel_box")
    assert "cornell_box" in str(info.value)
    missing = tmp_path / "nope.yaml"
    with pytest.raises(SceneError, match="nope.yaml"):
        load_scene(missing)


def test_malformed_yaml_reports_the_line(tmp_path):
    path = write(tmp_path, "materials:\n  white: {reflectance: 0.5\nobjects: []\n")
    with pytest.raises(SceneError) as info:
        load_scene(path)
    assert info.value.key == ""
    assert "line 3" in str(info.value)


def test_duplicate_yaml_key_is_refused(tmp_path):
    text = yaml.safe_dump(BASE, sort_keys=False) + "element_size: 0.25\n"
    with pytest.raises(SceneError, match="twice"):
        load_scene(write(tmp_path, text))


@pytest.mark.parametrize("text", ["", "- 1\n- 2\n", "just words\n"])
def test_top_level_must_be_a_mapping(tmp_path, text):
    with pytest.raises(SceneError, match="mapping"):
        load_scene(write(tmp_path, text))


def test_unreadable_mesh_file(tmp_path):
    (tmp_path / "broken.obj").write_text("this is not an obj file\n")
    doc = edited(lambda d: d["objects"].append({"type": "mesh", "file": "broken.obj", "material": "white"}))
    with pytest.raises(SceneError, match=r"objects\[2\]\.file"):
        load_scene(write(tmp_path, doc))


def test_scene_error_is_an_input_error():
    with pytest.raises(HemiradInputError):
        parse_scene(["not", "a", "mapping"], file="inline")


# ---------------------------------------------------------------------------------------
# the vocabularies: one list each, which the loader and the command line both take


@pytest.mark.parametrize("key, names", [("pattern", PATTERN_CHOICES), ("criterion", CRITERION_NAMES),
                                        ("device", DEVICE_NAMES)])
def test_the_loader_takes_each_vocabulary_and_names_it_when_refusing(key, names):
    section = "solver" if key == "device" else "refine"
    for name in names:
        if name != "cuda:N":
            scene = parse_scene(edited(lambda d: d.setdefault(section, {}).update({key: name})))
            assert getattr(getattr(scene, section), key) == name
    with pytest.raises(SceneError, match=f"{section}.{key}") as error:
        parse_scene(edited(lambda d: d.setdefault(section, {}).update({key: "no_such_name"})))
    assert ", ".join(names) in str(error.value)


def test_the_command_line_offers_the_same_vocabularies():
    from hemirad.cli import build_parser

    actions = {a.dest: a for a in build_parser()._actions}
    assert tuple(actions["refine"].choices) == PATTERN_CHOICES
    assert tuple(actions["criterion"].choices) == CRITERION_NAMES
    assert all(name in actions["device"].help for name in DEVICE_NAMES)


def test_the_criteria_registry_defines_exactly_the_named_criteria():
    from hemirad.adaptive.criteria import CRITERIA

    # answer: judged between solves, not per shot; auto: answer or the paper's, by the scene
    assert tuple(CRITERIA) + ("answer", "auto") == CRITERION_NAMES
