"""Patches: groups of initial elements that shoot together, and the tree of sub-patches each
may shoot from instead (docs/DESIGN.md §1.4).

A patch is the set of a planar surface's elements whose centroids fall into one square cell
of side ``patch_size`` laid over that plane; on a curved surface, a cap of the elements in
one cube of side ``patch_size`` whose normals lie within ``CURVED_PATCH_CONE`` of each other.
Each patch is split recursively into quadrants (of its own bounding square in the plane)
down to single elements: the nodes of that tree are the shooters a patch may use
where its centroid is a poor stand-in for its extent (``transport.shooters``).

Nodes are numbered depth-first, and every node's elements are one contiguous range of
*leaf positions*, so "is element e in node n" is ``lo[n] <= leaf[e] < hi[n]``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from hemirad.core.fastops import cross3
from hemirad.geometry.mesh import Mesh


@dataclass(frozen=True)
class PatchTree:
    """The patches of an initial mesh of T elements and their sub-patch trees (N nodes, P patches).

    Attributes:
        leaf: (T,) int64 each initial element's leaf position (a permutation of 0..T-1).
        patch: (T,) int64 each initial element's patch.
        root: (P,) int64 the node of each patch.
        lo, hi: (N,) int64 each node's range [lo, hi) of leaf positions.
        child_start: (N + 1,) int64 and child_ids: (C,) int64: the children of node n are
            ``child_ids[child_start[n]:child_start[n + 1]]`` (none: a single element).
        centroid, normal: (N, 3) float64 where a node shoots from: the area-weighted centroid
            of its elements (on a curved surface, ``_eye_point``) and their
            plane's unit normal.
    """

    leaf: torch.Tensor
    patch: torch.Tensor
    root: torch.Tensor
    lo: torch.Tensor
    hi: torch.Tensor
    child_start: torch.Tensor
    child_ids: torch.Tensor
    centroid: torch.Tensor
    normal: torch.Tensor

    @property
    def num_patches(self) -> int:
        return len(self.root)

    @property
    def num_nodes(self) -> int:
        return len(self.lo)

    def children(self, node: int) -> list[int]:
        return self.child_ids[int(self.child_start[node]):int(self.child_start[node + 1])].tolist()


# Degrees: the widest angle between the normals of one curved patch's elements and its largest
# element's. At 25 degrees a hemicube along the patch's mean normal misplaces at most ~10% of a
# member's cosine lobe (1 - cos 25 degrees) near its horizon.
CURVED_PATCH_CONE = 25.0


def element_sides(mesh: Mesh) -> np.ndarray:
    """(T,) each element's side: sqrt(2 A), the legs of the right isosceles triangles a
    square cell of that side is meshed into."""
    return np.sqrt(2.0 * mesh.areas.cpu().numpy())


def plane_axes(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors u, v spanning the plane of the unit ``normal`` (3,), u x v = normal;
    or of each of the (k, 3) ``normal``, as two (k, 3)."""
    normal = np.asarray(normal, dtype=np.float64)
    helper = np.eye(3)[np.argmin(np.abs(normal), axis=-1)]  # the world axis least along the normal
    u = cross3(helper, normal)
    u /= _lengths(u)[..., None]
    return u, cross3(normal, u)


def _lengths(x: np.ndarray) -> np.ndarray:
    """(...,) the length of each of the (..., 3) vectors ``x``, to the last bit as
    ``np.linalg.norm`` gives one vector's (a dot product; a sum of squares rounds otherwise)."""
    return np.sqrt((x[..., None, :] @ x[..., :, None])[..., 0, 0])


