"""Mesh files: read once per load (trimesh) with the materials a glTF or OBJ + MTL file gives
each face (``filematerials``), and a scene's ``type: mesh`` objects checked.

The loader reads each mesh file to check it and estimate its element count, and keeps what
it read on the ``MeshFile`` (``contents``); meshing and the checkpoint's fingerprint use
that instead of reading the file again.
"""
from __future__ import annotations

import hashlib
import io
import math
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import unquote

import numpy as np

from hemirad.scene.filematerials import (NO_MATERIALS, FileMaterials, gltf_document, gltf_materials, obj_materials,
                                         tag_index, tagged_gltf)
from hemirad.scene.keys import MAX_COORDINATE, Checker, is_number
from hemirad.scene.model import MeshFile

_TRANSFORM_KEYS = ("translate", "rotate", "scale", "matrix")


def mesh_formats() -> tuple[str, ...]:
    """File extensions trimesh can read as triangle meshes (point clouds excluded)."""
    from trimesh.exchange.load import mesh_formats

    return tuple(sorted(set(mesh_formats()) - {"xyz", "stl_ascii"}))


class MeshFileUnreadable(Exception):
    """Reading a mesh file failed; ``original`` is what trimesh (or the OS) raised."""

    def __init__(self, original: BaseException):
        super().__init__(str(original))
        self.original = original

    @property
    def reason(self) -> str:
        """The failure for a sentence: the message without its final stop, or its type's name."""
        return str(self.original).strip().rstrip(".!") or type(self.original).__name__


@dataclass(frozen=True, eq=False)
class MeshContents:
    """A mesh file as read, unprocessed: its triangles as in the file, and their materials."""

    path: Path
    vertices: np.ndarray  # (V, 3) float64, read-only
    faces: np.ndarray  # (F, 3) int64, read-only
    sha256: str  # of the file's bytes (a .gltf's: and of the buffer files it names)
    face_materials: np.ndarray  # (F,) int64, read-only: index into materials.materials; -1: none given
    materials: FileMaterials = NO_MATERIALS

    def used_materials(self) -> list[int]:
        """The indices into ``materials.materials`` that faces use, in ascending order."""
        return [int(i) for i in np.unique(self.face_materials) if i >= 0]


def read_mesh_file(path: Path) -> MeshContents:
    """Read any file trimesh can load as one triangle mesh, unprocessed, with the materials
    of a glTF or OBJ + MTL file (``filematerials``) per face.

    The triangles are trimesh's: its geometries (a glTF primitive, an OBJ's faces of one
    material) moved to their place in the file's scene and concatenated in its order.

    Raises:
        MeshFileUnreadable: the file cannot be read or parsed.
    """
    import trimesh

    path = Path(path)
    ext = path.suffix.lower().lstrip(".")
    try:
        data = path.read_bytes()
        digest = hashlib.sha256(data)
        text = _as_utf8(data, ext)
        materials, slot_of = NO_MATERIALS, _no_slot
        if ext in ("glb", "gltf"):
            text, materials, slot_of = _gltf_materials(data, ext, path, digest)
        elif ext == "obj":
            materials = obj_materials((text or data).decode("utf-8", "replace"), path)
            slot_of = _mtl_slot
        if text is None:
            scene = trimesh.load_scene(path, process=False)
        else:  # the file as edited here (stray bytes decoded, glTF materials tagged)
            scene = trimesh.load_scene(io.BytesIO(text), file_type=ext, process=False,
                                       resolver=trimesh.resolvers.FilePathResolver(path))
        meshes = [g for g in scene.dump() if isinstance(g, trimesh.Trimesh)]  # as trimesh.load_mesh
    except Exception as exc:  # trimesh raises many kinds; any of them means an unreadable file
        raise MeshFileUnreadable(exc) from exc
    vertices = np.zeros((0, 3), dtype=np.float64)
    faces = np.zeros((0, 3), dtype=np.int64)
    slots = np.zeros(0, dtype=np.int64)
    if meshes:
        vertices = np.concatenate([np.asarray(m.vertices, dtype=np.float64).reshape(-1, 3) for m in meshes])
        offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
        faces = np.concatenate([np.asarray(m.faces, dtype=np.int64).reshape(-1, 3) + o
                                for m, o in zip(meshes, offsets)])
        slots = np.concatenate([np.full(len(m.faces), slot_of(m, materials), dtype=np.int64) for m in meshes])
    if materials.problem is None and len(slots) and (slots < 0).all() and materials.materials and ext == "obj":
        # every face has a material by the OBJ's usemtl lines, yet trimesh attached none
        materials = FileMaterials(problem="trimesh could not read its material library")
    for a in (vertices, faces, slots):
        a.flags.writeable = False  # shared by everything that meshes the scene
    return MeshContents(path, vertices, faces, digest.hexdigest(), slots, materials)


