"""Timings of the progressive solver: one Fig. 6(c)-class adaptive solve, and seconds per shot
against element count. For reading, never for asserting.

    python scripts/bench.py [--quick] [--device cpu|cuda|auto] [--repeat 3] [--out figures/bench.md]

1. The adaptive solve: the floating-rectangle room (``floating``), pattern 2, 100 shots,
   hemicube 256, the gradient criterion at ``--threshold`` (chosen so that the mesh ends near
   the paper's 94,791 elements), ``--repeat`` times, without the run's error estimate (a
   final gather over ``solver.error_samples`` points, which ``stats.json`` times apart). Prints the median wall time and the range, seconds per shot split into raster
   (culling and drawing), read-back, form factors + AD (decoding, hit points, the
   Jacobian), refinement (criterion, selection, splitting, re-upload) and
   update, and the peak resident memory; then where the time goes inside (the same solve
   again under cProfile: the functions with the most time of their own), so that the
   next bottleneck is visible; and the number of torch operators per shot (the solve once
   more, counted: on a GPU each that computes is a kernel launch).
2. The scaling table: the same room meshed to about 1k, 10k, 100k and 1M elements, no
   refinement, ``--shots`` shots after a warm-up shot, seconds per shot by phase.
3. Convergence: shots and seconds to 1e-2, 1e-3 and 1e-4 unshot power for each bundled
   scene as shipped, in the paper's configuration (every element shoots, every shot
   rendered: the release before patches), one patch a shot (patches, overshooting, kept
   form-factor rows: the release before sweeps) and with the defaults (sweeps), with the
   hemicubes rendered; then a Fig. 6(c)-class mesh made by
   refining during the first 40 patch shots and converged to 1e-3.

The tables, with the machine described, go to ``--out`` (Markdown; ``figures/bench.md`` on
the CPU, ``figures/bench_cuda.md`` with ``--device cuda``). ``--quick`` runs a small version
of each (a smoke test; its numbers are not the benchmark's).
"""
from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import platform
import resource
import time
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

import hemirad
from hemirad.assembly import make_solver
from hemirad.core.device import select_device
from hemirad.scene.meshing import build_mesh
from hemirad.transport.gl import GLContext

ROOT = Path(__file__).resolve().parent.parent
PHASES = ("raster", "readback", "form_factors", "gradient", "refine", "update")
PHASE_NAMES = {"raster": "raster", "readback": "read-back", "form_factors": "form factors (decode, sum)",
               "gradient": "form factors + AD (hit points, Jacobian)", "refine": "refinement", "update": "update"}


