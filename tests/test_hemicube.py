"""The hemicube renderer: per-face frustum culling changes no pixel."""
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import hemirad
from hemirad.geometry.split import split_triangles
from hemirad.scene.meshing import build_mesh
from hemirad.transport.hemicube import FACES, face_visibility
from hemirad.assembly import make_solver
from hemirad.core.errors import HemiradWarning
from hemirad.transport.renderer import HemicubeRenderer
from hemirad.transport import solver as solver_module
from hemirad.transport.solver import ProgressiveSolver
from hemirad.transport import sweep as sweep_module
from hemirad.transport.nearfield import NearShooter
from hemirad.transport.sweep import GroupLight, make_a_part

from patches import refined_solve


def refined_mesh(name):
    """A bundled scene's mesh with a patch of it split twice (pattern 2: T-vertices)."""
    mesh = build_mesh(hemirad.load_scene(name))
    for _ in range(2):
        selected = torch.zeros(mesh.num_elements, dtype=torch.bool)
        selected[::7] = True
        mesh, _ = split_triangles(mesh, selected, "pattern2")
    return mesh


@pytest.mark.parametrize("name", ["cornell_box", "floating", "office"])
def test_culled_render_gives_the_unculled_atlas_bit_for_bit(name):
    mesh = refined_mesh(name)
    culled = HemicubeRenderer(mesh, 64)
    full = HemicubeRenderer(mesh, 64, cull=False)
    try:
        shooters = torch.linspace(0, mesh.num_elements - 1, 25).long().tolist()
        for shooter in shooters:
            seen = culled.render(shooter)
            drawn = culled.hemicube.drawn_triangles
            seen_full = full.render(shooter)
            assert torch.equal(seen.element, seen_full.element) and torch.equal(seen.front, seen_full.front), shooter
            assert torch.equal(culled.from_element(shooter), full.from_element(shooter))
            # and the point of it: far fewer triangles drawn than five times all of them, a
            # triangle across two cones by those two faces alone (1.05-1.07 times the
            # triangles here; 1.28-1.34 when such a triangle was drawn by all five faces)
            assert full.hemicube.drawn_triangles == 5 * mesh.num_elements
            assert drawn < 1.2 * mesh.num_elements
    finally:
        culled.close()
        full.close()


def test_refined_solve_is_the_same_with_and_without_culling():
    culled, full = (refined_solve("floating_coarse", 15, cull=cull) for cull in (True, False))
    assert culled.mesh.num_elements > build_mesh(hemirad.load_scene("floating_coarse")).num_elements  # it split
    assert torch.equal(culled.mesh.triangles, full.mesh.triangles)
    assert torch.equal(culled.state.radiosity, full.state.radiosity)


def test_a_prefetched_hemicube_is_the_one_rendered_when_asked_for():
    # A sweep starts drawing the next patch's hemicube before it asks for this one's (read
    # back then, decoded when asked for): what it is later handed must be that placement's
    # render, whatever was asked for in between, and count once.
    mesh = build_mesh(hemirad.load_scene("cornell_box"))
    renderer, direct = HemicubeRenderer(mesh, 64), HemicubeRenderer(mesh, 64)
    try:
        placements = [(mesh.centroids[k].numpy(), mesh.normals[k].numpy(), np.array([0.6, 0.3, 0.74]))
                      for k in (5, 900, 2000)]
        renderer.prefetch_at(*placements[0])
        renderer.prefetch_at(*placements[1])  # the first read back to draw this one
        renderer.prefetch_at(*placements[1])  # pending already: ignored
        between = renderer.render_at(*placements[2])  # asked for another first
        first = renderer.render_at(*placements[0])
        second = renderer.render_at(*placements[1])
        assert renderer.renders == 3
        for got, placement in ((between, placements[2]), (first, placements[0]), (second, placements[1])):
            want = direct.render_at(*placement)
            assert torch.equal(got.element, want.element) and torch.equal(got.front, want.front)
            assert torch.equal(got.form_factors, want.form_factors) and torch.equal(got.eye, want.eye)
        with pytest.raises(RuntimeError):
            renderer.hemicube.collect()  # nothing submitted
    finally:
        renderer.close()
        direct.close()


def _solve_office_in_sweeps(cache_mb: float | None = None) -> ProgressiveSolver:
    scene = hemirad.load_scene("office")
    scene.solver.resolution, scene.solver.unshot_fraction = 64, 1e-2
    scene.solver.patch_size = 0.4  # a floor patch then straddles a footprint and shoots from its quadrants
    if cache_mb is not None:
        scene.solver.cache_mb = cache_mb
    solver = make_solver(scene)
    try:
        solver.run(scene.solver.max_shots, scene.solver.unshot_fraction)
    finally:
        solver.close()
    return solver


