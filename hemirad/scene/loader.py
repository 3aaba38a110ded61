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
      - {type: mesh, name: shelf, file: shelf.glb}  # no material: the file's (filematerials.py),
                                                    # shelf.<name>, or materials.<name> if defined
    camera: {position: [...], look_at: [...], up: [0, 1, 0], fov: 40, width: 512,
             height: 512, exposure: auto, supersample: 3}
    solver: {max_shots: 500, unshot_fraction: 1.0e-3, resolution: 128, ambient: true}
    falsecolour: [room.floor]          # surfaces drawn as false-colour maps of the light on them
    units: photometric                 # emission in lm/m^2 (default radiometric: W/m^2)
    unit: m                            # the scene unit, for grid spacing and flux
    sensors: [{position: [...], normal: [0, 1, 0], name: desk}]
    grids: [{name: desk, work_plane: {height: 0.75, min: [x, z], max: [x, z]}, spacing: 0.2}]

A material may give ``flux: <lumens>`` (and ``colour``) instead of ``emission``.
    meshing: {contacts: auto, intersections: true}    # contacts: mesh touched surfaces conforming to
                                       # what touches them (auto: where patches shoot);
                                       # intersections: cut surfaces where others
                                       # pass through them, what closed solids hold dropped

This module reads the top level, materials and objects; the checks of single values are in
``keys.py``, the YAML dialect in ``yamlfile.py``, mesh objects and their files in
``meshfile.py``, the materials of mesh files in ``filematerials.py``, the camera, solver
and refine blocks in ``options.py``, and units, sensors and grids in ``sensorblocks.py``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from hemirad.core.colour import REC709_LUMINANCE
from hemirad.core.errors import SceneError
from hemirad.scene.keys import Checker, closest, did_you_mean, join
from hemirad.scene.filematerials import scene_materials
from hemirad.scene.meshfile import read_mesh_object
from hemirad.scene.meshing import box_face_corners, quad_triangles
from hemirad.scene.model import (MAX_EMISSION, MIN_EMISSION, Box, FaceOverride, Material, MeshFile, Quad, Room, Scene,
                                 SceneObject)
from hemirad.scene.options import MAX_TRIANGLES, read_camera, read_meshing, read_patch_size, read_refine, read_solver
from hemirad.scene.sensorblocks import read_grids, read_length_unit, read_sensors, read_units
from hemirad.scene.yamlfile import parse_yaml

#: How far (a fraction of its size) a quad's corners may lie off their mean plane. The
#: mesher follows a slight twist (the Cornell box's red wall is 0.0014 off), not a fold.
MAX_QUAD_TWIST = 0.05

#: The smallest object, as a fraction of the scene's size: 32-bit floats keep about 7 digits.
MIN_RELATIVE_SIZE = 1e-6

__all__ = ["MAX_TRIANGLES", "SCENES_DIR", "bundled_scenes", "load_scene", "parse_scene"]

SCENES_DIR = Path(__file__).resolve().parent.parent / "scenes"

_TOP_KEYS = ("element_size", "materials", "objects", "camera", "solver", "refine", "falsecolour", "units", "unit",
             "sensors", "grids", "meshing")

#: The longest surface name ``falsecolour`` may hold: it becomes part of a file name.
MAX_SURFACE_NAME = 200
_MATERIAL_KEYS = ("reflectance", "emission", "flux", "colour")

#: The luminous flux a material may give, in lumens (the brightest lamps give about 1e6).
MAX_FLUX = 1e15
_COMMON_KEYS = ("type", "name", "material", "element_size", "patch_size")
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
    "mesh": ("file",),  # without a material, its faces take the file's materials
}
_FACE_KEYS = ("material", "element_size")

# Why a mesh file gives a face no material, by its extension.
_NO_MATERIAL_WHY = {
    ".obj": "a face before any usemtl line",
    ".glb": "a primitive without a material",
    ".gltf": "a primitive without a material",
    "": "only glTF and OBJ + MTL files give materials",
}

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
    data = parse_yaml(shown, text)
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
    with np.errstate(all="ignore"):  # extreme numbers are refused by the checks, not warned about
        return reader.scene(data, source)


