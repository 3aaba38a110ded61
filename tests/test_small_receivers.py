"""Receivers that cover few hemicube pixels: their form factor against Lambert's closed form
at sub-pixel offsets, visibility behind a blocker and beside edges, and power conserved
with the correction on."""
import numpy as np
import pytest
import torch
import yaml

import hemirad
from hemirad.assembly import make_solver
from hemirad.core.errors import SceneError
from hemirad.geometry.analytic import point_to_polygon, point_to_triangles
from hemirad.geometry.mesh import Mesh
from hemirad.scene.meshing import build_mesh
from hemirad.scene.model import resolved_small_receivers
from hemirad.transport.formfactor import delta_form_factors, hemicube_directions
from hemirad.transport.renderer import HemicubeRenderer
from hemirad.transport.smallreceivers import (BOUNCE_MAX_PIXELS, MAX_PIXELS, atlas_pixels, footprint_pixels, sample_barycentrics,
                                              small_receiver_form_factors, small_receiver_rows)
from hemirad.transport.solver import ProgressiveSolver

from patches import assert_power_balances, closed_box, open_box, quad, quads_mesh, random_materials

R = 32  # a coarse hemicube: a top-face pixel is 2/R = 1/16 wide at distance 1
PIXEL = 2.0 / R
EYE_NORMAL = np.array([0.0, 0.0, 1.0])


def triangle_mesh(corners) -> Mesh:
    """One triangle, its front toward the origin (for corners seen counter-clockwise from it)."""
    return Mesh(torch.tensor(np.asarray(corners, dtype=np.float64)), torch.tensor([[0, 1, 2]]),
                torch.zeros(1), torch.zeros(1), ["receiver"])


def backdrop() -> Mesh:
    """A 10 x 10 ceiling at z = 2 facing down: most of the row, so that a small receiver is a
    small part of it."""
    return quads_mesh([quad((-5, 5, 2), (10, 0, 0), (0, -10, 0))], [2.5])


def look_up(renderer: HemicubeRenderer):
    """The hemicube at the origin looking along +z."""
    return renderer.render_at(np.zeros(3), EYE_NORMAL, np.array([1.0, 0.0, 0.0]))


def ceiling_triangle(x0, y0, leg):
    """A right triangle with legs ``leg`` along x and y at z = 1, facing down."""
    return [[x0, y0, 1.0], [x0, y0 + leg, 1.0], [x0 + leg, y0, 1.0]]


def wall_triangle(y0, z0, leg):
    """A right triangle with legs ``leg`` along y and z on the wall x = 1, facing -x (seen on
    the hemicube's +x side face)."""
    return [[1.0, y0, z0], [1.0, y0, z0 + leg], [1.0, y0 + leg, z0]]


def test_atlas_pixels_finds_every_pixel_of_its_own_direction():
    directions = hemicube_directions(R).reshape(-1, 3)
    assert torch.equal(atlas_pixels(directions, R), torch.arange(3 * R * R))


def test_sample_points_are_the_centroids_of_equal_sub_triangles():
    for level in (1, 2, 4):
        bary = sample_barycentrics(level)
        assert bary.shape == (level * level, 3) and bool((bary > 0).all())
        torch.testing.assert_close(bary.sum(1), torch.ones(level * level, dtype=torch.float64))
        # equal-area pieces: their centroids average to the triangle's centroid
        torch.testing.assert_close(bary.mean(0), torch.full((3,), 1 / 3, dtype=torch.float64))
        assert len(torch.unique(bary, dim=0)) == level * level


