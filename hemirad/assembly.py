"""The solver a scene asks for: its initial mesh, patches and their shooter tests, the
refiner, and the progressive solver over them (``make_solver``)."""
from __future__ import annotations

import numpy as np
import torch

from hemirad.adaptive.answer import round_splits
from hemirad.adaptive.refine import Refiner
from hemirad.adaptive.shooter_split import point_source_test
from hemirad.core.device import select_device
from hemirad.geometry.mesh import Mesh
from hemirad.geometry.patches import PatchTree, build_patches, element_sides, group_patches, rim_runs
from hemirad.geometry.patterns import CHILDREN
from hemirad.lighting.photometry import emission_table
from hemirad.scene.meshing import build_mesh, surface_objects
from hemirad.scene.model import MeshFile, Scene, resolved_reflector_resolution, resolved_small_receivers
from hemirad.transport.shooters import PatchShooters, ShooterTest, either, hidden_centroid_test
from hemirad.transport.solver import ProgressiveSolver

#: ``solver.patch_size: auto`` makes patches of about this many elements a side,
AUTO_PATCH_ELEMENTS = 2.0
#: and, where refinement is judged on the answer, at most this share of the scene's smallest
#: extent (the smallest side of its bounding box: a room's height). A patch shoots from one
#: point, whose error grows with its size over its distance to what it lights; those
#: distances follow the scene's size, not its elements', and once refined elements show the
#: light finely the shooters' error is what is left. Measured (refinement judged on the answer
#: from the shipped sizes x2 to a third of the finest uniform mesh's elements; relative MSE,
#: seconds): office, whose x2 wall patches were 2 m, 0.00027 in 7.9 s uncapped, 0.00017 in
#: 9.6 s at 0.25, 0.00016 in 10.8 s at 0.15 and in 11.7 s at 0.1; Cornell box 0.00037,
#: 0.00041, 0.00030, 0.00030 (9.4 s uncapped, 11.3 s at 0.15); floating 0.00018, 0.00016,
#: 0.00017 (4.0 s, 7.1 s). Not without refinement: on the shipped unrefined meshes of office
#: and floating (wall patches 1 m, capped to 0.4 m) it took 40% longer and moved the error by
#: under 2%, the elements' own error being the larger there.
AUTO_PATCH_SCENE = 0.15
#: The answer's first solve, which only ranks the elements for a round that will solve the
#: refined mesh afresh, caps its patches at this share instead; the refined solves regroup
#: the initial elements at ``AUTO_PATCH_SCENE`` (``refined_patches``). Measured (runs from x2
#: to a third of the finest uniform mesh's elements, relMSE, seconds, each against the
#: default in the same minutes): floating 0.000022 in 2.77 s against 2.98 s, naming its
#: finest's error 0.000021 in 2.37-2.40 s against 2.57 s; office 0.000041 in 4.02 s against
#: 0.000040 in 4.26 s; the Cornell box 0.000104 in 2.76 s against 2.86 s. At 0.45: floating
#: 0.000022 in 2.40 s, office 0.000042 in 3.88 s; at 0.5 and uncapped, floating 0.000027 in
#: the release before (its 1 m wall patches' centroids draw errors the ranking then chases).
#: A run that will make no round (its budget or ``refine.rounds`` allows none) solves with
#: ``AUTO_PATCH_SCENE`` from the start: its first solve is its answer.
FIRST_SOLVE_PATCH_SCENE = 0.3
#: With contacts meshed, the elements round a footprint whose rim is at least this many patch
#: sides long shoot apart from the others (``rim_stretches``),
RIM_PATCHES = 2.0
#: together only along a stretch of the rim that turns at most this many degrees.
RIM_TURN = 30.0
#: ``solver.emitter_eyes: auto`` gives a scene's lamps eyes where their elements' median side
#: is more than this share of the scene's smallest extent (``emitter_eye_level``).
EYE_SCENE = 0.035
#: A patch's light to receivers within this many patch radii is sent as its elements send it
#: (``transport.nearfield``). Measured in a closed 1 m box of 0.25 m cells (patches of 8 to 32
#: elements, reflectance 0.7): 3 leaves up to 4% per element, 4 (the box all near) 0.5%.
NEAR_REACH = 4.0


