"""Property-based fuzzing of the scene loader: whatever the document, it either loads or
raises ``HemiradInputError`` (which the command line shows as one paragraph); any other
exception would reach the user as a traceback.

Five sources of documents: random nested data over the scene vocabulary (with huge, tiny
and non-finite numbers), random edits of the bundled scenes' parsed data (with shared and
self-containing values, as YAML aliases make), random edits of their text, YAML text with
anchors, aliases, merge keys, deep nesting and numbers of thousands of digits put into a
working scene, and alias bombs; the last two in bounded time.
"""
from __future__ import annotations

import copy
import math
import time
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hemirad.core.errors import HemiradInputError
from hemirad.scene.loader import SCENES_DIR, load_scene, parse_scene
from hemirad.scene.model import Scene

DATA = Path(__file__).parent / "data"
SOURCES = [*sorted(SCENES_DIR.glob("*.yaml")), DATA / "small_room.yaml"]
DOCUMENTS = [(p, yaml.safe_load(p.read_text())) for p in SOURCES]

# Deterministic (derandomize) so a CI run cannot fail on an example no one has seen; the
# budget keeps the whole file to a few seconds.
FUZZ = settings(max_examples=150, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])

KEYS = ["element_size", "materials", "objects", "camera", "solver", "refine", "reflectance", "emission",
        "type", "name", "material", "min", "max", "faces", "floor", "corners", "file", "transform",
        "translate", "rotate", "scale", "matrix", "crease_angle", "position", "look_at", "up", "fov",
        "width", "height", "exposure", "supersample", "max_shots", "unshot_fraction", "resolution",
        "ambient", "pattern", "criterion", "threshold", "max_depth", "max_elements", "view_surface", "falsecolour",
        "white", "lamp"]
WORDS = ["room", "box", "quad", "mesh", "white", "lamp", "auto", "pattern2", "gradient", "tetra.obj",
         "missing.obj", "room.floor", ""]

scalars = st.one_of(
    st.none(), st.booleans(),
    st.integers(min_value=-(10**400), max_value=10**400),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, 1, 2, 0.5, 1e-300, 1e300, -1]),
    st.sampled_from(WORDS), st.text(max_size=8),
    # huge, tiny and non-finite numbers: none may reach a message or a check unbounded
    st.sampled_from([5e-324, 1e-320, 1e308, -1e308, 1e39, 1e15 + 1, math.nan, math.inf]),
    st.sampled_from([1, -1]).map(lambda sign: sign * 10**5000),  # built late: hypothesis cannot print it
)
keys = st.one_of(st.sampled_from(KEYS), st.text(max_size=6), st.integers(-3, 3))
documents = st.recursive(
    scalars,
    lambda inner: st.one_of(st.lists(inner, max_size=5), st.dictionaries(keys, inner, max_size=6)),
    max_leaves=40,
)


def loads_or_refuses(data, folder: Path = DATA) -> None:
    try:
        scene = parse_scene(data, file="fuzz.yaml", folder=folder)
    except HemiradInputError as exc:
        text = str(exc)
        assert text.startswith("fuzz.yaml") and "\n\n" not in text
        return
    assert isinstance(scene, Scene)
    assert any(m.emits for m in scene.materials)  # the loader's own promise: an emission or a flux
    for m in scene.materials:
        assert all(0 <= x < 1 for x in m.reflectance) and all(math.isfinite(x) for x in m.emission)


@FUZZ
@given(documents)
def test_random_documents_load_or_raise_an_input_error(data):
    loads_or_refuses(data)


@FUZZ
@given(documents, st.sampled_from(KEYS))
def test_random_documents_under_a_real_top_level_key(value, key):
    doc = copy.deepcopy(DOCUMENTS[-1][1])
    doc[key] = value
    loads_or_refuses(doc)


def _paths(node, prefix=()):
    """Every (container path, key) in a nested document."""
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for k, v in items:
        yield prefix, k
        yield from _paths(v, prefix + (k,))


@st.composite
def mutated_scenes(draw):
    """A bundled scene's data with 1-3 random edits: a value replaced, a key deleted or added,
    a list shortened or lengthened."""
    source, original = draw(st.sampled_from(DOCUMENTS))
    doc = copy.deepcopy(original)
    for _ in range(draw(st.integers(1, 3))):
        paths = list(_paths(doc))
        if not paths:
            break
        prefix, key = draw(st.sampled_from(paths))
        parent = doc
        for p in prefix:
            parent = parent[p]
        action = draw(st.sampled_from(["replace", "delete", "add", "duplicate"]))
        if action == "replace":
            parent[key] = draw(documents)
        elif action == "delete":
            del parent[key]
        elif action == "add" and isinstance(parent, dict):
            parent[draw(keys)] = draw(documents)
        elif isinstance(parent, list):
            parent.append(copy.deepcopy(parent[key]))
    return source, doc


@FUZZ
@given(mutated_scenes())
def test_mutated_bundled_scenes_load_or_raise_an_input_error(case):
    source, doc = case
    loads_or_refuses(doc, folder=source.parent)


