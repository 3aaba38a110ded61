"""The README's lighting-design example: the bundled office in lumens (a 6,000 lm panel, a
desk work plane and the room's working plane as EN 12464-1 grids, four sensors), solved
and written as a table (figures/lighting.md) and pictures (figures/lighting_*.png).

    python scripts/lighting_example.py [-o figures]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import hemirad
from hemirad.output import export

ROOT = Path(__file__).resolve().parent.parent


def table(result, seconds: float) -> str:
    stats = result.stats
    lines = ["| grid | points | spacing (m) | Em (lx) | Emin (lx) | Emax (lx) | U0 | Emin/Emax |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name, g in stats["grids"].items():
        lines.append(f"| {name} | {g['columns']} x {g['rows']} | {g['spacing_m']:.3f} | {g['Em']:.0f} | "
                     f"{g['Emin']:.0f} | {g['Emax']:.0f} | {g['U0']:.2f} | {g['Emin_Emax']:.2f} |")
    lines += ["", "| sensor | position (m) | normal | lux |", "|---|---|---|---:|"]
    s = result.sensors
    for name, point, normal, lux in zip(s.names, s.points.tolist(), s.normals.tolist(), s.lux.tolist()):
        lines.append(f"| {name} | {', '.join(f'{x:g}' for x in point)} | "
                     f"{', '.join(f'{x:g}' for x in normal)} | {lux:.0f} |")
    lines += ["", f"{stats['elements']} elements, {stats['shots']} shots, unshot fraction "
                  f"{stats['unshot_fraction']:.1e}, {seconds:.1f} s (solve, sensors and grids)."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", type=Path, default=ROOT / "figures")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    result = hemirad.solve(hemirad.load_scene("office_lighting"))
    seconds = time.perf_counter() - start
    args.output.mkdir(parents=True, exist_ok=True)
    (args.output / "lighting.md").write_text(table(result, seconds))
    for name, grid in result.grids.items():
        export.write_png(args.output / f"lighting_grid_{name}.png", result.grid_picture(grid))
    export.write_png(args.output / "lighting_floor.png", result.surface_falsecolour("room.floor"))
    export.write_png(args.output / "lighting_view.png", result.image())
    export.write_png(args.output / "lighting_luminance.png", result.luminance_image())
    print((args.output / "lighting.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
