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

from hemirad.adaptive.shadow_edges import occlusion_pairs, shadow_edge_terms
from hemirad.transport.view import HemicubeView

# PyTorch's own forward-mode set-up scripts its decompositions on first use and warns that
# torch.jit.script is deprecated (a FutureWarning in torch 2.15, a DeprecationWarning in
# 2.11): nothing a user of hemirad can act on.
for _category in (FutureWarning, DeprecationWarning):
    warnings.filterwarnings("ignore", message=r".*torch\.jit\.script.*deprecated", category=_category,
                            module=r"torch\.jit")


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