def machine(device: torch.device) -> str:
    cpu = platform.processor() or platform.machine()
    try:
        names = [line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")]
        cpu = names[0] if names else cpu
    except OSError:
        pass
    memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    if device.type == "cuda":
        where = f"CUDA on {torch.cuda.get_device_name(device)}"
    elif GLContext.is_software():
        where = "CPU, one intra-op thread during solves beside a software renderer"
    else:
        where = f"CPU, {torch.get_num_threads()} intra-op threads"
    return (f"{cpu}, {os.cpu_count()} cores, {memory:.0f} GiB; {platform.system()} {platform.release()}; "
            f"GL renderer {GLContext.renderer_name()}; torch {torch.__version__} ({where}); "
            f"Python {platform.python_version()}")


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def adaptive_scene(threshold: float, shots: int, resolution: int, device: torch.device):
    scene = hemirad.load_scene("floating")
    scene.solver.paper()  # the paper's configuration, as its Fig. 6(c)
    scene.solver.max_shots, scene.solver.unshot_fraction, scene.solver.resolution = shots, 0.0, resolution
    scene.solver.device = str(device)
    scene.solver.error_samples = 0  # the solve alone: the run's error estimate (a final gather) is another job
    scene.refine.pattern, scene.refine.criterion, scene.refine.threshold = "pattern2", "gradient", threshold
    return scene


def adaptive(threshold: float, shots: int, resolution: int, device: torch.device,
             repeat: int = 1) -> tuple[dict, list[str]]:
    """The adaptive solve ``repeat`` times (the same numbers each time); the run of median wall
    time is reported, with the range, since a shared machine's speed drifts between runs."""
    runs = []
    for _ in range(repeat):
        scene = adaptive_scene(threshold, shots, resolution, device)
        start = time.perf_counter()
        result = hemirad.solve(scene)
        runs.append((time.perf_counter() - start, result))
        print(f"adaptive solve: {runs[-1][0]:.1f} s", flush=True)
    runs.sort(key=lambda run: run[0])
    walls = [wall for wall, _ in runs]
    wall, result = runs[(repeat - 1) // 2]
    phases = result.stats["seconds"]["solve_phases"]
    run = {"elements": result.mesh.num_elements, "initial": result.stats["initial_elements"],
           "shots": result.stats["shots"], "wall": wall, "walls": walls, "mesh": result.stats["seconds"]["mesh"],
           "phases": phases, "peak_rss_mib": peak_rss_mib()}
    spread = f" (median of {repeat} runs: {', '.join(f'{w:.1f}' for w in walls)} s)" if repeat > 1 else ""
    lines = [f"Fig. 6(c)-class solve: `floating`, pattern 2, gradient criterion, threshold {threshold:g} "
             f"(relative), hemicube {resolution}, {run['shots']} shots: {run['initial']} -> "
             f"**{run['elements']} elements in {wall:.1f} s wall**{spread} (meshing {run['mesh']:.2f} s), "
             f"peak resident memory {run['peak_rss_mib']:.0f} MiB. The paper: 94,791 elements, "
             "100 shots, 8,613 s.", "",
             "| phase (the median run) | seconds in all | ms per shot |", "|---|---:|---:|"]
    for name in PHASES:
        lines.append(f"| {PHASE_NAMES[name]} | {phases[name]:.2f} | {1e3 * phases[name] / run['shots']:.1f} |")
    other = result.stats["seconds"]["solve"] - sum(phases.values())
    lines.append(f"| other (shooter choice, bookkeeping) | {other:.2f} | {1e3 * other / run['shots']:.1f} |")
    return run, lines


def profile(threshold: float, shots: int, resolution: int, device: torch.device, top: int = 15) -> list[str]:
    """The adaptive solve once more under cProfile: the functions with the most time of
    their own (torch operators by name, hemirad functions by file and line)."""
    scene = adaptive_scene(threshold, shots, resolution, device)
    profiler = cProfile.Profile()
    profiler.enable()
    hemirad.solve(scene)
    profiler.disable()
    stats = pstats.Stats(profiler).stats  # {(file, line, name): (calls, _, own, cumulative, _)}
    total = sum(own for _, _, own, _, _ in stats.values())
    rows = sorted(stats.items(), key=lambda item: -item[1][2])[:top]
    lines = [f"Where the time goes (the same solve under cProfile, which slows it to {total:.1f} s; "
             f"the {top} functions with the most time of their own):", "",
             "| function | calls | own seconds | share |", "|---|---:|---:|---:|"]
    for (file, line, name), (calls, _, own, _, _) in rows:
        where = name if file == "~" else f"{Path(file).name}:{line} {name}"
        lines.append(f"| `{where}` | {calls} | {own:.2f} | {100 * own / total:.1f}% |")
    return lines


class _OperatorCount(TorchDispatchMode):
    """Counts the ATen operators torch runs, views (no data touched) apart."""

    def __init__(self):
        super().__init__()
        self.computing = self.views = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        if func.is_view:  # its output aliases an input
            self.views += 1
        else:
            self.computing += 1
        return out


def operator_counts(threshold: float, shots: int, resolution: int, device: torch.device) -> list[str]:
    """The adaptive solve once more, counting torch's operators: on a GPU each one that
    computes is at least one kernel launch, so their number per shot bounds how fast a shot
    can be however fast the GPU."""
    scene = adaptive_scene(threshold, shots, resolution, device)
    count = _OperatorCount()
    with count:
        result = hemirad.solve(scene)
    done = result.stats["shots"]
    return [f"Torch operators per shot (the same solve once more, counted): "
            f"{count.computing / done:,.0f} that compute, {count.views / done:,.0f} views "
            f"({result.mesh.num_elements} elements at the end)."]


def per_shot(scene, shots: int, resolution: int, device: torch.device) -> dict:
    scene.solver.paper()  # seconds per element shot
    scene.solver.resolution = resolution
    solver = make_solver(scene, device=device)
    mesh = solver.mesh
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


def scaling(targets: list[int], shots: int, resolution: int, device: torch.device) -> tuple[list[dict], list[str]]:
    scene = hemirad.load_scene("floating")
    base = build_mesh(scene).num_elements
    lines = [f"Seconds per shot without refinement (`floating` meshed finer, hemicube {resolution}, "
             f"{shots} shots after a warm-up):", "",
             "| elements | ms/shot | raster | read-back | form factors | update | ms per 1k elements |",
             "|---:|---:|---:|---:|---:|---:|---:|"]
    rows = []
    for target in targets:
        r = per_shot(scene.with_element_sizes_scaled((base / target) ** 0.5), shots, resolution, device)
        rows.append(r)
        ms = {k: 1e3 * r[k] for k in ("per_shot", "raster", "readback", "form_factors", "update")}
        lines.append(f"| {r['elements']} | {ms['per_shot']:.1f} | {ms['raster']:.1f} | {ms['readback']:.2f} | "
                     f"{ms['form_factors']:.1f} | {ms['update']:.2f} | {ms['per_shot'] / r['elements'] * 1e3:.3f} |")
        print(lines[-1], flush=True)
    return rows, lines


CONVERGENCE_SCENES = ("cornell_box", "office", "floating")
CONVERGENCE_TARGETS = (1e-2, 1e-3, 1e-4)


def converge(name: str, targets, configuration: str, device: torch.device, max_shots: int
             ) -> tuple[int, int | None, list[tuple]]:
    """One scene solved onwards through the unshot targets: its elements, its patches (None
    when elements shoot), and (shots, seconds, renders) at each target."""
    scene = hemirad.load_scene(name)
    if configuration == "paper":
        scene.solver.paper()
        scene.solver.cache_mb = 0.0  # every shot renders, as before rows were kept
    elif configuration == "one patch a shot":
        scene.solver.sweeps = False
    solver = make_solver(scene, device=device)
    out = []
    try:
        start = time.perf_counter()
        for target in targets:
            solver.run(max_shots, target)
            out.append((solver.state.shots, time.perf_counter() - start, solver.hemicubes_rendered))
    finally:
        solver.close()
    patches = solver.patches.tree.num_patches if solver.patches is not None else None
    return solver.mesh.num_elements, patches, out


def convergence(scenes, targets, device: torch.device, max_shots: int = 400_000) -> list[str]:
    lines = ["Shots (hemicubes rendered) and seconds to reach each unshot fraction, bundled scenes as shipped; "
             "*paper*: every element shoots and every shot renders (the release before patches), "
             "*one patch a shot*: patches, overshooting, kept rows (the release before sweeps); "
             "*default*: patches shooting in sweeps from the kept light (a shot per patch that shoots):", "",
             "| scene | configuration | elements | patches | " + " | ".join(f"to {t:g}" for t in targets) + " |",
             "|---|---|---:|---:|" + "---:|" * len(targets)]
    for name in scenes:
        for configuration in ("paper", "one patch a shot", "default"):
            elements, patches, reached = converge(name, targets, configuration, device, max_shots)
            cells = [f"{shots} ({renders}) / {seconds:.1f} s" for shots, seconds, renders in reached]
            lines.append(f"| {name} | {configuration} | {elements} | {patches or '-'} | " + " | ".join(cells) + " |")
            print(lines[-1], flush=True)
    return lines


def converged_adaptive(device: torch.device, threshold: float = 3e-3, refine_shots: int = 40,
                       resolution: int = 256) -> list[str]:
    """A Fig. 6(c)-class mesh, converged: ``floating`` with the defaults (patches), pattern 2
    and the gradient criterion during the first ``refine_shots`` shots, then shot on to 1e-3."""
    scene = hemirad.load_scene("floating")
    scene.solver.resolution, scene.solver.device = resolution, str(device)
    scene.solver.error_samples = 0  # the solve alone (as ``adaptive_scene``)
    r = scene.refine
    r.pattern, r.criterion, r.threshold, r.shots = "pattern2", "gradient", threshold, refine_shots
    start = time.perf_counter()
    result = hemirad.solve(scene)
    wall = time.perf_counter() - start
    return [f"Fig. 6(c)-class, converged: `floating` with the defaults (patches), pattern 2, gradient "
            f"threshold {threshold:g} during the first {refine_shots} shots, hemicube {resolution}, then to "
            f"{scene.solver.unshot_fraction:g} unshot: {result.stats['initial_elements']} -> "
            f"**{result.mesh.num_elements} elements, {result.stats['shots']} shots "
            f"({result.stats['hemicubes_rendered']} hemicubes), {wall:.1f} s**."]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threshold", type=float, default=1.35e-4,
                        help="the adaptive solve's gradient threshold (relative to the lamp)")
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--shots", type=int, default=20, help="shots per row of the scaling table")
    parser.add_argument("--device", default="cpu", help="cpu (the default), cuda, cuda:N or auto")
    parser.add_argument("--out", type=Path, help="default figures/bench.md (figures/bench_cuda.md on CUDA)")
    parser.add_argument("--repeat", type=int, default=3, help="adaptive solves; the median is reported")
    parser.add_argument("--no-profile", dest="profile", action="store_false", help="skip the profiled solve")
    parser.add_argument("--quick", action="store_true", help="a smoke test: small sizes, few shots")
    parser.add_argument("--convergence-only", action="store_true",
                        help="only the convergence table and the converged Fig. 6(c)-class solve, written to "
                             "--out (default figures/bench_convergence.md)")
    args = parser.parse_args()
    device = select_device(args.device)
    GLContext.get(gpu=device.type == "cuda")
    if args.out is None:
        name = "bench_convergence" if args.convergence_only else "bench"
        args.out = ROOT / "figures" / (f"{name}_cuda.md" if device.type == "cuda" else f"{name}.md")
    if args.quick:
        args.out = Path("bench_quick.md")
        adaptive_args, targets, shots = (1e-3, 10, 64, device), [1000, 10000], 3
    else:
        adaptive_args = (args.threshold, 100, args.resolution, device)
        targets, shots = [1000, 10000, 100000, 1000000], args.shots
    print(machine(device), flush=True)
    if args.convergence_only:
        lines = [*convergence(CONVERGENCE_SCENES, CONVERGENCE_TARGETS, device), "", *converged_adaptive(device)]
        args.out.write_text("\n".join(["# Convergence", "", f"Made by `python scripts/bench.py --convergence-only` "
                                        f"on: {machine(device)}.", "", *lines, ""]))
        print(f"\nwrote {args.out}")
        return
    run, adaptive_lines = adaptive(*adaptive_args, repeat=1 if args.quick else max(args.repeat, 1))
    print("\n".join(adaptive_lines), "\n", flush=True)
    profile_lines = profile(*adaptive_args) if args.profile else []
    profile_lines += ["", *operator_counts(*adaptive_args)]
    print("\n".join(profile_lines), "\n", flush=True)
    rows, scaling_lines = scaling(targets, shots, adaptive_args[2], device)
    convergence_lines = (convergence(("floating",), (5e-2,), device) if args.quick
                         else convergence(CONVERGENCE_SCENES, CONVERGENCE_TARGETS, device))
    if not args.quick:
        convergence_lines += ["", *converged_adaptive(device)]
    command = "python scripts/bench.py" + (f" --device {args.device}" if device.type == "cuda" else "")
    text = ["# Benchmark", "", f"Made by `{command}` on: {machine(device)}.", "",
            *adaptive_lines, "", *profile_lines, "", *scaling_lines, "", *convergence_lines, ""]
    args.out.write_text("\n".join(text))
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