@pytest.mark.parametrize("leg_pixels, pixel_sum_off_by", [(0.5, 1.0), (3.0, 0.25)])
@pytest.mark.parametrize("face", ["top", "side"])
def test_a_small_receiver_gets_its_closed_form_at_every_sub_pixel_offset(face, leg_pixels, pixel_sum_off_by):
    # A triangle an eighth of a pixel's footprint, and one of 4.5 pixels, moved over a 5 x 5
    # grid of offsets within one pixel: the pixel sum gives it nothing or a whole pixel (or a
    # few pixels more or less); the correction gives Lambert's factor at every offset.
    leg = leg_pixels * PIXEL
    offsets = [PIXEL * i / 5 for i in range(5)]
    renderer = None
    corrected_error, pixel_error = [], []
    try:
        for a in offsets:
            for b in offsets:
                corners = (ceiling_triangle(0.31 + a, 0.17 + b, leg) if face == "top"
                           else wall_triangle(0.21 + a, 0.37 + b, leg))
                mesh = Mesh.concatenate([backdrop(), triangle_mesh(corners)])
                if renderer is None:
                    renderer = HemicubeRenderer(mesh, R)
                else:
                    renderer.set_geometry(mesh)
                view = look_up(renderer)
                exact = float(point_to_triangles(view.eye, view.frame[2], mesh.corners[-1:])[0])
                F = small_receiver_form_factors(view, mesh.corners, mesh.areas)
                corrected_error.append(abs(float(F[-1]) / exact - 1))
                pixel_error.append(abs(float(view.form_factors[-1]) / exact - 1))
    finally:
        if renderer is not None:
            renderer.close()
    assert max(corrected_error) < 0.02, max(corrected_error)  # measured: under 0.2%
    assert max(pixel_error) > pixel_sum_off_by, max(pixel_error)  # measured 100% / 710%, 38% / 45%


def test_the_footprint_estimate_is_the_closed_form_over_a_pixels_weight():
    # Unoccluded, F_j / w(pixel) is how many pixels j covers: the estimate from its centroid
    # alone must agree for a small triangle anywhere on the hemicube.
    weights = delta_form_factors(R).reshape(-1)
    for corners in (ceiling_triangle(0.31, 0.17, 2 * PIXEL), ceiling_triangle(-0.6, 0.45, 2 * PIXEL),
                    wall_triangle(0.21, 0.37, 2 * PIXEL), wall_triangle(-0.5, 0.1, 2 * PIXEL)):
        mesh = Mesh.concatenate([backdrop(), triangle_mesh(corners)])
        renderer = HemicubeRenderer(mesh, R)
        try:
            view = look_up(renderer)
        finally:
            renderer.close()
        exact = float(point_to_triangles(view.eye, view.frame[2], mesh.corners[-1:])[0])
        centroid = (mesh.centroids[-1] - view.eye) @ view.frame.T
        weight = float(weights[atlas_pixels(centroid[None], R)[0]])
        footprint = float(footprint_pixels(view, mesh.corners, mesh.areas)[-1])
        # the pixel's weight is at its centre, up to half a pixel off the centroid's direction
        assert footprint == pytest.approx(exact / weight, rel=0.1)


def clipped_form_factor(corners: np.ndarray, x_min: float) -> float:
    """Lambert's factor from the origin (normal +z) to the part of the triangle with x >= x_min."""
    kept = []
    for a, b in zip(corners, np.roll(corners, -1, axis=0)):
        if a[0] >= x_min:
            kept.append(a)
        if (a[0] - x_min) * (b[0] - x_min) < 0:
            kept.append(a + (x_min - a[0]) / (b[0] - a[0]) * (b - a))
    if len(kept) < 3:
        return 0.0
    return float(point_to_polygon(torch.zeros(3, dtype=torch.float64), torch.tensor(EYE_NORMAL),
                                  torch.tensor(np.array(kept))))


