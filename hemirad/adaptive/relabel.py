"""Carry a hemicube's item atlas across a split instead of rendering it again.

Splitting changes no geometry: the children of an element tile its triangle exactly, so a
pixel that saw the parent sees one of its descendants, the one whose triangle holds the
pixel's hit point. Relabelling the parents' pixels by that test gives the atlas a new
render would give, except where a pixel centre lies within rounding of a new internal edge
and GL's tie rule picks the other child (no such pixel on the tested scenes).
A refining shot (``shot.py``) uses it between its passes and renders for real before the
shot is committed.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from hemirad.core.fastops import flatnonzero, marked_positions, segments
from hemirad.geometry.mesh import Mesh
from hemirad.geometry.split import inherit
from hemirad.transport.view import HemicubeView


@dataclass
class Descent:
    """Which new elements lie in which old ones after a split (``descendants``).

    Attributes:
        parent: (T',) the old element every new one lies in; ``parent[:T]`` is the identity
            (``split.split_triangles``: every old element keeps its index).
        ordered: (K,) the new elements that lie in split old ones, grouped by parent.
        start, count: (T,) each old element's run in ``ordered`` (start is 0 for an unsplit
            one); count 1: not split.
    """

    parent: torch.Tensor
    ordered: torch.Tensor
    start: torch.Tensor
    count: torch.Tensor


def relabel_view(view: HemicubeView, parent: torch.Tensor, split: torch.Tensor, mesh: Mesh) -> HemicubeView:
    """What the same hemicube sees after a split.

    Args:
        view: what it saw before.
        parent: (T',) the old element each element of the new ``mesh`` lies in.
        split: (K,) the old elements that were split, sorted.
        mesh: the new elements.
    Returns:
        the view of ``mesh``, its ``relabelled_pixels`` the pixels whose element was split.
    """
    descent = descendants(parent, split)
    pixels = split_pixels_of(view.element, descent)
    element = relabel_atlas(view.element, view.hits(pixels), pixels, descent, mesh)
    form_factors = relabel_form_factors(view.form_factors, descent, element, view.front, view.weight, pixels)
    return replace(view, element=element, normals=mesh.normals, points=mesh.centroids, form_factors=form_factors,
                   relabelled_pixels=pixels)


def descendants(parent: torch.Tensor, split: torch.Tensor) -> Descent:
    """Map old elements to the new ones that lie in them.

    Args:
        parent: (T',) for every new element the old one it lies in (``Refiner.split``), the
            identity on its first T entries.
        split: (K,) the old elements that were split, sorted (``unique(parent[T:])``).
    """
    T, device = int(parent.max()) + 1 if len(parent) else 0, parent.device  # parent[:T] is the identity
    appended = parent[T:]
    count = torch.ones(T, dtype=torch.int64, device=device).index_add_(0, appended, torch.ones_like(appended))
    in_split = torch.cat([split, torch.arange(T, len(parent), device=device)])  # ascending
    ordered = in_split.index_select(0, torch.argsort(parent.index_select(0, in_split), stable=True))
    split_count = count.index_select(0, split)
    start = torch.zeros(T, dtype=torch.int64, device=device)
    start.index_copy_(0, split, torch.cumsum(split_count, 0) - split_count)  # the runs follow each other
    return Descent(parent, ordered, start, count)


def split_pixels_of(element: torch.Tensor, descent: Descent) -> torch.Tensor:
    """(N,) the pixels whose element was split (it has more than one descendant)."""
    return marked_positions(element, descent.count > 1)


def relabel_atlas(element: torch.Tensor, hits: torch.Tensor, split_pixels: torch.Tensor, descent: Descent,
                  mesh: Mesh) -> torch.Tensor:
    """The element each pixel sees after a split, from what it saw before.

    Args:
        element: (P,) old element per pixel, -1 for none.
        hits: (3, N) world points seen by ``split_pixels``, the (N,) pixels whose old element
            was split (``split_pixels_of``).
        descent: the split's ``descendants``.
        mesh: the new elements.
    Returns:
        (P,) new element per pixel, -1 for none.
    """
    out = element.clone()  # an unsplit element keeps its index
    if len(split_pixels) == 0:
        return out
    # Every (pixel, descendant of its old element) pair, then the descendant that holds the
    # hit point best: the largest smallest signed distance to its three edges (inside: >= 0).
    old_of_pixel = element.index_select(0, split_pixels)
    n_candidates = descent.count.index_select(0, old_of_pixel)
    device = element.device
    pixel, rank = segments(n_candidates)
    slot = descent.start.index_select(0, old_of_pixel).index_select(0, pixel) + rank  # (M,) into ordered
    candidate = descent.ordered.index_select(0, slot)
    # Each descendant's three edges as inward unit normals in its plane, with offsets from its
    # first corner, made once per descendant: a pair's distances are then three dot products
    # of the hit point relative to that corner (small numbers, as precise as the element).
    inward, offset, corner = _edge_planes(mesh, descent.ordered)  # (K, 3, 3), (K, 3), (K, 3)
    y = hits.index_select(1, pixel) - corner.index_select(0, slot).T  # (3, M)
    planes = inward.index_select(0, slot)  # (M, 3 edges, 3)
    distance = (planes[:, :, 0] * y[0, :, None] + planes[:, :, 1] * y[1, :, None]
                + planes[:, :, 2] * y[2, :, None]) - offset.index_select(0, slot)  # (M, 3)
    margin = torch.minimum(torch.minimum(distance[:, 0], distance[:, 1]), distance[:, 2])
    best = torch.full((len(split_pixels),), -torch.inf, dtype=margin.dtype, device=device).scatter_reduce(
        0, pixel, margin, "amax")
    is_best = margin == best[pixel]
    chosen = torch.full((len(split_pixels),), len(descent.parent), dtype=torch.int64, device=device)
    chosen = chosen.scatter_reduce(0, pixel[is_best], candidate[is_best], "amin")  # ties: the lower index
    out[split_pixels] = chosen.to(out.dtype)
    return out


def _edge_planes(mesh: Mesh, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """For the triangles ``rows`` (K,) with corners a, b, c: (K, 3, 3) the unit normal of each
    edge a -> b, b -> c, c -> a within the triangle's plane, pointing inside, (K, 3) its
    offset and (K, 3) the corner a: a point y of the plane lies at the signed distance
    ``inward . (y - a) - offset`` from the edge's line."""
    corners = mesh.corners_of(rows)  # (K, 3, 3)
    start, end = corners, corners.roll(-1, dims=1)
    n = mesh.normals.index_select(0, rows)[:, None, :].expand_as(corners)
    inward = torch.linalg.cross(n, end - start, dim=2)  # n x edge: to the left of the edge
    inward = inward / inward.norm(dim=2, keepdim=True)
    first = corners[:, 0]
    return inward, (inward * (start - first[:, None, :])).sum(2), first


def relabel_form_factors(form_factors: torch.Tensor, descent: Descent, element: torch.Tensor,
                         front: torch.Tensor, weight: torch.Tensor, split_pixels: torch.Tensor) -> torch.Tensor:
    """F after a split from F before: unsplit elements keep theirs, the new ones sum their
    pixels (all among ``split_pixels``). The same, bit for bit, as summing the whole
    relabelled atlas (``formfactor.element_form_factors``): each element's pixels are summed
    in the same order.

    Args:
        form_factors: (T,) before; descent: the split's ``descendants``; element: (P,)
            relabelled; front, weight: (P,).
    Returns:
        (T',)
    """
    out = inherit(form_factors, descent.parent).index_fill_(0, descent.ordered, 0.0)
    pixels = split_pixels.index_select(0, flatnonzero(front.index_select(0, split_pixels)))
    # summed in pixel order from zero, as a bincount of the whole atlas sums them
    return out.index_add_(0, element.index_select(0, pixels), weight.index_select(0, pixels))
