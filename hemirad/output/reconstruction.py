"""Vertex values from element values: how the piecewise-constant solution is carried to the
vertices that Gouraud shading, the exports and the error estimates interpolate.

An element's radiosity is the mean of the true radiosity over its area (a hemicube counts
the pixels it covers; the closed-form factor integrates over it). The paper's display
averages the elements around each vertex (``display.vertex_values``). That blurs: on a
radiosity with curvature f'' the average of the ring around a vertex is off by about
h^2 f'' / 6 for elements of size h, as much again as linear interpolation between exact
vertex values costs (h^2 f'' / 8), and at a surface's border, where a vertex has elements
on one side only, it misses the slope by half an element, a first-order error.

``quadratic_vertex_values`` fits instead, per vertex, a quadratic in the surface's tangent
plane to the means of the elements within two rings of it (each element's mean of the
quadratic, not its value at the centroid: exact for any quadratic radiosity, borders
included) and takes the fit's value at the vertex, in the spirit of the higher-order
reconstructions of Salesin, Lischinski & DeRose (1992). Where light jumps (a shadow edge
sharper than an element) a quadratic overshoots; the value is clamped into the range of the
elements it was fitted to, widened only to the linear fit's value (which at a border rightly
extrapolates past every element's mean) and never below zero.

Measured on the bundled scenes converged, the same solves shown both ways (relative MSE of
the picture against the path-traced references): the fit's 0.44-0.52x the average's at 700
to 3,100 elements; over the accuracy study (figures/accuracy_converged.md, against the
release before) 0.56-0.72x on the finest uniform meshes (10,000-11,000 elements).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch

from hemirad.geometry.mesh import Mesh, vertex_sharing_pairs
from hemirad.output import display
from hemirad.scene.model import RECONSTRUCTION_CHOICES

#: The fit weighs an element by its area times exp(-r^2 / 2 s^2), r its centroid's distance
#: from the vertex and s this many times the vertex's element size (the square root of the
#: mean area of the elements at the vertex): the first ring counts most, the second steadies
#: the curvature. Measured at 1, 1.4, 2 and 18 on the bundled scenes (uniform meshes x1 and
#: x0.5): 1 the best or within 1% of it on each.
FIT_WIDTH = 1.0
#: A fit whose normal matrix is worse conditioned than this falls back to a linear fit, then
#: to the mean (a vertex with too few elements around it, e.g. a lone triangle's).
MAX_CONDITION = 1e8


def vertex_element_pairs(mesh: Mesh, rings: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    """(Q,), (Q,): the (vertex, element) pairs of each vertex with the elements within
    ``rings`` rings of it (ring 1: the elements it is a corner of; ring k + 1: those sharing
    a vertex with ring k), sorted by vertex. Vertices are shared only inside a surface, so
    the rings never cross to another surface."""
    T, V = mesh.num_elements, len(mesh.vertices)
    corner_element = torch.arange(T, device=mesh.triangles.device).repeat_interleave(3)
    with warnings.catch_warnings():  # torch's notes on its sparse support, not about these tensors
        warnings.simplefilter("ignore", UserWarning)
        incidence = torch.sparse_coo_tensor(
            torch.stack([mesh.triangles.reshape(-1), corner_element]),
            torch.ones(3 * T, dtype=torch.float64, device=corner_element.device), (V, T)).coalesce()
        pairs = incidence
        for _ in range(rings - 1):
            pairs = torch.sparse.mm(torch.sparse.mm(pairs, incidence.t()), incidence).coalesce()
    vertex, element = pairs.indices()
    return vertex, element


def _tangent_frames(mesh: Mesh) -> tuple[torch.Tensor, torch.Tensor]:
    """(V, 3), (V, 3): two unit vectors spanning each vertex's tangent plane (normal to the
    area-weighted mean of its elements' normals)."""
    V = len(mesh.vertices)
    normal = torch.zeros(V, 3, dtype=torch.float64, device=mesh.vertices.device).index_add_(
        0, mesh.triangles.reshape(-1), (mesh.normals * mesh.areas[:, None]).repeat_interleave(3, dim=0))
    return _plane_frames(normal / normal.norm(dim=1, keepdim=True).clamp(min=1e-300))


