"""False-colour pictures: a value over a plane or a surface (illuminance, irradiance) or
over the camera view (luminance), with a colour bar in its unit and labelled iso-lines.

``plane_picture`` draws any field given as a grid of values over a rectangle (a calculation
grid, a surface seen straight on); ``surface_picture`` and ``luminance_picture`` feed it
what the solve gives. Drawing is matplotlib's (its Agg renderer, no display): colour bars,
iso-lines with their values on them and labelled axes are its job.

The colour map is viridis: perceptually uniform (equal steps of value look like equal steps
of colour, so the picture does not invent edges the light does not have), its lightness
rises monotonically (more light reads as brighter, in grey print too), and it stays
readable with the common colour-vision deficiencies. It holds no neutral grey, so "no
surface here" is drawn in one. The stepped maps of lighting tools carry the same
information here as the iso-lines at "nice" levels drawn over a continuous map.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch

from hemirad.core.colour import REC709_LUMINANCE, luminance
from hemirad.geometry.mesh import Mesh
from hemirad.output import display
from hemirad.output.meshview import surface_frame, surface_view

#: The colour map (see the module's docstring for why).
COLOUR_MAP = "viridis"
#: Where a picture has no value (no surface, or a surface that reflects nothing): neutral grey.
NO_DATA_GREY = (0.5, 0.5, 0.5)
#: Iso-lines: black, over a white halo so that they read on the dark and light ends alike.
LINE_COLOUR, HALO_COLOUR = "black", "white"
#: The camera view's log scale shows this many decades below its brightest pixel.
LOG_DECADES = 4.0
_DPI = 100
_MAP_INCHES = 6.4  # the map's longer side


class Figure(NamedTuple):
    """A drawn picture before rasterising: the matplotlib figure, the map's axes and its
    colour bar (so that a caller can find where a data point lands in the picture)."""
    figure: object
    axes: object
    colorbar: object


def nice_levels(lo: float, hi: float, count: int = 8) -> np.ndarray:
    """About ``count`` iso-line levels strictly between ``lo`` and ``hi``, at multiples of 1,
    2, 2.5 or 5 times a power of ten (500, 750, 1000 lx, not 487.3); empty when the range
    is empty or not finite."""
    from matplotlib.ticker import MaxNLocator

    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        return np.zeros(0)
    ticks = MaxNLocator(nbins=count, steps=[1, 2, 2.5, 5, 10]).tick_values(lo, hi)
    return np.asarray([t for t in ticks if lo < t < hi], dtype=np.float64)


def _value_format(value: float) -> str:
    return f"{value:.4g}"


def plane_figure(values, extent, unit: str, title: str, levels=None, xlabel: str = "x", ylabel: str = "y",
                 log: bool = False, axes: bool = True) -> Figure:
    """A false-colour map of ``values`` over a rectangle, with a colour bar and iso-lines.

    Args:
        values: (ny, nx) float, NaN where there is no value. Value [j, i] is that of the
            cell centred at x = x0 + (i + 0.5) (x1 - x0) / nx, y = y0 + (j + 0.5) (y1 - y0) / ny:
            a grid of points at the centres of equal cells, row 0 along y0.
        extent: (x0, x1, y0, y1), the rectangle the grid covers; x0 > x1 (or y0 > y1) runs
            that axis the other way (a floor seen from above, z growing downwards).
        unit: the colour bar's label, e.g. ``"lx"`` or ``"W/m^2"``.
        title: above the map.
        levels: iso-line values; None: ``nice_levels`` of the values' range; ``()``: none.
        xlabel, ylabel: the axes' names.
        log: a logarithmic colour scale over ``LOG_DECADES`` below the largest value (values
            below it take the lowest colour); for luminances, which span decades.
        axes: draw ticks and axis names (False for a camera view, whose axes are pixels).

    Returns:
        The ``Figure``; ``render`` turns it into pixels.
    """
    from matplotlib import colormaps, patheffects
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import LogNorm, Normalize
    from matplotlib.figure import Figure as MplFigure

    data = np.asarray(values, dtype=np.float64)
    if data.ndim != 2 or data.shape[0] < 1 or data.shape[1] < 1:
        raise ValueError(f"expected an (ny, nx) grid of values, got shape {data.shape}")
    x0, x1, y0, y1 = (float(v) for v in extent)
    if not all(math.isfinite(v) for v in (x0, x1, y0, y1)) or x0 == x1 or y0 == y1:
        raise ValueError(f"expected a finite rectangle (x0, x1, y0, y1) of non-zero size, got {extent}")
    data = np.where(np.isfinite(data), data, np.nan)
    finite = data[np.isfinite(data)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)

    if log and hi > 0:
        lo = max(lo, hi * 10.0 ** -LOG_DECADES)
        shown = np.where(np.isnan(data), np.nan, np.maximum(data, lo))  # below the scale: its lowest colour
        norm = LogNorm(vmin=lo, vmax=hi if hi > lo else lo * 10.0)
    else:
        shown = data
        norm = Normalize(vmin=lo, vmax=hi if hi > lo else lo + max(abs(lo), 1.0))
    if levels is None:
        levels = nice_levels(lo, hi) if not log else np.zeros(0)
    levels = np.unique(np.asarray([v for v in np.asarray(levels, dtype=np.float64).reshape(-1) if math.isfinite(v)]))

    # Size: the map's longer side _MAP_INCHES, its aspect the rectangle's (within 1:4),
    # plus room for the colour bar, the title and the axes' labels.
    aspect = abs(x1 - x0) / abs(y1 - y0)
    aspect = min(max(aspect, 0.25), 4.0)
    map_w, map_h = (_MAP_INCHES, _MAP_INCHES / aspect) if aspect >= 1 else (_MAP_INCHES * aspect, _MAP_INCHES)
    fig = MplFigure(figsize=(map_w + 1.9, map_h + 1.1), dpi=_DPI, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    cmap = colormaps[COLOUR_MAP].with_extremes(bad=NO_DATA_GREY)
    image = ax.imshow(np.ma.masked_invalid(shown), cmap=cmap, norm=norm, origin="lower",
                      extent=(x0, x1, y0, y1), interpolation="nearest", aspect="equal")
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_title(title)
    if axes:
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
    else:
        ax.set_axis_off()
    colorbar = fig.colorbar(image, ax=ax, label=unit, shrink=0.9)

    inside = levels[(levels > lo) & (levels < hi)] if len(levels) else levels
    if len(inside) and finite.size:
        ny, nx = data.shape
        xs = x0 + (np.arange(nx) + 0.5) * (x1 - x0) / nx
        ys = y0 + (np.arange(ny) + 0.5) * (y1 - y0) / ny
        halo = [patheffects.withStroke(linewidth=2.6, foreground=HALO_COLOUR)]
        lines = ax.contour(xs, ys, np.ma.masked_invalid(data), levels=inside, colors=LINE_COLOUR,
                           linewidths=0.9)
        lines.set(path_effects=halo)
        labels = ax.clabel(lines, inline=True, fontsize=8, fmt=_value_format)
        for label in labels:
            label.set_path_effects(halo)
        colorbar.set_ticks(inside)
        colorbar.ax.set_yticklabels([_value_format(v) for v in inside])
        colorbar.add_lines(lines)
    return Figure(fig, ax, colorbar)


def render(figure: Figure) -> np.ndarray:
    """(h, w, 3) uint8 sRGB pixels of a drawn ``Figure``, first row at the top."""
    canvas = figure.figure.canvas
    canvas.draw()
    return np.ascontiguousarray(np.asarray(canvas.buffer_rgba())[:, :, :3])


def plane_picture(values, extent, unit: str, title: str, levels=None, xlabel: str = "x",
                  ylabel: str = "y") -> np.ndarray:
    """(h, w, 3) uint8: a false-colour map of a grid of values over a rectangle, with a
    colour bar labelled ``unit`` and iso-lines with their values written on them; NaN
    cells (no surface) neutral grey. See ``plane_figure`` for the arguments."""
    return render(plane_figure(values, extent, unit, title, levels, xlabel, ylabel))


# ----------------------------------------------------------------------------------------
# surfaces


def element_irradiance(display_radiosity: torch.Tensor, emission: torch.Tensor,
                       reflectance: torch.Tensor) -> torch.Tensor:
    """The irradiance falling on each element: H = (B - E) / rho per channel.

    What an element reflects is rho H, so its radiosity B = E + rho H (B the display
    radiosity, with the ambient term, which is then part of H). Where rho is 0 in a channel
    the element shows nothing of the light it receives there: that channel is NaN.

    Args:
        display_radiosity, emission, reflectance: (T, 3) per element.

    Returns:
        (T, 3) float64, NaN where the reflectance is 0.
    """
    b, e, rho = (torch.as_tensor(x, dtype=torch.float64) for x in (display_radiosity, emission, reflectance))
    return torch.where(rho > 0, (b - e) / torch.where(rho > 0, rho, 1.0), torch.nan)


def vertex_values_with_gaps(mesh: Mesh, element_values: torch.Tensor) -> torch.Tensor:
    """``display.vertex_values`` of (T,) element values some of which are NaN (no data):
    each vertex the area-weighted mean of the elements around it that have a value, NaN
    where none has; T-vertices on their edges (``conforming_vertex_values``). Returns (V,)."""
    values = torch.as_tensor(element_values, dtype=torch.float64).reshape(-1)
    known = torch.isfinite(values)
    sums = display.vertex_values(mesh, torch.stack([torch.where(known, values, 0.0), known.to(values.dtype)], 1))
    # Both columns are means over the same weights, so their ratio is the mean over the known ones.
    per_vertex = torch.where(sums[:, 1] > 0, sums[:, 0] / torch.where(sums[:, 1] > 0, sums[:, 1], 1.0), torch.nan)
    return display.conforming_vertex_values(mesh, per_vertex)


class SurfaceValues(NamedTuple):
    """A surface's values seen straight on, ready for ``plane_figure``: ``values`` (h, w),
    row 0 at the bottom, NaN off the surface or where it has no value; ``extent`` (x0, x1,
    y0, y1); the axes' names."""
    values: np.ndarray
    extent: tuple[float, float, float, float]
    xlabel: str
    ylabel: str


