"""What a picture draws: the surfaces as triangles with a value at every corner.

Gouraud shading interpolates the vertex values linearly over each element, and on a
radiosity with curvature f'' that is off by about h^2 f'' / 8 inside elements of size h
even where the vertex values are exact: on the walls and ceilings of the bundled scenes,
which refinement leaves coarse, most of a picture's error. ``quadratic_shading`` draws each
element as 4**levels triangles over a lattice whose points take the blend of the element's
corners' fitted polynomials (``reconstruction.vertex_fits``: the quadratics the vertex
values come from), weighted by the point's barycentric coordinates: exact where the
radiosity is quadratic, continuous across every edge (a point on an edge blends the two
fits at its ends only, whichever side draws it) and equal to the vertex values at the
vertices. Each value is clamped, as the vertex values are, into the range of the element
values its fits saw, widened to the Gouraud value there, and never below zero where they
are not: a shadow edge sharper than an element gets no overshoot.

Elements with T-vertices are drawn as ``display.conforming_triangles`` cuts them (the
pieces), so the lattice's edges meet the finer neighbours' edges point for point.

Measured (converged, against the path-traced references; the same solutions shown both ways):
relative MSE 0.68-0.73x Gouraud's on the finest uniform meshes of the three bundled scenes
(about 10,000 elements), 0.42-0.66x on the answer's refined runs with a third of the
elements, where more of the error is smooth variation over large elements. One level (4
triangles an element) gave 0.73-0.77x and 0.50-0.73x.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import torch

from hemirad.geometry.mesh import Mesh, barycentric
from hemirad.output import display
from hemirad.output.reconstruction import element_fits, reconstructed_vertex_values, vertex_fits

#: Each display triangle is cut into 4**SHADING_LEVELS.
SHADING_LEVELS = 2
#: ... fewer on meshes so large that the cut triangles would pass this many.
MAX_SHADED_TRIANGLES = 4_000_000


@dataclass(frozen=True)
class Shading:
    """Triangles over the surfaces with a value at each of their points, which a picture
    interpolates linearly (``render.render_view(..., positions=)``).

    Attributes:
        positions: (N, 3) float64 the points; the mesh's vertices first.
        values: (N, C) float64 the value at each.
        triangles: (M, 3) int64 indices into ``positions``.
        pieces: (D, 3) int64 the display triangles cut (``display.conforming_triangles``),
            vertex indices; source: (D,) the element each lies in.
        lattice: (D, K) int64 each piece's lattice points, indices into ``positions``, in the
            order of ``lattice_points(levels)``.
        levels: each piece is cut into 4**levels triangles (0: Gouraud).
    """

    positions: torch.Tensor
    values: torch.Tensor
    triangles: torch.Tensor
    pieces: torch.Tensor
    source: torch.Tensor
    lattice: torch.Tensor
    levels: int

    def at(self, mesh: Mesh, element: torch.Tensor, coordinates: torch.Tensor) -> torch.Tensor:
        """(S, C) the value drawn at points given by their ``element`` (S,) and barycentric
        ``coordinates`` (S, 3) on its corners (``mesh.triangles[element]``)."""
        points = (mesh.corners.index_select(0, element).to(torch.float64) * coordinates[:, :, None]).sum(1)
        piece, lam = self._piece_containing(element, points)
        n = 2 ** self.levels
        s, t = (lam[:, 1] * n).clamp(min=0), (lam[:, 2] * n).clamp(min=0)
        i = s.floor().clamp(max=n - 1)
        j = torch.minimum(t.floor(), n - 1 - i)
        fs, ft = s - i, t - j
        upper = (fs + ft > 1) & (i + j < n - 1)
        i, j = i.long(), j.long()
        index = _lattice_index(n, self.lattice.device)
        lower_points = torch.stack([index[i, j], index[i + 1, j], index[i, j + 1]], 1)
        lower_weights = torch.stack([1 - fs - ft, fs, ft], 1)
        upper_points = torch.stack([index[i + 1, j], index[(i + 1).clamp(max=n), (j + 1).clamp(max=n)], index[i, j + 1]], 1)
        upper_weights = torch.stack([1 - ft, fs + ft - 1, 1 - fs], 1)
        which = torch.where(upper[:, None], upper_points, lower_points)  # (S, 3) lattice positions
        weights = torch.where(upper[:, None], upper_weights, lower_weights).clamp(min=0)
        point = self.lattice[piece[:, None], which]  # (S, 3) indices into positions
        return (weights[:, :, None] * self.values[point]).sum(1)

    def element_deviation(self, mesh: Mesh, element_values: torch.Tensor) -> torch.Tensor:
        """(T,) the RMS, over each element's lattice points, of the drawn value's distance
        from the element's own quadratic (``reconstruction.element_fits``, fitted to the
        ``element_values`` (T, 1) of it and its vertex-sharing neighbours, kept within twice
        their range): 0 where the light
        is quadratic, large where it varies faster than the element resolves (the answer's
        ranking, ``adaptive.answer.element_errors``)."""
        lam = lattice_coordinates(self.levels).to(self.values.device)  # (K, 3)
        T, K = mesh.num_elements, len(lam)
        element = torch.arange(T, device=self.values.device).repeat_interleave(K)
        coordinates = lam.repeat(T, 1)  # (T K, 3)
        points = (mesh.corners.index_select(0, element).to(torch.float64) * coordinates[:, :, None]).sum(1)
        fits = element_fits(mesh, element_values)
        # within the range of the values fitted to, widened by its width on either side: a
        # quadratic through the few elements of a small face can swing far outside them (a
        # Cornell box block's top at 0.56 m elements read 12 times its light, and made 99% of
        # the estimate); clamped into the range itself, the ranking from the shipped meshes
        # lost 5-25% of its accuracy (floating, office)
        low, high = fits.low[element], fits.high[element]
        model = torch.minimum(torch.maximum(fits.at(element, points), 2 * low - high), 2 * high - low)
        return (model - self.at(mesh, element, coordinates)).pow(2).sum(1).reshape(T, K).mean(1).sqrt()

    @cached_property
    def _pieces_by_element(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The pieces sorted by element (P,), and (T,) where each element's begin and how many
        it has (every element has one at least)."""
        order = torch.argsort(self.source, stable=True)
        count = torch.bincount(self.source)
        return order, torch.cumsum(count, 0) - count, count

    def _piece_containing(self, element: torch.Tensor, points: torch.Tensor):
        """(S,) the piece of each point's element that holds it, and (S, 3) its barycentric
        coordinates there."""
        order, start, count = self._pieces_by_element
        best_piece = torch.zeros(len(element), dtype=torch.int64, device=element.device)
        best_lam = torch.zeros(len(element), 3, dtype=torch.float64, device=element.device)
        best_fit = torch.full((len(element),), -float("inf"), dtype=torch.float64, device=element.device)
        for c in range(int(count.max()) if len(count) else 0):
            has = count.index_select(0, element) > c
            piece = order[(start.index_select(0, element) + c).clamp(max=len(order) - 1)]
            lam = barycentric(self.positions[self.pieces[piece]], points)
            fit = torch.where(has, lam.amin(1), torch.full_like(best_fit, -float("inf")))
            better = fit > best_fit
            best_piece = torch.where(better, piece, best_piece)
            best_lam = torch.where(better[:, None], lam, best_lam)
            best_fit = torch.where(better, fit, best_fit)
        return best_piece, best_lam


