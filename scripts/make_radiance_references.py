"""Compute RADIANCE's irradiance at sensor points of the bundled scenes (needs pyradiance).

    python scripts/make_radiance_references.py [--scenes cornell_box office] [--repeats 32]
                                               [--out tests/references] [--gather]

For ``cornell_box`` and ``office`` it writes ``radiance_<scene>.json`` beside the path-traced
images: the points (on the floor, walls, the ceiling, a block or desk top, and in mid-air
with tilted normals), RGB irradiance by ``rtrace -I`` (``hemirad.evaluation.irradiance_reference``:
the scene's own initial triangles, Lambertian ``plastic``, emitters as ``light`` of radiance
E / pi), the direct light alone (``-ab 0``), and the reference's own noise.

Noise: ``rtrace -u+`` draws independent samples, so the ``--repeats`` evaluations of a point
are independent estimates; the reference is their mean and its standard error is their
standard deviation over sqrt(repeats), stored per point and channel. RADIANCE seeds its
generator the same way every run: the same inputs give the same numbers.

Where the points are. A surface point is the closest point of the named surface to the
position given, lifted off it by 1e-4 of the scene's diagonal (so that no ray of either
program starts inside the surface); its normal is the surface's. Every point lies farther
from every other surface, and from its own surface's outline, than that surface's element
size (checked here; surfaces wholly behind a point's plane, which it cannot see, aside): the references test a sensor, not how a constant-per-element mesh
resolves the light next to a corner or an edge, which is a separate, known error.

``--gather`` also solves each scene with hemirad (converged to 1e-4 unshot, the scene's own
mesh and hemicube) and gathers its display radiosity at every point with a 256 hemicube
(``HemicubeRenderer.render_at``: sum of B_j times the delta form factors), and again with
the emitters' reflectance set to 0 (what RADIANCE's ``light`` does), and prints per point
RADIANCE's value, hemirad's, and their differences. It prints; it writes nothing.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

import hemirad
from hemirad.evaluation import irradiance_reference as ir
from hemirad.evaluation.metrics import luminance
from hemirad.evaluation.reference import geometry_summary
from hemirad.scene.meshing import build_mesh

ROOT = Path(__file__).resolve().parent.parent

#: Per scene: (name, surface or None, position, normal for a mid-air point). Positions on a
#: surface are snapped to it; see the module docstring for the rules they follow.
POINTS = {
    "cornell_box": [  # millimetres; elements 40 (the light 30)
        ("floor_open", "floor", (400, 0, 150), None),  # sees the whole light: the closed-form check
        ("floor_back_green", "floor", (130, 0, 430), None),
        ("floor_back_red", "floor", (490, 0, 490), None),
        ("back_wall", "back_wall", (150, 300, 559.2), None),
        ("green_wall", "green_wall", (0, 250, 200), None),
        ("red_wall", "red_wall", (553, 300, 150), None),
        ("ceiling", "ceiling", (150, 548.8, 130), None),
        ("short_block_top", "short_block.top", (186, 165, 168), None),
        ("tall_block_top", "tall_block.top", (368, 330, 351), None),
        ("tall_block_side", "tall_block.side0", (344, 165, 271.5), None),
        ("midair_above_tall_block", None, (278, 420, 300), (1, 1, -1)),
        ("midair_facing_green", None, (120, 300, 150), (-1, 0.3, 0.2)),
        ("midair_facing_down", None, (450, 250, 120), (0.4, -1, 0.6)),
    ],
    "office": [  # metres; floor elements 0.15, walls and ceiling 0.5, furniture 0.2
        ("floor_open", "room.floor", (1.0, 0, 1.0), None),
        ("floor_under_desk", "room.floor", (2.4, 0, 2.55), None),
        ("floor_by_chair", "room.floor", (2.5, 0, 1.3), None),
        ("floor_far_corner", "room.floor", (4.2, 0, 3.2), None),
        ("wall_x_min", "room.x_min", (0, 1.2, 2.0), None),
        ("wall_z_max", "room.z_max", (2.5, 1.5, 4.0), None),
        ("wall_x_max", "room.x_max", (5.0, 1.5, 1.2), None),
        ("ceiling", "room.ceiling", (1.0, 2.7, 3.0), None),
        ("desk_top", "desk.top.top", (2.55, 0.75, 2.42), None),
        ("chair_seat", "chair.seat.top", (2.525, 0.47, 1.825), None),
        ("midair_tilted", None, (1.5, 1.5, 1.0), (0.5, 1, 0.3)),
        ("midair_facing_desk", None, (3.8, 1.0, 3.0), (-0.6, 0.3, -0.7)),
        ("midair_work_plane", None, (4.0, 0.85, 1.0), (0, 1, 0)),
        ("midair_facing_down", None, (2.5, 1.6, 2.0), (0, -1, 0.2)),
    ],
}

#: How far a surface point is lifted off its surface, as a fraction of the scene's diagonal.
LIFT = 1e-4


def closest_on_triangles(point: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """(T, 3) the closest point of each triangle (T, 3, 3) to ``point`` (3,) (Ericson,
    Real-Time Collision Detection 5.1.5, vectorised)."""
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    ab, ac, ap = b - a, c - a, point - a
    d1, d2 = (ab * ap).sum(1), (ac * ap).sum(1)
    bp, cp = point - b, point - c
    d3, d4 = (ab * bp).sum(1), (ac * bp).sum(1)
    d5, d6 = (ab * cp).sum(1), (ac * cp).sum(1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v, w = vb / denom, vc / denom
        out = a + ab * v[:, None] + ac * w[:, None]  # inside the face
        # edges (checked before vertices, which override them)
        t_ab = d1 / (d1 - d3)
        on_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        out = np.where(on_ab[:, None], a + ab * t_ab[:, None], out)
        t_ac = d2 / (d2 - d6)
        on_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        out = np.where(on_ac[:, None], a + ac * t_ac[:, None], out)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        on_bc = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
        out = np.where(on_bc[:, None], b + (c - b) * t_bc[:, None], out)
    out = np.where(((d1 <= 0) & (d2 <= 0))[:, None], a, out)
    out = np.where(((d3 >= 0) & (d4 <= d3))[:, None], b, out)
    out = np.where(((d6 >= 0) & (d5 <= d6))[:, None], c, out)
    return out


def distance_to_segments(point: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """(E,) the distance from ``point`` (3,) to each segment (E, 3) -> (E, 3)."""
    d = ends - starts
    t = np.clip(((point - starts) * d).sum(1) / np.maximum((d * d).sum(1), 1e-300), 0.0, 1.0)
    return np.linalg.norm(starts + d * t[:, None] - point, axis=1)


def outline(triangles: np.ndarray) -> np.ndarray:
    """(B, 2) the edges used by one triangle only: a surface's outline."""
    edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    return unique[counts == 1]