def _gltf_materials(data: bytes, ext: str, path: Path, digest) -> tuple[bytes | None, FileMaterials, object]:
    """A glTF's materials, the file with them tagged for trimesh (None: read the file as it
    is), and how to tell a geometry's material. Adds the buffer files a ``.gltf`` names to
    ``digest``. A file that is no glTF is left to trimesh, which says why."""
    try:
        doc = gltf_document(data, ext)
    except ValueError:
        return None, NO_MATERIALS, _no_slot
    buffers = doc.get("buffers", [])
    for b in buffers if isinstance(buffers, list) else []:
        uri = b.get("uri") if isinstance(b, dict) else None
        if isinstance(uri, str) and not uri.startswith("data:") and (path.parent / unquote(uri)).is_file():
            digest.update((path.parent / unquote(uri)).read_bytes())
    materials = gltf_materials(doc)
    if not materials.materials:
        return None, materials, _no_slot
    return tagged_gltf(data, ext, doc), materials, _tagged_slot


def _no_slot(mesh, materials: FileMaterials) -> int:
    return -1


def _tagged_slot(mesh, materials: FileMaterials) -> int:
    """The file's index of a glTF geometry's material (``tagged_gltf``), -1 for none."""
    return tag_index(getattr(getattr(mesh.visual, "material", None), "name", None))


def _mtl_slot(mesh, materials: FileMaterials) -> int:
    """The index of an OBJ geometry's material (trimesh names it as ``usemtl`` does), -1 for none."""
    name = getattr(getattr(mesh.visual, "material", None), "name", None)
    return materials.index(name) if isinstance(name, str) else -1


#: Mesh formats that are text, where a comment (or a name) may hold bytes of any encoding.
_TEXT_FORMATS = ("obj", "off")


def _as_utf8(data: bytes, ext: str) -> bytes | None:
    """A text-format mesh file that is not valid UTF-8, re-encoded as UTF-8 (read as Latin-1,
    which maps every byte to a character and keeps ASCII, all that numbers and keywords
    use); None for a valid UTF-8 or binary file, read as it is."""
    if ext not in _TEXT_FORMATS:
        return None
    try:
        data.decode("utf-8")
        return None
    except UnicodeDecodeError:
        return data.decode("latin-1").encode("utf-8")


def cached_contents(obj: MeshFile) -> MeshContents | None:
    """What the loader read for ``obj``; None when it read nothing or ``obj.path`` changed since."""
    contents = obj.contents
    return contents if isinstance(contents, MeshContents) and contents.path == Path(obj.path) else None


def contents_of(obj: MeshFile) -> MeshContents:
    """``obj``'s mesh file as the loader read it, or read now (a MeshFile made without the loader)."""
    return cached_contents(obj) or read_mesh_file(obj.path)