def lattice_points(levels: int) -> list[tuple[int, int]]:
    """The (i, j) of a piece's lattice, i + j <= 2**levels: the point with barycentric
    coordinates (1 - (i + j) / n, i / n, j / n) on the piece's corners."""
    n = 2 ** levels
    return [(i, j) for i in range(n + 1) for j in range(n + 1 - i)]


def lattice_coordinates(levels: int) -> torch.Tensor:
    """(K, 3) float64 the barycentric coordinates of ``lattice_points(levels)``."""
    n = 2 ** levels
    return torch.tensor([[1 - (i + j) / n, i / n, j / n] for i, j in lattice_points(levels)], dtype=torch.float64)


def _lattice_index(n: int, device) -> torch.Tensor:
    """(n + 1, n + 1) int64: the position of (i, j) in ``lattice_points`` (-1 past the diagonal)."""
    index = torch.full((n + 1, n + 1), -1, dtype=torch.int64, device=device)
    k = 0
    for i in range(n + 1):
        for j in range(n + 1 - i):
            index[i, j] = k
            k += 1
    return index


def _lattice_triangles(n: int) -> torch.Tensor:
    """(n^2, 3) int64 the small triangles of a lattice, as positions in ``lattice_points``,
    wound as the piece is."""
    index = _lattice_index(n, "cpu")
    small = []
    for i in range(n):
        for j in range(n - i):
            small.append((index[i, j], index[i + 1, j], index[i, j + 1]))
            if i + j < n - 1:
                small.append((index[i + 1, j], index[i + 1, j + 1], index[i, j + 1]))
    return torch.tensor(small, dtype=torch.int64)


