"""Patches shoot, elements receive: grouping, conservation, closed-box answers, and the same
answer at two patch sizes."""
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

import hemirad
from hemirad.adaptive.shooter_split import point_source_test
from hemirad.assembly import NEAR_REACH, emitter_eye_level, make_solver
from hemirad.core.colour import luminance
from hemirad.core.errors import HemiradWarning
from hemirad.geometry.mesh import Mesh
from hemirad.geometry.patches import build_patches, element_sides, plane_axes
from hemirad.lighting.photometry import emission_table
from hemirad.scene.meshing import build_mesh, grid_quad
from hemirad.transport.shooters import PatchShooters, back_face_share, either, eye_points, hidden_centroid_test
from hemirad.transport.solver import ProgressiveSolver

from patches import assert_power_balances, closed_box, open_box, quad, quads_mesh, random_materials


def patch_solver(mesh, rho, E, patch_size, resolution=32, overshoot=True, split_test=None, near_reach=NEAR_REACH,
                 eye_level=0, **options):
    tree = build_patches(mesh, np.full(mesh.num_elements, patch_size))
    shooters = PatchShooters(tree, torch.device("cpu"), split_test, eye_level=eye_level)
    return ProgressiveSolver(mesh, rho, E, resolution, patches=shooters, overshoot=overshoot, near_reach=near_reach,
                             **options)


def test_patches_tile_each_plane_and_their_trees_reach_every_element():
    mesh = closed_box(element_size=0.25)  # 6 faces of 4 x 4 cells, 32 triangles each
    tree = build_patches(mesh, np.full(mesh.num_elements, 0.5))
    assert 6 * 4 <= tree.num_patches <= 6 * 9  # 2 x 2 cells of 0.5 a face, wherever the grid starts
    assert sorted(tree.leaf.tolist()) == list(range(mesh.num_elements))
    for patch in range(tree.num_patches):
        members = torch.nonzero(tree.patch == patch).reshape(-1)
        assert len(members) >= 1 and len(torch.unique(mesh.plane_ids[members])) == 1
        extent = mesh.centroids[members].amax(0) - mesh.centroids[members].amin(0)
        assert float(extent.max()) < 0.5  # one cell of the grid
        root = int(tree.root[patch])
        leaves = tree.leaf[members]
        assert int(leaves.min()) == int(tree.lo[root]) and int(leaves.max()) + 1 == int(tree.hi[root])
        # the children partition their parent, and a node's centroid is its elements' area centroid
        children = tree.children(root)
        assert sum(int(tree.hi[c] - tree.lo[c]) for c in children) == (len(members) if children else 0)
        areas = mesh.areas[members]
        centroid = (mesh.centroids[members] * areas[:, None]).sum(0) / areas.sum()
        torch.testing.assert_close(tree.centroid[root], centroid)
    assert np.allclose(element_sides(mesh), 0.25)


def test_a_plane_takes_the_patch_size_asked_over_most_of_its_area():
    # a 1 m square of 0.25 m cells with a 5 cm strip of 2.5 cm cells along one side, one
    # surface: the strip's many small elements must not set the plane's grid (by count they
    # are five in six of its elements, by area a twentieth)
    square, square_triangles = grid_quad(quad((0, 0, 0), (1, 0, 0), (0, 1, 0)), 0.25)
    strip, strip_triangles = grid_quad(quad((0, 1, 0), (1, 0, 0), (0, 0.05, 0)), 0.025)
    triangles = torch.cat([torch.as_tensor(square_triangles), torch.as_tensor(strip_triangles) + len(square)])
    zeros = torch.zeros(len(triangles), dtype=torch.int64)
    mesh = Mesh(torch.cat([torch.as_tensor(square), torch.as_tensor(strip)]), triangles, zeros, zeros, ["floor"])
    assert len(torch.unique(mesh.plane_ids)) == 1
    tree = build_patches(mesh, 2 * element_sides(mesh))  # auto patches: two element sides
    in_square = mesh.centroids[:, 1] < 1.0
    assert len(torch.unique(tree.patch[in_square])) == 4  # its 2 x 2 cells of 0.5 m, not 32 of 5 cm
    assert len(torch.unique(tree.patch[~in_square])) == 2  # the strip along the cells it crosses