def clean_triangles(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, dict[str, int]]:
    """Which triangles to keep, and why the others go.

    A triangle goes if a corner is not finite, if its area is zero (below 1e-12 of the
    squared bounding-box diagonal, which also covers repeated corners), or if it repeats
    an earlier triangle with the same winding (two coincident elements would fight for
    the same hemicube pixels).

    Args:
        vertices: (V, 3); faces: (F, 3) with vertices already merged by position.

    Returns:
        keep: (F,) bool; dropped: counts by reason.
    """
    c = vertices[faces]  # (F, 3, 3)
    finite = np.isfinite(c).all(axis=(1, 2))
    used = c[finite].reshape(-1, 3)
    diag = float(np.linalg.norm(np.ptp(used, axis=0))) if len(used) else 0.0
    with np.errstate(invalid="ignore", over="ignore"):
        doubled_area = np.linalg.norm(np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]), axis=1)
    nonzero = finite & (doubled_area > 2e-12 * diag**2)
    # the same triangle twice: compare rotations brought to start at the smallest index
    rolled = np.stack([np.roll(faces, -k, axis=1) for k in range(3)], 1)  # (F, 3, 3)
    canon = rolled[np.arange(len(faces)), faces.argmin(axis=1)]
    first = np.zeros(len(faces), dtype=bool)
    if len(faces):
        _, index = np.unique(canon, axis=0, return_index=True)
        first[index] = True
    keep = nonzero & first
    dropped = {"non-finite": int((~finite).sum()), "zero-area": int((finite & ~nonzero).sum()),
               "duplicate": int((nonzero & ~first).sum())}
    return keep, dropped


def subdivided_triangles(vertices: np.ndarray, faces: np.ndarray, element_size: float) -> int:
    """A bound on the triangles meshing (``meshing._subdivide``) makes of ``faces``, counted without making them:
    each round bisects every edge longer than the size, so a triangle whose longest edge is
    ``2^k`` sizes long becomes at most about ``4^k`` triangles, however thin it is (the
    measured count is 0.4 to 1 times this). An exact integer, however large."""
    c = vertices[faces]
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        longest = np.linalg.norm(c - np.roll(c, 1, axis=1), axis=2).max(axis=1) / element_size
        rounds = np.ceil(np.log2(np.maximum(longest, 1.0)))
    rounds = np.where(np.isfinite(rounds), rounds, 2000).astype(np.int64)
    values, counts = np.unique(rounds, return_counts=True)
    return sum(int(n) * 4 ** int(k) for k, n in zip(values, counts))


# ----------------------------------------------------------------------------------------
# the loader's checks of a mesh object


def read_mesh_object(check: Checker, spec: dict, key: str, name: str, material: str, size: float,
                     folder: Path, folder_shown: str) -> tuple[MeshFile, float]:
    """A ``type: mesh`` object, a bound on the initial triangles it makes, and its placed
    corners (those of the triangles meshing keeps).

    Args:
        check: the document's checker; spec: the object's mapping at ``key``.
        folder: where relative paths are read from; folder_shown: how to name it.
    """
    file = spec["file"]
    if not isinstance(file, str) or not file:
        check.fail(f"{key}.file", check.required_what["file"], file)
    # absolute, so the scene still finds it if the working directory changes later
    path = (Path(file) if Path(file).is_absolute() else folder / file).absolute()
    formats = mesh_formats()
    ext = path.suffix.lower().lstrip(".")
    if ext not in formats:
        check.fail(f"{key}.file", f"a mesh file in a format trimesh reads ({', '.join(formats)})", file,
                   f"The extension '.{ext}' is not one of them." if ext else "The file has no extension.")
    if not path.is_file():
        check.fail(f"{key}.file", "an existing mesh file", file,
                   f"Relative paths are read from the scene file's folder ({folder_shown}).")
    transform = read_transform(check, spec.get("transform", {}), f"{key}.transform")
    crease = 30.0
    if "crease_angle" in spec:
        crease = check.bounded(spec["crease_angle"], f"{key}.crease_angle", "an angle in degrees in [0, 180]",
                               lambda x: 0.0 <= x <= 180.0)
    try:
        contents = read_mesh_file(path)
    except MeshFileUnreadable as exc:
        check.fail(f"{key}.file", "a mesh file trimesh can read", file, f"Reading it failed: {exc.reason}.")
    vertices, faces = _usable_triangles(check, contents, file, f"{key}.file", transform)
    obj = MeshFile(path, material, size, tuple(map(tuple, transform.tolist())), crease, name, contents=contents)
    return obj, subdivided_triangles(vertices, faces, size), vertices[np.unique(faces)]


