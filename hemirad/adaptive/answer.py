"""Refinement judged on the answer: split where the converged solution is least well
represented, then give the new elements the light they really receive (docs/DESIGN.md §3.8).

Per-shot criteria (``criteria.py``) judge one shot at a time against a fixed threshold;
they never see the smooth variation over large elements that dominates an image's error,
and a threshold cannot be tuned to a mesh size. Here the judge is the solution itself:

1. **Estimate.** An element's error is how far the picture (as the caller's display draws
   it: ``pipeline`` passes ``output.shading``'s) lies inside it from a model of the
   radiosity fitted to the element and its neighbours: its own quadratic under the default
   shading, a linear model under Gouraud's (``element_errors``).
2. **Split** the elements of the largest squared error times area (their share of the
   image's squared error) first, as many as the round's element budget allows.
3. **Solve the refined mesh afresh** (``patches_for``: with the initial mesh's patches, each
   now holding its elements' children, which the scene gives), or without a scene, **regather**: a split element's children inherit its radiosity; each child then gets
   what every shooter has sent so far reaching it: each node whose light reached a split
   element is rendered on the refined mesh and its accumulated power
   (``PatchShooters.sent``) is spread by its form factors to the children, as its shots
   would have spread it. Per split element the children's total is scaled to what the
   element had received, so the redistribution moves light between siblings and creates
   none: power is conserved exactly, and what a child gained or lost over its inherited
   value joins its unshot radiosity, to be shot on. Measured (figures/accuracy_converged.md):
   the fresh solve is the better answer on the same mesh (its emitters shoot element by
   element), and with sweeps it costs about what the regather and the shots after it cost:
   both render every node's hemicube once on the new mesh.
4. **Shoot on** to the stopping rule, and repeat while the budget and the tolerance allow.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Protocol

import torch

from hemirad.core.errors import HemiradWarning
from hemirad.core.fastops import flatnonzero
from hemirad.geometry.mesh import Mesh, vertex_sharing_pairs
from hemirad.scene.model import RefineOptions
from hemirad.transport.solver import ambient_term



class Picture(Protocol):
    """What the ranking needs of a picture drawn from element values (``output.shading.Shading``)."""

    levels: int  # 0: the vertex values Gouraud-shaded; more: shaded inside the elements
    values: torch.Tensor  # (N, C) the values drawn, the mesh's vertices' first

    def element_deviation(self, mesh: Mesh, element_values: torch.Tensor) -> torch.Tensor:
        """(T,) how far the picture lies inside each element from the element's own fit."""


#: How a picture draws (T, C) element values (``output.shading.picture_shading``), which the
#: ranking judges (``element_errors``).
Display = Callable[[Mesh, torch.Tensor], Picture]

if TYPE_CHECKING:
    from hemirad.adaptive.refine import Refiner
    from hemirad.transport.shooters import PatchShooters
    from hemirad.transport.solver import ProgressiveSolver


