"""The whole job, scene to outputs: the library entry points behind the CLI.

    result = hemirad.solve(hemirad.load_scene("cornell_box"))
    result.write("out/")    # image.png, image.exr, luminance.png, mesh.png, mesh.ply, mesh.glb, stats.json
                            # (and sensors.csv, grid_<name>.csv for a scene's sensors and grids)

    # a long run that can be killed, then continued by the same call with resume=True
    # (to the same result, bit for bit)
    result = hemirad.solve(scene, checkpoint="out/checkpoint.pt", checkpoint_every=100)
"""
from __future__ import annotations

import contextlib
import dataclasses
import difflib
import fcntl
import math
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from hemirad import checkpoint as checkpoints
from hemirad.adaptive.answer import (Display, RoundReport, element_errors, estimated_relative_error, ranking_solve,
                                     refine_by_answer)
from hemirad.adaptive.refine import Refiner
from hemirad.assembly import make_solver, refined_patches
from hemirad.core.atomic import remove_stale_temporaries
from hemirad.core.colour import luminance
from hemirad.core.device import select_device
from hemirad.core.errors import HemiradInputError, SceneError, bounded_repr
from hemirad.evaluation.gathered_error import GatheredError, gathered_error, image_gathered_error
from hemirad.geometry.mesh import Mesh
from hemirad.geometry.split import angle_quality
from hemirad.lighting import photometry, survey
from hemirad.lighting.gathered import GatherReport, finished_radiosity
from hemirad.lighting.grids import MAX_GRID_POINTS, grid_counts, grid_spacing
from hemirad.lighting.sensors import SENSOR_RESOLUTION, irradiance_at
from hemirad.output import display, export, falsecolour, gltf
from hemirad.output.importance import view_importance
from hemirad.output.meshview import pick_surface, surface_view
from hemirad.output.reconstruction import reconstructed_vertex_values
from hemirad.output.render import render_view
from hemirad.output.shading import Shading, picture_shading
from hemirad.scene.meshing import build_mesh
from hemirad.scene.model import ANSWER, CAMERA_IMPORTANCE, Camera, Scene
from hemirad.transport.gl import GLContext, check_image_size
from hemirad.transport.solver import ProgressiveSolver, ShotReport, ambient_term


#: The files ``Result.write`` makes in an output folder, by kind; besides these, one
#: ``falsecolour_file(name)`` for each surface the scene's ``falsecolour`` names.
OUTPUT_FILES = {"image": "image.png", "HDR image": "image.exr", "luminance": "luminance.png",
                "mesh view": "mesh.png", "mesh": "mesh.ply", "glTF": "mesh.glb", "stats": "stats.json"}

#: Photometric values from the radiometric ones a scene in W/m^2 gives, with their units:
#: 683 lm/W times the luminance (Rec. 709) of the colour.
LUMINANCE_UNIT, ILLUMINANCE_UNIT = "cd/m^2", "lx"


def falsecolour_file(surface: str) -> str:
    """The file the false-colour picture of ``surface`` (a name as the scene gives it) is
    written to: ``falsecolour_room.floor.png``; characters a file name should not hold
    (anything but letters, digits, ``.``, ``_`` and ``-``) become ``_``."""
    return "falsecolour_" + re.sub(r"[^A-Za-z0-9._-]", "_", surface) + ".png"


def output_names(scene: Scene) -> list[str]:
    """Every file name a run of ``scene`` writes into its output folder (not the checkpoint)."""
    return [*OUTPUT_FILES.values(), *dict.fromkeys(falsecolour_file(name) for name in scene.falsecolour),
            *survey.output_names(scene)]