def surface_values(mesh: Mesh, vertex_values: torch.Tensor, surface: int, size: int = 512) -> SurfaceValues:
    """Per-vertex values over one surface seen straight on (``surface_view``'s picture),
    interpolated linearly across each triangle.

    The axes are the scene's own where the surface lies along two of them (the faces of
    rooms and boxes, axis-aligned quads): a floor seen from above spans its x range left to
    right and its z range top to bottom. Otherwise they are distances along the surface
    from its lower left corner.

    Args:
        mesh: the mesh.
        vertex_values: (V,) float, NaN at vertices without a value.
        surface: a surface index (``meshview.pick_surface``).
        size: pixels along the longer side.
    """
    vertex = torch.as_tensor(vertex_values, dtype=torch.float64).reshape(-1)
    known = torch.isfinite(vertex)
    # Channels: the value, 1 where the vertex has one, 1 everywhere on the surface. A pixel
    # whose triangle has a vertex without value has its second channel below 1.
    channels = torch.stack([torch.where(known, vertex, 0.0), known.to(torch.float64), torch.ones_like(vertex)], 1)
    view = surface_view(mesh, channels, surface, size=size, edges=False, background=(0.0, 0.0, 0.0))
    valid = (view[:, :, 2] > 0.5) & (view[:, :, 1] > 1.0 - 1e-4)
    values = np.where(valid, view[:, :, 0].astype(np.float64), np.nan)[::-1]  # row 0 at the bottom

    frame = surface_frame(mesh, surface)
    axes = []
    for row in range(2):  # image right, then image up
        direction = frame.basis[row]
        along = int(np.argmax(np.abs(direction)))
        lo, hi = float(frame.lo[row]), float(frame.hi[row])
        if abs(direction[along]) > 1.0 - 1e-9:  # a scene axis, either way round
            sign = 1.0 if direction[along] > 0 else -1.0
            c = float(frame.center[along])
            axes.append((c + sign * lo, c + sign * hi, "xyz"[along]))
        else:
            axes.append((0.0, hi - lo, "along the surface" if row == 0 else "across the surface"))
    (x0, x1, xlabel), (y0, y1, ylabel) = axes
    return SurfaceValues(np.ascontiguousarray(values), (x0, x1, y0, y1), xlabel, ylabel)


