"""Gradients of the form factors with respect to the shooter's position (docs/DESIGN.md §2)."""
import math

import numpy as np
import pytest
import torch

from hemirad.adaptive.gradient import ReceiverPatches, form_factor_jacobian, interior_form_factors
from hemirad.adaptive.shadow_edges import occlusion_pairs
from hemirad.geometry.analytic import point_to_polygon
from hemirad.geometry.mesh import Mesh
from hemirad.transport.renderer import HemicubeRenderer

Z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)


def rectangle(x0, x1, y0, y1, z, angle=0.0, centre=(0.0, 0.0)):
    """(4, 3) a horizontal rectangle at height z, rotated by ``angle`` degrees about the
    vertical through ``centre``, wound to face down (towards a source below it)."""
    corners = np.array([[x0, y0], [x0, y1], [x1, y1], [x1, y0]], dtype=np.float64) - centre
    a = math.radians(angle)
    corners = corners @ np.array([[math.cos(a), math.sin(a)], [-math.sin(a), math.cos(a)]]) + centre
    return np.column_stack([corners, np.full(4, z)])


def shot(point, polygons, resolution=256):
    """Render from a tiny upward-facing source at ``point``; the other polygons are meshed
    as two triangles each. Returns the render's view and the element ranges."""
    h = 1e-3
    p = np.asarray(point, dtype=np.float64)
    vertices = [np.array([p + [h, 0, 0], p + [-h / 2, h, 0], p + [-h / 2, -h, 0]])]
    triangles, ranges = [[0, 1, 2]], []
    for poly in polygons:
        base = sum(len(v) for v in vertices)
        vertices.append(poly)
        ranges.append(slice(len(triangles), len(triangles) + 2))
        triangles += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    mesh = Mesh(np.concatenate(vertices), triangles, range(len(triangles)), [0] * len(triangles))
    ff = HemicubeRenderer(mesh, resolution)
    try:
        view = ff.render(0)
    finally:
        ff.close()
    return view, ranges


def lambert_gradient(eye, receiver, blockers=()):
    """dF/dc of the visible part: the receiver minus the blockers' shadows, which lie inside it
    (a shadow subtends the same projected solid angle as its blocker)."""
    c = torch.as_tensor(eye, dtype=torch.float64).detach().clone().requires_grad_(True)
    F = point_to_polygon(c, Z, torch.tensor(receiver))
    for b in blockers:
        F = F - point_to_polygon(c, Z, torch.tensor(b))
    (grad,) = torch.autograd.grad(F, c)
    return float(F.detach()), grad


def relative_error(J, reference):
    return float((J - reference).norm() / reference.norm())


RECEIVER = rectangle(-1.0, 1.2, -1.0, 1.1, 1.0)
BLOCKER = rectangle(-0.2, 0.3, -0.25, 0.2, 0.6)
rng = np.random.default_rng(7)
EYES = [np.array([*rng.uniform(-0.2, 0.2, 2), 0.0]) for _ in range(4)]


def test_interior_gradient_equals_finite_differences_of_the_same_function():
    view, ranges = shot(EYES[0], [RECEIVER, BLOCKER], resolution=64)
    T = len(view.normals)
    _, J = form_factor_jacobian(view, interior=True, shadow_edges=False)
    patches = ReceiverPatches.from_view(view)
    step = 1e-5
    for axis in range(3):
        dc = torch.zeros(3, dtype=torch.float64)
        dc[axis] = step
        fd = (interior_form_factors(view.eye + dc, patches, T)
              - interior_form_factors(view.eye - dc, patches, T)) / (2 * step)
        torch.testing.assert_close(J[:, axis], fd, rtol=1e-4, atol=1e-9)


