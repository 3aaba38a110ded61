"""Hemicubes of a mesh's elements, rendered and turned into ``HemicubeView`` records."""
from __future__ import annotations

from typing import Iterator

import numpy as np
import torch

from hemirad.core.timing import Profiler
from hemirad.geometry.mesh import Mesh
from hemirad.transport.formfactor import delta_form_factors, form_factors_and_back_share
from hemirad.transport.hemicube import Hemicube, tangent_frame
from hemirad.transport.view import HemicubeView


def clip_planes(mesh: Mesh, points: torch.Tensor | None = None) -> tuple[float, float]:
    """The (near, far) distances of a hemicube in ``mesh``'s scene; near is also how far the
    eye sits off the shooter's plane. ``points`` (N, 3): eyes that may lie outside the
    mesh's bounds (sensors), whose hemicubes must reach across the mesh too.

    The eye sits just off the shooter so that its own plane (and coplanar neighbours) falls
    below every face's field of view; depth is linear (``hemicube.py``), so a near plane
    this close loses no precision.
    """
    lo, hi = mesh.bounding_box()
    if points is not None and len(points):
        points = torch.as_tensor(points, dtype=lo.dtype, device=lo.device)
        lo, hi = torch.minimum(lo, points.min(dim=0).values), torch.maximum(hi, points.max(dim=0).values)
    diagonal = float((hi - lo).norm())
    return 1e-6 * diagonal, 1.01 * diagonal


#: Prefetched hemicubes read back and not asked for yet, at most (an atlas each, 1 MB at
#: resolution 256).
READY_MAX = 2


