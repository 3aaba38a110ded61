"""Progressive-refinement radiosity (Cohen, Chen, Wallace & Greenberg 1988), RGB.

The state is per element: radiosity B and unshot radiosity dB, (T, 3) float64 each. A shot
takes the element with the most unshot power, renders its hemicube, and hands every
receiver j the radiosity  rho_j dB_s F_sj A_s / A_j  (docs/DESIGN.md §1).
"""
from __future__ import annotations

import collections
import contextlib
import os
import sys
import threading
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable, Iterator, Protocol

import numpy as np
import torch

from hemirad.core.errors import HemiradWarning
from hemirad.core.fastops import flatnonzero, row_sums
from hemirad.core.runtime import deterministic, keep_freed_memory, release_freed_memory, torch_threads
from hemirad.core.timing import Profiler
from hemirad.geometry.mesh import Mesh
from hemirad.geometry.split import GrowingRows
from hemirad.scene.model import SMALL_RECEIVER_CHOICES
from hemirad.transport.gl import GLContext
from hemirad.transport.hemicube import OFF_AXIS_TANGENT
from hemirad.transport.nearfield import TOTALS as NEAR_TOTALS
from hemirad.transport.nearfield import NearReceivers, NearShooter, incident_power, near_fields
from hemirad.transport.renderer import HemicubeRenderer
from hemirad.transport.rowcache import FormFactorRows
from hemirad.transport.shooters import PatchShooters, eye_points
from hemirad.transport.smallreceivers import BOUNCE_MAX_PIXELS, MAX_PIXELS, small_receiver_form_factors
from hemirad.transport.sweep import GroupLight, SweepTransport, make_a_part
from hemirad.transport.view import HemicubeView

# The phases a solve's time is reported in (``ProgressiveSolver.timings``, stats.json).
PHASES = ("raster", "readback", "form_factors", "gradient", "refine", "update")

#: The version of the numbers a solve produces. Bump it with any change, anywhere (meshing,
#: hemicubes, form factors, gradients, criteria, splitting, this solver), that alters any
#: number a solve gives: a mesh, a radiosity, a split decision (``scripts/fingerprint.py``
#: shows it). Checkpoints record it, and one made under another arithmetic is not resumed.
#: 29: a round's growth is held to its ranking solve's kept light scaled to every patch
#: (``whole_kept_light_bytes``), and a budget's ranking round reports its interpolation estimate;
#: 28: where an element budget sizes the rounds, a round's solve that a split follows shoots
#: the emitters, then the patches holding most of their light, once, then bounces the light
#: among the patches drawn (``answer.ranking_solve``);
#: 27: a round's solve that refinement judged on the answer follows with a split stops at
#: ten times the unshot fraction (``answer.RANKING_UNSHOT``);
#: 26: refinement judged on the answer ranks the elements by their error over the three
#: colour channels, not by luminance, weighed by the camera's pixels (refine.importance), and
#: sizes a round for 0.8 of its tolerance; its first solve shoots from patches capped at 0.3
#: of the scene's extent where a round will follow;
#: 25: a round of refinement by the answer grows the mesh no more than its fresh solve's kept
#: light is predicted to fit ``solver.cache_mb`` (``answer.memory_growth``), and lamps whose
#: elements are small beside the scene shoot without eyes (``assembly.emitter_eye_level``);
#: 24: a sweep that outgrows ``solver.cache_mb`` goes one patch at a time up to
#: ``GROUPS_AHEAD`` groups later (its worker's groups are taken in later);
#: 23: a footprint's rim shoots by its straight stretches (alone at its corners), and a
#: curved cap another object reaches into is made from smaller cubes, not its elements;
#: 22: near-field pairs half a source side apart or more take one Gauss rule over each
#: whole source edge;
#: 21: with patches, nodes that emit nothing draw at ``reflector_resolution`` (auto: half
#: of a resolution over 128);
#: 20: a sweep group's small-receiver rows are made together (the last bits of atan2);
#: 19: near fields take a small receiver's factor from its points (by reciprocity), and
#: Lambert's factor to a triangle wholly above its point sums its three edges alone;
#: 18: the answer's first solve corrects the lamps' small receivers only;
#: 17: a round of refinement by the answer grows the mesh up to 5.5 times, and no more than
#: its tolerance is predicted to need;
#: 16: only the lamps' shots correct receivers of a few pixels (reflecting shooters those
#: under a pixel, refining), and unrefined runs correct the lamps';
#: 15: a face hovering a hair in front of a surface covers it where contacts are meshed;
#: 14: emitters shoot from eyes where refinement is judged on the answer; 13: no round for a
#: sliver of the budget; 12: contour integrals cut at the receiver
#: edges' feet, near totals by area with contacts meshed; 11: a covered node shoots whole,
#: rounds grow the mesh up to 2.5 times; 10: rounds to an element budget by equal ratios;
#: 9: refining by the answer, auto patches capped and rounds two levels deep; 8: near fields
#: made many shooters at once (rounding).
ARITHMETIC = 29

# Memory for kept form-factor rows by default: a row costs 12 bytes per element it reaches.
DEFAULT_CACHE_BYTES = 256 << 20
#: A sweep makes the near fields of this many patches' nodes at once (``nearfield.near_fields``;
#: a group, in patch index order), keeping their hemicubes' views until then (1 MB each at
#: resolution 256; ``GROUPS_AHEAD`` + 1 groups' at most).
NEAR_BATCH = 32
#: How many groups the drawing thread may run ahead of the worker that makes their light
#: (``ProgressiveSolver._make_group``), which runs at the lowest priority (``_yield_to_drawing``):
#: the light is needed at the sweep's end, the drawing thread and Mesa's two threads are the
#: sweep's critical path, and the worker takes what cores they leave. Where the drawing
#: thread would wait for it, it makes the parts of the groups that the worker has not begun
#: (``sweep.make_a_part``), so a short lead costs no time and holds fewer views.
#: Measured on 2 cores (interleaved runs, seconds and peak memory), 8 groups ahead against 2:
#: the furnished room 9.5 / 9.3 s, 1.67 / 1.50 GB against 9.4 / 9.4 s, 1.51 / 1.43 GB; refined
#: once by the answer 79.6 s, 3.57 GB against 81.2 s, 3.28 GB; the study's floating and office
#: runs to 3,416 elements the same within 0.1 s.
GROUPS_AHEAD = 2


