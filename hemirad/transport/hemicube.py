"""Hemicube item buffers rendered with OpenGL.

The five faces are drawn into one unsigned-integer atlas and read back at once:

    rows [0, R)                      top face, R x R, looking along the normal
    rows [R + i R/2, R + (i+1) R/2)  side face i (+x, -x, +y, -y of the local frame), R x R/2

Rows run bottom-up inside each face, as GL reads them; ``formfactor.hemicube_directions``
uses the same layout, so nothing is ever flipped. A pixel holds 0 where it sees nothing,
``id + 1`` where it sees the front of element ``id``, and ``(id + 1) | BACK_FACE_BIT``
where it sees its back (which occludes but receives nothing).

Each face draws only the triangles that can reach its view cone (``face_visibility``): a
triangle inside another face's cone, or below the horizon, covers none of its pixels, so
leaving it out changes no pixel, and each triangle is then drawn about once instead of
five times. The kept triangles keep their relative order, so depth ties resolve
as in a full draw, and the item atlas is the one an unculled render gives, bit for bit.
"""
from __future__ import annotations

import ctypes
import functools
import math
import time
from typing import Callable

import moderngl
import numpy as np
import torch

from hemirad.core.fastops import cross3
from hemirad.core.timing import Profiler
from hemirad.transport.gl import GLContext

BACK_FACE_BIT = 1 << 31

# Each face in the hemicube's local frame (z = shooter normal): forward, right and up axes,
# chosen so that right x up = -forward (a proper rotation keeps GL's front-face winding),
# and the lowest up-coordinate the face covers (sides only see the upper half, z >= 0).
FACES = (
    ((0, 0, 1), (1, 0, 0), (0, -1, 0), -1.0),   # top
    ((1, 0, 0), (0, -1, 0), (0, 0, 1), 0.0),    # +x
    ((-1, 0, 0), (0, 1, 0), (0, 0, 1), 0.0),    # -x
    ((0, 1, 0), (1, 0, 0), (0, 0, 1), 0.0),     # +y
    ((0, -1, 0), (-1, 0, 0), (0, 0, 1), 0.0),   # -y
)

_VERTEX_SHADER = """
#version 330
uniform mat4 mvp;
in vec3 position;
out float view_depth;
void main() {
    gl_Position = mvp * vec4(position, 1.0);
    view_depth = gl_Position.w;  // the frustum's last row is (0, 0, -1, 0): w is the view distance
}
"""

# Depth is written linearly in view distance: a fixed-point depth buffer then has the same
# precision everywhere, so the near plane can sit very close to the eye without z-fighting.
_FRAGMENT_SHADER = """
#version 330
uniform float near;
uniform float far;
uniform int first_item;  // the draw's first triangle's position in the drawn list
in float view_depth;
out uint item;
void main() {
    gl_FragDepth = (view_depth - near) / (far - near);
    item = uint(first_item + gl_PrimitiveID + 1) | (gl_FrontFacing ? 0u : 0x80000000u);
}
"""

_FACE_AXES = [(np.array(forward, dtype=float), np.array(right, dtype=float), np.array(up, dtype=float), bottom)
              for forward, right, up, bottom in FACES]


def face_viewports(resolution: int) -> list[tuple[int, int, int, int]]:
    """(x, y, width, height) of each face in the atlas."""
    half = resolution // 2
    return [(0, 0, resolution, resolution)] + [
        (0, resolution + i * half, resolution, half) for i in range(4)]


#: A tangent hint for hemicubes whose frame nothing else fixes (a patch's, a sensor's). A
#: pixel counts whole for the element its centre sees, so an outline running along the pixel
#: rows is off by the same fraction of a pixel all along it: under a 1 x 0.6 lamp seen from
#: 2 away (32 x 19 pixels), a frame along the lamp's edges errs by 1.0%, and a penumbra cast
#: by a blocker's edge along the rows by 5% (tests/test_patches.py). Scenes are mostly drawn
#: along their axes, so the frame is turned off every axis (29 degrees about y, 57 about x,
#: 20 about z; the hint is projected into the hemicube's plane): an edge then crosses the
#: rows, its pixels' errors cancel along it, and the lamp's point errs by 0.09%, the
#: penumbra by 1.7%. Fixed, so results are reproducible.
OFF_AXIS_TANGENT = np.array([math.cos(0.5), 0.31, math.sin(0.5)])


