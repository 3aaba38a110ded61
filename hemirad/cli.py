"""``python -m hemirad scene.yaml``: solve a scene and write its image, mesh and stats."""
from __future__ import annotations

import argparse
import shlex
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

from hemirad.core.device import DEVICES, DEVICE_NAMES, is_device_name
from hemirad.core.errors import HemiradInputError, HemiradWarning
from hemirad.geometry.patterns import PATTERN_CHOICES, describe_patterns
from hemirad.lighting.gathered import GatherReport
from hemirad.scene.loader import MAX_SURFACE_NAME, MAX_TRIANGLES, bundled_scenes, load_scene
from hemirad.scene.model import (CRITERION_NAMES, FINAL_GATHER_CHOICES, IMPORTANCE_CHOICES, RECONSTRUCTION_CHOICES,
                                 SMALL_RECEIVER_CHOICES)
from hemirad.scene.options import MAX_CACHE_MB, MAX_ROUND_GROWTH
from hemirad.scene.sensorfile import read_sensor_file


def _number(text: str, kind=float):
    """``kind(text)``, or the one-line complaint argparse shows (its own names the function)."""
    try:
        return kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, "
                                         f"got {text!r}") from None


def _positive_int(text: str) -> int:
    value = _number(text, int)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text}")
    return value


def _non_negative_int(text: str) -> int:
    value = _number(text, int)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text}")
    return value


def _depth(text: str) -> int:
    value = _number(text, int)
    if not 0 <= value <= 16:
        raise argparse.ArgumentTypeError(f"expected an integer from 0 to 16, got {text}")
    return value


def _element_budget(text: str) -> int:
    value = _positive_int(text)
    if value > MAX_TRIANGLES:
        raise argparse.ArgumentTypeError(f"expected at most {MAX_TRIANGLES:,} elements, got {text}")
    return value


def _resolution(text: str) -> int:
    value = _positive_int(text)
    if value < 8 or value % 2:
        raise argparse.ArgumentTypeError(f"expected an even integer >= 8, got {text}")
    return value


def _reflector_resolution(text: str) -> int | str:
    return text if text == "auto" else _resolution(text)


def _patch_size(text: str) -> float | str:
    if text in ("auto", "none"):
        return text
    return _positive_float(text)


def _surface_name(text: str) -> str:
    if not 0 < len(text) <= MAX_SURFACE_NAME:
        raise argparse.ArgumentTypeError(f"expected a surface name of 1 to {MAX_SURFACE_NAME} characters")
    return text


def _device(text: str) -> str:
    if not is_device_name(text):
        raise argparse.ArgumentTypeError(f"expected one of {', '.join(DEVICE_NAMES)}, got {text!r}")
    return text


def _positive_float(text: str) -> float:
    value = _number(text)
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text}")
    return value


def _megabytes(text: str) -> float:
    value = _number(text)
    if not 0.0 <= value <= MAX_CACHE_MB:
        raise argparse.ArgumentTypeError(f"expected a number of megabytes from 0 to 1e7, got {text}")
    return value


def _round_growth(text: str) -> float:
    value = _number(text)
    if not 1.0 < value <= MAX_ROUND_GROWTH:
        raise argparse.ArgumentTypeError(f"expected a number above 1 and at most {MAX_ROUND_GROWTH:g}, got {text}")
    return value


def _fraction(text: str) -> float:
    value = _number(text)
    if not 0.0 <= value < 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1), got {text}")
    return value