@dataclass
class Result:
    """A solved scene, what ``solve`` returns; every tensor is float64 on the CPU.

    Attributes:
        scene: what was solved (its camera and ``solver.ambient`` still steer the display).
        mesh: the final mesh (refined, when refinement was on): vertices (V, 3), triangles
            (T, 3), surface and material (T,), surface_names, level (T,).
        radiosity: (T, 3) element radiosity B, linear RGB exitance in the scene's units.
        unshot: (T, 3) unshot radiosity left when the solver stopped.
        reflectance, emission: (T, 3) per element.
        stats: what stats.json holds: element counts (initial, final, per level), splits,
            shots, unshot fraction, emitted / absorbed / escaped power, seconds per phase,
            the grids' statistics.
        sensors: the scene's sensors read on the solved mesh (``survey.SensorReadings``:
            names, points, irradiance (N, 3), lux (N,)), or None when it has none.
        grids: each grid's readings by name (``survey.GridReadings``: points (rows,
            columns, 3), irradiance, lux (rows, columns), statistics).
        Both are computed by ``solve``, after the last shot, from ``display_radiosity``.
    """

    scene: Scene
    mesh: Mesh
    radiosity: torch.Tensor
    unshot: torch.Tensor
    reflectance: torch.Tensor
    emission: torch.Tensor
    stats: dict = field(default_factory=dict)
    sensors: survey.SensorReadings | None = None
    grids: dict[str, survey.GridReadings] = field(default_factory=dict)
    _shading: tuple | None = field(default=None, init=False, repr=False, compare=False)  # (settings, Shading)
    _guide: tuple | None = field(default=None, init=False, repr=False, compare=False)  # (settings, (T,) errors)

    @classmethod
    def of_solver(cls, scene: Scene, solver: ProgressiveSolver) -> "Result":
        """The solver's current solution (on the CPU), without statistics."""
        s = solver.state
        return cls(scene, solver.mesh.to("cpu"), s.radiosity.cpu(), s.unshot.cpu(), solver.reflectance.cpu(),
                   solver.emission.cpu())

    def estimate_error(self) -> GatheredError | None:
        """The displayed solution's relative RMS error, estimated by final gathers at the
        scene's ``solver.error_samples`` points (``evaluation.gathered_error``); None for 0."""
        o = self.scene.solver
        return gathered_error(self.mesh, self.display_radiosity, self.emission, self.reflectance,
                              o.error_samples, o.resolution, shading=self.shading(), guide=self.error_guide())

    def estimate_image_error(self, camera: Camera | None = None, samples: int | None = None,
                             mask=None) -> GatheredError | None:
        """The relative RMS error of the picture from ``camera`` (default: the scene's), as a
        per-pixel comparison with a rendered reference weighs it, estimated by final gathers
        at the points ``samples`` of its pixels see (default ``solver.error_samples``), of
        those in ``mask`` (H, W) bool when given (``evaluation.gathered_error``)."""
        o = self.scene.solver
        return image_gathered_error(self.mesh, self.display_radiosity, self.emission, self.reflectance,
                                    self.scene.camera if camera is None else camera,
                                    o.error_samples if samples is None else samples, o.resolution, mask=mask,
                                    shading=self.shading(), guide=self.error_guide())

    def error_guide(self) -> torch.Tensor:
        """(T,) each element's interpolation estimate (``adaptive.answer.element_errors`` of
        the picture as drawn), which the final-gather estimates sample by
        (``evaluation.gathered_error``, ``GUIDE_SHARE``). Made once for the settings it reads:
        both estimates sample by it."""
        settings = (self.scene.solver.reconstruction, self.scene.solver.ambient)
        if self._guide is None or self._guide[0] != settings:
            self._guide = settings, element_errors(self.mesh, self.display_radiosity, _picture(self.scene))
        return self._guide[1]

    @property
    def ambient(self) -> torch.Tensor:
        """(3,) ambient radiosity of the unshot energy (zero when the scene turns it off)."""
        if not self.scene.solver.ambient:
            return torch.zeros(3, dtype=torch.float64)
        return ambient_term(self.unshot, self.reflectance, self.mesh.areas)

    @property
    def display_radiosity(self) -> torch.Tensor:
        """(T, 3) radiosity as shown: B plus the reflected ambient term."""
        return self.radiosity + self.reflectance * self.ambient

    def irradiance_at(self, points, normals, resolution: int = SENSOR_RESOLUTION) -> torch.Tensor:
        """(N, 3) the irradiance at any ``points`` (N, 3) on small areas facing ``normals``
        (N, 3), gathered from ``display_radiosity`` by a hemicube at each point."""
        return irradiance_at(self.mesh, self.display_radiosity, points, normals, resolution)

    def illuminance_at(self, points, normals, resolution: int = SENSOR_RESOLUTION) -> torch.Tensor:
        """(N,) the illuminance in lux at ``points`` facing ``normals`` (see ``irradiance_at``)."""
        return photometry.illuminance(self.irradiance_at(points, normals, resolution), self.scene.units)

    def luminance(self) -> torch.Tensor:
        """(T,) every element's luminance in cd/m^2: the Rec. 709 luminance of its display
        radiosity in lm/m^2 (times 683 lm/W in a radiometric scene) over pi, as a
        Lambertian surface's."""
        return photometry.luminance_cd(self.display_radiosity, self.scene.units)

    def vertex_radiosity(self) -> torch.Tensor:
        """(V, 3) display radiosity at the vertices, as ``solver.reconstruction`` carries it
        there from the elements within each surface (``output.reconstruction``), and at
        T-vertices interpolated along the unsplit edge they lie on, so shading has no seams."""
        return reconstructed_vertex_values(self.mesh, self.display_radiosity, self.scene.solver.reconstruction)

    def exposure(self) -> float:
        """Display value per unit radiosity: the camera's, or automatic (the area-weighted mean
        luminance of non-emitting surfaces maps to 0.18)."""
        if self.scene.camera.exposure is not None:
            return self.scene.camera.exposure
        emitting = (self.emission > 0).any(dim=1)
        return display.auto_exposure(self.display_radiosity, self.mesh.areas, emitting)

    def shading(self, vertex_radiosity: torch.Tensor | None = None) -> Shading:
        """The display radiosity as pictures draw it (``output.shading``): each element cut
        into a lattice shaded from the fitted quadratics around its corners, or, with
        ``solver.reconstruction: mean`` (the paper's), the vertex values Gouraud-shaded.
        Made once for the settings it reads. ``vertex_radiosity``: ``vertex_radiosity()``, to
        reuse one already computed."""
        settings = (self.scene.solver.reconstruction, self.scene.solver.ambient)
        if self._shading is None or self._shading[0] != settings:
            self._shading = settings, picture_shading(self.mesh, self.display_radiosity, settings[0], vertex_radiosity)
        return self._shading[1]

    def linear_image(self, shading: Shading | None = None) -> np.ndarray:
        """(height, width, 3) float32 camera view of the display radiosity: linear, in the
        scene's units (W/m^2), before exposure and sRGB. ``shading``: ``shading()``, to reuse
        one already made."""
        shading = self.shading() if shading is None else shading
        return render_view(self.mesh, shading.values, self.scene.camera, triangles=shading.triangles,
                           positions=shading.positions)

    def image(self, linear: np.ndarray | None = None) -> np.ndarray:
        """(height, width, 3) uint8 sRGB camera view. ``linear``: ``linear_image()``, to
        reuse one already rendered."""
        return display.to_srgb8(self.linear_image() if linear is None else linear, self.exposure())

    def radiance_image(self, linear: np.ndarray | None = None) -> np.ndarray:
        """(height, width, 3) float32 radiance the camera sees, B / pi (the surfaces are
        Lambertian), in the scene's units per steradian (W/(m^2 sr)): what image.exr holds."""
        linear = self.linear_image() if linear is None else linear
        return (np.asarray(linear, dtype=np.float64) / math.pi).astype(np.float32)

    def coverage_image(self) -> np.ndarray:
        """(height, width) float32: the share of each camera pixel that surfaces cover (the
        view with every vertex 1); 0 where the camera sees nothing."""
        ones = torch.ones(len(self.mesh.vertices), 3, dtype=torch.float32)
        view = render_view(self.mesh, ones, self.scene.camera, triangles=display.conforming_triangles(self.mesh))
        return view[:, :, 0]

    @property
    def lumens_per_unit(self) -> float:
        """Lumens per unit of the scene's power: 683 lm/W in a radiometric scene, 1 in a
        photometric one (``lighting.photometry``)."""
        return photometry.lumens_per_unit(self.scene.units)

    def luminance_image(self, factor: float | None = None, unit: str = LUMINANCE_UNIT,
                        linear: np.ndarray | None = None) -> np.ndarray:
        """(h, w, 3) uint8: the camera view's luminance in false colour with a colour bar (a
        log scale; pixels that see no surface grey). ``factor``: lumens per unit of the
        scene's power (default ``lumens_per_unit``). ``linear``: ``linear_image()``, to
        reuse one already rendered."""
        factor = self.lumens_per_unit if factor is None else factor
        linear = self.linear_image() if linear is None else linear
        return falsecolour.luminance_picture(linear, self.coverage_image(), unit, "Luminance", factor)

    def irradiance(self) -> torch.Tensor:
        """(T, 3) the irradiance falling on each element, (B - E) / rho per channel with B
        the display radiosity (so the ambient term is in it); NaN where rho is 0."""
        return falsecolour.element_irradiance(self.display_radiosity, self.emission, self.reflectance)

    def surface_falsecolour(self, surface: str, factor: float | None = None, unit: str = ILLUMINANCE_UNIT,
                            size: int = 512, levels=None) -> np.ndarray:
        """(h, w, 3) uint8: the light falling on one surface (a name, as for ``mesh_image``),
        seen straight on, as a false-colour map of ``factor`` (default ``lumens_per_unit``)
        times the luminance of its irradiance, with a colour bar in ``unit`` and iso-lines
        (``levels``; None: nice numbers over its range). Default: illuminance in lux."""
        factor = self.lumens_per_unit if factor is None else factor
        index = pick_surface(self.mesh, surface)
        title = f"Light falling on {self.mesh.surface_names[index]}"
        return falsecolour.surface_picture(self.mesh, self.irradiance(), index, unit, title, factor, size, levels)

    def grid_picture(self, grid, levels=None) -> np.ndarray:
        """(h, w, 3) uint8: a calculation grid's illuminance (``self.grids[name]``) over its
        rectangle in false colour, a colour bar in lux, iso-lines (``levels``; None: nice
        numbers), its Em, Emin and U0 in the title."""
        g, s = grid.grid, grid.statistics
        u0 = f", U0 {s['U0']:.2f}" if s["U0"] is not None else ""
        title = f"Grid {g.name}: Em {s['Em']:.4g} lx, Emin {s['Emin']:.4g} lx{u0}"
        return falsecolour.grid_picture(grid.lux.numpy(), g.origin, g.u, g.v, ILLUMINANCE_UNIT, title, levels)

    def mesh_image(self, surface: str | None = None, size: int = 512,
                   vertex_radiosity: torch.Tensor | None = None) -> np.ndarray:
        """(H, W, 3) uint8: one surface seen straight on, its elements shaded and outlined
        (the paper's (a)'(b)'(c)' pictures). ``surface``: a name such as ``room.floor``;
        default the scene's ``refine.view_surface``, else the floor. ``vertex_radiosity``:
        ``vertex_radiosity()``, to reuse one already computed."""
        index = pick_surface(self.mesh, surface or self.scene.refine.view_surface)
        vertex = self.vertex_radiosity() if vertex_radiosity is None else vertex_radiosity
        linear = surface_view(self.mesh, vertex, index, size=size)
        return display.to_srgb8(linear, self.exposure())

    def write(self, folder) -> dict[str, Path]:
        """Write image.png, image.exr, luminance.png, mesh.png, mesh.ply, mesh.glb, stats.json,
        a falsecolour_<surface>.png for each surface the scene's ``falsecolour`` names, and
        sensors.csv and grid_<name>.csv for the scene's sensors and grids into ``folder``
        (made if missing), each atomically, under the folder's lock (``output_lock``);
        returns their paths by kind. Raises HemiradInputError if it cannot write, another
        run holds the folder, or a result is not finite (then nothing is written)."""
        with output_lock(folder, output_names(self.scene)) as folder:
            return self._write(folder)

    def _write(self, folder: Path) -> dict[str, Path]:
        paths = {kind: folder / name for kind, name in OUTPUT_FILES.items()}
        surfaces = dict.fromkeys(self.scene.falsecolour)
        paths.update({f"falsecolour {name}": folder / falsecolour_file(name) for name in surfaces})
        tables = {}
        if self.sensors is not None:
            tables["sensors"] = (folder / "sensors.csv", self.sensors.table())
        grid_pictures = {}
        for name, grid in self.grids.items():
            tables[f"grid {name}"] = (folder / grid.file_name, grid.table())
            grid_pictures[f"grid picture {name}"] = (folder / survey.grid_file_name(name, ".png"), grid)
        vertex = self.vertex_radiosity()
        check_finite(self, vertex)  # before anything is written
        start = time.perf_counter()
        linear = self.linear_image(self.shading(vertex))
        export.write_png(paths["image"], self.image(linear))
        export.write_exr(paths["HDR image"], self.radiance_image(linear))
        export.write_png(paths["luminance"], self.luminance_image(linear=linear))
        export.write_png(paths["mesh view"], self.mesh_image(vertex_radiosity=vertex))
        for name in surfaces:
            export.write_png(paths[f"falsecolour {name}"], self.surface_falsecolour(name))
        for kind, (path, grid) in grid_pictures.items():
            export.write_png(path, self.grid_picture(grid))
            paths[kind] = path
        rendered = time.perf_counter()
        export.write_ply(paths["mesh"], self.mesh, vertex, display.to_srgb8(vertex.numpy(), self.exposure()))
        self.write_glb(paths["glTF"])
        for kind, (path, (header, rows)) in tables.items():
            export.write_csv(path, header, rows)
            paths[kind] = path
        self.stats.setdefault("seconds", {}).update(
            render=rendered - start, export=time.perf_counter() - rendered)
        export.write_stats(paths["stats"], self.stats)
        return paths

    def write_glb(self, path) -> Path:
        """Write the picture as drawn (``shading()``: its triangles and points) as binary glTF:
        COLOR_0 the exposed linear display colour, the linear radiosity as ``_RADIOSITY`` (see
        ``output.gltf``). Returns the path."""
        shading = self.shading()
        gltf.write_glb(path, shading.positions, shading.triangles, shading.values,
                       gltf.display_color(shading.values, self.exposure()))
        return Path(path)


