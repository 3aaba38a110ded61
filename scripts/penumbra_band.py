"""The floating rectangle's penumbra on the floor, pixel by pixel against the path-traced
reference: the finest uniform mesh of the accuracy study against refinement judged on the
answer. For reading, never for asserting.

    python scripts/penumbra_band.py [--grid 80] [--out figures/penumbra_band.md]

The band: the points of a grid over the floor that see between ``BAND`` of the lamp's
unoccluded form factor (hemicubes at the points of the unrefined scene); each is compared
at its reference pixel where the camera sees it and the pixel shows only floor
(``evaluation.pixels``). Prints, per run, the largest, 90th-percentile and median relative
error there, the share within 3% (the goal: all of them), and the mean (a bias).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

import hemirad
from hemirad.evaluation.penumbra import floor_penumbra
from hemirad.evaluation.pixels import errors_at_points
from hemirad.evaluation.reference import Reference

REFERENCES = Path(__file__).resolve().parent.parent / "tests" / "references"
#: The visible share of the lamp that makes a floor point part of the penumbra band.
BAND = (0.05, 0.95)
#: (label, element-size factor, rounds of the answer (0: none), element budget)
RUNS = (("uniform x0.5 (the study's finest)", 0.5, 0, None),
        ("answer from x1, three rounds toward 44,000 elements", 1.0, 3, 44_000),
        ("answer from x2 to 3,426 elements (a third of the finest's)", 2.0, 8, 3426))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--grid", type=int, default=80, help="grid points along each side of the floor")
    parser.add_argument("--out", type=Path, default=Path("figures/penumbra_band.md"))
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    shipped = hemirad.load_scene("floating")
    grid_points, inside, floor = floor_penumbra(shipped, args.grid, BAND)
    points = grid_points[inside].numpy()
    reference = Reference.load(REFERENCES, "floating")
    lines = ["# The floating rectangle's penumbra, pixel by pixel", "",
             f"Made by `python scripts/penumbra_band.py --grid {args.grid}`: {len(points)} floor points seeing "
             f"{BAND[0]:.0%}-{BAND[1]:.0%} of the lamp, each at its reference pixel where that shows only floor; "
             "every run converged to 1e-3 unshot power, small receivers as `auto` makes them (`lamps` uniform, `closed_form` refined). Relative error of "
             "the displayed radiance against the path tracer.", "",
             "| run | elements | seconds | pixels | largest | 90th percentile | median | within 3% | mean |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for label, factor, rounds, budget in RUNS:
        scene = shipped.with_element_sizes_scaled(factor)
        scene.solver.unshot_fraction = 1e-3
        if rounds:
            scene.refine.pattern, scene.refine.criterion = "pattern2", "answer"
            scene.refine.rounds, scene.refine.tolerance = rounds, 0.0
            if budget is not None:
                scene.refine.max_elements = budget
        start = time.perf_counter()
        result = hemirad.solve(scene, progress=None)
        seconds = time.perf_counter() - start
        error = errors_at_points(result, points, floor, reference)
        size = np.abs(error)
        lines.append(f"| {label} | {result.mesh.num_elements} | {seconds:.1f} | {len(error)} | {size.max():.1%} | "
                     f"{np.percentile(size, 90):.1%} | {np.median(size):.1%} | {(size <= 0.03).mean():.1%} | "
                     f"{error.mean():+.1%} |")
        print(lines[-1], flush=True)
    args.out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