@st.composite
def mutated_texts(draw):
    """A bundled scene's text with a few characters deleted, inserted or replaced."""
    source, _ = draw(st.sampled_from(DOCUMENTS))
    text = source.read_text()
    for _ in range(draw(st.integers(1, 4))):
        i = draw(st.integers(0, len(text)))
        piece = draw(st.sampled_from([":", "-", "[", "]", "{", "}", " ", "\n", "\t", "#", "'", '"', "0", "-1",
                                      "e", ".", ",", "&a", "*a", "!!python/object:os.system", "\x00", "\u00e9"]))
        mode = draw(st.sampled_from(["insert", "delete", "replace"]))
        if mode == "insert":
            text = text[:i] + piece + text[i:]
        elif mode == "delete":
            text = text[:i] + text[i + draw(st.integers(1, 20)):]
        else:
            text = text[:i] + piece + text[i + len(piece):]
    return source, text


@pytest.fixture(scope="module")
def scene_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fuzz")
    (folder / "tetra.obj").write_bytes((DATA / "tetra.obj").read_bytes())
    return folder


@FUZZ
@given(mutated_texts())
def test_mutated_scene_files_load_or_raise_an_input_error(scene_folder, case):
    source, text = case
    path = scene_folder / source.name
    path.write_text(text, encoding="utf-8", errors="surrogatepass")
    try:
        load_scene(path)
    except HemiradInputError as exc:
        assert str(path) in str(exc)


@FUZZ
@given(st.binary(max_size=200))
def test_random_bytes_as_a_scene_file_raise_an_input_error(scene_folder, data):
    path = scene_folder / "bytes.yaml"
    path.write_bytes(data)
    try:
        load_scene(path)
    except HemiradInputError:
        pass
    else:
        pytest.fail("random bytes made a scene")  # they cannot hold materials, objects and camera


@FUZZ
@given(st.sampled_from(KEYS), documents, st.integers(0, 2))
def test_shared_and_self_containing_values_load_or_raise_an_input_error(key, value, how):
    """What YAML aliases build: one object at several places, or inside itself."""
    doc = copy.deepcopy(DOCUMENTS[-1][1])
    if how == 0:
        shared = [value, value]
        doc[key] = [shared, shared, {"material": shared}]
    elif how == 1:
        looped = {"type": "quad", "material": "white"}
        looped["corners"] = [looped] * 4
        doc["objects"] = list(doc["objects"]) + [looped]
        doc[key] = {"x": looped, "objects": [looped]}
    else:
        looped_list: list = [value]
        looped_list.append(looped_list)
        doc[key] = looped_list
    loads_or_refuses(doc)


# YAML text: anchors (&a, &b), aliases (*a, *b, possibly before their anchor), merge keys,
# nesting, and numbers YAML reads but no float holds.
yaml_leaves = st.sampled_from(["1", "0.5", "-0.0", "1e400", "-1e400", ".nan", ".inf", "-.inf", "5e-324", "1.0e308",
                               "9" * 500, "9" * 5000, "-" + "1" * 4400, "0x" + "f" * 300, "'x'", "room.floor", "lamp",
                               "white", "*a", "*b", "[]", "{}", "true", "null"])
yaml_keys = st.sampled_from(KEYS + ["<<", "<<", "x"])
yaml_texts = st.recursive(
    yaml_leaves,
    lambda inner: st.one_of(
        st.lists(inner, max_size=5).map(lambda items: "[" + ", ".join(items) + "]"),
        st.lists(st.tuples(yaml_keys, inner), max_size=5).map(
            lambda pairs: "{" + ", ".join(f"{k}: {v}" for k, v in pairs) + "}"),
        st.tuples(st.sampled_from(["&a ", "&b "]), inner).map("".join),
    ),
    max_leaves=30,
)
TOP_LINES = ("element_size", "materials", "camera", "solver", "objects")


def _replace_top_line(text: str, key: str, value: str) -> str:
    lines = text.splitlines()
    return "\n".join(f"{key}: {value}" if line.startswith(f"{key}:") else line for line in lines) + "\n"


def _refused_quickly(scene_folder, text: str) -> None:
    path = scene_folder / "text.yaml"
    path.write_text(text)
    start = time.perf_counter()
    try:
        load_scene(path)
    except HemiradInputError as exc:
        assert str(path) in str(exc) and "\n" not in str(exc) and len(str(exc)) <= 2000
    assert time.perf_counter() - start < 5


@FUZZ
@given(st.sampled_from(TOP_LINES), yaml_texts, st.integers(0, 300))
def test_yaml_with_aliases_merge_keys_nesting_and_huge_numbers(scene_folder, key, value, depth):
    base = (Path(__file__).parent / "bad_inputs" / "base.yaml").read_text()
    if depth > 100:  # nested far past the limit, around the value
        value = "[" * depth + value + "]" * depth
    _refused_quickly(scene_folder, _replace_top_line(base, key, value))


@FUZZ
@given(st.integers(2, 40), st.integers(1, 12), st.sampled_from(TOP_LINES))
def test_alias_bombs_are_refused_in_bounded_time(scene_folder, fan_out, levels, key):
    base = (Path(__file__).parent / "bad_inputs" / "base.yaml").read_text()
    lines = ["  v0: &l0 [" + ", ".join(["x"] * fan_out) + "]"]
    lines += [f"  v{i}: &l{i} [" + ", ".join([f"*l{i - 1}"] * fan_out) + "]" for i in range(1, levels + 1)]
    value = "\n" + "\n".join(lines)
    _refused_quickly(scene_folder, _replace_top_line(base, key, value))
