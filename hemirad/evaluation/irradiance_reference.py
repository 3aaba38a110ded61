"""Irradiance at points computed by RADIANCE, the reference the sensors are tested against.

A reference is the scene's own initial mesh (``meshing.build_mesh``: the triangles the solver
starts from) written as RADIANCE polygons, and ``rtrace -I`` (irradiance at a point for a
given normal) run there with unbiased Monte Carlo settings (``RTRACE_OPTIONS``). RADIANCE is
an optional dependency, shipped by pyradiance (``pip install hemirad[reference]``); only
making a reference needs it, reading one does not.

Translation (``radiance_scene``):

* every triangle is a ``polygon`` with the same winding (RADIANCE's front, like hemirad's,
  is where the corners run counter-clockwise);
* a non-emitting material is ``plastic`` with its RGB reflectance, specularity 0 and
  roughness 0: a Lambertian reflector of exactly that reflectance;
* an emitting material is a ``light`` of radiance E / pi per channel (E the exitance), one
  source per triangle. RADIANCE's direct light from a source polygon is biased upward by
  about 3% of (size / distance)^2 (it subdivides a source into at most a few dozen parts):
  0.2% for a 0.25 triangle one unit away, 0.05% at 0.125, 0.004% at 0.0625, measured
  against Lambert's closed form. ``emitter_splits`` cuts each emitting triangle into
  4^emitter_splits pieces; each piece is one more source at every shading point, so the
  cost grows in proportion (16 times at 2 splits, hours for a reference), and the bundled
  scenes' emitter elements are small enough as they are: 30 mm at 128 mm or more from the
  Cornell points (at most 0.16%), 0.2 m at 1.1 m or more from the office's (0.1%).

What differs by construction:

* RADIANCE's ``light`` does not reflect; hemirad's emitters do (their ``reflectance``). The
  reference lacks the light an emitter reflects back into the scene; ``make_radiance_references.py``
  measures how much that is with hemirad's own solver.
* RADIANCE's ``plastic`` reflects on both sides, hemirad's elements on their front only.
  Only back faces a point can see matter, and in a closed scene none can be seen, except
  where a box's bottom lies on the floor face to face with it (the office's legs): there
  the two are coplanar and either one is a few square centimetres of the floor's colour or
  the leg's.

Units: ``rtrace -I`` gives irradiance (power per area), as hemirad's sensors do: a
surface j of radiosity B_j seen under the delta form factors F_j adds B_j F_j.
"""
from __future__ import annotations

import json
import math
import os
import re
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hemirad.core.errors import HemiradInputError
from hemirad.geometry.mesh import Mesh
from hemirad.scene.model import Scene

#: rtrace's settings, unbiased and converged (see the script for the noise they leave):
#: -aa 0 turns the irradiance cache off (every point gets its own hemisphere of
#: -ad samples, no interpolation bias); -ab 100 with Russian roulette (-lr 0, -lw 1e-6)
#: ends paths without truncating them; -u+ draws independent random samples, so the
#: repeated evaluations of one point are independent estimates; the light sources are
#: subdivided to 1% of the distance (-ds) with jittered samples (-dj 1) and no source
#: thresholding (-dt 0, -dc 1); -av 0 adds no ambient guess; -dr 0: no mirrors.
RTRACE_OPTIONS = ("-aa", "0", "-ad", "2048", "-as", "0", "-ab", "100", "-lr", "0", "-lw", "1e-6",
                  "-av", "0", "0", "0", "-u+", "-ds", "0.01", "-dj", "1", "-dt", "0", "-dc", "1", "-dr", "0")

#: Direct light only: the same source sampling, no indirect bounce.
RTRACE_DIRECT_OPTIONS = ("-ab", "0", "-u+", "-ds", "0.01", "-dj", "1", "-dt", "0", "-dc", "1", "-dr", "0")


#: Each emitting triangle is given to RADIANCE as 4^EMITTER_SPLITS (see the module docstring).
EMITTER_SPLITS = 0