def element_errors(mesh: Mesh, radiosity: torch.Tensor, display: Display) -> torch.Tensor:
    """(T,) each element's estimated error: how far the picture (``display``) lies inside it
    from a model of the radiosity around it.

    Gouraud-shaded (the paper's ``mean`` display): the RMS over the element's corners of the
    vertex values' distance from a linear model, the element's value with the gradient that
    best fits (least squares, weighted by area) its vertex-sharing neighbours' values at
    their centroids. Where the radiosity varies linearly the shading follows it and the
    estimate is 0; it grows with curvature and at shadow edges.

    Shaded inside elements (``output.shading``, the default): one order up, the RMS over the
    element's 15 lattice points of the shading's distance from the element's own quadratic
    (``reconstruction.element_fits``: fitted to its value and its vertex-sharing neighbours'
    by their means). Where the radiosity is quadratic both are exact and the estimate is 0;
    it grows where the light varies faster than an element resolves (a shadow edge, a
    contact's corner), which the vertex fits' clamped blend and the element's own fit see
    differently. Measured (to a third of the finest uniform mesh's elements, the three
    bundled scenes): relative MSE 0.90-0.98x the Gouraud ranking's with the same shading
    from x2, about the same from x1 on the Cornell box, 1.09x on floating; the estimate
    reads 0.41-1.06x the measured error over the converged accuracy study's 47 runs (the
    Gouraud one read 1.2-1.7x the Gouraud picture's, and 3x on floating's finest shaded
    one). What it cannot see is an error the shading and the element's fit share: on the
    Cornell box, walls and ceiling a few percent bright beside the room's concave edges,
    where the light falls faster than any quadratic (a seventh of it estimated there). A
    leave-one-out residual added (each element's mean against its neighbours' quadratic)
    read 1.1-1.9x but ranked no better (the Cornell box the same, floating 1.04 -> 1.08x,
    office 0.53 -> 0.58x the finest's relative MSE).

    The distance is taken over the three colour channels (the root of the squares summed),
    as the accuracy study's relative MSE against the references measures a picture's error.
    Ranked by luminance instead, the Cornell box's red wall (whose light is nearly all red,
    weighed at 0.21 by luminance) counted a fifth of its share: the tall block's shadow on it
    stayed on 8 cm elements, 4-6% off on both sides of its penumbra; by channels, its run to a
    third of the finest uniform mesh's elements from x2 reads 0.000108 against 0.000114
    (floating's and office's the same).

    Args:
        mesh: the elements; radiosity: (T, C) the radiosity shown (C = 3: RGB).
        display: how the picture draws (T, C) element values (``pipeline`` passes
            ``shading.picture_shading`` with the scene's ``solver.reconstruction``).
    """
    value = radiosity
    shading = display(mesh, value)
    if shading.levels > 0:
        return shading.element_deviation(mesh, value)
    shown = shading.values[mesh.triangles]  # (T, 3, C) the vertex values at each corner
    i, j = vertex_sharing_pairs(mesh)
    i, j = i[i != j], j[i != j]
    centroids, normals = mesh.centroids, mesh.normals
    d = centroids.index_select(0, j) - centroids.index_select(0, i)  # (P, 3)
    w = mesh.areas.index_select(0, j)
    moments = torch.zeros(mesh.num_elements, 3, 3, dtype=value.dtype, device=value.device).index_add_(
        0, i, w[:, None, None] * d[:, :, None] * d[:, None, :])
    # no slope along the normal: the neighbours span the plane only
    scale = mesh.areas * moments.diagonal(dim1=1, dim2=2).sum(1).clamp(min=1e-300) / mesh.areas.clamp(min=1e-300)
    moments += scale[:, None, None] * normals[:, :, None] * normals[:, None, :]
    rhs = torch.zeros(mesh.num_elements, 3, value.shape[1], dtype=value.dtype, device=value.device).index_add_(
        0, i, w[:, None, None] * d[:, :, None] * (value.index_select(0, j) - value.index_select(0, i))[:, None, :])
    slope = torch.linalg.lstsq(moments, rhs).solution  # (T, 3 axes, C)
    model = value[:, None, :] + (mesh.corners - centroids[:, None, :]) @ slope  # (T, 3 corners, C)
    return (model - shown).pow(2).sum(2).mean(1).sqrt()


def estimated_relative_error(mesh: Mesh, radiosity: torch.Tensor, display: Display,
                             errors: torch.Tensor | None = None, emission: torch.Tensor | None = None,
                             importance: torch.Tensor | None = None) -> float:
    """The interpolation estimate of the picture's relative RMS error: sqrt(sum A e^2 / sum A
    |B|^2) over the elements (``element_errors`` e of the ``display``, or the ``errors``
    already found; |B|^2 the radiosity's channels squared and summed, as e's are) that do not
    emit, given their ``emission`` (T, 3): a lamp's own light, hundreds of times its
    surroundings', would swamp the sum (it made this estimate read 2-9x low before it was
    left out). ``importance`` (T,): each element's weight beside its area (the ranking's,
    ``split_by_error``); default 1."""
    e = element_errors(mesh, radiosity, display) if errors is None else errors
    weight = mesh.areas if emission is None else torch.where((emission > 0).any(1), 0.0, mesh.areas)
    if importance is not None:
        weight = weight * importance
    return float(((weight * e * e).sum() / (weight * radiosity.pow(2).sum(1)).sum().clamp(min=1e-300)).sqrt())


