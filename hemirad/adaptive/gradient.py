"""Form factors as differentiable functions of the shooter's position (docs/DESIGN.md §2).

The hemicube's item buffer is a step function of the eye position; what it sees is turned
into a smooth torch expression of the eye c whose value at the rendered eye c0 is the
hemicube's F_sj and whose derivative is the first-order change of F_sj as c moves:

* the **interior** term holds each pixel's receiver patch fixed (its world hit point y_q,
  the receiver normal n_j and the area dA_q it covers) and lets the point-to-patch kernel
  K_q(c) = (n_s . (y_q - c)) (n_j . (c - y_q)) / (pi |y_q - c|^4) dA_q vary;
* the **shadow-edge** term adds, where neighbouring pixels see an occluder N in front of a
  farther receiver F, the coverage F gains or loses as the eye's parallax slides N's edge
  across it: F_F += -dF_bar ((delta(X_N) - delta(X_F)) . e) / h, zero in value at c0.

Both are sums of per-pixel (per-pair) terms, each a pure function of c over tensors of one
render; ``form_factor_gradient`` takes their Jacobian by autograd, with no Python loop over
elements or pixels, over the pixels of the elements asked for only
(``form_factor_jacobian`` adds the form factors themselves). The paper's forward
("bottom-up") mode, three tangents for N outputs, is kept as the reference
(``mode="forward"``); the default gives every term its own copy of c and gets the same
Jacobian from one backward pass, which torch runs an order of magnitude faster.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch
from torch.func import jacfwd

from hemirad.core.device import cached_per_device
from hemirad.core.fastops import flatnonzero, on_host, row_sums, take_or_none
from hemirad.transport.hemicube import FACES
from hemirad.transport.view import HemicubeView, pixel_directions, pixel_faces

# PyTorch's own forward-mode set-up scripts its decompositions on first use and warns that
# torch.jit.script is deprecated (a FutureWarning in torch 2.15, a DeprecationWarning in
# 2.11): nothing a user of hemirad can act on.
for _category in (FutureWarning, DeprecationWarning):
    warnings.filterwarnings("ignore", message=r".*torch\.jit\.script.*deprecated", category=_category,
                            module=r"torch\.jit")


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
class ReceiverPatches:
    """The receiver patch behind every front-facing pixel of a render (Q pixels), frozen.

    The patches are kept relative to the rendered eye c0, with the dot products that do not
    depend on the eye precomputed, so that in the kernel the variable c enters only through
    d = c - c0 in three dot products per pixel: AD then differentiates a few (Q,) products
    rather than the (3, Q) y - c, and |y - c|^2 suffers no cancellation at c0.

    Attributes:
        origin: (3,) c0.
        offset: (3, Q) y_q - c0 for each pixel's world point y_q.
        element: (Q,) receiver j; normal: (3, Q) n_j.
        shooter_normal: (3,) n_s.
        facing: (Q,) n_s . (y_q - c0); receiver_facing: (Q,) n_j . (y_q - c0);
        distance2: (Q,) |y_q - c0|^2.
        scale: (Q,) w_q / kernel_q(c0), so that K_q(c0) is the hemicube's own weight w_q:
            the patch area dA_q (and pi) are defined by it rather than recomputed.
    """

    origin: torch.Tensor
    offset: torch.Tensor
    element: torch.Tensor
    normal: torch.Tensor
    shooter_normal: torch.Tensor
    facing: torch.Tensor
    receiver_facing: torch.Tensor
    distance2: torch.Tensor
    scale: torch.Tensor

    @staticmethod
    def from_view(view: HemicubeView, wanted: torch.Tensor | None = None,
                  pixels: torch.Tensor | None = None) -> "ReceiverPatches":
        """The patches of the front-facing pixels, or only of those that see an element marked
        in ``wanted`` (T,) bool, looked for among ``pixels`` (N,) when given."""
        pixels = view.wanted_pixels(wanted, pixels, front=True)
        element = view.element.index_select(0, pixels)
        offset = view.hits(pixels) - view.eye[:, None]
        normal = view.normals_of(element)
        shooter_normal = view.frame[2]
        facing, receiver_facing, distance2 = shooter_normal @ offset, (normal * offset).sum(0), (offset * offset).sum(0)
        # point_to_patch_kernel at c = c0, where d = 0 leaves these three terms exactly (same numbers)
        kernel = facing * -receiver_facing / (distance2 * distance2)
        return ReceiverPatches(view.eye, offset, element, normal, shooter_normal, facing, receiver_facing, distance2,
                               view.weight.index_select(0, pixels) / kernel)


def point_to_patch_kernel(c: torch.Tensor, patches: ReceiverPatches) -> torch.Tensor:
    """(Q,) (n_s . (y - c)) (n_j . (c - y)) / |y - c|^4 for every patch (the form factor
    kernel without pi and dA_q).

    Args:
        c: (3,) the eye, or (3, Q) one eye per patch (``eye_gradients``).
    """
    d = (c - patches.origin[:, None]) if c.dim() == 2 else (c - patches.origin)[:, None]  # (3, Q) or (3, 1)
    towards_receiver = patches.facing - patches.shooter_normal @ d  # n_s . (y - c)
    towards_shooter = (d * patches.normal).sum(0) - patches.receiver_facing  # n_j . (c - y)
    r2 = patches.distance2 - 2.0 * (d * patches.offset).sum(0) + (d * d).sum(0)  # |y - c|^2
    return towards_receiver * towards_shooter / (r2 * r2)


def interior_terms(c: torch.Tensor, patches: ReceiverPatches) -> torch.Tensor:
    """(Q,) K_q(c) = w_q kernel_q(c) / kernel_q(c0): each pixel's share of F_sj with its
    receiver patch frozen, the hemicube's w_q at c = c0; c as in ``point_to_patch_kernel``."""
    return patches.scale * point_to_patch_kernel(c, patches)