def split_triangles(corners: np.ndarray, levels: int) -> np.ndarray:
    """(T * 4^levels, 3, 3) the triangles (T, 3, 3) split at their edge midpoints ``levels``
    times, each piece in its parent's winding."""
    for _ in range(levels):
        a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
        ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
        corners = np.stack([np.stack(t, axis=1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))],
                           axis=1).reshape(-1, 3, 3)
    return corners


def radiance_scene(scene: Scene, mesh: Mesh, emitter_splits: int = EMITTER_SPLITS) -> str:
    """The scene as a RADIANCE scene description (text for ``oconv``).

    Args:
        scene: its materials; mesh: the triangles (e.g. ``build_mesh(scene)``), whose
            ``material`` indexes ``scene.materials``.
        emitter_splits: each emitting triangle becomes 4^emitter_splits polygons.

    Returns:
        One ``plastic`` or ``light`` per material (named ``m<index>``), then one ``polygon``
        per triangle in the mesh's order (named ``t<index>``, or ``t<index>.<piece>`` for an
        emitter's pieces), numbers with 9 significant digits.
    """
    lines = []
    emitting = [any(e > 0 for e in material.emission) for material in scene.materials]
    for index, material in enumerate(scene.materials):
        if emitting[index]:
            radiance = " ".join(f"{e / math.pi:.9g}" for e in material.emission)
            lines.append(f"void light m{index}\n0\n0\n3 {radiance}")
        else:
            reflectance = " ".join(f"{r:.9g}" for r in material.reflectance)
            lines.append(f"void plastic m{index}\n0\n0\n5 {reflectance} 0 0")
    corners = mesh.corners.cpu().numpy()
    for index, (triangle, material) in enumerate(zip(corners, mesh.material.tolist())):
        if emitting[material] and emitter_splits > 0:
            for piece, part in enumerate(split_triangles(triangle[None], emitter_splits)):
                numbers = " ".join(f"{x:.9g}" for x in part.reshape(-1))
                lines.append(f"m{material} polygon t{index}.{piece}\n0\n0\n9 {numbers}")
        else:
            numbers = " ".join(f"{x:.9g}" for x in triangle.reshape(-1))
            lines.append(f"m{material} polygon t{index}\n0\n0\n9 {numbers}")
    return "\n".join(lines) + "\n"


def radiance_tools() -> tuple[Path, dict]:
    """The folder of RADIANCE's programs and the environment they need (``RAYPATH``).

    Raises:
        HemiradInputError: pyradiance is not installed.
    """
    try:
        import pyradiance
    except ImportError as exc:
        raise HemiradInputError(
            "making an irradiance reference needs RADIANCE, which pyradiance ships, an optional "
            "dependency: pip install 'hemirad[reference]' (or pip install pyradiance).") from exc
    package = Path(pyradiance.__file__).resolve().parent
    env = dict(os.environ, RAYPATH=os.pathsep.join([".", str(package / "lib")]))
    return package / "bin", env


def radiance_version() -> str:
    """``rtrace -version``, e.g. ``"RADIANCE 6.0a"``."""
    binaries, env = radiance_tools()
    done = subprocess.run([str(binaries / "rtrace"), "-version"], capture_output=True, text=True, env=env, check=True)
    return done.stdout.strip()