def test_a_sweep_gives_the_same_numbers_with_and_without_prefetching(monkeypatch):
    # office: some of its patches split, and their nodes are drawn prefetched as well
    prefetched = _solve_office_in_sweeps()
    monkeypatch.setattr(ProgressiveSolver, "_prefetch_node", lambda self, node: None)
    drawn_when_asked = _solve_office_in_sweeps()
    assert prefetched.sweep_count > 1
    assert prefetched.patches.shooter_splits > 0
    assert torch.equal(prefetched.state.radiosity, drawn_when_asked.state.radiosity)
    assert prefetched.hemicubes_rendered == drawn_when_asked.hemicubes_rendered


def test_a_sweep_gives_the_same_numbers_however_far_its_worker_lags(monkeypatch):
    # the worker takes its groups' light in when it can; the solver in group order
    joined = []
    join = ProgressiveSolver._join_group
    monkeypatch.setattr(ProgressiveSolver, "_join_group", lambda self, making: joined.append(1) or join(self, making))
    behind = _solve_office_in_sweeps()
    assert len(joined) > 3  # groups enough for the worker to fall behind
    monkeypatch.setattr(solver_module, "GROUPS_AHEAD", 0)  # each group taken in as soon as it is sent
    in_step = _solve_office_in_sweeps()
    assert torch.equal(behind.state.radiosity, in_step.state.radiosity)
    assert torch.equal(behind.state.unshot, in_step.state.unshot)


def test_the_drawing_thread_makes_what_the_lagging_worker_has_not_begun_with_the_same_numbers(monkeypatch):
    # a worker slowed down: the drawing thread makes parts of the groups instead of waiting
    # (sweep.make_a_part); the numbers are those of a run whose worker made them all
    made_by = []

    def slowed_on_the_worker(make):
        def slowed(*args, **kwargs):
            worker = threading.current_thread().name.startswith("hemirad-sweep")
            made_by.append("worker" if worker else "drawing")
            if worker:
                time.sleep(0.02)
            return make(*args, **kwargs)
        return slowed
    for part in ("small_receiver_rows", "near_fields"):
        monkeypatch.setattr(sweep_module, part, slowed_on_the_worker(getattr(sweep_module, part)))
    shared = _solve_office_in_sweeps()
    assert made_by.count("drawing") > 0 and made_by.count("worker") > 0, made_by
    made_by.clear()
    monkeypatch.setattr(solver_module, "make_a_part", lambda groups: False)  # wait for the worker
    worker_only = _solve_office_in_sweeps()
    assert made_by.count("drawing") == 0
    assert torch.equal(shared.state.radiosity, worker_only.state.radiosity)
    assert torch.equal(shared.state.unshot, worker_only.state.unshot)


def test_a_group_made_part_by_part_by_two_threads_gives_what_one_thread_makes(monkeypatch):
    # GroupLight's parts (its rows a batch of views at a time, then its near fields) taken by
    # whichever thread comes first: the rows assembled in view order (a lamp's eyes summed by
    # their weights), the near fields made from them, and a part's error raised where the
    # group is taken in, not lost on the worker. Views are numbers here, their rows constants.
    made_by = []

    def rows_of(views, corners, areas, limits):
        made_by.append(threading.current_thread().name)
        time.sleep(0.02)
        if -1 in views:
            raise ValueError("a view that cannot be read")
        return [torch.full((4,), 1.0 / view) for view in views]
    monkeypatch.setattr(sweep_module, "small_receiver_rows", rows_of)
    monkeypatch.setattr(sweep_module, "near_fields", lambda mesh, shooters, reach, totals: [
        float(s.form_factors.sum()) for s in shooters])
    mesh = SimpleNamespace(corners=None, areas=None)
    lamp_eyes = [(view, 0.1, 0.3) for view in range(2, 22)]  # 20 views: with the one below, three batches
    small = {7: [(1, 0.1, 1.0)], 9: lamp_eyes}
    shooters = {node: NearShooter(None, None, None, None, None, None) for node in (7, 9)}
    shooters[8] = NearShooter(None, None, None, None, None, torch.ones(4))
    expected_lamp = torch.zeros(4)
    for view, _, weight in lamp_eyes:
        expected_lamp.add_(weight * torch.full((4,), 1.0 / view))

    def made(shared: bool, views: dict):
        with ThreadPoolExecutor(1, thread_name_prefix="hemirad-sweep") as worker:
            light = GroupLight(worker, mesh, views, shooters, 1.0, "area")
            while shared and not light.done() and make_a_part([light]):
                pass
            return light.result()
    for shared in (False, True):
        made_by.clear()
        rows, near = made(shared, small)
        assert torch.equal(rows[7], torch.ones(4)) and torch.equal(rows[9], expected_lamp)
        assert near == {7: 4.0, 9: float(expected_lamp.sum()), 8: 4.0}
        assert len(made_by) == 3 and ("MainThread" in made_by) == shared, made_by
    with pytest.raises(ValueError, match="cannot be read"):
        made(True, {7: [(-1, 0.1, 1.0)], 9: lamp_eyes})