def tangent_frame(normal: np.ndarray, tangent_hint: np.ndarray) -> np.ndarray:
    """(3, 3) rows t, b, n: a right-handed orthonormal frame with n along ``normal``."""
    n = normal / np.linalg.norm(normal)
    t = tangent_hint - n * np.dot(tangent_hint, n)
    if np.linalg.norm(t) < 1e-9 * max(np.linalg.norm(tangent_hint), 1e-30):
        t = np.eye(3)[np.argmin(np.abs(n))]
        t = t - n * np.dot(t, n)
    t = t / np.linalg.norm(t)
    return np.stack([t, cross3(n, t), n])


def _frustum(left, right, bottom, top, near, far) -> np.ndarray:
    return np.array([
        [2 * near / (right - left), 0, (right + left) / (right - left), 0],
        [0, 2 * near / (top - bottom), (top + bottom) / (top - bottom), 0],
        [0, 0, -(far + near) / (far - near), -2 * far * near / (far - near)],
        [0, 0, -1, 0],
    ])


# Each face's view cone as the intersection of half-spaces a . d >= 0 (a in the local frame):
# the top's z >= |x| and z >= |y|, a side's (+x here) x >= |y|, x >= z and z >= 0 (sides see
# only the upper half); z >= 0 holds in the top's cone too, and belongs to all five.
_HALF_SPACES = np.array([
    (-1, 0, 1), (1, 0, 1), (0, -1, 1), (0, 1, 1),  # 0-3: z - x, z + x, z - y, z + y
    (1, -1, 0), (1, 1, 0), (-1, -1, 0), (-1, 1, 0),  # 4-7: x - y, x + y, -x - y, y - x
    (1, 0, -1), (-1, 0, -1), (0, 1, -1), (0, -1, -1),  # 8-11: x - z, -x - z, y - z, -y - z
    (0, 0, 1),  # 12: z
], dtype=np.float64)
_FACE_HALF_SPACES = ((0, 1, 2, 3, 12), (4, 5, 8, 12), (6, 7, 9, 12), (5, 7, 10, 12), (4, 6, 11, 12))  # as FACES
_FACE_MASKS = np.array([sum(1 << h for h in spaces) for spaces in _FACE_HALF_SPACES], dtype=np.int32)
_HALF_SPACE_BITS = (1 << np.arange(len(_HALF_SPACES))).astype(np.float64)