def _restore(scene: Scene, solver: ProgressiveSolver, state: dict, run: dict, path, initial_elements: int) -> dict:
    """Load a checkpoint's solver state; returns the seconds the earlier runs spent."""
    try:
        if int(run["initial_elements"]) != initial_elements:
            raise ValueError(f"the scene meshes to {initial_elements} elements, the checkpoint's run "
                             f"started with {run['initial_elements']}")
        # after a round's split the patches were regrouped on the refined mesh (``refine_by_answer``)
        split = scene.refines_by_answer and any(int(r["split"]) for r in run.get("answer", {}).get("rounds", []))
        solver.load_state_dict(state, (lambda: refined_patches(scene, solver, state["patches"])) if split else None)
        return {"mesh": float(run["seconds"]["mesh"]), "solve": float(run["seconds"]["solve"])}
    except (KeyError, TypeError, ValueError, IndexError, RuntimeError) as exc:
        raise HemiradInputError(f"cannot resume from {path}: its content does not fit this scene ({exc}). "
                                f"Start without --resume to begin afresh.") from exc


def check_gl_limits(scene: Scene, gpu: bool = False) -> None:
    """Refuse, before any work, sizes the OpenGL framebuffers cannot hold: the hemicube atlas
    (R x 3R) and the supersampled camera image (tried, since a side within the limit may
    still be too large a framebuffer). Otherwise the image would fail only after the whole
    solve. ``gpu``: the solve draws with the GPU's context (made here if none is)."""
    r = scene.solver.resolution
    check_image_size(3 * r, lambda limit: _key_error(
        scene, "solver.resolution", f"at most {limit // 6 * 2} (the hemicube is drawn into an "
        f"R x 3R image, and OpenGL allows {limit} pixels a side here)", r), gpu)
    cam = scene.camera
    # the supersample when the scene changed it, else the larger side
    key = "camera.supersample" if cam.supersample != Camera.supersample else \
        ("camera.width" if cam.width >= cam.height else "camera.height")
    got = {"camera.supersample": cam.supersample, "camera.width": cam.width, "camera.height": cam.height}[key]

    def refusal(limit: int) -> HemiradInputError:
        return _key_error(scene, key, f"a camera size that, times supersample, OpenGL can draw here "
                          f"(at most {limit} pixels a side, and a framebuffer this machine can make)", got,
                          f"The camera is {cam.width} x {cam.height} at supersample {cam.supersample}, "
                          f"{cam.width * cam.supersample} x {cam.height * cam.supersample} pixels; "
                          f"lower supersample or the size.")

    check_image_size(max(cam.width, cam.height) * cam.supersample, refusal, gpu)
    if not GLContext.framebuffer_fits(cam.width * cam.supersample, cam.height * cam.supersample, gpu):
        raise refusal(GLContext.max_image_size(gpu))