def regather(solver: "ProgressiveSolver", parent: torch.Tensor, split: torch.Tensor, received: torch.Tensor,
             nodes: list[int]) -> None:
    """Give the children of split elements the light every node has sent them so far.

    Args:
        solver: continuing on the refined mesh (``adopt_split`` done), with patches.
        parent: (T',) the element of the previous mesh each element lies in.
        split: (S,) the previous mesh's elements that were split (sorted).
        received: (S, 3) the power each of them had received (its B less its emission, times
            its area over its reflectance; 0 where it reflects nothing).
        nodes: the nodes whose light reached some split element.
    """
    patches, state = solver.patches, solver.state
    changed = flatnonzero(torch.isin(parent, split))  # (C,) the children, first ones included
    is_changed = torch.zeros(len(parent), dtype=torch.bool, device=parent.device)
    is_changed[changed] = True
    which = torch.searchsorted(split, parent.index_select(0, changed))  # (C,) index into split
    gathered = torch.zeros(len(changed), 3, dtype=torch.float64, device=solver.device)
    for node in nodes:
        # the node's row for the children only: the per-element scaling below takes the
        # place of the row's own (``small_receiver_form_factors``), and later shots render
        # the few rows they need in full
        view = solver.render(node)
        F = solver.node_row(node, view, among=is_changed)
        part = F.index_select(0, changed)[:, None] * patches.sent[node]  # (C, 3)
        near = solver.near_receivers_of(node, F, among=changed, view=view)
        if near is not None and len(near.rows):
            # near the node, its light as its sources sent it (``nearfield``), unscaled
            lo, hi = patches.bounds(node)
            part[torch.searchsorted(changed, near.rows)] = near.weights.T @ patches.by_source(
                node, patches.sent_by_leaf[lo:hi])
        gathered += part
    # each split element's children share exactly what it had received
    total = torch.zeros_like(received).index_add_(0, which, gathered)
    scale = torch.where(total > 0, received / total.clamp(min=1e-300), torch.zeros_like(total))
    area = solver.areas.index_select(0, changed)
    area_share = area / torch.zeros_like(received[:, 0]).index_add_(0, which, area).index_select(0, which)
    share = torch.where((total > 0).index_select(0, which), gathered * scale.index_select(0, which),
                        received.index_select(0, which) * area_share[:, None])
    rho = solver.reflectance.index_select(0, changed)
    radiosity = solver.emission.index_select(0, changed) + rho * share / area[:, None]
    reflects = rho > 0  # a black element keeps its inherited value (its emission)
    radiosity = torch.where(reflects, radiosity, state.radiosity.index_select(0, changed))
    state.unshot.index_add_(0, changed, radiosity - state.radiosity.index_select(0, changed))
    state.radiosity.index_copy_(0, changed, radiosity)


def reaching_nodes(solver: "ProgressiveSolver", split: torch.Tensor) -> list[int]:
    """The nodes that have shot and whose kept row (on the current mesh) reaches one of the
    ``split`` elements; every node that shot whose row is no longer kept."""
    patches, T = solver.patches, solver.mesh.num_elements
    nodes = []
    for node in flatnonzero(patches.sent.abs().sum(1) > 0).tolist():
        row = solver.rows.get(node, T)
        if row is None or bool((row.index_select(0, split) > 0).any()):
            nodes.append(node)
    return nodes


