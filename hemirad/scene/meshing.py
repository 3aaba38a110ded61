"""Turn a scene's objects into the initial triangle mesh the solver starts from.

Every planar face (of a room or a box), every quad and every smooth patch of one material
of an imported mesh becomes its own *surface*: vertices are shared inside a surface and
never between surfaces, so vertex averaging of radiosity never blends across a crease, a
change of material or an object boundary. Planar pieces are laid out as near-square grids;
imported meshes are split at sharp edges and where their faces' materials differ, and
subdivided until no edge is longer than the element size.

Everything here is deterministic: the same scene gives bit-identical arrays.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace
from fractions import Fraction
from pathlib import Path

import numpy as np
import torch

from hemirad.core.errors import HemiradInputError, HemiradWarning
from hemirad.geometry.creases import CREASE_STRIP, crease_sides
from hemirad.geometry.mesh import Mesh
from hemirad.scene.contacts import (CONTACT_TOLERANCE, SurfaceGeometry, bounding_boxes, conform_to_contacts,
                                    overlapping, scene_size, unit_normals)
from hemirad.scene.intersections import cut_at_intersections
from hemirad.scene.meshfile import MeshContents, MeshFileUnreadable, clean_triangles, contents_of
from hemirad.scene.model import Box, MeshFile, Quad, Room, Scene

# ceil(length / size) with a little slack, so 0.9 / 0.3 = 3.0000000000000004 gives 3 cells.
_CELL_SLACK = 1e-9


@dataclass
class _Surface:
    name: str
    vertices: torch.Tensor  # (V, 3) float64
    triangles: torch.Tensor  # (T, 3) int64, indices into vertices
    material: int
    element_size: float  # what it was meshed at
    # its outline triangles, as described (a quad's two, a mesh patch's own before
    # subdivision): (V, 3) float64 and (T, 3) int64; closed solids are found from them
    shell: tuple[np.ndarray, np.ndarray]
    # the (4, 3) corners of the quad it is the grid of (None once remeshed or cut)
    quad: torch.Tensor | None = None
    # (C, 2, 3) the sides of that quad its grid is graded toward (concave creases)
    creases: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))


# ----------------------------------------------------------------------------------------
# planar pieces


def _cells(length: float, element_size: float) -> int:
    ratio = length / element_size
    if not math.isfinite(ratio):  # past 1e308 cells: counted exactly, only ever to be refused
        return max(1, math.ceil(Fraction(length) / Fraction(element_size)))
    return max(1, math.ceil(ratio - _CELL_SLACK))


def _quad_cells(c: torch.Tensor, element_size: float) -> tuple[int, int]:
    """The grid ``grid_quad`` lays over the quad ``c`` (4, 3): cells along edge 01 and edge 03."""
    nu = _cells(max(float((c[1] - c[0]).norm()), float((c[2] - c[3]).norm())), element_size)
    nv = _cells(max(float((c[3] - c[0]).norm()), float((c[2] - c[1]).norm())), element_size)
    return nu, nv


def quad_triangles(corners, element_size: float) -> int:
    """How many triangles ``grid_quad`` makes of a quad, counted without making them (an
    exact integer, however large: a long thin quad at a small size makes a great many)."""
    nu, nv = _quad_cells(torch.as_tensor(corners, dtype=torch.float64).reshape(4, 3), element_size)
    return 2 * nu * nv


def _grid_lines(cells: int, graded_low: bool, graded_high: bool) -> torch.Tensor:
    """(cells + 1 + graded sides,) the grid's parameters along one axis: equal cells, and in
    the first and last cell a line ``CREASE_STRIP`` of a cell from a graded side."""
    lines = torch.linspace(0.0, 1.0, cells + 1, dtype=torch.float64)
    strip = CREASE_STRIP / cells
    extra = ([strip] if graded_low else []) + ([1.0 - strip] if graded_high else [])
    return torch.sort(torch.cat([lines, torch.tensor(extra, dtype=torch.float64)])).values


def grid_quad(corners: torch.Tensor, element_size: float,
              graded: tuple[bool, bool, bool, bool] = (False, False, False, False)) -> tuple[torch.Tensor, torch.Tensor]:
    """Lay a near-square grid over a quad and split each cell into two triangles.

    The quad is interpolated bilinearly between its corners, so a slightly non-planar
    quad (such as the Cornell box's red wall) is followed faithfully. Each cell is split
    along its shorter diagonal, which avoids needlessly thin triangles on skewed quads.

    Args:
        corners: (4, 3) corners in order around the quad; the front (normal) side is given
            by the right-hand rule over corners 0, 1, 2.
        element_size: target cell side; edge 01 (and 32) get ``ceil(length / size)`` cells,
            likewise edge 03 (and 12).
        graded: per side (01, 12, 23, 30), whether the cells along it are split
            ``CREASE_STRIP`` of a cell from it, a strip of thin elements along a concave
            crease (``hemirad.geometry.creases``).

    Returns:
        vertices: ((nu + 1) * (nv + 1), 3) float64, row-major over (v, u) (nu and nv
            counting the strips' cells).
        triangles: (2 * nu * nv, 3) int64, wound like the quad.
    """
    if not element_size > 0:
        raise ValueError(f"element_size must be positive, got {element_size}")
    c = torch.as_tensor(corners, dtype=torch.float64).reshape(4, 3)
    nu, nv = _quad_cells(c, element_size)

    u = _grid_lines(nu, graded[3], graded[1])
    v = _grid_lines(nv, graded[0], graded[2])
    nu, nv = len(u) - 1, len(v) - 1
    vv, uu = torch.meshgrid(v, u, indexing="ij")  # (nv + 1, nu + 1)
    uu, vv = uu[..., None], vv[..., None]
    grid = (1 - uu) * (1 - vv) * c[0] + uu * (1 - vv) * c[1] + uu * vv * c[2] + (1 - uu) * vv * c[3]
    vertices = grid.reshape(-1, 3)

    # cell (i, j) has corners a, b, c, d in the quad's own order 0, 1, 2, 3
    j, i = torch.meshgrid(torch.arange(nv), torch.arange(nu), indexing="ij")
    a = (j * (nu + 1) + i).reshape(-1)
    b, d = a + 1, a + nu + 1
    cc = d + 1
    ac = (vertices[cc] - vertices[a]).norm(dim=1)
    bd = (vertices[d] - vertices[b]).norm(dim=1)
    # On rectangles the diagonals tie; the tolerance keeps rounding from choosing at random.
    use_bd = (bd < ac * (1 - 1e-9))[:, None]
    first = torch.where(use_bd, torch.stack([a, b, d], 1), torch.stack([a, b, cc], 1))
    second = torch.where(use_bd, torch.stack([b, cc, d], 1), torch.stack([a, cc, d], 1))
    triangles = torch.stack([first, second], 1).reshape(-1, 3)
    return vertices, triangles


def box_face_corners(lo, hi, face: str, inward: bool) -> torch.Tensor:
    """(4, 3) corners of one face of the axis-aligned box [lo, hi], ordered so that the
    right-hand-rule normal points into the box (``inward``) or out of it.

    ``face`` is one of ``floor``/``ceiling`` (y = lo/hi), ``x_min``, ``x_max``, ``z_min``,
    ``z_max``.
    """
    axis, at_max = {"floor": (1, False), "ceiling": (1, True), "x_min": (0, False),
                    "x_max": (0, True), "z_min": (2, False), "z_max": (2, True)}[face]
    # (u, v) are the in-plane axes with e_u x e_v = +e_axis, so the order
    # (u0 v0), (u1 v0), (u1 v1), (u0 v1) has its normal along +axis.
    ua, va = (axis + 1) % 3, (axis + 2) % 3
    uv = [(0, 0), (1, 0), (1, 1), (0, 1)]
    # Along +axis is inward on the min face and outward on the max face.
    if inward == at_max:
        uv = uv[::-1]
    corners = torch.empty(4, 3, dtype=torch.float64)
    for k, (iu, iv) in enumerate(uv):
        corners[k, axis] = hi[axis] if at_max else lo[axis]
        corners[k, ua] = (lo, hi)[iu][ua]
        corners[k, va] = (lo, hi)[iv][va]
    return corners


def _quad_shell(corners: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """A quad's (4, 3) ``corners`` as its two outline triangles."""
    return corners.numpy().astype(np.float64), np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)


_BOX_FACE_NAMES = {"floor": "bottom", "ceiling": "top", "x_min": "x_min", "x_max": "x_max",
                   "z_min": "z_min", "z_max": "z_max"}


def _room_surfaces(room: Room, label: str, scene: Scene) -> list[_Surface]:
    out = []
    for face in Room.FACE_NAMES:
        override = room.faces.get(face)
        material = (override.material if override and override.material else None) or room.material
        size = (override.element_size if override and override.element_size else None) or room.element_size
        corners = box_face_corners(room.min, room.max, face, inward=True)
        v, t = grid_quad(corners, size)
        out.append(_Surface(f"{label}.{face}", v, t, scene.material_index(material), size, _quad_shell(corners),
                            corners))
    return out


def _box_surfaces(box: Box, label: str, scene: Scene) -> list[_Surface]:
    out = []
    for face in Room.FACE_NAMES:
        corners = box_face_corners(box.min, box.max, face, inward=False)
        v, t = grid_quad(corners, box.element_size)
        out.append(_Surface(f"{label}.{_BOX_FACE_NAMES[face]}", v, t, scene.material_index(box.material),
                            box.element_size, _quad_shell(corners), corners))
    return out


def _quad_surfaces(quad: Quad, label: str, scene: Scene) -> list[_Surface]:
    corners = torch.tensor(quad.corners, dtype=torch.float64)
    v, t = grid_quad(corners, quad.element_size)
    return [_Surface(label, v, t, scene.material_index(quad.material), quad.element_size, _quad_shell(corners),
                     corners)]


# ----------------------------------------------------------------------------------------
# imported meshes


def smooth_patches(vertices: np.ndarray, faces: np.ndarray, crease_angle: float,
                   groups: np.ndarray | None = None) -> list[np.ndarray]:
    """Group faces into patches joined across edges no sharper than ``crease_angle`` (degrees).

    Two faces are joined when they share an edge, their normals differ by at most the
    crease angle and they are in the same group (``groups``: (F,) int64, e.g. their
    materials; None: all in one); patches are the connected components of that relation.
    Faces with opposite winding across an edge differ by nearly 180 degrees and so stay apart.

    Returns:
        A list of (F_k,) int64 face-index arrays, ordered by their smallest face index,
        each sorted; together they partition ``range(len(faces))``.
    """
    import trimesh
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(faces)
    tm = trimesh.Trimesh(vertices, faces, process=False, validate=False)
    pairs = np.asarray(tm.face_adjacency, dtype=np.int64).reshape(-1, 2)
    angles = np.asarray(tm.face_adjacency_angles, dtype=np.float64).reshape(-1)
    joined = pairs[angles <= math.radians(crease_angle) + 1e-9]
    if groups is not None:
        joined = joined[groups[joined[:, 0]] == groups[joined[:, 1]]]
    graph = coo_matrix((np.ones(len(joined)), (joined[:, 0], joined[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    # scipy numbers components in order of their first face, so this order is stable
    order = np.argsort(labels, kind="stable")
    splits = np.flatnonzero(np.diff(labels[order])) + 1
    return [np.sort(p) for p in np.split(order, splits)]


def _subdivide(vertices: np.ndarray, faces: np.ndarray, element_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Bisect edges longer than ``element_size`` until none is left (conforming: each long
    edge gets one shared midpoint, so no T-vertices appear inside the patch)."""
    from trimesh.remesh import subdivide_to_size

    longest = float(np.linalg.norm(vertices[faces] - vertices[np.roll(faces, 1, axis=1)], axis=2).max())
    # Each round halves every long edge; the slack covers the medians the splits create.
    rounds = 2 * max(0, math.ceil(math.log2(max(longest / element_size, 1.0)))) + 8
    v, f = subdivide_to_size(vertices, faces, max_edge=element_size, max_iter=rounds)
    return np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)


def _face_materials(obj: MeshFile, contents: MeshContents, label: str, scene: Scene) -> np.ndarray:
    """(F,) int64 the scene material index of each face of the file: the object's material, or
    the scene material ``obj.file_materials`` names for the file's material of the face."""
    if obj.material is not None:
        return np.full(len(contents.faces), scene.material_index(obj.material), dtype=np.int64)
    names = [m.name for m in contents.materials.materials]
    table = np.array([scene.material_index(obj.file_materials[n]) if n in obj.file_materials else -1
                      for n in names] + [-1], dtype=np.int64)  # the last for a face with none
    per_face = table[contents.face_materials]
    if (per_face < 0).any():
        raise HemiradInputError(f"{label}: {int((per_face < 0).sum())} faces of the mesh file {obj.path} have no "
                                f"material (the object gives none, and neither does the file or its file_materials)")
    return per_face


def _mesh_file_surfaces(obj: MeshFile, label: str, scene: Scene) -> list[_Surface]:
    try:
        contents = contents_of(obj)
    except MeshFileUnreadable as exc:
        raise HemiradInputError(f"could not read the mesh file {obj.path}: {exc}") from exc
    raw_vertices, raw_faces = contents.vertices, contents.faces
    if len(raw_faces) == 0:
        raise HemiradInputError(f"{label}: the mesh file {obj.path} holds no triangles")
    if raw_faces.min() < 0 or raw_faces.max() >= len(raw_vertices):
        raise HemiradInputError(f"{label}: the mesh file {obj.path} indexes vertices it does not have")
    face_material = _face_materials(obj, contents, label, scene)

    # Merge by exact position so adjacency sees through per-corner normals and UVs
    # (and STL's unshared corners); np.unique's sorted order keeps this deterministic.
    vertices, inverse = np.unique(raw_vertices, axis=0, return_inverse=True)
    faces = inverse.reshape(-1)[raw_faces]

    m = np.asarray(obj.transform, dtype=np.float64)
    vertices = vertices @ m[:3, :3].T + m[:3, 3]
    if np.linalg.det(m[:3, :3]) < 0:
        faces = faces[:, [0, 2, 1]]  # a mirroring transform would turn every face inside out

    keep, dropped = clean_triangles(vertices, faces)
    if not keep.all():
        reasons = ", ".join(f"{n} {why}" for why, n in dropped.items() if n)
        warnings.warn(f"{label}: dropped {int((~keep).sum())} of {len(faces)} triangles of "
                      f"{Path(obj.path).name} ({reasons})", HemiradWarning, stacklevel=3)
    faces, face_material = faces[keep], face_material[keep]
    if len(faces) == 0:
        raise HemiradInputError(f"{label}: the mesh file {obj.path} has no triangle with a non-zero area")

    # a patch has one material: vertices are not shared (nor radiosity averaged) across a
    # material's edge, as between a room's faces
    patches = smooth_patches(vertices, faces, obj.crease_angle, face_material)
    out = []
    for k, patch in enumerate(patches):
        used, local = np.unique(faces[patch], return_inverse=True)
        shell = (vertices[used], local.reshape(-1, 3).astype(np.int64))
        v, f = _subdivide(*shell, obj.element_size)
        name = label if len(patches) == 1 else f"{label}.patch{k}"
        out.append(_Surface(name, torch.from_numpy(v), torch.from_numpy(f), int(face_material[patch[0]]),
                            obj.element_size, shell))
    return out


# ----------------------------------------------------------------------------------------
# the scene


def _labels(scene: Scene) -> list[str]:
    """One name per object; a name shared by several objects falls back to ``objects[i]``."""
    names = [o.name for o in scene.objects]
    return [n if names.count(n) == 1 else f"objects[{i}]" for i, n in enumerate(names)]


def surface_objects(scene: Scene, mesh: Mesh) -> np.ndarray:
    """(S,) int64 the index in ``scene.objects`` of each surface of ``build_mesh(scene)``'s mesh,
    from the surface names (``<object>`` or ``<object>.<face or patch>``)."""
    labels = {label: i for i, label in enumerate(_labels(scene))}
    return np.asarray([labels[name] if name in labels else labels[name.rsplit(".", 1)[0]]
                       for name in mesh.surface_names], dtype=np.int64)


def _remeshed(surfaces: list[_Surface], meshes: list[tuple[np.ndarray, np.ndarray] | None]) -> list[_Surface]:
    """The surfaces with the new (vertices, triangles) of those ``meshes`` gives (None: as
    they were), those left with no triangle dropped."""
    out = []
    for surface, new in zip(surfaces, meshes):
        if new is None:
            out.append(surface)
        elif len(new[1]):
            v, t = (torch.from_numpy(np.ascontiguousarray(a)) for a in new)
            out.append(_Surface(surface.name, v.to(torch.float64), t.to(torch.int64), surface.material,
                                surface.element_size, surface.shell))
    return out


def _geometry(surfaces: list[_Surface]) -> list[SurfaceGeometry]:
    return [SurfaceGeometry(s.vertices.numpy(), s.triangles.numpy(), s.element_size, s.creases) for s in surfaces]


#: Only sides at least this many cells long get a strip: along a short side (a desk leg's
#: foot, one cell) it cost patches and gained nothing (office, the answer from twice its
#: shipped elements to a third of the finest uniform mesh's: relMSE 0.0000431 in 5.2 s
#: against 0.0000445 in 5.6-5.8 s with every crease graded).
CREASE_CELLS = 2


def _grade_creases(surfaces: list[_Surface]) -> list[_Surface]:
    """The grids of quads with a strip of thin elements along each side at least
    ``CREASE_CELLS`` long that is a concave crease (``hemirad.geometry.creases``)."""
    if not surfaces:
        return surfaces
    geometry = _geometry(surfaces)
    tolerance = CONTACT_TOLERANCE * scene_size(geometry)
    corners = [g.vertices[g.triangles] for g in geometry]
    normals = [unit_normals(c) for c in corners]
    low, high = bounding_boxes(corners)
    out = []
    for i, surface in enumerate(surfaces):
        if surface.quad is None:
            out.append(surface)
            continue
        nu, nv = _quad_cells(surface.quad, surface.element_size)
        long_enough = np.array([nu, nv, nu, nv]) >= CREASE_CELLS
        near = np.flatnonzero(overlapping(low, high, i, tolerance))
        quad = surface.quad.numpy()
        sides = crease_sides(quad, np.concatenate([corners[j] for j in near]).reshape(-1, 3, 3),
                             np.concatenate([normals[j] for j in near]).reshape(-1, 3), tolerance, long_enough) \
            if len(near) and long_enough.any() else np.zeros(4, dtype=bool)
        if not sides.any():
            out.append(surface)
            continue
        v, t = grid_quad(surface.quad, surface.element_size, tuple(bool(x) for x in sides))
        creases = np.stack([quad[np.flatnonzero(sides)], quad[(np.flatnonzero(sides) + 1) % 4]], axis=1)
        out.append(replace(surface, vertices=v, triangles=t, creases=creases))
    return out


def _conform_to_contacts(surfaces: list[_Surface]) -> list[_Surface]:
    """The surfaces with those others touch meshed anew, and those covered whole dropped."""
    return _remeshed(surfaces, conform_to_contacts(_geometry(surfaces)))


def _cut_at_intersections(surfaces: list[_Surface]) -> list[_Surface]:
    """The surfaces cut where others pass through them, what closed solids hold dropped."""
    return _remeshed(surfaces, cut_at_intersections(_geometry(surfaces), [s.shell for s in surfaces]))


def build_mesh(scene: Scene) -> Mesh:
    """The initial mesh of a scene: one or more surfaces per object, in object order.

    Surface names are ``<object>.<face>`` for rooms (floor, ceiling, x_min, x_max, z_min,
    z_max) and boxes (bottom, top, x_min, ...), ``<object>`` for quads and ``<object>`` or
    ``<object>.patch<k>`` for the smooth patches (each of one material) of imported meshes,
    where ``<object>`` is the object's name (the loader names unnamed objects ``objects[i]``).

    With ``scene.meshing.intersections`` (on by default), surfaces are cut where others pass
    through them and what lies inside a closed solid is left out
    (``hemirad.scene.intersections``). With ``scene.meshing.creases`` (by default with
    refinement judged on the answer), a quad's grid gets a strip of thin elements along each
    side where another surface stands facing it (``hemirad.geometry.creases``). Then, with
    ``scene.meshing.contacts`` (by default
    with refinement judged on the answer), a planar surface that others touch is meshed
    conforming to where they touch, what they cover left out (``hemirad.scene.contacts``); a surface they cover whole is
    left out altogether.
    """
    surfaces: list[_Surface] = []
    builders = {Room: _room_surfaces, Box: _box_surfaces, Quad: _quad_surfaces, MeshFile: _mesh_file_surfaces}
    for obj, label in zip(scene.objects, _labels(scene)):
        surfaces.extend(builders[type(obj)](obj, label, scene))
    if scene.meshing.intersections:
        surfaces = _cut_at_intersections(surfaces)
    if scene.meshes_creases:
        surfaces = _grade_creases(surfaces)
    if scene.meshes_contacts:
        surfaces = _conform_to_contacts(surfaces)

    vertices, triangles, surface, material = [], [], [], []
    offset = 0
    for s, surf in enumerate(surfaces):
        vertices.append(surf.vertices)
        triangles.append(surf.triangles + offset)
        surface.append(torch.full((len(surf.triangles),), s, dtype=torch.int64))
        material.append(torch.full((len(surf.triangles),), surf.material, dtype=torch.int64))
        offset += len(surf.vertices)
    if not surfaces:
        empty = torch.zeros(0, dtype=torch.int64)
        return Mesh(torch.zeros(0, 3, dtype=torch.float64), torch.zeros(0, 3, dtype=torch.int64), empty, empty, [])
    return Mesh(torch.cat(vertices), torch.cat(triangles), torch.cat(surface), torch.cat(material),
                [s.name for s in surfaces])
