"""The whole job, scene to outputs: the library entry points behind the CLI.

    result = hemirad.solve(hemirad.load_scene("cornell_box"))
    result.write("out/")
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from . import display, export
from .errors import HemiradInputError
from .gl import GLContext
from .mesh import Mesh
from .meshing import build_mesh
from .meshview import pick_surface, surface_view
from .refine import Refiner
from .render import render_view
from .scene import Scene
from .solver import ProgressiveSolver, ShotReport, ambient_term
from .split import angle_quality


@dataclass
class Result:
    """A solved scene.

    Attributes:
        scene, mesh: what was solved.
        radiosity: (T, 3) element radiosity B.
        unshot: (T, 3) unshot radiosity left when the solver stopped.
        reflectance, emission: (T, 3) per element.
        stats: numbers worth keeping (elements, shots, unshot fraction, seconds per phase).
    """

    scene: Scene
    mesh: Mesh
    radiosity: torch.Tensor
    unshot: torch.Tensor
    reflectance: torch.Tensor
    emission: torch.Tensor
    stats: dict = field(default_factory=dict)

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

    def vertex_radiosity(self) -> torch.Tensor:
        """(V, 3) display radiosity at the vertices: area-weighted within each surface, and at
        T-vertices interpolated along the unsplit edge they lie on, so shading has no seams."""
        return display.conforming_vertex_values(self.mesh, display.vertex_values(self.mesh, self.display_radiosity))

    def exposure(self) -> float:
        if self.scene.camera.exposure is not None:
            return self.scene.camera.exposure
        emitting = (self.emission > 0).any(dim=1)
        return display.auto_exposure(self.display_radiosity, self.mesh.areas, emitting)

    def image(self) -> np.ndarray:
        """(height, width, 3) uint8 sRGB camera view."""
        linear = render_view(self.mesh, self.vertex_radiosity(), self.scene.camera,
                             triangles=display.conforming_triangles(self.mesh))
        return display.to_srgb8(linear, self.exposure())

    def mesh_image(self, surface: str | None = None, size: int = 512) -> np.ndarray:
        """(H, W, 3) uint8: one surface seen straight on, its elements shaded and outlined
        (the paper's (a)'(b)'(c)' pictures). ``surface``: a name such as ``room.floor``;
        default the scene's ``refine.view_surface``, else the floor."""
        index = pick_surface(self.mesh, surface or self.scene.refine.view_surface)
        linear = surface_view(self.mesh, self.vertex_radiosity(), index, size=size)
        return display.to_srgb8(linear, self.exposure())

    def write(self, folder) -> dict[str, Path]:
        """Write image.png, mesh.png, mesh.ply and stats.json into ``folder``; returns their paths."""
        folder = prepare_output_folder(folder)
        paths = {"image": folder / "image.png", "mesh view": folder / "mesh.png",
                 "mesh": folder / "mesh.ply", "stats": folder / "stats.json"}
        start = time.perf_counter()
        export.write_png(paths["image"], self.image())
        export.write_png(paths["mesh view"], self.mesh_image())
        rendered = time.perf_counter()
        vertex = self.vertex_radiosity()
        export.write_ply(paths["mesh"], self.mesh, vertex, display.to_srgb8(vertex.numpy(), self.exposure()))
        self.stats.setdefault("seconds", {}).update(
            render=rendered - start, export=time.perf_counter() - rendered)
        export.write_stats(paths["stats"], self.stats)
        return paths


def prepare_output_folder(folder) -> Path:
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise HemiradInputError(f"cannot create the output folder {folder}: {exc.strerror or exc}.") from exc
    if not os.access(folder, os.W_OK):
        raise HemiradInputError(f"the output folder {folder} is not writable.")
    return folder


def solve(scene: Scene, progress: Callable[[ShotReport], None] | None = None) -> Result:
    """Mesh the scene and run progressive refinement until the scene's stopping rule."""
    options = scene.solver
    start = time.perf_counter()
    mesh = build_mesh(scene)
    meshed = time.perf_counter()
    reflectance = scene.reflectance_table()[mesh.material]
    emission = scene.emission_table()[mesh.material]
    refiner = Refiner(scene.refine, emission) if scene.refine.enabled else None
    solver = ProgressiveSolver(mesh, reflectance, emission, options.resolution, refiner)
    try:
        state = solver.run(options.max_shots, options.unshot_fraction, progress)
    finally:
        solver.close()
    solved = time.perf_counter()
    final = solver.mesh
    levels = torch.bincount(final.level)
    stats = {
        "scene": str(scene.source) if scene.source else None,
        "elements": final.num_elements,
        "initial_elements": mesh.num_elements,
        "elements_per_level": levels.tolist(),
        "surfaces": len(final.surface_names),
        "shots": state.shots,
        "unshot_fraction": solver.unshot_fraction,
        "hemicube_resolution": options.resolution,
        "refine": {"pattern": scene.refine.pattern, "criterion": scene.refine.criterion,
                   "threshold": scene.refine.threshold, "relative": scene.refine.relative,
                   "absolute_threshold": refiner.threshold if refiner else None,
                   "splits": refiner.splits if refiner else 0},
        "largest_angle_degrees": angle_quality(final),
        "emitted_power": solver.emitted_power.tolist(),
        "absorbed_power": state.absorbed.tolist(),
        "escaped_power": state.escaped.tolist(),
        "gl_renderer": GLContext.renderer_name(),
        "seconds": {"mesh": meshed - start, "solve": solved - meshed,
                    "solve_phases": solver.timings()},
    }
    return Result(scene, final, state.radiosity, state.unshot, solver.reflectance, solver.emission, stats)
