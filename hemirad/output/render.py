"""Camera views of the solved mesh: Gouraud-shaded per-vertex radiosity through OpenGL, and
the element and point each pixel's centre sees.

The image is linear radiosity (no exposure, no sRGB); ``display.to_srgb8`` encodes it.
Antialiasing renders ``supersample`` times larger into a float framebuffer and box-filters
in linear space, which behaves the same on every driver (llvmpipe caps MSAA at 4 samples
and resolves in an unspecified way).
"""
from __future__ import annotations

import dataclasses
import math
import weakref

import moderngl
import numpy as np
import torch

from hemirad.core.errors import HemiradInputError
from hemirad.geometry.mesh import Mesh
from hemirad.scene.model import Camera
from hemirad.transport.gl import GLContext, check_image_size

_VERTEX_SHADER = """
#version 330
uniform mat4 clip_from_eye;
in vec3 in_position;  // relative to the camera position, rotated into eye space
in vec3 in_color;
out vec3 v_color;
void main() {
    v_color = in_color;
    gl_Position = clip_from_eye * vec4(in_position, 1.0);
}
"""

_FRAGMENT_SHADER = """
#version 330
in vec3 v_color;
out vec4 f_color;
void main() {
    f_color = vec4(v_color, 1.0);
}
"""

# One program per context; the context lives as long as the process, but keying weakly
# keeps this correct if a test ever makes and drops its own.
_PROGRAMS: "weakref.WeakKeyDictionary[moderngl.Context, moderngl.Program]" = weakref.WeakKeyDictionary()


def _program(ctx: moderngl.Context) -> moderngl.Program:
    program = _PROGRAMS.get(ctx)
    if program is None:
        program = ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
        _PROGRAMS[ctx] = program
    return program


def camera_basis(camera: Camera) -> np.ndarray:
    """(3, 3) float64 rows: right, up, backward (the eye-space x, y, z axes in world space).

    OpenGL's eye space looks down -z, so the third row points from the target to the eye.
    """
    eye = np.asarray(camera.position, dtype=np.float64)
    forward = np.asarray(camera.look_at, dtype=np.float64) - eye
    if not np.linalg.norm(forward) > 0:
        raise HemiradInputError("camera.look_at must differ from camera.position.")
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(camera.up, dtype=np.float64))
    if not np.linalg.norm(right) > 1e-9:
        raise HemiradInputError("camera.up must not be parallel to the viewing direction (look_at - position).")
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return np.stack([right, up, -forward])


def perspective(fov_y_degrees: float, aspect: float, near: float, far: float) -> np.ndarray:
    """(4, 4) float64 OpenGL projection (eye space -> clip space), row-major."""
    f = 1.0 / math.tan(math.radians(fov_y_degrees) / 2.0)
    return np.array([
        [f / aspect, 0.0, 0.0, 0.0],
        [0.0, f, 0.0, 0.0],
        [0.0, 0.0, (far + near) / (near - far), 2.0 * far * near / (near - far)],
        [0.0, 0.0, -1.0, 0.0],
    ])


def orthographic(left: float, right: float, bottom: float, top: float, near: float, far: float) -> np.ndarray:
    """(4, 4) float64 OpenGL parallel projection (glOrtho): the eye-space box
    [left, right] x [bottom, top] x [-far, -near] to the clip cube, row-major."""
    return np.array([
        [2.0 / (right - left), 0.0, 0.0, -(right + left) / (right - left)],
        [0.0, 2.0 / (top - bottom), 0.0, -(top + bottom) / (top - bottom)],
        [0.0, 0.0, -2.0 / (far - near), -(far + near) / (far - near)],
        [0.0, 0.0, 0.0, 1.0],
    ])


def _point_triangle_distance(point: torch.Tensor, corners: torch.Tensor) -> torch.Tensor:
    """Euclidean distance from one point (3,) to each triangle (T, 3, 3); returns (T,).

    Inside the triangle's prism the distance is the plane distance; outside, the nearest
    point lies on an edge. Degenerate triangles fall through to their edges.
    """
    a, b, c = corners.unbind(dim=1)
    normal = torch.linalg.cross(b - a, c - a)
    nn = (normal * normal).sum(-1)
    plane_offset = ((point - a) * normal).sum(-1)
    projected = point - normal * (plane_offset / nn.clamp_min(1e-300))[:, None]
    inside = nn > 0
    edge_distances = []
    for start, end in ((a, b), (b, c), (c, a)):
        edge = end - start
        inside &= (torch.linalg.cross(edge, projected - start) * normal).sum(-1) >= 0
        t = (((point - start) * edge).sum(-1) / (edge * edge).sum(-1).clamp_min(1e-300)).clamp(0.0, 1.0)
        edge_distances.append((point - (start + t[:, None] * edge)).norm(dim=-1))
    plane_distance = plane_offset.abs() / nn.clamp_min(1e-300).sqrt()
    return torch.where(inside, plane_distance, torch.stack(edge_distances).amin(dim=0))