def interior_form_factors(c: torch.Tensor, patches: ReceiverPatches, num_elements: int) -> torch.Tensor:
    """F_sj(c) with each pixel's receiver patch frozen; equals the hemicube's F_sj at c = eye.

    Args:
        c: (3,) eye position (the variable).
        patches: the render's receiver patches.
    Returns:
        (T,) sum over the pixels q seeing j of ``interior_terms``.
    """
    return summed_rows(patches.element, interior_terms(c, patches), num_elements)


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
    if len(keep) == 0:  # often so in a refining shot's later passes
        return OcclusionPairs.none(view.eye.device)
    pair = pair.index_select(0, keep)
    a, b, ea, eb = a.index_select(0, pair), b.index_select(0, pair), ea.index_select(0, keep), eb.index_select(0, keep)
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


def summed_rows(index: torch.Tensor, values: torch.Tensor, size: int) -> torch.Tensor:
    """(size, ...) the sum of the (N, ...) ``values`` rows at each of their (N,) ``index``
    (an index_add: differentiable, and in a fixed order under ``runtime.deterministic``)."""
    return torch.zeros((size, *values.shape[1:]), dtype=values.dtype, device=values.device).index_add(0, index, values)


def eye_gradients(terms, eye: torch.Tensor, count: int) -> torch.Tensor:
    """(count, 3) d term_i / dc for ``terms``: (3, count) eyes -> (count,) values, where term i
    reads column i only.

    Each term gets its own copy of the eye, so that one reverse sweep of their sum yields
    every term's gradient: the Jacobian of count outputs by three inputs that forward mode
    gets from three tangents, at the cost of one backward pass (torch's forward-mode rules
    for elementwise ops run through Python decompositions, about 10x slower for the small
    terms of a refining shot's later passes; ``form_factor_gradient(mode="forward")`` keeps
    that path as the reference).
    """
    eyes = eye[:, None].expand(3, count).clone().requires_grad_()
    with torch.enable_grad():
        gradient, = torch.autograd.grad(terms(eyes).sum(), eyes)
    return gradient.T