#: How many times a round may grow the mesh, before grading, by default (``refine.round_growth``;
#: pattern 2 splits up to 1.5 times the elements, children split again). Each round is a fresh solve of its whole mesh, and
#: a split goes two generations deep (``GENERATIONS``), so one large round places its elements
#: as well as two smaller ones, for one solve fewer. Measured (runs from x2 to a third of the
#: finest uniform mesh's elements, relMSE and the faster of two timings, alternating): at most
#: 2.5 times (two rounds) against 5.5 times (one): floating 0.00005 in 6.3 s against 0.00005 in
#: 4.7 s, Cornell box 0.00023 in 9.7 s against 0.00024 in 5.6 s, office one round either way
#: (0.00013). Earlier, before children split again within a round, rounds of 2.5 times against
#: doubling were 0.00032 in 25% of the finest's seconds against 0.00030 in 42% (Cornell box).
#: What fewer rounds lose is local: the floor 1 cm outside the Cornell box's blocks (the slow
#: contact test, 41,000 elements) is within 5% at 25 of 26 points, median 0.8%, in three rounds
#: of at most 2.5 times, and at 23 of 26, median 2.0%, in two of at most 5.5: a feature the
#: first solve cannot see is found by the rounds after it.
ROUND_GROWTH = RefineOptions.round_growth
#: With a tolerance, a round adds the elements that the error falling as 1 / elements would
#: need to reach it (``tolerance_splits``), so a run close to its tolerance is not grown 5.5
#: times. Measured (the interpolation estimate, the three bundled scenes from x2 and x1): over
#: a first round it fell as elements^-0.96 to elements^-1.4 (rounds of up to 5.5 times;
#: elements^-1.1 to elements^-1.7 in rounds of 2.5), over later ones as elements^-0.7 or not at
#: all (what is left is the solution's own error, not the shading's). So a round sized so
#: about reaches a tolerance the first round can, and stops short of one near that floor,
#: whose rounds then run to ``rounds`` or the budget.
ERROR_ORDER = 1.0
#: A round may split an element and then its children (``split_by_error``), where a child's
#: score (error squared times area) is predicted as this share of its parent's: a quarter of
#: the area, and a little under half the error (an edge's error falls with the element's
#: side; a smooth variation's faster). Measured (answer to a third of the finest uniform
#: mesh's elements, relative MSE; one generation / two at 1/16, 1/32, 1/64): floating from
#: x1 0.00058 / 0.00025 / 0.00025 / 0.00035, from x2 0.00017 / 0.00007 / 0.00008 / 0.00009;
#: office from x2 0.00016 / 0.00013 / 0.00012 / 0.00012, from x1 0.00033 throughout (its
#: budget is one partial round); Cornell box from x2 0.00030 / 0.00035 / 0.00032 / 0.00031,
#: from x1 0.00027 / 0.00031 / 0.00028 / 0.00027. A third generation changed nothing.
CHILD_SCORE = 1.0 / 32.0
GENERATIONS = 2
#: A round's solve that a split follows only ranks the elements, and is stopped at this many
#: times the run's unshot fraction (``rank_on``; 1e-2 at the default 1e-3): the light still
#: unshot is spread thin, and moves the interpolation errors that rank the elements little.
#: Measured (runs from x2 to a third of the finest uniform mesh's elements, relMSE as a
#: multiple of the finest's, seconds against the ranking solve converged, in the same
#: minutes, with refined patches then larger: docs/MEASUREMENTS.md): office 0.472x either
#: way in 0.94 of the seconds, the Cornell box 0.977x against 0.984x in 0.89, floating naming
#: its finest's error 0.766x against 0.777x in 0.95; at 30 and 100 times the errors the same
#: (the Cornell box 0.970x, 0.969x), the seconds no fewer (the sweeps past 1e-2 reuse kept
#: rows).
RANKING_UNSHOT = 10.0


#: Where the rounds are sized by an element budget, a ranking solve stops sooner: of the
#: light the emitters' shots left unshot, only the patches that hold this share of it shoot,
#: the strongest first, once, and the light then bounces among the patches drawn so far
#: (``ranking_solve``). The first bounce of most of the light draws the features that rank the
#: elements (the floor under a lamp lighting the ceiling, a wall's colour on the next); the
#: many patches that hold little of it are not drawn (office: 30% of its patches hold 92%).
#: Measured (runs from x2 to a third of the finest uniform mesh's elements, relMSE as a
#: multiple of the finest's; seconds as the study counts them, the faster of two interleaved
#: runs after a warm-up, against the ranking solve to 1e-2): office 0.452x against 0.456x in
#: 3.85 s against 4.27 s, the Cornell box 0.983x against 0.980x in 2.88 s against 2.85 s,
#: floating 0.747x against 0.732x in 2.78 s against 2.89 s. Without the bounces among the
#: patches drawn, floating's penumbra band (``tests/test_penumbra_band.py``) read 3.09% at
#: its worst point, over its 3% (at shares of 0.6-0.9 too); at 0.5 the Cornell box 1.034x, at
#: 0.8 1.007x and no faster; the emitters' shots alone (direct light) office 0.448x in 0.79 of
#: the seconds, but the Cornell box 1.086x and floating 1.066x, whose ceiling or shadowed floor
#: the reflectors light.
RANKING_SHARE = 0.7


def ranking_unshot(unshot_fraction: float) -> float:
    """The unshot fraction a solve that only ranks stops at, for a run's ``unshot_fraction``:
    ``RANKING_UNSHOT`` times it, at most 1e-2 (the looser rule measured), never below it."""
    return max(unshot_fraction, min(RANKING_UNSHOT * unshot_fraction, 1e-2))


def strongest_holding(power: torch.Tensor, share: float) -> int:
    """How many of the (P,) ``power`` (>= 0), the largest first, hold ``share`` of their sum
    (at most those above 0)."""
    ordered = torch.sort(power, descending=True).values
    holding = int((torch.cumsum(ordered, 0) < share * float(ordered.sum())).sum()) + 1
    return min(holding, int((power > 0).sum()))


