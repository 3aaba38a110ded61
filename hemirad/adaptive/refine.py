"""The refinement scheduler: which receivers of a shot to split, within the bounds."""
from __future__ import annotations

import torch

from hemirad.adaptive.criteria import CRITERIA, ShotContext
from hemirad.adaptive.shot import refining_shot
from hemirad.core.colour import luminance
from hemirad.core.fastops import flatnonzero
from hemirad.geometry.mesh import Mesh
from hemirad.geometry.patterns import CHILDREN
from hemirad.geometry.split import SplitRounds
from hemirad.scene.model import AUTO_CRITERION, PAPER_CRITERION, RefineOptions
from hemirad.transport.view import HemicubeView



class Refiner:
    """Chooses the elements to split during a shot and splits them; runs a solver's shots
    (``shoot``: the ``transport.solver.ShotRefiner`` a ``ProgressiveSolver`` takes).

    Args:
        options: the scene's refine block.
        emission: (T, 3) per-element emission, for a threshold relative to the brightest emitter.
        relabel: between the passes of a refining shot, carry the hemicube's item atlas over
            to the children (``relabel.py``) instead of rendering again; the shot is still
            committed with a real render of the final mesh.
        bound: leave out of the interior Jacobian the receivers whose criterion bounds that
            part of their score under the threshold (``could_exceed``): the same splits,
            with less autograd work.
    """

    def __init__(self, options: RefineOptions, emission: torch.Tensor, relabel: bool = True, bound: bool = True):
        if options.pattern not in CHILDREN:
            raise ValueError(f"unknown split pattern {options.pattern!r}")
        self.options = options
        # None for refinement judged on the answer (``answer.py``), which uses this object's
        # split pattern, grading and limits only; ``auto`` here, without a scene to say
        # whether patches shoot, is the paper's criterion (``Scene.refine_criterion``)
        self.criterion = CRITERIA.get(PAPER_CRITERION if options.criterion == AUTO_CRITERION else options.criterion)
        self.threshold = options.threshold
        if options.relative and self.criterion is not None and self.criterion.radiosity_units:
            self.threshold *= float(luminance(emission).max())
        self.children = CHILDREN[options.pattern]
        self.relabel, self.bound = relabel, bound
        self.splits = 0

    def shoot(self, solver, shooter: int, shot_power: torch.Tensor) -> HemicubeView:
        """Run one shot of ``solver`` (a ``ProgressiveSolver``), splitting as the criterion
        asks (``shot.refining_shot``); returns the view to commit."""
        return refining_shot(self, solver, shooter, shot_power)

    def state_dict(self) -> dict:
        """What a resumed solve needs beyond the options: the split count and the threshold
        in radiosity units (it was made relative to the emission at the start)."""
        return {"splits": self.splits, "threshold": self.threshold}

    def load_state_dict(self, state: dict) -> None:
        self.splits, self.threshold = int(state["splits"]), float(state["threshold"])

    @property
    def jacobian(self) -> str | None:
        """Which form-factor gradient the criterion needs: "full", "interior" or None."""
        return self.criterion.jacobian

    def splittable(self, mesh: Mesh, shooter, rows: torch.Tensor | None = None) -> torch.Tensor:
        """(T,) bool: the receivers a shot from ``shooter`` may split, whatever their score:
        under the depth limit, with children no smaller than ``min_area``, and not the
        shooter's own (its hemicube is being used): ``shooter`` an element's index, or a
        (K,) tensor of the elements a patch shoots from; among ``rows`` (R,) only, when given."""
        o = self.options
        if rows is None:
            out = (mesh.level < o.max_depth) & (mesh.areas / self.children >= o.min_area)
            out[shooter] = False
            return out
        level, areas = mesh.level.index_select(0, rows), mesh.areas.index_select(0, rows)
        keep = (level < o.max_depth) & (areas / self.children >= o.min_area)
        keep &= (rows != shooter) if isinstance(shooter, int) else ~torch.isin(rows, shooter)
        out = torch.zeros(mesh.num_elements, dtype=torch.bool, device=rows.device)
        out[rows[keep]] = True
        return out

    def _candidates(self, ctx: ShotContext) -> tuple[torch.Tensor, torch.Tensor]:
        """(T,) bool the pass's candidates (every ``splittable`` receiver when it names none)
        and (R,) their indices."""
        candidates = self.splittable(ctx.mesh, ctx.shooter) if ctx.candidates is None else ctx.candidates
        return candidates, flatnonzero(candidates)

    def could_exceed(self, ctx: ShotContext, view: HemicubeView, pixels: torch.Tensor | None = None
                     ) -> torch.Tensor | None:
        """(T,) bool: the pass's candidates whose score's interior part may pass the threshold
        (the criterion's ``interior_bound``), the only ones whose interior Jacobian is needed;
        None when the criterion has no bound (all candidates then need it).

        Args:
            ctx: the pass, before its Jacobian; view: what its hemicube saw.
            pixels: (N,) optional: every pixel that sees a candidate is among these.
        """
        if self.criterion.interior_bound is None:
            return None
        candidates, rows = self._candidates(ctx)
        out = torch.zeros_like(candidates)
        bound = self.criterion.interior_bound(ctx, rows, view.distance_of(rows),
                                              view.sine_sums(pixels).index_select(0, rows))
        out[rows] = bound * (1.0 + 1e-9) > self.threshold  # room for rounding: at the threshold, the exact score
        return out

    def select(self, ctx: ShotContext) -> torch.Tensor:
        """(T,) bool: receivers over the threshold among the pass's candidates (by default
        every ``splittable`` one), largest first when the element budget binds (it is never
        exceeded)."""
        mesh, o = ctx.mesh, self.options
        candidates, rows = self._candidates(ctx)
        score = self.criterion.score(ctx, rows)
        over = score > self.threshold
        rows, score = rows[over], score[over]
        room = (o.max_elements - mesh.num_elements) // (self.children - 1)
        if len(rows) > room:
            # stable sort: ties keep index order, so the choice is deterministic
            order = torch.argsort(score, descending=True, stable=True)
            rows = rows[order[:max(room, 0)]]
        eligible = torch.zeros_like(candidates)
        eligible[rows] = True
        return eligible

    def split(self, mesh: Mesh, selected: torch.Tensor) -> tuple[Mesh, torch.Tensor]:
        """Split the selected elements and, for pattern 2, then every element left more than one
        level coarser than a neighbour (2:1 grading), within the element budget.

        Returns:
            the new mesh, and (T',) the index in ``mesh`` each new element descends from.
        """
        device = mesh.triangles.device
        chosen = flatnonzero(selected)
        if len(chosen) == 0:
            return mesh, torch.arange(mesh.num_elements, device=device)
        rounds = SplitRounds(mesh, self.options.pattern, room=2 * len(chosen))  # grading adds some more
        while len(chosen):
            self.splits += len(chosen)
            V = rounds.num_vertices
            corner_vertices = rounds.triangles.index_select(0, chosen).reshape(-1)
            rounds.split(chosen)
            if self.options.pattern != "pattern2":
                break
            # a new violation has a vertex of a split triangle (or a new one)
            near = torch.ones(rounds.num_vertices, dtype=torch.bool, device=device)
            near[:V] = False
            near[corner_vertices] = True
            chosen = rounds.unbalanced(near)
            room = (self.options.max_elements - rounds.num_elements) // (self.children - 1)
            chosen = chosen[:max(room, 0)]  # the budget wins over grading
        return rounds.result()
