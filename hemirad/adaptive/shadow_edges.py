"""The shadow-edge term of the form-factor gradient (docs/DESIGN.md §2).

Where two neighbouring pixels of one hemicube face see an occluder N in front of a farther
receiver F, moving the eye slides N's edge across F by parallax, and F gains or loses the
coverage it sweeps: F_F += -dF_bar ((delta(X_N) - delta(X_F)) . e) / h, zero in value at the
rendered eye. This module finds those pixel pairs (``occlusion_pairs``) and gives the term
as a function of the eye (``shadow_edge_terms``) for ``gradient.form_factor_gradient`` to
differentiate.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from hemirad.core.device import cached_per_device
from hemirad.core.fastops import flatnonzero, on_host, row_sums, take_or_none
from hemirad.transport.hemicube import FACES
from hemirad.transport.view import HemicubeView, pixel_faces


@cached_per_device
def neighbour_pairs(resolution: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every pair of 4-neighbour pixels within one face of the atlas (flattened indices).

    Returns:
        a, b (M,) int64 with b right of or above a, and step (M, 2) float64, the unit
        image-plane step from a to b. Do not modify (cached).
    """
    R = resolution
    grid = torch.arange(3 * R * R).reshape(3 * R, R)
    rows = pixel_faces(R)
    same_face = rows[:-1] == rows[1:]
    horizontal = (grid[:, :-1].reshape(-1), grid[:, 1:].reshape(-1))
    vertical = (grid[:-1][same_face].reshape(-1), grid[1:][same_face].reshape(-1))
    step = torch.cat([torch.tensor([[1.0, 0.0]], dtype=torch.float64).expand(len(horizontal[0]), 2),
                      torch.tensor([[0.0, 1.0]], dtype=torch.float64).expand(len(vertical[0]), 2)])
    return torch.cat([horizontal[0], vertical[0]]), torch.cat([horizontal[1], vertical[1]]), step