def depth_range(mesh: Mesh, camera: Camera) -> tuple[float, float] | None:
    """(near, far) clip distances that clip nothing visible, or None if all lies behind.

    far: the deepest bounding-box corner along the view axis. near: the distance to the
    closest point of the mesh, times the cosine of the frustum's corner half-angle (no
    visible point can be shallower than that). The depth buffer is fixed point, so near
    is kept as far out as this bound allows rather than set to a tiny constant.
    """
    eye = np.asarray(camera.position, dtype=np.float64)
    backward = camera_basis(camera)[2]
    lo, hi = (x.detach().cpu().numpy() for x in mesh.bounding_box())
    box_corners = np.array([[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]]
                            for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    deepest = float(((box_corners - eye) @ -backward).max())
    if not deepest > 0:
        return None
    far = deepest * 1.01

    tan_y = math.tan(math.radians(camera.fov) / 2.0)
    tan_x = tan_y * camera.width / camera.height
    cos_corner = 1.0 / math.sqrt(1.0 + tan_x * tan_x + tan_y * tan_y)
    nearest = float(_point_triangle_distance(torch.as_tensor(eye), mesh.corners.detach().cpu()).min())
    # Floor: a camera lying on a surface would otherwise get near = 0.
    near = max(0.99 * nearest * cos_corner, far * 1e-5)
    return min(near, far * 0.5), far


def render_view(mesh: Mesh, vertex_colors, camera: Camera, triangles=None, positions=None) -> np.ndarray:
    """Render the mesh with Gouraud-interpolated vertex colours from the camera.

    Depth-tested, both faces drawn, black background, box-filtered supersampling.

    Args:
        mesh: the mesh to draw.
        vertex_colors: (V, 3) linear values per vertex (torch or numpy).
        camera: position, look_at, up, vertical fov, width, height, supersample.
        triangles: (T'', 3) int64 indices into ``mesh.vertices`` to draw instead of
            ``mesh.triangles``, e.g. ``display.conforming_triangles(mesh)`` for a mesh with
            T-vertices; None draws the elements themselves.
        positions: (N, 3) the points ``triangles`` and ``vertex_colors`` refer to instead of
            ``mesh.vertices``, on the mesh's surfaces (a ``shading.Shading``'s).

    Returns:
        (height, width, 3) float32 linear values, first row at the top of the image.
    """
    width, height = int(camera.width), int(camera.height)
    ss = max(1, int(camera.supersample))
    colors = vertex_colors.detach().cpu().numpy() if isinstance(vertex_colors, torch.Tensor) else np.asarray(vertex_colors)
    colors = np.ascontiguousarray(colors, dtype=np.float32).reshape(-1, 3)
    points = mesh.vertices if positions is None else torch.as_tensor(positions)
    if len(colors) != len(points):
        raise ValueError(f"need one colour per vertex ({len(points)}), got {len(colors)}")
    if width < 1 or height < 1:
        raise HemiradInputError(f"camera width and height must be positive, got {width} x {height}.")

    ctx = GLContext.get()
    check_image_size(max(width, height) * ss, lambda limit: HemiradInputError(
        f"camera size {width} x {height} with supersample {ss} exceeds the OpenGL "
        f"framebuffer limit of {limit} pixels; lower camera.supersample or the size."))

    image = np.zeros((height, width, 3), dtype=np.float32)
    draw = mesh.triangles if triangles is None else torch.as_tensor(triangles, dtype=torch.int64).reshape(-1, 3)
    if mesh.num_elements == 0 or len(draw) == 0:
        return image
    clip = depth_range(mesh, camera)
    if clip is None:
        return image

    basis = camera_basis(camera)
    # Translate to the eye in float64 before the float32 upload: scene coordinates far from
    # the origin would otherwise lose precision in the GPU's model-view transform.
    eye = np.asarray(camera.position, dtype=np.float64)
    eye_space = ((points.detach().cpu().numpy() - eye) @ basis.T).astype(np.float32)
    indices = draw.detach().cpu().numpy().astype(np.int32)
    projection = perspective(camera.fov, width / height, *clip)

    program = _program(ctx)
    # GLSL reads matrices column-major.
    program["clip_from_eye"].write(projection.T.astype(np.float32).tobytes())

    big_w, big_h = width * ss, height * ss
    raw = _draw(ctx, program, eye_space, colors, indices, big_w, big_h)
    # glReadPixels returns the bottom row first; images are stored top row first.
    big = np.frombuffer(raw, dtype=np.float32).reshape(big_h, big_w, 4)[::-1, :, :3]
    return big.reshape(height, ss, width, ss, 3).mean(axis=(1, 3), dtype=np.float64).astype(np.float32)


def _draw(ctx, program, positions: np.ndarray, colors: np.ndarray, indices: np.ndarray, big_w: int,
          big_h: int) -> bytes:
    """Draw (V, 3) float32 eye-space ``positions`` with (V, 3) float32 ``colors`` as the (T, 3)
    int32 triangles ``indices`` into a new ``big_w`` x ``big_h`` float framebuffer; its RGBA
    float32 pixels, bottom row first. Every GL object made is released."""
    resources = []
    try:
        color_rb = ctx.renderbuffer((big_w, big_h), components=4, dtype="f4")
        resources.append(color_rb)
        depth_rb = ctx.depth_renderbuffer((big_w, big_h))
        resources.append(depth_rb)
        fbo = ctx.framebuffer(color_attachments=[color_rb], depth_attachment=depth_rb)
        resources.append(fbo)
        position_vbo = ctx.buffer(positions.tobytes())
        resources.append(position_vbo)
        color_vbo = ctx.buffer(colors.tobytes())
        resources.append(color_vbo)
        ibo = ctx.buffer(indices.tobytes())
        resources.append(ibo)
        vao = ctx.vertex_array(
            program,
            [(position_vbo, "3f", "in_position"), (color_vbo, "3f", "in_color")],
            index_buffer=ibo,
            index_element_size=4,
        )
        resources.append(vao)
        # The scope restores the previous framebuffer and enable flags on exit, so other
        # users of the shared context (the hemicube) see no change in state.
        scope = ctx.scope(fbo, enable_only=moderngl.DEPTH_TEST)
        resources.append(scope)
        with scope:
            fbo.viewport = (0, 0, big_w, big_h)
            ctx.depth_func = "<"
            fbo.clear(0.0, 0.0, 0.0, 1.0, depth=1.0)
            vao.render(moderngl.TRIANGLES)
            raw = fbo.read(components=4, dtype="f4")
    finally:
        for resource in reversed(resources):
            resource.release()
    return raw


def pixel_elements(mesh: Mesh, camera: Camera) -> torch.Tensor:
    """(H * W,) int64 the element each pixel's centre sees (-1: none), row by row from the top."""
    unshared, flat = _unshared(mesh.to("cpu")), _centres(camera)
    number = torch.arange(1, mesh.num_elements + 1, dtype=torch.float64).repeat_interleave(3)
    ids = render_view(unshared, torch.stack([number, torch.zeros_like(number), torch.zeros_like(number)], 1), flat)
    return torch.as_tensor(np.rint(ids[..., 0]).astype(np.int64)).reshape(-1) - 1


def _unshared(mesh: Mesh) -> Mesh:
    """``mesh`` with each element drawn with its own three vertices, so that a vertex value
    is the element's: its index (exact in float32 below 2^24), its corners' offsets."""
    T = mesh.num_elements
    return Mesh(mesh.corners.reshape(-1, 3), torch.arange(3 * T).reshape(T, 3), mesh.surface, mesh.material,
                mesh.surface_names, mesh.level)


def _centres(camera: Camera) -> Camera:
    """``camera`` drawing pixel centres: one surface each."""
    return dataclasses.replace(camera, supersample=1)


def pixel_points(mesh: Mesh, camera: Camera) -> tuple[torch.Tensor, torch.Tensor]:
    """The surface point each pixel's centre sees.

    Returns:
        (H * W,) the element each pixel sees (-1: none), row by row from the top
        (``pixel_elements``), and (H * W, 3) float64 the point (on the element's plane).
    """
    mesh = mesh.to("cpu")
    element = pixel_elements(mesh, camera)
    unshared, flat = _unshared(mesh), _centres(camera)
    eye = torch.tensor(camera.position, dtype=torch.float64)
    offsets = torch.as_tensor(render_view(unshared, unshared.vertices - eye, flat), dtype=torch.float64).reshape(-1, 3)
    points = eye + offsets
    seen = element >= 0
    # onto the element's plane, undoing the float32 of the render
    c0, n = mesh.corners[element[seen], 0], mesh.normals[element[seen]]
    points[seen] -= ((points[seen] - c0) * n).sum(1, keepdim=True) * n
    return element, points