@dataclass(frozen=True)
class _FitProblem:
    """The weighted least-squares problems of fits around P centres (the vertices, or the
    elements), which depend on the mesh alone: the (centre, element) pairs, sorted by
    centre, each pair's basis (the element's means of 1, x, y, x^2, xy, y^2 in its centre's
    tangent frame, in units of the centre's element size) and weight."""

    centre: torch.Tensor  # (Q,)
    element: torch.Tensor  # (Q,)
    basis: torch.Tensor  # (Q, 6)
    weight: torch.Tensor  # (Q,)
    origin: torch.Tensor  # (P, 3) the centres
    u: torch.Tensor  # (P, 3) their tangent frames
    w: torch.Tensor  # (P, 3)
    size: torch.Tensor  # (P,) their element sizes


def _fit_problem(mesh: Mesh) -> _FitProblem:
    """The problems of the vertices' fits: each to the elements within two rings of it."""
    device = mesh.vertices.device
    V = len(mesh.vertices)
    vertex, element = vertex_element_pairs(mesh)
    u, w = _tangent_frames(mesh)
    corner_vertex = mesh.triangles.reshape(-1)
    ring_area = torch.zeros(V, dtype=torch.float64, device=device).index_add_(0, corner_vertex, mesh.areas.repeat_interleave(3))
    ring_count = torch.zeros(V, dtype=torch.float64, device=device).index_add_(
        0, corner_vertex, torch.ones(3 * mesh.num_elements, dtype=torch.float64, device=device))
    size = (ring_area / ring_count.clamp(min=1)).sqrt().clamp(min=1e-300)  # (V,) the vertex's element size
    return _problem_around(mesh, mesh.vertices, u, w, size, vertex, element)


def _element_fit_problem(mesh: Mesh) -> _FitProblem:
    """The problems of the elements' own fits: each to itself and the elements that share a
    vertex with it, around its centroid, in its plane."""
    u, w = _plane_frames(mesh.normals)
    element, near = vertex_sharing_pairs(mesh)
    return _problem_around(mesh, mesh.centroids, u, w, mesh.areas.sqrt().clamp(min=1e-300), element, near)