def _yield_to_drawing() -> None:
    """Give the calling thread (a sweep's worker) the lowest priority, where a thread has a
    nice value of its own (Linux): it then runs on what the drawing threads leave
    (``GROUPS_AHEAD``)."""
    if sys.platform.startswith("linux"):
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
        except OSError:  # not allowed here: the same numbers, at the same priority
            pass


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


class ShotRefiner(Protocol):
    """What refines the mesh during a shot (``adaptive.refine.Refiner``): the solver hands it
    each shot and commits the view it returns.

    ``shoot`` may render the shooter's hemicube several times, split receivers through
    ``ProgressiveSolver.adopt_split`` between the renders, and returns what the committed
    pass saw, a real render of the final mesh. ``state_dict`` / ``load_state_dict`` carry
    what a resumed solve needs beyond the options.
    """

    def shoot(self, solver: "ProgressiveSolver", shooter: int, shot_power: torch.Tensor) -> HemicubeView: ...

    def state_dict(self) -> dict: ...

    def load_state_dict(self, state: dict) -> None: ...


class ProgressiveSolver:
    """Shoots until a shot count or an unshot-energy fraction is reached, refining the mesh
    during each shot when given a refiner.

    Args:
        mesh: the initial elements.
        reflectance, emission: (T, 3) per element.
        resolution: hemicube resolution R.
        reflector_resolution: with patches, the resolution of the nodes none of whose elements
            emits (``scene.model.resolved_reflector_resolution``); None: ``resolution``.
        refiner: splits receivers during shots (``ShotRefiner``; docs/DESIGN.md §3); None
            for a fixed mesh.
        cull: per-face frustum culling in the hemicube (the same numbers, drawn faster).
        patches: shoot by patches (their elements' power from the nodes of their trees)
            instead of by elements; None: every element shoots, as in the paper.
        overshoot: with patches, a shooter also shoots the radiosity it can expect to
            receive later, rho_s times the ambient term (Feda & Purgathofer 1992), and keeps
            it as negative unshot radiosity; power stays conserved exactly and the solve
            converges in fewer shots.
        sweeps: with patches, while no refiner runs the shots, every patch holding unshot
            power shoots it at once (a Jacobi sweep: two sparse products over the kept
            light, ``sweep.SweepTransport``) instead of the strongest alone; each patch
            that shoots counts as a shot. Overshooting is then moot. Should the kept light
            outgrow ``cache_bytes``, the solve goes on shooting one patch at a time.
        near_reach: the receivers within this many shooter radii of a shooter's centroid
            get its light as its initial elements send it (``nearfield``); 0: none. Without
            patches, as each element sends it (the paper's configuration has none).
        near_totals: how much of a source's light its near receivers take
            (``nearfield.TOTALS``): G's hemicube's total, or the source's own.
        refine_shots: with a refiner, refine during the first this many shots only, then
            shoot on the mesh they made; None: every shot.
        cache_bytes: memory for the form-factor rows of shooters that shot
            (``FormFactorRows``): a shooter that shoots again on an unchanged mesh reuses its
            row instead of rendering its hemicube again (the same numbers).
        device: where the tensors live and the torch work runs (``device.select_device``);
            on CUDA the hemicubes are drawn by the GPU's OpenGL context. The inputs may be
            anywhere; ``state_dict`` is always on the CPU.
        small_receivers: how receivers that cover few hemicube pixels get their form factors
            (``scene.model.SMALL_RECEIVER_CHOICES``): pixels, lamps or closed_form
            (``smallreceivers``), applied to the row a shot uses and keeps (``shot_row``); the views the refiner and
            the shooter tests read keep their pixel sums.
        refined_small_receivers: the same once ``adopt_split`` has refined the mesh (the
            answer's rounds); None: ``small_receivers`` throughout.
    Attributes:
        mesh, reflectance, emission, areas: current, as refinement changes them (on ``device``).
        profiler: the seconds spent per phase (``PHASES``), the refiner's included.
    """

    def __init__(self, mesh: Mesh, reflectance: torch.Tensor, emission: torch.Tensor, resolution: int,
                 refiner: ShotRefiner | None = None, cull: bool = True, cache_bytes: int = DEFAULT_CACHE_BYTES,
                 patches: PatchShooters | None = None, overshoot: bool = False, near_reach: float = 0.0,
                 near_totals: str = "hemicube",
                 refine_shots: int | None = None, device: torch.device | str = "cpu",
                 small_receivers: str = "pixels", refined_small_receivers: str | None = None, sweeps: bool = False,
                 reflector_resolution: int | None = None):
        self.device = torch.device(device)
        mesh = mesh.to(self.device)
        reflectance, emission = reflectance.to(self.device), emission.to(self.device)
        self.mesh = mesh
        self.areas = mesh.areas
        self._adopt(reflectance, emission, SolverState(radiosity=emission.clone(), unshot=emission.clone()))
        self.emitted_power = (emission * self.areas[:, None]).sum(0)  # (3,)
        self.profiler = Profiler(PHASES)
        self.renderer = HemicubeRenderer(mesh, resolution, cull, self.device, self.profiler)
        # with patches, the nodes that emit nothing draw at this resolution (``_renderer_of``)
        self.reflector_resolution = reflector_resolution if reflector_resolution != resolution else None
        self.reflector_renderer: HemicubeRenderer | None = None  # made when a node first draws there
        refined_small_receivers = small_receivers if refined_small_receivers is None else refined_small_receivers
        for choice in (small_receivers, refined_small_receivers):
            if choice not in SMALL_RECEIVER_CHOICES:
                raise ValueError(f"small_receivers must be one of {', '.join(SMALL_RECEIVER_CHOICES)}, "
                                 f"not {choice!r}")
        self.small_receivers, self.refined_small_receivers = small_receivers, refined_small_receivers
        self.refiner = refiner
        self.refine_shots = refine_shots
        self.rows = FormFactorRows(cache_bytes)
        self.patches = patches
        self.overshoot = overshoot and patches is not None
        self.sweeps = sweeps and patches is not None
        self.sweep_count = 0  # sweeps made (``sweeps``)
        self._transport: SweepTransport | None = None  # the kept light of the nodes that shot
        self._outgrown_bytes = 0  # what the kept light held when it outgrew ``cache_bytes``
        if near_totals not in NEAR_TOTALS:
            raise ValueError(f"near_totals must be one of {', '.join(NEAR_TOTALS)}, not {near_totals!r}")
        self.near_reach, self.near_totals = near_reach, near_totals
        self._near: dict[int, NearReceivers] = {}
        self._views: dict[int, HemicubeView] = {}  # rendered for shooters whose near field is not made yet
        self._emitters: tuple[np.ndarray, np.ndarray] | None = None  # ``_emitting``
        self._worker: ThreadPoolExecutor | None = None  # makes sweep groups' light (``_make_group``)
        if patches is not None:
            self.use_patches(patches)

    def close(self) -> None:
        for renderer in self._renderers:
            renderer.close()
        if self._worker is not None:
            self._worker.shutdown()

    @property
    def _renderers(self) -> list[HemicubeRenderer]:
        return [self.renderer] + ([self.reflector_renderer] if self.reflector_renderer is not None else [])

    @property
    def cache_bytes(self) -> int:
        """The memory the kept rows, and the light kept for sweeps, may each take."""
        return self.rows.budget_bytes

    @property
    def kept_light_bytes(self) -> int:
        """What the light kept for sweeps holds (``sweep.SweepTransport.nbytes``); where it
        outgrew ``cache_bytes``, what it held then; 0 where none was kept."""
        return self._transport.nbytes if self._transport is not None else self._outgrown_bytes

    @property
    def whole_kept_light_bytes(self) -> int:
        """``kept_light_bytes`` as if every patch had been drawn: scaled by all the patches
        over those drawn, where a solve stopped before drawing them all (``answer.ranking_solve``).
        The patches it leaves hold little light and see less, so this errs high: on the bundled
        scenes' first solves 0.98-1.92x what drawing them all kept."""
        if self._transport is None or not self._transport.groups:
            return self.kept_light_bytes
        drawn = self._drawn_patches()
        return int(self.kept_light_bytes * len(drawn) / int(drawn.sum()))

    def _drawn_patches(self) -> torch.Tensor:
        """(P,) bool the patches whose groups' light the sweeps keep (drawn before)."""
        groups = torch.tensor(sorted(self._transport.groups), dtype=torch.int64, device=self.device)
        return torch.isin(torch.arange(self.patches.tree.num_patches, device=self.device) // NEAR_BATCH, groups)

    @property
    def hemicubes_rendered(self) -> int:
        return sum(renderer.renders for renderer in self._renderers)

    @property
    def reflector_hemicube_resolution(self) -> int:
        """The resolution the reflecting nodes drew at: ``reflector_resolution`` where any did
        (``_renderer_of``), else that of every node."""
        drew = self.reflector_renderer is not None and self.reflector_renderer.renders > 0
        return (self.reflector_renderer if drew else self.renderer).hemicube.resolution

    def _renderer_of(self, node: int) -> HemicubeRenderer:
        """Where ``node`` (of the patches' trees) draws: at ``reflector_resolution`` when none of
        its elements emits and its receivers under a pixel get their pixel sums (not
        ``closed_form``: a refined mesh's). There a coarser hemicube only moves receivers from
        pixel sums to closed forms, and while shots refine their criteria judge the pixels:
        the Fig. 6(c)-class run, refined and converged, with its reflectors at half its 256
        split to 91,424 elements against 89,333, and took 45.3 s against 44.8 s once its
        refining shots drew at 256."""
        if (self.reflector_resolution is None or self.small_receivers == "closed_form"
                or self._emitting(node)[0]):
            return self.renderer
        if self.reflector_renderer is None:
            self.reflector_renderer = HemicubeRenderer(self.mesh, self.reflector_resolution, self.renderer.hemicube.cull,
                                                       self.device, self.profiler)
        return self.reflector_renderer

    def _set_geometry(self, mesh: Mesh) -> None:
        for renderer in self._renderers:
            renderer.set_geometry(mesh)

    def use_patches(self, patches: PatchShooters) -> None:
        """Shoot with ``patches``, built on the current mesh (whose elements are its leaves)."""
        self.patches = patches
        patches.use_mesh(self.mesh)
        self._forget_kept_light()

    def _forget_kept_light(self) -> None:
        """Drop what was kept for the shooters of the current mesh and patches (rows, near
        fields, views, the sweeps' matrices): they changed."""
        self.rows.clear()
        self._near.clear()
        self._views.clear()
        self._emitters = None
        self._transport = None

    def restart(self, patches: PatchShooters) -> None:
        """Solve the current mesh afresh with ``patches`` built on it: every radiosity back to
        the emission, all of it unshot; the shots and sweeps made so far stay counted."""
        self.use_patches(patches)
        state = self.state
        state.radiosity.copy_(self.emission)
        state.unshot.copy_(self.emission)
        state.absorbed.zero_()
        state.escaped.zero_()

    @property
    def unshot_fraction(self) -> float:
        """The magnitude of the unshot power over the emitted power (overshooting leaves
        some unshot radiosity negative)."""
        unshot_power = (self.state.unshot.abs() * self.areas[:, None]).sum()
        return float(unshot_power / self.emitted_power.sum())

    @property
    def active_refiner(self) -> ShotRefiner | None:
        """The refiner while shots may still refine (``refine_shots``), else None."""
        if self.refine_shots is not None and self.state.shots >= self.refine_shots:
            return None
        return self.refiner

    def render(self, shooter: int) -> HemicubeView:
        """What the hemicube of ``shooter`` (an element, or with patches a node of their
        trees) sees on the current mesh, with F_sj."""
        if self.patches is None:
            return self.renderer.render(shooter)
        return self._renderer_of(shooter).render_at(*self._placement(shooter))

    def _placement(self, node: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where a node of the patches' trees renders its hemicube: ``render_at``'s point,
        normal and tangent."""
        tree = self.patches.tree
        return tree.centroid[node].numpy(), tree.normal[node].numpy(), OFF_AXIS_TANGENT

    def shooter_elements(self, shooter: int) -> int | torch.Tensor:
        """The elements ``shooter`` is: the element itself, or (K,) a node's elements."""
        return shooter if self.patches is None else self.patches.members(shooter)

    def shooter_frame(self, shooter: int) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(3,) the normal ``shooter`` shoots along and (K, 3) its elements' corners less the
        point it shoots from (None for an element: its own corners less their mean)."""
        if self.patches is None:
            return self.mesh.normals[shooter], None
        # A node's extent is its shooter discretisation, which splitting receivers cannot mend
        # (``adaptive.shooter_split`` splits the shooter): receivers are judged against the
        # extent of one element, the one nearest the node's centroid, as when elements shoot.
        tree = self.patches.tree
        members = self.patches.members(shooter)
        centroid = tree.centroid[shooter].to(self.device)
        nearest = members[int(torch.argmin((self.mesh.centroids.index_select(0, members) - centroid).norm(dim=1)))]
        corners = self.mesh.corners_of(int(nearest))
        return tree.normal[shooter].to(self.device), corners - corners.mean(0)

    def eye_moves(self, shooter: int, split: torch.Tensor) -> bool:
        """Whether splitting the (K,) elements ``split`` moves the hemicube of ``shooter``: an
        element's sits at its centroid (its index then holds its first child); a node's stays."""
        return self.patches is None and bool((split == shooter).any())

    def _adopt(self, reflectance: torch.Tensor, emission: torch.Tensor, state: SolverState) -> None:
        """Make these the per-element values, kept in buffers that splits append to
        (``split.GrowingRows``; rows are carried over without copying the old ones)."""
        self._per_element = [GrowingRows(v) for v in (reflectance, emission, state.radiosity, state.unshot)]
        self.reflectance, self.emission, state.radiosity, state.unshot = (rows.values for rows in self._per_element)
        self.state = state

    def adopt_split(self, mesh: Mesh, parent: torch.Tensor) -> None:
        """Continue on ``mesh``, made by splitting the current one: its element i lies in the
        current element ``parent[i]`` (T',), and inherits its B and dB (radiosities, so power
        is conserved) and its reflectance and emission. Every element keeps its index (a
        split one's now holds its first child: ``split.split_triangles``)."""
        self.mesh = mesh
        self.reflectance, self.emission, self.state.radiosity, self.state.unshot = (
            rows.inherit(parent) for rows in self._per_element)
        self.areas = mesh.areas
        self.small_receivers = self.refined_small_receivers
        self._set_geometry(mesh)
        self._forget_kept_light()
        if self.patches is not None:
            self.patches.inherit(parent)

    def shoot(self, limit: int | None = None) -> int | None:
        """One shot from the element (or with patches, the patch) with the largest unshot
        power, or with ``sweeps`` a sweep of at most ``limit`` patches' shots; None when
        nothing is left. Returns the element, or the (strongest) patch.

        With a refiner, the refiner runs the shot (it may split receivers and redo it
        before anything is committed); the view it returns is committed.
        """
        if self.patches is not None:
            return self._sweep(limit) if self.sweeps and self.active_refiner is None else self._shoot_patch()
        state = self.state
        power = state.unshot * self.areas[:, None]  # (T, 3)
        shooter = int(torch.argmax(row_sums(power)))
        shot_power = power[shooter].clone()
        if float(shot_power.sum()) <= 0.0:
            return None
        F = self._shot_form_factors(shooter, shot_power)
        with self.profiler.phase("update"):
            near = self.near_receivers_of(shooter, F)
            if near is None:
                self._receive(shot_power, F)
            else:
                self._receive_incident(incident_power(F, shot_power, near, shot_power[None]), shot_power)
            self.state.unshot[shooter] = 0.0  # spent
            self.state.shots += 1
        return shooter

    def _shoot_patch(self) -> int | None:
        """One shot of the patch with the most unshot power: each node of its cut shoots its
        elements' unshot power (and with ``overshoot``, rho times the ambient more)."""
        patches, state = self.patches, self.state
        ambient = None
        if self.overshoot:  # what each element would shoot: its unshot radiosity and rho times the ambient
            ambient = ambient_term(state.unshot, self.reflectance, self.areas).clamp(min=0.0)
            patch = patches.strongest((state.unshot + self.reflectance * ambient) * self.areas[:, None])
        else:
            patch = patches.strongest(state.unshot * self.areas[:, None])
        if patch is None:
            return None
        nodes = patches.cut(patch, self.render_and_keep, self.mesh.corners)
        for node in nodes:
            with self.profiler.phase("update"):
                members = patches.members(node)
                shot = state.unshot.index_select(0, members)  # (K, 3) radiosity
                if ambient is not None:
                    shot = shot + self.reflectance.index_select(0, members) * ambient
                member_power = shot * self.areas.index_select(0, members)[:, None]
                shot_power = member_power.sum(0)
                source_power = None
                if self.near_reach > 0:  # by the node's near-field sources
                    lo, hi = patches.bounds(node)
                    source_power = patches.by_source(node, torch.zeros(hi - lo, 3, dtype=shot.dtype, device=self.device)
                                                     .index_add_(0, patches.leaf.index_select(0, members) - lo, member_power))
                # taken before the shot: a refining shot may split the node's elements, whose
                # children then inherit what is left
                state.unshot.index_add_(0, members, -shot)
                patches.record(node, members, member_power)
            F = self._shot_form_factors(node, shot_power)
            with self.profiler.phase("update"):
                near = self.near_receivers_of(node, F)
                self._receive_incident(incident_power(F, shot_power, near, source_power), shot_power)
        self._views.clear()
        state.shots += 1
        return patch

    def _sweep(self, limit: int | None = None, drawn_only: bool = False) -> int | None:
        """Every patch holding unshot power shoots it, all at once (``sweeps``); with ``limit``,
        only that many, the strongest; ``drawn_only``: only those whose groups' light is kept.
        Returns the strongest, None when nothing is left."""
        patches, state, tree = self.patches, self.state, self.patches.tree
        with self.profiler.phase("update"):
            power = state.unshot * self.areas[:, None]  # (T, 3)
            magnitude = patches.magnitudes(power)
            if drawn_only:
                drawn = self._drawn_patches()
                magnitude = magnitude.masked_fill(~drawn, 0.0)
            shooting = flatnonzero(magnitude > 0)
            if len(shooting) == 0:
                return None
            held = None  # (T,) bool the elements of patches that do not shoot this time
            if drawn_only:
                held = (~drawn).index_select(0, patches.patch)
                power = power.masked_fill(held[:, None], 0.0)
            elif limit is not None and len(shooting) > limit:
                strongest = torch.argsort(magnitude.index_select(0, shooting), descending=True, stable=True)
                shooting = torch.sort(shooting.index_select(0, strongest[:limit])).values
                held = torch.ones(tree.num_patches, dtype=torch.bool, device=self.device).index_fill_(
                    0, shooting, False).index_select(0, patches.patch)
                power = power.masked_fill(held[:, None], 0.0)
        if self._transport is None:
            self._transport = SweepTransport(self.mesh.num_elements, tree.num_nodes, len(tree.leaf), self.device)
        transport = self._transport
        # Patches join the kept light a group at a time (``NEAR_BATCH`` patches in index order,
        # every group that holds one that shoots): their near fields are made together, and a
        # group is the same whichever sweep first needs it, so the numbers do not depend on
        # the sweep (a resumed run's first sweep makes the near fields of every group it needs).
        # A group's rows and near fields are made on a worker thread while this one draws the
        # next groups' hemicubes (``_make_group``, up to ``GROUPS_AHEAD``): torch's kernels let
        # go of the interpreter, and the near fields' contour integrals are mostly kernel. While
        # this thread would wait for the oldest group, it makes parts of it, or of the groups
        # after it, that the worker has not begun (``make_a_part``).
        groups = sorted({patch // NEAR_BATCH for patch in shooting.tolist()} - transport.groups)
        order = [patch for g in groups for patch in range(g * NEAR_BATCH, min((g + 1) * NEAR_BATCH, tree.num_patches))]
        new: dict[int, tuple[torch.Tensor, HemicubeView | None]] = {}  # the group's nodes: (F, view)
        making = collections.deque()  # the groups before: (its nodes, what the worker makes of them)
        taken: list[int] = []  # the bytes each group taken in added to the kept light, in group order
        kept_before = transport.nbytes

        def take_in() -> None:
            while not making[0][1].done() and make_a_part([light for _, light in making]):
                pass
            before = transport.nbytes
            self._join_group(making.popleft())
            taken.append(transport.nbytes - before)

        for i, patch in enumerate(order):
            if i + 1 < len(order):  # drawn while this patch's hemicube is decoded and used
                self._prefetch(order[i + 1])
            nodes = patches.cut(patch, self.render_and_keep, self.mesh.corners)
            while making and making[0][1].done():
                take_in()
            # rows not kept are made with the group's (``_make_group``); the nodes of a split
            # patch that its cut did not draw are drawn here, each while the one before is used
            drawn = [node for node in nodes if node not in self.rows and node not in self._views]
            following = dict(zip(drawn, drawn[1:]))
            if drawn:
                self._prefetch_node(drawn[0])
            for node in nodes:
                F, view = self.rows.get(node, self.mesh.num_elements), self._views.pop(node, None)
                if F is None and view is None:
                    if node in following:
                        self._prefetch_node(following[node])
                    view = self.render(node)
                new[node] = (F, view)
            # the views of nodes that split into their children: each holds a hemicube's pixels
            self._views.clear()
            if i + 1 < len(order) and order[i + 1] // NEAR_BATCH == patch // NEAR_BATCH:
                continue
            transport.groups.add(patch // NEAR_BATCH)
            making.append((new, self._make_group(new)))
            new = {}
            ahead = GROUPS_AHEAD if i + 1 < len(order) else 0
            while len(making) > ahead:
                take_in()
            # every run has taken in all but the last ``ahead`` groups sent (this one may have taken
            # in more, its worker being quicker): the memory check reads only those, so the point
            # where it stops does not depend on the worker's speed
            sent = len(taken) + len(making)
            settled = kept_before + sum(taken[:max(0, sent - ahead)])
            if settled > self.rows.budget_bytes:  # over the memory asked for: one patch at a time
                while making:  # every group sent is taken in (its rows and near fields kept), as in every run
                    take_in()
                warnings.warn(f"the light kept for sweeps outgrew solver.cache_mb ({self.rows.budget_bytes >> 20} MB) "
                              f"at {self.mesh.num_elements} elements: from here patches shoot one at a time, drawing "
                              f"again each hemicube whose row was dropped, which can take many times longer; a "
                              f"larger solver.cache_mb (--cache-mb) keeps the sweeps", HemiradWarning)
                self.sweeps, self._transport, self._outgrown_bytes = False, None, transport.nbytes
                return self._shoot_patch()
        with self.profiler.phase("update"):
            leaf_power = torch.zeros(len(tree.leaf), 3, dtype=power.dtype, device=self.device).index_add_(
                0, patches.leaf, power)
            patches.record_sweep(transport.node_of_leaf, leaf_power)
            if held is None:
                state.unshot.zero_()
            else:
                state.unshot.masked_fill_(~held[:, None], 0.0)
            self._receive_incident(transport.incident(leaf_power), leaf_power.sum(0))
        state.shots += len(shooting)
        self.sweep_count += 1
        return int(torch.argmax(magnitude))

    def _prefetch(self, patch: int) -> None:
        """Start drawing the hemicube of ``patch``'s root if its cut will render it (the first
        time it shoots), so that the rasteriser works while this thread does."""
        if patch not in self.patches.cuts:
            self._prefetch_node(int(self.patches.tree.root[patch]))

    def _prefetch_node(self, node: int) -> None:
        """Start drawing the hemicube of ``node`` (``HemicubeRenderer.prefetch_at``)."""
        self._renderer_of(node).prefetch_at(*self._placement(node))

    def _shot_form_factors(self, shooter: int, shot_power: torch.Tensor) -> torch.Tensor:
        """(T,) F_sj of a shot of ``shot_power`` (3,) from ``shooter``: its kept or rendered row,
        or, while shots refine, what the refiner's last pass saw (the mesh may have grown)."""
        refiner = self.active_refiner
        if refiner is None:
            return self.form_factors_of(shooter)
        view = refiner.shoot(self, shooter, shot_power)
        self._keep_view(shooter, view)
        return self.node_row(shooter, view)

    def form_factors_of(self, shooter: int) -> torch.Tensor:
        """(T,) F_sj from ``shooter`` on the current mesh: its kept row, else rendered (and kept)."""
        F = self.rows.get(shooter, self.mesh.num_elements)
        if F is None:
            view = self._views.get(shooter)
            F = self._row(shooter, self.render(shooter) if view is None else view)
        return F

    def _row(self, shooter: int, view: HemicubeView) -> torch.Tensor:
        """(T,) the row ``shooter`` shoots with (``node_row``) given its ``view``, kept with the view."""
        self._keep_view(shooter, view)
        F = self.node_row(shooter, view)
        self.rows.put(shooter, F)
        return F

    def node_row(self, shooter: int, view: HemicubeView, among: torch.Tensor | None = None) -> torch.Tensor:
        """(T,) the row ``shooter`` (its hemicube's ``view``) shoots with: the view's
        ``shot_row``, or for a node of emitting elements with eyes (``_eyes``), the mean of
        those of its eyes (the first of a one-element node's is its centroid, the view's own).
        ``among``: as ``shot_row``'s."""
        eyes = self._eyes(shooter)
        if eyes is None:
            return self.shot_row(view, among, self._emits(shooter))
        F = torch.zeros_like(view.form_factors)
        for eye_view, weight in self._eye_views(shooter, view, eyes):
            F += weight * self.shot_row(eye_view, among, True)
        return F

    def _eye_views(self, shooter: int, view: HemicubeView, eyes: tuple[torch.Tensor, torch.Tensor]
                   ) -> Iterator[tuple[HemicubeView, float]]:
        """What each of the ``eyes`` (``_eyes``) of ``shooter`` sees, and its weight, drawn in
        turn (the next while the caller uses one). A one-element node's first eye is its
        centroid: its ``view``; a larger node's centroid is none of its eyes, and its view
        only served the shooter test."""
        points, weights = eyes[0].cpu().numpy(), eyes[1].tolist()
        _, normal, tangent = self._placement(shooter)
        first = 1 if len(self.patches.members(shooter)) == 1 else 0
        if first:
            yield view, weights[0]
        yield from zip(self.renderer.views_at(points[first:], normal, tangent), weights[first:])

    def _emits(self, shooter: int) -> bool:
        """Whether an element of ``shooter`` emits, as ``shot_row`` asks it (pixel sums need
        not know, and are not asked)."""
        return self.small_receivers != "pixels" and self._emitting(shooter)[0]

    def _emitting(self, shooter: int) -> tuple[bool, bool]:
        """Whether any, and whether all, of the elements of ``shooter`` (a node; without
        patches, an element) emit; found for every shooter at once while the mesh and patches
        are unchanged (a sweep asks each node several times)."""
        if self._emitters is None:
            emits = (self.emission > 0).any(dim=1)  # (T,)
            if self.patches is None:
                self._emitters = (emits.cpu().numpy(),) * 2
            else:
                emitting = self.patches.member_counts(emits)
                self._emitters = emitting > 0, emitting == self.patches.member_counts()
        some, every = self._emitters
        return bool(some[shooter]), bool(every[shooter])

    def _eyes(self, shooter: int) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Where a node whose elements all emit shoots from, with the patches' ``eye_level``:
        (E, 3) the eyes of its elements (``shooters.eye_points``) and (E,) their shares of its
        area; None for any other node (it shoots from its centroid)."""
        if self.patches is None or self.patches.eye_level == 0:
            return None
        if not self._emitting(shooter)[1]:
            return None
        members = self.patches.members(shooter)
        per_element = 4 ** self.patches.eye_level
        areas = self.areas.index_select(0, members)
        weights = (areas / (areas.sum() * per_element)).repeat_interleave(per_element)
        return eye_points(self.mesh.corners_of(members), self.patches.eye_level), weights

    def _make_group(self, nodes: dict[int, tuple[torch.Tensor | None, HemicubeView]]) -> GroupLight:
        """Start making a sweep group's rows and near fields: the ``nodes`` (node -> (row or
        None, view)) without a row get one (``node_row``). The hemicubes (a lamp's eyes' too) are
        drawn here, and rows of pixel sums made; the rows of small receivers (a lamp's, from
        its eyes' views: ``sweep.GroupLight`` sums them) and the near fields on the worker
        thread, and this one where it would wait for them (``sweep.GroupLight``), which touch
        no state of the solver: taken in by ``_join_group``. Made here, a lamp's eyes' rows
        held the drawing thread 0.2-0.3 s a solve on floating refined by the answer, while the
        worker waited for its group."""
        batch = {}  # node -> [(view, pixel limit, weight)]: its hemicube's, or its eyes'
        for node, (F, view) in nodes.items():
            if F is not None:
                continue
            eyes = self._eyes(node)
            limit = self._small_receiver_limit(self._emits(node))  # a node with eyes emits
            if limit is None:
                F = self.node_row(node, view)  # pixel sums
            else:
                batch[node] = ([(v, limit, weight) for v, weight in self._eye_views(node, view, eyes)]
                               if eyes is not None else [(view, limit, 1.0)])
                continue
            self.rows.put(node, F)
            nodes[node] = (F, view)
        shooters = ({node: self._near_shooter(node, F, view) for node, (F, view) in nodes.items()}
                    if self.near_reach > 0 else {})
        if self._worker is None:
            self._worker = ThreadPoolExecutor(1, thread_name_prefix="hemirad-sweep", initializer=_yield_to_drawing)
        return GroupLight(self._worker, self.mesh, batch, shooters, self.near_reach, self.near_totals)

    def _join_group(self, making: tuple[dict, GroupLight]) -> None:
        """Take in what the worker made of a sweep group (``_make_group``: its nodes, as the
        sweep gathered them, and their ``GroupLight``), waiting for it if need be, and add the nodes to
        the sweeps' kept light."""
        nodes, light = making
        with self.profiler.phase("update"):
            rows, near = light.result()
            for node, F in rows.items():
                self.rows.put(node, F)
                nodes[node] = (F, nodes[node][1])
            self._near.update(near)
            for node, (F, _) in nodes.items():
                self._transport.add(node, self.patches.bounds(node), F, self._near.get(node),
                                    self.patches.sources(node)[1])
        release_freed_memory()  # the group's views, rows and near fields were freed by both threads

    def _small_receiver_limit(self, emits: bool) -> float | None:
        """The footprint in pixels under which a shooter's receivers get their factors from
        ``small_receivers`` (``shot_row``), None where it hands out its pixel sums."""
        if self.small_receivers == "pixels" or (self.small_receivers == "lamps" and not emits):
            return None
        return MAX_PIXELS if emits else BOUNCE_MAX_PIXELS

    def shot_row(self, view: HemicubeView, among: torch.Tensor | None, emits: bool) -> torch.Tensor:
        """(T,) the F_sj a shot from ``view`` (of the current mesh) hands out: its pixel sums, or
        those of the receivers covering few pixels replaced
        (``smallreceivers.small_receiver_form_factors``; with ``among`` (T,) bool, only those,
        unscaled): with ``small_receivers`` lamps or closed_form, under ``MAX_PIXELS`` pixels
        for a shooter that ``emits``; with closed_form, under ``BOUNCE_MAX_PIXELS`` for one
        that only reflects.

        A receiver's reflected light comes from hundreds of shooters, whose pixel luck averages
        out, where its direct light comes from a few lamp nodes (measured: ``BOUNCE_MAX_PIXELS``,
        ``scene.model.resolved_small_receivers``)."""
        limit = self._small_receiver_limit(emits)
        if limit is None:
            return view.form_factors
        with self.profiler.phase("form_factors"):
            return small_receiver_form_factors(view, self.mesh.corners, self.mesh.areas, limit, among=among)

    def render_and_keep(self, shooter: int) -> HemicubeView:
        """``render(shooter)``, kept for the shooter's row, made when it shoots (a node the
        patches' test splits never does)."""
        view = self.render(shooter)
        self._views[shooter] = view
        return view

    def _keep_view(self, shooter: int, view: HemicubeView) -> None:
        """Keep what ``shooter``'s hemicube saw until its near field is made from it."""
        if self.near_reach > 0 and shooter not in self._near:
            self._views[shooter] = view

    def near_receivers_of(self, shooter: int, F: torch.Tensor, among: torch.Tensor | None = None,
                          view: HemicubeView | None = None) -> NearReceivers | None:
        """The receivers near ``shooter`` (a node; without patches, an element) that get its
        light as its near-field sources send it (``nearfield``), kept while the mesh is
        unchanged; None without a near field (``near_reach`` 0). ``view``: what the hemicube that gave
        the row F (T,) saw (default: the one rendered for this shot, else a new render).
        With ``among`` (R,), only those among these elements, unscaled, and not kept."""
        if self.near_reach <= 0:
            return None
        if among is None and shooter in self._near:
            return self._near[shooter]
        near = near_fields(self.mesh, [self._near_shooter(shooter, F, view)], self.near_reach, self.near_totals,
                           among)[0]
        if among is None:
            self._near[shooter] = near
        return near

    def _near_shooter(self, shooter: int, F: torch.Tensor | None, view: HemicubeView | None) -> NearShooter:
        """What ``nearfield`` needs of ``shooter`` (an element, or a node of the patches) shooting
        the row F (T,) seen in ``view`` (None: the one kept for it, else a new render); F None:
        to be filled in (``sweep.GroupLight``)."""
        if view is None:
            view = self._views.pop(shooter, None)
        if view is None:
            view = self.render(shooter)
        if self.patches is None:  # the element is its own source
            members = torch.tensor([shooter], device=self.device)
            return NearShooter(members, self.mesh.corners_of(members), self.mesh.centroids[shooter],
                               self.mesh.normals[shooter], view, F)
        tree = self.patches.tree
        return NearShooter(self.patches.members(shooter), self.patches.sources(shooter)[0],
                           tree.centroid[shooter].to(self.device), tree.normal[shooter].to(self.device), view, F)

    def _receive_incident(self, incident: torch.Tensor, shot_power: torch.Tensor) -> None:
        """Hand every receiver what reaches its front, ``incident`` (T, 3) power, of a shot of
        ``shot_power`` (3,); the rest escaped."""
        state = self.state
        delta = self.reflectance * incident / self.areas[:, None]
        state.radiosity += delta
        state.unshot += delta
        state.absorbed += ((1.0 - self.reflectance) * incident).sum(0)
        state.escaped += shot_power - incident.sum(0)

    def _receive(self, shot_power: torch.Tensor, F: torch.Tensor) -> None:
        """Hand every receiver what a shot of ``shot_power`` (3,) with form factors F (T,) gives it."""
        state = self.state
        delta = received_radiosity(F, shot_power, self.reflectance, self.areas)
        state.radiosity += delta
        state.unshot += delta
        state.absorbed += ((1.0 - self.reflectance) * F[:, None]).sum(0) * shot_power
        state.escaped += (1.0 - F.sum()) * shot_power

    def run(self, max_shots: int, unshot_fraction: float,
            progress: Callable[[ShotReport], None] | None = None) -> SolverState:
        start = time.perf_counter()
        keep_freed_memory()
        with self._solving():
            while self.state.shots < max_shots and self.unshot_fraction > unshot_fraction:
                shooter = self.shoot(limit=max_shots - self.state.shots)
                if shooter is None:
                    break
                if progress is not None:
                    progress(ShotReport(self.state.shots, shooter, self.mesh.num_elements,
                                        self.unshot_fraction, time.perf_counter() - start))
        return self.state

    @contextlib.contextmanager
    def _solving(self) -> Iterator[None]:
        """Torch on one thread beside llvmpipe's (on a GPU's GL, on all), deterministic."""
        with torch_threads(1 if GLContext.is_software() else torch.get_num_threads()), deterministic(self.device):
            yield

    def sweep_drawn(self) -> bool:
        """One sweep of the patches whose light the sweeps keep (those drawn before), the
        others' unshot power held: a bounce among them costs two sparse products and draws no
        hemicube. Whether any shot (none where patches do not sweep, or nothing is kept)."""
        if not self.sweeps or self._transport is None or self.active_refiner is not None:
            return False
        keep_freed_memory()
        with self._solving():
            return self._sweep(drawn_only=True) is not None

    def timings(self) -> dict[str, float]:
        """Seconds per phase so far (``PHASES``)."""
        return self.profiler.state_dict()

    def state_dict(self) -> dict:
        """Everything later shots depend on, as plain tensors, numbers and strings.

        Keys: ``mesh`` (``Mesh.state_dict``; refinement changes it), ``reflectance``,
        ``emission``, ``radiosity``, ``unshot`` (T, 3) float64; ``absorbed``, ``escaped``,
        ``emitted_power`` (3,) float64; ``shots``; ``refiner`` and ``patches`` (their own
        ``state_dict``, or None), ``small_receivers`` (the choice the next shot makes) and
        ``timings``. ``emitted_power`` is kept rather than recomputed because the
        refined mesh's areas sum to it only to rounding, and the stopping rule divides by it.
        """
        s = self.state
        saved = {"reflectance": self.reflectance, "emission": self.emission, "radiosity": s.radiosity,
                 "unshot": s.unshot, "absorbed": s.absorbed, "escaped": s.escaped,
                 "emitted_power": self.emitted_power}
        return {"mesh": self.mesh.state_dict(), **{k: v.cpu().clone() for k, v in saved.items()}, "shots": s.shots,
                "sweeps": self.sweep_count, "refiner": self.refiner.state_dict() if self.refiner is not None else None,
                "patches": self.patches.state_dict() if self.patches is not None else None,
                "small_receivers": self.small_receivers, "timings": self.timings()}

    def load_state_dict(self, state: dict, patches_for: Callable[[], PatchShooters] | None = None) -> None:
        """Continue from ``state_dict()``'s output: the next shot is the one that would have followed.
        ``patches_for()``: the patches of the saved mesh, where they were built on it
        (``restart``), made once the mesh is loaded; None: those the solver was made with.

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
        timings = state["timings"]
        if not isinstance(timings, dict) or set(timings) != set(PHASES):
            raise ValueError(f"timings must give the seconds of {', '.join(PHASES)}")
        self.mesh, self.areas = mesh, mesh.areas
        per_element = {k: v.to(self.device) for k, v in per_element.items()}
        self._adopt(per_element["reflectance"], per_element["emission"],
                    SolverState(per_element["radiosity"], per_element["unshot"], int(state["shots"]),
                                state["absorbed"], state["escaped"]))
        self.emitted_power = state["emitted_power"].to(torch.float64).to(self.device)
        self.sweep_count = int(state.get("sweeps", 0))
        small_receivers = state.get("small_receivers", self.small_receivers)  # older states: as made
        if small_receivers not in (self.small_receivers, self.refined_small_receivers):
            raise ValueError(f"the state was saved with small_receivers {small_receivers!r}")
        self.small_receivers = small_receivers
        if (state.get("patches") is None) != (self.patches is None):
            raise ValueError("the state was saved with patches " + ("off" if state.get("patches") is None else "on"))
        if self.refiner is not None:
            self.refiner.load_state_dict(state["refiner"])
        if patches_for is not None:
            self.use_patches(patches_for())
        if self.patches is not None:
            self.patches.load_state_dict(state["patches"], T)
        self._forget_kept_light()
        self._set_geometry(mesh)
        self.profiler.load_state_dict(timings)
