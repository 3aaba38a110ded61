"""The triangle mesh the solver works on: geometry and per-element bookkeeping, no algorithms.

Elements are triangles. Vertices are shared only inside one *surface* (a planar face of a
room or box, a quad, or a smooth patch of an imported mesh), so averaging element values to
vertices never blends across a crease or between objects.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Any, Callable, Hashable

import torch

from hemirad.core.device import as_tensor
from hemirad.core.fastops import row_sums


class DerivedCache:
    """Values derived from an immutable object's data, each computed once and then kept.

    The model is trimesh's ``Cache``, without its change tracking: the owner (a ``Mesh``)
    never changes, so nothing stored here can go stale and nothing is ever dropped. Keys are
    the names of what is stored (a mesh uses its property names: ``"centroids"``,
    ``"areas"``, ``"normals"``, ``"plane_ids"``, ...). ``put`` is how a mesh made from
    another (a split) is handed values already known, so they are not computed again.
    """

    __slots__ = ("_values",)

    def __init__(self):
        self._values: dict[Hashable, Any] = {}

    def get(self, key: Hashable, compute: Callable[[], Any] | None = None) -> Any:
        """The value stored under ``key``; if there is none, ``compute()``, stored under
        ``key`` and returned (None where no ``compute`` is given)."""
        try:
            return self._values[key]
        except KeyError:
            return None if compute is None else self.put(key, compute())

    def put(self, key: Hashable, value: Any) -> Any:
        """Store ``value`` under ``key`` (it must be what ``get``'s compute would give) and
        return it."""
        self._values[key] = value
        return value

    def contains(self, key: Hashable) -> bool:
        """Whether a value is stored under ``key`` (computed or put)."""
        return key in self._values

    __contains__ = contains

    def __repr__(self) -> str:
        return f"DerivedCache({sorted(map(str, self._values))})"


@dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh with a surface and a material per triangle. Immutable: assigning an
    attribute raises ``dataclasses.FrozenInstanceError``; splitting and ``to`` return new
    meshes, and ``dataclasses.replace(mesh, surface=...)`` makes a changed copy. (The
    tensors must not be written in place either: the derived values in ``cache`` rely on
    it.) Equality is identity: two meshes are never compared tensor by tensor.

    Attributes:
        vertices: (V, 3) float64 positions.
        triangles: (T, 3) int64 vertex indices, counter-clockwise seen from the front
            (the normal is ``(v1 - v0) x (v2 - v0)``).
        surface: (T,) int64 surface index of each triangle.
        material: (T,) int64 index into the scene's material table.
        surface_names: one readable name per surface, e.g. ``"objects[0].floor"``.
        level: (T,) int64 refinement depth of each triangle (0 for the initial mesh).
        edge_parents: (V, 2) int64: for a vertex made at the midpoint of an edge by
            splitting, that edge's two end vertices; -1 for every other vertex. This is
            what finds the T-vertices that edge splitting leaves on unsplit neighbours.
        cache: the ``DerivedCache`` of what is computed from the above (``corners``,
            ``centroids``, ``areas``, ``normals``, ``plane_ids``, the midpoint index of
            ``edges.midpoint_index``): computed once per mesh, or handed over by the split
            that made it (``inherit_geometry``, ``cache.put``).
    """

    vertices: torch.Tensor
    triangles: torch.Tensor
    surface: torch.Tensor
    material: torch.Tensor
    surface_names: list[str] = field(default_factory=list)
    level: torch.Tensor | None = None
    edge_parents: torch.Tensor | None = None
    cache: DerivedCache = field(default_factory=DerivedCache, init=False, repr=False)

    def __post_init__(self):
        # The one place the fields are written: normalising what __init__ was given.
        def settle(name: str, value, dtype: torch.dtype, shape: tuple[int, ...]) -> None:
            object.__setattr__(self, name, as_tensor(value, dtype=dtype).reshape(shape))

        settle("vertices", self.vertices, torch.float64, (-1, 3))
        for name, shape in (("triangles", (-1, 3)), ("surface", (-1,)), ("material", (-1,))):
            settle(name, getattr(self, name), torch.int64, shape)
        n = len(self.triangles)
        level, parents = self.level, self.edge_parents
        if level is None:
            level = torch.zeros(n, dtype=torch.int64, device=self.triangles.device)
        if parents is None:
            parents = torch.full((len(self.vertices), 2), -1, dtype=torch.int64, device=self.vertices.device)
        settle("level", level, torch.int64, (-1,))
        settle("edge_parents", parents, torch.int64, (-1, 2))
        if len(self.surface) != n or len(self.material) != n or len(self.level) != n:
            raise ValueError("surface, material and level need one entry per triangle")
        if len(self.edge_parents) != len(self.vertices):
            raise ValueError("edge_parents needs one row per vertex")

    @property
    def num_elements(self) -> int:
        return len(self.triangles)

    # The derived geometry below is computed once per mesh and kept in ``cache`` (or handed
    # over by ``inherit_geometry``).
    @property
    def corners(self) -> torch.Tensor:
        """(T, 3, 3) float64 the three vertex positions of every triangle."""
        return self.cache.get("corners", lambda: self.vertices[self.triangles])

    @property
    def centroids(self) -> torch.Tensor:
        """(T, 3) float64"""
        return self.cache.get("centroids", lambda: _centroids(self.vertices, self.triangles))

    @property
    def _cross(self) -> torch.Tensor:
        return self.cache.get("cross", lambda: _cross(self.corners))

    @property
    def areas(self) -> torch.Tensor:
        """(T,) float64"""
        return self.cache.get("areas", lambda: _area(self._cross))

    @property
    def normals(self) -> torch.Tensor:
        """(T, 3) float64 unit normals."""
        return self.cache.get("normals", lambda: _unit(self._cross))

    def corners_of(self, index) -> torch.Tensor:
        """(..., 3, 3) the vertex positions of the triangles ``index`` (an int or an (R,)
        tensor), without computing every triangle's (``corners``)."""
        if isinstance(index, torch.Tensor) and index.dim() == 1:  # index_select: several times faster
            vertex = self.triangles.index_select(0, index).reshape(-1)
            return self.vertices.index_select(0, vertex).reshape(len(index), 3, 3)
        return self.vertices[self.triangles[index]]

    _HANDED_OVER = ("centroids", "areas", "normals")

    def inherit_geometry(self, old: "Mesh", rows: torch.Tensor) -> None:
        """Take over ``old``'s computed centroids, areas and normals: this mesh has ``old``'s
        triangles at the same indices except at ``rows`` (replaced ones, and every index
        past ``old``'s end), and only those rows are computed. Every formula works row by
        row, so the numbers are the ones a computation of all rows gives. (``corners``, the
        largest, is not handed over: the solver reads it by ``corners_of``.)

        Args:
            old: the mesh this one was made from (its vertices are a prefix of this one's).
            rows: (K,) int64 indices into this mesh.
        """
        names = [name for name in self._HANDED_OVER if old.cache.contains(name)]
        if not names:
            return
        corners = self.corners_of(rows)
        cross = _cross(corners)
        fresh = {"centroids": lambda: (corners[:, 0] + corners[:, 1] + corners[:, 2]) / 3.0,
                 "areas": lambda: _area(cross), "normals": lambda: _unit(cross)}
        for name in names:
            before = old.cache.get(name)
            merged = torch.empty((self.num_elements, *before.shape[1:]), dtype=before.dtype, device=before.device)
            merged[:len(before)] = before
            self.cache.put(name, merged.index_copy_(0, rows, fresh[name]()))

    @property
    def plane_ids(self) -> torch.Tensor:
        """(T,) int64: the elements of one planar surface share an id; an element of a curved
        surface has one of its own. (Elements with different ids may still be coplanar.)
        Split meshes inherit their parent's ids, children lying in their parent's plane."""
        return self.cache.get("plane_ids", self._plane_ids)

    def _plane_ids(self) -> torch.Tensor:
        normals, T = self.normals, self.num_elements
        offsets = (normals * self.centroids).sum(1, keepdim=True)
        planes = torch.cat([normals, offsets / max(float(self.vertices.abs().max()), 1e-30)], dim=1)  # (T, 4)
        S = int(self.surface.max()) + 1 if T else 0
        index = self.surface[:, None].expand(-1, 4)
        high = torch.full((S, 4), -torch.inf, dtype=planes.dtype, device=planes.device).scatter_reduce(0, index, planes, "amax")
        low = torch.full((S, 4), torch.inf, dtype=planes.dtype, device=planes.device).scatter_reduce(0, index, planes, "amin")
        planar = ((high - low) < 1e-6).all(dim=1)  # (S,)
        return torch.where(planar[self.surface], self.surface, S + torch.arange(T, device=planes.device))

    def bounding_box(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self.vertices.min(dim=0).values, self.vertices.max(dim=0).values

    _TENSORS = ("vertices", "triangles", "surface", "material", "level", "edge_parents")

    def to(self, device: torch.device | str) -> "Mesh":
        """The same mesh with its tensors on ``device`` (itself when they are there already)."""
        device = torch.device(device)
        if self.vertices.device == device:
            return self
        return Mesh(**{k: getattr(self, k).to(device) for k in self._TENSORS}, surface_names=list(self.surface_names))

    def state_dict(self) -> dict:
        """The mesh as tensors and its surface names (a list of strings), for checkpoints."""
        return {**{k: getattr(self, k).cpu().clone() for k in self._TENSORS}, "surface_names": list(self.surface_names)}

    @classmethod
    def from_state_dict(cls, state: dict) -> "Mesh":
        """The mesh ``state_dict`` described; ValueError if the parts do not fit together."""
        if not all(isinstance(state.get(k), torch.Tensor) for k in cls._TENSORS):
            raise ValueError(f"a mesh needs the tensors {', '.join(cls._TENSORS)}")
        names = state.get("surface_names")
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise ValueError("surface_names must be a list of strings")
        mesh = cls(**{k: state[k] for k in cls._TENSORS}, surface_names=names)
        if mesh.num_elements and (int(mesh.triangles.min()) < 0 or int(mesh.triangles.max()) >= len(mesh.vertices)):
            raise ValueError("triangles index vertices the mesh does not have")
        return mesh

    @staticmethod
    def concatenate(parts: list["Mesh"]) -> "Mesh":
        """Join meshes; surface indices and names are renumbered, materials kept."""
        vertices, triangles, surface, material, names, level, parents = [], [], [], [], [], [], []
        v_off = s_off = 0
        for p in parts:
            vertices.append(p.vertices)
            triangles.append(p.triangles + v_off)
            surface.append(p.surface + s_off)
            material.append(p.material)
            level.append(p.level)
            parents.append(torch.where(p.edge_parents >= 0, p.edge_parents + v_off, p.edge_parents))
            names.extend(p.surface_names or [f"surface{s_off + i}" for i in range(int(p.surface.max()) + 1 if len(p.surface) else 0)])
            v_off += len(p.vertices)
            s_off += int(p.surface.max()) + 1 if len(p.surface) else 0
        return Mesh(torch.cat(vertices), torch.cat(triangles), torch.cat(surface), torch.cat(material), names,
                    torch.cat(level), torch.cat(parents))


def vertex_sharing_pairs(mesh: Mesh) -> tuple[torch.Tensor, torch.Tensor]:
    """(P,) and (P,): the pairs (i, j) of elements that share a vertex, each element with
    itself included, sorted by i (the same surface only: vertices are not shared across
    surfaces)."""
    T = mesh.num_elements
    corner_element = torch.arange(T, device=mesh.triangles.device).repeat_interleave(3)
    with warnings.catch_warnings():  # torch's notes on its sparse support, not about these tensors
        warnings.simplefilter("ignore", UserWarning)
        incidence = torch.sparse_coo_tensor(
            torch.stack([corner_element, mesh.triangles.reshape(-1)]),
            torch.ones(3 * T, dtype=torch.float64, device=corner_element.device), (T, len(mesh.vertices)),
            check_invariants=False).coalesce()
        i, j = torch.sparse.mm(incidence, incidence.t()).coalesce().indices()
    return i, j


def barycentric(triangles: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """(n, 3) the barycentric coordinates of ``points`` (n, 3) in the planes of their
    ``triangles`` (n, 3, 3), by corner (a point outside its triangle has a negative one)."""
    a, b, c = triangles.unbind(1)
    e0, e1, p = b - a, c - a, points - a
    d00, d01, d11 = row_sums(e0 * e0), row_sums(e0 * e1), row_sums(e1 * e1)
    d20, d21 = row_sums(p * e0), row_sums(p * e1)
    det = d00 * d11 - d01 * d01
    v, w = (d11 * d20 - d01 * d21) / det, (d00 * d21 - d01 * d20) / det
    return torch.stack([1.0 - v - w, v, w], 1)


def _centroids(vertices: torch.Tensor, triangles: torch.Tensor) -> torch.Tensor:
    v, t = vertices, triangles
    return (v[t[:, 0]] + v[t[:, 1]] + v[t[:, 2]]) / 3.0  # mean(dim=1) over (T, 3, 3) is several times slower


def _cross(corners: torch.Tensor) -> torch.Tensor:
    """(T, 3) (v1 - v0) x (v2 - v0): twice the area, along the normal."""
    return torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])


def _area(cross: torch.Tensor) -> torch.Tensor:
    return 0.5 * cross.norm(dim=1)


def _unit(x: torch.Tensor) -> torch.Tensor:
    return x / x.norm(dim=1, keepdim=True)