def near_totals(scene: Scene) -> str:
    """How much of a source's light its near receivers take (``nearfield.TOTALS``): the
    source's own factors (``area``) where the contacts are meshed, else G's hemicube's total.
    Measured (relative MSE against the references, converged): with contacts meshed, ``area``
    moved the Cornell box's uniform meshes from 0.00070 / 0.00019 to 0.00070 / 0.00016 (2,596
    and 9,890 elements), the answer's runs to a third of the finest uniform mesh's elements
    from x2 on floating 0.00012 -> 0.00010, Cornell box 0.00031 -> 0.00030, office 0.00013 ->
    0.00014, and the floor's corners in floating's penumbra band from -6.6% to within 3% (a
    wall patch's centroid sees less of the floor at its foot than its edge does, and the
    hemicube's total keeps that shortfall). Without contacts a floor source straddles a
    block's footprint and ``area`` counts it wholly exposed: the Cornell box's shipped mesh
    0.00117 -> 0.00136."""
    return "area" if scene.meshes_contacts else "hemicube"


def make_solver(scene: Scene, mesh: Mesh | None = None, *, device: torch.device | str | None = None,
                cull: bool = True, relabel: bool = True, bound: bool = True) -> ProgressiveSolver:
    """The progressive solver for ``scene``: its initial ``mesh`` (``build_mesh(scene)`` when
    None) with the materials' reflectance and emission (a flux made an exitance over the
    material's area in ``mesh``), the hemicube resolution of
    ``scene.solver``, the patches that shoot unless ``scene.solver.patch_size`` is none
    (with the hidden-centroid test, and eq. 7's with ``shooter_split``), and a ``Refiner``
    when ``scene.refine`` asks for refinement.

    Args:
        device: where to solve; default ``scene.solver.device`` (``select_device``).
        cull, relabel, bound: the equivalent fast paths (``ProgressiveSolver``, ``Refiner``),
            switchable to show that they change no number.
    """
    mesh = build_mesh(scene) if mesh is None else mesh
    reflectance = scene.reflectance_table()[mesh.material]
    emission = emission_table(scene, mesh)[mesh.material]  # a material's flux spread over its area
    per_shot = scene.refine.enabled and not scene.refines_by_answer  # the answer's rounds run in pipeline.solve
    refiner = Refiner(scene.refine, emission, relabel=relabel, bound=bound) if per_shot else None
    device = torch.device(select_device(scene.solver.device) if device is None else device)
    options = scene.solver
    patches = make_patches(scene, mesh, device, emission) if options.shoots_patches else None
    return ProgressiveSolver(mesh, reflectance, emission, options.resolution, refiner, cull=cull,
                             cache_bytes=int(options.cache_mb * (1 << 20)), patches=patches,
                             overshoot=options.overshoot, sweeps=options.sweeps, near_reach=NEAR_REACH if patches is not None else 0.0,
                             near_totals=near_totals(scene),
                             refine_shots=scene.refine.shots if refiner is not None else None, device=device,
                             small_receivers=resolved_small_receivers(options.small_receivers, refiner is not None),
                             refined_small_receivers=resolved_small_receivers(options.small_receivers, True),
                             reflector_resolution=resolved_reflector_resolution(options) if patches is not None else None)


def make_patches(scene: Scene, mesh: Mesh, device: torch.device, emission: torch.Tensor | None = None) -> PatchShooters:
    """The patches of the initial ``mesh`` (of (T, 3) ``emission``, by default the scene's) as
    ``scene.solver`` asks, with the shooter tests; where refinement judged on the answer will
    make a round, capped at ``FIRST_SOLVE_PATCH_SCENE`` for the first solve, with those of
    ``AUTO_PATCH_SCENE`` kept for the refined ones (``PatchShooters.regroup``)."""
    owner = surface_objects(scene, mesh)[mesh.surface.cpu().numpy()]  # (T,) each element's object
    tree = _patch_tree(scene, mesh, owner, AUTO_PATCH_SCENE)
    regroup = None
    if _will_refine(scene, mesh):
        regroup = tree.patch
        tree = _patch_tree(scene, mesh, owner, FIRST_SOLVE_PATCH_SCENE)
    emission = emission_table(scene, mesh)[mesh.material] if emission is None else emission
    return PatchShooters(tree, device, shooter_test(scene), source_corners=mesh.corners,
                         eye_level=emitter_eye_level(scene, mesh, emission), regroup=regroup)


