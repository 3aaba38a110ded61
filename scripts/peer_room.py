"""A real scene measured against path-traced values at its surface points: time, peak memory
and error of a converged solve. For reading, never for asserting.

    python scripts/peer_room.py ROOM_DIR [--scene scene.yaml] [--points POINTS.npz]
        [--unshot-fraction 1e-3] [--patch-size auto] [--resolution N] [--rounds N]
        [--round-growth G] [--final-gather none|contacts|all] [--profile]

ROOM_DIR holds a scene in hemirad's format and an ``.npz`` of surface points (``points``,
``normals`` (N, 3), path-traced radiosity ``B`` (N, 3) and its standard error ``se``), such as
the furnished room of a public radiosity program that the project compares against (RRV's
room3, converted). Prints the solve's seconds, shots, hemicubes, patches, elements, peak
resident memory (and the part of it that importing torch alone takes), the power that
escaped through back faces, and the relative error of the luminance at the points (median,
90th percentile, largest, and the mean signed error: a bias), of the element values there and
of the picture as drawn (``Result.shading``: shaded inside the elements).
"""
from __future__ import annotations

import argparse
import cProfile
import pstats
import resource
from pathlib import Path

import numpy as np
import torch

RSS_AFTER_IMPORT_MB = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

import hemirad  # noqa: E402  (imported after the measurement above)
from hemirad.evaluation.metrics import luminance  # noqa: E402
from hemirad.evaluation.surface_points import elements_at  # noqa: E402
from hemirad.geometry.mesh import barycentric  # noqa: E402
from hemirad.scene.model import FINAL_GATHER_CHOICES  # noqa: E402


def measure(scene_path: Path, points_path: Path, args) -> dict:
    scene = hemirad.load_scene(scene_path)
    options = scene.solver
    options.unshot_fraction = args.unshot_fraction
    if args.patch_size is not None:
        options.patch_size = None if args.patch_size == "none" else (
            "auto" if args.patch_size == "auto" else float(args.patch_size))
    if args.resolution:
        options.resolution = args.resolution
    if args.final_gather:
        options.final_gather = args.final_gather
    if args.rounds:  # refinement judged on the answer (the default criterion with patches)
        scene.refine.pattern, scene.refine.rounds, scene.refine.tolerance = "pattern2", args.rounds, 0.0
        if args.round_growth:
            scene.refine.round_growth = args.round_growth
    torch.set_num_threads(1)
    profile = cProfile.Profile() if args.profile else None
    if profile:
        profile.enable()
    result = hemirad.solve(scene)
    if profile:
        profile.disable()
    stats = result.stats
    # the error estimate timed apart; the final gathers, where asked for, counted
    seconds = stats["seconds"]["mesh"] + stats["seconds"]["solve"] + stats["seconds"].get("final_gather", 0.0)
    data = np.load(points_path)
    points = torch.as_tensor(data["points"], dtype=torch.float64)
    normals = torch.as_tensor(data["normals"], dtype=torch.float64)
    where = elements_at(result.mesh, points, normals)
    found = (where >= 0).numpy()
    element = where[torch.as_tensor(found)]
    coordinates = barycentric(result.mesh.corners[element], points[torch.as_tensor(found)]).clamp(min=0)
    shown = result.shading().at(result.mesh, element, coordinates / coordinates.sum(1, keepdim=True))
    truth = luminance(data["B"][found])
    errors = {"element": luminance(result.radiosity.numpy()[element.numpy()]) / truth - 1,
              "shown": luminance(shown.numpy()) / truth - 1}
    emitted = float(sum(stats["emitted_power"]))
    report = {
        "seconds": seconds, "shots": stats["shots"], "hemicubes": stats["hemicubes_rendered"],
        "patches": stats["patches"], "elements": stats["elements"], "unshot": stats["unshot_fraction"],
        "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "import_mb": RSS_AFTER_IMPORT_MB, "escaped": float(sum(stats["escaped_power"])) / emitted,
        "points": int(found.sum()), "of": len(found), "estimated": stats["estimated_error"],
        "errors": {kind: {"median": float(np.median(np.abs(error))), "p90": float(np.percentile(np.abs(error), 90)),
                          "max": float(np.abs(error).max()), "bias": float(error.mean()),
                          "rms": float(np.sqrt(((error * truth) ** 2).sum() / (truth ** 2).sum()))}
                   for kind, error in errors.items()},
    }
    if profile:
        pstats.Stats(profile).sort_stats(args.sort).print_stats(40)
    return report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("room", type=Path, help="folder of the scene and its points")
    parser.add_argument("--scene", default=None, help="the scene file in ROOM (default: the one .yaml there)")
    parser.add_argument("--points", type=Path, default=None, help="the points (default: the one .npz beside ROOM)")
    parser.add_argument("--unshot-fraction", type=float, default=1e-3)
    parser.add_argument("--patch-size", default=None, help="auto, none or a side length (default: the scene's)")
    parser.add_argument("--resolution", type=int, default=None)
    parser.add_argument("--rounds", type=int, default=0,
                        help="refine by the answer this many rounds (pattern 2; default 0: the scene's mesh)")
    parser.add_argument("--round-growth", type=float, default=None,
                        help="with --rounds, the most a round may grow the mesh (default: the scene's refine.round_growth)")
    parser.add_argument("--final-gather", choices=FINAL_GATHER_CHOICES, default=None,
                        help="finish the solution by final gathers (solver.final_gather; default: the scene's)")
    parser.add_argument("--profile", action="store_true", help="print where the solve's time goes")
    parser.add_argument("--sort", default="tottime", help="the profile's order (pstats keys: tottime, cumulative, ...)")
    args = parser.parse_args()
    scene_path = args.room / args.scene if args.scene else next(iter(sorted(args.room.glob("*.yaml"))), None)
    points_path = args.points or next(iter(sorted(args.room.parent.glob("*.npz"))), None)
    if scene_path is None or not scene_path.is_file():
        parser.error(f"no scene file {scene_path or args.room / '*.yaml'}: ROOM is the folder of the scene "
                     f"(for RRV's room3, room3_hemirad), or name it with --scene")
    if points_path is None or not points_path.is_file():
        parser.error(f"no points file {points_path or args.room.parent / '*.npz'}: the .npz beside ROOM, or --points")
    r = measure(scene_path, points_path, args)
    print(f"{scene_path}: {r['elements']:,} elements, {r['patches']} patches")
    print(f"converged to {r['unshot']:.1e} unshot in {r['seconds']:.1f} s: {r['shots']:,} shots, "
          f"{r['hemicubes']:,} hemicubes; peak memory {r['peak_mb']:.0f} MB "
          f"({r['import_mb']:.0f} MB of it importing torch and numpy)")
    print(f"escaped through back faces: {100 * r['escaped']:.2f}% of the emitted power")
    for kind, label in (("element", "element values"), ("shown", "the picture as drawn")):
        e = r["errors"][kind]
        print(f"luminance error at {r['points']} of {r['of']} points, {label}: median {100 * e['median']:.1f}%, "
              f"90th percentile {100 * e['p90']:.1f}%, largest {100 * e['max']:.1f}%, mean {100 * e['bias']:+.1f}%; "
              f"relative RMS {100 * e['rms']:.1f}%")
    print(f"the run's own estimate over all its surfaces: {100 * r['estimated']:.1f}%")


if __name__ == "__main__":
    main()
