"""Mesh views: one surface seen straight on, shaded, with its element edges drawn over it.

These are the paper's (a)' (b)' (c)' pictures (the floor's mesh after each refinement
pattern). The view is a parallel projection along the surface's mean normal, framed on the
surface's bounding rectangle, so elements keep their true shapes and relative sizes.
"""
from __future__ import annotations

from typing import NamedTuple

import moderngl
import numpy as np
import torch

from hemirad.core.errors import HemiradInputError
from hemirad.geometry.edges import unique_edges
from hemirad.geometry.mesh import Mesh
from hemirad.output.display import conforming_triangles
from hemirad.output.render import _program, orthographic
from hemirad.transport.gl import GLContext, check_image_size

# Below this length of world +y projected onto the surface, the surface faces up or down
# and +y no longer gives a stable image "up"; -z is used instead.
_UP_FALLBACK = 0.1


def _surface_areas(mesh: Mesh) -> torch.Tensor:
    count = int(mesh.surface.max()) + 1 if mesh.num_elements else 0
    count = max(count, len(mesh.surface_names))
    return torch.zeros(count, dtype=torch.float64).index_add_(0, mesh.surface, mesh.areas)


def pick_surface(mesh: Mesh, name: str | None = None) -> int:
    """The index of a surface, chosen by name.

    Args:
        mesh: the mesh with its ``surface_names``.
        name: an exact surface name (``"room.floor"``); else the unique surface whose name
            ends with ``"." + name`` (``"floor"`` finds ``"room.floor"``); None picks the
            largest surface named ``*.floor``, and the largest surface of all if none is.

    Raises:
        HemiradInputError: no surface matches, or a suffix matches several; the message
            lists the names there are.
    """
    names = list(mesh.surface_names)
    areas = _surface_areas(mesh)
    if len(areas) == 0:
        raise HemiradInputError("the mesh has no surfaces to show.")

    def largest(candidates: list[int]) -> int:
        return max(candidates, key=lambda i: (float(areas[i]), -i))

    if name is None:
        floors = [i for i, n in enumerate(names) if n.endswith(".floor") or n == "floor"]
        return largest(floors) if floors else largest(list(range(len(areas))))
    if name in names:
        return names.index(name)
    matches = [i for i, n in enumerate(names) if n.endswith("." + name)]
    if len(matches) == 1:
        return matches[0]
    available = ", ".join(names) if names else "(none)"
    if matches:
        raise HemiradInputError(
            f"surface name {name!r} is ambiguous: it matches {', '.join(names[i] for i in matches)}. "
            f"Give the full name; the surfaces are: {available}.")
    raise HemiradInputError(f"no surface named {name!r}; the surfaces are: {available}.")


def view_basis(normal: np.ndarray) -> np.ndarray:
    """(3, 3) rows right, up, normal for looking at a surface's front along -normal.

    Image up is world +y projected onto the surface (walls appear upright). A surface
    facing up or down (floor, ceiling) has no such direction; it uses -z instead, so a
    floor seen from above has +x to the right and -z at the top, as the floor appears
    to a camera looking towards -z.
    """
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    up = np.array([0.0, 1.0, 0.0]) - n[1] * n
    if np.linalg.norm(up) < _UP_FALLBACK:
        up = np.array([0.0, 0.0, -1.0]) - (-n[2]) * n
    up /= np.linalg.norm(up)
    right = np.cross(up, n)  # right x up = normal: a right-handed eye frame facing -normal
    return np.stack([right, up, n])