def test_a_nodes_members_and_their_counts_follow_the_receivers_splits():
    # after a split the children share their parent's leaf position: a node holds exactly the
    # elements whose leaf position lies in its [lo, hi), in element order, and counts them so
    mesh = closed_box(element_size=0.25)
    patches = PatchShooters(build_patches(mesh, np.full(mesh.num_elements, 0.5)), torch.device("cpu"))
    parent = torch.cat([torch.arange(mesh.num_elements), torch.arange(0, mesh.num_elements, 3).repeat(3)])
    patches.inherit(parent)
    marked = torch.arange(len(parent)) % 5 == 0
    counts, marked_counts = patches.member_counts(), patches.member_counts(marked)
    leaf, tree = patches.leaf, patches.tree
    for node in range(tree.num_nodes):
        inside = torch.nonzero((leaf >= tree.lo[node]) & (leaf < tree.hi[node])).reshape(-1)
        assert torch.equal(patches.members(node), inside)
        assert counts[node] == len(inside) and marked_counts[node] == int(marked[inside].sum())


def test_every_node_splits_into_the_quadrants_of_its_box_numbered_depth_first():
    # uneven elements (two sizes on one floor) make trees of several depths and lopsided quadrants
    floor = quad((0, 0, 0), (1.0, 0, 0), (0, 0.6, 0))
    mesh = quads_mesh([floor, quad((1.0, 0, 0), (0.7, 0, 0), (0, 0.6, 0))], [0.1, 0.06])
    tree = build_patches(mesh, np.full(mesh.num_elements, 0.5))
    u, v = (torch.from_numpy(axis) for axis in plane_axes(mesh.normals[0].numpy()))  # the floor's
    depth, next_number = 0, 0

    def check(node, members, level):  # the recursive definition the tree must equal
        nonlocal depth, next_number
        assert node == next_number  # depth-first: a node, then each child's subtree in turn
        next_number += 1
        depth = max(depth, level)
        assert sorted(tree.leaf[members].tolist()) == list(range(int(tree.lo[node]), int(tree.hi[node])))
        areas = mesh.areas[members]
        torch.testing.assert_close(tree.centroid[node], (mesh.centroids[members] * areas[:, None]).sum(0) / areas.sum())
        if len(members) == 1:
            assert tree.children(node) == []
            return
        xy = torch.stack([mesh.centroids[members] @ u, mesh.centroids[members] @ v], 1)
        mid = 0.5 * (xy.amin(0) + xy.amax(0))
        quadrant = (xy[:, 0] > mid[0]).long() * 2 + (xy[:, 1] > mid[1]).long()
        parts = [members[quadrant == q] for q in range(4) if (quadrant == q).any()]
        if len(parts) == 1:  # coincident centroids: halves
            parts = [members[:len(members) // 2], members[len(members) // 2:]]
        assert len(tree.children(node)) == len(parts)
        for child, part in zip(tree.children(node), parts):
            assert int(tree.lo[child]) >= int(tree.lo[node]) and int(tree.hi[child]) <= int(tree.hi[node])
            check(child, part, level + 1)

    for patch in range(tree.num_patches):
        check(int(tree.root[patch]), torch.nonzero(tree.patch == patch).reshape(-1), 0)
    assert next_number == tree.num_nodes and depth >= 3


@pytest.mark.parametrize("totals", ["hemicube", "area"])
def test_power_balances_with_overshooting_and_split_shooters(totals):
    # An open box (its top removed), a glowing corner, both shooter tests on, the emitting
    # patches shooting from eyes: received + unshot + escaped = emitted to 1e-9, with the
    # unshot power partly negative.
    mesh = open_box(element_size=0.25)
    rho, E = random_materials(mesh.num_elements, seed=1, span=0.7, low=0.2, glowing=8)
    solver = patch_solver(mesh, rho, E, 0.5, split_test=either(hidden_centroid_test(), point_source_test(0.5)),
                          near_totals=totals, eye_level=1)
    try:
        state = solver.run(max_shots=150, unshot_fraction=0.0)
    finally:
        solver.close()
    assert solver.patches.shooter_splits > 0 and bool((state.unshot < 0).any())
    assert any(solver._eyes(node) is not None for cut in solver.patches.cuts.values() for node in cut)
    emitted = (E * mesh.areas[:, None]).sum(0)
    assert_power_balances(state, mesh.areas, rho, E, emitted, rtol=1e-9)
    assert bool((state.escaped > 0.05 * emitted).all())  # the open top lets light out
    assert len(solver._near) > 0 and all(bool((n.weights >= 0).all()) for n in solver._near.values())


@pytest.mark.parametrize("totals", ["hemicube", "area"])
def test_power_balances_in_sweeps_and_they_converge_to_what_single_shots_do(totals):
    # The same open box: sweeps (every patch at once, from the kept light) conserve power to
    # 1e-9, also when the shot limit cuts a sweep short, and converge to the answer of
    # shooting one patch at a time.
    mesh = open_box(element_size=0.25)
    rho, E = random_materials(mesh.num_elements, seed=1, span=0.7, low=0.2, glowing=8)
    emitted = (E * mesh.areas[:, None]).sum(0)
    split_test = either(hidden_centroid_test(), point_source_test(0.5))
    answers = []
    for sweeps, shots in ((True, 100), (True, 100000), (False, 100000)):
        solver = patch_solver(mesh, rho, E, 0.5, split_test=split_test, near_totals=totals, sweeps=sweeps)
        try:
            state = solver.run(max_shots=shots, unshot_fraction=1e-9 if shots > 100 else 0.0)
        finally:
            solver.close()
        assert solver.patches.shooter_splits > 0
        assert_power_balances(state, mesh.areas, rho, E, emitted, rtol=1e-9)
        if shots == 100:
            assert state.shots == 100 and solver.sweep_count > 2 and bool((state.unshot > 0).any())
        else:
            answers.append(state.radiosity)
    torch.testing.assert_close(answers[0], answers[1], rtol=1e-7, atol=0)


def test_sweeps_that_outgrow_the_memory_asked_for_say_so_and_go_on_one_patch_at_a_time():
    # The open box with 64 kB for the kept light: the first sweeps' matrices outgrow it, the
    # user is told which option keeps the sweeps, and the solve goes on to the same answer
    mesh = open_box(element_size=0.25)
    rho, E = random_materials(mesh.num_elements, seed=1, span=0.7, low=0.2, glowing=8)
    answers = []
    for cache_bytes in (256 << 20, 64 << 10):
        solver = patch_solver(mesh, rho, E, 0.5, sweeps=True, cache_bytes=cache_bytes)
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                state = solver.run(max_shots=100000, unshot_fraction=1e-9)
        finally:
            solver.close()
        said = [str(w.message) for w in caught if issubclass(w.category, HemiradWarning)]
        assert solver.sweeps == (cache_bytes > 1 << 20) and len(said) == (0 if solver.sweeps else 1)
        assert all("solver.cache_mb" in message for message in said)
        assert_power_balances(state, mesh.areas, rho, E, (E * mesh.areas[:, None]).sum(0), rtol=1e-9)
        answers.append(state.radiosity)
    torch.testing.assert_close(answers[0], answers[1], rtol=1e-7, atol=0)


def test_power_balances_when_elements_shoot_with_a_near_field():
    mesh = open_box(element_size=0.25)
    rho, E = random_materials(mesh.num_elements, seed=2, span=0.7, low=0.2, glowing=8)
    solver = ProgressiveSolver(mesh, rho, E, 32, near_reach=NEAR_REACH)
    try:
        state = solver.run(max_shots=400, unshot_fraction=0.0)
    finally:
        solver.close()
    assert len(solver._near) > 0
    assert_power_balances(state, mesh.areas, rho, E, (E * mesh.areas[:, None]).sum(0), rtol=1e-9)


def box_errors(element_size, patch_size, rho, **options):
    """The closed unit box of ``element_size`` cells, every element emitting 2 with reflectance
    ``rho``, solved to 1e-5 unshot power with a hemicube of 128 (patches of ``patch_size``, or
    every element shooting when None): each element's error against the exact E / (1 - rho),
    and the mean patch's elements."""
    mesh = closed_box(element_size=element_size)
    T = mesh.num_elements
    R = torch.full((T, 3), rho, dtype=torch.float64)
    E = torch.full((T, 3), 2.0, dtype=torch.float64)
    expected = 2.0 / (1 - rho)
    if patch_size is None:
        solver, per_patch = ProgressiveSolver(mesh, R, E, 128, **options), 1.0
    else:
        solver = patch_solver(mesh, R, E, patch_size, 128, **options)
        per_patch = float(torch.bincount(solver.patches.tree.patch).float().mean())
    try:
        state = solver.run(max_shots=50000, unshot_fraction=1e-5)
    finally:
        solver.close()
    assert solver.unshot_fraction <= 1e-5
    mean = (state.radiosity * mesh.areas[:, None]).sum(0) / mesh.areas.sum()
    torch.testing.assert_close(mean, torch.full((3,), expected, dtype=torch.float64), rtol=1e-4, atol=0)
    return (state.radiosity[:, 0] / expected - 1).abs(), per_patch


@pytest.mark.parametrize("rho", [0.3, 0.7])
def test_uniformly_emitting_closed_box_converges_to_its_exact_answer_per_element(rho):
    # The exact answer is E / (1 - rho) everywhere. From one point, a shooter's light to its
    # neighbours along the box's edges falls short of what its area sends (the area-to-area
    # factor grows steeply where two faces meet): 7% per element at rho 0.7 even with every
    # element shooting, 6-9% with patches. The near field sends it as the shooter's elements
    # do, with their own factors: per element within 1% with patches of about 8, 18 and 32
    # elements, and with every element shooting (measured at rho 0.7: 0.3%, 0.5%, 0.35%, 0.5%).
    for size, cells, per_patch in ((None, 0.25, 1), (0.5, 0.25, 8), (0.5, 1 / 6, 18), (1.0, 0.25, 32)):
        errors, found = box_errors(cells, size, rho, near_reach=NEAR_REACH)
        assert found == pytest.approx(per_patch, rel=0.1)
        assert float(errors.max()) <= 0.01, (size, cells, float(errors.max()))
    for size in (None, 0.5):  # without the near field
        errors, _ = box_errors(0.25, size, rho, near_reach=0.0)
        assert float(errors.max()) > 0.025


def test_own_totals_keep_a_closed_box_right_beyond_the_near_field():
    # A box of 8 x 8 cells a face with patches of 8 elements: the near field (4 patch radii)
    # no longer covers it. Keeping the hemicube's total over the near receivers keeps the
    # point's error in that total (5.4% at rho 0.7); each source's own total, the rest of its
    # hemisphere G's scaled to fit, leaves the hemicube's pixels (0.9%).
    errors = {totals: float(box_errors(0.125, 0.25, 0.7, near_reach=NEAR_REACH, near_totals=totals)[0].max())
              for totals in ("hemicube", "area")}
    assert errors["area"] < 0.015 and errors["hemicube"] > 3 * errors["area"], errors


def test_two_patch_sizes_give_the_same_cornell_box():
    means = []
    for size in ("auto", 120.0):
        scene = hemirad.load_scene("cornell_box")
        scene.solver.patch_size, scene.solver.resolution, scene.solver.unshot_fraction = size, 64, 1e-3
        solver = make_solver(scene)
        try:
            solver.run(scene.solver.max_shots, scene.solver.unshot_fraction)
            areas = solver.areas[:, None]
            lit = (solver.emission == 0).all(dim=1)
            means.append(((solver.state.radiosity * areas)[lit].sum(0) / areas[lit].sum()))
            patches = solver.patches.tree.num_patches
        finally:
            solver.close()
    assert patches < 600  # 120 mm patches: about 3 x 3 elements
    assert float((means[0] / means[1] - 1).abs().max()) < 0.01


def test_patches_converge_in_fewer_shots_and_renders_than_elements():
    counts = {}
    for size, sweeps in ((None, False), ("auto", False), ("auto", True)):
        scene = hemirad.load_scene("floating")
        scene.solver.patch_size, scene.solver.resolution, scene.solver.unshot_fraction = size, 32, 1e-2
        scene.solver.sweeps = sweeps
        solver = make_solver(scene)
        try:
            solver.run(scene.solver.max_shots, scene.solver.unshot_fraction)
            counts[size, sweeps] = (solver.state.shots, solver.hemicubes_rendered, solver.sweep_count)
        finally:
            solver.close()
    elements = counts[None, False]
    assert counts["auto", False][0] < elements[0] / 4 and counts["auto", False][1] < elements[1] / 2
    # sweeps: no more renders than one patch at a time, and a few dozen steps instead of
    # thousands of shots
    assert counts["auto", True][1] <= counts["auto", False][1] and counts["auto", True][2] < elements[0] / 50


def penumbra_setup(emitter_size):
    """A 0.4 m square emitter 1 m above a floor strip, a 0.3 m blocker half way, the emitter
    meshed at ``emitter_size``: the mesh, rho, E, the floor's elements, their radiosity by
    Lambert's closed form for the part of the emitter each centroid sees (the emitter less
    the blocker's projection from it), and the penumbra's elements."""
    from hemirad.geometry.analytic import point_to_polygon

    emitter = quad([-0.2, 1.0, -0.2], [0.4, 0, 0], [0, 0, 0.4])  # faces down
    blocker = quad([-0.15, 0.5, -0.15], [0, 0, 0.3], [0.3, 0, 0])  # faces up
    floor = quad([-0.8, 0.0, -0.02], [0, 0, 0.04], [1.6, 0, 0])  # faces up
    mesh = quads_mesh([emitter, blocker, floor], [emitter_size, 0.3, 0.04])
    T = mesh.num_elements
    rho = torch.zeros(T, 3, dtype=torch.float64)
    rho[mesh.surface == 2] = 0.5
    E = torch.zeros(T, 3, dtype=torch.float64)
    E[mesh.surface == 0] = 10.0
    on_floor = torch.nonzero(mesh.surface == 2).reshape(-1)
    up = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)

    def closed_form(p):
        F = point_to_polygon(p, up, emitter)
        shadow = p + (blocker - p) * (1.0 - p[1]) / (0.5 - p[1])  # on the emitter's plane
        lo, hi = torch.maximum(shadow.amin(0), emitter.amin(0)), torch.minimum(shadow.amax(0), emitter.amax(0))
        if hi[0] > lo[0] and hi[2] > lo[2]:
            hidden = torch.tensor([[lo[0], 1, lo[2]], [hi[0], 1, lo[2]], [hi[0], 1, hi[2]], [lo[0], 1, hi[2]]],
                                  dtype=torch.float64)
            F = F - point_to_polygon(p, up, hidden)
        return 0.5 * 10.0 * F

    expected = torch.stack([closed_form(p) for p in mesh.centroids[on_floor]])
    lit = expected > 0.1 * expected.max()
    penumbra = lit & (expected < 0.98 * expected.max())
    assert int(penumbra.sum()) > 40
    return mesh, rho, E, on_floor, expected, penumbra


def test_a_split_emitter_draws_the_penumbra_a_centroid_shot_cannot():
    # One hemicube at the emitter's centroid draws a hard shadow; shooting from the parts
    # eq. 7 asks for follows the penumbra, down to the emitter's own elements (2.5 cm: the
    # staircase of their centroids is what is left).
    mesh, rho, E, on_floor, expected, penumbra = penumbra_setup(0.025)
    T = mesh.num_elements
    errors = {}
    for split in (None, point_source_test(0.5)):
        tree = build_patches(mesh, np.full(T, 1.0))  # the emitter is one patch
        shooters = PatchShooters(tree, torch.device("cpu"), split)
        solver = ProgressiveSolver(mesh, rho, E, 256, patches=shooters, overshoot=False, near_reach=0.0,
                                   small_receivers="closed_form")  # the default: no pixel luck on the floor
        try:
            solver.run(1, 0.0)  # the emitter's shot: nothing else reflects anything back
        finally:
            solver.close()
        error = solver.state.radiosity[on_floor, 0] / expected - 1
        errors[split is not None] = float(error[penumbra].abs().max())
    # measured: 1.00 and 0.017 (0.050 with the hemicubes' pixel rows along the blocker's
    # edges, which then err by the same fraction of a pixel all along them)
    assert errors[False] > 0.15 and errors[True] < 0.03, errors


def test_lamps_get_eyes_where_their_elements_are_large_beside_the_scene():
    # floating's lamp of 0.2 m elements under a 2.5 m ceiling (8%) shoots from eyes where the
    # answer refines; meshed at 0.05 m (2%) it does not need them, nor does any unrefined run
    def level(lamp_element, criterion="answer", eyes="auto"):
        scene = hemirad.load_scene("floating")
        scene.refine.pattern, scene.refine.criterion = "pattern2", criterion
        scene.solver.emitter_eyes = eyes
        lamp_material = {m.name for m in scene.materials if m.emits}
        for obj in scene.objects:
            if obj.material in lamp_material:
                obj.element_size = lamp_element
        mesh = build_mesh(scene)
        return emitter_eye_level(scene, mesh, emission_table(scene, mesh)[mesh.material])

    assert level(0.2) == 1 and level(0.05) == 0
    assert level(0.2, criterion="gradient") == 0
    assert level(0.05, eyes=2) == 2


def test_emitter_eyes_draw_the_penumbra_its_elements_centroids_cannot():
    # The geometry above with the emitter as 32 triangles of 0.1 m, each shooting alone from
    # its centroid: a staircase of 32 point sources. With eyes, each shoots from the
    # centroids of 4**level equal parts of itself: level L is the emitter meshed 2**L times
    # finer, without its elements.
    mesh, rho, E, on_floor, expected, penumbra = penumbra_setup(0.1)
    errors, renders = [], []
    for level in (0, 1, 2):
        shooters = PatchShooters(build_patches(mesh, np.zeros(mesh.num_elements)), torch.device("cpu"), eye_level=level)
        solver = ProgressiveSolver(mesh, rho, E, 256, patches=shooters, overshoot=False, near_reach=0.0,
                                   small_receivers="closed_form")
        try:
            solver.run(32, 0.0)  # each emitting element's shot
        finally:
            solver.close()
        errors.append(float((solver.state.radiosity[on_floor, 0] / expected - 1)[penumbra].abs().max()))
        renders.append(solver.hemicubes_rendered)
    # measured: 0.247, 0.097, 0.017
    assert errors[0] > 0.15 and errors[1] < 0.6 * errors[0] and errors[2] < 0.03, errors
    assert renders == [32, 128, 512]


def test_a_sweep_makes_a_lamps_eye_rows_on_its_worker_as_single_shots_make_them():
    # In sweeps a lamp's eyes are drawn on the drawing thread and their rows made with their
    # group's on the worker, summed by their weights (``sweep.GroupLight``): the rows and the
    # light shots one at a time give, to the last bits a batch rounds otherwise.
    mesh, rho, E, on_floor, expected, penumbra = penumbra_setup(0.1)
    made = []
    for sweeps in (False, True):
        shooters = PatchShooters(build_patches(mesh, np.zeros(mesh.num_elements)), torch.device("cpu"), eye_level=1)
        solver = ProgressiveSolver(mesh, rho, E, 64, patches=shooters, overshoot=False, near_reach=0.0,
                                   small_receivers="closed_form", sweeps=sweeps)
        try:
            solver.run(32, 0.0)  # each emitting element's shot
        finally:
            solver.close()
        lamp = shooters.tree.root[shooters.patch[mesh.surface == 0]].tolist()
        assert len(lamp) == 32 and solver.hemicubes_rendered >= 32 * 4
        made.append((torch.stack([solver.rows.get(node, mesh.num_elements) for node in lamp]),
                     solver.state.radiosity[on_floor, 0]))
    (shot_rows, shot_floor), (swept_rows, swept_floor) = made
    assert bool((shot_rows[:, on_floor] > 0).any())
    torch.testing.assert_close(swept_rows, shot_rows, rtol=1e-12, atol=1e-18)
    torch.testing.assert_close(swept_floor, shot_floor, rtol=1e-12, atol=0)


def test_eye_points_share_a_triangle_equally_and_begin_at_its_centroid():
    corners = torch.tensor([[[0.0, 0, 0], [2, 0, 0], [0, 1, 0]], [[1, 1, 1], [1, 2, 1], [1, 1, 3]]],
                           dtype=torch.float64)
    for level in range(3):
        eyes = eye_points(corners, level).reshape(2, 4 ** level, 3)
        torch.testing.assert_close(eyes[:, 0], corners.mean(1))
        torch.testing.assert_close(eyes.mean(1), corners.mean(1))  # equal parts: their mean is the centroid
        # every eye inside its triangle
        a, b, c = corners.unbind(1)
        u = eyes - a[:, None]
        M = torch.stack([b - a, c - a], 2)  # (2, 3, 2)
        w = torch.linalg.lstsq(M[:, None].expand(-1, 4 ** level, -1, -1), u[..., None]).solution[..., 0]
        assert bool(((w > 0) & (w.sum(-1, keepdim=True) < 1)).all())


def test_a_patch_under_a_cover_splits_where_it_leaves_it_and_stops_where_it_does_not():
    # A glowing 1 m ceiling, one patch, with a panel hung 5 mm below its x < 0.75 part (its
    # back to the ceiling). The patch's centroid is hidden, so it splits; its part under the
    # panel would split down to single elements, every one of them shooting into the panel's
    # back, where it lies wholly under the panel; its part beside the panel splits until its
    # light leaves from where it is.
    ceiling = quad([0.0, 1.0, 0.0], [1.0, 0, 0], [0, 0, 1.0])  # faces down
    panel = quad([-0.01, 0.995, -0.01], [0.76, 0, 0], [0, 0, 1.02])  # faces down
    mesh = quads_mesh([ceiling, panel], [1.0 / 16, 0.5])
    T = mesh.num_elements
    rho = torch.full((T, 3), 0.5, dtype=torch.float64)
    E = torch.zeros(T, 3, dtype=torch.float64)
    E[mesh.surface == 0] = 1.0
    tree = build_patches(mesh, np.full(T, 2.0))
    solver = ProgressiveSolver(mesh, rho, E, 64, patches=PatchShooters(tree, torch.device("cpu"), hidden_centroid_test()),
                               near_reach=0.0)
    try:
        nodes = solver.patches.cut(int(tree.patch[0]), solver.render, solver.mesh.corners)
        power = torch.stack([solver.areas[solver.patches.members(node)].sum() for node in nodes])
        into_back = sum(float(p) * back_face_share(solver.render(node)) for p, node in zip(power, nodes))
    finally:
        solver.close()
    under = int(((mesh.surface == 0) & (mesh.centroids[:, 0] < 0.75)).sum())  # 384 elements
    assert len(nodes) < under / 8  # measured: 10 (388 when the covered part split down to its elements)
    # what the ceiling shoots into the panel's back: its covered part's power, not more
    # (measured: 0.750 of it, and 0.749 from the 388; a centroid shot from the patch sends 1.00)
    assert abs(into_back / float(power.sum()) - 0.75) < 0.03


def test_an_object_can_set_its_own_patch_size():
    # The floating room's walls and floor at their default patches, the board's elements each
    # shooting on its own, and the lamp in one patch.
    from hemirad.scene.meshing import surface_objects

    scene = hemirad.load_scene("floating")
    board = next(i for i, o in enumerate(scene.objects) if o.name == "board.top")
    lamp = next(i for i, o in enumerate(scene.objects) if o.name == "lamp")
    scene.objects[board].patch_size, scene.objects[lamp].patch_size = "none", 5.0
    solver = make_solver(scene)
    try:
        tree, mesh = solver.patches.tree, solver.mesh
        of = torch.from_numpy(surface_objects(scene, mesh))[mesh.surface]
        on_board, on_lamp = of == board, of == lamp
        assert len(torch.unique(tree.patch[on_board])) == int(on_board.sum())  # one element a patch
        assert len(torch.unique(tree.patch[on_lamp])) == 1 and int(on_lamp.sum()) > 1
        others = ~(on_board | on_lamp)
        assert len(torch.unique(tree.patch[others])) < int(others.sum()) / 3  # about 2 x 2 elements
    finally:
        solver.close()

def test_auto_patches_refined_by_the_answer_are_capped_by_the_scene_size():
    # Office at twice its element sizes: 1 m wall elements make 2 m auto patches; refining by
    # the answer the refined solves' are at most AUTO_PATCH_SCENE of the room's 2.7 m height
    # and the first solve's, which only ranks, at most FIRST_SOLVE_PATCH_SCENE of it (unless
    # no round can follow: then the first solve is the answer); a length the scene asks for is
    # kept as asked.
    from hemirad.assembly import AUTO_PATCH_SCENE, FIRST_SOLVE_PATCH_SCENE, make_patches

    def widest(mesh, patch) -> float:
        centroids = mesh.centroids
        return max(float((centroids[patch == p].amax(dim=0) - centroids[patch == p].amin(dim=0)).max())
                   for p in torch.unique(patch))

    def first_and_refined(scene):
        mesh = build_mesh(scene)
        patches = make_patches(scene, mesh, torch.device("cpu"))
        refined = patches.tree.patch if patches.regroup is None else patches.regroup
        return widest(mesh, patches.tree.patch), widest(mesh, refined)

    scene = hemirad.load_scene("office").with_element_sizes_scaled(2.0)
    cap, first_cap = AUTO_PATCH_SCENE * 2.7, FIRST_SOLVE_PATCH_SCENE * 2.7
    assert min(first_and_refined(scene)) > 1.5 * cap  # unrefined: two elements a side
    scene.refine.pattern, scene.refine.criterion = "pattern2", "answer"
    assert scene.refines_by_answer
    first, refined = first_and_refined(scene)
    assert refined < cap < first < first_cap
    scene.refine.rounds = 0
    assert max(first_and_refined(scene)) < cap
    scene.refine.rounds, scene.refine.max_elements = 1, build_mesh(scene).num_elements
    assert max(first_and_refined(scene)) < cap
    scene.refine.max_elements = 200_000
    scene.solver.patch_size = 1.5
    assert min(first_and_refined(scene)) > 1.5 * cap


def test_a_bad_patch_size_is_one_paragraph_naming_the_key(tmp_path):
    from hemirad.core.errors import SceneError

    text = (Path(hemirad.__file__).parent / "scenes" / "floating.yaml").read_text()
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace("solver:\n", "solver:\n  patch_size: -1\n", 1))
    with pytest.raises(SceneError, match=r"solver\.patch_size"):
        hemirad.load_scene(bad)