def _run_sums(x: np.ndarray, starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(k, 3) the sums of the k runs of rows ``x[starts[i]:starts[i] + counts[i]]`` of the
    (n, 3) ``x``, each added row after row, to the last bit as ``ndarray.sum(0)`` adds one
    run (``np.add.reduceat`` does not)."""
    total = x[starts].copy()
    by_length = np.argsort(-counts, kind="stable")
    for rank in range(1, int(counts.max(initial=1))):
        live = by_length[:int(np.searchsorted(-counts[by_length], -rank, side="left"))]
        total[live] += x[starts[live] + rank]
    return total


def build_patches(mesh: Mesh, patch_size: np.ndarray, owner: np.ndarray | None = None,
                  apart: np.ndarray | None = None) -> PatchTree:
    """Group the elements of ``mesh`` into patches of about ``patch_size`` (T,) (a side length
    per element, 0 for an element that shoots on its own; a plane takes its elements'
    median by area) and build each patch's quadrant tree. ``owner`` (T,): the object each element
    belongs to (default: its surface); a curved patch shoots as one only where no other
    object passes through it (``_curved_cells``). ``apart`` (T,) int: elements of different
    values never share a patch (default: all 0; ``rim_runs`` gives a footprint's sides)."""
    centroids = mesh.centroids.cpu().numpy()
    normals = mesh.normals.cpu().numpy()
    areas = mesh.areas.cpu().numpy()
    corners = mesh.corners.cpu().numpy()
    patch_size = np.asarray(patch_size)
    plane_ids = mesh.plane_ids.cpu().numpy()
    apart = np.zeros(len(plane_ids), dtype=np.int64) if apart is None else np.asarray(apart)
    groups, alone = _plane_cells(plane_ids, centroids, normals, areas, patch_size, apart)
    owner = mesh.surface.cpu().numpy() if owner is None else np.asarray(owner)
    groups += _curved_cells(alone, owner, centroids, normals, areas, corners, patch_size)
    return _grow_trees(mesh, groups)


def group_patches(mesh: Mesh, group: np.ndarray) -> PatchTree:
    """The patches of ``mesh`` given each element's ``group`` (T,) (integers; patches numbered
    in increasing group), each split into its quadrant tree. For a refined mesh whose
    elements carry the patch of the initial element they lie in
    (``PatchShooters.inherit``): refinement makes elements inside patches, not new patches."""
    _, key = np.unique(np.asarray(group), return_inverse=True)
    order = np.argsort(key, kind="stable")
    cuts = np.flatnonzero(np.diff(key[order])) + 1
    u, v = _mean_plane_axes(order, mesh.normals.cpu().numpy(), mesh.areas.cpu().numpy(), np.r_[0, cuts])
    return _grow_trees(mesh, list(zip(np.split(order, cuts), u, v)))


def _grow_trees(mesh: Mesh, groups: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> PatchTree:
    """The tree of patches ``groups`` (members (k,), plane axes u, v), in order: every patch
    split into the quadrants of its centroids' bounding square in its plane, down to single
    elements, all patches' nodes of one depth at a time.

    Each splitting node's elements are one contiguous run of ``order`` (position -> element);
    a stable sort of each run by quadrant makes its children's runs, so ``order`` ends as the
    leaves' order. Nodes are made breadth-first and numbered depth-first at the end."""
    centroids, normals, areas = (x.cpu().numpy() for x in (mesh.centroids, mesh.normals, mesh.areas))
    corners, plane_ids = mesh.corners.cpu().numpy(), mesh.plane_ids.cpu().numpy()
    sizes = np.asarray([len(members) for members, _, _ in groups], dtype=np.int64)
    order = np.concatenate([members for members, _, _ in groups]).astype(np.int64)
    # positions in the plane, once per patch: a node's quadrants are of its own points' box
    xy = np.concatenate([centroids[members] @ np.stack([u, v]).T for members, u, v in groups])
    patch = np.empty(mesh.num_elements, dtype=np.int64)
    patch[order] = np.repeat(np.arange(len(groups)), sizes)
    lo = _exclusive_cumsum(sizes)
    levels = [(np.arange(len(groups)), lo, lo + sizes, np.full(len(groups), -1))]  # (ids, lo, hi, parent)
    eyes = []  # per level: (ids, eye, normal) of its nodes of several elements
    count = len(groups)
    while True:
        ids, lo, hi, _ = levels[-1]
        split = hi - lo > 1
        if not split.any():
            break
        ids, lo, n = ids[split], lo[split], (hi - lo)[split]
        at = np.repeat(lo - _exclusive_cumsum(n), n) + np.arange(int(n.sum()))  # the runs' positions
        run = np.repeat(np.arange(len(lo)), n)
        starts = _exclusive_cumsum(n)
        eyes.append((ids, *_node_eyes(order[at], starts, centroids, normals, areas, corners, plane_ids)))
        # quadrants of each run's bounding box; a run all in one splits in halves by position
        p = xy[at]
        mid = 0.5 * (np.minimum.reduceat(p, starts) + np.maximum.reduceat(p, starts))[run]
        quadrant = (p[:, 0] > mid[:, 0]).astype(np.int64) * 2 + (p[:, 1] > mid[:, 1])
        filled = np.bincount(run * 4 + quadrant, minlength=4 * len(lo)).reshape(-1, 4)
        alone = ((filled > 0).sum(1) == 1)[run]
        rank = np.arange(len(at)) - starts[run]
        quadrant = np.where(alone, (rank >= (n // 2)[run]).astype(np.int64), quadrant)
        counts = np.bincount(run * 4 + quadrant, minlength=4 * len(lo))
        by_quadrant = np.argsort(run * 4 + quadrant, kind="stable")
        order[at], xy[at] = order[at[by_quadrant]], xy[at[by_quadrant]]
        child = np.flatnonzero(counts)  # (run, quadrant) pairs holding elements, in order
        child_lo = lo[child // 4] + (np.cumsum(counts.reshape(-1, 4), 1) - counts.reshape(-1, 4)).reshape(-1)[child]
        levels.append((count + np.arange(len(child)), child_lo, child_lo + counts[child], ids[child // 4]))
        count += len(child)
    return _numbered_depth_first(levels, eyes, order, patch, centroids, normals)


def _plane_cells(plane_ids: np.ndarray, centroids: np.ndarray, normals: np.ndarray, areas: np.ndarray,
                 patch_size: np.ndarray, apart: np.ndarray
                 ) -> tuple[list[tuple[np.ndarray, np.ndarray, np.ndarray]], np.ndarray]:
    """The patches of the planes, as (members (k,), plane axes u, v): per plane, the elements
    whose centroids share a cell of the plane's square grid (its side the plane's median patch
    size by area, ``_median_patch_size``; its origin the lowest element centroid) and a value
    of ``apart`` (T,); and (m,) the elements alone on their plane (those of curved surfaces),
    left to ``_curved_cells``."""
    order = np.argsort(plane_ids, kind="stable")
    bounds = np.flatnonzero(np.diff(plane_ids[order])) + 1
    out, alone = [], []
    for members in np.split(order, bounds):
        if len(members) == 1:
            alone.append(members)
            continue
        u, v = (axis[0] for axis in _mean_plane_axes(members, normals, areas))
        size = _median_patch_size(patch_size[members], areas[members])
        if size <= 0:  # patches turned off
            out += _each_alone(members, normals)
            continue
        out += _each_alone(members[patch_size[members] <= 0], normals)  # those asked to shoot alone
        members = members[patch_size[members] > 0]
        xy = centroids[members] @ np.stack([u, v]).T  # (k, 2)
        # The grid starts at the lowest centroid, not at the plane's corner: aligned with the
        # element cells, every patch centroid falls on a mesh vertex, and measured on the
        # Cornell box against its reference that tripled the error (relative MSE
        # 0.0089 against 0.0025); why is not yet understood.
        origin = xy.min(0)
        cell = np.floor((xy - origin) / size).astype(np.int64)
        key = cell[:, 0] * (int(cell[:, 1].max()) + 1) + cell[:, 1]
        if apart[members].any():  # cells split by ``apart`` (all 0: the cells as they are)
            _, key = np.unique(np.stack([apart[members], key], axis=1), axis=0, return_inverse=True)
            key = key.reshape(-1)
        by_cell = np.argsort(key, kind="stable")
        cuts = np.flatnonzero(np.diff(key[by_cell])) + 1
        out += [(members[part], u, v) for part in np.split(by_cell, cuts)]
    return out, np.concatenate(alone) if alone else np.zeros(0, dtype=np.int64)


def _median_patch_size(sizes: np.ndarray, areas: np.ndarray) -> float:
    """The patch side of a plane's (or a curved object's) elements from their ``sizes`` (k,):
    the median weighted by ``areas`` (k,), the size asked for over half their area. Weighted
    by count, the strips along its creases and round its footprints, many and thin, set it
    (office's floor from the shipped sizes x2: 0.29 m against the 0.41 m asked for over most
    of its area, and 274 patches instead of 150)."""
    order = np.argsort(sizes, kind="stable")
    cumulative = np.cumsum(areas[order])
    return float(sizes[order][min(np.searchsorted(cumulative, 0.5 * cumulative[-1]), len(order) - 1)])


def _curved_cells(members: np.ndarray, owner: np.ndarray, centroids: np.ndarray, normals: np.ndarray,
                  areas: np.ndarray, corners: np.ndarray, patch_size: np.ndarray
                  ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The patches of curved surfaces from their (m,) elements, each alone on its plane: per
    object (``owner`` (T,)), caps (``_caps``) on a grid of side the object's median patch size
    by area."""
    out = []
    low, high = corners.min(1), corners.max(1)  # (T, 3) each element's bounding box
    for s in np.unique(owner[members]):
        group = members[owner[members] == s]
        size = _median_patch_size(patch_size[group], areas[group])
        if size <= 0:  # patches turned off: every element shoots alone
            out += _each_alone(group, normals)
        else:
            out += _caps(group, size, s, owner, centroids, normals, areas, low, high)
    return out


def _caps(group: np.ndarray, size: float, own: int, owner: np.ndarray, centroids: np.ndarray,
          normals: np.ndarray, areas: np.ndarray, low: np.ndarray, high: np.ndarray
          ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The caps of the elements ``group`` (k,) of object ``own``: those whose centroids share a
    cube of side ``size``, and whose normals lie within ``CURVED_PATCH_CONE`` of the cube's
    largest element's (one hemicube along their mean normal then stands in for them as it does
    for a plane patch; a sphere's cube holds a cap, a thin shell's two sides part). Where
    another object reaches into a cap's bounding box (``low``, ``high`` (T, 3), every
    element's), the cap is made again from cubes of half the side, down to single elements:
    a lamp's globe pierced by its holder must not shoot the light of its part inside the
    holder from a point outside it (measured on a furnished room: 6% too bright everywhere).
    Halving, rather than every element of such a cap shooting alone, leaves alone only those
    beside the other object: on that room 1,589 patches instead of 1,748 (the teapot, which
    reaches into a globe's bounding box, 376 -> 236; the globes 354 -> 335), 1,747 hemicubes
    instead of 1,906, the same error at its points (median 1.7%, relative RMS 3.4%)."""
    out = []
    cos_cone = np.cos(np.radians(CURVED_PATCH_CONE))
    cell = np.floor((centroids[group] - centroids[group].min(0)) / size).astype(np.int64)
    _, key = np.unique(cell, axis=0, return_inverse=True)
    for c in range(int(key.max()) + 1):
        left = group[key.reshape(-1) == c]
        while len(left):
            seed = left[int(np.argmax(areas[left]))]
            within = normals[left] @ normals[seed] >= cos_cone
            part = left[within]
            left = left[~within]
            if len(part) > 1 and _crossed(part, own, owner, low, high):
                spread = float(np.ptp(centroids[part], axis=0).max())
                out += (_caps(part, size / 2, own, owner, centroids, normals, areas, low, high)
                        if spread > 0 else _each_alone(part, normals))  # (centroids that coincide)
            else:
                out.append((part, *(axis[0] for axis in _mean_plane_axes(part, normals, areas))))
    return out


def _mean_plane_axes(elements: np.ndarray, normals: np.ndarray, areas: np.ndarray,
                     starts: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``plane_axes`` (g, 3) u and v of the area-weighted mean normal of each of g runs of
    ``elements`` (k,), run i being ``elements[starts[i]:starts[i + 1]]`` (default: one run,
    all of them), each sum added row after row (``_run_sums``)."""
    starts = np.zeros(1, dtype=np.int64) if starts is None else starts
    normal = _run_sums(normals[elements] * areas[elements, None], starts, np.diff(np.r_[starts, len(elements)]))
    return plane_axes(normal / _lengths(normal)[:, None])


@dataclass(frozen=True)
class HoleRim:
    """The rim of one hole in a planar surface of a mesh (m edges).

    Attributes:
        surface: the surface it lies in.
        a, b: (m,) int64 its edges' vertices, directed as its triangles give them.
        element: (m,) int64 the element each edge bounds.
        own: (k,) int64 the surface's elements; ends: (r,) int64 the rim's vertices.
    """

    surface: int
    a: np.ndarray
    b: np.ndarray
    element: np.ndarray
    own: np.ndarray
    ends: np.ndarray


def hole_rims(mesh: Mesh, least: np.ndarray | None = None) -> list[HoleRim]:
    """The rims of the holes in the planar surfaces of ``mesh``: where something stands on
    a surface (a block's footprint, left out by contact meshing, a lamp hung under a
    ceiling) or passes through it. A boundary loop is a hole where it runs clockwise seen
    from the surface's front (its signed area, sum (a x b) . n over its edges as the
    triangles give them, is negative); the outline runs counter-clockwise. With ``least``
    (T,), only the holes whose rim is at least as long as the median of ``least`` over the
    surface's elements by area (as its patch grid takes it). On a mesh refined with hanging
    vertices the split edges read as boundaries: find rims on the initial mesh."""
    triangles = mesh.triangles.cpu().numpy()
    vertices = mesh.vertices.cpu().numpy()
    normals = mesh.normals.cpu().numpy()
    areas = mesh.areas.cpu().numpy()
    surface = mesh.surface.cpu().numpy()
    rims = []
    for s in np.unique(surface):
        own = np.flatnonzero(surface == s)
        if len(own) < 2 or np.abs(normals[own] - normals[own[0]]).max() > 1e-9:  # planar surfaces only
            continue
        a = triangles[own].reshape(-1)
        b = triangles[own][:, [1, 2, 0]].reshape(-1)
        element = np.repeat(own, 3)
        keys = np.minimum(a, b) * len(vertices) + np.maximum(a, b)
        unique, counts = np.unique(keys, return_counts=True)
        boundary = np.isin(keys, unique[counts == 1])  # the directed edges on the boundary
        a, b, element = a[boundary], b[boundary], element[boundary]
        if len(a) == 0:
            continue
        # the boundary's loops: components of its vertices joined by its edges
        ends, index = np.unique(np.concatenate([a, b]), return_inverse=True)
        ia, ib = index[:len(a)], index[len(a):]
        graph = coo_matrix((np.ones(len(a)), (ia, ib)), shape=(len(ends), len(ends)))
        count, label = connected_components(graph, directed=False)
        loop = label[ia]
        signed = np.einsum("ij,j->i", cross3(vertices[a], vertices[b]), normals[own[0]])
        area, perimeter = np.zeros(count), np.zeros(count)
        np.add.at(area, loop, signed)
        np.add.at(perimeter, loop, np.linalg.norm(vertices[b] - vertices[a], axis=1))
        shortest = 0.0 if least is None else _median_patch_size(least[own], areas[own])
        for hole in np.flatnonzero((area < 0) & (perimeter >= shortest)):
            edges = np.flatnonzero(loop == hole)
            rims.append(HoleRim(int(s), a[edges], b[edges], element[edges], own, ends[label == hole]))
    return rims


def rim_runs(mesh: Mesh, least: np.ndarray | None = None, turn: float = 180.0) -> np.ndarray:
    """(T,) the straight runs of the rims of holes in planar surfaces (``hole_rims``, with
    ``least``) that each element lies along. 0: the element has no corner on a hole's rim;
    k > 0: its corners on the rim lie on run k (numbered over the mesh), a stretch of the
    rim whose edges turn at most ``turn`` degrees from its first's; -1: they lie on two runs
    (at a corner of the footprint), on the rims of two holes, or on a rim that is not one
    loop."""
    triangles = mesh.triangles.cpu().numpy()
    vertices = mesh.vertices.cpu().numpy()
    runs = np.zeros(len(triangles), dtype=np.int64)
    cos_turn = np.cos(np.radians(turn))
    for rim in hole_rims(mesh, least):
        own = rim.own
        touching = np.isin(triangles[own], rim.ends).any(1)  # a corner on this rim
        edge_run = _straight_runs(rim.a, rim.b, vertices, cos_turn)
        if edge_run is None:  # not one loop: every element along it alone
            runs[own[touching]] = -1
            continue
        first = runs.max() + 1
        # each rim vertex's runs: the runs of the (two) rim edges that meet at it
        vertex_runs = np.concatenate([np.stack([rim.a, edge_run], 1), np.stack([rim.b, edge_run], 1)])
        for k in np.flatnonzero(touching):
            met = np.unique(vertex_runs[np.isin(vertex_runs[:, 0], triangles[own[k]]), 1])
            alone = len(met) > 1 or runs[own[k]] != 0  # two runs, or two holes
            runs[own[k]] = -1 if alone else first + met[0]
    return runs


def _straight_runs(a: np.ndarray, b: np.ndarray, vertices: np.ndarray, cos_turn: float) -> np.ndarray | None:
    """The run (0, 1, ...) of each of the m directed edges a -> b (m,) of one boundary loop,
    walked in order from the edge after its sharpest turn: a run ends where an edge turns
    more than ``turn`` (``cos_turn``) from the run's first. None where the edges are not one
    loop (a vertex two edges leave, or several loops)."""
    after = dict(zip(a.tolist(), range(len(a))))
    if len(after) != len(a):
        return None
    direction = vertices[b] - vertices[a]
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    order = [0]
    while len(order) < len(a):
        order.append(after.get(int(b[order[-1]]), -1))
        if order[-1] < 0 or order[-1] == 0:
            return None
    if after.get(int(b[order[-1]]), -1) != 0:
        return None
    # start at the sharpest turn, so a run does not wrap round the loop's start
    turns = np.einsum("ij,ij->i", direction[order], direction[np.roll(order, 1)])
    order = np.roll(order, -int(np.argmin(turns)))
    run = np.zeros(len(a), dtype=np.int64)
    current, start = 0, order[0]
    for e in order:
        if direction[e] @ direction[start] < cos_turn:
            current, start = current + 1, e
        run[e] = current
    return run


def _each_alone(elements: np.ndarray, normals: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """A patch of one element for each of ``elements`` (k,), with its own plane's axes."""
    u, v = plane_axes(normals[elements].reshape(-1, 3))
    return list(zip(elements.reshape(-1, 1), u, v))


def _crossed(part: np.ndarray, own: int, owner: np.ndarray, low: np.ndarray, high: np.ndarray) -> bool:
    """Whether an element of an object other than ``own`` reaches into the bounding box of the
    elements ``part`` (k,), given every element's box ``low``, ``high`` (T, 3); boxes that
    only touch (an object resting on another) do not count."""
    box_low, box_high = low[part].min(0), high[part].max(0)
    slack = 1e-9 * float(np.abs(box_high).max() + np.abs(box_low).max())
    inside = np.all((low < box_high - slack) & (high > box_low + slack), axis=1)
    return bool((inside & (owner != own)).any())


def _exclusive_cumsum(x: np.ndarray) -> np.ndarray:
    return np.concatenate([[0], np.cumsum(x)[:-1]]).astype(np.int64)


def _node_eyes(elements: np.ndarray, starts: np.ndarray, centroids: np.ndarray, normals: np.ndarray,
               areas: np.ndarray, corners: np.ndarray, plane_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each of k nodes shoots from (k, 3) and its unit normal (k, 3), the elements of
    node i being ``elements[starts[i]:starts[i + 1]]``: the area-weighted centroid and mean
    normal of its elements; on a curved surface (elements of several planes), ``_eye_point``."""
    weight = areas[elements]
    ends = np.append(starts[1:], len(elements))
    counts = ends - starts
    # every sum as one node's own would add it (the same eyes to the last bit as node by node)
    total = np.asarray([weight[start:end].sum() for start, end in zip(starts.tolist(), ends.tolist())])
    eye = _run_sums(centroids[elements] * weight[:, None], starts, counts) / total[:, None]
    normal = _run_sums(normals[elements] * weight[:, None], starts, counts)
    normal /= _lengths(normal)[:, None]
    plane = plane_ids[elements]
    for i in np.flatnonzero(np.minimum.reduceat(plane, starts) != np.maximum.reduceat(plane, starts)):
        eye[i] = _eye_point(elements[starts[i]:ends[i]], eye[i], normal[i], centroids, corners)
    return eye, normal


def _eye_point(members: np.ndarray, centroid: np.ndarray, normal: np.ndarray, centroids: np.ndarray,
               corners: np.ndarray) -> np.ndarray:
    """Where a curved node shoots from: its area-weighted centroid lies off its surface (under
    a convex cap, where its hemicube would see its own back faces), so the centroid of its
    element nearest to that point, raised along the node's ``normal`` until no corner of its
    elements ``members`` lies above (none of them in its own hemicube)."""
    nearest = members[int(np.argmin(np.linalg.norm(centroids[members] - centroid, axis=1)))]
    point = centroids[nearest]
    rise = float(((corners[members].reshape(-1, 3) - point) @ normal).max())
    return point + max(rise, 0.0) * normal


def _numbered_depth_first(levels: list[tuple[np.ndarray, ...]], eyes: list[tuple[np.ndarray, ...]],
                          order: np.ndarray, patch: np.ndarray, centroids: np.ndarray,
                          normals: np.ndarray) -> PatchTree:
    """The ``PatchTree`` of nodes made breadth-first: ``levels`` (ids, lo, hi, parent) per
    depth, each node's children made together in order; ``eyes`` (ids, eye, normal) of the
    nodes of several elements; ``order`` the leaves' elements. Renumbered depth-first, a
    node before its children and each child's subtree before its next sibling's."""
    ids, lo, hi, parent = (np.concatenate(column) for column in zip(*levels))  # ids == arange(N)
    size = np.ones(len(ids), dtype=np.int64)  # nodes in each subtree
    for level, _, _, up in reversed(levels[1:]):
        np.add.at(size, up, size[level])
    number = np.empty(len(ids), dtype=np.int64)
    roots = levels[0][0]
    number[roots] = _exclusive_cumsum(size[roots])
    for level, _, _, up in levels[1:]:  # siblings are made together: runs of one parent
        before = np.cumsum(size[level]) - size[level]
        first = np.maximum.accumulate(np.where(np.r_[True, up[1:] != up[:-1]], np.arange(len(level)), 0))
        number[level] = number[up] + 1 + before - before[first]
    eye, normal = np.empty((len(ids), 3)), np.empty((len(ids), 3))
    single = hi - lo == 1
    eye[single], normal[single] = centroids[order[lo[single]]], normals[order[lo[single]]]
    for level, at, toward in eyes:
        eye[level], normal[level] = at, toward
    children = np.arange(len(roots), len(ids))
    children = children[np.argsort(number[parent[children]], kind="stable")]
    child_count = np.zeros(len(ids), dtype=np.int64)
    child_count[number] = np.bincount(parent[len(roots):], minlength=len(ids))
    leaf = np.empty(len(order), dtype=np.int64)
    leaf[order] = np.arange(len(order))
    by_number = np.argsort(number)
    return PatchTree(*(torch.from_numpy(np.ascontiguousarray(x)) for x in (
        leaf, patch, number[roots], lo[by_number], hi[by_number], np.concatenate([[0], np.cumsum(child_count)]),
        number[children], eye[by_number], normal[by_number])))