def place_points(mesh, specs) -> tuple[list, np.ndarray, np.ndarray, list]:
    """The points of ``specs`` in ``mesh``: names, (N, 3) points, (N, 3) unit normals, and
    per point the clearance (distance over element size) to its nearest surface in front of it
    or its own surface's outline."""
    corners = mesh.corners.numpy()
    normals_t = mesh.normals.numpy()
    surface = mesh.surface.numpy()
    areas = mesh.areas.numpy()
    lo, hi = (x.numpy() for x in mesh.bounding_box())
    lift = LIFT * float(np.linalg.norm(hi - lo))
    # Initial elements are halves of squares: the square's side is the element size.
    element_size = np.array([math.sqrt(2 * float(np.median(areas[surface == s])))
                             for s in range(len(mesh.surface_names))])
    names, points, normals, clearances = [], [], [], []
    for name, surface_name, position, normal in specs:
        position = np.array(position, dtype=np.float64)
        own = None
        if surface_name is not None:
            own = mesh.surface_names.index(surface_name)
            mine = np.flatnonzero(surface == own)
            closest = closest_on_triangles(position, corners[mine])
            nearest = int(np.argmin(np.linalg.norm(closest - position, axis=1)))
            normal = normals_t[mine[nearest]]
            position = closest[nearest] + lift * normal
        normal = np.array(normal, dtype=np.float64)
        normal /= np.linalg.norm(normal)
        clearance = math.inf
        for s in range(len(mesh.surface_names)):
            mine = np.flatnonzero(surface == s)
            if s == own:
                edges = outline(mesh.triangles.numpy()[mine])
                vertices = mesh.vertices.numpy()
                distance = distance_to_segments(position, vertices[edges[:, 0]], vertices[edges[:, 1]]).min()
            else:
                # Only what lies in front of the sensor's plane can be seen (a desk top's
                # bottom face, 5 cm under a point on its top, cannot).
                mine = mine[((corners[mine] - position) @ normal > lift).any(axis=1)]
                if not len(mine):
                    continue
                distance = np.linalg.norm(closest_on_triangles(position, corners[mine]) - position, axis=1).min()
            clearance = min(clearance, distance / element_size[s])
        if clearance <= 1.0:
            raise SystemExit(f"{name}: only {clearance:.2f} element sizes from a surface or an outline; move it")
        names.append(name)
        points.append(position)
        normals.append(normal)
        clearances.append(clearance)
    return names, np.array(points), np.array(normals), clearances