def test_a_receiver_half_behind_a_blocker_gets_half_its_form_factor():
    # A triangle of about 12 pixels at z = 1, a blocker at z = 0.5 whose edge hides the part
    # of it with x < c, c chosen (by bisection on Lambert's factor of the clipped triangle) so
    # that exactly half of its form factor is hidden; over 4 x 4 sub-pixel offsets of both.
    # The shadow map resolves the edge to its pixels (half a pixel column either way), so
    # one offset may read 0.3 to 0.7; on average the half is found.
    leg = 5.0 * PIXEL
    ratios = []
    renderer = None
    try:
        for i in range(4):
            for j in range(4):
                x0, y0 = 0.31 + PIXEL * i / 4, 0.17 + PIXEL * j / 4
                corners = np.array(ceiling_triangle(x0, y0, leg))
                whole = clipped_form_factor(corners, -np.inf)
                lo, hi = x0, x0 + leg
                for _ in range(50):
                    c = 0.5 * (lo + hi)
                    lo, hi = (c, hi) if clipped_form_factor(corners, c) > 0.5 * whole else (lo, c)
                blocker = quads_mesh([quad((-3, 3, 0.5), (3 + 0.5 * c, 0, 0), (0, -6, 0))], [10.0])
                mesh = Mesh.concatenate([backdrop(), blocker, triangle_mesh(corners)])
                if renderer is None:
                    renderer = HemicubeRenderer(mesh, R)
                else:
                    renderer.set_geometry(mesh)
                F = small_receiver_form_factors(look_up(renderer), mesh.corners, mesh.areas)
                ratios.append(float(F[-1]) / whole)
        # the same receiver wholly behind the blocker gets nothing
        blocker = quads_mesh([quad((-3, 3, 0.5), (3.5, 0, 0), (0, -6, 0))], [10.0])
        mesh = Mesh.concatenate([backdrop(), blocker, triangle_mesh(corners)])
        renderer.set_geometry(mesh)
        hidden = small_receiver_form_factors(look_up(renderer), mesh.corners, mesh.areas)
    finally:
        if renderer is not None:
            renderer.close()
    assert abs(np.mean(ratios) - 0.5) < 0.04, np.mean(ratios)  # measured 0.511
    assert 0.3 < min(ratios) and max(ratios) < 0.7, (min(ratios), max(ratios))  # measured 0.35, 0.54
    assert float(hidden[-1]) == 0.0


def test_unoccluded_receivers_beside_a_concave_and_a_convex_edge_are_not_hidden():
    # Seen from the origin looking up (+z), two triangles of 4.5 pixels, each with a leg on an
    # edge that lies just short of a pixel centre, so that the pixel over the edge sees the
    # face beyond it: one on the ceiling z = 1 in its corner with the wall x = 0.405 (concave:
    # that pixel sees the wall, on the eye's side of the ceiling's plane, but the ray to the
    # triangle crosses no wall), one on the underside z = 0.6 of a box at its edge with the
    # box's side face x = -0.282 (convex: that pixel sees the side face, and the ray to the
    # triangle crosses its plane, but beyond the face, behind the underside's plane). Both
    # are wholly visible: each gets its unoccluded closed form.
    leg = 3 * PIXEL
    concave = triangle_mesh([[0.405, 0.11, 1.0], [0.405 - leg, 0.11, 1.0], [0.405, 0.11 + leg, 1.0]])
    ceiling = quads_mesh([quad((-5, 5, 1), (5.405 - leg, 0, 0), (0, -10, 0))], [0.5])  # up to the triangle
    wall = quads_mesh([quad((0.405, -5, 0), (0, 10, 0), (0, 0, 1))], [0.5])  # facing -x
    leg = 0.6 * 3 * PIXEL
    convex = triangle_mesh([[-0.282, -0.07, 0.6], [-0.282 - leg, -0.07, 0.6], [-0.282, -0.07 + leg, 0.6]])
    box_bottom = quads_mesh([quad((-1.282, 1, 0.6), (1 - leg, 0, 0), (0, -2, 0))], [0.25])  # facing down
    box_side = quads_mesh([quad((-0.282, -1, 0.6), (0, 2, 0), (0, 0, 0.3))], [0.25])  # facing +x
    mesh = Mesh.concatenate([ceiling, wall, box_bottom, box_side, concave, convex])
    renderer = HemicubeRenderer(mesh, R)
    try:
        view = look_up(renderer)
    finally:
        renderer.close()
    T = mesh.num_elements
    beyond = {T - 2: set(range(ceiling.num_elements, ceiling.num_elements + wall.num_elements)),
              T - 1: set(range(T - 2 - box_side.num_elements, T - 2))}
    for j, faces in beyond.items():  # some of each triangle's sample points lie in pixels that see the other face
        local = (sample_barycentrics(3) @ mesh.corners[j] - view.eye) @ view.frame.T
        assert faces & set(view.element[atlas_pixels(local, R)].tolist())
    exact = point_to_triangles(view.eye, view.frame[2], mesh.corners[-2:])
    F = small_receiver_form_factors(view, mesh.corners, mesh.areas)
    assert bool((exact > 0).all())
    torch.testing.assert_close(F[-2:], exact, rtol=0.02, atol=0)