def prepare_output_folder(folder, names=None) -> Path:
    """Create ``folder`` (and its parents) if needed; HemiradInputError when it cannot be
    written, or when one of the files a run writes there (``names``, default
    ``OUTPUT_FILES``'s; the checkpoint's too) is a folder (or not a file)."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise HemiradInputError(f"cannot create the output folder {folder}: {exc.strerror or exc}.") from exc
    if not os.access(folder, os.W_OK):
        raise HemiradInputError(f"the output folder {folder} is not writable.")
    for name in (*(OUTPUT_FILES.values() if names is None else names), checkpoints.FILENAME):
        path = folder / name
        if path.exists() and not path.is_file():
            raise HemiradInputError(f"cannot write {path}: it exists and is not a regular file "
                                    f"({'a folder' if path.is_dir() else 'a special file'}); move it away "
                                    f"or choose another output folder.")
    return folder


_LOCK_NAME = ".hemirad.lock"
_held: dict[Path, object] = {}  # output folders this process holds the lock of


@contextlib.contextmanager
def output_lock(folder, names=None):
    """Hold ``folder`` (prepared for the files ``names``, see ``prepare_output_folder``) for
    one run: a second run writing there is refused (HemiradInputError) until this one ends,
    and the temporary files a killed run left there are removed. Re-entrant within a
    process; yields the folder."""
    names = list(OUTPUT_FILES.values() if names is None else names)
    folder = prepare_output_folder(folder, names)
    key = folder.resolve()
    if key in _held:
        yield folder
        return
    try:
        handle = open(folder / _LOCK_NAME, "a")
    except OSError as exc:
        raise HemiradInputError(f"cannot lock the output folder {folder}: {exc.strerror or exc}.") from exc
    try:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            raise HemiradInputError(f"another hemirad run is writing to the output folder {folder}; wait for "
                                    f"it to finish or choose another folder (-o).") from exc
        _held[key] = handle
        try:
            remove_stale_temporaries(folder, (*names, checkpoints.FILENAME))
            yield folder
        finally:
            del _held[key]
    finally:
        handle.close()  # releases the lock


def check_finite(result: "Result", vertex_radiosity: torch.Tensor) -> None:
    """Refuse to write a result holding NaN or infinity, or radiosity too large for the
    outputs' 32-bit floats (extreme emissions or sizes): HemiradInputError, nothing written."""
    limit = float(np.finfo(np.float32).max)
    for name, values in (("element radiosity", result.display_radiosity), ("vertex radiosity", vertex_radiosity)):
        bad = ~torch.isfinite(values).all(dim=1) | (values.abs() > limit).any(dim=1)
        if bool(bad.any()):
            raise HemiradInputError(
                f"the solve's {name} is not finite, or too large for a 32-bit float, at {int(bad.sum())} of "
                f"{len(values)} places; the scene's emissions or sizes are too extreme to compute with. "
                f"Nothing was written.")
    exposure = result.exposure()
    if not (math.isfinite(exposure) and exposure > 0):
        raise HemiradInputError(f"the image's exposure comes out as {exposure!r}: the scene's radiosity is too "
                                f"small or too large to show. Set camera.exposure, or scale the emissions. "
                                f"Nothing was written.")


