"""What one hemicube render saw: ``HemicubeView``, the record every later stage reads.

The solver sums its form factors, the gradient turns its pixels into receiver patches and
occlusion pairs, the criteria bound scores from it, and relabelling carries it across a
split; like PyTorch3D's ``Fragments`` for one rasterisation, it is made once per render (or
per relabelling) and read, never changed.

No depth is kept: every pixel's hit point is recomputed exactly where its ray meets the
plane of the element it sees (``HemicubeView.hits``), which the fixed-point depth buffer
could give only to its precision.
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace
from functools import cached_property

import torch

from hemirad.core.device import cached_per_device
from hemirad.core.fastops import flatnonzero, marked_positions, row_sums
from hemirad.transport.formfactor import element_form_factors, hemicube_directions
from hemirad.transport.hemicube import face_viewports


@cached_per_device
def pixel_faces(resolution: int) -> torch.Tensor:
    """(3R,) int64: which hemicube face (index into ``FACES``) each atlas row belongs to."""
    rows = torch.empty(3 * resolution, dtype=torch.int64)
    for face, (_, y0, _, height) in enumerate(face_viewports(resolution)):
        rows[y0:y0 + height] = face
    return rows


@cached_per_device
def pixel_directions(resolution: int) -> torch.Tensor:
    """(3, P) ``hemicube_directions`` flattened, components first: per-pixel arithmetic
    then runs over contiguous rows. Do not modify (cached)."""
    return hemicube_directions(resolution).reshape(-1, 3).T.contiguous()


@cached_per_device
def pixel_sines(resolution: int) -> torch.Tensor:
    """(P,) the sine of each pixel ray's angle from the hemicube's axis (the local z). Do not
    modify (cached)."""
    d = pixel_directions(resolution)
    return d[:2].norm(dim=0) / d.norm(dim=0)


@dataclass(frozen=True)
class HemicubeView:
    """What the hemicube of one shooter saw (P = 3R^2 pixels of the atlas, flattened; T
    elements), as detached tensors on the solver's device.

    Attributes:
        element: (P,) int32 element seen by each pixel, -1 for none (int32: half the bytes
            of the views a sweep holds for its worker).
        front: (P,) bool, the pixel sees an element's front (a back face occludes but
            receives nothing).
        weight: (P,) float64 delta form factor of each pixel (``delta_form_factors``).
        eye: (3,) float64, where the hemicube was rendered (just off the shooter's centroid).
        frame: (3, 3) float64, rows t, b, n of its local frame; n is the shooter's normal.
        normals, points: (T, 3) float64 every element's unit normal and a point on its plane
            (its centroid), of the mesh the view is of.
        form_factors: (T,) float64 F_sj, the sum of ``weight`` over the front-facing pixels
            of each element.
        resolution: R.
        back_share: () float64, the sum of ``weight`` over the pixels that see a back face:
            the share of the shooter's power that its hemicube sends into them.
        relabelled_pixels: (N,) int64 for a view carried over a split
            (``adaptive.relabel.relabel_view``), the pixels relabelled, the only ones that
            see new elements; None for a render.
    """

    element: torch.Tensor
    front: torch.Tensor
    weight: torch.Tensor
    eye: torch.Tensor
    frame: torch.Tensor
    normals: torch.Tensor
    points: torch.Tensor
    form_factors: torch.Tensor
    resolution: int
    back_share: torch.Tensor
    relabelled_pixels: torch.Tensor | None = None

    def copy(self) -> "HemicubeView":
        """The same view over copies of its tensors (made outside ``torch.inference_mode``,
        they are ones autograd may use)."""
        return replace(self, **{f.name: getattr(self, f.name).clone() for f in fields(self)
                                if isinstance(getattr(self, f.name), torch.Tensor)})

    @cached_property
    def distance(self) -> torch.Tensor:
        """(T,) n_j . (p_j - eye): each element's plane seen from the eye."""
        return row_sums((self.points - self.eye) * self.normals)

    def distance_of(self, k: torch.Tensor) -> torch.Tensor:
        """(N,) ``distance`` of the (N,) elements ``k`` only (the same numbers)."""
        return row_sums((self.points.index_select(0, k) - self.eye) * self.normals.index_select(0, k))

    def normals_of(self, k: torch.Tensor) -> torch.Tensor:
        """(3, N) the normals of the (N,) elements ``k``, components first (a transposed
        view: the arithmetic on it is faster than copying it into that layout)."""
        return self.normals.index_select(0, k).T

    def hits(self, pixels: torch.Tensor) -> torch.Tensor:
        """(3, N) the world points the given pixels (N,) see, components first.

        Exact: the pixel's ray meets the plane of the element it sees. A pass that needs few
        pixels (a later pass of a refining shot) computes only those; one that needs many
        computes every pixel's once, without the gathers, and indexes that.
        """
        if len(pixels) > len(self.element) // 3:  # measured: the gathers cost about 3x per pixel
            return self._all_hits.index_select(1, pixels)
        directions = self.frame.T @ pixel_directions(self.resolution, self.eye.device).index_select(1, pixels)
        k = self.element.index_select(0, pixels).clamp(min=0)
        return self._hits(k, self.distance_of(k), directions)

    @cached_property
    def _all_hits(self) -> torch.Tensor:
        k = self.element.clamp(min=0)
        directions = self.frame.T @ pixel_directions(self.resolution, self.eye.device)
        return self._hits(k, self.distance.index_select(0, k), directions)

    def _hits(self, k: torch.Tensor, distance: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
        """(3, N) where the rays (3, N) ``directions`` from the eye meet the planes of the
        (N,) elements ``k``, whose ``distance`` (N,) is given."""
        return self.eye[:, None] + (distance / (directions * self.normals_of(k)).sum(0)) * directions

    def sine_sums(self, pixels: torch.Tensor | None = None) -> torch.Tensor:
        """(T,) per element, the sum over its front-facing pixels of w_q sin(theta_q), theta_q
        the angle between the pixel's ray and the shooter's normal (``gradient_score_bound``);
        over ``pixels`` (N,) only when given (elements none of them see get 0 or a partial sum)."""
        sine = pixel_sines(self.resolution, self.eye.device)
        element, front, weight = self.element, self.front, self.weight
        if pixels is not None:
            element, front, weight, sine = (x.index_select(0, pixels) for x in (element, front, weight, sine))
        return element_form_factors(element, front, weight * sine, len(self.normals))

    def wanted_pixels(self, wanted: torch.Tensor | None, pixels: torch.Tensor | None = None,
                      front: bool = False) -> torch.Tensor:
        """(N,) the pixels that see an element marked in ``wanted`` (every element when None),
        front-facing only with ``front``; only ``pixels`` are examined when given (the rest
        are known to see none of the wanted elements)."""
        element = self.element if pixels is None else self.element.index_select(0, pixels)
        if wanted is None:
            found = flatnonzero(element >= 0)
        else:
            found = marked_positions(element, wanted)
        if front:  # a front-facing pixel sees an element: a subset of the found ones
            seen_front = self.front if pixels is None else self.front.index_select(0, pixels)
            found = found.index_select(0, flatnonzero(seen_front.index_select(0, found)))
        return found if pixels is None else pixels.index_select(0, found)