class HemicubeRenderer:
    """What the hemicube of any element of a mesh sees, and so its form factors to all of them.

    Args:
        mesh: the elements (triangles counter-clockwise seen from the front); its bounds
            fix the clip planes (``clip_planes``) for this renderer's life.
        resolution: hemicube resolution R.
        cull: draw each hemicube face only the triangles that can reach it (same result, faster).
        device: where the torch work runs (the mesh's tensors must be there); on CUDA the
            OpenGL context must be on the GPU too (``GLContext.get(gpu=True)``).
        profiler: accumulates ``raster``, ``readback`` and ``form_factors`` (decoding and
            summing) seconds; a new one when None.
        clip: the (near, far) planes, for eyes outside the mesh's bounds; default
            ``clip_planes(mesh)``.
    Attributes:
        renders: hemicubes rendered so far.
    """

    def __init__(self, mesh: Mesh, resolution: int, cull: bool = True, device: torch.device | str = "cpu",
                 profiler: Profiler | None = None, clip: tuple[float, float] | None = None):
        self.device = torch.device(device)
        self.profiler = profiler if profiler is not None else Profiler(("raster", "readback", "form_factors"))
        self.weights = delta_form_factors(resolution, self.device)  # (3R, R)
        self.near, self.far = clip_planes(mesh) if clip is None else clip
        self.renders = 0  # hemicubes rendered
        self.hemicube = Hemicube(resolution, cull, gpu=self.device.type == "cuda", profiler=self.profiler)
        self._prefetched = None  # (key, eye, frame) of a hemicube submitted, not yet read back
        # read back before they were asked for: key -> (atlas, eye, frame)
        self._ready: dict[bytes, tuple[tuple[np.ndarray, np.ndarray], np.ndarray, np.ndarray]] = {}
        self.set_geometry(mesh)

    def set_geometry(self, mesh: Mesh) -> None:
        """Replace the mesh (after refinement); it must stay inside the first one's bounds."""
        self._drop_prefetched()
        self.mesh = mesh
        self.hemicube.set_geometry(mesh.vertices, mesh.triangles)

    def close(self) -> None:
        self._drop_prefetched()
        self.hemicube.release()

    def render(self, shooter: int) -> HemicubeView:
        """Render the hemicube of element ``shooter`` (a point at its centroid) and sum its
        form factors to every element."""
        mesh = self.mesh
        corners = mesh.corners_of(shooter).cpu().numpy()
        return self.render_at(mesh.centroids[shooter].cpu().numpy(), mesh.normals[shooter].cpu().numpy(),
                              corners[1] - corners[0])

    def prefetch_at(self, point: np.ndarray, normal: np.ndarray, tangent: np.ndarray) -> None:
        """Start drawing the hemicube ``render_at`` will be asked for with these arguments, and
        return at once: the rasteriser works while the caller does. The one drawn before, if
        not asked for yet, is read back first and kept as read: a sweep prefetches the next
        patch's hemicube before it asks for this one's, whose form factors and use then run
        while the next is drawn. Ignored when this one is pending or read back, or when
        ``READY_MAX`` are read back and not asked for."""
        key = _key(point, normal, tangent)
        if key in self._ready or len(self._ready) >= READY_MAX or (
                self._prefetched is not None and self._prefetched[0] == key):
            return
        self._prefetched = (key, *self._submit(point, normal, tangent))

    def render_at(self, point: np.ndarray, normal: np.ndarray, tangent: np.ndarray) -> HemicubeView:
        """Render the hemicube at ``point`` (3,) on a surface of unit ``normal`` (3,), its frame
        turned by the in-plane ``tangent`` (3,), and sum its form factors to every element
        (the one ``prefetch_at`` started, when asked for the same)."""
        key = _key(point, normal, tangent)
        if self._prefetched is not None and self._prefetched[0] == key:
            self._read_back()
        if key in self._ready:
            return self._view(*self._ready.pop(key))
        eye, frame = self._submit(point, normal, tangent)
        return self._view(self.hemicube.collect(), eye, frame)

    def views_at(self, points: np.ndarray, normals: np.ndarray, tangents: np.ndarray) -> Iterator[HemicubeView]:
        """``render_at`` for each of the (N, 3) ``points``, in order, with its (N, 3) ``normals``
        and ``tangents`` (or one (3,) each for all), the next one drawn (``prefetch_at``) while
        the caller uses this one."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        normals, tangents = (np.broadcast_to(np.asarray(x, dtype=np.float64), points.shape) for x in (normals, tangents))
        if len(points):
            self.prefetch_at(points[0], normals[0], tangents[0])
        for i in range(len(points)):
            if i + 1 < len(points):
                self.prefetch_at(points[i + 1], normals[i + 1], tangents[i + 1])
            yield self.render_at(points[i], normals[i], tangents[i])

    def _submit(self, point: np.ndarray, normal: np.ndarray, tangent: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Draw the hemicube at this placement (``Hemicube.submit``) and return its eye and
        frame: culled while the one prefetched before, if any, is still being drawn, which is
        then read back (``_read_back``) to free the framebuffer."""
        eye, frame = self._placed(point, normal, tangent)
        lists = self.hemicube.draw_lists(eye, frame)
        self._read_back()
        self.renders += 1
        self.hemicube.submit(eye, frame, self.near, self.far, lists)
        return eye, frame

    def _read_back(self) -> None:
        """Wait for the prefetched hemicube, if any, and keep its atlas as read."""
        if self._prefetched is not None:
            key, eye, frame = self._prefetched
            self._prefetched = None
            self._ready[key] = (self.hemicube.collect(), eye, frame)

    def _placed(self, point: np.ndarray, normal: np.ndarray, tangent: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The hemicube's eye (3,), just off the surface, and its frame (3, 3)."""
        return point + self.near * normal, tangent_frame(normal, tangent)

    def _view(self, atlas: tuple[np.ndarray, np.ndarray], eye: np.ndarray, frame: np.ndarray) -> HemicubeView:
        """The view of a hemicube's decoded ``atlas`` (``Hemicube.collect``) drawn at ``eye``."""
        mesh = self.mesh
        with self.profiler.phase("form_factors"):
            element, front = (torch.from_numpy(x).to(self.device).reshape(-1) for x in atlas)
            weight = self.weights.reshape(-1)
            F, back_share = form_factors_and_back_share(element, front, weight, mesh.num_elements)
        return HemicubeView(element, front, weight, torch.from_numpy(eye).to(self.device),
                            torch.from_numpy(np.ascontiguousarray(frame, dtype=np.float64)).to(self.device),
                            mesh.normals, mesh.centroids, F, self.hemicube.resolution, back_share)

    def _drop_prefetched(self) -> None:
        """Forget the prefetched hemicubes (the mesh changes, or the renderer closes)."""
        self._read_back()
        self._ready.clear()

    def from_element(self, shooter: int) -> torch.Tensor:
        """(T,) F_sj from element ``shooter`` to every element j."""
        return self.render(shooter).form_factors


def _key(point: np.ndarray, normal: np.ndarray, tangent: np.ndarray) -> bytes:
    """What identifies a hemicube's placement, exactly."""
    return b"".join(np.asarray(a, dtype=np.float64).tobytes() for a in (point, normal, tangent))
