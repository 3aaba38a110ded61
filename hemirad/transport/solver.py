"""Progressive-refinement radiosity (Cohen, Chen, Wallace & Greenberg 1988), RGB.

The state is per element: radiosity B and unshot radiosity dB, (T, 3) float64 each. A shot
takes the element with the most unshot power, renders its hemicube, and hands every
receiver j the radiosity  rho_j dB_s F_sj A_s / A_j  (DESIGN §1).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import torch

from hemirad.adaptive.criteria import ShotContext
from hemirad.output.display import luminance
from hemirad.core.fastops import row_sums
from hemirad.transport.formfactor import HemicubeFormFactors, element_form_factors
from hemirad.transport.gl import GLContext
from hemirad.adaptive.gradient import ShotView, form_factor_gradient
from hemirad.geometry.mesh import Mesh
from hemirad.adaptive.refine import Refiner
from hemirad.adaptive.relabel import descendants, relabel_atlas, relabel_form_factors, split_pixels_of
from hemirad.core.runtime import deterministic, keep_freed_memory, torch_threads
from hemirad.geometry.split import GrowingRows, inherit

#: The version of the numbers a solve produces. Bump it with any change, anywhere (meshing,
#: hemicubes, form factors, gradients, criteria, splitting, this solver), that alters any
#: number a solve gives: a mesh, a radiosity, a split decision (``scripts/fingerprint.py``
#: shows it). Checkpoints record it, and one made under another arithmetic is not resumed.
ARITHMETIC = 1


def received_radiosity(form_factors: torch.Tensor, shot_power: torch.Tensor,
                       reflectance: torch.Tensor, areas: torch.Tensor) -> torch.Tensor:
    """Radiosity each receiver reflects from one shot.

    Args:
        form_factors: (T,) F_sj from the shooter to every element.
        shot_power: (3,) the shooter's unshot power dB_s A_s.
        reflectance: (T, 3) rho_j.
        areas: (T,) A_j.
    Returns:
        (T, 3) rho_j F_sj dB_s A_s / A_j.
    """
    return reflectance * (form_factors / areas)[:, None] * shot_power[None, :]


def ambient_term(unshot: torch.Tensor, reflectance: torch.Tensor, areas: torch.Tensor) -> torch.Tensor:
    """Cohen et al.'s ambient radiosity: the unshot power, spread evenly and inter-reflected.

    Args:
        unshot: (T, 3) dB; reflectance: (T, 3); areas: (T,).
    Returns:
        (3,) ambient radiosity; element j is displayed as B_j + rho_j * ambient.
    """
    total_area = areas.sum()
    mean_reflectance = (reflectance * areas[:, None]).sum(0) / total_area
    mean_unshot = (unshot * areas[:, None]).sum(0) / total_area
    return mean_unshot / (1.0 - mean_reflectance)


@dataclass
class Seen:
    """What one pass's hemicube sees (P pixels, flattened), rendered or relabelled.

    Attributes:
        element: (P,) element per pixel, -1 for none; front: (P,) bool.
        eye: (3,) and frame: (3, 3) of the hemicube.
        form_factors: (T,) F_sj summed from these pixels.
        changed: (N,) for a relabelled atlas, the pixels relabelled (the only ones that see
            new elements); None for a render.
    """

    element: torch.Tensor
    front: torch.Tensor
    eye: torch.Tensor
    frame: object
    form_factors: torch.Tensor
    changed: torch.Tensor | None = None

    def relabelled(self, view: ShotView, parent: torch.Tensor, split: torch.Tensor, mesh: Mesh,
                   weight: torch.Tensor) -> "Seen":
        """What the same hemicube sees after a split (``relabel.py``): ``parent`` (T',) maps
        the new ``mesh``'s elements to the old ones, of which the (K,) sorted ``split`` were
        split; ``view`` is this pass's ShotView."""
        descent = descendants(parent, split)
        pixels = split_pixels_of(self.element, descent)
        element = relabel_atlas(self.element, view.hits(pixels), pixels, descent, mesh)
        form_factors = relabel_form_factors(self.form_factors, descent, element, self.front, weight, pixels)
        return Seen(element, self.front, self.eye, self.frame, form_factors, pixels)


@dataclass
class SolverState:
    """Everything a solve has computed so far.

    Attributes:
        radiosity: (T, 3) B.
        unshot: (T, 3) dB.
        shots: shots done.
        absorbed: (3,) power absorbed by receivers, (1 - rho) of what reached their front.
        escaped: (3,) power that reached no element's front (open scenes, back faces).
    """

    radiosity: torch.Tensor
    unshot: torch.Tensor
    shots: int = 0
    absorbed: torch.Tensor | None = None
    escaped: torch.Tensor | None = None

    def __post_init__(self):
        zero = torch.zeros(3, dtype=torch.float64, device=self.radiosity.device)
        self.absorbed = zero.clone() if self.absorbed is None else self.absorbed.to(zero)
        self.escaped = zero.clone() if self.escaped is None else self.escaped.to(zero)


@dataclass
class ShotReport:
    shots: int
    shooter: int
    elements: int
    unshot_fraction: float
    seconds: float


class ProgressiveSolver:
    """Shoots until a shot count or an unshot-energy fraction is reached, refining the mesh
    during each shot when given a ``Refiner``.

    Args:
        mesh: the initial elements.
        reflectance, emission: (T, 3) per element.
        resolution: hemicube resolution R.
        refiner: splits receivers during shots (DESIGN §3); None for a fixed mesh.
        cull: per-face frustum culling in the hemicube (the same numbers, drawn faster).
        relabel: between the passes of a refining shot, carry the hemicube's item atlas over
            to the children (``relabel.py``) instead of rendering again; the shot is still
            committed with a real render of the final mesh.
        bound: leave out of the interior Jacobian the receivers whose criterion bounds that
            part of their score under the threshold (``Refiner.could_exceed``): the same
            splits, with less autograd work.
        device: where the tensors live and the torch work runs (``device.select_device``);
            on CUDA the hemicubes are drawn by the GPU's OpenGL context. The inputs may be
            anywhere; ``state_dict`` is always on the CPU.
    Attributes:
        mesh, reflectance, emission, areas: current, as refinement changes them (on ``device``).
    """

    def __init__(self, mesh: Mesh, reflectance: torch.Tensor, emission: torch.Tensor, resolution: int,
                 refiner: Refiner | None = None, cull: bool = True, relabel: bool = True, bound: bool = True,
                 device: torch.device | str = "cpu"):
        self.device = torch.device(device)
        mesh = mesh.to(self.device)
        reflectance, emission = reflectance.to(self.device), emission.to(self.device)
        self.mesh = mesh
        self.areas = mesh.areas
        self._adopt(reflectance, emission, SolverState(radiosity=emission.clone(), unshot=emission.clone()))
        self.emitted_power = (emission * self.areas[:, None]).sum(0)  # (3,)
        self.form_factors = HemicubeFormFactors(mesh, resolution, cull, self.device)
        self.refiner = refiner
        self.relabel = relabel
        self.bound = bound
        self.update_seconds = self.gradient_seconds = self.refine_seconds = 0.0

    def close(self) -> None:
        self.form_factors.close()

    @property
    def unshot_fraction(self) -> float:
        unshot_power = (self.state.unshot * self.areas[:, None]).sum()
        return float(unshot_power / self.emitted_power.sum())

    def _render(self, shooter: int) -> "Seen":
        """What the hemicube of ``shooter`` sees, rendered, with F_sj."""
        ff = self.form_factors
        element, front, eye, frame = ff.render(shooter)
        element, front = element.reshape(-1), front.reshape(-1)
        start = time.perf_counter()
        F = element_form_factors(element, front, ff.weights.reshape(-1), self.mesh.num_elements)
        ff.seconds += time.perf_counter() - start
        return Seen(element, front, torch.from_numpy(eye).to(self.device), frame, F)

    def _gradient(self, seen: "Seen", ctx: ShotContext) -> tuple[torch.Tensor | None, ShotView]:
        """dF_sj/dc when the criterion reads it (else None), and the pass's ShotView.

        J is computed for the pass's candidates whose score could pass the threshold
        (``Refiner.could_exceed``); its other rows are zero.
        """
        ff = self.form_factors
        start = time.perf_counter()
        view = ShotView.from_render(seen.element, seen.front, ff.weights, seen.eye, seen.frame, ff.normals,
                                    ff.centroids)
        wanted = self.refiner.jacobian
        J = None
        if wanted is not None:
            options = self.refiner.options
            J = form_factor_gradient(view, interior=options.interior or wanted == "interior",
                                     shadow_edges=options.shadow_edges and wanted == "full", wanted=ctx.candidates,
                                     plane_ids=self.mesh.plane_ids, pixels=seen.changed,
                                     interior_wanted=self.refiner.could_exceed(ctx, view, seen.changed) if self.bound else None)
        self.gradient_seconds += time.perf_counter() - start
        return J, view

    def _luminance_per_form_factor(self, shot_power: torch.Tensor, rows: torch.Tensor | None = None) -> torch.Tensor:
        """(T,) or (R,) for ``rows``: the luminance of what a receiver gets per unit F_sj from
        ``shot_power`` (3,), rho_j dB_s A_s / A_j; a child's differs from its parent's by its area."""
        if rows is None:
            return luminance(self.reflectance * shot_power) / self.areas
        return luminance(self.reflectance.index_select(0, rows) * shot_power) / self.areas.index_select(0, rows)

    def _adopt(self, reflectance: torch.Tensor, emission: torch.Tensor, state: SolverState) -> None:
        """Make these the per-element values, kept in buffers that splits append to
        (``split.GrowingRows``; rows are carried over without copying the old ones)."""
        self._per_element = [GrowingRows(v) for v in (reflectance, emission, state.radiosity, state.unshot)]
        self.reflectance, self.emission, state.radiosity, state.unshot = (rows.values for rows in self._per_element)
        self.state = state

    def _split(self, selected: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Split the selected elements; children inherit B and dB. Every element keeps its
        index (a split one's now holds its first child: ``split.split_triangles``).

        Returns:
            (T',) the old element each new one lies in, and (K,) the old elements that were
            split (the selected ones and those grading added), sorted.
        """
        T = self.mesh.num_elements
        self.mesh, parent = self.refiner.split(self.mesh, selected)
        self.reflectance, self.emission, self.state.radiosity, self.state.unshot = (
            rows.inherit(parent) for rows in self._per_element)
        self.areas = self.mesh.areas
        self.form_factors.set_geometry(self.mesh)
        return parent, torch.unique(parent[T:])

    def shoot(self) -> int | None:
        """One shot from the element with the largest unshot power; None when nothing is left.

        With a refiner, receivers it selects are split and the shot is redone on the new
        elements before anything is committed, until no receiver needs splitting. Each pass
        judges only the elements the previous one made: the first judges every splittable
        receiver, the next the children of those it split, and so on down the levels, as a
        recursive subdivision would. Unsplit receivers keep their pixels, so judging them
        again would only repeat the verdict (or follow the hemicube's aliasing at split
        edges); gradients are computed for the judged receivers only. Between passes what the
        hemicube sees is carried over to the children (``relabel``) rather than rendered
        again; the pass that is committed is always a real render.
        """
        state = self.state
        power = state.unshot * self.areas[:, None]  # (T, 3)
        shooter = int(torch.argmax(row_sums(power)))
        shot_power = power[shooter].clone()
        if float(shot_power.sum()) <= 0.0:
            return None
        candidates = None if self.refiner is None else self.refiner.splittable(self.mesh, shooter)
        gain = None if self.refiner is None else self._luminance_per_form_factor(shot_power)
        relabelled = None  # what the next pass sees, when carried over instead of rendered
        while True:
            seen = relabelled if relabelled is not None else self._render(shooter)
            if self.refiner is None:
                break
            start = time.perf_counter()
            ctx = ShotContext(self.mesh, shooter, seen.eye, self.form_factors.normals[shooter], seen.form_factors,
                              gain, None, candidates)
            self.refine_seconds += time.perf_counter() - start
            ctx.jacobian, view = self._gradient(seen, ctx)
            start = time.perf_counter()
            selected = self.refiner.select(ctx)
            if not bool(selected.any()):
                self.refine_seconds += time.perf_counter() - start
                if relabelled is not None:  # commit what a real render of the final mesh sees
                    seen = self._render(shooter)
                break
            T = self.mesh.num_elements
            parent, split = self._split(selected)
            new = torch.cat([split, torch.arange(T, len(parent), device=self.device)])  # their rows in the new mesh
            candidates = self.refiner.splittable(self.mesh, shooter, new)
            gain = inherit(gain, parent).index_copy_(0, new, self._luminance_per_form_factor(shot_power, new))
            relabelled = None
            if self.relabel and not bool((split == shooter).any()):  # the eye has not moved
                relabelled = seen.relabelled(view, parent, split, self.mesh, self.form_factors.weights.reshape(-1))
            self.refine_seconds += time.perf_counter() - start
        F = seen.form_factors
        delta = received_radiosity(F, shot_power, self.reflectance, self.areas)
        start = time.perf_counter()
        state.radiosity += delta
        state.unshot += delta
        state.unshot[shooter] = 0.0
        state.absorbed += ((1.0 - self.reflectance) * F[:, None]).sum(0) * shot_power
        state.escaped += (1.0 - F.sum()) * shot_power
        state.shots += 1
        self.update_seconds += time.perf_counter() - start
        return shooter

    def run(self, max_shots: int, unshot_fraction: float,
            progress: Callable[[ShotReport], None] | None = None) -> SolverState:
        start = time.perf_counter()
        keep_freed_memory()
        with torch_threads(1 if GLContext.is_software() else torch.get_num_threads()), deterministic(self.device):
            while self.state.shots < max_shots and self.unshot_fraction > unshot_fraction:
                shooter = self.shoot()
                if shooter is None:
                    break
                if progress is not None:
                    progress(ShotReport(self.state.shots, shooter, self.mesh.num_elements,
                                        self.unshot_fraction, time.perf_counter() - start))
        return self.state

    def timings(self) -> dict[str, float]:
        return {**self.form_factors.timings(), "gradient": self.gradient_seconds,
                "refine": self.refine_seconds, "update": self.update_seconds}

    def state_dict(self) -> dict:
        """Everything later shots depend on, as plain tensors, numbers and strings.

        Keys: ``mesh`` (``Mesh.state_dict``; refinement changes it), ``reflectance``,
        ``emission``, ``radiosity``, ``unshot`` (T, 3) float64; ``absorbed``, ``escaped``,
        ``emitted_power`` (3,) float64; ``shots``; ``refiner`` (its own ``state_dict``, or
        None) and ``timings``. ``emitted_power`` is kept rather than recomputed because the
        refined mesh's areas sum to it only to rounding, and the stopping rule divides by it.
        """
        s = self.state
        saved = {"reflectance": self.reflectance, "emission": self.emission, "radiosity": s.radiosity,
                 "unshot": s.unshot, "absorbed": s.absorbed, "escaped": s.escaped,
                 "emitted_power": self.emitted_power}
        return {"mesh": self.mesh.state_dict(), **{k: v.cpu().clone() for k, v in saved.items()}, "shots": s.shots,
                "refiner": self.refiner.state_dict() if self.refiner is not None else None,
                "timings": self.timings()}

    def load_state_dict(self, state: dict) -> None:
        """Continue from ``state_dict()``'s output: the next shot is the one that would have followed.

        The solver must have been made for the same scene (resolution, refiner options, and
        the initial mesh, whose bounds set the hemicube's near and far planes). Raises
        ValueError when the parts do not fit together, e.g. a truncated or edited state.
        """
        mesh = Mesh.from_state_dict(state["mesh"]).to(self.device)
        T = mesh.num_elements
        per_element = {k: state[k] for k in ("reflectance", "emission", "radiosity", "unshot")}
        for key, value in per_element.items():
            if not isinstance(value, torch.Tensor) or value.shape != (T, 3) or value.dtype != torch.float64:
                raise ValueError(f"{key} must be a ({T}, 3) float64 tensor")
        for key in ("absorbed", "escaped", "emitted_power"):
            if not isinstance(state[key], torch.Tensor) or state[key].shape != (3,):
                raise ValueError(f"{key} must be a (3,) tensor")
        if (state["refiner"] is None) != (self.refiner is None):
            raise ValueError("the state was saved with refinement " + ("off" if state["refiner"] is None else "on"))
        self.mesh, self.areas = mesh, mesh.areas
        per_element = {k: v.to(self.device) for k, v in per_element.items()}
        self._adopt(per_element["reflectance"], per_element["emission"],
                    SolverState(per_element["radiosity"], per_element["unshot"], int(state["shots"]),
                                state["absorbed"], state["escaped"]))
        self.emitted_power = state["emitted_power"].to(torch.float64).to(self.device)
        if self.refiner is not None:
            self.refiner.load_state_dict(state["refiner"])
        self.form_factors.set_geometry(mesh)
        t = state["timings"]
        self.form_factors.hemicube.raster_seconds = float(t["raster"])
        self.form_factors.hemicube.readback_seconds = float(t["readback"])
        self.form_factors.seconds = float(t["form_factors"])
        self.gradient_seconds, self.refine_seconds, self.update_seconds = (
            float(t["gradient"]), float(t["refine"]), float(t["update"]))

