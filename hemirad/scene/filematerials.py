"""Materials that mesh files carry: glTF 2.0 and OBJ + MTL, read exactly, and how a scene's
mesh object takes them.

trimesh reads the geometry (``meshfile.py``); the material values are read here from the
files themselves, because trimesh stores colours as 8-bit integers and drops what it does
not model (an MTL's ``Ke``, glTF's ``KHR_materials_emissive_strength``):

- glTF 2.0: the diffuse reflectance is ``pbrMetallicRoughness.baseColorFactor`` (RGB,
  linear; alpha, metallic, roughness and every texture are ignored), the emission is
  ``emissiveFactor`` times ``KHR_materials_emissive_strength.emissiveStrength`` (default 1).
- OBJ + MTL: the reflectance is ``Kd`` and the emission ``Ke`` (default 0) of the material
  a face's ``usemtl`` names, in the library the OBJ's ``mtllib`` names (relative to the OBJ).

A file material is known by its own name (a glTF material without a name, or sharing it
with another of the file's, is ``material<i>``, ``i`` its index in the file). In a scene it
becomes the material ``<object name>.<material name>``, unless the scene's ``materials:``
define that name or the file's material name, which then replace it (the object's name
first).
"""
from __future__ import annotations

import json
import math
import re
import struct
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

from hemirad.core.errors import HemiradWarning
from hemirad.scene.keys import Checker
from hemirad.scene.model import MAX_EMISSION, MIN_EMISSION, Material

_GLB_MAGIC, _GLB_JSON = 0x46546C67, 0x4E4F534A
#: The name a glTF material is given while trimesh reads the file, so that each primitive's
#: geometry says which of the file's materials it has (trimesh keeps the name, not the index).
_TAG = "hemirad-file-material-"


@dataclass(frozen=True)
class FileMaterial:
    name: str
    reflectance: tuple[float, ...] | None  # as in the file; None: the file gives none (an MTL without Kd)
    emission: tuple[float, ...]  # as in the file, the glTF emissive strength applied
    textured: bool = False  # the file gives a colour texture, which is ignored


@dataclass(frozen=True)
class FileMaterials:
    """What a mesh file says about its materials."""

    materials: tuple[FileMaterial, ...] = ()
    # why the file's materials cannot be used (a missing MTL, a malformed value), one
    # sentence; None when they can. Only an object that takes its materials from the file
    # is refused for it.
    problem: str | None = None

    def index(self, name: str) -> int:
        """The index of the material called ``name``; -1 when there is none."""
        return next((i for i, m in enumerate(self.materials) if m.name == name), -1)


NO_MATERIALS = FileMaterials()


# ----------------------------------------------------------------------------------------
# glTF 2.0


def gltf_document(data: bytes, ext: str) -> dict:
    """The JSON document of a ``.glb`` (its first chunk) or ``.gltf`` file.

    Raises:
        ValueError: the bytes are not a glTF 2.0 file's layout or JSON.
    """
    if ext == "glb":
        text = _glb_chunks(data)[0][1]
    else:
        text = data
    doc = json.loads(text.decode("utf-8-sig"))
    if not isinstance(doc, dict):
        raise ValueError("the glTF JSON is not an object")
    return doc


def _glb_chunks(data: bytes) -> list[tuple[int, bytes]]:
    """(type, bytes) of each chunk of a binary glTF, the JSON chunk first."""
    if len(data) < 20:
        raise ValueError("too short for a binary glTF")
    magic, version, length = struct.unpack_from("<III", data, 0)
    if magic != _GLB_MAGIC or version != 2:
        raise ValueError("not a binary glTF 2.0 file")
    chunks, offset = [], 12
    while offset + 8 <= min(length, len(data)):
        size, kind = struct.unpack_from("<II", data, offset)
        chunks.append((kind, data[offset + 8:offset + 8 + size]))
        offset += 8 + size
    if not chunks or chunks[0][0] != _GLB_JSON:
        raise ValueError("the binary glTF's first chunk is not JSON")
    return chunks


def tagged_gltf(data: bytes, ext: str, doc: dict) -> bytes:
    """The same file with its i-th material named ``_TAG + i``, for trimesh to read."""
    doc = dict(doc)
    doc["materials"] = [{**m, "name": f"{_TAG}{i}"} for i, m in enumerate(doc["materials"])]
    text = json.dumps(doc).encode("utf-8")
    if ext != "glb":
        return text
    text += b" " * (-len(text) % 4)  # chunks are 4-byte aligned; JSON is padded with spaces
    body = struct.pack("<II", len(text), _GLB_JSON) + text
    for kind, chunk in _glb_chunks(data)[1:]:
        body += struct.pack("<II", len(chunk), kind) + chunk
    return struct.pack("<III", _GLB_MAGIC, 2, 12 + len(body)) + body