def closed_box_solver(mesh, rho, E, resolution=32):
    return ProgressiveSolver(mesh, rho, E, resolution, small_receivers="closed_form")


def test_a_closed_box_of_small_elements_keeps_rows_of_one_and_gets_the_closed_forms():
    # Elements of 1/20 of the box at a 32 hemicube: most cover under a pixel. Each row still
    # sums to 1 (the hemicube's total), and each corrected element (under MAX_PIXELS) reads
    # its unoccluded closed form (an empty box hides nothing), where the pixel sums are off
    # by far more.
    mesh = closed_box(element_size=0.05)
    renderer = HemicubeRenderer(mesh, R)
    try:
        views = [renderer.render(s) for s in (0, 1234, 3001, 4567)]
    finally:
        renderer.close()
    for view in views:
        F = small_receiver_form_factors(view, mesh.corners, mesh.areas)
        assert abs(float(F.sum()) - 1.0) < 1e-12
        exact = point_to_triangles(view.eye, view.frame[2], mesh.corners)
        pixel_sums = view.form_factors
        small = footprint_pixels(view, mesh.corners, mesh.areas) < MAX_PIXELS
        seen = small & (exact > 1e-6)  # leave out the grazing ones, a rounding of nothing
        assert int(seen.sum()) > 0.8 * mesh.num_elements * 5 / 6  # the five faces the shooter sees
        corrected_error = ((F - exact).abs() / exact)[seen]
        pixel_error = ((pixel_sums - exact).abs() / exact)[seen]
        assert float(corrected_error.max()) < 0.02, float(corrected_error.max())
        assert float(pixel_error.max()) > 0.5


def test_power_balances_with_small_receivers_closed_box_and_open_box():
    # received + unshot + escaped = emitted to 1e-9, computed from the radiosities; in the
    # closed box nothing escapes (to rounding, never a negative amount beyond it), in the
    # box without a top some does.
    for open_top in (False, True):
        mesh = open_box(element_size=0.1) if open_top else closed_box(element_size=0.1)
        rho, E = random_materials(mesh.num_elements, seed=2, span=0.7, low=0.2, glowing=6)
        solver = closed_box_solver(mesh, rho, E)
        try:
            state = solver.run(max_shots=80, unshot_fraction=0.0)
        finally:
            solver.close()
        emitted = (E * mesh.areas[:, None]).sum(0)
        assert_power_balances(state, mesh.areas, rho, E, emitted, rtol=1e-9)
        if open_top:
            assert bool((state.escaped > 0.05 * emitted).all())
        else:
            assert float(state.escaped.abs().max()) < 1e-12 * float(emitted.max())


def test_kept_rows_are_the_corrected_ones():
    mesh = closed_box(element_size=0.1)
    T = mesh.num_elements
    rho = torch.full((T, 3), 0.5, dtype=torch.float64)
    E = torch.zeros(T, 3, dtype=torch.float64)
    E[0] = 1.0
    solver = closed_box_solver(mesh, rho, E)
    reflector = T // 2  # emits nothing
    try:
        view = solver.render_and_keep(0)  # as a patch's shooter test renders it
        kept = solver.form_factors_of(0)
        renders = solver.hemicubes_rendered
        reflector_view = solver.render_and_keep(reflector)
        reflector_kept = solver.form_factors_of(reflector)
    finally:
        solver.close()
    assert renders == 1  # the row came from the cache
    assert torch.equal(kept, small_receiver_form_factors(view, mesh.corners, mesh.areas))
    assert not torch.equal(kept, view.form_factors)  # the view keeps its pixel sums
    # a shooter that only reflects corrects only its receivers under a pixel: the others'
    # luck averages out over the many reflecting shooters, where the few lamps' does not
    assert torch.equal(reflector_kept, small_receiver_form_factors(reflector_view, mesh.corners, mesh.areas,
                                                                   BOUNCE_MAX_PIXELS))
    corrected = small_receiver_form_factors(reflector_view, mesh.corners, mesh.areas)
    assert not torch.equal(reflector_kept, corrected)  # it has receivers of a few pixels to correct
    # with lamps, a reflecting shooter hands out its pixel sums, a lamp its corrected row
    lamps = ProgressiveSolver(mesh, rho, E, 32, small_receivers="lamps")
    try:
        assert torch.equal(lamps.form_factors_of(0), kept)
        assert torch.equal(lamps.form_factors_of(reflector), reflector_view.form_factors)
    finally:
        lamps.close()


