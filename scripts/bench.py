"""Seconds per shot of the progressive solver, split into raster, read-back and torch.

    python scripts/bench.py [--scene floating] [--shots 30] [--resolution 128] [--adaptive]

Runs the scene at several element sizes (the scene's own, scaled) for a fixed number of
shots and prints a Markdown table; ``--adaptive`` adds one adaptive solve (pattern 2, 100
shots: the paper's Fig. 6(c) on ``floating``) with its phases and peak memory. Timings are
for reading, never for asserting.
"""
from __future__ import annotations

import argparse
import copy
import platform
import resource
import time

import torch

import hemirad
from hemirad import load_scene
from hemirad.gl import GLContext
from hemirad.meshing import build_mesh
from hemirad.solver import ProgressiveSolver


def bench(scene, shots: int, resolution: int) -> dict:
    mesh = build_mesh(scene)
    reflectance = scene.reflectance_table()[mesh.material]
    emission = scene.emission_table()[mesh.material]
    solver = ProgressiveSolver(mesh, reflectance, emission, resolution)
    try:
        solver.shoot()  # warm-up: shader compilation and first allocations
        warm = solver.timings()
        start = time.perf_counter()
        solver.run(shots + 1, unshot_fraction=0.0)
        wall = time.perf_counter() - start
        phases = {k: (v - warm[k]) / shots for k, v in solver.timings().items()}
    finally:
        solver.close()
    return {"elements": mesh.num_elements, "shots": shots, "per_shot": wall / shots, **phases}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="floating")
    parser.add_argument("--shots", type=int, default=30)
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--adaptive", action="store_true", help="also time one adaptive solve")
    parser.add_argument("--factors", type=float, nargs="+", default=[2.0, 1.0, 0.5, 0.25],
                        help="element-size multipliers (smaller: more elements)")
    args = parser.parse_args()
    scene = load_scene(args.scene)
    print(f"scene {args.scene}, hemicube {args.resolution}, {args.shots} shots after one warm-up; "
          f"{GLContext.renderer_name()}, {platform.processor() or platform.machine()}, "
          f"torch {torch.__version__} with {torch.get_num_threads()} threads\n")
    print("| size factor | elements | ms/shot | raster | read-back | torch form factors | update |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for factor in args.factors:
        r = bench(scene.with_element_sizes_scaled(factor), args.shots, args.resolution)
        ms = {k: 1e3 * r[k] for k in ("per_shot", "raster", "readback", "form_factors", "update")}
        print(f"| {factor:g} | {r['elements']} | {ms['per_shot']:.2f} | {ms['raster']:.2f} | "
              f"{ms['readback']:.2f} | {ms['form_factors']:.2f} | {ms['update']:.2f} |", flush=True)
    if args.adaptive:
        bench_adaptive(scene, args.resolution)


def bench_adaptive(scene, resolution: int) -> None:
    scene = copy.deepcopy(scene)
    scene.solver.max_shots, scene.solver.unshot_fraction, scene.solver.resolution = 100, 0.0, resolution
    scene.refine.pattern = "pattern2"
    start = time.perf_counter()
    result = hemirad.solve(scene)
    wall = time.perf_counter() - start
    shots = result.stats["shots"]
    phases = result.stats["seconds"]["solve_phases"]
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"\nadaptive solve: pattern 2, threshold {scene.refine.threshold:g} relative, {shots} shots, "
          f"{result.mesh.num_elements} final elements, {wall:.1f} s wall, peak RSS {peak:.0f} MiB\n")
    print("| phase | s in all | ms per shot |")
    print("|---|---:|---:|")
    for name, seconds in phases.items():
        print(f"| {name} | {seconds:.2f} | {1e3 * seconds / shots:.1f} |")


if __name__ == "__main__":
    main()