def _plane_frames(normal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(P, 3), (P, 3): two unit vectors spanning the planes of unit ``normal`` (P, 3)."""
    helper = torch.zeros_like(normal)
    helper[:, 0] = (normal[:, 0].abs() < 0.9).to(normal.dtype)
    helper[:, 1] = 1.0 - helper[:, 0]
    u = torch.linalg.cross(normal, helper)
    u = u / u.norm(dim=1, keepdim=True).clamp(min=1e-300)
    return u, torch.linalg.cross(normal, u)


def _problem_around(mesh: Mesh, origin: torch.Tensor, u: torch.Tensor, w: torch.Tensor, size: torch.Tensor,
                    centre: torch.Tensor, element: torch.Tensor) -> _FitProblem:
    # the pairs' coordinates in their centre's tangent plane, in units of its element size
    scale = size.index_select(0, centre)[:, None]
    uq, wq = u.index_select(0, centre), w.index_select(0, centre)
    offset = mesh.centroids.index_select(0, element) - origin.index_select(0, centre)  # (Q, 3)
    x, y = (offset * uq).sum(1) / scale[:, 0], (offset * wq).sum(1) / scale[:, 0]
    # an element's mean of x^2 is its centroid's x^2 plus (1/12) sum over its corners of
    # (corner - centroid)_x^2 (a triangle's second moment), and alike for xy and y^2
    spread = mesh.corners.index_select(0, element) - mesh.centroids.index_select(0, element)[:, None, :]  # (Q, 3, 3)
    sx, sy = (spread * uq[:, None, :]).sum(-1) / scale, (spread * wq[:, None, :]).sum(-1) / scale
    basis = torch.stack([torch.ones_like(x), x, y, x * x + (sx * sx).sum(1) / 12,
                         x * y + (sx * sy).sum(1) / 12, y * y + (sy * sy).sum(1) / 12], 1)  # (Q, 6)
    weight = (mesh.areas.index_select(0, element) / (scale[:, 0] * scale[:, 0])
              * torch.exp(-(x * x + y * y) / (2 * FIT_WIDTH * FIT_WIDTH)))  # (Q,)
    return _FitProblem(centre, element, basis, weight, origin.to(torch.float64), u, w, size)


def _normal_matrices(problem: _FitProblem, terms: int, V: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(V, terms, terms) each vertex's normal matrix X^T W X, with the identity where it is
    too ill conditioned to solve, and (V,) bool: where it was not."""
    X = problem.basis[:, :terms]
    normal_matrix = torch.zeros(V, terms, terms, dtype=torch.float64, device=X.device).index_add_(
        0, problem.centre, problem.weight[:, None, None] * X[:, :, None] * X[:, None, :])
    singular = torch.linalg.svdvals(normal_matrix)  # (V, terms), descending
    posed = (singular[:, -1] * MAX_CONDITION > singular[:, 0]) & (singular[:, 0] > 0)
    safe = torch.where(posed[:, None, None], normal_matrix, torch.eye(terms, dtype=torch.float64, device=X.device))
    return safe, posed


def _fitted_range(problem: _FitProblem, values: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(P, C), (P, C): the least and greatest of the element values each centre's fit saw."""
    V, C = len(problem.size), values.shape[1]
    index = problem.centre[:, None].expand(-1, C)
    near = values.index_select(0, problem.element)
    low = torch.full((V, C), float("inf"), dtype=torch.float64, device=values.device).scatter_reduce(0, index, near, "amin")
    high = torch.full((V, C), -float("inf"), dtype=torch.float64, device=values.device).scatter_reduce(0, index, near, "amax")
    return low, high


def quadratic_vertex_values(mesh: Mesh, element_values: torch.Tensor) -> torch.Tensor:
    """Each vertex's value of a weighted least-squares quadratic fitted to the element means
    within two rings of it, clamped into their range.

    Args:
        mesh: the mesh; its triangles index its vertices.
        element_values: (T, C) or (T,) each element's mean value.

    Returns:
        (V, C) or (V,) float64. Exact for element means of a quadratic over the tangent plane
        wherever the fit is well posed; elsewhere a linear fit, or the area-weighted mean
        (``display.vertex_values``). A vertex no triangle uses gets 0.
    """
    device = mesh.vertices.device
    values = torch.as_tensor(element_values).to(device=device, dtype=torch.float64)
    squeeze = values.dim() == 1
    values = values[:, None] if squeeze else values
    if values.shape[0] != mesh.num_elements:
        raise ValueError(f"need one value per element ({mesh.num_elements}), got {values.shape[0]}")
    V, C = len(mesh.vertices), values.shape[1]
    mean = display.vertex_values(mesh, values)
    if mesh.num_elements == 0:
        return mean[:, 0] if squeeze else mean
    problem = _fit_problem(mesh)
    vertex, element, basis, weight = problem.centre, problem.element, problem.basis, problem.weight

    fits = []  # (posed (V,), value (V, C)) of the quadratic, then the linear fit
    for terms in (6, 3):
        X = basis[:, :terms]
        safe, posed = _normal_matrices(problem, terms, V)
        # the fit's value at the vertex (x = y = 0) is its constant term: sum_q c_q v_q with
        # c_q = w_q X_q . (X^T W X)^-1 e_0, one solve per vertex for all channels
        first = torch.zeros(V, terms, 1, dtype=torch.float64, device=device)
        first[:, 0] = 1.0
        g = torch.linalg.solve(safe, first)[:, :, 0]  # (V, terms)
        c = weight * (X * g.index_select(0, vertex)).sum(1)  # (Q,)
        fits.append((posed, torch.zeros(V, C, dtype=torch.float64, device=device).index_add_(
            0, vertex, c[:, None] * values.index_select(0, element))))
    (quadratic_posed, quadratic), (linear_posed, linear) = fits

    # No new extremes: into the range of the values fitted to, widened to the linear fit's
    # value, which at a surface's border rightly extrapolates past every element's mean.
    low, high = _fitted_range(problem, values)
    # (never below zero, where the values are not: radiosity is not negative)
    widened_low = torch.maximum(torch.where(linear_posed[:, None], torch.minimum(low, linear), low), low.clamp(max=0))
    widened_high = torch.where(linear_posed[:, None], torch.maximum(high, linear), high)
    # too few elements for a quadratic (a corner's lone triangle): the linear fit, kept from zero
    fitted = torch.where(linear_posed[:, None], torch.maximum(linear, low.clamp(max=0)), mean)
    fitted = torch.where(quadratic_posed[:, None],
                         torch.minimum(torch.maximum(quadratic, widened_low), widened_high), fitted)
    return fitted[:, 0] if squeeze else fitted


@dataclass(frozen=True)
class LocalFits:
    """The polynomial fitted around each of P centres (the vertices: ``vertex_fits``; the
    elements: ``element_fits``), to be read near it."""

    origin: torch.Tensor  # (P, 3) the centres
    u: torch.Tensor  # (P, 3), (P, 3) their tangent frames
    w: torch.Tensor
    size: torch.Tensor  # (P,) their element sizes, the unit of x and y
    coefficients: torch.Tensor  # (P, 6, C) of 1, x, y, x^2, xy, y^2
    low: torch.Tensor  # (P, C), (P, C): the range of the element values fitted to
    high: torch.Tensor

    def at(self, centre: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """(..., C) the fits of ``centre`` (...,) at ``points`` (..., 3)."""
        offset = points - self.origin[centre]
        size = self.size[centre]
        x, y = (offset * self.u[centre]).sum(-1) / size, (offset * self.w[centre]).sum(-1) / size
        basis = torch.stack([torch.ones_like(x), x, y, x * x, x * y, y * y], -1)  # (..., 6)
        return (basis[..., :, None] * self.coefficients[centre]).sum(-2)


def vertex_fits(mesh: Mesh, element_values: torch.Tensor, fallback: torch.Tensor) -> LocalFits:
    """The whole polynomial of every vertex's fit (``quadratic_vertex_values`` keeps only its
    value at the vertex): the quadratic where it is well posed, else the linear fit, else the
    constant ``fallback`` (V, C) (the vertex's shown value). ``element_values``: (T, C)."""
    return _fits(_fit_problem(mesh), element_values, fallback)


def element_fits(mesh: Mesh, element_values: torch.Tensor) -> LocalFits:
    """Every element's own quadratic, fitted (as the vertices' are, by the elements' means)
    to its value and those of the elements sharing a vertex with it, around its centroid:
    where that is ill posed, the linear fit, else its value. ``element_values``: (T, C)."""
    values = torch.as_tensor(element_values).to(device=mesh.vertices.device, dtype=torch.float64)
    return _fits(_element_fit_problem(mesh), values, values)


def _fits(problem: _FitProblem, element_values: torch.Tensor, fallback: torch.Tensor) -> LocalFits:
    values = torch.as_tensor(element_values).to(device=problem.origin.device, dtype=torch.float64)
    P, C = len(problem.size), values.shape[1]
    coefficients = torch.zeros(P, 6, C, dtype=torch.float64, device=values.device)
    coefficients[:, 0] = fallback
    for terms in (3, 6):  # the quadratic, where posed, over the linear fit
        X = problem.basis[:, :terms]
        safe, posed = _normal_matrices(problem, terms, P)
        rhs = torch.zeros(P, terms, C, dtype=torch.float64, device=values.device).index_add_(
            0, problem.centre, (problem.weight[:, None] * X)[:, :, None] * values.index_select(0, problem.element)[:, None, :])
        fit = torch.zeros_like(coefficients)
        fit[:, :terms] = torch.linalg.solve(safe, rhs)
        coefficients = torch.where(posed[:, None, None], fit, coefficients)
    low, high = _fitted_range(problem, values)
    return LocalFits(problem.origin, problem.u, problem.w, problem.size, coefficients, low, high)


def reconstructed_vertex_values(mesh: Mesh, element_values: torch.Tensor, reconstruction: str = "quadratic") -> torch.Tensor:
    """The values the display shades with: ``quadratic_vertex_values`` or the paper's mean
    (``display.vertex_values``), with every T-vertex given the value of the unsplit edge it
    lies on (``display.conforming_vertex_values``: no shading seam)."""
    if reconstruction not in RECONSTRUCTION_CHOICES:
        raise ValueError(f"reconstruction must be one of {RECONSTRUCTION_CHOICES}, got {reconstruction!r}")
    fit = quadratic_vertex_values if reconstruction == "quadratic" else display.vertex_values
    return display.conforming_vertex_values(mesh, fit(mesh, element_values))