def surface_picture(mesh: Mesh, irradiance: torch.Tensor, surface: int, unit: str, title: str,
                    factor: float = 1.0, size: int = 512, levels=None) -> np.ndarray:
    """(h, w, 3) uint8: the light falling on one surface as a false-colour map.

    Args:
        mesh: the mesh.
        irradiance: (T, 3) per element (``element_irradiance``), NaN where unknown; the
            map shows ``factor`` times its luminance (Rec. 709), elements with a NaN channel
            as no data, interpolated to the vertices as the other views are.
        surface: a surface index (``meshview.pick_surface``).
        unit, title: the colour bar's label and the title.
        factor: e.g. ``LUMENS_PER_WATT`` for lux from W/m^2; 1 for a scene already in lm/m^2.
        size: pixels of the surface's longer side (the map's resolution, not the picture's).
        levels: iso-line values (None: nice numbers over the range).
    """
    h = torch.as_tensor(irradiance, dtype=torch.float64)
    element = torch.where(torch.isfinite(h).all(dim=1), factor * luminance(torch.nan_to_num(h)), torch.nan)
    seen = surface_values(mesh, vertex_values_with_gaps(mesh, element), surface, size)
    return plane_picture(seen.values, seen.extent, unit, title, levels, seen.xlabel, seen.ylabel)