def gouraud_shading(mesh: Mesh, vertex_values: torch.Tensor) -> Shading:
    """The vertex values (V, C) interpolated linearly over the display triangles (the paper's
    display)."""
    pieces, source = display.conforming_triangles(mesh, return_source=True)
    values = torch.as_tensor(vertex_values).to(torch.float64)
    # lattice_points(0) is (0, 0), (0, 1), (1, 0): the corners c0, c2, c1
    return Shading(mesh.vertices.to(torch.float64), values.reshape(len(mesh.vertices), -1), pieces, pieces, source,
                   pieces[:, [0, 2, 1]], 0)


def quadratic_shading(mesh: Mesh, element_values: torch.Tensor, vertex_values: torch.Tensor,
                      levels: int = SHADING_LEVELS) -> Shading:
    """Each display triangle cut into 4**levels, its lattice points given the barycentric
    blend of its corners' fitted polynomials (module docstring).

    Args:
        mesh: the mesh; element_values: (T, C) each element's mean value.
        vertex_values: (V, C) the values shown at the vertices
            (``reconstruction.reconstructed_vertex_values``, quadratic).
        levels: how finely to cut; 0 is ``gouraud_shading``.
    """
    if levels == 0:
        return gouraud_shading(mesh, vertex_values)
    pieces, source = display.conforming_triangles(mesh, return_source=True)
    device = mesh.vertices.device
    shown = torch.as_tensor(vertex_values).to(device=device, dtype=torch.float64)
    values = torch.as_tensor(element_values).to(device=device, dtype=torch.float64)
    squeeze = values.dim() == 1
    values, shown = (values[:, None], shown[:, None]) if squeeze else (values, shown)
    fits = vertex_fits(mesh, values, shown)
    vertices = mesh.vertices.to(torch.float64)
    V, D, n = len(vertices), len(pieces), 2 ** levels

    def blend(corner: torch.Tensor, lam: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """(..., C): the fits of ``corner`` (..., k) weighted by ``lam`` (..., k) at ``points``
        (..., 3), clamped as the module docstring says."""
        raw = (lam[..., None] * fits.at(corner, points[..., None, :].expand(*corner.shape, 3))).sum(-2)
        linear = (lam[..., None] * shown[corner]).sum(-2)
        low, high = fits.low[corner].amin(-2), fits.high[corner].amax(-2)
        floor = torch.maximum(torch.minimum(low, linear), low.clamp(max=0))
        return torch.minimum(torch.maximum(raw, floor), torch.maximum(high, linear))

    # edge points, once per edge of the pieces: the lattice's n - 1 inner points on it
    directed = torch.cat([pieces[:, [0, 1]], pieces[:, [1, 2]], pieces[:, [2, 0]]])  # (3D, 2)
    edges, edge_of = torch.unique(directed.sort(dim=1).values, dim=0, return_inverse=True)  # (E, 2), (3D,)
    steps = torch.arange(1, n, device=device, dtype=torch.float64) / n  # (n - 1,)
    along = torch.stack([1 - steps, steps], 1).expand(len(edges), -1, -1)  # (E, n - 1, 2)
    ends = edges[:, None, :].expand(-1, n - 1, -1)  # (E, n - 1, 2)
    edge_points = (along[..., None] * vertices[ends]).sum(-2)  # (E, n - 1, 3)
    edge_values = blend(ends, along, edge_points)

    # inner points, once per piece
    lattice = lattice_points(levels)
    is_inner = [i > 0 and j > 0 and i + j < n for i, j in lattice]
    inner = [p for p, keep in zip(lattice, is_inner) if keep]
    inner_lam = lattice_coordinates(levels)[torch.tensor(is_inner)].to(device)  # (I, 3)
    corners3 = pieces[:, None, :].expand(-1, len(inner), -1)  # (D, I, 3)
    lam3 = inner_lam[None].expand(D, -1, -1)
    inner_points = (lam3[..., None] * vertices[corners3]).sum(-2)  # (D, I, 3)
    inner_values = blend(corners3, lam3, inner_points)

    # each piece's lattice as indices into positions: vertices, then edge points, then inner
    E = len(edges)
    table = torch.empty(D, len(lattice), dtype=torch.int64, device=device)
    edge_id = edge_of.reshape(3, D).T  # (D, 3): the piece's edges c0c1, c1c2, c2c0
    inner_rank = {p: r for r, p in enumerate(inner)}
    for k, (i, j) in enumerate(lattice):
        if (i, j) == (0, 0):
            table[:, k] = pieces[:, 0]
        elif (i, j) == (n, 0):
            table[:, k] = pieces[:, 1]
        elif (i, j) == (0, n):
            table[:, k] = pieces[:, 2]
        elif (i, j) in inner_rank:
            table[:, k] = V + E * (n - 1) + torch.arange(D, device=device) * len(inner) + inner_rank[(i, j)]
        else:
            # on an edge: from corner a, `step` of n toward corner b
            if j == 0:
                edge, a, step = 0, pieces[:, 0], i
            elif i + j == n:
                edge, a, step = 1, pieces[:, 1], j
            else:
                edge, a, step = 2, pieces[:, 2], n - j
            first = edges[edge_id[:, edge], 0]
            from_first = torch.where(a == first, step, n - step)
            table[:, k] = V + edge_id[:, edge] * (n - 1) + from_first - 1
    triangles = table[:, _lattice_triangles(n).to(device)].reshape(-1, 3)
    positions = torch.cat([vertices, edge_points.reshape(-1, 3), inner_points.reshape(-1, 3)])
    point_values = torch.cat([shown, edge_values.reshape(-1, shown.shape[1]), inner_values.reshape(-1, shown.shape[1])])
    return Shading(positions, point_values, triangles, pieces, source, table, levels)


def picture_shading(mesh: Mesh, element_values: torch.Tensor, reconstruction: str = "quadratic",
                    vertex_values: torch.Tensor | None = None) -> Shading:
    """What a picture of ``element_values`` (T, C) draws under ``solver.reconstruction``:
    quadratic shading over the fitted vertex values (fewer levels on meshes too large for
    ``MAX_SHADED_TRIANGLES``), or, for the paper's ``mean``, Gouraud over the averaged
    ones. ``vertex_values``: ``reconstructed_vertex_values``'s, to reuse ones already made."""
    if vertex_values is None:
        vertex_values = reconstructed_vertex_values(mesh, element_values, reconstruction)
    if reconstruction != "quadratic":
        return gouraud_shading(mesh, vertex_values)
    levels = SHADING_LEVELS
    while levels > 0 and mesh.num_elements * 4 ** levels > MAX_SHADED_TRIANGLES:
        levels -= 1
    return quadratic_shading(mesh, element_values, vertex_values, levels)