class _Parser(argparse.ArgumentParser):
    """Reports a bad command line as one paragraph, like every other input error, exit code 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message}. See '{self.prog} --help'.\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="hemirad",
        description="Solve a scene by progressive-refinement radiosity and write image.png, image.exr "
                    "(linear radiance), luminance.png (false colour), mesh.png, mesh.ply and mesh.glb "
                    "(per-vertex colour and radiosity) and stats.json.")
    parser.add_argument("scene", help="a scene file (YAML) or the name of a bundled scene "
                                      f"({', '.join(bundled_scenes())})")
    parser.add_argument("-o", "--output", type=Path,
                        help="output folder (default: <scene name>_out in the current folder)")
    parser.add_argument("--shots", type=_positive_int, help="stop after this many shots (solver.max_shots)")
    parser.add_argument("--unshot-fraction", type=_fraction,
                        help="stop when unshot / emitted power falls below this (solver.unshot_fraction)")
    parser.add_argument("--resolution", type=_resolution, help="hemicube resolution (solver.resolution)")
    parser.add_argument("--reflector-resolution", type=_reflector_resolution, metavar="auto|N",
                        help="with patches, the hemicube resolution of nodes that emit nothing: auto (half "
                             "of --resolution, not under 128) or an even integer (solver.reflector_resolution)")
    parser.add_argument("--patch-size", type=_patch_size, metavar="auto|none|SIZE",
                        help="patches that shoot for their elements: auto (about 2 x 2 elements), a side "
                             "length, or none: every element shoots, as in the paper (solver.patch_size)")
    parser.add_argument("--sensors", type=Path, metavar="FILE",
                        help="also read the irradiance and illuminance at the sensors of FILE, a CSV of lines "
                             "x,y,z,nx,ny,nz[,name] (a header line and # comments allowed); writes OUT/sensors.csv")
    parser.add_argument("--small-receivers", choices=SMALL_RECEIVER_CHOICES,
                        help="form factors of receivers that cover few hemicube pixels: lamps, Lambert's closed "
                             "form times the visibility the hemicube finds in the lamps' shots; closed_form, that "
                             "and in every shot for receivers under a pixel; pixels, their pixels' sum as in the "
                             "paper; auto (the default), closed_form when refining, else lamps "
                             "(solver.small_receivers)")
    parser.add_argument("--reconstruction", choices=RECONSTRUCTION_CHOICES,
                        help="how element values reach the vertices that shading and exports interpolate: "
                             "quadratic (the default), a quadratic fitted around each vertex; mean, the "
                             "area-weighted mean of its elements, as in the paper (solver.reconstruction)")
    parser.add_argument("--final-gather", choices=FINAL_GATHER_CHOICES,
                        help="once the solve ends, give elements the light a hemicube at their centroid gathers: "
                             "contacts, those beside what stands on or hangs under a surface (where the shots' "
                             "patches see past its edges); all, every element (one hemicube each); none (the "
                             "default) (solver.final_gather)")
    parser.add_argument("--cache-mb", type=_megabytes, metavar="MB",
                        help="memory for the form-factor rows and the light kept between sweeps; a solve that "
                             "outgrows it goes on one patch at a time, which can take many times longer "
                             "(solver.cache_mb, default 256)")
    parser.add_argument("--error-samples", type=_non_negative_int, metavar="N",
                        help="points at which the solution checks its own error by final gathers "
                             "(stats.json's estimated_error; 0: none; solver.error_samples, default 1000)")
    parser.add_argument("--picture-error-samples", type=_non_negative_int, metavar="N",
                        help="points the camera's pixels see at which the picture's error is estimated "
                             "the same way (stats.json's estimated_picture_error; solver.picture_error_samples, "
                             "default 0: none)")
    parser.add_argument("--device", type=_device,
                        help="where the solve runs (solver.device): " +
                             "; ".join(f"{name}, {meaning}" for name, meaning in DEVICES.items()))
    refine = parser.add_argument_group("adaptive meshing (override the scene's refine block)")
    refine.add_argument("--refine", choices=PATTERN_CHOICES, help=f"split pattern: {describe_patterns()}")
    refine.add_argument("--criterion", choices=CRITERION_NAMES,
                        help="what decides a split: answer, between converged solves where the solution's "
                             "estimated error is largest; a per-shot criterion (gradient: the paper's eq. 7); "
                             "auto (the default): answer with patches, gradient when every element shoots")
    refine.add_argument("--threshold", type=_positive_float,
                        help="split when the criterion's radiosity variation (luminance) exceeds this")
    scale = refine.add_mutually_exclusive_group()
    scale.add_argument("--relative", dest="relative", action="store_true", default=None,
                       help="the threshold is a fraction of the brightest emitter's radiosity (default)")
    scale.add_argument("--absolute", dest="relative", action="store_false",
                       help="the threshold is in radiosity units")
    refine.add_argument("--max-depth", type=_depth, help="splits of one initial element, at most (0 to 16)")
    refine.add_argument("--max-elements", type=_element_budget, help="element budget")
    refine.add_argument("--refine-shots", type=_positive_int, metavar="N",
                        help="refine during the first N shots, then shoot on the mesh they made (refine.shots)")
    refine.add_argument("--tolerance", type=_fraction, metavar="E",
                        help="criterion answer: refine until the estimated relative RMS error is below E "
                             "(refine.tolerance, default 0.01)")
    refine.add_argument("--rounds", type=_depth, metavar="N",
                        help="criterion answer: at most N refinements between converged solves (refine.rounds)")
    refine.add_argument("--round-growth", type=_round_growth, metavar="G",
                        help="criterion answer: the most one refinement may grow the elements; smaller rounds "
                             "cost more solves and find more of what a coarse solve cannot see "
                             "(refine.round_growth, default 5.5)")
    refine.add_argument("--importance", choices=IMPORTANCE_CHOICES,
                        help="criterion answer: weigh an element's error by how much of the camera's picture it "
                             "fills (camera) or by its area alone (surfaces); auto: camera unless the scene has "
                             "sensors or grids (refine.importance)")
    pictures = parser.add_argument_group("pictures")
    pictures.add_argument("--falsecolour", action="append", type=_surface_name, metavar="SURFACE",
                          help="also write falsecolour_SURFACE.png, the light falling on that surface (e.g. "
                               "room.floor) as a false-colour map in lux; repeat for more surfaces "
                               "(replaces the scene's falsecolour list)")
    runs = parser.add_argument_group("long runs")
    runs.add_argument("--checkpoint-every", type=_non_negative_int, default=0, metavar="N",
                      help="write OUT/checkpoint.pt after every N shots, and when the run ends (default 0: never)")
    runs.add_argument("--resume", action="store_true",
                      help="continue the run whose OUT/checkpoint.pt is there (same scene and options; "
                           "--shots may be raised), with the same result as a run never stopped")
    parser.add_argument("-q", "--quiet", action="store_true", help="print nothing but warnings and errors")
    return parser


def _show_warning(message, category, filename, lineno, file=None, line=None):
    if issubclass(category, HemiradWarning):
        print(f"hemirad: warning: {message}", file=sys.stderr)
    else:
        print(warnings.formatwarning(message, category, filename, lineno, line), file=sys.stderr, end="")


class _Progress:
    """A progress bar of shots with the unshot fraction and element count beside it.

    The header and bar appear at the first shot, so an error found before solving (a
    checkpoint that does not fit) is printed alone, and a resumed run's bar starts where
    the checkpoint left off.
    """

    def __init__(self, total: int, quiet: bool, header: str = ""):
        self.total, self.quiet, self.header, self.bar = total, quiet, header, None

    def __call__(self, report) -> None:
        if self.quiet:
            return
        if isinstance(report, GatherReport):  # the solve is done: the final gathers' own bar
            if self.bar is not None and self.bar.unit == "shot":
                self.close()
            if self.bar is None:
                self._open(report.elements, 0, "gather", desc="final gathers")
            self.bar.update(report.gathered - self.bar.n)
            return
        if self.bar is None:
            if self.header:
                print(self.header, file=sys.stderr)
            self._open(self.total, report.shots - 1, "shot")
        self.bar.update(report.shots - self.bar.n)
        self.bar.set_postfix(unshot=f"{report.unshot_fraction:.2e}", elements=report.elements, refresh=False)

    def _open(self, total: int, initial: int, unit: str, **options) -> None:
        from tqdm import tqdm

        self.bar = tqdm(total=total, initial=initial, unit=unit, file=sys.stderr, dynamic_ncols=True, **options)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def run(args: argparse.Namespace, argv: list[str] | None = None) -> int:
    """Solve and write as ``args`` say; ``argv`` (the command line) is echoed in the resume hint."""
    from hemirad.pipeline import output_lock, output_names

    say = (lambda *a: None) if args.quiet else (lambda *a: print(*a, file=sys.stderr))
    scene = load_scene(args.scene)
    solver_options = {"max_shots": ("--shots", args.shots), "unshot_fraction": ("--unshot-fraction",
                      args.unshot_fraction), "resolution": ("--resolution", args.resolution),
                      "reflector_resolution": ("--reflector-resolution", args.reflector_resolution),
                      "device": ("--device", args.device), "patch_size": ("--patch-size", args.patch_size),
                      "small_receivers": ("--small-receivers", args.small_receivers),
                      "reconstruction": ("--reconstruction", args.reconstruction),
                      "final_gather": ("--final-gather", args.final_gather),
                      "cache_mb": ("--cache-mb", args.cache_mb),
                      "error_samples": ("--error-samples", args.error_samples),
                      "picture_error_samples": ("--picture-error-samples", args.picture_error_samples)}
    refine_options = {"pattern": ("--refine", args.refine), "criterion": ("--criterion", args.criterion),
                      "threshold": ("--threshold", args.threshold),
                      "relative": ("--relative" if args.relative else "--absolute", args.relative),
                      "max_depth": ("--max-depth", args.max_depth), "max_elements": ("--max-elements", args.max_elements),
                      "shots": ("--refine-shots", args.refine_shots), "tolerance": ("--tolerance", args.tolerance),
                      "rounds": ("--rounds", args.rounds), "round_growth": ("--round-growth", args.round_growth),
                      "importance": ("--importance", args.importance)}
    for block, options in (("solver", solver_options), ("refine", refine_options)):
        given = {k: v for k, (_, v) in options.items() if v is not None}
        setattr(scene, block, replace(getattr(scene, block), **given))
        scene.command_line.update({f"{block}.{k}": options[k][0] for k in given})
    if args.falsecolour:
        scene.falsecolour = list(args.falsecolour)
        scene.command_line.update({f"falsecolour[{i}]": "--falsecolour" for i in range(len(args.falsecolour))})
    if args.sensors is not None:
        scene.sensors += read_sensor_file(args.sensors, {s.name for s in scene.sensors}, len(scene.sensors))
    name = scene.source.stem if scene.source else str(args.scene)
    # Held until the outputs are written: checked (and a second run refused) before solving, not after.
    with output_lock(args.output or Path(f"{name}_out"), output_names(scene)) as output:
        return _solve_and_write(args, argv, scene, output, say)


def _solve_and_write(args: argparse.Namespace, argv: list[str] | None, scene, output: Path, say) -> int:
    from hemirad import checkpoint as checkpoints
    from hemirad.pipeline import solve

    checkpoint = output / checkpoints.FILENAME if (args.checkpoint_every or args.resume) else None
    # Printed with the first shot: errors found while setting up then stay a single paragraph.
    header = (f"hemirad: solving {scene.source or args.scene} (up to {scene.solver.max_shots} shots, "
              f"stop below {scene.solver.unshot_fraction:g} unshot, hemicube {scene.solver.resolution})")
    progress = _Progress(scene.solver.max_shots, args.quiet, header)
    start = time.perf_counter()
    try:
        result = solve(scene, progress=progress, checkpoint=checkpoint, checkpoint_every=args.checkpoint_every,
                       resume=args.resume)
    except KeyboardInterrupt:
        progress.close()  # before the message, so the bar does not overwrite it
        print(_interrupted(checkpoint, argv), file=sys.stderr)
        return 130
    finally:
        progress.close()
    paths = result.write(output)
    if checkpoint is not None:
        paths["checkpoint"] = checkpoint
    stats = result.stats
    resumed = f" (resumed at shot {stats['resumed_from_shot']})" if stats.get("resumed_from_shot") is not None else ""
    estimate = stats.get("estimated_error")
    estimate = (f", estimated error {estimate:.1%} +- {stats['estimated_error_standard_error']:.1%}"
                if estimate is not None else "")
    if stats.get("estimated_picture_error") is not None:
        estimate += (f" (the picture's {stats['estimated_picture_error']:.1%} +- "
                     f"{stats['estimated_picture_error_standard_error']:.1%})")
    if "final_gather" in stats:
        estimate += f", {stats['final_gather']['elements']} elements finished by final gathers"
    say(f"hemirad: {stats['elements']} elements, {stats['shots']} shots{resumed}, unshot fraction "
        f"{stats['unshot_fraction']:.3g}{estimate}, {time.perf_counter() - start:.1f} s")
    for kind, path in paths.items():
        say(f"  {kind:10s} {path}")
    for line in lighting_table(result):
        say(line)
    return 0


def lighting_table(result) -> list[str]:
    """The lines printed after a run for its sensors and grids: illuminance in lux, and
    each grid's EN 12464-1 figures (mean, minimum, maximum, the two uniformities)."""
    def ratio(x) -> str:
        return "-" if x is None else f"{x:.2f}"

    lines = []
    if result.sensors is not None:
        width = max(6, *(len(n) for n in result.sensors.names))
        lines += ["sensors:", f"  {'name':{width}s} {'lux':>10s}"]
        lines += [f"  {name:{width}s} {lux:10.4g}" for name, lux in zip(result.sensors.names,
                                                                         result.sensors.lux.tolist())]
    if result.grids:
        width = max(4, *(len(n) for n in result.grids))
        lines += ["grids (lux):", f"  {'grid':{width}s} {'points':>9s} {'spacing':>9s} {'Em':>9s} {'Emin':>9s} "
                                  f"{'Emax':>9s} {'U0':>5s} {'Emin/Emax':>9s}"]
        for name, grid in result.grids.items():
            st, (rows, columns) = grid.statistics, grid.layout.shape
            lines.append(f"  {name:{width}s} {f'{columns}x{rows}':>9s} {grid.layout.spacing:9.3g} {st['Em']:9.4g} "
                         f"{st['Emin']:9.4g} {st['Emax']:9.4g} {ratio(st['U0']):>5s} {ratio(st['Emin_Emax']):>9s}")
    return lines


def _interrupted(checkpoint: Path | None, argv: list[str] | None) -> str:
    """What Ctrl-C leaves behind and, when there is a checkpoint, the command that continues."""
    from hemirad import checkpoint as checkpoints

    shots = checkpoints.saved_shots(checkpoint) if checkpoint is not None else None
    if shots is None:
        return "hemirad: interrupted; nothing was saved (--checkpoint-every N makes a long run resumable)."
    args = list(sys.argv[1:] if argv is None else argv)
    if "--resume" not in args:
        args.append("--resume")
    return (f"hemirad: interrupted; {checkpoint} holds the run up to shot {shots}. "
            f"Continue it with: hemirad {shlex.join(args)}")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    warnings.showwarning = _show_warning
    try:
        return run(args, argv)
    except HemiradInputError as exc:
        print(f"hemirad: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("hemirad: interrupted", file=sys.stderr)
        return 130