def _key_error(scene: Scene, key: str, expected: str, got: object = ..., hint: str = "") -> HemiradInputError:
    """The error about ``key`` of ``scene``: naming the scene file, or the command-line
    option when that is where the value came from (``Scene.command_line``)."""
    option = scene.command_line.get(key)
    if option is None:
        return SceneError(str(scene.source) if scene.source else "<scene>", key, expected, got, hint)
    shown = f", got {bounded_repr(got)}" if got is not ... else ""
    return HemiradInputError(f"{option} (given on the command line, for {key}): expected {expected}{shown}. {hint}")


def _surface_hint(mesh: Mesh, name: str, error: HemiradInputError) -> str:
    """What to say of a surface name ``pick_surface`` refused: the names close to it (by
    spelling, whole or after the object's name), and what surfaces there are."""
    names = list(mesh.surface_names)
    if any(n.endswith("." + name) for n in names):  # ambiguous: pick_surface lists the matches
        return str(error)[:1].upper() + str(error)[1:]
    close = difflib.get_close_matches(name, names, n=3, cutoff=0.6)
    close += [n for n in names if n not in close and difflib.get_close_matches(name, [n.rsplit(".", 1)[-1]],
                                                                                 cutoff=0.6)][:3 - len(close)]
    shown = ", ".join(names[:12]) + (f" and {len(names) - 12} more" if len(names) > 12 else "")
    near = f" The closest names: {', '.join(close)}." if close else ""
    return f"No surface named {bounded_repr(name)}.{near} The scene's surfaces: {shown}."
def check_grid_sizes(scene: Scene) -> None:
    """Refuse a grid of more than ``MAX_GRID_POINTS`` points (each a hemicube), before meshing."""
    for grid in scene.grids:
        columns, rows = grid_counts(grid, scene.metres_per_unit)
        if columns * rows > MAX_GRID_POINTS:
            spacing = grid_spacing(grid, scene.metres_per_unit)
            raise _key_error(scene, f"{grid.key}.spacing" if grid.spacing is not None else grid.key,
                             f"a grid of at most {MAX_GRID_POINTS:,} points (each is a hemicube rendered)",
                             hint=f"At a spacing of {spacing:.4g} scene units it has {columns:,} x {rows:,} "
                                  f"points; give a larger spacing.")


def check_before_solving(scene: Scene, mesh: Mesh, solver: ProgressiveSolver) -> None:
    """What can only be checked once the scene is meshed, checked before any shot: the
    surfaces ``refine.view_surface`` and ``falsecolour`` name, an emitted power that is
    finite and positive, and grids that see some surface (a hemicube at their points until
    one does)."""
    try:
        pick_surface(mesh, scene.refine.view_surface)
    except HemiradInputError as exc:
        raise _key_error(scene, "refine.view_surface", "the name of a surface of the scene",
                         scene.refine.view_surface, str(exc)[:1].upper() + str(exc)[1:]) from exc
    files: dict[str, str] = {}
    first = {name: i for i, name in reversed(list(enumerate(scene.falsecolour)))}  # a repeated name once
    for name, i in sorted(first.items(), key=lambda item: item[1]):
        key = f"falsecolour[{i}]"
        try:
            pick_surface(mesh, name)
        except HemiradInputError as exc:
            raise _key_error(scene, key, "the name of a surface of the scene", name,
                             _surface_hint(mesh, name, exc)) from exc
        other = files.setdefault(falsecolour_file(name), name)
        if other != name:
            raise _key_error(scene, key, "surface names that give different file names", name,
                             f"Both {other!r} and {name!r} would be written to {falsecolour_file(name)}.")
    power = solver.emitted_power.cpu()
    if not (bool(torch.isfinite(power).all()) and bool((power > 0).any())):
        raise _key_error(scene, "materials", "emissions and areas whose emitted power is finite and positive",
                         hint=f"The emitting surfaces give a power of {power.tolist()}: the emissions or "
                              f"the emitters' sizes are too extreme to compute with.")
    for grid in survey.blind_grids(scene, mesh):
        raise _key_error(scene, grid.key, "a grid that sees some surface of the scene",
                         hint=f"No point of grid {grid.name!r} sees any surface, front or back: it lies outside "
                              f"the scene, or faces away from all of it (its normal is {list(grid.normal)}).")