def test_value_is_the_hemicube_form_factor():
    view, _ = shot(EYES[1], [RECEIVER, BLOCKER], resolution=64)
    F, _ = form_factor_jacobian(view)
    hemicube = torch.bincount(view.element[view.front], view.weight[view.front], minlength=len(view.normals))
    torch.testing.assert_close(F, hemicube, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("eye", EYES)
def test_unoccluded_gradient_matches_lambert(eye):
    view, (receiver,) = shot(eye, [RECEIVER])
    _, J = form_factor_jacobian(view)
    _, reference = lambert_gradient(view.eye, RECEIVER)
    assert relative_error(J[receiver].sum(0), reference) < 0.02


BLOCKED_CASES = {
    "parallel blocker": (RECEIVER, BLOCKER),
    "blocker rotated 30 degrees": (RECEIVER, rectangle(-0.2, 0.3, -0.25, 0.2, 0.6, angle=30, centre=(0.05, -0.02))),
    # The receiver runs from the top face across the seam onto the +x side face (x/z > 1),
    # and the blocker's shadow edge crosses the seam with it.
    "across the top/side seam": (rectangle(0.2, 0.9, -0.35, 0.35, 0.4), rectangle(0.14, 0.4, -0.15, 0.15, 0.25)),
}


@pytest.mark.parametrize("case", list(BLOCKED_CASES))
def test_shadow_edge_term_makes_the_gradient_see_the_blocker(case):
    receiver_polygon, blocker_polygon = BLOCKED_CASES[case]
    for eye in EYES:
        eye = eye * (0.25 if "seam" in case else 1.0)
        view, (receiver, _) = shot(eye, [receiver_polygon, blocker_polygon])
        F_value, reference = lambert_gradient(view.eye, receiver_polygon, [blocker_polygon])
        F, J = form_factor_jacobian(view)
        _, J_interior = form_factor_jacobian(view, shadow_edges=False)
        assert float(F[receiver].sum()) == pytest.approx(F_value, rel=0.01)
        assert relative_error(J[receiver].sum(0), reference) < 0.10
        assert relative_error(J_interior[receiver].sum(0), reference) > 0.50


def test_gradient_of_some_elements_is_their_rows_of_the_full_gradient():
    # The solver's later passes ask only for the new elements' gradients: the restricted
    # computation must give exactly those rows (and the full F).
    view, ranges = shot(EYES[1], [RECEIVER, BLOCKER], resolution=64)
    F_full, J_full = form_factor_jacobian(view)
    wanted = torch.zeros(len(view.normals), dtype=torch.bool)
    wanted[ranges[0]] = True  # the receiver, with the blocker's shadow edge on it
    F, J = form_factor_jacobian(view, wanted=wanted)
    assert torch.equal(F, F_full)
    assert J_full[wanted].abs().sum() > 0 and J_full[~wanted].abs().sum() > 0
    torch.testing.assert_close(J[wanted], J_full[wanted], rtol=1e-12, atol=1e-15)
    assert not J[~wanted].any()


def test_plane_ids_change_no_gradient_and_mark_planar_surfaces():
    import hemirad
    from hemirad.scene.meshing import build_mesh
    from hemirad.geometry.split import split_triangles

    scene = hemirad.load_scene("floating")
    mesh = build_mesh(scene)
    ids = mesh.plane_ids
    # every bundled surface is planar: one id per surface
    assert torch.equal(ids, mesh.surface)
    selected = torch.zeros(mesh.num_elements, dtype=torch.bool)
    selected[::5] = True
    split, parent = split_triangles(mesh, selected, "pattern2")
    assert torch.equal(split.plane_ids, ids[parent])  # inherited
    fresh = Mesh(split.vertices, split.triangles, split.surface, split.material)
    assert torch.equal(fresh.plane_ids, split.plane_ids)  # and what computing them afresh gives

    ff = HemicubeRenderer(split, 64)
    try:
        lamp = int(torch.nonzero(scene.emission_table()[split.material].sum(1) > 0)[0])
        view = ff.render(lamp)
    finally:
        ff.close()
    F, J = form_factor_jacobian(view)
    F_ids, J_ids = form_factor_jacobian(view, plane_ids=split.plane_ids)
    assert torch.equal(F, F_ids) and torch.equal(J, J_ids)
    assert len(occlusion_pairs(view).far_element) > 0  # the board's shadow edge


def test_a_curved_surface_gives_each_element_its_own_plane_id():
    # a tent: two faces of one surface meeting at a ridge
    vertices = [[0, 0, 0], [1, 0, 0], [1, 1, 1], [0, 1, 1], [0, 2, 0], [1, 2, 0]]
    triangles = [[0, 1, 2], [0, 2, 3], [3, 2, 5], [3, 5, 4]]
    mesh = Mesh(vertices, triangles, [0, 0, 0, 0], [0, 0, 0, 0])
    assert len(set(mesh.plane_ids.tolist())) == 4


def test_pairs_touching_some_pixels_are_those_a_full_scan_finds():
    from hemirad.adaptive.shadow_edges import neighbour_pairs, pairs_touching

    R = 16
    a, b, _ = neighbour_pairs(R)
    pixels = torch.tensor([0, 5, R - 1, R, R * R - 1, R * R, R * R + R // 2 * R - 1, 3 * R * R - 1])
    marked = torch.zeros(3 * R * R, dtype=torch.bool)
    marked[pixels] = True
    expected = (marked[a] | marked[b]).nonzero().reshape(-1)
    assert torch.equal(pairs_touching(pixels, R), expected)


def test_boundary_pairs_found_by_image_shifts_are_those_a_scan_of_every_pair_finds():
    from hemirad.adaptive.shadow_edges import boundary_pairs, neighbour_pairs

    R = 16
    a, b, _ = neighbour_pairs(R)
    generator = torch.Generator().manual_seed(3)
    # blocks of elements with holes, so that pairs cross faces' seams, element edges and empty pixels
    element = torch.randint(-1, 4, (3 * R * R // 4,), generator=generator).repeat_interleave(4)
    expected = ((element[a] != element[b]) & (element[a] >= 0) & (element[b] >= 0)).nonzero().reshape(-1)
    assert len(expected) > 100
    assert torch.equal(boundary_pairs(element, R), expected)


@pytest.mark.parametrize("terms", [dict(), dict(shadow_edges=False), dict(interior=False)])
def test_one_backward_pass_gives_the_forward_mode_jacobian(terms):
    # The default (reverse) path gives every pixel's term its own copy of the eye; forward
    # mode (jacfwd, the paper's) differentiates the summed function: the same derivative.
    from hemirad.adaptive.gradient import form_factor_gradient

    for eye in EYES[:2]:
        view, ranges = shot(eye, [RECEIVER, BLOCKER], resolution=64)
        wanted = torch.zeros(len(view.normals), dtype=torch.bool)
        wanted[ranges[0]] = True
        for restricted in (None, wanted):
            J = form_factor_gradient(view, wanted=restricted, **terms)
            J_forward = form_factor_gradient(view, wanted=restricted, mode="forward", **terms)
            assert J_forward.abs().max() > 0
            torch.testing.assert_close(J, J_forward, rtol=1e-12, atol=1e-12 * float(J_forward.abs().max()))


def test_an_unknown_differentiation_mode_is_refused():
    from hemirad.adaptive.gradient import form_factor_gradient

    view, _ = shot(EYES[0], [RECEIVER], resolution=16)
    with pytest.raises(ValueError, match="mode"):
        form_factor_gradient(view, mode="sideways")


def test_the_gradient_is_the_same_under_inference_mode():
    # A caller may run a solve under torch.inference_mode, where no backward pass can run.
    from hemirad.adaptive.gradient import form_factor_gradient

    view, _ = shot(EYES[0], [RECEIVER, BLOCKER], resolution=32)
    J = form_factor_gradient(view)
    with torch.inference_mode():  # everything made under it, as a solve under it would
        J_inference = form_factor_gradient(shot(EYES[0], [RECEIVER, BLOCKER], resolution=32)[0])
    torch.testing.assert_close(J_inference, J, rtol=1e-12, atol=1e-12 * float(J.abs().max()))