@cached_per_device
def pixel_pairs(resolution: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Where each pixel's pairs sit in ``neighbour_pairs``: (P,) the index of the pair with
    its right-hand neighbour and (P,) that with the neighbour above, -1 where there is none
    (the last column; the top row of a face). Do not modify (cached)."""
    a, b, _ = neighbour_pairs(resolution)
    P = 3 * resolution * resolution
    right = torch.full((P,), -1, dtype=torch.int64)
    up = torch.full((P,), -1, dtype=torch.int64)
    index = torch.arange(len(a))
    horizontal = b - a == 1
    right[a[horizontal]] = index[horizontal]
    up[a[~horizontal]] = index[~horizontal]
    return right, up


@cached_per_device
def same_face_rows(resolution: int) -> torch.Tensor:
    """(3R - 1,) bool: atlas row r and row r + 1 lie on one face (their vertical pairs are
    ``neighbour_pairs``'). Do not modify (cached)."""
    rows = pixel_faces(resolution)
    return rows[:-1] == rows[1:]


def boundary_pairs(label: torch.Tensor, resolution: int) -> torch.Tensor:
    """(M,) sorted indices into ``neighbour_pairs`` of the pairs whose two pixels carry
    different labels (neither of them -1): elements, or the planes they lie in.

    Found by comparing the atlas with itself shifted by one column and one row, over
    contiguous memory, instead of gathering both ends of every pair; the result is the
    same, in the same order.

    Args:
        label: (P,) int64 per pixel, -1 for none.
    """
    R = resolution
    same_face = same_face_rows(R, label.device)
    cpu = on_host(label)
    image = (label.numpy() if cpu else label).reshape(3 * R, R)  # NumPy compares int64 ~3x faster
    seen = image >= 0
    horizontal = ((image[:, :-1] != image[:, 1:]) & seen[:, :-1] & seen[:, 1:]).reshape(-1)
    vertical = ((image[:-1] != image[1:]) & seen[:-1] & seen[1:])[same_face.numpy() if cpu else same_face].reshape(-1)
    if cpu:
        horizontal, vertical = torch.from_numpy(horizontal), torch.from_numpy(vertical)
    return torch.cat([flatnonzero(horizontal), flatnonzero(vertical) + len(horizontal)])


def pairs_touching(pixels: torch.Tensor, resolution: int) -> torch.Tensor:
    """(M,) sorted indices into ``neighbour_pairs`` of the pairs that include any of ``pixels``."""
    right, up = pixel_pairs(resolution, pixels.device)
    R = resolution
    found = torch.cat([right[pixels], right[(pixels - 1).clamp(min=0)][pixels >= 1],
                       up[pixels], up[(pixels - R).clamp(min=0)][pixels >= R]])
    return torch.unique(found[found >= 0])


@dataclass
class OcclusionPairs:
    """Neighbouring pixel pairs at which a nearer element N hides a farther receiver F.

    Attributes:
        near_hit, far_hit: (K, 3) the two pixels' world hit points X_N, X_F.
        far_element: (K,) F's element index.
        axis: (K, 2) unit image-plane step from N's pixel to F's pixel.
        face: (K,) the hemicube face both pixels lie on.
        weight: (K,) mean delta form factor of the two pixels.
    """

    near_hit: torch.Tensor
    far_hit: torch.Tensor
    far_element: torch.Tensor
    axis: torch.Tensor
    face: torch.Tensor
    weight: torch.Tensor

    @staticmethod
    def none(device: torch.device) -> "OcclusionPairs":
        """No pairs (K = 0)."""
        def empty(*shape, dtype=torch.float64):
            return torch.zeros(shape, dtype=dtype, device=device)

        return OcclusionPairs(empty(0, 3), empty(0, 3), empty(0, dtype=torch.int64), empty(0, 2),
                              empty(0, dtype=torch.int64), empty(0))


def _straddling_pairs(view: HemicubeView, a: torch.Tensor, b: torch.Tensor, wanted: torch.Tensor | None,
                      plane_ids: torch.Tensor | None, pixels: torch.Tensor | None
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Of the pixel pairs ``neighbour_pairs`` gives (ends ``a``, ``b``), those whose pixels
    see two different elements (on different planes, with ``plane_ids``), one of them
    ``wanted``: (K,) their indices and (K,) the elements at either end."""
    R = view.resolution

    def ends(side, pair):  # the element at one end of each pair
        return view.element.index_select(0, side.index_select(0, pair))

    if pixels is not None and len(pixels) < len(view.element) // 16:
        # A later pass of a refining shot: the few pairs that touch a wanted element's pixel.
        pair = pairs_touching(view.wanted_pixels(wanted, pixels), R)
        ea, eb = ends(a, pair), ends(b, pair)
        keep = (ea != eb) & (ea >= 0) & (eb >= 0)
        if plane_ids is not None:
            keep &= plane_ids.index_select(0, ea.clamp(min=0)) != plane_ids.index_select(0, eb.clamp(min=0))
    else:  # all pairs across an element (or plane) boundary, then those touching a wanted element
        label = view.element
        if plane_ids is not None:
            label = take_or_none(plane_ids, label)
        pair = boundary_pairs(label, R)
        ea, eb = ends(a, pair), ends(b, pair)
        keep = torch.ones(len(pair), dtype=torch.bool, device=pair.device) if wanted is None else \
            wanted.index_select(0, ea) | wanted.index_select(0, eb)
    keep = flatnonzero(keep)
    return pair.index_select(0, keep), ea.index_select(0, keep), eb.index_select(0, keep)


def occlusion_pairs(view: HemicubeView, wanted: torch.Tensor | None = None, plane_ids: torch.Tensor | None = None,
                    pixels: torch.Tensor | None = None) -> OcclusionPairs:
    """Find the 4-neighbour pixel pairs within one face that straddle an occluding edge.

    A pair qualifies when the pixels see different elements, the farther one F is seen from
    the front, X_F lies beyond N's plane and X_N lies in front of F's plane (both as seen
    from the eye). The two plane tests reject edges where surfaces merely meet: coplanar
    neighbours, concave creases (X_F in front of N's plane) and convex creases seen from
    outside (X_N behind F's plane); only true occluders are left.

    Args:
        view: one render.
        wanted: (T,) bool, optional: only pairs whose farther element is marked.
        plane_ids: (T,) int64, optional (``Mesh.plane_ids``): pairs on one plane are
            dropped before the plane tests, which would reject them anyway.
        pixels: (N,) optional: the only pixels that may see a wanted element.
    """
    R = view.resolution
    a, b, step = neighbour_pairs(R, view.eye.device)
    pair, ea, eb = _straddling_pairs(view, a, b, wanted, plane_ids, pixels)
    if len(pair) == 0:  # often so in a refining shot's later passes
        return OcclusionPairs.none(view.eye.device)
    a, b = a.index_select(0, pair), b.index_select(0, pair)
    # Without plane ids most such pairs are coplanar neighbours on a finely meshed surface:
    # the plane tests run over all of them, in components-first layout.
    def side(X, k):  # signed distance of X (3, K) from element k's plane, positive on the eye's side
        n, p = view.normals_of(k), view.points.index_select(0, k).T
        return (n * (X - p)).sum(0) * -torch.sign(view.distance_of(k))

    Xa, Xb = view.hits(a), view.hits(b)  # (3, K)
    da2 = ((Xa - view.eye[:, None]) ** 2).sum(0)
    db2 = ((Xb - view.eye[:, None]) ** 2).sum(0)
    a_near = da2 < db2
    b_behind_a, a_before_b = side(Xb, ea), side(Xa, eb)
    far_behind_near = torch.where(a_near, b_behind_a, a_before_b)  # X_F from N's plane
    near_before_far = torch.where(a_near, a_before_b, b_behind_a)  # X_N from F's plane
    far = torch.where(a_near, b, a)
    tol = 1e-7 * torch.maximum(da2, db2).sqrt()
    occludes = view.front[far] & (far_behind_near < -tol) & (near_before_far > tol)
    if wanted is not None:
        occludes &= wanted[torch.where(a_near, eb, ea)]
    occludes = flatnonzero(occludes)
    a_near, far = a_near[occludes], far[occludes]
    near = torch.where(a_near, a[occludes], b[occludes])
    axis = torch.where(a_near[:, None], step[pair[occludes]], -step[pair[occludes]])  # from N's pixel towards F's
    en, ef = view.element[near], view.element[far]
    Xa, Xb = Xa[:, occludes].T, Xb[:, occludes].T  # (K, 3)
    to_near = torch.where(a_near[:, None], Xa, Xb) - view.eye
    to_far = torch.where(a_near[:, None], Xb, Xa) - view.eye
    # Both parallax points lie on the ray between the two pixel centres: taking each pixel's
    # own hit point would add the image-plane offset between them (one pixel, of either
    # sign) to the parallax, a bias that does not shrink relative to the edge term as the
    # eye moves along the view axis.
    ray = 0.5 * to_near / to_near.norm(dim=1, keepdim=True) + 0.5 * to_far / to_far.norm(dim=1, keepdim=True)

    def on_plane(k):
        return view.eye + (view.distance_of(k) / row_sums(ray * view.normals.index_select(0, k)))[:, None] * ray

    weight = 0.5 * (view.weight[near] + view.weight[far])
    return OcclusionPairs(on_plane(en), on_plane(ef), ef, axis, pixel_faces(R, view.eye.device)[near // R], weight)


def face_axes(frame: torch.Tensor) -> torch.Tensor:
    """(5, 3, 3) world forward, right and up axes of every hemicube face."""
    local = torch.tensor([face[:3] for face in FACES], dtype=torch.float64, device=frame.device)  # (5, 3, 3)
    return local @ frame


def shadow_edge_terms(c: torch.Tensor, view: HemicubeView, pairs: OcclusionPairs) -> torch.Tensor:
    """The coverage each occlusion pair's farther element gains or loses as the occluding
    edge slides with the eye: zero at c = eye; its derivative is the visibility part of dF_sj/dc.

    Args:
        c: (3,) the eye, or (3, K) one eye per pair (``eye_gradients``).
    Returns:
        (K,)
    """
    K = len(pairs.far_element)
    axes = face_axes(view.frame)[pairs.face].repeat(2, 1, 1)  # (2K, 3, 3): forward, right, up
    points = torch.cat([pairs.near_hit, pairs.far_hit])  # (2K, 3): X_N then X_F
    eyes = c.T.repeat(2, 1) if c.dim() == 2 else c  # (2K, 3) or (3,): the pair's eye for both points
    h = 2.0 / view.resolution

    def image_points(eye):  # (2K, 2) face-image coordinates of X_N and X_F seen from ``eye``
        depth_right_up = torch.einsum("kc,kac->ka", points - eye, axes)
        return depth_right_up[:, 1:] / depth_right_up[:, :1]

    shift = image_points(eyes) - image_points(view.eye)  # the second term is constant
    parallax = ((shift[:K] - shift[K:]) * pairs.axis).sum(1)
    return -pairs.weight * parallax / h
