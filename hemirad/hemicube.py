"""Hemicube item buffers rendered with OpenGL.

The five faces are drawn into one unsigned-integer atlas and read back at once:

    rows [0, R)                      top face, R x R, looking along the normal
    rows [R + i R/2, R + (i+1) R/2)  side face i (+x, -x, +y, -y of the local frame), R x R/2

Rows run bottom-up inside each face, as GL reads them; ``formfactor.hemicube_directions``
uses the same layout, so nothing is ever flipped. A pixel holds 0 where it sees nothing,
``id + 1`` where it sees the front of element ``id``, and ``(id + 1) | BACK_FACE_BIT``
where it sees its back (which occludes but receives nothing).
"""
from __future__ import annotations

import time

import moderngl
import numpy as np
import torch

from .gl import GLContext

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
uniform mat4 view;
in vec3 position;
out float view_depth;
void main() {
    view_depth = -(view * vec4(position, 1.0)).z;
    gl_Position = mvp * vec4(position, 1.0);
}
"""

# Depth is written linearly in view distance: a fixed-point depth buffer then has the same
# precision everywhere, so the near plane can sit very close to the eye without z-fighting.
_FRAGMENT_SHADER = """
#version 330
uniform float near;
uniform float far;
in float view_depth;
out uint item;
void main() {
    gl_FragDepth = (view_depth - near) / (far - near);
    item = uint(gl_PrimitiveID + 1) | (gl_FrontFacing ? 0u : 0x80000000u);
}
"""


def face_viewports(resolution: int) -> list[tuple[int, int, int, int]]:
    """(x, y, width, height) of each face in the atlas."""
    half = resolution // 2
    return [(0, 0, resolution, resolution)] + [
        (0, resolution + i * half, resolution, half) for i in range(4)]


def tangent_frame(normal: np.ndarray, tangent_hint: np.ndarray) -> np.ndarray:
    """(3, 3) rows t, b, n: a right-handed orthonormal frame with n along ``normal``."""
    n = normal / np.linalg.norm(normal)
    t = tangent_hint - n * np.dot(tangent_hint, n)
    if np.linalg.norm(t) < 1e-9 * max(np.linalg.norm(tangent_hint), 1e-30):
        t = np.eye(3)[np.argmin(np.abs(n))]
        t = t - n * np.dot(t, n)
    t = t / np.linalg.norm(t)
    return np.stack([t, np.cross(n, t), n])


def _frustum(left, right, bottom, top, near, far) -> np.ndarray:
    return np.array([
        [2 * near / (right - left), 0, (right + left) / (right - left), 0],
        [0, 2 * near / (top - bottom), (top + bottom) / (top - bottom), 0],
        [0, 0, -(far + near) / (far - near), -2 * far * near / (far - near)],
        [0, 0, -1, 0],
    ])


class Hemicube:
    """Renders hemicube item buffers of one triangle soup.

    Args:
        resolution: R, the top face's width in pixels (even).
    Attributes:
        raster_seconds, readback_seconds: accumulated time in drawing and in read-back.
    """

    def __init__(self, resolution: int):
        if resolution < 2 or resolution % 2:
            raise ValueError(f"hemicube resolution must be an even number >= 2, got {resolution}")
        self.resolution = resolution
        self.ctx = GLContext.get()
        self.program = self.ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
        size = (resolution, 3 * resolution)
        self._color = self.ctx.renderbuffer(size, components=1, dtype="u4")
        self._depth = self.ctx.depth_renderbuffer(size)
        self.fbo = self.ctx.framebuffer(color_attachments=[self._color], depth_attachment=self._depth)
        self._items = np.empty((3 * resolution, resolution), dtype=np.uint32)
        self._vbo = self._vao = None
        self.num_triangles = 0
        self.raster_seconds = self.readback_seconds = 0.0

    def set_geometry(self, corners: torch.Tensor) -> None:
        """Upload the triangles to draw; item ids are their row indices.

        Args:
            corners: (T, 3, 3) vertex positions, counter-clockwise seen from the front.
        """
        self.release_geometry()
        data = np.ascontiguousarray(corners.detach().cpu().numpy(), dtype=np.float32)
        self._vbo = self.ctx.buffer(data.tobytes())
        self._vao = self.ctx.vertex_array(self.program, [(self._vbo, "3f", "position")])
        self.num_triangles = len(data)

    def release_geometry(self) -> None:
        for obj in (self._vao, self._vbo):
            if obj is not None:
                obj.release()
        self._vbo = self._vao = None

    def release(self) -> None:
        self.release_geometry()
        for obj in (self.fbo, self._color, self._depth, self.program):
            obj.release()

    def render(self, eye: np.ndarray, frame: np.ndarray, near: float, far: float) -> np.ndarray:
        """Draw the five faces seen from ``eye``.

        Args:
            eye: (3,) world position of the hemicube's centre.
            frame: (3, 3) rows t, b, n of the local frame (``tangent_frame``), n the normal.
            near, far: clip distances; everything between them along each face's axis is seen.
        Returns:
            (3R, R) uint32 item atlas (see the module docstring). Overwritten by the next call.
        """
        start = time.perf_counter()
        ctx = self.ctx
        self.fbo.use()
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.disable(moderngl.CULL_FACE)
        self.fbo.clear(depth=1.0)  # colour to 0 ("nothing"); a float clear of an integer buffer writes its bit pattern
        self.program["near"].value = near
        self.program["far"].value = far
        translate = np.eye(4)
        translate[:3, 3] = -np.asarray(eye, dtype=np.float64)
        for (forward, right, up, bottom), viewport in zip(FACES, face_viewports(self.resolution)):
            rotation = np.eye(4)
            rotation[:3, :3] = np.stack([np.asarray(right) @ frame, np.asarray(up) @ frame, -np.asarray(forward) @ frame])
            view = rotation @ translate
            mvp = _frustum(-near, near, bottom * near, near, near, far) @ view
            self.program["mvp"].write(mvp.T.astype(np.float32).tobytes())
            self.program["view"].write(view.T.astype(np.float32).tobytes())
            ctx.viewport = viewport
            if self._vao is not None:
                self._vao.render(moderngl.TRIANGLES)
        ctx.finish()
        mid = time.perf_counter()
        self.fbo.read_into(self._items, components=1, dtype="u4")
        self.raster_seconds += mid - start
        self.readback_seconds += time.perf_counter() - mid
        return self._items
