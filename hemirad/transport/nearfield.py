"""The light a patch sends to receivers close to it, spread as its extent sends it
(docs/DESIGN.md §1.4).

A patch shoots from one hemicube at its centroid G. For a receiver many patch sizes away
that point stands in well for the patch; for one beside it (the floor along a wall patch)
it does not: the light near the patch's edges is drawn as if it all left from G. For the
receivers within ``reach`` patch radii of G, the hemicube's share of the patch's power is
kept (the same total, so power stays conserved exactly and nothing is created), but it is
redistributed among them as the patch's own elements would send it: each element's
unoccluded point-to-triangle form factor (Lambert) from its centroid, times the visibility
the hemicube found from G (its form factor over the unoccluded one from G).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from hemirad.core.fastops import flatnonzero
from hemirad.geometry.analytic import point_to_triangles
from hemirad.geometry.mesh import Mesh


@dataclass(frozen=True)
class NearReceivers:
    """How a node's elements reach the receivers near it.

    Attributes:
        rows: (n,) the near receivers (not the node's own elements).
        weights: (k, n) per initial element of the node (k), its unoccluded form factor to each near
            receiver times that receiver's visibility from G; rows of a receiver G does not
            see are zero.
    """

    rows: torch.Tensor
    weights: torch.Tensor


def near_receivers(mesh: Mesh, members: torch.Tensor, sources: torch.Tensor, point: torch.Tensor,
                   normal: torch.Tensor, form_factors: torch.Tensor, reach: float,
                   among: torch.Tensor | None = None) -> NearReceivers:
    """The near receivers of the node whose (K,) ``members`` shoot from ``point`` (3,) along
    ``normal`` (3,), and their weights from the (k, 3) ``sources`` (its initial elements'
    centroids), given the node's hemicube ``form_factors`` (T,); only those among the (R,)
    elements ``among`` when given."""
    radius = float((mesh.corners_of(members).reshape(-1, 3) - point).norm(dim=1).max())
    candidates = torch.arange(mesh.num_elements, device=point.device) if among is None else among
    outside = torch.ones(mesh.num_elements, dtype=torch.bool, device=point.device)
    outside[members] = False
    near = (mesh.centroids.index_select(0, candidates) - point).norm(dim=1) < reach * radius
    near &= outside.index_select(0, candidates)
    near &= form_factors.index_select(0, candidates) > 0  # what G does not see at all stays unseen (occluded, or behind)
    rows = candidates[near]
    corners = mesh.corners_of(rows)  # (n, 3, 3)
    from_point = point_to_triangles(point, normal, corners)  # (n,)
    visibility = torch.where(from_point > 0, form_factors.index_select(0, rows) / from_point.clamp(min=1e-300),
                             torch.zeros_like(from_point))
    k, n = len(sources), len(rows)
    # every (source, receiver) pair in one call: each pair's point against its triangle
    from_sources = point_to_triangles(sources[:, None, None, :].expand(k, n, 1, 3).reshape(k * n, 1, 3), normal,
                                      corners[None].expand(k, n, 3, 3).reshape(k * n, 3, 3)).reshape(k, n)
    # Lambert's formula does not know sides: a source behind a receiver's plane (an element of
    # a floor patch that lies under a block, below the block's side) would light its back
    in_front = ((sources[:, None, :] - mesh.centroids.index_select(0, rows)[None]) *
                mesh.normals.index_select(0, rows)[None]).sum(-1) > 0  # (k, n)
    weights = torch.where(in_front, from_sources, torch.zeros_like(from_sources)) * visibility  # (k, n)
    return NearReceivers(rows, weights)


def incident_power(form_factors: torch.Tensor, shot_power: torch.Tensor, near: NearReceivers | None,
                   member_power: torch.Tensor | None) -> torch.Tensor:
    """(T, 3) the power reaching every receiver's front from a node's shot of ``shot_power`` (3,),
    its initial elements holding (k, 3) ``member_power`` of it: F_sj times the power, but among the
    ``near`` receivers the same total spread by the elements' own weights."""
    incident = form_factors[:, None] * shot_power[None, :]
    if near is None or len(near.rows) == 0:
        return incident
    spread = near.weights.T @ member_power  # (n, 3)
    from_point = incident.index_select(0, near.rows)
    spread_total = spread.sum(0)  # (3,)
    spreads = spread_total > 0  # a channel with nothing to spread by (no power in it) keeps G's numbers
    scale = torch.where(spreads, from_point.sum(0) / spread_total.clamp(min=1e-300), 0.0)  # keeps G's total
    redistributed = torch.where(spreads[None, :], spread * scale[None, :], from_point)
    return incident.index_copy(0, near.rows, redistributed)