# ----------------------------------------------------------------------------------------
# the camera view


def luminance_values(linear: np.ndarray, coverage: np.ndarray | None = None, factor: float = 1.0) -> np.ndarray:
    """(H, W) float64: ``factor`` times the luminance of Lambertian surfaces of radiosity
    ``linear`` (B / pi, Rec. 709 weights of the colour).

    Args:
        linear: (H, W, 3) the camera view's linear radiosity (``render.render_view``).
        coverage: (H, W) the share of each pixel that surfaces cover (the same view of
            ones); a pixel's value is that of its covered part, NaN where less than half is
            covered. None: every pixel covered.
        factor: e.g. ``LUMENS_PER_WATT`` for cd/m^2 from a scene in W/m^2.
    """
    lum = np.asarray(linear, dtype=np.float64) @ np.asarray(REC709_LUMINANCE) * (factor / math.pi)
    if coverage is None:
        return lum
    cover = np.asarray(coverage, dtype=np.float64)
    return np.where(cover >= 0.5, lum / np.maximum(cover, 0.5), np.nan)


def luminance_picture(linear: np.ndarray, coverage: np.ndarray | None, unit: str, title: str = "Luminance",
                      factor: float = 1.0) -> np.ndarray:
    """(h, w, 3) uint8: the camera view's luminance (``luminance_values``) in false colour
    on a logarithmic scale (a view holds its lamps and its shadows, decades apart), with a
    colour bar labelled ``unit``; pixels that see no surface grey."""
    values = luminance_values(linear, coverage, factor)[::-1]  # row 0 at the bottom
    height, width = values.shape
    return render(plane_figure(values, (0.0, float(width), 0.0, float(height)), unit, title, log=True, axes=False))


# ----------------------------------------------------------------------------------------
# calculation grids


def grid_extent(origin, u, v) -> tuple[tuple[float, float, float, float], str, str]:
    """The rectangle ``origin`` + [0,1] ``u`` + [0,1] ``v`` (3-vectors) as a picture's extent
    and axis labels: in scene coordinates where u and v run along axes (a work plane: x and
    z), else distances along u and v from the origin."""
    origin, u, v = (np.asarray(x, dtype=np.float64) for x in (origin, u, v))
    names = "xyz"
    extent, labels = [], []
    for edge, fallback in ((u, "along u"), (v, "along v")):
        axis = int(np.argmax(np.abs(edge)))
        if np.count_nonzero(edge) == 1:
            extent += [origin[axis], origin[axis] + edge[axis]]
            labels.append(names[axis])
        else:
            extent += [0.0, float(np.linalg.norm(edge))]
            labels.append(fallback)
    return tuple(extent), labels[0], labels[1]


def grid_picture(values, origin, u, v, unit: str, title: str, levels=None) -> np.ndarray:
    """(h, w, 3) uint8: a calculation grid's values (rows along v, columns along u) over its
    rectangle, with a colour bar in ``unit`` and iso-lines (``plane_picture``)."""
    extent, xlabel, ylabel = grid_extent(origin, u, v)
    return plane_picture(np.asarray(values, dtype=np.float64), extent, unit, title, levels, xlabel, ylabel)
