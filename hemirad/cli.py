"""``python -m hemirad scene.yaml``: solve a scene and write its image, mesh and stats."""
from __future__ import annotations

import argparse
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

from .errors import HemiradInputError, HemiradWarning


def _positive_int(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text}")
    return value


def _resolution(text: str) -> int:
    value = _positive_int(text)
    if value < 8 or value % 2:
        raise argparse.ArgumentTypeError(f"expected an even integer >= 8, got {text}")
    return value


def _positive_float(text: str) -> float:
    value = float(text)
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text}")
    return value


def _fraction(text: str) -> float:
    value = float(text)
    if not 0.0 <= value < 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1), got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hemirad",
        description="Solve a scene by progressive-refinement radiosity and write image.png, "
                    "mesh.ply (per-vertex radiosity) and stats.json.")
    parser.add_argument("scene", help="a scene file (YAML) or the name of a bundled scene "
                                      "(cornell_box, floating)")
    parser.add_argument("-o", "--output", type=Path,
                        help="output folder (default: <scene name>_out in the current folder)")
    parser.add_argument("--shots", type=_positive_int, help="stop after this many shots (solver.max_shots)")
    parser.add_argument("--unshot-fraction", type=_fraction,
                        help="stop when unshot / emitted power falls below this (solver.unshot_fraction)")
    parser.add_argument("--resolution", type=_resolution, help="hemicube resolution (solver.resolution)")
    refine = parser.add_argument_group("adaptive meshing (override the scene's refine block)")
    refine.add_argument("--refine", choices=("none", "pattern1", "pattern2"),
                        help="split pattern: pattern1 (centroid, 1 -> 3), pattern2 (edge midpoints, 1 -> 4)")
    refine.add_argument("--criterion", choices=("gradient", "receiver", "partial_visibility",
                                                "neighbor_difference", "uniform"),
                        help="what decides a split (default gradient, the paper's eq. 7)")
    refine.add_argument("--threshold", type=_positive_float,
                        help="split when the criterion's radiosity variation (luminance) exceeds this")
    scale = refine.add_mutually_exclusive_group()
    scale.add_argument("--relative", dest="relative", action="store_true", default=None,
                       help="the threshold is a fraction of the brightest emitter's radiosity (default)")
    scale.add_argument("--absolute", dest="relative", action="store_false",
                       help="the threshold is in radiosity units")
    refine.add_argument("--max-depth", type=_positive_int, help="splits of one initial element, at most")
    refine.add_argument("--max-elements", type=_positive_int, help="element budget")
    parser.add_argument("-q", "--quiet", action="store_true", help="print nothing but warnings and errors")
    return parser


def _show_warning(message, category, filename, lineno, file=None, line=None):
    if issubclass(category, HemiradWarning):
        print(f"hemirad: warning: {message}", file=sys.stderr)
    else:
        print(warnings.formatwarning(message, category, filename, lineno, line), file=sys.stderr, end="")


class _Progress:
    """A progress bar of shots with the unshot fraction and element count beside it."""

    def __init__(self, total: int, quiet: bool):
        self.bar = None
        if not quiet:
            from tqdm import tqdm
            self.bar = tqdm(total=total, unit="shot", file=sys.stderr, dynamic_ncols=True)

    def __call__(self, report) -> None:
        if self.bar is not None:
            self.bar.update(report.shots - self.bar.n)
            self.bar.set_postfix(unshot=f"{report.unshot_fraction:.2e}", elements=report.elements, refresh=False)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def run(args: argparse.Namespace) -> int:
    from .loader import load_scene
    from .pipeline import prepare_output_folder, solve

    say = (lambda *a: None) if args.quiet else (lambda *a: print(*a, file=sys.stderr))
    scene = load_scene(args.scene)
    overrides = {"max_shots": args.shots, "unshot_fraction": args.unshot_fraction, "resolution": args.resolution}
    scene.solver = replace(scene.solver, **{k: v for k, v in overrides.items() if v is not None})
    overrides = {"pattern": args.refine, "criterion": args.criterion, "threshold": args.threshold,
                 "relative": args.relative, "max_depth": args.max_depth, "max_elements": args.max_elements}
    scene.refine = replace(scene.refine, **{k: v for k, v in overrides.items() if v is not None})
    name = scene.source.stem if scene.source else str(args.scene)
    output = prepare_output_folder(args.output or Path(f"{name}_out"))  # fail before solving, not after
    say(f"hemirad: solving {scene.source or args.scene} (up to {scene.solver.max_shots} shots, "
        f"stop below {scene.solver.unshot_fraction:g} unshot, hemicube {scene.solver.resolution})")
    progress = _Progress(scene.solver.max_shots, args.quiet)
    start = time.perf_counter()
    try:
        result = solve(scene, progress=progress)
    finally:
        progress.close()
    paths = result.write(output)
    stats = result.stats
    say(f"hemirad: {stats['elements']} elements, {stats['shots']} shots, unshot fraction "
        f"{stats['unshot_fraction']:.3g}, {time.perf_counter() - start:.1f} s")
    for kind, path in paths.items():
        say(f"  {kind:9s} {path}")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    warnings.showwarning = _show_warning
    try:
        return run(args)
    except HemiradInputError as exc:
        print(f"hemirad: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("hemirad: interrupted", file=sys.stderr)
        return 130