def _patch_tree(scene: Scene, mesh: Mesh, owner: np.ndarray, cap: float) -> PatchTree:
    """The patches of ``mesh`` (``owner`` (T,) each element's object), the answer's ``auto``
    sizes capped at ``cap`` of the scene's smallest extent."""
    size = patch_sizes(scene, mesh, owner, cap)
    apart = rim_stretches(scene, mesh, size)
    if apart is not None:
        size[apart < 0] = 0.0  # at a footprint's corners
    return build_patches(mesh, size, owner, apart)


def _will_refine(scene: Scene, mesh: Mesh) -> bool:
    """Whether refinement judged on the answer may make a round from ``mesh``: the rounds
    and the element budget allow one, as ``refine_by_answer`` asks it (``round_splits``)."""
    refine = scene.refine
    return scene.refines_by_answer and refine.rounds > 0 and round_splits(
        mesh.num_elements, refine.max_elements, CHILDREN[refine.pattern], refine.rounds, refine.round_growth) > 0


def emitter_eye_level(scene: Scene, mesh: Mesh, emission: torch.Tensor) -> int:
    """``solver.emitter_eyes`` made definite for the initial ``mesh`` of (T, 3) ``emission``:
    ``auto`` is 1 with refinement judged on the answer where the emitting elements' median
    side is more than ``EYE_SCENE`` of the scene's smallest extent (``scene_extent``), else 0.

    A lamp's elements shoot as points, and the penumbrae they draw are staircases once the
    receivers are finer than they are. Measured (relative MSE against the references,
    converged): the answer's runs to a third of the finest uniform mesh's elements, from x2
    / x1, floating 0.00010 / 0.00023 -> 0.00009 / 0.00022, Cornell box 0.00030 / 0.00026 ->
    0.00028 / 0.00022, office 0.00014 / 0.00033 -> 0.00013 / 0.00028, in 7-25% more seconds
    (the study's goal rows: three more hemicubes a solve per lamp element; eyes on the
    refined meshes' solves only kept the x1 runs' error as it was, for about the same
    seconds); floating's penumbra band after three rounds from x1 from 3.9% largest, 99.0%
    within 3% to 2.1%, all within 3%. Their lamps' elements are 4.8-8% of the scene's
    extent as shipped (twice that from x2). The furnished room of ``scripts/peer_room.py``
    lights its globes with 1,080 elements of 2.4% of its height, each shooting alone once
    refined: refined once by the answer, 85.5 s without eyes against 176.5 s with (4,737
    hemicubes against 12,099), the same errors at its 185 points (median 0.8% / 0.9% as
    drawn, relative RMS 2.2%). The shipped uniform meshes gain nothing (floating 0.00165 ->
    0.00162, Cornell box 0.00117 -> 0.00123, office 0.00072 -> 0.00074; floating x0.5
    0.00053 for 60% more seconds)."""
    eyes = scene.solver.emitter_eyes
    if eyes != "auto":
        return int(eyes)
    emitting = (emission > 0).any(1).cpu().numpy()
    if not scene.refines_by_answer or not emitting.any():
        return 0
    return int(float(np.median(element_sides(mesh)[emitting])) > EYE_SCENE * scene_extent(mesh))


def shooter_test(scene: Scene) -> ShooterTest:
    """Where a node shoots from its children: the hidden-centroid test, and eq. 7's with
    ``solver.shooter_split``."""
    test = hidden_centroid_test()
    return test if scene.solver.shooter_split is None else either(test, point_source_test(scene.solver.shooter_split))