def test_a_sweep_outgrowing_its_memory_gives_the_same_numbers_however_slow_its_worker(monkeypatch):
    # the sweep goes one patch at a time where the light kept outgrows cache_mb (3 MB: partway
    # through the reflectors' first sweep), which it must find at the same patch whether or
    # not the worker kept up (read from the light as the worker happened to leave it, the
    # quick run stopped after 325 hemicubes and the slow one after 425)
    shoot_patch = ProgressiveSolver._shoot_patch

    def solve_and_stopping_point():
        """The solve, and the hemicubes drawn when its sweep gave way to single patches."""
        drawn = []
        monkeypatch.setattr(ProgressiveSolver, "_shoot_patch",
                            lambda self: drawn.append(self.hemicubes_rendered) or shoot_patch(self))
        with pytest.warns(HemiradWarning, match="outgrew solver.cache_mb"):
            solver = _solve_office_in_sweeps(cache_mb=3.0)
        return solver, drawn[0]
    quick, quick_stop = solve_and_stopping_point()

    near_fields = sweep_module.near_fields

    def slow_near_fields(*args):
        time.sleep(0.05)
        return near_fields(*args)
    monkeypatch.setattr(sweep_module, "near_fields", slow_near_fields)
    slow, slow_stop = solve_and_stopping_point()
    assert quick_stop == slow_stop > 0
    assert torch.equal(quick.state.radiosity, slow.state.radiosity)
    assert quick.hemicubes_rendered == slow.hemicubes_rendered


def _local(points):
    return np.asarray(points, dtype=np.float64)


def test_face_visibility_keeps_what_a_face_can_see_and_drops_the_rest():
    vertices = _local([
        [-0.2, -0.2, 1.0], [0.2, -0.2, 1.0], [0.0, 0.2, 1.0],     # straight up: top face only
        [1.0, -0.1, 0.2], [1.0, 0.1, 0.2], [1.0, 0.0, 0.4],       # towards +x, low: +x side only
        [0.0, 0.0, -1.0], [1.0, 0.0, -1.0], [0.0, 1.0, -1.0],     # below the horizon: no face
        [-1.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 0.0, 2.0],       # spans top, +x and -x
        [1.0, 0.0, 1.0], [1.0, 0.1, 1.0], [1.0, -0.1, 1.0],       # on the top / +x seam: those two
    ])
    triangles = np.arange(15).reshape(5, 3)
    visible = face_visibility(vertices, triangles)
    assert visible.shape == (len(FACES), 5)
    assert visible[:, 4].tolist() == [True, True, False, False, False]
    assert visible[:, 0].tolist() == [True, False, False, False, False]
    assert visible[:, 1].tolist() == [False, True, False, False, False]
    assert not visible[:, 2].any()
    assert visible[0, 3] and visible[1, 3] and visible[2, 3]


def test_face_visibility_never_drops_a_triangle_with_a_vertex_inside_a_face():
    rng = np.random.default_rng(3)
    vertices = rng.normal(size=(3000, 3))
    triangles = rng.integers(0, len(vertices), size=(1000, 3))
    visible = face_visibility(vertices, triangles)
    for f, (forward, right, up, bottom) in enumerate(FACES):
        depth = vertices @ np.asarray(forward, float)
        x, y = vertices @ np.asarray(right, float), vertices @ np.asarray(up, float)
        inside = (depth > 1e-3) & (np.abs(x) <= depth) & (y >= bottom * depth) & (y <= depth)
        has_inside_vertex = inside[triangles].any(axis=1)
        assert visible[f][has_inside_vertex].all()
        assert not visible[f].all()  # and it does cull
