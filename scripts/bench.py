"""Timings of the progressive solver: one Fig. 6(c)-class adaptive solve, and seconds per shot
against element count. For reading, never for asserting.

    python scripts/bench.py [--quick] [--out figures/bench.md]

1. The adaptive solve: the floating-rectangle room (``floating``), pattern 2, 100 shots,
   hemicube 256, the gradient criterion at ``--threshold`` (chosen so that the mesh ends near
   the paper's 94,791 elements). Prints wall time, seconds per shot split into raster
   (culling and drawing), read-back, form factors + AD (decoding, hit points, the
   forward-mode Jacobian), refinement (criterion, selection, splitting, re-upload) and
   update, and the peak resident memory.
2. The scaling table: the same room meshed to about 1k, 10k, 100k and 1M elements, no
   refinement, ``--shots`` shots after a warm-up shot, seconds per shot by phase.

Both tables, with the machine described, go to ``--out`` (Markdown). ``--quick`` runs a
small version of each (a smoke test; its numbers are not the benchmark's).
"""
from __future__ import annotations

import argparse
import os
import platform
import resource
import time
from pathlib import Path

import torch

import hemirad
from hemirad.gl import GLContext
from hemirad.meshing import build_mesh
from hemirad.solver import ProgressiveSolver

ROOT = Path(__file__).resolve().parent.parent
PHASES = ("raster", "readback", "form_factors", "gradient", "refine", "update")
PHASE_NAMES = {"raster": "raster", "readback": "read-back", "form_factors": "form factors (decode, sum)",
               "gradient": "form factors + AD (hit points, Jacobian)", "refine": "refinement", "update": "update"}


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        names = [line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")]
        cpu = names[0] if names else cpu
    except OSError:
        pass
    memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    return (f"{cpu}, {os.cpu_count()} cores, {memory:.0f} GiB; {platform.system()} {platform.release()}; "
            f"GL renderer {GLContext.renderer_name()}; torch {torch.__version__} (CPU, one intra-op thread "
            f"during solves beside a software renderer); Python {platform.python_version()}")


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def adaptive(threshold: float, shots: int, resolution: int) -> tuple[dict, list[str]]:
    scene = hemirad.load_scene("floating")
    scene.solver.max_shots, scene.solver.unshot_fraction, scene.solver.resolution = shots, 0.0, resolution
    scene.refine.pattern, scene.refine.criterion, scene.refine.threshold = "pattern2", "gradient", threshold
    start = time.perf_counter()
    result = hemirad.solve(scene)
    wall = time.perf_counter() - start
    phases = result.stats["seconds"]["solve_phases"]
    run = {"elements": result.mesh.num_elements, "initial": result.stats["initial_elements"],
           "shots": result.stats["shots"], "wall": wall, "mesh": result.stats["seconds"]["mesh"],
           "phases": phases, "peak_rss_mib": peak_rss_mib()}
    lines = [f"Fig. 6(c)-class solve: `floating`, pattern 2, gradient criterion, threshold {threshold:g} "
             f"(relative), hemicube {resolution}, {run['shots']} shots: {run['initial']} -> "
             f"**{run['elements']} elements in {wall:.1f} s wall** (meshing {run['mesh']:.2f} s), "
             f"peak resident memory {run['peak_rss_mib']:.0f} MiB. The paper: 94,791 elements, "
             "100 shots, 8,613 s.", "",
             "| phase | seconds in all | ms per shot |", "|---|---:|---:|"]
    for name in PHASES:
        lines.append(f"| {PHASE_NAMES[name]} | {phases[name]:.2f} | {1e3 * phases[name] / run['shots']:.1f} |")
    other = result.stats["seconds"]["solve"] - sum(phases.values())
    lines.append(f"| other (shooter choice, bookkeeping) | {other:.2f} | {1e3 * other / run['shots']:.1f} |")
    return run, lines


def per_shot(scene, shots: int, resolution: int) -> dict:
    mesh = build_mesh(scene)
    reflectance = scene.reflectance_table()[mesh.material]
    emission = scene.emission_table()[mesh.material]
    solver = ProgressiveSolver(mesh, reflectance, emission, resolution)
    try:
        solver.run(1, unshot_fraction=0.0)  # warm-up: shader compilation and first allocations
        warm = solver.timings()
        start = time.perf_counter()
        solver.run(shots + 1, unshot_fraction=0.0)
        wall = time.perf_counter() - start
        phases = {k: (v - warm[k]) / shots for k, v in solver.timings().items()}
    finally:
        solver.close()
    return {"elements": mesh.num_elements, "per_shot": wall / shots, **phases}


def scaling(targets: list[int], shots: int, resolution: int) -> tuple[list[dict], list[str]]:
    scene = hemirad.load_scene("floating")
    base = build_mesh(scene).num_elements
    lines = [f"Seconds per shot without refinement (`floating` meshed finer, hemicube {resolution}, "
             f"{shots} shots after a warm-up):", "",
             "| elements | ms/shot | raster | read-back | form factors | update | ms per 1k elements |",
             "|---:|---:|---:|---:|---:|---:|---:|"]
    rows = []
    for target in targets:
        r = per_shot(scene.with_element_sizes_scaled((base / target) ** 0.5), shots, resolution)
        rows.append(r)
        ms = {k: 1e3 * r[k] for k in ("per_shot", "raster", "readback", "form_factors", "update")}
        lines.append(f"| {r['elements']} | {ms['per_shot']:.1f} | {ms['raster']:.1f} | {ms['readback']:.2f} | "
                     f"{ms['form_factors']:.1f} | {ms['update']:.2f} | {ms['per_shot'] / r['elements'] * 1e3:.3f} |")
        print(lines[-1], flush=True)
    return rows, lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threshold", type=float, default=1.35e-4,
                        help="the adaptive solve's gradient threshold (relative to the lamp)")
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--shots", type=int, default=20, help="shots per row of the scaling table")
    parser.add_argument("--out", type=Path, default=ROOT / "figures" / "bench.md")
    parser.add_argument("--quick", action="store_true", help="a smoke test: small sizes, few shots")
    args = parser.parse_args()
    if args.quick:
        args.out = Path("bench_quick.md") if args.out == ROOT / "figures" / "bench.md" else args.out
        adaptive_args, targets, shots = (1e-3, 10, 64), [1000, 10000], 3
    else:
        adaptive_args, targets, shots = (args.threshold, 100, args.resolution), [1000, 10000, 100000, 1000000], args.shots
    print(machine(), flush=True)
    run, adaptive_lines = adaptive(*adaptive_args)
    print("\n".join(adaptive_lines), "\n", flush=True)
    rows, scaling_lines = scaling(targets, shots, adaptive_args[2])
    text = ["# Benchmark", "", f"Made by `python scripts/bench.py` on: {machine()}.", "",
            *adaptive_lines, "", *scaling_lines, ""]
    args.out.write_text("\n".join(text))
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