def tag_index(name: object) -> int:
    """The file's index of a material ``tagged_gltf`` named; -1 for any other name."""
    if isinstance(name, str) and name.startswith(_TAG) and name[len(_TAG):].isdigit():
        return int(name[len(_TAG):])
    return -1


def gltf_materials(doc: dict) -> FileMaterials:
    """The materials of a glTF document (``gltf_document``), in the file's order."""
    materials = doc.get("materials", [])
    if not isinstance(materials, list) or not all(isinstance(m, dict) for m in materials):
        return FileMaterials(problem="its materials are not a list of JSON objects")
    names = _unique_names([m.get("name") for m in materials])
    out = []
    try:
        for i, (m, name) in enumerate(zip(materials, names)):
            where = f"materials[{i}] ({name})"
            pbr = _json_object(m.get("pbrMetallicRoughness", {}), f"{where}.pbrMetallicRoughness")
            base = _numbers(pbr.get("baseColorFactor", [1.0, 1.0, 1.0, 1.0]), 4,
                            f"{where}.pbrMetallicRoughness.baseColorFactor")
            factor = _numbers(m.get("emissiveFactor", [0.0, 0.0, 0.0]), 3, f"{where}.emissiveFactor")
            extensions = _json_object(m.get("extensions", {}), f"{where}.extensions")
            strength_of = _json_object(extensions.get("KHR_materials_emissive_strength", {}),
                                       f"{where}.extensions.KHR_materials_emissive_strength")
            strength = _numbers([strength_of.get("emissiveStrength", 1.0)], 1,
                                f"{where}.extensions.KHR_materials_emissive_strength.emissiveStrength")[0]
            textured = "baseColorTexture" in pbr or "emissiveTexture" in m
            out.append(FileMaterial(name, base[:3], tuple(f * strength for f in factor), textured))
    except ValueError as exc:
        return FileMaterials(problem=str(exc))
    return FileMaterials(tuple(out))


def _unique_names(given: list) -> list[str]:
    """Each material's name, or ``material<i>`` where it has none or shares it with another."""
    names = [g if isinstance(g, str) and g else f"material{i}" for i, g in enumerate(given)]
    while True:
        counts = Counter(names)
        shared = [i for i, n in enumerate(names) if counts[n] > 1 and n != f"material{i}"]
        if not shared:
            return names
        for i in shared:
            names[i] = f"material{i}"


def _json_object(v, where: str) -> dict:
    if not isinstance(v, dict):
        raise ValueError(f"its {where} is not a JSON object")
    return v


def _numbers(v, n: int, where: str) -> tuple[float, ...]:
    if (not isinstance(v, list) or len(v) != n
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)):
        raise ValueError(f"its {where} is not {n} finite number{'s' if n > 1 else ''}")
    return tuple(float(x) for x in v)


# ----------------------------------------------------------------------------------------
# OBJ + MTL


_MTLLIB = re.compile(r"^[ \t]*mtllib[ \t]+(.*?)[ \t]*$", re.MULTILINE)
_USEMTL = re.compile(r"^[ \t]*usemtl(?:[ \t]+(.*?))?[ \t]*$", re.MULTILINE)
_FACE = re.compile(r"^[ \t]*f[ \t]", re.MULTILINE)


def obj_materials(text: str, obj_path: Path) -> FileMaterials:
    """The materials an OBJ's faces use: those its ``usemtl`` lines name, from the library
    its first ``mtllib`` names (relative to the OBJ), in the library's order."""
    text = text.replace("\r\n", "\n").replace("\\\n", "")
    library = next((m.group(1) for m in _MTLLIB.finditer(text)), None)
    statements = list(_USEMTL.finditer(text))
    ends = [m.start() for m in statements[1:]] + [len(text)]
    # a material is used when a face follows its usemtl before the next one
    used = {m.group(1) or "" for m, end in zip(statements, ends) if _FACE.search(text, m.end(), end)}
    if not used:
        return NO_MATERIALS
    if not library:
        return FileMaterials(problem=f"it uses materials ({', '.join(sorted(used))}) but names no "
                                     f"material library (no mtllib line)")
    path = _library_path(obj_path, library)
    if path is None:
        return FileMaterials(problem=f"its material library {library!r} (mtllib) is not in the OBJ's folder")
    try:
        materials = parse_mtl(_text(path.read_bytes()))
    except OSError as exc:
        return FileMaterials(problem=f"its material library {library!r} cannot be read: {exc.strerror or exc}")
    except ValueError as exc:
        return FileMaterials(problem=f"its material library {library!r}: {exc}")
    missing = sorted(used - set(materials))
    if missing:
        return FileMaterials(problem=f"usemtl names {', '.join(map(repr, missing))}, which its material "
                                     f"library {library!r} does not define")
    return FileMaterials(tuple(materials.values()))


def _library_path(obj_path: Path, library: str) -> Path | None:
    """Where the MTL is: beside the OBJ at the path ``mtllib`` gives, or by its file name alone
    (an OBJ exported elsewhere may name an absolute or a Windows path)."""
    folder = Path(obj_path).parent
    for candidate in (folder / library, folder / library.replace("\\", "/").rsplit("/", 1)[-1]):
        if candidate.is_file():
            return candidate
    return None


