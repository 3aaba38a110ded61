"""Reproduce section 4 of Hasebe & Makino: Figs. 5-7, Table 1 and the mesh-quality figures.

    python scripts/reproduce_figures.py [--quick] [--out figures]

For each scene (office = Fig. 5, floating = Fig. 6, floating_coarse = Fig. 7) it solves
(a) without refinement, (b) with pattern 1 and (c) with pattern 2, 100 shots each and one
threshold for all, and writes into the output folder:

    <scene>_a.png, _b.png, _c.png            camera images
    <scene>_a_mesh.png, ...                  the floor's mesh, the paper's (a)'(b)'(c)'
    <scene>.png                              the six side by side
    table1.md, mesh_quality.md, summary.json

``--quick`` (for tests) runs the same pipeline with a small hemicube, fewer shots, coarser
meshes and smaller pictures.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

import hemirad
from hemirad.evaluation.penumbra import grid_cell, surface_grid, visible_light_fraction
from hemirad.output import export
from hemirad.output.meshview import pick_surface
from hemirad.scene.meshing import build_mesh
from hemirad.transport.gl import GLContext

SCENES = {"office": "Fig. 5", "floating": "Fig. 6", "floating_coarse": "Fig. 7"}
RUNS = {"a": "none", "b": "pattern1", "c": "pattern2"}
# The paper's Table 1 (Figs. 6 and 7 only; it gives no times for Fig. 5).
PAPER_TABLE = {("floating", "a"): (1511, 2148), ("floating", "b"): (8023, 43680),
               ("floating", "c"): (8613, 94791), ("floating_coarse", "a"): (1060, 1112),
               ("floating_coarse", "b"): (8233, 45416), ("floating_coarse", "c"): (8688, 93140)}
PAPER_ANGLE_VARIANCE = {"pattern1": 247.0, "pattern2": 1.35}


def configure(name: str, pattern: str, args) -> hemirad.scene.Scene:
    scene = hemirad.load_scene(name)
    scene.solver.paper()  # every element shoots from its centroid, as in the paper
    scene.meshing.contacts = False  # and every surface is meshed on its own, as the paper's were
    scene.solver.max_shots, scene.solver.unshot_fraction = args.shots, 0.0
    scene.solver.resolution = args.resolution
    scene.refine.pattern, scene.refine.threshold, scene.refine.relative = pattern, args.threshold, True
    scene.refine.criterion = "gradient"  # the paper's eq. 7, per shot
    scene.refine.max_depth, scene.refine.max_elements = args.max_depth, args.max_elements
    if args.quick:  # smaller pictures (and, from main, fewer shots, a smaller hemicube, shallower refinement)
        scene.camera.width, scene.camera.height = scene.camera.width // 3, scene.camera.height // 3
        scene.camera.supersample = 1
    return scene


def penumbra_of_floor(scene, grid_count: int, resolution: int, band: tuple[float, float]):
    """The floor's penumbra band, from hemicubes at grid points of the unrefined scene."""
    mesh = build_mesh(scene)
    floor = pick_surface(mesh, "floor")
    emitting = (scene.emission_table()[mesh.material] > 0).any(1)
    points, normal, axes = surface_grid(mesh, floor, grid_count)
    visible = visible_light_fraction(mesh, emitting, points, normal, resolution)
    in_band = (visible > band[0]) & (visible < band[1])
    return points, axes, in_band


def shadow_tracking(result, penumbra, grid_count: int) -> dict:
    """Element density on the floor inside the penumbra band against outside it."""
    points, axes, in_band = penumbra
    mesh = result.mesh
    floor = pick_surface(mesh, "floor")
    on_floor = mesh.surface == floor
    floor_area = float(mesh.areas[on_floor].sum())
    cells = grid_cell(mesh.centroids[on_floor], points, axes, grid_count)
    near = int(in_band[cells].sum())
    band_share = float(in_band.double().mean())
    far = int(on_floor.sum()) - near
    near_density = near / (band_share * floor_area)
    far_density = far / ((1 - band_share) * floor_area)
    return {"floor_elements": int(on_floor.sum()), "near_shadow_elements": near, "far_elements": far,
            "band_share_of_floor": band_share, "density_near_per_m2": near_density,
            "density_far_per_m2": far_density, "density_ratio": near_density / far_density}


def side_by_side(paths: list[Path], labels: list[str], out: Path, height: int) -> None:
    tiles = []
    for path, label in zip(paths, labels):
        image = Image.open(path).convert("RGB")
        image = image.resize((round(image.width * height / image.height), height))
        ImageDraw.Draw(image).text((6, 4), label, fill=(255, 255, 0))
        tiles.append(image)
    rows = [tiles[:3], tiles[3:]]
    width = max(sum(t.width for t in row) + 4 * (len(row) - 1) for row in rows)
    canvas = Image.new("RGB", (width, 2 * height + 4), (255, 255, 255))
    for r, row in enumerate(rows):
        x = 0
        for tile in row:
            canvas.paste(tile, (x, r * (height + 4)))
            x += tile.width + 4
    canvas.save(out)