def test_the_option_is_read_checked_and_the_paper_keeps_pixels(tmp_path):
    scene = hemirad.load_scene("floating_coarse")
    assert scene.solver.small_receivers == "auto"
    assert resolved_small_receivers("auto", refined=False) == "lamps"
    assert resolved_small_receivers("auto", refined=True) == "closed_form"
    assert resolved_small_receivers("pixels", refined=True) == "pixels"
    scene.solver.paper()
    assert scene.solver.small_receivers == "pixels"
    doc = {"element_size": 0.5,
           "materials": {"white": {"reflectance": 0.7}, "lamp": {"reflectance": 0.0, "emission": 10.0}},
           "objects": [{"type": "room", "min": [0, 0, 0], "max": [4, 2.5, 4], "material": "white"},
                       {"type": "quad", "material": "lamp",
                        "corners": [[1, 2.49, 1], [2, 2.49, 1], [2, 2.49, 2], [1, 2.49, 2]]}],
           "camera": {"position": [2, 1.5, 0.2], "look_at": [2, 1, 4]}}
    for value in ("auto", "pixels", "lamps", "closed_form", "exact"):
        path = tmp_path / f"{value}.yaml"
        path.write_text(yaml.safe_dump({**doc, "solver": {"small_receivers": value}}, sort_keys=False))
        if value != "exact":
            assert hemirad.load_scene(path).solver.small_receivers == value
            continue
        with pytest.raises(SceneError) as error:
            hemirad.load_scene(path)
        message = str(error.value)
        assert "solver.small_receivers" in message and "auto, pixels, lamps, closed_form" in message and path.name in message


def test_the_command_line_option_sets_it_and_refuses_other_values(capsys):
    from hemirad.cli import build_parser
    parser = build_parser()
    assert parser.parse_args(["floating", "--small-receivers", "pixels"]).small_receivers == "pixels"
    assert parser.parse_args(["floating"]).small_receivers is None  # the scene's own, or the default
    with pytest.raises(SystemExit) as exit_code:
        parser.parse_args(["floating", "--small-receivers", "exact"])
    assert exit_code.value.code == 2 and "closed_form" in capsys.readouterr().err