def test_reflectors_draw_at_their_own_resolution_and_power_still_balances():
    # The open box of the tests above, emitting patches at 64, the others at 32: each node's
    # hemicube has its resolution, power balances to 1e-9, and the answer is the one with
    # every node at 64 to within what the coarser pixels of the reflected light move it.
    mesh = open_box(element_size=0.25)
    rho, E = random_materials(mesh.num_elements, seed=1, span=0.7, low=0.2, glowing=8)
    emitted = (E * mesh.areas[:, None]).sum(0)
    answers = {}
    for reflectors in (64, 32):
        solver = patch_solver(mesh, rho, E, 0.5, resolution=64, reflector_resolution=reflectors, sweeps=True)
        try:
            state = solver.run(max_shots=100_000, unshot_fraction=1e-4)
            tree = solver.patches.tree
            glowing = [int(tree.root[p]) for p in range(tree.num_patches)
                       if bool((E[solver.patches.members(int(tree.root[p]))] > 0).any())]
            dark = [int(tree.root[p]) for p in range(tree.num_patches) if int(tree.root[p]) not in glowing]
            assert glowing and dark
            assert {solver.render(n).resolution for n in glowing} == {64}
            assert {solver.render(n).resolution for n in dark} == {reflectors}
        finally:
            solver.close()
        assert_power_balances(state, mesh.areas, rho, E, emitted, rtol=1e-9)
        answers[reflectors] = luminance(state.radiosity - E)
    weights = mesh.areas / mesh.areas.sum()
    difference = float((weights * (answers[32] - answers[64]).abs()).sum() / (weights * answers[64]).sum())
    assert 0 < difference < 0.01, difference
    # where reflectors' receivers under a pixel get closed forms (refined meshes), all draw at 64
    solver = patch_solver(mesh, rho, E, 0.5, resolution=64, reflector_resolution=32, small_receivers="closed_form")
    try:
        tree = solver.patches.tree
        assert {solver.render(int(tree.root[p])).resolution for p in range(tree.num_patches)} == {64}
    finally:
        solver.close()