# ----------------------------------------------------------------------------------------
# file and YAML level


def _raise_missing_file(shown: str, path: Path):
    names = bundled_scenes()
    close = closest(path.stem if path.suffix else shown, names)
    hint = f"Did you mean the bundled scene '{close}'? " if close else ""
    hint += f"Bundled scenes: {', '.join(names) or 'none'}."
    if path.exists():
        raise SceneError(shown, "", "a scene file", got=shown, hint=f"It is not a regular file. {hint}")
    raise SceneError(shown, "", "an existing scene file or the name of a bundled scene", got=shown, hint=hint)


def _quad_triangle_normals(c: np.ndarray) -> np.ndarray:
    """(4, 3) the doubled normals of the four corner triangles (012, 123, 230, 301) of quad c (4, 3)."""
    i = np.arange(4)
    return np.cross(c[(i + 1) % 4] - c[i], c[(i + 2) % 4] - c[i])


# ----------------------------------------------------------------------------------------
# the checker


class _Reader(Checker):
    """Walks the document; every method takes the key path of what it reads."""

    def __init__(self, file: str, folder: Path, folder_shown: str):
        super().__init__(file, _REQUIRED_WHAT)
        self.folder, self.folder_shown = folder, folder_shown
        self.materials: dict[str, Material] = {}  # those under materials:
        self.file_materials: dict[str, Material] = {}  # those mesh files give, by scene name
        self.default_size: float | None = None
        # (estimated triangles, key of the element_size that decides them)
        self.estimates: list[tuple[float, str]] = []
        self.sizes: dict[str, float] = {}  # element_size keys and their values
        self.bounds: list[tuple[str, np.ndarray]] = []  # (key that places an object, (N, 3) its points)

    def size(self, v, key: str) -> float:
        return self.bounded(v, key, "a positive element size (scene units)", lambda x: x > 0)

    def material_name(self, v, key: str) -> str:
        names = list(self.materials)
        if not isinstance(v, str) or v not in self.materials:
            self.fail(key, f"a material defined under materials ({', '.join(names) or 'the scene defines none'})", v,
                      did_you_mean(v, names))
        return v

    # --- sections ---

    def scene(self, data, source: Path | None) -> Scene:
        if data is None:
            self.fail("", "a YAML mapping with the keys materials, objects and camera at the top level",
                      hint="The file is empty.")
        top = self.section(data, "", "a YAML mapping with the keys materials, objects and camera at the top level",
                           _TOP_KEYS, ("objects", "camera"))
        if "element_size" in top:
            self.default_size = self.size(top["element_size"], "element_size")
        self.read_materials(top.get("materials", {}))
        objects = self.read_objects(top["objects"])
        camera = read_camera(self, top["camera"])
        solver = read_solver(self, top.get("solver", {}))
        refine = read_refine(self, top.get("refine", {}))
        surfaces = self.read_falsecolour(top.get("falsecolour", []))
        units = read_units(self, top["units"]) if "units" in top else "radiometric"
        unit = read_length_unit(self, top["unit"]) if "unit" in top else 1.0
        sensors = read_sensors(self, top["sensors"]) if "sensors" in top else []
        grids = read_grids(self, top["grids"]) if "grids" in top else []
        meshing = read_meshing(self, top.get("meshing", {}))
        self.check_light(objects)
        self.check_object_sizes()
        self.check_triangle_budget()
        materials = list(self.materials.values()) + list(self.file_materials.values())
        return Scene(materials, objects, camera, solver, refine, source, falsecolour=surfaces, sensors=sensors,
                     grids=grids, units=units, metres_per_unit=unit, meshing=meshing)

    def read_falsecolour(self, v) -> list[str]:
        """A list of surface names; whether the scene has them is checked once it is meshed."""
        if not isinstance(v, list):
            self.fail("falsecolour", "a list of surface names such as [room.floor]", v,
                      f"Write one name as [{v}]." if isinstance(v, str) and len(v) <= MAX_SURFACE_NAME else "")
        for i, name in enumerate(v):
            if not isinstance(name, str) or not 0 < len(name) <= MAX_SURFACE_NAME:
                self.fail(f"falsecolour[{i}]", f"a surface name such as room.floor (1 to {MAX_SURFACE_NAME} "
                          f"characters)", name)
        return list(v)

    def read_materials(self, v):
        # empty (or absent) when every object takes its materials from its mesh file
        m = self.mapping(v, "materials", "a mapping of material names to {reflectance, emission}")
        for name, spec in m.items():
            key = join("materials", name)
            if not isinstance(name, str) or not name:
                self.fail(key, "a material name (a non-empty string)", name)
            spec = self.section(spec, key, "a mapping with reflectance and optionally emission", _MATERIAL_KEYS,
                                ("reflectance",))
            rho = self.rgb(spec["reflectance"], f"{key}.reflectance",
                           "three numbers in [0, 1) or one number (grey)", lambda x: 0.0 <= x < 1.0)
            emission = (0.0, 0.0, 0.0)
            if "emission" in spec:
                emission = self.rgb(spec["emission"], f"{key}.emission",
                                    f"three finite numbers >= 0 or one number (each 0 or from {MIN_EMISSION:g} "
                                    f"to {MAX_EMISSION:g}, so that radiosity fits the outputs' 32-bit floats)",
                                    lambda x: x == 0.0 or MIN_EMISSION <= x <= MAX_EMISSION)
            material = Material(name, rho, emission)
            if "flux" in spec:
                if "emission" in spec:
                    self.fail(f"{key}.flux", "either emission or flux, not both", spec["flux"],
                              "Give the flux's colour as colour: [r, g, b].")
                material.flux = self.bounded(spec["flux"], f"{key}.flux",
                                             f"a luminous flux in lumens, > 0 and at most {MAX_FLUX:g}",
                                             lambda x: 0 < x <= MAX_FLUX)
            if "colour" in spec:
                if "flux" not in spec:
                    self.fail(f"{key}.colour", "a colour only beside flux (the colour of the light it gives)",
                              spec["colour"], "An emission gives its colour itself.")
                colour = self.rgb(spec["colour"], f"{key}.colour", "three numbers >= 0 or one number, "
                                  "at most 1e6, not all 0 (only the colour counts, not the size)",
                                  lambda x: 0 <= x <= 1e6)
                if not sum(w * c for w, c in zip(REC709_LUMINANCE, colour)) > 0:
                    self.fail(f"{key}.colour", "a colour with some luminance (not all zero)", list(colour))
                material.colour = colour
            self.materials[name] = material

    def read_objects(self, v) -> list[SceneObject]:
        expected = "a non-empty list of objects (room, box, quad, mesh)"
        if not isinstance(v, list) or not v:
            self.fail("objects", expected, v)
        objects, names = [], {}
        for i, spec in enumerate(v):
            key = f"objects[{i}]"
            spec = self.mapping(spec, key, "an object mapping with a type (room, box, quad or mesh)")
            kind = self.object_type(spec, key)
            name = spec.get("name", key)  # unnamed objects are called by their key path
            if not isinstance(name, str) or not name:
                self.fail(f"{key}.name", "a non-empty string", name)
            if name in names:
                self.fail(f"{key}.name", "a name no other object has", name, f"{names[name]} is also called {name!r}.")
            names[name] = key
            material = self.material_name(spec["material"], f"{key}.material") if "material" in spec else None
            size, size_key = self.object_size(spec, key)
            read = getattr(self, f"read_{kind}")
            objects.append(read(spec, key, name, material, size, size_key))
            if "patch_size" in spec:
                objects[-1].patch_size = read_patch_size(self, spec["patch_size"], f"{key}.patch_size")
        return objects

    def object_type(self, spec: dict, key: str) -> str:
        """The object's type, once its keys are checked against that type's."""
        if "type" not in spec:
            self.fail(f"{key}.type", _REQUIRED_WHAT["type"], hint="The key is missing.")
        kind = spec["type"]
        if not isinstance(kind, str) or kind not in _OBJECT_KEYS:
            self.fail(f"{key}.type", _REQUIRED_WHAT["type"], kind, did_you_mean(kind, _OBJECT_KEYS))
        for k in spec:
            others = [t for t, keys in _OBJECT_KEYS.items() if k in keys and k not in _OBJECT_KEYS[kind]]
            if others:
                self.fail(f"{key}.{k}", f"one of the keys {', '.join(_OBJECT_KEYS[kind])}", k,
                          f"'{k}' belongs to {' and '.join(others)} objects, and this one is a {kind}.")
        self.keys(spec, key, _OBJECT_KEYS[kind], _OBJECT_REQUIRED[kind])
        return kind

    def object_size(self, spec: dict, key: str) -> tuple[float, str]:
        if "element_size" in spec:
            return self.size(spec["element_size"], f"{key}.element_size"), f"{key}.element_size"
        if self.default_size is None:
            self.fail(f"{key}.element_size", "a positive element size",
                      hint="The object has none and the scene sets no top-level element_size default.")
        return self.default_size, "element_size"

    def min_max(self, spec: dict, key: str):
        lo, hi = self.point(spec["min"], f"{key}.min"), self.point(spec["max"], f"{key}.max")
        for axis, (a, b) in enumerate(zip(lo, hi)):
            if not a < b:
                self.fail(f"{key}.max", "a point above min on every axis", list(hi),
                          f"On axis {'xyz'[axis]}, min is {a:g} and max is {b:g}.")
        self.bounds.append((f"{key}.max", np.array([lo, hi])))
        return lo, hi

    def box_face_estimates(self, lo, hi, sizes: list[tuple[float, str]]):
        """Adds the triangle count of each of six faces; sizes in Room.FACE_NAMES order."""
        for face, (size, size_key) in zip(Room.FACE_NAMES, sizes):
            corners = box_face_corners(lo, hi, face, inward=True).numpy()
            self.estimate(quad_triangles(corners, size), size, size_key)

    def read_room(self, spec, key, name, material, size, size_key) -> Room:
        lo, hi = self.min_max(spec, key)
        faces, sizes = {}, []
        overrides = self.section(spec.get("faces", {}), f"{key}.faces",
                                 f"a mapping from face names ({', '.join(Room.FACE_NAMES)}) to overrides",
                                 Room.FACE_NAMES)
        for face in Room.FACE_NAMES:
            fkey = f"{key}.faces.{face}"
            if face not in overrides:
                sizes.append((size, size_key))
                continue
            o = self.section(overrides[face], fkey, "a mapping with material and/or element_size", _FACE_KEYS)
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
        expected = "four corners [[x, y, z], ...] of a convex planar quadrilateral, in order around it"
        v = spec["corners"]
        if not isinstance(v, list) or len(v) != 4:
            self.fail(f"{key}.corners", expected, v)
        corners = tuple(self.point(c, f"{key}.corners[{i}]") for i, c in enumerate(v))
        c = np.array(corners)
        extent = float(np.ptp(c, axis=0).max())
        if extent <= 1e-9 * float(np.abs(c).max()):
            self.fail(f"{key}.corners", expected, v, "The corners coincide (to the precision of their coordinates).")
        # The shape tests are made on the quad scaled to size 1: a tiny (or huge) quad is
        # the same quad, and its squared lengths must not underflow to "collinear".
        c = (c - c[0]) / extent
        for i in range(4):
            for j in range(i + 1, 4):
                if np.linalg.norm(c[i] - c[j]) <= 1e-9:
                    self.fail(f"{key}.corners", expected, v, f"Corners {i} and {j} coincide.")
        # Each corner triangle must turn the same way as the whole quad: this refuses
        # collinear corners, bow-ties (corners out of order) and concave quads, all of
        # which fold the bilinear grid the mesher lays over the quad.
        normals = _quad_triangle_normals(c)
        if (np.linalg.norm(normals, axis=1) <= 1e-9).any():
            self.fail(f"{key}.corners", expected, v, "Three of the corners are collinear.")
        vector_area = np.cross(c[2] - c[0], c[3] - c[1])
        if (normals @ vector_area <= 0).any():
            self.fail(f"{key}.corners", expected, v,
                      "The corners are out of order (a bow-tie) or make a concave shape.")
        off_plane = np.abs((c - c.mean(axis=0)) @ (vector_area / np.linalg.norm(vector_area)))
        if off_plane.max() > MAX_QUAD_TWIST:
            self.fail(f"{key}.corners", expected, v,
                      f"The corners lie up to {off_plane.max():.2g} of the quad's size off its mean plane "
                      f"(at most {MAX_QUAD_TWIST:g} is allowed); make it two quads or a mesh.")
        self.estimate(quad_triangles(np.array(corners), size), size, size_key)
        self.bounds.append((f"{key}.corners", np.array(corners)))
        return Quad(corners, material, size, name)

    def read_mesh(self, spec, key, name, material, size, size_key) -> MeshFile:
        obj, triangles, corners = read_mesh_object(self, spec, key, name, material, size, self.folder,
                                                   self.folder_shown)
        self.estimate(triangles, size, size_key)
        self.bounds.append((f"{key}.transform" if "transform" in spec else f"{key}.file", corners))
        if material is None:
            obj.file_materials = self.materials_from_file(obj, key, spec["file"])
        return obj

    def materials_from_file(self, obj: MeshFile, key: str, shown: str) -> dict[str, str]:
        """A mesh object without a material: its faces take the file's, each named in the scene as
        ``filematerials.scene_materials`` says; a face the file gives none is refused."""
        contents, why = obj.contents, _NO_MATERIAL_WHY.get(Path(obj.path).suffix.lower(), _NO_MATERIAL_WHY[""])
        if contents.materials.problem:
            self.fail(f"{key}.file", "a mesh file whose materials can be read, or a material on the object", shown,
                      f"The object has no material, so it takes the file's, and {contents.materials.problem}.")
        unassigned = int((contents.face_materials < 0).sum())
        if unassigned:
            self.fail(f"{key}.material", _REQUIRED_WHAT["material"],
                      hint=f"The key is missing, and {unassigned} of the {len(contents.faces)} faces of {shown} "
                           f"have no material in the file ({why}).")
        return scene_materials(self, key, shown, obj.name, contents.materials, contents.used_materials(),
                               self.materials, self.file_materials)

    # --- whole-scene checks ---

    def estimate(self, triangles: int, size: float, size_key: str):
        """Record that ``triangles`` initial triangles come from the element size at ``size_key``
        (an exact integer, however large: the count meshing would make, or its bound)."""
        self.estimates.append((triangles, size_key))
        self.sizes[size_key] = size

    def check_object_sizes(self):
        """Refuse an object too small beside the scene for 32-bit floats to tell its corners apart."""
        points = np.concatenate([p for _, p in self.bounds])
        scene_size = float(np.ptp(points, axis=0).max())
        for key, p in self.bounds:
            size = float(np.ptp(p, axis=0).max())
            if size < MIN_RELATIVE_SIZE * scene_size:
                self.fail(key, f"an object at least {MIN_RELATIVE_SIZE:g} of the scene's size", hint=(
                    f"It is {size:.3g} across and the scene {scene_size:.3g}; OpenGL draws in 32-bit floats, "
                    f"which cannot tell its corners apart."))

    def check_light(self, objects: list[SceneObject]):
        used = {o.material for o in objects if o.material is not None}
        used |= {f.material for o in objects if isinstance(o, Room) for f in o.faces.values() if f.material}
        used |= {n for o in objects if isinstance(o, MeshFile) for n in o.file_materials.values()}
        materials = {**self.materials, **self.file_materials}
        if any(materials[n].emits for n in used):
            return
        emitting = [n for n, m in materials.items() if m.emits]
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
        by_key: dict[str, int] = {}
        for n, k in self.estimates:
            by_key[k] = by_key.get(k, 0) + n
        key = max(by_key, key=by_key.get)
        self.fail(key, f"an element size that keeps the scene under {MAX_TRIANGLES:,} triangles",
                  self.sizes[key],
                  hint=f"The scene would start with {_count(total)} triangles, {_count(by_key[key])} of them "
                       f"from this element size; make it larger.")


def _count(n: int) -> str:
    """A triangle count for a message, however many digits it has: ``about 12,345`` or ``more than 10^42``."""
    return f"about {n:,}" if n < 10**12 else f"more than 10^{len(str(n)) - 1}"