def form_factor_gradient(view: HemicubeView, interior: bool = True, shadow_edges: bool = True,
                         wanted: torch.Tensor | None = None, plane_ids: torch.Tensor | None = None,
                         pixels: torch.Tensor | None = None,
                         interior_wanted: torch.Tensor | None = None, mode: str = "reverse") -> torch.Tensor:
    """dF_sj/dc for every element, by autograd: (T, 3).

    Args:
        view: one render.
        interior, shadow_edges: which terms to include (for accuracy studies).
        wanted: (T,) bool, optional: the elements whose gradient is needed. Only their
            pixels and edges enter the differentiated function, so the cost follows their
            share of the image; J is zero in the other rows, and the same as without
            ``wanted`` in these.
        plane_ids: (T,) ``Mesh.plane_ids``, optional: speeds up finding shadow edges.
        pixels: (N,) optional, with ``wanted``: the only pixels that may see a wanted element.
        interior_wanted: (T,) bool, optional, within ``wanted``: the only elements whose
            interior term is needed, besides those with shadow-edge pairs (which get both).
            The rows of the others then hold their shadow-edge term alone.
        mode: "reverse", one backward pass over per-term copies of the eye
            (``eye_gradients``), or "forward", ``torch.func.jacfwd`` with three tangents
            (the paper's bottom-up mode): the same derivative, to rounding.
    Under ``torch.inference_mode``, where autograd records nothing, the view's tensors are
    copied out of it and the derivative is taken outside it.
    """
    if mode not in ("reverse", "forward"):
        raise ValueError(f"mode must be 'reverse' or 'forward', not {mode!r}")
    if torch.is_inference_mode_enabled():
        with torch.inference_mode(False):
            def copy(t):
                return None if t is None else t.clone()

            return form_factor_gradient(view.copy(), interior, shadow_edges, copy(wanted), copy(plane_ids),
                                        copy(pixels), copy(interior_wanted), mode)
    T = len(view.normals)
    pairs = occlusion_pairs(view, wanted, plane_ids, pixels) if shadow_edges else None
    if interior_wanted is not None:
        if pairs is not None:
            interior_wanted = interior_wanted.clone()
            interior_wanted[pairs.far_element] = True
        wanted = interior_wanted if wanted is None else wanted & interior_wanted
    patches = ReceiverPatches.from_view(view, wanted, pixels) if interior else None
    # Terms with nothing to sum are left out of the differentiated function (and when both
    # are, so is autograd: its set-up costs more than a later pass's few pixels).
    if patches is not None and len(patches.element) == 0:
        patches = None
    if pairs is not None and len(pairs.far_element) == 0:
        pairs = None
    if patches is None and pairs is None:
        return torch.zeros(T, 3, dtype=torch.float64, device=view.eye.device)

    # (index, terms) per term: each term's value is a function of the eye alone, summed by index
    parts = ([(patches.element, lambda c: interior_terms(c, patches))] if patches is not None else []) + \
            ([(pairs.far_element, lambda c: shadow_edge_terms(c, view, pairs))] if pairs is not None else [])
    if mode == "forward":
        return jacfwd(lambda c: sum(summed_rows(index, terms(c), T) for index, terms in parts))(view.eye)
    J = torch.zeros(T, 3, dtype=torch.float64, device=view.eye.device)
    for index, terms in parts:
        J.index_add_(0, index, eye_gradients(terms, view.eye, len(index)))
    return J


def form_factor_jacobian(view: HemicubeView, interior: bool = True, shadow_edges: bool = True,
                         wanted: torch.Tensor | None = None, plane_ids: torch.Tensor | None = None
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """F_sj (T,), the hemicube form factors of every element, and their gradient J (T, 3)
    with respect to the eye (``form_factor_gradient``, same arguments)."""
    return view.form_factors, form_factor_gradient(view, interior, shadow_edges, wanted, plane_ids)