def test_a_bad_reflector_resolution_is_one_paragraph_naming_the_key(tmp_path):
    from hemirad.core.errors import SceneError

    text = (Path(hemirad.__file__).parent / "scenes" / "floating.yaml").read_text()
    for value in ("33", "half"):
        bad = tmp_path / "bad.yaml"
        bad.write_text(text.replace("solver:\n", f"solver:\n  reflector_resolution: {value}\n", 1))
        with pytest.raises(SceneError, match=r"solver\.reflector_resolution.*auto or an even whole number"):
            hemirad.load_scene(bad)


def test_sweep_matrices_are_the_same_whatever_batches_their_entries_came_in():
    # a resumed run adds its nodes in other batches than the run it continues: the matrix, and
    # so every sum over it, must not depend on that
    from hemirad.transport.sweep import _SortedCSR

    g = torch.Generator().manual_seed(5)
    shape = (40, 30)
    cells = torch.randperm(shape[0] * shape[1], generator=g)[:300]
    rows, columns = cells // shape[1], cells % shape[1]
    values = torch.rand(300, generator=g, dtype=torch.float64)
    whole = _SortedCSR(shape, torch.device("cpu"))
    key = rows * shape[1] + columns
    whole.merge(key, values)
    parts = _SortedCSR(shape, torch.device("cpu"))
    for part in torch.randperm(300, generator=g).split([170, 1, 129]):
        parts.merge(key[part], values[part])
    for a, b in ((whole.crow, parts.crow), (whole.columns, parts.columns), (whole.values, parts.values)):
        assert torch.equal(a, b)
    dense = torch.zeros(shape, dtype=torch.float64).index_put_((rows, columns), values)
    assert torch.equal(whole.matrix().to_dense(), dense)
    power = torch.rand(shape[1], 3, generator=g, dtype=torch.float64)
    assert torch.equal(whole.matrix() @ power, parts.matrix() @ power)