def rim_stretches(scene: Scene, mesh: Mesh, size: np.ndarray) -> np.ndarray | None:
    """(T,) where contacts are meshed, the straight stretches of the footprints' rims that
    the elements of ``mesh`` lie along (``geometry.patches.rim_runs``, turning at most
    ``RIM_TURN``; -1 at a corner), for patches of sides ``size`` (T,); None elsewhere.

    Beside what stands on a surface its elements shoot only with those along the same
    stretch of the rim, and alone at its corners: a floor patch reaching round a block's
    corner, or over its rim, shoots from a centroid that sees the block's side otherwise
    than the rim does. Cornell box at 8 cm elements, contacts meshed: the tall block's front
    11% dark with such patches, 0.3% off every element shooting; the answer's second round
    relMSE 0.00205 -> 0.00039. On a refined mesh a rim element's children shoot as one patch
    (``refined_patches``): against each refined rim element alone, 6.9 s for 0.00039
    instead of 11.0 s for 0.00037. Only footprints whose rim is at least ``RIM_PATCHES``
    patch sides long: the office's desk and chair legs (rims of 0.2 m among 0.3 m patches)
    changed nothing but doubled its rounds' seconds."""
    return rim_runs(mesh, RIM_PATCHES * size, RIM_TURN) if scene.meshes_contacts else None


def refined_patches(scene: Scene, solver: ProgressiveSolver, saved: dict | None = None) -> PatchShooters:
    """The patches of the solver's mesh after refinement judged on the answer split it
    (docs/DESIGN.md §3.8): those of the initial mesh, each now holding its elements' children
    (``solver.patches.patch``, carried through the split, or after the first solve's larger
    patches its ``regroup``; ``saved``: a saved run's ``PatchShooters.state_dict``), with
    every emitting element, and every one whose object's
    patch size is none, alone; near a node its light leaves from the children of the initial
    elements its elements lie in (``PatchShooters``' ``source_split``). Measured on office
    refined twice (12,751 elements), relative MSE: patches built afresh at the refined
    elements' sizes (2,577) 0.00014 in a 32 s solve, these (601) the same in 24 s; the lamp
    shooting from its patches' centroids 0.00025."""
    mesh, patches = solver.mesh, solver.patches
    group, source = (patches.patch, patches.source) if saved is None else (saved["patch"], saved["source"])
    if saved is None and patches.regroup is not None:  # the first solve's larger patches
        group = patches.regroup.to(source.device).index_select(0, source)
    group = group.cpu().numpy().copy()
    owner = surface_objects(scene, mesh)[mesh.surface.cpu().numpy()]
    alone = (solver.emission > 0).any(dim=1).cpu().numpy() | (patch_sizes(scene, mesh, owner) <= 0)
    group[alone] = group.max() + 1 + np.flatnonzero(alone)
    return PatchShooters(group_patches(mesh, group), solver.device, shooter_test(scene), source=source,
                         source_corners=patches.source_corners, source_split=scene.refine.pattern,
                         eye_level=patches.eye_level)


def scene_extent(mesh: Mesh) -> float:
    """The smallest side of the mesh's bounding box that is not 0 (inf where every side is:
    a point caps nothing)."""
    low, high = mesh.bounding_box()
    sides = (high - low).cpu().numpy()
    sides = sides[sides > 0]
    return float(sides.min()) if len(sides) else float("inf")


def patch_sizes(scene: Scene, mesh: Mesh, owner: np.ndarray, cap: float = AUTO_PATCH_SCENE) -> np.ndarray:
    """(T,) the patch side each element asks for: its object's (``owner`` (T,), the index in
    ``scene.objects`` of each element's) ``patch_size``, else the solver's; ``auto`` is
    ``AUTO_PATCH_ELEMENTS`` element sides (refining by the answer, at most ``cap`` times the
    mesh's smallest extent, ``scene_extent``), ``none`` 0 (it shoots alone)."""
    asked = [obj.patch_size if obj.patch_size is not None else scene.solver.patch_size for obj in scene.objects]
    # per object: a multiple of the element side (auto) and a length (a number), one of them 0
    factor = np.asarray([AUTO_PATCH_ELEMENTS if size == "auto" else 0.0 for size in asked])
    length = np.asarray([0.0 if size in ("auto", "none", None) else float(size) for size in asked])
    # A mesh file's triangles may be finer than its element_size (they are split only when
    # coarser): its auto patches are about 2 x 2 elements of that size, not of its triangles
    nominal = np.asarray([obj.element_size if isinstance(obj, MeshFile) else 0.0 for obj in scene.objects])
    auto = factor[owner] * np.maximum(element_sides(mesh), nominal[owner])
    if scene.refines_by_answer:
        auto = np.minimum(auto, cap * scene_extent(mesh))
    return auto + length[owner]