def table1(runs: dict) -> str:
    lines = ["# Table 1: computation time, elements and shots",
             "",
             f"Ours: {MACHINE}; hemicube {ARGS.resolution}, threshold {ARGS.threshold:g} "
             f"(relative to the lamp's radiosity), max depth {ARGS.max_depth}. Time is the solve "
             "(meshing, hemicubes, gradients, refinement, shots), not pictures. The paper's times "
             "are from its own machine (about 2001).",
             "",
             "| image | ours: time [s] | ours: elements | ours: shots | paper: time [s] | paper: elements | paper: shots |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for name, fig in SCENES.items():
        for run in RUNS:
            r = runs[name, run]
            paper = PAPER_TABLE.get((name, run))
            p = f"{paper[0]} | {paper[1]} | 100" if paper else "- | - | -"
            lines.append(f"| {fig}({run}) | {r['seconds']:.1f} | {r['elements']} | {r['shots']} | {p} |")
    lines += ["", "Pattern 2 against pattern 1:", "",
              "| scene | elements ratio | time ratio | paper: elements ratio | paper: time ratio |",
              "|---|---:|---:|---:|---:|"]
    for name, fig in SCENES.items():
        b, c = runs[name, "b"], runs[name, "c"]
        pb, pc = PAPER_TABLE.get((name, "b")), PAPER_TABLE.get((name, "c"))
        paper = f"{pc[1] / pb[1]:.2f} | {pc[0] / pb[0]:.3f}" if pb else "- | -"
        lines.append(f"| {fig} ({name}) | {c['elements'] / b['elements']:.2f} | "
                     f"{c['seconds'] / b['seconds']:.3f} | {paper} |")
    lines += ["", "The paper reports pattern 2 with up to about 2.2x the elements of pattern 1 for at "
              "most about 7.9% more time."]
    return "\n".join(lines) + "\n"


def mesh_quality(runs: dict) -> str:
    lines = ["# Mesh quality and shadow tracking", "",
             "Largest interior angle of each element of the final mesh (degrees): mean and "
             "variance (degrees squared), per run; the paper averages the variance over its "
             "scenes: 247 for pattern 1 and 1.35 for pattern 2.", "",
             "| image | pattern | elements | mean largest angle | variance |",
             "|---|---|---:|---:|---:|"]
    for name, fig in SCENES.items():
        for run, pattern in RUNS.items():
            r = runs[name, run]
            lines.append(f"| {fig}({run}) | {pattern} | {r['elements']} | {r['angle']['mean']:.2f} | "
                         f"{r['angle']['variance']:.2f} |")
    lines += ["", "| pattern | mean over scenes of the variance | paper |", "|---|---:|---:|"]
    for run, pattern in list(RUNS.items())[1:]:
        mean = np.mean([runs[name, run]["angle"]["variance"] for name in SCENES])
        lines.append(f"| {pattern} | {mean:.2f} | {PAPER_ANGLE_VARIANCE[pattern]} |")
    lines += ["", "Does refinement track the shadows? Floor elements per square metre inside the "
              "penumbra band (0.1 < visible share of the lamp < 0.9, found with hemicubes from a "
              "grid of floor points) against outside it:", "",
              "| image | floor elements | band's share of floor | density in band | density outside | ratio |",
              "|---|---:|---:|---:|---:|---:|"]
    for name, fig in SCENES.items():
        for run in RUNS:
            t = runs[name, run]["shadow"]
            lines.append(f"| {fig}({run}) | {t['floor_elements']} | {t['band_share_of_floor']:.2f} | "
                         f"{t['density_near_per_m2']:.0f} | {t['density_far_per_m2']:.0f} | "
                         f"{t['density_ratio']:.2f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    global ARGS, MACHINE
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent.parent / "figures")
    parser.add_argument("--quick", action="store_true", help="small and fast, for tests")
    parser.add_argument("--threshold", type=float, default=3e-4)
    parser.add_argument("--max-depth", type=int, default=4)
    parser.add_argument("--max-elements", type=int, default=200_000)
    args = parser.parse_args(argv)
    args.shots = 20 if args.quick else 100
    args.resolution = 64 if args.quick else 128
    if args.quick:
        args.max_depth = min(args.max_depth, 2)
    grid_count = 16 if args.quick else 40
    ARGS = args
    MACHINE = (f"{platform.machine()}, {os.cpu_count()} cores, torch on one thread during solves, "
               f"{GLContext.renderer_name()}")
    args.out.mkdir(parents=True, exist_ok=True)

    runs = {}
    for name, fig in SCENES.items():
        penumbra = penumbra_of_floor(configure(name, "none", args), grid_count, 128, (0.1, 0.9))
        pictures = []
        for run, pattern in RUNS.items():
            scene = configure(name, pattern, args)
            start = time.perf_counter()
            result = hemirad.solve(scene)
            seconds = time.perf_counter() - start
            camera, mesh_view = args.out / f"{name}_{run}.png", args.out / f"{name}_{run}_mesh.png"
            export.write_png(camera, result.image())
            export.write_png(mesh_view, result.mesh_image("floor", size=160 if args.quick else 480))
            pictures += [camera]
            runs[name, run] = {"scene": name, "figure": fig, "run": run, "pattern": pattern,
                               "seconds": seconds, "elements": result.mesh.num_elements,
                               "initial_elements": result.stats["initial_elements"],
                               "elements_per_level": result.stats["elements_per_level"],
                               "shots": result.stats["shots"], "angle": result.stats["largest_angle_degrees"],
                               "shadow": shadow_tracking(result, penumbra, grid_count)}
            print(f"{fig}({run}) {name} {pattern}: {result.mesh.num_elements} elements, "
                  f"{seconds:.1f} s", file=sys.stderr, flush=True)
        meshes = [args.out / f"{name}_{run}_mesh.png" for run in RUNS]
        labels = [f"{fig}({r})" for r in RUNS] + [f"{fig}({r})'" for r in RUNS]
        side_by_side(pictures + meshes, labels, args.out / f"{name}.png", 120 if args.quick else 240)

    (args.out / "table1.md").write_text(table1(runs))
    (args.out / "mesh_quality.md").write_text(mesh_quality(runs))
    (args.out / "summary.json").write_text(json.dumps(
        {"settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items() if k != "out"},
         "machine": MACHINE, "runs": list(runs.values())}, indent=2, sort_keys=True))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