@pytest.mark.parametrize("resolutions", [(R,) * 5, (R, R // 2, R, R // 2, R // 2)])
def test_rows_made_together_are_the_rows_made_alone(resolutions):
    # A sweep makes its group's rows in one pass; each must be what its view gives alone (a
    # row dropped from the cache and made again gets the same), to the last bits that the
    # vectorised atan2 rounds by its place in the batch, also where its lamps and reflectors
    # draw at two resolutions. Cornell box: the blocks hide receivers from some eyes, so the
    # shadow-map test decides.
    scene = hemirad.load_scene("cornell_box")
    scene.meshing.contacts = False  # the elements as chosen below
    mesh = build_mesh(scene)
    renderers = {r: HemicubeRenderer(mesh, r) for r in set(resolutions)}
    try:
        views = [renderers[r].render(s) for s, r in zip((0, 17, 400, 1311, 2600), resolutions)]
    finally:
        for renderer in renderers.values():
            renderer.close()
    limits = [MAX_PIXELS, BOUNCE_MAX_PIXELS, MAX_PIXELS, 2.5, BOUNCE_MAX_PIXELS]
    together = small_receiver_rows(views, mesh.corners, mesh.areas, limits)
    alone = [small_receiver_form_factors(v, mesh.corners, mesh.areas, limit) for v, limit in zip(views, limits)]
    for a, b in zip(together, alone):
        torch.testing.assert_close(a, b, rtol=1e-13, atol=1e-16)
    assert sum(not torch.equal(a, v.form_factors) for a, v in zip(together, views)) >= 3  # corrected rows


def test_samples_made_in_several_passes_give_the_one_pass_rows_bit_for_bit(monkeypatch):
    # a sweep group's samples are made SAMPLE_CHUNK at a time (to bound the temporaries), in
    # runs of whole receivers: the rows are the same to the last bit as in one pass
    from hemirad.transport import smallreceivers

    mesh = build_mesh(hemirad.load_scene("cornell_box"))
    renderer = HemicubeRenderer(mesh, R)
    try:
        views = [renderer.render(s) for s in (0, 17, 400)]
    finally:
        renderer.close()
    limits = [MAX_PIXELS, 2.5, MAX_PIXELS]
    one_pass = small_receiver_rows(views, mesh.corners, mesh.areas, limits)
    passes = []
    made = smallreceivers._visible_form_factors
    monkeypatch.setattr(smallreceivers, "_visible_form_factors", lambda *a: passes.append(len(a[2])) or made(*a))
    monkeypatch.setattr(smallreceivers, "SAMPLE_CHUNK", 37)  # not a whole number of any receiver's samples
    several = small_receiver_rows(views, mesh.corners, mesh.areas, limits)
    assert len(passes) > 10 and sum(passes) > len(passes)
    for a, b in zip(one_pass, several):
        assert torch.equal(a, b)


def test_a_sweeps_kept_rows_are_its_nodes_rows_made_alone():
    scene = hemirad.load_scene("cornell_box")
    scene.solver.small_receivers, scene.solver.resolution = "closed_form", 32
    solver = make_solver(scene)
    try:
        solver.shoot()  # one sweep: every patch that holds light (the lamp's) shoots
        solver.shoot()  # and the light it gave: most patches, a group at a time
        nodes = [n for cut in solver.patches.cuts.values() for n in cut]
        checked = 0
        for node in nodes[::7]:
            kept = solver.rows.get(node, solver.mesh.num_elements)
            if kept is None:
                continue
            torch.testing.assert_close(kept, solver.node_row(node, solver.render(node)), rtol=1e-13, atol=1e-16)
            checked += 1
    finally:
        solver.close()
    assert checked >= 10


def test_the_shadow_map_test_reads_the_point_each_pixel_sees_in_a_turned_frame():
    # The samples' test works per sample in its own view's frame; against the pixels' exact hit
    # points (``HemicubeView.hits``) in frames turned off every axis, where mixing up the
    # frame's rows and columns shows (an axis-aligned frame would hide it).
    from hemirad.core.fastops import row_sums
    from hemirad.transport.smallreceivers import _TOLERANCE, _sample_weights
    mesh = build_mesh(hemirad.load_scene("cornell_box"))
    renderer = HemicubeRenderer(mesh, R)
    try:
        views = [renderer.render(s) for s in (17, 1311)]
    finally:
        renderer.close()
    points, owner = mesh.centroids, torch.arange(mesh.num_elements)
    for view in views:
        assert not torch.allclose(view.frame.abs(), torch.eye(3, dtype=torch.float64))  # turned
        weight, visible = _sample_weights([view], torch.zeros_like(owner), points, owner)
        hidden = (weight > 0) & (visible == 0)
        ray = points - view.eye
        pixels = atlas_pixels(ray @ view.frame.T, view.resolution)
        k = view.element[pixels]
        other = (k >= 0) & (k != owner) & (weight > 0)
        kk = k.clamp(min=0)
        toward = row_sums(view.normals[kk] * ray)
        d_k = view.distance[kk]
        crosses = (d_k * toward > 0) & (d_k.abs() < (1.0 - _TOLERANCE) * toward.abs())
        d_j = view.distance
        seen_at = view.hits(pixels) - view.eye[:, None]
        in_front = (view.normals.T * seen_at).sum(0) - d_j > _TOLERANCE * d_j.abs()
        expected = other & crosses & in_front
        assert int(expected.sum()) >= 20  # the blocks hide elements
        assert int((hidden != expected).sum()) <= 2  # rounding at the tolerance's edge