def surface_view(mesh: Mesh, vertex_colors, surface: int | list[int], size: int = 512,
                 edges: bool = True, edge_color=(0.0, 0.0, 0.0),
                 background=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Draw one surface (or several) straight on, Gouraud-shaded, with its element edges.

    The projection is parallel, along the area-weighted mean normal of the chosen
    triangles, looking at their front; the image is framed on their bounding rectangle in
    that view, keeping the aspect ratio, with the longer side ``size`` pixels. Orientation
    is ``view_basis``'s: image up is world +y on walls and -z on floors and ceilings
    (seen from above, a floor has +x right and -z up). Only the chosen surfaces are drawn;
    T-vertices are closed with ``conforming_triangles``. Edges are the elements' own
    (from ``mesh.triangles``), one pixel wide, drawn over the fill slightly towards the
    viewer. The line pass is framed half a pixel inside the fill's frame so that the
    outline falls on the outermost pixel rows and columns instead of off the image.

    Args:
        mesh: the mesh.
        vertex_colors: (V, 3) linear colour per vertex (torch or numpy), e.g.
            ``conforming_vertex_values(mesh, vertex_values(mesh, radiosity))``.
        surface: a surface index or a list of them (see ``pick_surface``).
        size: pixels along the longer side of the image.
        edges: draw element edges.
        edge_color: linear RGB of the edges.
        background: linear RGB where no chosen surface covers a pixel.

    Returns:
        (H, W, 3) float32 linear values, first row at the top of the image.
    """
    colors = vertex_colors.detach().cpu().numpy() if isinstance(vertex_colors, torch.Tensor) else np.asarray(vertex_colors)
    colors = np.ascontiguousarray(colors, dtype=np.float32).reshape(-1, 3)
    if len(colors) != len(mesh.vertices):
        raise ValueError(f"need one colour per vertex ({len(mesh.vertices)}), got {len(colors)}")
    size = int(size)
    if size < 1:
        raise HemiradInputError(f"the view size must be a positive number of pixels, got {size}.")
    surfaces = [int(surface)] if isinstance(surface, (int, np.integer)) else [int(s) for s in surface]
    part = _chosen_part(mesh, surfaces)
    eye_space, lo, hi, width, height = _eye_frame(mesh, part, surfaces, size)
    ctx = GLContext.get()
    check_image_size(max(width, height), lambda limit: HemiradInputError(
        f"view size {size} exceeds the OpenGL framebuffer limit of {limit} pixels."))

    # Depth: the surface's own relief plus a margin; edges move half the margin towards the
    # viewer so they win the depth test on their own surface but stay hidden behind
    # nearer parts of a curved one.
    margin = (hi[2] - lo[2]) + 1e-3 * max(hi[0] - lo[0], hi[1] - lo[1])
    projection = orthographic(lo[0], hi[0], lo[1], hi[1], -(hi[2] + 2 * margin), -(lo[2] - 2 * margin))
    shrink = np.diag([1.0 - 1.0 / width, 1.0 - 1.0 / height, 1.0, 1.0])
    fill = _Pass(eye_space.astype(np.float32), colors, conforming_triangles(part).numpy().astype(np.int32),
                 projection)
    line_indices = unique_edges(part.triangles).numpy().astype(np.int32)  # (E, 2)
    lines = _Pass((eye_space + np.array([0.0, 0.0, 0.5 * margin])).astype(np.float32),
                  np.broadcast_to(np.asarray(edge_color, dtype=np.float32), colors.shape).copy(),
                  line_indices, shrink @ projection) if edges and len(line_indices) else None
    raw = _draw(ctx, width, height, background, fill, lines)
    # glReadPixels returns the bottom row first.
    image = np.frombuffer(raw, dtype=np.float32).reshape(height, width, 4)[::-1, :, :3]
    return np.ascontiguousarray(image)


def _chosen_part(mesh: Mesh, surfaces: list[int]) -> Mesh:
    """The triangles of the ``surfaces`` as a mesh of their own over all of ``mesh``'s
    vertices, so display triangles index the same vertex array and colours."""
    chosen = torch.isin(mesh.surface, torch.tensor(surfaces, dtype=torch.int64))
    if not bool(chosen.any()):
        raise HemiradInputError(f"surface {surfaces} has no elements to show.")
    return Mesh(mesh.vertices, mesh.triangles[chosen], mesh.surface[chosen], mesh.material[chosen],
                list(mesh.surface_names), mesh.level[chosen], mesh.edge_parents)


class SurfaceFrame(NamedTuple):
    """Where surfaces are seen straight on (``surface_view``'s frame).

    Attributes:
        basis: (3, 3) float64 rows right, up, normal (``view_basis`` of the area-weighted
            mean normal).
        center: (3,) float64 the world point at the frame's origin (the mean of the
            surfaces' vertices).
        lo, hi: (3,) float64 the corners of the surfaces' bounding box in the frame; the
            image spans [lo[0], hi[0]] left to right and [lo[1], hi[1]] bottom to top.
    """
    basis: np.ndarray
    center: np.ndarray
    lo: np.ndarray
    hi: np.ndarray


def surface_frame(mesh: Mesh, surface: int | list[int]) -> SurfaceFrame:
    """The frame ``surface_view`` draws ``surface`` (an index or a list of them) in: a
    pixel's centre at column i, row r of a W x H view lies at
    ``center + basis.T @ (lo[0] + (i + 0.5) (hi[0] - lo[0]) / W, hi[1] - (r + 0.5) (hi[1] - lo[1]) / H, *)``."""
    surfaces = [int(surface)] if isinstance(surface, (int, np.integer)) else [int(s) for s in surface]
    return _frame(mesh, _chosen_part(mesh, surfaces), surfaces)[0]


def _frame(mesh: Mesh, part: Mesh, surfaces: list[int]) -> tuple[SurfaceFrame, np.ndarray]:
    """``part``'s ``SurfaceFrame``, and (V, 3) float64 every vertex of ``mesh`` in it."""
    normal_sum = torch.linalg.cross(part.corners[:, 1] - part.corners[:, 0],
                                    part.corners[:, 2] - part.corners[:, 0]).sum(dim=0).numpy()
    if not np.linalg.norm(normal_sum) > 0:
        raise HemiradInputError(f"surface {surfaces} has no area facing any direction; it cannot be shown straight on.")
    basis = view_basis(normal_sum)
    used = torch.unique(part.triangles).numpy()
    world = mesh.vertices.numpy()
    center = world[used].mean(axis=0)
    # float64 until the upload, relative to the surface's centre (precision far from the origin).
    eye_space = (world - center) @ basis.T
    lo, hi = eye_space[used].min(axis=0), eye_space[used].max(axis=0)
    return SurfaceFrame(basis, center, lo, hi), eye_space


def _eye_frame(mesh: Mesh, part: Mesh, surfaces: list[int], size: int):
    """Where ``part`` is seen straight on along its area-weighted mean normal.

    Returns:
        eye_space: (V, 3) float64 every vertex of ``mesh`` in the view's frame (right, up,
            towards the viewer), relative to the part's centre.
        lo, hi: (3,) float64 the corners of the part's bounding box in that frame.
        width, height: the image size in pixels, the longer side ``size``.
    """
    frame, eye_space = _frame(mesh, part, surfaces)
    lo, hi = frame.lo, frame.hi
    extent_u, extent_v = hi[0] - lo[0], hi[1] - lo[1]
    if not (extent_u > 0 and extent_v > 0):
        raise HemiradInputError(f"surface {surfaces} is seen edge-on along its mean normal; it cannot be shown straight on.")
    if extent_u >= extent_v:
        width, height = size, max(1, int(round(size * extent_v / extent_u)))
    else:
        width, height = max(1, int(round(size * extent_u / extent_v))), size
    return eye_space, lo, hi, width, height


class _Pass(NamedTuple):
    """One draw of ``_draw``: (V, 3) float32 eye-space positions and linear colours, int32
    indices ((F, 3) triangles or (E, 2) lines) and the (4, 4) clip-from-eye matrix."""
    positions: np.ndarray
    colors: np.ndarray
    indices: np.ndarray
    clip_from_eye: np.ndarray


def _draw(ctx: moderngl.Context, width: int, height: int, background, fill: _Pass, lines: _Pass | None) -> bytes:
    """The fill triangles, then (unless None) the lines over them, into a fresh
    ``width`` x ``height`` float RGBA framebuffer; its pixels, bottom row first."""
    program = _program(ctx)
    resources = []

    def keep(resource):
        resources.append(resource)
        return resource

    def vertex_array(draw: _Pass):
        return keep(ctx.vertex_array(
            program,
            [(keep(ctx.buffer(draw.positions.tobytes())), "3f", "in_position"),
             (keep(ctx.buffer(draw.colors.tobytes())), "3f", "in_color")],
            index_buffer=keep(ctx.buffer(draw.indices.tobytes())), index_element_size=4))

    try:
        color_rb = keep(ctx.renderbuffer((width, height), components=4, dtype="f4"))
        depth_rb = keep(ctx.depth_renderbuffer((width, height)))
        fbo = keep(ctx.framebuffer(color_attachments=[color_rb], depth_attachment=depth_rb))
        # The scope restores framebuffer and enable flags for the context's other users.
        with keep(ctx.scope(fbo, enable_only=moderngl.DEPTH_TEST)):
            fbo.viewport = (0, 0, width, height)
            fbo.clear(*(float(c) for c in background), 1.0, depth=1.0)
            ctx.depth_func = "<"
            program["clip_from_eye"].write(fill.clip_from_eye.T.astype(np.float32).tobytes())
            vertex_array(fill).render(moderngl.TRIANGLES)
            if lines is not None:
                ctx.depth_func = "<="
                ctx.line_width = 1.0
                program["clip_from_eye"].write(lines.clip_from_eye.T.astype(np.float32).tobytes())
                line_vao = vertex_array(lines)
                line_vao.render(moderngl.LINES)
                # GL lines are half-open (the last pixel is left for the next segment), which
                # leaves gaps at the outline's corners; the end points as 1-pixel points close them.
                ctx.point_size = 1.0
                line_vao.render(moderngl.POINTS)
            return fbo.read(components=4, dtype="f4")
    finally:
        ctx.depth_func = "<"  # the GL default, which the other passes rely on
        for resource in reversed(resources):
            resource.release()