def ranking_solve(solver: "ProgressiveSolver", max_shots: int, unshot_fraction: float,
                  progress: Callable | None = None, *, by_budget: bool = True) -> torch.Tensor | None:
    """The solve of a round that a split may follow, which only ranks the elements, within
    ``max_shots`` shots, stopping where the unshot fraction falls to
    ``ranking_unshot(unshot_fraction)``: where the rounds are sized by an element budget
    (``by_budget``), sooner, once the patches holding power (after ``restart``, the emitters)
    have shot once, the strongest patches holding ``RANKING_SHARE`` of the power they left
    unshot once after them (in sweeps, a sweep each), and then the patches drawn so far as
    long as a sweep of theirs moves more than the stopping rule's share of the light
    (``ProgressiveSolver.sweep_drawn``). ``progress``: the solver's per-shot callback. Returns
    the (T, 3) radiosity to rank by: stopped sooner, with the light it left unshot as Cohen
    et al.'s ambient term; else None, the solver's.

    Where a tolerance sizes and ends the rounds, the estimate must read the error's level,
    not only rank it: stopped sooner, the Cornell box's read 0.84-0.96x its converged
    answer's (without the bounces among the patches drawn 0.74-0.79x; office and floating
    1.00-1.11x), and its run from x1 naming the finest uniform mesh's error stopped at 3,126
    elements, 2.99x that error (4,566, 0.75x, solved to the unshot fraction)."""
    stop = ranking_unshot(unshot_fraction)
    if not by_budget:
        solver.run(max_shots, stop, progress)
        return None
    for share in (1.0, RANKING_SHARE):
        power = solver.patches.magnitudes(solver.state.unshot * solver.areas[:, None])
        solver.run(min(max_shots, solver.state.shots + strongest_holding(power, share)), stop, progress)
    # then the light bounces among the patches drawn, as long as a bounce moves more than the
    # stopping rule's share of it: no hemicube more, two sparse products a bounce
    while solver.unshot_fraction > stop and solver.state.shots < max_shots:
        before = solver.unshot_fraction
        if not solver.sweep_drawn() or before - solver.unshot_fraction < stop:
            break
    return solver.state.radiosity + solver.reflectance * ambient_term(solver.state.unshot, solver.reflectance,
                                                                      solver.areas)


#: A round that would grow the mesh by less than this share is not made: it is a fresh solve
#: of the whole mesh for a sliver of it. Measured: office from the shipped mesh to 3,701
#: elements, whose first round's grading left 3,692, then made rounds of 6 and 3 elements,
#: each a solve as long as the first (27.9 s where one round takes 14.7). Nor where the
#: tolerance is predicted to need less (the estimate is within that share of it): the Cornell
#: box from x2, asked for the finest uniform mesh's error, made a round of 19 elements after
#: one of 1,600, for 3 s of its 10.
MIN_ROUND_GROWTH = 0.05
#: A round toward a tolerance is sized for this share of it (``tolerance_splits``): the
#: interpolation estimate reads 0.5-1.7x the measured error, and over a first round it fell
#: as elements^-0.8 to elements^-1.55 (the answer from x2 on the three bundled scenes, ranked
#: by the camera's pixels), so a round sized for the tolerance itself either stopped over it
#: (the Cornell box named the finest uniform mesh's error: 2,481 elements, relMSE 1.12x it)
#: or fell just short and made a second round of a tenth more elements, a whole solve for
#: them (floating: 1,895 then 2,081 elements, 3.9 s). Sized for 0.8 of it: the Cornell box
#: 3,099 elements, 0.99x, 3.0 s; floating one round, 2,381 elements, 2.6 s, 0.7x.
TOLERANCE_AIM = 0.8
#: A round grows the mesh no more than the light its fresh solve keeps for the sweeps allows
#: (``solver.cache_mb``; past it they shoot one patch at a time, many times slower). That
#: light grows faster than the elements, up to their square (every node seeing every element,
#: the nodes growing with the elements), which ``memory_growth`` takes it to do. Measured over
#: rounds (elements ratio, kept light ratio): floating from x2 3.2x / 5.8x, 3.1x / 3.4x, 3.1x /
#: 3.2x; office from x1 2.7x / 3.5x, 2.7x / 2.8x; the furnished room of
#: ``scripts/peer_room.py`` 2.0x / 3.5x (60 -> 213 MB), so its default round of 5.5 times
#: outgrew 256 MB and took 405 s where a round of 2 took 161 s. The order a round showed does
#: not foretell the next's: the Cornell box from x2, its rounds held to the order the round
#: before had shown, outgrew the memory going from 12,996 to 30,000 elements.
KEPT_LIGHT_ORDER = 2.0
#: Where the memory allows a round less growth than this, refinement stops (with a warning):
#: a fresh solve of the whole mesh for a little more of it, or one past the memory, costs more
#: than it gives. Measured on the Cornell box, whose closed box every patch sees nearly whole,
#: its rounds held to what fits but going on regardless: from x2 to 30,000 elements in three
#: rounds, 1,020 -> 5,538 -> 12,996 -> 30,000 elements, the last round past the memory, 100.8 s
#: for relative MSE 0.00009, where its 12,996 elements had 0.00008 in 19.1 s; from x1, 28,470
#: elements in 289.5 s for 0.00008 where 17,622 had 0.00007 in 75.4 s.
MIN_MEMORY_GROWTH = 1.5