def solve(scene: Scene, progress: Callable[[ShotReport], None] | None = None, checkpoint=None,
          checkpoint_every: int = 0, resume: bool = False) -> Result:
    """Mesh the scene and run progressive refinement until the scene's stopping rule.

    Args:
        scene: from ``load_scene``; ``scene.solver`` and ``scene.refine`` may be edited first.
        progress: called after every shot with a ``ShotReport`` (shots, shooter, elements,
            unshot fraction, seconds), and with ``solver.final_gather`` with a
            ``lighting.gathered.GatherReport`` (gathered, elements, seconds) as the gathers
            go; raising from it (e.g. KeyboardInterrupt) stops the solve.
        checkpoint: path of a checkpoint file (e.g. ``out/checkpoint.pt``), or None for none.
            With a path, a checkpoint is also written when the solve ends, so that a finished
            run can be continued with a larger ``max_shots``.
        checkpoint_every: write the checkpoint after every this many shots (0: only at the end).
        resume: continue from ``checkpoint`` instead of starting afresh; the result is the
            same, bit for bit, as that of a run never interrupted.
    Raises:
        HemiradInputError: a bad mesh file, a size over the OpenGL limits, a checkpoint that
            is missing, unreadable or made for another scene or other options.
    """
    if checkpoint_every < 0:
        raise ValueError(f"checkpoint_every must be >= 0, got {checkpoint_every}")
    if checkpoint is None and (checkpoint_every or resume):
        raise ValueError("checkpoint_every and resume need a checkpoint path")
    _check_answer_refinement(scene)
    options = scene.solver
    device = select_device(options.device)
    check_gl_limits(scene, gpu=device.type == "cuda")
    saved = None
    if checkpoint is not None:
        fingerprint = checkpoints.fingerprint(scene)
        if resume:  # read before meshing, so that a wrong checkpoint fails fast
            saved = checkpoints.read(checkpoint, fingerprint)
            if saved[0]["shots"] > options.max_shots:  # it would report more shots than asked for
                raise _key_error(scene, "solver.max_shots", f"at least the {saved[0]['shots']} shots the "
                                 f"checkpoint {checkpoint} already holds, to resume it", options.max_shots,
                                 "A resumed run only adds shots; start without --resume for a shorter run.")
    check_grid_sizes(scene)
    start = time.perf_counter()
    mesh = build_mesh(scene)
    meshed = time.perf_counter()
    # Built from the initial mesh even when resuming: its bounds set the hemicube's near and
    # far planes, which must be those of the run being continued.
    solver = make_solver(scene, mesh, device=device)
    before = {"mesh": 0.0, "solve": 0.0}  # seconds spent by the runs this one continues
    resumed_from = None
    rounds, answer_refiner = None, None
    estimate = _ErrorEstimate(scene, solver)
    try:
        check_before_solving(scene, mesh, solver)
        if saved is not None:
            before = _restore(scene, solver, *saved, checkpoint, mesh.num_elements)
            resumed_from = solver.state.shots

        def elapsed() -> dict[str, float]:
            return {"mesh": before["mesh"] + meshed - start, "solve": before["solve"] + time.perf_counter() - meshed}

        saver = None
        if checkpoint is not None:
            saver = _CheckpointWriter(checkpoint, fingerprint, checkpoint_every, solver, mesh.num_elements, elapsed,
                                      None if saved is None else solver.state.shots)
        if scene.refines_by_answer:
            rounds, answer_refiner = _refine_by_answer(scene, solver, progress, saver,
                                                       None if saved is None else saved[1], checkpoint, estimate)
        else:
            solver.run(options.max_shots, options.unshot_fraction,
                       progress if saver is None else saver.after_shot(progress))
        if saver is not None:
            saver.finish()
    finally:
        solver.close()
    times, gather_stats = elapsed(), None
    if options.final_gather != "none":
        gather_stats = estimate.finish_by_gathers(mesh, progress)
    result = estimate.result()
    final = result.mesh
    stats = result.stats
    stats.update(_stats(scene, solver, final, mesh.num_elements, times, resumed_from, rounds, answer_refiner))
    if gather_stats is not None:
        stats["seconds"]["final_gather"] = gather_stats.pop("seconds")
        stats["final_gather"] = gather_stats
    stats.update(units=scene.units, metres_per_unit=scene.metres_per_unit,
                 flux=photometry.flux_emissions(scene, mesh))
    gathered, seconds = estimate()  # the last round's, when refinement judged on the answer made one here
    interpolation = estimated_relative_error(final, result.radiosity, emission=result.emission,
                                             display=_picture(scene))
    stats.update(_estimate_stats(gathered, interpolation))
    stats["seconds"]["estimate"] = seconds  # the final mesh's estimate (each round's counts in "solve")
    if options.picture_error_samples:
        started = time.perf_counter()
        picture = result.estimate_image_error(samples=options.picture_error_samples)
        stats.update(estimated_picture_error=picture.relative_rms if picture else None,
                     estimated_picture_error_standard_error=picture.standard_error if picture else None)
        stats["seconds"]["picture_estimate"] = time.perf_counter() - started
    if scene.sensors or scene.grids:
        measured = time.perf_counter()
        result.sensors, result.grids = survey.measure(scene, final, result.display_radiosity)
        stats["sensors"] = len(scene.sensors)
        stats["grids"] = {name: grid.stats(scene.metres_per_unit) for name, grid in result.grids.items()}
        stats["seconds"]["sensors"] = time.perf_counter() - measured
    return result