def _text(data: bytes) -> str:
    """A text file's characters: UTF-8, else Latin-1 (which maps every byte, so a stray byte in
    a comment or a name does not stop the numbers being read)."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        return data.decode("latin-1")


def parse_mtl(text: str) -> dict[str, FileMaterial]:
    """Each ``newmtl`` of an MTL library with its ``Kd`` and ``Ke`` as exact floats (one number
    means grey); every other statement is ignored.

    Raises:
        ValueError: a Kd or Ke that is not one or three finite numbers (``spectral`` and
            ``xyz`` colours are not read), or one before any ``newmtl``; names the line.
    """
    found: dict[str, dict] = {}
    current = None
    for number, line in enumerate(text.replace("\\\n", "").splitlines(), 1):
        parts = line.split("#", 1)[0].split(None, 1)
        if not parts:
            continue
        keyword, rest = parts[0].lower(), parts[1].strip() if len(parts) > 1 else ""
        if keyword == "newmtl":
            if not rest:
                raise ValueError(f"line {number}: newmtl without a name")
            current = found.setdefault(rest, {"name": rest, "reflectance": None, "emission": (0.0, 0.0, 0.0)})
        elif keyword in ("kd", "ke"):
            if current is None:
                raise ValueError(f"line {number}: {parts[0]} before any newmtl")
            current["reflectance" if keyword == "kd" else "emission"] = _colour(rest, number, parts[0])
    return {name: FileMaterial(**m) for name, m in found.items()}


def _colour(rest: str, number: int, keyword: str) -> tuple[float, float, float]:
    values = rest.split()
    try:
        rgb = [float(x) for x in values]
    except ValueError:
        rgb = []
    if len(rgb) == 1:
        rgb *= 3
    if len(rgb) != 3 or not all(math.isfinite(x) for x in rgb):
        raise ValueError(f"line {number}: {keyword} {rest!r} is not one or three finite numbers (r g b)")
    return tuple(rgb)


# ----------------------------------------------------------------------------------------
# a scene's mesh object taking its file's materials


def scene_materials(check: Checker, key: str, shown: str, object_name: str, file: FileMaterials,
                    used: list[int], yaml: dict[str, Material], taken: dict[str, Material]) -> dict[str, str]:
    """The scene material each of a mesh object's file materials becomes, checked.

    A file material ``m`` of the object ``o`` is the scene's material ``o.m`` or ``m`` when
    ``materials:`` defines it (in that order); otherwise it becomes a new material ``o.m``
    with the file's values, which are checked as the YAML's are (reflectance in [0, 1),
    emission 0 or within [MIN_EMISSION, MAX_EMISSION]), and added to ``taken``.

    Args:
        key: the object's key path (``objects[3]``); shown: the file as the scene names it.
        used: the indices into ``file.materials`` the object's faces use.
        yaml: the materials the scene file defines; taken: the file materials of earlier
            objects, by scene name (updated).

    Returns:
        The file material's name -> the scene material's name, for each used one.
    """
    out = {}
    for i in used:
        m = file.materials[i]
        qualified = f"{object_name}.{m.name}"
        if qualified in yaml or m.name in yaml:
            out[m.name] = qualified if qualified in yaml else m.name
            continue
        fix = (f"Fix the file, or define {m.name!r} under materials (which then replaces it), or give the "
               f"object a material.")
        if m.reflectance is None:
            check.fail(f"{key}.file", "a mesh file whose materials each give a diffuse colour", shown,
                       f"Its material {m.name!r} has no Kd. {fix}")
        if not all(0.0 <= x < 1.0 for x in m.reflectance):
            check.fail(f"{key}.file", "a mesh file whose materials' reflectances are each in [0, 1)", shown,
                       f"Its material {m.name!r} has a reflectance of {list(m.reflectance)}. {fix}")
        if not all(x == 0.0 or MIN_EMISSION <= x <= MAX_EMISSION for x in m.emission):
            check.fail(f"{key}.file", f"a mesh file whose materials' emissions are each 0 or from "
                                      f"{MIN_EMISSION:g} to {MAX_EMISSION:g}", shown,
                       f"Its material {m.name!r} has an emission of {list(m.emission)}. {fix}")
        if qualified in taken:
            check.fail(f"{key}.name", "a name that, joined to its file's material names, names no other "
                                      "object's material", object_name,
                       f"Its material {m.name!r} would be called {qualified!r}, as another object's is.")
        if m.textured:
            warnings.warn(f"{key}: the material {m.name!r} of {shown} has a texture, which is ignored: its colour "
                          f"factors alone give the reflectance and emission", HemiradWarning, stacklevel=2)
        taken[qualified] = Material(qualified, tuple(m.reflectance), tuple(m.emission))
        out[m.name] = qualified
    return out