def _usable_triangles(check: Checker, contents: MeshContents, shown: str, key: str,
                      transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A mesh file's vertices after ``transform`` and the triangles of them meshing keeps."""
    faces, vertices = contents.faces, contents.vertices
    if len(faces) == 0:
        check.fail(key, "a mesh file with at least one triangle", shown, "It holds no triangles.")
    if faces.min() < 0 or faces.max() >= len(vertices):
        check.fail(key, "a mesh file whose faces index its own vertices", shown,
                   f"A face names vertex {int(faces.max()) + 1} (or a negative one); there are {len(vertices)}.")
    with np.errstate(invalid="ignore", over="ignore"):
        v = vertices @ transform[:3, :3].T + transform[:3, 3]
    # Meshing drops zero-area and non-finite triangles with a warning (by this same test);
    # with none left there is nothing to mesh, and that is this key's fault.
    usable, _ = clean_triangles(v, faces)
    if not usable.any():
        check.fail(key, "a mesh file with at least one triangle of non-zero area and finite corners", shown,
                   f"All {len(faces)} of its triangles are degenerate (zero area) or have NaN/infinite corners.")
    used = v[faces[usable]]
    if np.abs(used).max() > MAX_COORDINATE:
        check.fail(key, f"a mesh whose placed corners stay within +-{MAX_COORDINATE:g}", shown,
                   f"A corner lies at {np.abs(used).max():.3g} after the transform; OpenGL draws in 32-bit floats.")
    return v, faces[usable]


def read_transform(check: Checker, v, key: str) -> np.ndarray:
    """(4, 4) the affine placement of a mesh: ``matrix``, or ``translate``/``rotate``/``scale``."""
    t = check.section(v, key, "a mapping with translate/rotate/scale, or with matrix", _TRANSFORM_KEYS)
    if "matrix" in t:
        if len(t) > 1:
            check.fail(key, "either matrix or translate/rotate/scale, not both", sorted(t))
        m = _read_matrix(check, t["matrix"], f"{key}.matrix")
    else:
        translate = check.point(t["translate"], f"{key}.translate") if "translate" in t else (0.0, 0.0, 0.0)
        rotate = check.vec3(t["rotate"], f"{key}.rotate", "three angles in degrees [rx, ry, rz]") \
            if "rotate" in t else (0.0, 0.0, 0.0)
        scale = (1.0, 1.0, 1.0)
        if "scale" in t:
            s = t["scale"]
            scale = (check.number(s, f"{key}.scale", "a non-zero number or three"),) * 3 if is_number(s) \
                else check.vec3(s, f"{key}.scale", "a non-zero number or three [sx, sy, sz]")
        m = transform_matrix(translate, rotate, scale)
    if abs(np.linalg.det(m[:3, :3])) < 1e-300 or np.linalg.cond(m[:3, :3]) > 1e12:
        check.fail(key, "an invertible transform", t, "A zero scale flattens the mesh.")
    return m


def _read_matrix(check: Checker, rows, key: str) -> np.ndarray:
    expected = "a 4 x 4 affine matrix (four rows of four numbers, the last row 0 0 0 1)"
    if not isinstance(rows, list) or len(rows) != 4 or not all(isinstance(r, list) and len(r) == 4 for r in rows):
        check.fail(key, expected, rows)
    for i, r in enumerate(rows):
        for j, x in enumerate(r):
            check.number(x, f"{key}[{i}][{j}]", "a finite number")
    m = np.array(rows, dtype=np.float64)
    if not np.allclose(m[3], [0, 0, 0, 1], rtol=0, atol=1e-12):
        check.fail(key, expected, rows, "Projective transforms are not supported.")
    return m


def transform_matrix(translate, rotate, scale) -> np.ndarray:
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