def _check_answer_refinement(scene: Scene) -> None:
    """Refinement judged on the answer shoots by patches (each refined mesh is solved afresh by
    the initial mesh's patches)."""
    if not scene.refines_by_answer:
        return
    if not scene.solver.shoots_patches:
        raise _key_error(scene, "refine.criterion", "a per-shot criterion when every element shoots "
                         "(solver.patch_size none)", ANSWER, "Refinement judged on the answer solves each "
                         "refined mesh by the initial mesh's patches; use solver.patch_size auto, or another criterion.")


def _picture(scene: Scene) -> Display:
    """How ``scene``'s pictures draw element values (``solver.reconstruction``), for the
    answer's ranking to judge what is shown."""
    return lambda mesh, values: picture_shading(mesh, values, scene.solver.reconstruction)


def ranking_importance(scene: Scene) -> Callable[[Mesh], torch.Tensor] | None:
    """What the answer's ranking weighs an element's error by beside its area
    (``refine.importance``): how much of the scene camera's picture it fills, or None."""
    if scene.refine_importance != CAMERA_IMPORTANCE:
        return None
    camera = scene.camera
    return lambda mesh: view_importance(mesh, camera)


def _refine_by_answer(scene: Scene, solver: ProgressiveSolver, progress, saver: "_CheckpointWriter | None",
                      run: dict | None, path, estimate: "_ErrorEstimate") -> tuple[list[RoundReport], Refiner]:
    """Shoot to the stopping rule and refine where the answer is worst, in rounds
    (``adaptive.answer``), until ``estimate`` (or, where the scene asks for no samples, the
    interpolation estimate) is under the tolerance; checkpointed by ``saver`` after shots and
    after every round's split, and resumed from a checkpoint's ``run`` (read from ``path``);
    returns the rounds and the refiner that split."""
    options, refine = scene.solver, scene.refine
    refiner = Refiner(dataclasses.replace(refine, criterion=ANSWER), solver.emission)
    shown = _picture(scene)
    reports: list[RoundReport] = []
    if run is not None:
        try:
            refiner.load_state_dict(run["answer"]["refiner"])
            reports += [RoundReport(int(r["round"]), int(r["elements"]), int(r["split"]),
                                    float(r["estimated_error"]), int(r["shots"]), int(r.get("kept_bytes", 0)))
                        for r in run["answer"]["rounds"]]
        except (KeyError, TypeError, ValueError) as exc:
            raise HemiradInputError(f"cannot resume from {path}: its rounds of refinement judged on the answer "
                                    f"are missing or do not fit ({exc}). Start without --resume to begin "
                                    "afresh.") from exc

    def stopping_estimate() -> float:
        gathered, _ = estimate()
        if gathered is None:
            return estimated_relative_error(solver.mesh, solver.state.radiosity, emission=solver.emission,
                                            display=shown)
        return gathered.relative_rms

    shot_done = progress
    if saver is not None:
        saver.answer = lambda: {"refiner": refiner.state_dict(), "rounds": [dataclasses.asdict(r) for r in reports]}
        shot_done = saver.after_shot(progress)
    refine_by_answer(solver, refiner, refine.max_elements, refine.tolerance, refine.rounds,
                     lambda: solver.run(options.max_shots, options.unshot_fraction, shot_done),
                     # without checkpoints: a run stopped in a ranking solve resumes its round afresh
                     # (the solve's second step depends on where its first ended)
                     rank_on=lambda: ranking_solve(solver, options.max_shots, options.unshot_fraction, progress,
                                                   by_budget=refine.tolerance <= 0),
                     report=None if saver is None else (lambda _: saver.save()), reports=reports,
                     patches_for=lambda: refined_patches(scene, solver), estimate=stopping_estimate,
                     display=shown, importance=ranking_importance(scene))
    return reports, refiner


class _ErrorEstimate:
    """The final-gather estimate of ``solver``'s current solution (``Result.estimate_error``)
    and its seconds, made once per (shots, elements): the last round's of refinement judged
    on the answer is the finished run's, and its ``result()`` (its picture's shading made
    once) is the run's."""

    def __init__(self, scene: Scene, solver: ProgressiveSolver):
        self.scene, self.solver = scene, solver
        self._key: tuple | None = None  # (shots, elements) of the solution below
        self._result: Result | None = None
        self._estimate: tuple | None = None  # the estimate, its seconds

    def result(self) -> Result:
        """The solver's current solution (``Result.of_solver``)."""
        key = (self.solver.state.shots, self.solver.mesh.num_elements)
        if key != self._key:
            self._key, self._result, self._estimate = key, Result.of_solver(self.scene, self.solver), None
        return self._result

    def finish_by_gathers(self, initial: Mesh, progress: Callable[[GatherReport], None] | None = None) -> dict:
        """Give the elements ``solver.final_gather`` names (on the solution refined from
        ``initial``) the light their centroids gather (``lighting.gathered``); the estimate is
        then the gathered solution's. What stats.json's final_gather says: the mode, the
        elements gathered, the relative change of their luminance times area, the seconds."""
        start = time.perf_counter()
        result, mode = self.result(), self.scene.solver.final_gather
        radiosity, elements = finished_radiosity(mode, initial, result.mesh, result.radiosity, result.emission,
                                                 result.reflectance, result.ambient, self.scene.solver.resolution,
                                                 progress)
        weights = result.mesh.areas[elements]
        before = float(luminance(result.radiosity[elements]) @ weights)
        after = float(luminance(radiosity[elements]) @ weights)
        self._result, self._estimate = dataclasses.replace(result, radiosity=radiosity), None
        return {"mode": mode, "elements": len(elements), "luminance_change": after / before - 1 if before else 0.0,
                "seconds": time.perf_counter() - start}

    def __call__(self) -> tuple[GatheredError | None, float]:
        result = self.result()
        if self._estimate is None:
            start = time.perf_counter()
            self._estimate = result.estimate_error(), time.perf_counter() - start
        return self._estimate