@pytest.mark.parametrize("totals", ["hemicube", "area"])
def test_near_fields_made_together_are_each_shooters_own(totals, monkeypatch):
    # Many shooters' near fields are made in one pass (and in runs of at most PAIR_CHUNK
    # pairs, a run of one shooter broadcast rather than gathered): each must be what that
    # shooter alone gives, to rounding (vectorised transcendentals may differ in the last bit).
    from hemirad.transport import nearfield
    scene = hemirad.load_scene("cornell_box")
    scene.solver.resolution = 64
    solver = make_solver(scene)
    try:
        patches = solver.patches
        shooters = []
        for patch in range(0, patches.tree.num_patches, 23):
            for node in patches.cut(patch, solver.render_and_keep, solver.mesh.corners):
                shooters.append(solver._near_shooter(node, solver.form_factors_of(node), None))
        alone = [nearfield.near_fields(solver.mesh, [s], NEAR_REACH, totals)[0] for s in shooters]
        monkeypatch.setattr(nearfield, "PAIR_CHUNK", 2000)  # runs of several shooters, and of one
        together = nearfield.near_fields(solver.mesh, shooters, NEAR_REACH, totals)
        assert len(together) == len(shooters)
        for one, many in zip(alone, together):
            assert torch.equal(one.rows, many.rows)
            assert one.weights.shape == many.weights.shape
            torch.testing.assert_close(many.weights, one.weights, rtol=1e-12, atol=1e-18)
            torch.testing.assert_close(many.far_scale, one.far_scale, rtol=1e-12, atol=0.0)
        assert sum(len(n.rows) for n in alone) > 20 * len(shooters)  # not a vacuous comparison
    finally:
        solver.close()