def face_visibility(local: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Which triangles may cover pixels of each face: (5, T) bool.

    A face's view cone is an intersection of half-spaces (``_HALF_SPACES``), so a triangle
    whose three vertices all lie outside one of them lies outside it: that face cannot see
    it. Every other triangle is drawn by the face: one inside a cone is drawn by that face
    alone, one across two cones by those two (not by all five), one below the horizon by
    none. A vertex counts as outside only beyond a margin far above float32 rounding in GL's
    own clipping, and a face's pixel centres lie half a pixel inside its cone, so the test
    never drops a triangle that GL would draw. Per vertex it costs thirteen dot products; per
    triangle two ANDs of bit masks.

    Args:
        local: (V, 3) float64 vertex positions relative to the eye, in the local frame.
        triangles: (T, 3) vertex indices.
    """
    margin = 1e-5 * (np.abs(local) @ np.ones(3))  # (V,)
    # (V,) bits: a float product of 0/1 flags and powers of two is exact, and faster than int's
    outside = ((local @ _HALF_SPACES.T < -margin[:, None]) @ _HALF_SPACE_BITS).astype(np.int32)
    corners = outside.take(triangles)  # (T, 3)
    common = corners[:, 0] & corners[:, 1] & corners[:, 2]  # the half-spaces all three lie outside
    return (common[None, :] & _FACE_MASKS[:, None]) == 0


class Hemicube:
    """Renders hemicube item buffers of one indexed triangle mesh.

    Args:
        resolution: R, the top face's width in pixels (even).
        cull: leave out of each face the triangles outside its view cone (the default). The
            atlas is the same without it (every face then draws every triangle); the
            option exists to show that.
        gpu: draw with the process's GPU context (``GLContext.get(gpu=True)``).
        profiler: accumulates the ``raster`` (culling and drawing) and ``readback`` seconds;
            a new one when None.
    Attributes:
        drawn_triangles: triangles drawn by the last render, over its five faces.
    """

    def __init__(self, resolution: int, cull: bool = True, gpu: bool = False, profiler: Profiler | None = None):
        if resolution < 2 or resolution % 2:
            raise ValueError(f"hemicube resolution must be an even number >= 2, got {resolution}")
        self.resolution = resolution
        self.cull = cull
        self.ctx = GLContext.get(gpu)
        self.program = self.ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
        size = (resolution, 3 * resolution)
        self._color = self.ctx.renderbuffer(size, components=1, dtype="u4")
        self._depth = self.ctx.depth_renderbuffer(size)
        self.fbo = self.ctx.framebuffer(color_attachments=[self._color], depth_attachment=self._depth)
        self._drawn = np.empty((3 * resolution, resolution), dtype=np.uint32)  # as read back
        self._vbo = self.ctx.buffer(reserve=12, dynamic=True)
        self._ibo = self.ctx.buffer(reserve=12, dynamic=True)
        self._vao = self.ctx.vertex_array(self.program, [(self._vbo, "3f", "position")],
                                          index_buffer=self._ibo, index_element_size=4)
        self._vertices = np.zeros((0, 3))
        self._triangles = np.zeros((0, 3), dtype=np.uint32)
        self._pending = None
        self._submitted = None  # (ids, ranges) of a render drawn and not yet read back
        self.num_triangles = self.drawn_triangles = 0
        self.profiler = profiler if profiler is not None else Profiler(("raster", "readback"))

    def set_geometry(self, vertices: torch.Tensor, triangles: torch.Tensor) -> None:
        """Set the mesh to draw; item ids are the triangles' row indices. It is uploaded by
        the next ``render``: a refining shot replaces the mesh several times between renders.

        Args:
            vertices: (V, 3) positions.
            triangles: (T, 3) vertex indices, counter-clockwise seen from the front.
        """
        self._pending = (vertices.detach(), triangles.detach())
        self.num_triangles = len(triangles)

    def _upload(self) -> None:
        vertices, triangles = self._pending
        self._pending = None
        self._vertices = vertices.cpu().numpy().astype(np.float64, copy=False)
        self._triangles = triangles.cpu().numpy().astype(np.uint32)
        _write(self._vbo, self._vertices.astype(np.float32))

    def release(self) -> None:
        for obj in (self._vao, self._vbo, self._ibo, self.fbo, self._color, self._depth, self.program):
            obj.release()

    def draw_lists(self, eye: np.ndarray, frame: np.ndarray) -> tuple[np.ndarray, list[tuple[int, int]]]:
        """The triangles each face of the hemicube at ``eye`` (3,) with ``frame`` (3, 3) draws:
        their ids in drawing order (N,), and per face the (first, count) range of that list it
        draws. CPU work alone once the mesh is uploaded: a caller makes the next hemicube's
        lists while the rasteriser still works on the one before (``submit``)."""
        start = time.perf_counter()
        if self._pending is not None:
            self._upload()
        if self.cull:
            visible = face_visibility((self._vertices - eye) @ frame.T, self._triangles)
        else:  # every face draws every triangle
            visible = np.ones((len(FACES), self.num_triangles), dtype=bool)
        # face by face, each in the triangles' order: positions in the flattened (5, T) mask
        ids = np.flatnonzero(visible)
        firsts = np.searchsorted(ids, np.arange(len(FACES) + 1) * self.num_triangles).tolist()
        ids %= max(self.num_triangles, 1)
        self.profiler.add("raster", time.perf_counter() - start)
        return ids, [(firsts[f], firsts[f + 1] - firsts[f]) for f in range(len(FACES))]

    def render(self, eye: np.ndarray, frame: np.ndarray, near: float, far: float) -> tuple[np.ndarray, np.ndarray]:
        """Draw the five faces seen from ``eye``.

        Args:
            eye: (3,) world position of the hemicube's centre.
            frame: (3, 3) rows t, b, n of the local frame (``tangent_frame``), n the normal.
            near, far: clip distances; everything between them along each face's axis is seen.
        Returns:
            element: (3R, R) int32, the triangle each pixel sees, -1 for none (the atlas of
                the module docstring, decoded);
            front: (3R, R) bool, the pixel sees a triangle's front (a back face occludes but
                receives nothing).
        """
        self.submit(eye, frame, near, far)
        return self.collect()

    def submit(self, eye: np.ndarray, frame: np.ndarray, near: float, far: float,
               lists: tuple[np.ndarray, list[tuple[int, int]]] | None = None) -> None:
        """The first half of ``render``: cull and draw, and let the driver start (``_flush``)
        without waiting for it; ``collect`` then waits and reads the atlas back. Between the
        two the caller's own work runs beside the rasteriser's threads (llvmpipe). One render
        at a time: ``collect`` before the next ``submit``. ``lists``: this placement's
        ``draw_lists``, when made already."""
        if self._submitted is not None:
            raise RuntimeError("a hemicube was submitted and not collected")
        eye = np.asarray(eye, dtype=np.float64)
        ids, ranges = self.draw_lists(eye, frame) if lists is None else lists
        start = time.perf_counter()
        _write(self._ibo, self._triangles[ids])
        ctx = self.ctx
        self.fbo.use()
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.disable(moderngl.CULL_FACE)
        self.fbo.clear(depth=1.0)  # colour to 0 ("nothing"); a float clear of an integer buffer writes its bit pattern
        self.program["near"].value = near
        self.program["far"].value = far
        translate = np.eye(4)
        translate[:3, 3] = -eye
        faces = zip(_FACE_AXES, face_viewports(self.resolution), ranges)
        for (forward, right, up, bottom), viewport, (first, count) in faces:
            if count == 0:
                continue
            rotation = np.eye(4)
            rotation[:3, :3] = np.stack([right @ frame, up @ frame, -forward @ frame])
            view = rotation @ translate
            mvp = _frustum(-near, near, bottom * near, near, near, far) @ view
            self.program["mvp"].write(mvp.T.astype(np.float32).tobytes())
            self.program["first_item"].value = first
            ctx.viewport = viewport
            self._vao.render(moderngl.TRIANGLES, vertices=3 * count, first=3 * first)
        _flush()
        self._submitted = (ids, ranges)
        self.profiler.add("raster", time.perf_counter() - start)

    def collect(self) -> tuple[np.ndarray, np.ndarray]:
        """Wait for the hemicube ``submit`` drew and read its atlas back, decoded (see
        ``render``)."""
        if self._submitted is None:
            raise RuntimeError("no hemicube was submitted")
        ids, ranges = self._submitted
        self._submitted = None
        start = time.perf_counter()
        _finish(self.ctx)
        mid = time.perf_counter()
        self.fbo.read_into(self._drawn, components=1, dtype="u4")
        self.drawn_triangles = sum(count for _, count in ranges)
        # position in the drawn list (+1; 0: nothing) -> triangle id (-1: nothing), in one
        # gather; a pixel sees a front when its item is neither 0 nor marked as a back face
        element = np.concatenate([[-1], ids]).astype(np.int32).take(self._drawn & np.uint32(BACK_FACE_BIT - 1))
        front = self._drawn - np.uint32(1) < np.uint32(BACK_FACE_BIT - 1)  # (0 - 1 wraps round)
        self.profiler.add("raster", mid - start)
        self.profiler.add("readback", time.perf_counter() - mid)
        return element, front


@functools.lru_cache(maxsize=2)
def _gl_function(name: str) -> Callable[[], None] | None:
    """``name`` (glFlush, glFinish) from the process's GL dispatch library (the one EGL's
    current context answers); None where there is none to load. Called through ctypes, it
    lets go of the interpreter while it runs, which moderngl's calls do not: another thread
    (the solver's worker) runs Python while this one waits for the rasteriser."""
    for library in ("libOpenGL.so.0", "libGL.so.1"):
        try:
            return getattr(ctypes.CDLL(library), name)
        except (OSError, AttributeError):
            continue
    return None


def _flush() -> None:
    """Hand the drawn commands to the driver now: llvmpipe rasterises a frame's bins only when
    it is flushed, which ``finish`` (or a read) would otherwise do, waiting."""
    flush = _gl_function("glFlush")
    if flush is not None:
        flush()


def _finish(ctx: moderngl.Context) -> None:
    """Wait for the drawn commands to complete, letting other threads run meanwhile
    (``_gl_function``)."""
    finish = _gl_function("glFinish")
    if finish is not None:
        finish()
    else:
        ctx.finish()


def _write(buffer: moderngl.Buffer, data: np.ndarray) -> None:
    """Replace a buffer's content, growing it (to twice the need) when it is too small."""
    data = np.ascontiguousarray(data)
    if data.nbytes > buffer.size:
        buffer.orphan(2 * data.nbytes)
    if data.nbytes:
        buffer.write(data.tobytes())