class _CheckpointWriter:
    """Writes a solve's checkpoint every ``every`` shots (counted from the run's start,
    resumed or not; 0 for never: after the report whose shots pass a multiple of it, as a
    sweep of many patches' shots may) and when it ends, with the run's initial element count and
    its seconds so far (``elapsed()``)."""

    def __init__(self, path, fingerprint: str, every: int, solver: ProgressiveSolver, initial_elements: int,
                 elapsed: Callable[[], dict], last_saved: int | None):
        self.path, self.fingerprint, self.every, self.solver = path, fingerprint, every, solver
        self.initial_elements, self.elapsed, self.last_saved = initial_elements, elapsed, last_saved
        self.answer: Callable[[], dict] | None = None  # the rounds of refinement judged on the answer

    def save(self) -> None:
        run = {"initial_elements": self.initial_elements, "seconds": self.elapsed()}
        if self.answer is not None:
            run["answer"] = self.answer()
        checkpoints.write(self.path, self.fingerprint, self.solver.state_dict(), run)
        self.last_saved = self.solver.state.shots

    def after_shot(self, progress: Callable[[ShotReport], None] | None) -> Callable[[ShotReport], None] | None:
        """The solver's per-shot callback: save when due, then report ``progress``."""
        if not self.every:
            return progress

        previous = self.solver.state.shots

        def on_shot(report: ShotReport) -> None:
            nonlocal previous
            if report.shots // self.every > previous // self.every:
                self.save()
            previous = report.shots
            if progress is not None:
                progress(report)

        return on_shot

    def finish(self) -> None:
        """Save the final state (so a finished run can be continued), unless just saved."""
        if self.solver.state.shots != self.last_saved:
            self.save()


def _estimate_stats(gathered: GatheredError | None, interpolation: float) -> dict:
    """stats.json's error estimates: by final gathers (``evaluation.gathered_error``; None
    where the scene asks for no samples) and the interpolation estimate refinement ranks
    elements by (``adaptive.answer``)."""
    return {"estimated_error": gathered.relative_rms if gathered else None,
            "estimated_error_standard_error": gathered.standard_error if gathered else None,
            "error_samples": gathered.samples if gathered else 0,
            "interpolation_error": interpolation}


def _stats(scene: Scene, solver: ProgressiveSolver, final: Mesh, initial_elements: int, seconds: dict,
           resumed_from: int | None, rounds: list[RoundReport] | None = None,
           answer_refiner: Refiner | None = None) -> dict:
    """What stats.json says of a finished solve; ``final``: its mesh on the CPU; ``rounds``
    and ``answer_refiner``: those of refinement judged on the answer."""
    state = solver.state
    refiner = solver.refiner or answer_refiner
    return {
        "scene": str(scene.source) if scene.source else None,
        "elements": final.num_elements,
        "initial_elements": initial_elements,
        "elements_per_level": torch.bincount(final.level).tolist(),
        "surfaces": len(final.surface_names),
        "shots": state.shots,
        "sweeps": solver.sweep_count,  # each of many patches' shots at once (``solver.sweeps``)
        "patches": solver.patches.tree.num_patches if solver.patches is not None else None,
        "shooter_splits": solver.patches.shooter_splits if solver.patches is not None else 0,
        "hemicubes_rendered": solver.hemicubes_rendered,
        "unshot_fraction": solver.unshot_fraction,
        "hemicube_resolution": scene.solver.resolution,
        "reflector_hemicube_resolution": solver.reflector_hemicube_resolution,
        "reconstruction": scene.solver.reconstruction,  # how the vertex values were made
        "refine": {"pattern": scene.refine.pattern, "criterion": scene.refine_criterion,
                   "threshold": scene.refine.threshold, "relative": scene.refine.relative,
                   "absolute_threshold": refiner.threshold if refiner else None,
                   "splits": refiner.splits if refiner else 0, "tolerance": scene.refine.tolerance if scene.refines_by_answer else None,
                   "importance": scene.refine_importance if scene.refines_by_answer else None,
                   "rounds": [dataclasses.asdict(r) for r in rounds] if rounds is not None else None},
        "largest_angle_degrees": angle_quality(final),
        "emitted_power": solver.emitted_power.tolist(),
        # signed: overshooting leaves some unshot radiosity negative; emitted = absorbed + escaped + unshot
        "unshot_power": (state.unshot * solver.areas[:, None]).sum(0).tolist(),
        "absorbed_power": state.absorbed.tolist(),
        "escaped_power": state.escaped.tolist(),
        "gl_renderer": GLContext.renderer_name(),
        "device": str(solver.device),
        "resumed_from_shot": resumed_from,
        "seconds": {**seconds, "solve_phases": solver.timings()},
    }
