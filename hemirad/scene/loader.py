"""Read a YAML scene file into a :class:`hemirad.scene.model.Scene`, checking every key.

Each mistake raises :class:`SceneError` naming the file, the key path inside it
(``objects[3].material``, ``camera.fov``), what was expected and what was found, so the
user can fix the file without reading code. Checks that need geometry (degenerate quads,
the scene's estimated triangle count) are done here too, before any meshing starts.

The schema, all lengths in scene units::

    element_size: 0.25                 # optional default for objects without their own
    materials:
      white: {reflectance: [0.7, 0.7, 0.7]}            # or one number (grey), each in [0, 1)
      lamp:  {reflectance: 0.0, emission: [10, 10, 10]}  # emission >= 0, default 0
    objects:
      - {type: room, min: [0, 0, 0], max: [4, 2.5, 4], material: white,
         faces: {floor: {element_size: 0.1, material: grey}}}
      - {type: box, min: [...], max: [...], material: white}
      - {type: quad, corners: [[...], [...], [...], [...]], material: lamp}
      - {type: mesh, file: chair.obj, material: white, crease_angle: 30,
         transform: {translate: [...], rotate: [rx, ry, rz], scale: 1.0}}
    camera: {position: [...], look_at: [...], up: [0, 1, 0], fov: 40, width: 512,
             height: 512, exposure: auto, supersample: 3}
    solver: {max_shots: 500, unshot_fraction: 1.0e-3, resolution: 128, ambient: true}
"""
from __future__ import annotations

import difflib
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from hemirad.core.device import DEVICE_NAMES, is_device_name
from hemirad.core.errors import SceneError
from hemirad.geometry.patterns import PATTERN_CHOICES
from hemirad.scene.meshing import clean_triangles
from hemirad.scene.model import (CRITERION_NAMES, Box, Camera, FaceOverride, Material, MeshFile, Quad, RefineOptions,
                                 Room, Scene, SceneObject, SolverOptions)

#: Refuse scenes whose estimated initial triangle count exceeds this.
MAX_TRIANGLES = 5_000_000

SCENES_DIR = Path(__file__).resolve().parent.parent / "scenes"

_TOP_KEYS = ("element_size", "materials", "objects", "camera", "solver", "refine")
_MATERIAL_KEYS = ("reflectance", "emission")
_COMMON_KEYS = ("type", "name", "material", "element_size")
_OBJECT_KEYS = {
    "room": _COMMON_KEYS + ("min", "max", "faces"),
    "box": _COMMON_KEYS + ("min", "max"),
    "quad": _COMMON_KEYS + ("corners",),
    "mesh": _COMMON_KEYS + ("file", "transform", "crease_angle"),
}
_OBJECT_REQUIRED = {
    "room": ("min", "max", "material"),
    "box": ("min", "max", "material"),
    "quad": ("corners", "material"),
    "mesh": ("file", "material"),
}
_FACE_KEYS = ("material", "element_size")
_TRANSFORM_KEYS = ("translate", "rotate", "scale", "matrix")
_CAMERA_KEYS = ("position", "look_at", "up", "fov", "width", "height", "exposure", "supersample")
_SOLVER_KEYS = ("max_shots", "unshot_fraction", "resolution", "ambient", "device")
_REFINE_KEYS = ("pattern", "criterion", "threshold", "relative", "max_depth", "min_area", "max_elements",
                "interior", "shadow_edges", "view_surface")

# What a missing required key should hold, for the error message.
_REQUIRED_WHAT = {
    "materials": "a mapping of material names to {reflectance, emission}",
    "objects": "a list of objects (room, box, quad, mesh)",
    "camera": "a camera mapping with at least position and look_at",
    "reflectance": "three numbers in [0, 1) or one number (grey)",
    "type": "an object type: room, box, quad or mesh",
    "min": "three numbers [x, y, z], the low corner",
    "max": "three numbers [x, y, z], the high corner",
    "material": "the name of a material defined under materials",
    "corners": "four points [[x, y, z], ...] running counter-clockwise seen from the front",
    "file": "the path of a mesh file, relative to the scene file's folder",
    "position": "three numbers [x, y, z], the eye position",
    "look_at": "three numbers [x, y, z], the point the camera looks at",
}


