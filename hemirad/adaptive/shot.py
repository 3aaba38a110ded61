"""One refining shot: judge the receivers, split, redo on the children, commit a real render.

The refiner (``refine.Refiner``) decides; this module runs the passes of a shot through the
solver's small interface (``render``, ``adopt_split``, ``mesh``, ``reflectance``, ``areas``,
``profiler``), so that the solver knows nothing of criteria, gradients or relabelling.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from hemirad.adaptive.criteria import ShotContext
from hemirad.adaptive.gradient import form_factor_gradient
from hemirad.adaptive.relabel import relabel_view
from hemirad.core.colour import luminance
from hemirad.geometry.split import inherit
from hemirad.transport.view import HemicubeView

if TYPE_CHECKING:
    from hemirad.adaptive.refine import Refiner
    from hemirad.transport.solver import ProgressiveSolver


def refining_shot(refiner: "Refiner", solver: "ProgressiveSolver", shooter: int, shot_power: torch.Tensor
                  ) -> HemicubeView:
    """Run the shot of ``shot_power`` (3,) from ``shooter``, splitting the receivers
    ``refiner`` selects and redoing the shot on the new elements until none is selected;
    returns what a real render of the final mesh sees, for the solver to commit.

    Each pass judges only the elements the previous one made: the first judges every
    splittable receiver, the next the children of those it split (and those 2:1 grading
    split), and so on down the levels, as a recursive subdivision would. Unsplit receivers
    keep their pixels, so judging them again would only repeat the verdict (or follow the
    hemicube's aliasing at split edges); gradients are computed for the judged receivers
    only. Between passes what the hemicube sees is carried over to the children
    (``relabel.relabel_view``, with ``refiner.relabel``) rather than rendered again.
    """
    profiler = solver.profiler
    candidates = refiner.splittable(solver.mesh, solver.shooter_elements(shooter))
    gain = luminance_per_form_factor(solver, shot_power)
    view = solver.render(shooter)
    while True:
        normal, offsets = solver.shooter_frame(shooter)
        ctx = ShotContext(mesh=solver.mesh, shooter=shooter, eye=view.eye, normal=normal, form_factors=view.form_factors,
                          luminance_per_form_factor=gain, candidates=candidates, shooter_offsets=offsets)
        with profiler.phase("gradient"):
            ctx.jacobian = shot_jacobian(refiner, ctx, view)
        with profiler.phase("refine"):
            selected = refiner.select(ctx)
            if not bool(selected.any()):
                break
            T = solver.mesh.num_elements
            mesh, parent = refiner.split(solver.mesh, selected)
            solver.adopt_split(mesh, parent)
            split = torch.unique(parent[T:])
            new = torch.cat([split, torch.arange(T, len(parent), device=split.device)])  # their rows in the new mesh
            candidates = refiner.splittable(mesh, solver.shooter_elements(shooter), new)
            gain = inherit(gain, parent).index_copy_(0, new, luminance_per_form_factor(solver, shot_power, new))
            if refiner.relabel and not solver.eye_moves(shooter, split):
                view = relabel_view(view, parent, split, mesh)
                continue
        view = solver.render(shooter)
    if view.relabelled_pixels is not None:  # commit what a real render of the final mesh sees
        view = solver.render(shooter)
    return view


def shot_jacobian(refiner: "Refiner", ctx: ShotContext, view: HemicubeView) -> torch.Tensor | None:
    """dF_sj/dc (T, 3) when the criterion reads it (else None), for the pass's candidates
    whose score could pass the threshold (``Refiner.could_exceed``, with ``refiner.bound``);
    its other rows are zero."""
    wanted = refiner.jacobian
    if wanted is None:
        return None
    options, pixels = refiner.options, view.relabelled_pixels
    return form_factor_gradient(view, interior=options.interior or wanted == "interior",
                                shadow_edges=options.shadow_edges and wanted == "full", wanted=ctx.candidates,
                                plane_ids=ctx.mesh.plane_ids, pixels=pixels,
                                interior_wanted=refiner.could_exceed(ctx, view, pixels) if refiner.bound else None)


def luminance_per_form_factor(solver: "ProgressiveSolver", shot_power: torch.Tensor,
                              rows: torch.Tensor | None = None) -> torch.Tensor:
    """(T,) or (R,) for ``rows``: the luminance of what a receiver gets per unit F_sj from
    ``shot_power`` (3,), rho_j dB_s A_s / A_j; a child's differs from its parent's by its area."""
    if rows is None:
        return luminance(solver.reflectance * shot_power) / solver.areas
    return luminance(solver.reflectance.index_select(0, rows) * shot_power) / solver.areas.index_select(0, rows)