def tolerance_splits(elements: int, estimated: float, tolerance: float, children: int) -> int:
    """How many of its ``elements`` a round splits (a split adds ``children`` - 1) to bring the
    ``estimated`` error to ``tolerance``, the error taken to fall as elements^-``ERROR_ORDER``."""
    needed = elements * (estimated / tolerance) ** (1.0 / ERROR_ORDER) - elements
    return max(0, math.ceil(needed / (children - 1)))


def memory_growth(kept_bytes: int, budget_bytes: int) -> float:
    """The most the next round may grow the mesh for its fresh solve's kept light, now
    ``kept_bytes`` and taken to grow as elements^``KEPT_LIGHT_ORDER``, to stay within
    ``budget_bytes``; inf where nothing was kept (no sweeps)."""
    return math.inf if kept_bytes <= 0 else (budget_bytes / kept_bytes) ** (1.0 / KEPT_LIGHT_ORDER)


def round_splits(elements: int, max_elements: int, children: int, rounds_left: int,
                 growth: float = ROUND_GROWTH) -> int:
    """How many of its ``elements`` a round splits on the way to ``max_elements`` (a split
    adds ``children`` - 1), ``rounds_left`` rounds at most: enough to grow the mesh ``growth``
    times where the budget needs more rounds than that; else the rounds it needs, each growing
    the mesh at most ``growth`` times, grow it by equal ratios, so no solve is spent
    on a last sliver of the budget; none where the budget leaves less than
    ``MIN_ROUND_GROWTH`` of the mesh. Measured (runs to a third of the finest uniform mesh's
    elements from x2, rounds at most doubling; relMSE, seconds against that mesh's): rounds
    of the most growth and the rest in a last one, Cornell box 0.00032 in 40%, floating
    0.00008 in 73%, office 0.00012 in 48%; equal ratios 0.00030 in 36%, 0.00008 in 59%,
    0.00013 in 47%; the rest taken with the round before (one solve fewer) 0.00032 in 28%,
    0.00012 in 56%, 0.00017 in 33% (office's round was too large for the answer it was
    ranked on)."""
    room = (max_elements - elements) // (children - 1)
    if room <= 0 or room * (children - 1) < MIN_ROUND_GROWTH * elements:
        return 0
    ratio = max_elements / elements
    rounds = max(1, math.ceil(math.log(ratio) / math.log(growth) - 1e-9))
    if rounds > rounds_left:
        return min(room, int((growth - 1.0) * elements / (children - 1)))
    return min(room, int((ratio ** (1.0 / rounds) - 1.0) * elements / (children - 1)))


@dataclass
class RoundReport:
    round: int
    elements: int
    split: int
    estimated_error: float
    shots: int
    kept_bytes: int = 0  # the light the round's solve kept for its sweeps, all patches drawn (``ProgressiveSolver.whole_kept_light_bytes``)