def _mesh_formats() -> tuple[str, ...]:
    """File extensions trimesh can read as triangle meshes (point clouds excluded)."""
    from trimesh.exchange.load import mesh_formats

    return tuple(sorted(set(mesh_formats()) - {"xyz", "stl_ascii"}))


class _YamlLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that reads ``1e-3`` as a float and refuses duplicate keys.

    PyYAML follows YAML 1.1, where a float needs a dot (``1e-3`` would be a string);
    scene files are written by people who expect YAML 1.2 numbers. Silently keeping the
    last of two equal keys hides typos, so that is an error too.
    """


_YamlLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?(?:[eE][-+]?[0-9]+)?
                    |[-+]?(?:[0-9][0-9_]*)?\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                    |[-+]?\.(?:inf|Inf|INF)
                    |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."),
)


def _construct_mapping(loader: _YamlLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
    seen = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if isinstance(key, (str, int, float, bool)) and key in seen:
            raise yaml.constructor.ConstructorError(
                "while reading a mapping", node.start_mark,
                f"found the key {key!r} twice (first on line {seen[key] + 1})", key_node.start_mark)
        if isinstance(key, (str, int, float, bool)):
            seen[key] = key_node.start_mark.line
    return loader.construct_mapping(node, deep=deep)


_YamlLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


# ----------------------------------------------------------------------------------------
# public API


def bundled_scenes() -> list[str]:
    """Names of the scenes shipped with the package, e.g. ``["cornell_box", "floating"]``."""
    return sorted(p.stem for p in SCENES_DIR.glob("*.yaml"))


def load_scene(path_or_name: str | Path) -> Scene:
    """Read a scene from a YAML file, or a bundled scene by name (``"cornell_box"``).

    A path that exists is read as a file; otherwise a bundled scene of that name is used.
    Imported mesh files are read too (to check them and estimate the element count), but
    nothing is meshed yet: ``hemirad.solve`` does that.

    Returns:
        The Scene; its ``solver`` and ``refine`` options may be edited before solving.
    Raises:
        SceneError: for any problem, naming the file, the key at fault and what was expected.
    """
    shown = str(path_or_name)
    path = Path(path_or_name)
    if path.is_file():
        folder_shown = str(path.parent)
    elif shown in bundled_scenes():
        path, folder_shown = SCENES_DIR / f"{shown}.yaml", "the bundled scenes folder"
    else:
        _raise_missing_file(shown, path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneError(shown, "", "a readable UTF-8 text file", hint=f"Reading it failed: {exc}.") from exc
    data = _parse_yaml(shown, text)
    return parse_scene(data, file=shown, folder=path.parent, folder_shown=folder_shown, source=path)


def parse_scene(data: Any, file: str = "<scene>", folder: str | Path = ".",
                folder_shown: str | None = None, source: Path | None = None) -> Scene:
    """Check an already-parsed YAML document (nested dicts and lists) and build the Scene.

    Args:
        data: the document, e.g. from ``yaml.safe_load``.
        file: how to name the document in error messages.
        folder: where relative mesh file paths are looked up.
        folder_shown: how to name ``folder`` in error messages (default: ``str(folder)``).
        source: stored as ``Scene.source``.
    """
    reader = _Reader(file, Path(folder), folder_shown if folder_shown is not None else str(folder))
    return reader.scene(data, source)


# ----------------------------------------------------------------------------------------
# file and YAML level


def _raise_missing_file(shown: str, path: Path):
    names = bundled_scenes()
    close = difflib.get_close_matches(path.stem if path.suffix else shown, names, n=1)
    hint = f"Did you mean the bundled scene '{close[0]}'? " if close else ""
    hint += f"Bundled scenes: {', '.join(names) or 'none'}."
    if path.exists():
        raise SceneError(shown, "", "a scene file", got=shown, hint=f"It is not a regular file. {hint}")
    raise SceneError(shown, "", "an existing scene file or the name of a bundled scene", got=shown, hint=hint)


def _parse_yaml(shown: str, text: str) -> Any:
    try:
        return yaml.load(text, Loader=_YamlLoader)  # a SafeLoader: builds only plain data
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else "an unknown line"
        problem = " ".join(str(part) for part in (exc.context, exc.problem) if part)
        raise SceneError(shown, "", "valid YAML",
                         hint=f"The YAML parser stopped at {where}: {problem}.") from exc
    except yaml.YAMLError as exc:
        raise SceneError(shown, "", "valid YAML", hint=f"The YAML parser failed: {exc}.") from exc


def _join(path: str, key: object) -> str:
    return f"{path}.{key}" if path else str(key)


def _is_number(v: object) -> bool:
    # YAML's true/false arrive as bool, a subclass of int: they are not numbers here.
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _is_finite(v: int | float) -> bool:
    """Finite as a float: YAML integers have no size limit, and past 1e308 none converts."""
    try:
        return math.isfinite(v)
    except OverflowError:
        return False


def _quad_triangle_normals(c: np.ndarray) -> np.ndarray:
    """(4, 3) the doubled normals of the four corner triangles (012, 123, 230, 301) of quad c (4, 3)."""
    i = np.arange(4)
    return np.cross(c[(i + 1) % 4] - c[i], c[(i + 2) % 4] - c[i])


def _transform_matrix(translate, rotate, scale) -> np.ndarray:
    """(4, 4) T @ Rz @ Ry @ Rx @ S: scale, then rotate about X, Y, Z (degrees), then translate."""
    rx, ry, rz = np.radians(rotate)

    def rot(a, i, j):
        m = np.eye(4)
        m[i, i], m[i, j], m[j, i], m[j, j] = math.cos(a), -math.sin(a), math.sin(a), math.cos(a)
        return m

    t = np.eye(4)
    t[:3, 3] = translate
    s = np.diag([*scale, 1.0])
    return t @ rot(rz, 0, 1) @ rot(ry, 2, 0) @ rot(rx, 1, 2) @ s


# ----------------------------------------------------------------------------------------
# the checker


class _Reader:
    """Walks the document; every method takes the key path of what it reads."""

    def __init__(self, file: str, folder: Path, folder_shown: str):
        self.file, self.folder, self.folder_shown = file, folder, folder_shown
        self.materials: dict[str, Material] = {}
        self.default_size: float | None = None
        # (estimated triangles, key of the element_size that decides them)
        self.estimates: list[tuple[float, str]] = []
        self.sizes: dict[str, float] = {}  # element_size keys and their values

    def fail(self, key: str, expected: str, got: object = ..., hint: str = ""):
        raise SceneError(self.file, key, expected, got, hint)

    # --- generic value checks ---

    def mapping(self, v, key: str, expected: str) -> dict:
        if not isinstance(v, dict):
            self.fail(key, expected, v)
        return v

    def keys(self, m: dict, key: str, allowed: tuple[str, ...], required: tuple[str, ...] = ()):
        for k in m:
            if not isinstance(k, str) or k not in allowed:
                close = difflib.get_close_matches(str(k), allowed, n=1)
                hint = f"Did you mean '{close[0]}'?" if close else ""
                self.fail(_join(key, k), f"one of the keys {', '.join(allowed)}", k, hint)
        for k in required:
            if k not in m:
                self.fail(_join(key, k), _REQUIRED_WHAT.get(k, "a value"), hint="The key is missing.")

    def number(self, v, key: str, expected: str) -> float:
        if not _is_number(v):
            hint = "true/false is not a number." if isinstance(v, bool) else ""
            self.fail(key, expected, v, hint)
        if not _is_finite(v):
            self.fail(key, expected, v, "The number must be finite (and below about 1e308).")
        return float(v)

    def integer(self, v, key: str, expected: str, lo: int, hi: int | None = None) -> int:
        if not isinstance(v, int) or isinstance(v, bool) or v < lo or (hi is not None and v > hi):
            hint = "true/false is not a number." if isinstance(v, bool) else ""
            self.fail(key, expected, v, hint)
        return int(v)

    def vec3(self, v, key: str, expected: str = "three numbers [x, y, z]") -> tuple[float, float, float]:
        if not isinstance(v, (list, tuple)) or len(v) != 3:
            self.fail(key, expected, v)
        for i, x in enumerate(v):
            self.number(x, f"{key}[{i}]", "a finite number")
        return tuple(float(x) for x in v)

    def rgb(self, v, key: str, expected: str, ok) -> tuple[float, float, float]:
        """One number (grey) or three; ``ok(x)`` says whether a channel value is allowed."""
        if _is_number(v):
            v = [v, v, v]
        if not isinstance(v, (list, tuple)) or len(v) != 3 or not all(_is_number(x) for x in v):
            hint = "true/false is not a number." if isinstance(v, bool) else ""
            self.fail(key, expected, v, hint)
        if not all(_is_finite(x) and ok(x) for x in v):
            self.fail(key, expected, v)
        return tuple(float(x) for x in v)

    def size(self, v, key: str) -> float:
        size = self.number(v, key, "a positive element size (scene units)")
        if size <= 0:
            self.fail(key, "a positive element size (scene units)", v)
        return size

    def material_name(self, v, key: str) -> str:
        names = list(self.materials)
        if not isinstance(v, str) or v not in self.materials:
            close = difflib.get_close_matches(str(v), names, n=1)
            hint = f"Did you mean '{close[0]}'?" if close else ""
            self.fail(key, f"a material defined under materials ({', '.join(names)})", v, hint)
        return v

    # --- sections ---

    def scene(self, data, source: Path | None) -> Scene:
        if data is None:
            self.fail("", "a YAML mapping with the keys materials, objects and camera at the top level",
                      hint="The file is empty.")
        top = self.mapping(data, "", "a YAML mapping with the keys materials, objects and camera at the top level")
        self.keys(top, "", _TOP_KEYS, ("materials", "objects", "camera"))
        if "element_size" in top:
            self.default_size = self.size(top["element_size"], "element_size")
        self.read_materials(top["materials"])
        objects = self.read_objects(top["objects"])
        camera = self.read_camera(top["camera"])
        solver = self.read_solver(top.get("solver", {}))
        refine = self.read_refine(top.get("refine", {}))
        self.check_light(objects)
        self.check_triangle_budget()
        return Scene(list(self.materials.values()), objects, camera, solver, refine, source)

    def read_materials(self, v):
        expected = "a non-empty mapping of material names to {reflectance, emission}"
        m = self.mapping(v, "materials", expected)
        if not m:
            self.fail("materials", expected, v)
        for name, spec in m.items():
            key = _join("materials", name)
            if not isinstance(name, str) or not name:
                self.fail(key, "a material name (a non-empty string)", name)
            spec = self.mapping(spec, key, "a mapping with reflectance and optionally emission")
            self.keys(spec, key, _MATERIAL_KEYS, ("reflectance",))
            rho = self.rgb(spec["reflectance"], f"{key}.reflectance",
                           "three numbers in [0, 1) or one number (grey)", lambda x: 0.0 <= x < 1.0)
            emission = (0.0, 0.0, 0.0)
            if "emission" in spec:
                emission = self.rgb(spec["emission"], f"{key}.emission",
                                    "three finite numbers >= 0 or one number", lambda x: x >= 0.0)
            self.materials[name] = Material(name, rho, emission)

    def read_objects(self, v) -> list[SceneObject]:
        expected = "a non-empty list of objects (room, box, quad, mesh)"
        if not isinstance(v, list) or not v:
            self.fail("objects", expected, v)
        objects, names = [], {}
        for i, spec in enumerate(v):
            key = f"objects[{i}]"
            spec = self.mapping(spec, key, "an object mapping with a type (room, box, quad or mesh)")
            if "type" not in spec:
                self.fail(f"{key}.type", _REQUIRED_WHAT["type"], hint="The key is missing.")
            kind = spec["type"]
            if not isinstance(kind, str) or kind not in _OBJECT_KEYS:
                close = difflib.get_close_matches(str(kind), list(_OBJECT_KEYS), n=1)
                self.fail(f"{key}.type", _REQUIRED_WHAT["type"], kind,
                          f"Did you mean '{close[0]}'?" if close else "")
            for k in spec:
                others = [t for t, keys in _OBJECT_KEYS.items() if k in keys and k not in _OBJECT_KEYS[kind]]
                if others:
                    self.fail(f"{key}.{k}", f"one of the keys {', '.join(_OBJECT_KEYS[kind])}", k,
                              f"'{k}' belongs to {' and '.join(others)} objects, and this one is a {kind}.")
            self.keys(spec, key, _OBJECT_KEYS[kind], _OBJECT_REQUIRED[kind])
            name = spec.get("name", key)  # unnamed objects are called by their key path
            if not isinstance(name, str) or not name:
                self.fail(f"{key}.name", "a non-empty string", name)
            if name in names:
                self.fail(f"{key}.name", "a name no other object has", name, f"{names[name]} is also called {name!r}.")
            names[name] = key
            material = self.material_name(spec["material"], f"{key}.material")
            size, size_key = self.object_size(spec, key)
            read = getattr(self, f"read_{kind}")
            objects.append(read(spec, key, name, material, size, size_key))
        return objects

    def object_size(self, spec: dict, key: str) -> tuple[float, str]:
        if "element_size" in spec:
            return self.size(spec["element_size"], f"{key}.element_size"), f"{key}.element_size"
        if self.default_size is None:
            self.fail(f"{key}.element_size", "a positive element size",
                      hint="The object has none and the scene sets no top-level element_size default.")
        return self.default_size, "element_size"

    def min_max(self, spec: dict, key: str):
        lo, hi = self.vec3(spec["min"], f"{key}.min"), self.vec3(spec["max"], f"{key}.max")
        for axis, (a, b) in enumerate(zip(lo, hi)):
            if not a < b:
                self.fail(f"{key}.max", "a point above min on every axis", list(hi),
                          f"On axis {'xyz'[axis]}, min is {a:g} and max is {b:g}.")
        return lo, hi

    def box_face_estimates(self, lo, hi, sizes: list[tuple[float, str]]):
        """Adds the estimate of each of six faces; sizes in Room.FACE_NAMES order."""
        dx, dy, dz = (b - a for a, b in zip(lo, hi))
        areas = (dx * dz, dx * dz, dy * dz, dy * dz, dx * dy, dx * dy)
        for area, (size, size_key) in zip(areas, sizes):
            self.estimate(2.0 * area / size / size, size, size_key)

    def read_room(self, spec, key, name, material, size, size_key) -> Room:
        lo, hi = self.min_max(spec, key)
        faces, sizes = {}, []
        overrides = self.mapping(spec.get("faces", {}), f"{key}.faces",
                                 f"a mapping from face names ({', '.join(Room.FACE_NAMES)}) to overrides")
        self.keys(overrides, f"{key}.faces", Room.FACE_NAMES)
        for face in Room.FACE_NAMES:
            fkey = f"{key}.faces.{face}"
            if face not in overrides:
                sizes.append((size, size_key))
                continue
            o = self.mapping(overrides[face], fkey, "a mapping with material and/or element_size")
            self.keys(o, fkey, _FACE_KEYS)
            fo = FaceOverride(
                material=self.material_name(o["material"], f"{fkey}.material") if "material" in o else None,
                element_size=self.size(o["element_size"], f"{fkey}.element_size") if "element_size" in o else None)
            faces[face] = fo
            sizes.append((fo.element_size, f"{fkey}.element_size") if fo.element_size else (size, size_key))
        self.box_face_estimates(lo, hi, sizes)
        return Room(lo, hi, material, size, faces, name)

    def read_box(self, spec, key, name, material, size, size_key) -> Box:
        lo, hi = self.min_max(spec, key)
        self.box_face_estimates(lo, hi, [(size, size_key)] * 6)
        return Box(lo, hi, material, size, name)

    def read_quad(self, spec, key, name, material, size, size_key) -> Quad:
        expected = "four corners [[x, y, z], ...] of a convex quadrilateral, in order around it"
        v = spec["corners"]
        if not isinstance(v, list) or len(v) != 4:
            self.fail(f"{key}.corners", expected, v)
        corners = tuple(self.vec3(c, f"{key}.corners[{i}]") for i, c in enumerate(v))
        c = np.array(corners)
        extent = float(np.ptp(c, axis=0).max())
        for i in range(4):
            for j in range(i + 1, 4):
                if np.linalg.norm(c[i] - c[j]) <= 1e-9 * extent:
                    self.fail(f"{key}.corners", expected, v, f"Corners {i} and {j} coincide.")
        # Each corner triangle must turn the same way as the whole quad: this refuses
        # collinear corners, bow-ties (corners out of order) and concave quads, all of
        # which fold the bilinear grid the mesher lays over the quad.
        normals = _quad_triangle_normals(c)
        if (np.linalg.norm(normals, axis=1) <= 1e-9 * extent**2).any():
            self.fail(f"{key}.corners", expected, v, "Three of the corners are collinear.")
        vector_area = np.cross(c[2] - c[0], c[3] - c[1])
        if (normals @ vector_area <= 0).any():
            self.fail(f"{key}.corners", expected, v,
                      "The corners are out of order (a bow-tie) or make a concave shape.")
        self.estimate(float(np.linalg.norm(vector_area)) / size / size, size, size_key)  # 2 * area / size^2
        return Quad(corners, material, size, name)

    def read_mesh(self, spec, key, name, material, size, size_key) -> MeshFile:
        file = spec["file"]
        if not isinstance(file, str) or not file:
            self.fail(f"{key}.file", _REQUIRED_WHAT["file"], file)
        # absolute, so the scene still finds it if the working directory changes later
        path = (Path(file) if Path(file).is_absolute() else self.folder / file).absolute()
        formats = _mesh_formats()
        ext = path.suffix.lower().lstrip(".")
        if ext not in formats:
            self.fail(f"{key}.file", f"a mesh file in a format trimesh reads ({', '.join(formats)})", file,
                      f"The extension '.{ext}' is not one of them." if ext else "The file has no extension.")
        if not path.is_file():
            self.fail(f"{key}.file", "an existing mesh file", file,
                      f"Relative paths are read from the scene file's folder ({self.folder_shown}).")
        transform = self.read_transform(spec.get("transform", {}), f"{key}.transform")
        crease = 30.0
        if "crease_angle" in spec:
            crease = self.number(spec["crease_angle"], f"{key}.crease_angle", "an angle in degrees in [0, 180]")
            if not 0.0 <= crease <= 180.0:
                self.fail(f"{key}.crease_angle", "an angle in degrees in [0, 180]", spec["crease_angle"])
        area, count = self.mesh_area(path, file, f"{key}.file", transform)
        self.estimate(2.0 * area / size / size + count, size, size_key)
        return MeshFile(path, material, size, tuple(map(tuple, transform.tolist())), crease, name)

    def read_transform(self, v, key: str) -> np.ndarray:
        t = self.mapping(v, key, "a mapping with translate/rotate/scale, or with matrix")
        self.keys(t, key, _TRANSFORM_KEYS)
        if "matrix" in t:
            if len(t) > 1:
                self.fail(key, "either matrix or translate/rotate/scale, not both", sorted(t))
            expected = "a 4 x 4 affine matrix (four rows of four numbers, the last row 0 0 0 1)"
            rows = t["matrix"]
            if not isinstance(rows, list) or len(rows) != 4 or not all(isinstance(r, list) and len(r) == 4 for r in rows):
                self.fail(f"{key}.matrix", expected, rows)
            for i, r in enumerate(rows):
                for j, x in enumerate(r):
                    self.number(x, f"{key}.matrix[{i}][{j}]", "a finite number")
            m = np.array(rows, dtype=np.float64)
            if not np.allclose(m[3], [0, 0, 0, 1], rtol=0, atol=1e-12):
                self.fail(f"{key}.matrix", expected, rows, "Projective transforms are not supported.")
        else:
            translate = self.vec3(t["translate"], f"{key}.translate") if "translate" in t else (0.0, 0.0, 0.0)
            rotate = self.vec3(t["rotate"], f"{key}.rotate", "three angles in degrees [rx, ry, rz]") \
                if "rotate" in t else (0.0, 0.0, 0.0)
            scale = (1.0, 1.0, 1.0)
            if "scale" in t:
                s = t["scale"]
                scale = (self.number(s, f"{key}.scale", "a non-zero number or three"),) * 3 if _is_number(s) \
                    else self.vec3(s, f"{key}.scale", "a non-zero number or three [sx, sy, sz]")
            m = _transform_matrix(translate, rotate, scale)
        if abs(np.linalg.det(m[:3, :3])) < 1e-300 or np.linalg.cond(m[:3, :3]) > 1e12:
            self.fail(key, "an invertible transform", t, "A zero scale flattens the mesh.")
        return m

    def mesh_area(self, path: Path, shown: str, key: str, transform: np.ndarray) -> tuple[float, int]:
        """Total area and triangle count of a mesh file after ``transform``; checks that it reads."""
        import trimesh

        try:
            tm = trimesh.load(path, force="mesh", process=False)
        except Exception as exc:  # trimesh raises many kinds; any of them means an unreadable file
            reason = str(exc).strip().rstrip(".!") or type(exc).__name__
            self.fail(key, "a mesh file trimesh can read", shown, f"Reading it failed: {reason}.")
        faces = np.asarray(getattr(tm, "faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3)
        vertices = np.asarray(getattr(tm, "vertices", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
        if len(faces) == 0:
            self.fail(key, "a mesh file with at least one triangle", shown, "It holds no triangles.")
        if faces.min() < 0 or faces.max() >= len(vertices):
            self.fail(key, "a mesh file whose faces index its own vertices", shown,
                      f"A face names vertex {int(faces.max()) + 1} (or a negative one); there are {len(vertices)}.")
        with np.errstate(invalid="ignore", over="ignore"):
            v = vertices @ transform[:3, :3].T + transform[:3, 3]
            c = v[faces]
            doubled = np.linalg.norm(np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]), axis=1)
        # Meshing drops zero-area and non-finite triangles with a warning (by this same test);
        # with none left there is nothing to mesh, and that is this key's fault.
        usable, _ = clean_triangles(v, faces)
        if not usable.any():
            self.fail(key, "a mesh file with at least one triangle of non-zero area and finite corners", shown,
                      f"All {len(faces)} of its triangles are degenerate (zero area) or have NaN/infinite corners.")
        return 0.5 * float(doubled[usable].sum()), len(faces)

    def read_camera(self, v) -> Camera:
        m = self.mapping(v, "camera", _REQUIRED_WHAT["camera"])
        self.keys(m, "camera", _CAMERA_KEYS, ("position", "look_at"))
        position, look_at = self.vec3(m["position"], "camera.position"), self.vec3(m["look_at"], "camera.look_at")
        up = self.vec3(m["up"], "camera.up") if "up" in m else (0.0, 1.0, 0.0)
        view = np.subtract(look_at, position)
        if np.linalg.norm(view) == 0:
            self.fail("camera.look_at", "a point different from camera.position", list(look_at))
        if np.linalg.norm(np.cross(view, up)) <= 1e-9 * np.linalg.norm(view) * np.linalg.norm(up):
            self.fail("camera.up", "a direction not parallel to the viewing direction", list(up))
        cam = Camera(position, look_at, up)
        if "fov" in m:
            cam.fov = self.number(m["fov"], "camera.fov", "a vertical field of view in degrees, 0 < fov < 180")
            if not 0 < cam.fov < 180:
                self.fail("camera.fov", "a vertical field of view in degrees, 0 < fov < 180", m["fov"])
        for k in ("width", "height"):
            if k in m:
                setattr(cam, k, self.integer(m[k], f"camera.{k}", "a whole number of pixels, 1 to 16384", 1, 16384))
        if "supersample" in m:
            cam.supersample = self.integer(m["supersample"], "camera.supersample", "a whole number from 1 to 8", 1, 8)
        if "exposure" in m and m["exposure"] != "auto":
            cam.exposure = self.number(m["exposure"], "camera.exposure", "'auto' or a positive number")
            if cam.exposure <= 0:
                self.fail("camera.exposure", "'auto' or a positive number", m["exposure"])
        return cam

    def read_solver(self, v) -> SolverOptions:
        m = self.mapping(v, "solver", "a mapping of solver options")
        self.keys(m, "solver", _SOLVER_KEYS)
        opts = SolverOptions()
        if "max_shots" in m:
            opts.max_shots = self.integer(m["max_shots"], "solver.max_shots", "a whole number >= 0", 0)
        if "unshot_fraction" in m:
            f = self.number(m["unshot_fraction"], "solver.unshot_fraction", "a number in [0, 1)")
            if not 0 <= f < 1:
                self.fail("solver.unshot_fraction", "a number in [0, 1)", m["unshot_fraction"])
            opts.unshot_fraction = f
        if "resolution" in m:
            r = self.integer(m["resolution"], "solver.resolution", "an even whole number >= 8", 8)
            if r % 2:
                self.fail("solver.resolution", "an even whole number >= 8", r,
                          "The hemicube's side faces are resolution / 2 pixels high.")
            opts.resolution = r
        if "ambient" in m:
            opts.ambient = self.boolean(m["ambient"], "solver.ambient")
        if "device" in m:
            if not is_device_name(m["device"]):
                self.fail("solver.device", "one of " + ", ".join(DEVICE_NAMES), m["device"],
                          "cuda needs PyTorch with CUDA and an NVIDIA GPU; auto picks it when there is one.")
            opts.device = m["device"]
        return opts

    def boolean(self, v, key: str) -> bool:
        if not isinstance(v, bool):
            self.fail(key, "true or false", v)
        return v

    def choice(self, v, key: str, options) -> str:
        if not isinstance(v, str) or v not in options:
            close = difflib.get_close_matches(str(v), list(options), n=1)
            self.fail(key, f"one of {', '.join(options)}", v, f"Did you mean {close[0]!r}?" if close else "")
        return v

    def read_refine(self, v) -> RefineOptions:
        m = self.mapping(v, "refine", "a mapping of refinement options")
        self.keys(m, "refine", _REFINE_KEYS)
        opts = RefineOptions()
        if "pattern" in m:
            opts.pattern = self.choice(m["pattern"], "refine.pattern", PATTERN_CHOICES)
        if "criterion" in m:
            opts.criterion = self.choice(m["criterion"], "refine.criterion", CRITERION_NAMES)
        if "threshold" in m:
            t = self.number(m["threshold"], "refine.threshold", "a number > 0")
            if not t > 0:
                self.fail("refine.threshold", "a number > 0", m["threshold"])
            opts.threshold = t
        for key in ("relative", "interior", "shadow_edges"):
            if key in m:
                setattr(opts, key, self.boolean(m[key], f"refine.{key}"))
        if "max_depth" in m:
            opts.max_depth = self.integer(m["max_depth"], "refine.max_depth", "a whole number from 0 to 16", 0, 16)
        if "min_area" in m:
            a = self.number(m["min_area"], "refine.min_area", "a number >= 0 (scene units squared)")
            if a < 0:
                self.fail("refine.min_area", "a number >= 0 (scene units squared)", m["min_area"])
            opts.min_area = a
        if "max_elements" in m:
            opts.max_elements = self.integer(m["max_elements"], "refine.max_elements",
                                             f"a whole number from 1 to {MAX_TRIANGLES:,}", 1, MAX_TRIANGLES)
        if "view_surface" in m:
            if not isinstance(m["view_surface"], str):
                self.fail("refine.view_surface", "a surface name such as room.floor", m["view_surface"])
            opts.view_surface = m["view_surface"]
        if not (opts.interior or opts.shadow_edges):
            self.fail("refine.interior", "at least one of interior and shadow_edges to be true", False)
        return opts

    # --- whole-scene checks ---

    def estimate(self, triangles: float, size: float, size_key: str):
        """Record that ``triangles`` initial triangles come from the element size at ``size_key``."""
        self.estimates.append((triangles, size_key))
        self.sizes[size_key] = size

    def check_light(self, objects: list[SceneObject]):
        used = {o.material for o in objects}
        used |= {f.material for o in objects if isinstance(o, Room) for f in o.faces.values() if f.material}
        if any(max(self.materials[n].emission) > 0 for n in used):
            return
        emitting = [n for n, m in self.materials.items() if max(m.emission) > 0]
        hint = "The scene has no light: nothing would be lit. "
        if emitting:
            hint += f"The material(s) {', '.join(emitting)} emit but no object uses them."
        else:
            hint += "Give a material a positive emission, e.g. emission: [10, 10, 10], and assign it to an object."
        self.fail("materials", "at least one material with emission > 0 that an object uses", hint=hint)

    def check_triangle_budget(self):
        total = sum(n for n, _ in self.estimates)
        if total <= MAX_TRIANGLES:
            return
        by_key: dict[str, float] = {}
        for n, k in self.estimates:
            by_key[k] = by_key.get(k, 0.0) + n
        key = max(by_key, key=by_key.get)
        self.fail(key, f"an element size that keeps the scene under {MAX_TRIANGLES:,} triangles",
                  self.sizes[key],
                  hint=f"The scene would start with about {_count(total)} triangles, {_count(by_key[key])} of them "
                       f"from this element size; make it larger.")


def _count(n: float) -> str:
    """A triangle estimate for a message; a size near 1e-200 makes it overflow to infinity."""
    return f"{n:,.0f}" if math.isfinite(n) else "more than 1e308"