def make(name: str, repeats: int, out: Path) -> ir.IrradianceReference:
    scene = hemirad.load_scene(name)
    mesh = build_mesh(scene)
    names, points, normals, clearances = place_points(mesh, POINTS[name])
    start = time.perf_counter()
    direct = ir.rtrace_irradiance(scene, mesh, points, normals, ir.RTRACE_DIRECT_OPTIONS, repeats)
    samples = ir.rtrace_irradiance(scene, mesh, points, normals, ir.RTRACE_OPTIONS, repeats)
    seconds = time.perf_counter() - start
    mean = samples.mean(axis=0)
    standard_error = samples.std(axis=0, ddof=1) / math.sqrt(repeats)
    relative = standard_error / mean
    info = {
        "scene": name,
        "units": "RGB irradiance (power per area, the scene's units), as rtrace -I gives it and as "
                 "hemirad's sensors sum radiosity B_j times form factors",
        "renderer": {"radiance": ir.radiance_version(), "program": "rtrace -I -h -ov",
                     "options": " ".join(ir.RTRACE_OPTIONS), "direct_options": " ".join(ir.RTRACE_DIRECT_OPTIONS),
                     "materials": "plastic (reflectance, specularity 0, roughness 0); emitters light "
                                  "(radiance = emission / pi), which does not reflect",
                     "geometry": "the scene's initial triangles (build_mesh), one polygon each; each emitting "
                                 f"triangle split into 4^{ir.EMITTER_SPLITS} polygons",
                     "emitter_splits": ir.EMITTER_SPLITS},
        "repeats": repeats,
        "lift": f"surface points lie {LIFT:g} of the scene's diagonal off their surface, along its normal",
        "seconds": round(seconds, 1),
        "noise": {
            "standard_error": "per point and channel: the standard deviation of the repeats over sqrt(repeats)",
            "largest_relative_standard_error": float(f"{relative.max():.3g}"),
            "median_relative_standard_error": float(f"{np.median(relative):.3g}"),
        },
        "smallest_clearance_in_element_sizes": float(f"{min(clearances):.3g}"),
        "geometry": geometry_summary(scene, mesh),
    }
    reference = ir.IrradianceReference(names, points, normals, mean, direct.mean(axis=0), standard_error, info)
    path = reference.save(out, name)
    print(f"{name}: {len(names)} points, {repeats} repeats in {seconds:.0f} s; relative standard error "
          f"median {np.median(relative):.2e}, largest {relative.max():.2e}; {path.name}")
    for n, e, d, r, c in zip(names, mean, reference.direct, relative.max(axis=1), clearances):
        print(f"  {n:26s} E {_rgb(e)}  direct {_rgb(d)}  noise {r:.1e}  clearance {c:.1f}")
    return reference


def _rgb(values) -> str:
    return " ".join(f"{v:9.4g}" for v in values)


def gather(name: str, out: Path) -> None:
    """Solve with hemirad (emitters not reflecting, as in RADIANCE, then as shipped) and print the 256-hemicube gather
    of its display radiosity at the reference's points beside RADIANCE's values."""
    from hemirad.transport.renderer import HemicubeRenderer

    reference = ir.IrradianceReference.load(out, name)
    columns = {}
    for label, emitter_reflects in (("no emitter reflection", False), ("hemirad", True)):
        scene = hemirad.load_scene(name)
        scene.solver.unshot_fraction = 1e-4
        if not emitter_reflects:
            scene.materials = [dataclasses.replace(m, reflectance=(0.0, 0.0, 0.0)) if max(m.emission) > 0 else m
                               for m in scene.materials]
        start = time.perf_counter()
        result = hemirad.solve(scene)
        solve_seconds = time.perf_counter() - start
        radiosity = result.display_radiosity
        renderer = HemicubeRenderer(result.mesh, 256)
        values = []
        for point, normal in zip(reference.points, reference.normals):
            tangent = np.eye(3)[int(np.argmin(np.abs(normal)))]
            view = renderer.render_at(point, normal, tangent)
            values.append((view.form_factors @ radiosity).numpy())
        renderer.close()
        columns[label] = np.array(values)
        print(f"{name}: {label}: solved in {solve_seconds:.1f} s, {result.stats['shots']} shots, "
              f"{result.mesh.num_elements} elements")
    shipped, ours = columns["hemirad"], columns["no emitter reflection"]
    ref = reference.irradiance
    print(f"\n{name}: irradiance, RADIANCE against hemirad's gather: luminance, and per channel the "
          f"largest difference")
    print("| point | RADIANCE | +- | hemirad | difference | worst channel | emitters reflecting |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for i, point_name in enumerate(reference.names):
        lum_ref, lum_ours, lum_shipped = luminance(ref[i]), luminance(ours[i]), luminance(shipped[i])
        noise = luminance(reference.standard_error[i]) / lum_ref
        channel = ours[i] / ref[i] - 1
        worst = channel[np.argmax(np.abs(channel))]
        print(f"| {point_name} | {lum_ref:.4g} | {100 * noise:.2f}% | {lum_ours:.4g} | "
              f"{100 * (lum_ours / lum_ref - 1):+.2f}% | {100 * worst:+.2f}% | {100 * (lum_shipped / lum_ref - 1):+.2f}% |")
    lift = luminance(shipped) / luminance(ours) - 1
    print(f"the emitters' reflection raises the points by {100 * lift.min():.2f}% to {100 * lift.max():.2f}% (luminance)")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", default=sorted(POINTS), choices=sorted(POINTS))
    parser.add_argument("--repeats", type=int, default=32, help="independent evaluations of every point")
    parser.add_argument("--out", type=Path, default=ROOT / "tests" / "references")
    parser.add_argument("--gather", action="store_true",
                        help="only compare hemirad's converged solution with the stored references")
    args = parser.parse_args(argv)
    for name in args.scenes:
        if args.gather:
            gather(name, args.out)
        else:
            make(name, args.repeats, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