def refine_by_answer(solver: "ProgressiveSolver", refiner: "Refiner", max_elements: int, tolerance: float,
                     rounds: int, shoot_on: Callable[[], None],
                     *, display: Display, rank_on: Callable[[], None] | None = None,
                     report: Callable[[RoundReport], None] | None = None,
                     reports: list[RoundReport] | None = None,
                     patches_for: Callable[[], "PatchShooters"] | None = None,
                     estimate: Callable[[], float] | None = None,
                     importance: Callable[[Mesh], torch.Tensor] | None = None) -> list[RoundReport]:
    """Alternate shooting to the stopping rule (``shoot_on``) and refining where the answer
    is worst, until the estimated relative error is under ``tolerance``, the mesh has
    ``max_elements``, or ``rounds`` refinements were made. Each round may at most grow the
    element count ``refiner.options.round_growth`` times (``ROUND_GROWTH``), so the estimate is renewed as the mesh
    learns, and no more than its fresh solve's kept light fits the solver's memory for it
    (``memory_growth``; where that allows less than ``MIN_MEMORY_GROWTH``, the rounds stop
    with a warning); the rounds to the budget grow it by equal ratios (``round_splits``), a round
    adds no more than ``TOLERANCE_AIM`` of the tolerance is predicted to need (``tolerance_splits``), and
    grading's extra splits never take it past the budget.

    ``rank_on()``: shoots a round that a split may follow, whose solve only ranks the
    elements (``ranking_solve``), and returns the (T, 3) radiosity its answer shows (None:
    the solver's); a round that stops the rounds is then shot on to the stopping rule
    (``shoot_on``); None: ``shoot_on`` for every round.
    ``refiner`` supplies the split pattern, the 2:1 grading and the depth and size limits.
    ``patches_for()``: the patches of the solver's mesh just split, to solve it afresh with
    (``ProgressiveSolver.restart``); None: ``regather`` and shoot on.
    ``estimate()``: the solver's solution's estimated relative error, which the rounds stop
    by (``pipeline`` passes the final-gather estimate, ``gathered_error``); None, and for a
    ranking solve that ``rank_on`` stopped sooner: the interpolation estimate the elements
    are ranked by (``estimated_relative_error``).
    ``display``: how the picture the ranking judges is drawn (``element_errors``).
    ``importance(mesh)``: (T,) each element's weight in the ranking beside its area (and in
    the interpolation estimate): how much of the picture it fills (``pipeline`` passes
    ``output.importance.view_importance``); None: area alone.
    ``report`` is called after each round's split. Returns one report per round (the first
    is the unrefined solve), appended to ``reports`` when given: a run resumed from a
    checkpoint passes the rounds it had finished and goes on with the next (its solver
    holds their mesh and light)."""
    reports = [] if reports is None else reports
    ranked_only = False  # whether the last round's solve only ranked (a split is always followed by a round)
    for index in range(len(reports), rounds + 1):
        mesh = solver.mesh
        growth = refiner.options.round_growth
        last = index == rounds or round_splits(mesh.num_elements, max_elements, refiner.children, rounds - index,
                                               growth) <= 0
        ranked_only = not last and rank_on is not None
        shown = rank_on() if ranked_only else shoot_on()
        stopped_sooner = ranked_only and shown is not None  # a budget's ranking solve (``ranking_solve``)
        if not stopped_sooner:  # as solved (once converged, the ambient term is negligible)
            shown = solver.state.radiosity
        # the elements' errors rank a round's splits, and make the interpolation estimate where
        # none is given: in a last round with an estimate they are not needed
        if not last or estimate is None:
            errors = element_errors(mesh, shown, display)
            weights = None if importance is None else importance(mesh)
        # of a ranking solve stopped sooner, the interpolation estimate: one by final gathers would
        # measure how far from converged it is (office from the shipped mesh: 0.037, its answer 0.0086)
        estimated = (estimated_relative_error(mesh, shown, display, errors, solver.emission, weights)
                     if estimate is None or stopped_sooner else estimate())
        reports.append(RoundReport(index, mesh.num_elements, 0, estimated, solver.state.shots,
                                   solver.whole_kept_light_bytes))
        if last or estimated <= tolerance:
            break
        fits = memory_growth(reports[-1].kept_bytes, solver.cache_bytes)
        count = round_splits(mesh.num_elements, max_elements, refiner.children, rounds - index, min(growth, fits))
        if fits < MIN_MEMORY_GROWTH:
            warnings.warn(f"refinement judged on the answer stopped at {mesh.num_elements} elements: a further "
                          f"round's solve would outgrow the memory for the light kept for sweeps "
                          f"(solver.cache_mb, {solver.cache_bytes >> 20} MB, of which it kept "
                          f"{reports[-1].kept_bytes >> 20} MB); a larger solver.cache_mb (--cache-mb) lets it go on",
                          HemiradWarning)
            break
        if tolerance > 0:
            reach = tolerance_splits(mesh.num_elements, estimated, tolerance, refiner.children)
            if reach * (refiner.children - 1) < MIN_ROUND_GROWTH * mesh.num_elements:
                break  # within a few per cent of the tolerance: not worth a fresh solve of the whole mesh
            aim = TOLERANCE_AIM * tolerance
            count = min(count, tolerance_splits(mesh.num_elements, estimated, aim, refiner.children))
        new_mesh, parent = split_by_error(refiner, mesh, errors, count, weights)
        while new_mesh.num_elements > max_elements and count > 0:
            # grading's splits came on top of the count's: fewer, until the budget holds
            count -= -(-(new_mesh.num_elements - max_elements) // (refiner.children - 1))
            new_mesh, parent = split_by_error(refiner, mesh, errors, count, weights)
        if new_mesh.num_elements == mesh.num_elements:
            break
        if patches_for is None:
            adopt_and_regather(solver, new_mesh, parent)
        else:
            solver.adopt_split(new_mesh, parent)
            solver.restart(patches_for())
        reports[-1].split = solver.mesh.num_elements - mesh.num_elements
        if report is not None:
            report(reports[-1])
    if ranked_only:  # the rounds stopped after a solve that only ranked: its answer is the run's
        shoot_on()
    return reports


def split_by_error(refiner: "Refiner", mesh: Mesh, errors: torch.Tensor, count: int,
                   importance: torch.Tensor | None = None) -> tuple[Mesh, torch.Tensor]:
    """Spend ``count`` splits where the squared error times area (times ``importance`` (T,),
    where given) is largest, a child's
    predicted as ``CHILD_SCORE`` of its parent's, over at most ``GENERATIONS`` generations
    (a child of this round's split split again). Returns the new mesh and (T',) the element
    of ``mesh`` each of its elements lies in, as ``Refiner.split`` does.

    The splits are the ``count`` largest scores among the elements' and their predicted
    descendants' (a generation-k descendant counted ``children``^k times: that many share
    the score), so they go deep where the error is steep and nowhere else; grading and the
    depth and size limits then act as on one split."""
    nothing = torch.empty(0, dtype=torch.int64, device=errors.device)
    splittable = refiner.splittable(mesh, nothing)
    area = mesh.areas if importance is None else mesh.areas * importance
    score = torch.where(splittable & (errors > 0), errors * errors * area, torch.zeros_like(errors))
    positive = score[score > 0]
    if count <= 0 or len(positive) == 0:
        return mesh, torch.arange(mesh.num_elements, device=errors.device)
    values = torch.cat([positive * CHILD_SCORE ** k for k in range(GENERATIONS)])
    copies = torch.cat([torch.full_like(positive, float(refiner.children ** k)) for k in range(GENERATIONS)])
    # equal scores go together: the cutoff is the lowest score whose splits, with all the
    # higher ones', fit in the count
    levels, group = torch.unique(values, return_inverse=True)  # ascending
    fitting = int((torch.zeros_like(levels).index_add_(0, group, copies).flip(0).cumsum(0) <= count).sum())
    if fitting == 0:  # not all of the largest ties fit: the first of them in index order, once
        first = torch.argsort(score, descending=True, stable=True)[:count]
        chosen = torch.zeros_like(splittable)
        chosen[first] = True
        return refiner.split(mesh, chosen)
    cutoff = float(levels[len(levels) - fitting])
    current, parent = mesh, torch.arange(mesh.num_elements, device=errors.device)
    for _ in range(GENERATIONS):
        chosen = (score >= cutoff) & refiner.splittable(current, nothing)  # cutoff > 0
        if not bool(chosen.any()):
            break
        current, step = refiner.split(current, chosen)
        split = torch.unique(step[len(score):])  # an element's index holds its first child
        score = score.index_select(0, step)
        score = torch.where(torch.isin(step, split), score * CHILD_SCORE, score)
        parent = parent.index_select(0, step)
    return current, parent


def adopt_and_regather(solver: "ProgressiveSolver", new_mesh: Mesh, parent: torch.Tensor) -> None:
    """Continue on ``new_mesh``, ``parent`` (T',) the solver's mesh's element each of its
    elements lies in, its split elements' children given their light (``regather``)."""
    mesh = solver.mesh
    split = torch.unique(parent[mesh.num_elements:])  # sorted; a split element's index holds its first child
    rho = solver.reflectance.index_select(0, split)
    before = solver.state.radiosity.index_select(0, split) - solver.emission.index_select(0, split)
    received = torch.where(rho > 0, before * mesh.areas.index_select(0, split)[:, None] / rho.clamp(min=1e-300),
                           torch.zeros_like(before))
    nodes = reaching_nodes(solver, split)
    solver.adopt_split(new_mesh, parent)
    regather(solver, parent, split, received, nodes)
