"""Render the path-traced references the accuracy tests compare against (needs Mitsuba 3).

    python scripts/make_references.py [--scenes cornell_box floating] [--spp 32768]
                                      [--height 128] [--variant llvm_ad_rgb] [--out tests/references]
    python scripts/make_references.py --scenes office_lighting --scaled-from office

For every bundled scene (default) it renders the scene's own initial mesh with Mitsuba's
path tracer (see ``hemirad.reference``) at the scene camera's aspect, ``--height`` pixels
high, and writes ``<scene>.npz`` (float16 linear radiance) and ``<scene>.json`` (how it was
made). The samples are rendered as two independent halves; the reference is their mean, and
their difference measures its own noise:

    E|a - b|^2 = 2 var(half)  and  var(mean) = var(half) / 2,  so
    relative MSE of the reference ~ relative_mse(a, b) / 4, mean relative error ~ MRE(a, b) / 2

(Gaussian noise: E|N(0, s^2 / 2)| = E|N(0, 2 s^2)| / 2). Those, and the SSIM between the
halves, are stored with the reference, over the same surface pixels the tests use.

``--scaled-from OTHER`` makes a scene's reference from OTHER's without rendering, where
the two differ only in how much light they emit: the same mesh, camera and reflectances,
and every emission OTHER's times one factor k. Light transport is linear in the emitted
light, and the path tracer's random choices (Russian roulette on the path throughput) do
not depend on it, so the rendering would be k times OTHER's, sample for sample, noise
included; the JSON says it was derived so.

Mitsuba is optional: ``pip install 'hemirad[reference]'``. The LLVM variant is used when
it runs (on Debian it needs the package libllvm19), the scalar one otherwise (10-30x slower).
This script never opens an OpenGL context: Mesa's llvmpipe and Dr.Jit load different LLVMs.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

import hemirad
from hemirad.evaluation import metrics, reference
from hemirad.lighting.photometry import emission_table
from hemirad.scene.meshing import build_mesh

ROOT = Path(__file__).resolve().parent.parent


def surface_pixels_from_reference(radiance: np.ndarray, emission_radiance: float) -> np.ndarray:
    """(H, W) bool: ``metrics.surface_mask`` estimated from the image alone (this script
    opens no rasteriser): a pixel is on geometry when it is not black (there is no
    environment light), and an emitter when it is at least half the dimmest emitter's
    radiance. Used only for the noise estimate; the tests use exact coverage."""
    lum = metrics.luminance(radiance)
    return metrics.surface_mask((lum > 0).astype(np.float32), (lum >= 0.5 * emission_radiance).astype(np.float32))


def make(name: str, spp: int, height: int, out: Path, seed: int, variant: str) -> dict:
    scene = hemirad.load_scene(name)
    mesh = build_mesh(scene)
    camera = reference.reference_camera(scene.camera, height)
    start = time.perf_counter()
    halves = []
    for half in range(2):
        def progress(done, half=half):
            print(f"\r  {name}: half {half + 1}/2, {done}/{spp // 2} spp", end="", file=sys.stderr, flush=True)
        halves.append(reference.render_reference(scene, camera, spp // 2, seed=2 * seed + half,
                                                 mesh=mesh, progress=progress))
    seconds = time.perf_counter() - start
    print(file=sys.stderr)
    a, b = halves
    mean = 0.5 * (a + b)

    emitted = emission_table(scene, mesh).numpy()  # a flux made an exitance
    dimmest = min(float(metrics.luminance(e)) for e in emitted if e.max() > 0) / np.pi
    mask = surface_pixels_from_reference(mean, dimmest)
    noise = {
        "relative_mse": metrics.relative_mse(a, b, mask) / 4.0,
        # |mean - a| = |a - b| / 2 exactly: the MRE(a, b) / 2 estimate, relative to the mean.
        "mean_relative_error": metrics.mean_relative_error(mean, a, mask),
        "ssim_between_halves": metrics.ssim(a, b, mask, metrics.reference_exposure(mean, mask)),
    }
    info = {
        "scene": name,
        "units": "linear RGB radiance; a hemirad radiosity B compares as B / pi",
        "camera": {"position": list(camera.position), "look_at": list(camera.look_at), "up": list(camera.up),
                   "fov": camera.fov, "width": camera.width, "height": camera.height},
        "renderer": {"mitsuba": _mitsuba_version(), "variant": variant, "integrator": "path",
                     "max_depth": "unlimited (Russian roulette)", "rfilter": "box", "sampler": "independent"},
        "spp": spp,
        "seeds": [2 * seed, 2 * seed + 1],
        "seconds": round(seconds, 1),
        "noise": {k: float(f"{v:.4g}") for k, v in noise.items()},
        "geometry": reference.geometry_summary(scene),
    }
    paths = reference.Reference(mean, info).save(out, name)
    sizes = ", ".join(f"{p.name} {p.stat().st_size / 1024:.0f} KB" for p in paths)
    print(f"{name}: {camera.width} x {camera.height}, {spp} spp in {seconds:.0f} s; noise {info['noise']}; {sizes}")
    return info


def scaled(name: str, source: str, out: Path) -> dict:
    """Write the reference of scene ``name`` as ``source``'s times the one factor between
    their emissions (see the module's docstring); SystemExit when they differ otherwise."""
    scene, other = hemirad.load_scene(name), hemirad.load_scene(source)
    mesh, other_mesh = build_mesh(scene), build_mesh(other)
    same_mesh = all(torch.equal(getattr(mesh, k), getattr(other_mesh, k)) for k in ("vertices", "triangles", "material"))
    if not (same_mesh and scene.camera == other.camera and
            [m.reflectance for m in scene.materials] == [m.reflectance for m in other.materials]):
        raise SystemExit(f"{name} and {source} differ in more than their emissions: render {name} instead")
    mine, theirs = emission_table(scene, mesh), emission_table(other, other_mesh)
    factor = float(mine.max() / theirs.max())
    if not torch.allclose(mine, theirs * factor, rtol=1e-12, atol=0.0):
        raise SystemExit(f"{name}'s emissions are not {source}'s times one factor: render {name} instead")
    ref = reference.Reference.load(out, source)
    info = {**ref.info, "scene": name, "geometry": reference.geometry_summary(scene),
            "derived": {"from": source, "factor": factor,
                        "how": f"{source}'s radiance times the factor: the scenes differ only in their "
                               f"emissions, all in this ratio, and light transport is linear in them"}}
    paths = reference.Reference(ref.radiance * np.float32(factor), info).save(out, name)
    print(f"{name}: {source}'s reference times {factor:.6g}; {', '.join(p.name for p in paths)}")
    return info


def _mitsuba_version() -> str:
    import mitsuba
    return mitsuba.__version__


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", default=None, help="default: every bundled scene")
    parser.add_argument("--spp", type=int, default=32768, help="samples per pixel in all (two halves)")
    parser.add_argument("--height", type=int, default=reference.REFERENCE_HEIGHT)
    parser.add_argument("--variant", default=None, help="a Mitsuba variant; default the fastest that runs")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=ROOT / "tests" / "references")
    parser.add_argument("--scaled-from", metavar="OTHER",
                        help="derive the scenes' references from OTHER's, which differs only in its emissions")
    args = parser.parse_args(argv)
    if args.scaled_from:
        for name in args.scenes or []:
            scaled(name, args.scaled_from, args.out)
        return 0
    torch.set_num_threads(1)  # Dr.Jit uses the cores; torch only meshes here
    variant = reference.select_variant(args.variant)
    for name in args.scenes or hemirad.bundled_scenes():
        make(name, args.spp, args.height, args.out, args.seed, variant)
    return 0


if __name__ == "__main__":
    sys.exit(main())