def rtrace_irradiance(scene: Scene, mesh: Mesh, points: np.ndarray, normals: np.ndarray,
                      options=RTRACE_OPTIONS, repeats: int = 1, emitter_splits: int = EMITTER_SPLITS) -> np.ndarray:
    """Irradiance at points by ``rtrace -I``, each point evaluated ``repeats`` times.

    Args:
        scene, mesh: what ``radiance_scene`` writes.
        points: (N, 3) positions; normals: (N, 3) unit normals of the sensors.
        options: rtrace's settings (``RTRACE_OPTIONS``, ``RTRACE_DIRECT_OPTIONS``).
        repeats: evaluations of every point; with ``-u+`` they are independent estimates.
        emitter_splits: passed to ``radiance_scene``.

    Returns:
        (repeats, N, 3) float64 RGB irradiance. RADIANCE seeds its generator the same way
        every run, so the same inputs give the same numbers.
    """
    binaries, env = radiance_tools()
    points, normals = np.asarray(points, dtype=np.float64), np.asarray(normals, dtype=np.float64)
    rays = np.concatenate([points, normals], axis=1)
    text = "".join(" ".join(f"{x:.12g}" for x in ray) + "\n" for ray in np.tile(rays, (repeats, 1)))
    with tempfile.TemporaryDirectory() as folder:
        octree = Path(folder) / "scene.oct"
        with open(octree, "wb") as out:
            subprocess.run([str(binaries / "oconv"), "-"], input=radiance_scene(scene, mesh, emitter_splits).encode(),
                           stdout=out, env=env, check=True, cwd=folder)
        done = subprocess.run([str(binaries / "rtrace"), "-I", "-h", "-ov", *options, str(octree)],
                              input=text, capture_output=True, text=True, env=env, cwd=folder)
    if done.returncode != 0:
        raise RuntimeError(f"rtrace failed ({done.returncode}): {done.stderr.strip()}")
    values = np.array([[float(x) for x in line.split()] for line in done.stdout.splitlines() if line.strip()])
    return values.reshape(repeats, len(points), 3)


@dataclass
class IrradianceReference:
    """RADIANCE's irradiance at a scene's sensor points, and how it was made.

    Attributes:
        names: (N,) a label per point (``"floor_open"``, ``"midair_tilted"``, ...).
        points: (N, 3) positions in scene units; normals: (N, 3) unit sensor normals.
        irradiance: (N, 3) RGB irradiance, the mean of the repeated evaluations.
        direct: (N, 3) RGB irradiance of the direct light only (``RTRACE_DIRECT_OPTIONS``).
        standard_error: (N, 3) the standard error of ``irradiance``: the spread of the
            repeated evaluations over the square root of their number.
        info: JSON-able facts: scene, RADIANCE version, every rtrace setting, repeats,
            seconds, the geometry summary.
    """

    names: list
    points: np.ndarray
    normals: np.ndarray
    irradiance: np.ndarray
    direct: np.ndarray
    standard_error: np.ndarray
    info: dict

    def save(self, folder, scene_name: str) -> Path:
        """Write ``radiance_<scene_name>.json``: ``info`` plus one record per point."""
        path = Path(folder) / f"radiance_{scene_name}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        records = [{"name": name, "point": _round(p, 9), "normal": _round(n, 9), "irradiance": _round(e, 7),
                    "direct": _round(d, 7), "standard_error": _round(s, 3)}
                   for name, p, n, e, d, s in zip(self.names, self.points, self.normals, self.irradiance,
                                                  self.direct, self.standard_error)]
        text = json.dumps({**self.info, "points": records}, indent=2)
        # One line per list of numbers: [0.7, 0.7, 0.7] rather than a line per number.
        text = re.sub(r"\[\s+([^\[\]{}\"]*?)\s+\]", lambda m: "[" + ", ".join(
            x.strip() for x in m.group(1).split(",")) + "]", text)
        path.write_text(text + "\n")
        return path

    @classmethod
    def load(cls, folder, scene_name: str) -> "IrradianceReference":
        data = json.loads((Path(folder) / f"radiance_{scene_name}.json").read_text())
        records = data.pop("points")

        def column(key):
            return np.array([r[key] for r in records], dtype=np.float64).reshape(len(records), 3)
        return cls([r["name"] for r in records], column("point"), column("normal"), column("irradiance"),
                   column("direct"), column("standard_error"), data)


def _round(values, digits: int) -> list:
    return [float(f"{float(v):.{digits}g}") for v in values]
