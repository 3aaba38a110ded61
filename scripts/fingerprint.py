"""Fingerprints of the solves whose numbers a change to the code's structure must not move.

    python scripts/fingerprint.py [--quick] [-o fingerprints.json] [--check figures/fingerprints.json]

Runs, through the public API only (``hemirad.load_scene``, ``hemirad.solve``), the
benchmark's Fig. 6(c)-class solve and every run of the paper's figures (office, floating,
floating_coarse; unrefined, pattern 1, pattern 2; 100 shots, hemicube 128), and records for
each a SHA-256 of its final mesh (vertices, triangles, surfaces, materials, levels) and of
its radiosities (B, the displayed B, the per-vertex values the pictures draw, the stats'
power sums), bit for bit. ``--check`` compares
with a saved file and exits 1 naming each run that differs.

The hashes are of float64 bits: they are the same on machines of one kind (one CPU family,
one Mesa, one torch), not across kinds. Make the reference with the code before a change,
then check the code after it on the same machine. ``figures/fingerprints.json`` holds those
of the release that made it, on the machine ``figures/bench.md`` names. ``--quick`` runs
small versions (fewer shots, a smaller hemicube) in about a minute. A change that moves
these hashes on purpose bumps ``hemirad.transport.solver.ARITHMETIC`` (checkpoints of the
old numbers are then not resumed).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np

import hemirad

FIGURE_SCENES = ("office", "floating", "floating_coarse")
PATTERNS = ("none", "pattern1", "pattern2")


def runs(quick: bool) -> dict[str, dict]:
    """The solves, by name: scene and the solver and refine options each sets."""
    shots, resolution = (12, 32) if quick else (100, 128)
    out = {"bench": {"scene": "floating", "max_shots": shots, "resolution": 64 if quick else 256,
                     "pattern": "pattern2", "criterion": "gradient", "threshold": 1.35e-4, "max_depth": 4,
                     "max_elements": 200_000}}
    for name in FIGURE_SCENES:
        for pattern in PATTERNS:
            out[f"{name}/{pattern}"] = {"scene": name, "max_shots": shots, "resolution": resolution,
                                        "pattern": pattern, "criterion": "gradient", "threshold": 3e-4,
                                        "max_depth": 2 if quick else 4, "max_elements": 200_000}
    return out


def digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(np.asarray(a))
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def fingerprint(settings: dict) -> dict:
    scene = hemirad.load_scene(settings["scene"])
    if hasattr(scene.solver, "paper"):  # the paper's configuration: every element shoots
        scene.solver.paper()
    if hasattr(scene, "meshing"):  # the paper's meshes: every surface meshed on its own
        scene.meshing.contacts = False
    scene.solver.max_shots, scene.solver.unshot_fraction = settings["max_shots"], 0.0
    scene.solver.resolution = settings["resolution"]
    scene.solver.error_samples = 0  # the solve's seconds, as the benchmark's: no final gathers
    r = scene.refine
    r.pattern, r.criterion, r.threshold, r.relative = (settings["pattern"], settings["criterion"],
                                                       settings["threshold"], True)
    r.max_depth, r.max_elements = settings["max_depth"], settings["max_elements"]
    start = time.perf_counter()
    result = hemirad.solve(scene)
    seconds = time.perf_counter() - start
    m = result.mesh
    power = {k: result.stats[k] for k in ("emitted_power", "absorbed_power", "escaped_power") if k in result.stats}
    return {"elements": m.num_elements, "shots": result.stats["shots"],
            "mesh": digest(m.vertices, m.triangles, m.surface, m.material, m.level),
            "radiosity": digest(result.radiosity, result.display_radiosity, result.vertex_radiosity()),
            "power": hashlib.sha256(json.dumps(power, sort_keys=True).encode()).hexdigest(),
            "seconds": round(seconds, 1)}


def compare(found: dict, saved: dict) -> list[str]:
    differ = []
    for name, run in found.items():
        old = saved.get(name)
        if old is None:
            differ.append(f"{name}: not in the saved file")
            continue
        for key in ("elements", "shots", "mesh", "radiosity", "power"):
            if run[key] != old[key]:
                differ.append(f"{name}: {key} differs ({old[key]} -> {run[key]})")
    return differ


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small versions of the runs")
    parser.add_argument("-o", "--out", type=Path, help="write the fingerprints here (JSON)")
    parser.add_argument("--check", type=Path, help="compare with fingerprints saved earlier")
    parser.add_argument("--only", help="run only the runs whose name contains this")
    args = parser.parse_args(argv)
    found = {}
    for name, settings in runs(args.quick).items():
        if args.only and args.only not in name:
            continue
        found[name] = fingerprint(settings)
        print(f"{name}: {found[name]['elements']} elements, {found[name]['seconds']} s", file=sys.stderr, flush=True)
    if args.out:
        args.out.write_text(json.dumps({"quick": args.quick, "runs": found}, indent=2, sort_keys=True) + "\n")
    if args.check:
        saved = json.loads(args.check.read_text())
        if saved.get("quick") != args.quick:
            print(f"{args.check} was made {'with' if saved.get('quick') else 'without'} --quick", file=sys.stderr)
            return 1
        differ = compare(found, saved["runs"])
        print("\n".join(differ) if differ else f"all {len(found)} runs equal bit for bit", file=sys.stderr)
        return 1 if differ else 0
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
