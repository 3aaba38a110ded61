"""Hemicube form factors against their definition and against closed forms."""
import numpy as np
import pytest
import torch

from hemirad.geometry.analytic import (parallel_rectangles, perpendicular_rectangles, point_to_polygon,
                                      point_to_triangles, small_triangle_factors, triangle_to_triangles)
from hemirad.geometry.mesh import Mesh
from hemirad.transport.formfactor import delta_form_factors, raw_delta_form_factors
from hemirad.transport.renderer import HemicubeRenderer

from patches import closed_box, open_box, quad, quads_mesh

X, Y, Z = np.eye(3)


def test_analytic_formulas_reproduce_the_catalog():
    # Independent numbers from Howell's catalog guard the references the hemicube is held to.
    for (a, b, c), F in [((1, 1, 1), 0.19982), ((2, 1, 1), 0.28588), ((1, 1, 2), 0.06859), ((2, 2, 1), 0.41525)]:
        assert float(parallel_rectangles(a, b, c)) == pytest.approx(F, abs=1e-5)
    for (h, w, l), F in [((1, 1, 1), 0.20004), ((1, 2, 1), 0.11643), ((2, 1, 1), 0.23285), ((1, 1, 2), 0.24064)]:
        assert float(perpendicular_rectangles(h, w, l)) == pytest.approx(F, abs=1e-5)
    for (a, b, c), F in [((1, 1, 1), 0.13853), ((2, 1, 1), 0.16738), ((1, 1, 2), 0.05986), ((3, 2, 1), 0.21758)]:
        corner = torch.tensor([[0, 0, c], [a, 0, c], [a, b, c], [0, b, c]], dtype=torch.float64)
        F_lambert = point_to_polygon(torch.zeros(3, dtype=torch.float64), torch.tensor([0, 0, 1.0], dtype=torch.float64), corner)
        assert float(F_lambert) == pytest.approx(F, abs=1e-5)


@pytest.mark.parametrize("resolution", [8, 32, 128, 256])
def test_delta_form_factors_sum_to_one(resolution):
    assert float(delta_form_factors(resolution).sum()) == pytest.approx(1.0, abs=1e-12)
    assert (delta_form_factors(resolution) > 0).all()


def test_raw_delta_form_factors_converge_to_one_like_the_midpoint_rule():
    errors = [abs(float(raw_delta_form_factors(R).sum()) - 1) for R in (8, 32, 128)]
    assert errors[0] < 1e-2
    # O(1/R^2): each 4x in resolution cuts the error about 16x.
    assert errors[1] < errors[0] / 12 and errors[2] < errors[1] / 12


def test_closed_box_form_factors_sum_to_one():
    mesh = closed_box(element_size=0.25)
    ff = HemicubeRenderer(mesh, 64)
    try:
        for shooter in (0, 17, mesh.num_elements - 1):
            F = ff.from_element(shooter)
            assert float(F.sum()) == pytest.approx(1.0, rel=1e-2)
            assert float(F[shooter]) == 0.0
    finally:
        ff.close()



def test_what_a_hemicube_sends_into_back_faces_is_what_fronts_and_the_sky_do_not_receive():
    # a box seen from inside (fronts), the same box turned inside out (backs), a half-turned
    # one, and the turned box open at the top (some pixels see nothing): every pixel's power
    # goes to a front, into a back or out, none twice
    box, lidless = closed_box(element_size=0.25), open_box(element_size=0.25)

    def turned(mesh, which):
        triangles = torch.where(which[:, None], mesh.triangles[:, [0, 2, 1]], mesh.triangles)
        return Mesh(mesh.vertices, triangles, mesh.surface, mesh.material, mesh.surface_names)

    everything = torch.ones(box.num_elements, dtype=torch.bool)
    for mesh, back in ((box, 0.0), (turned(box, everything), 1.0),
                       (turned(box, torch.arange(box.num_elements) % 2 == 0), None),
                       (turned(lidless, torch.ones(lidless.num_elements, dtype=torch.bool)), None)):
        ff = HemicubeRenderer(mesh, 64)
        try:
            view = ff.render_at(np.array([0.4, 0.45, 0.0]), Z, X)  # on the floor, inside
            sky = float(view.weight[view.element < 0].sum())
            assert float(view.back_share) + float(view.form_factors.sum()) + sky == pytest.approx(1.0, rel=1e-12)
            masked = float(view.weight[(view.element >= 0) & ~view.front].sum())
            assert float(view.back_share) == pytest.approx(masked, rel=1e-12, abs=1e-15)
            if back is not None:
                assert float(view.back_share) == pytest.approx(back, abs=1e-12)
            else:
                assert 0.1 < float(view.back_share) < 0.9
        finally:
            ff.close()


def area_to_area(mesh, source_count, resolution):
    """F from the first ``source_count`` elements (one patch) to the rest, area-weighted."""
    ff = HemicubeRenderer(mesh, resolution)
    try:
        areas = mesh.areas
        rows = torch.stack([ff.from_element(i)[source_count:].sum() for i in range(source_count)])
        return float((areas[:source_count] * rows).sum() / areas[:source_count].sum())
    finally:
        ff.close()


def two_patches(source, target, source_element):
    """A mesh of a finely meshed source patch followed by a one-element-per-half target."""
    mesh = quads_mesh([source, target], [source_element, 10.0])
    return mesh, int((mesh.surface == 0).sum())


HOWELL_CASES = {
    # Directly opposed squares / 2x1 rectangles at distance 1; the target faces the source.
    "opposed 1x1 at 1": (quad(0 * X, X, Y), quad(Z, Y, X), parallel_rectangles(1, 1, 1)),
    "opposed 2x1 at 1": (quad(0 * X, 2 * X, Y), quad(Z, Y, 2 * X), parallel_rectangles(2, 1, 1)),
    # Perpendicular, sharing the unit edge along x: from the w-wide one (in z = 0) to the h-high one (in y = 0).
    "perpendicular h=1 w=1": (quad(0 * X, X, Y), quad(0 * X, Z, X), perpendicular_rectangles(1, 1, 1)),
    "perpendicular h=1 w=2": (quad(0 * X, X, 2 * Y), quad(0 * X, Z, X), perpendicular_rectangles(1, 2, 1)),
}


@pytest.mark.parametrize("case", list(HOWELL_CASES))
def test_hemicube_matches_howell_at_resolution_256(case):
    source, target, reference = HOWELL_CASES[case]
    mesh, n = two_patches(source, target, source_element=1 / 8)
    assert (mesh.normals[:n] @ torch.tensor(Z)).min() > 0.999  # the source faces +z
    F = area_to_area(mesh, n, 256)
    assert F == pytest.approx(float(reference), rel=0.02)


def test_hemicube_converges_to_lambert_as_resolution_grows():
    """Point-to-rectangle factors at jittered points: the error shrinks about like 1/R."""
    rectangle = np.array([[-0.5, -0.3, 1], [0.7, -0.3, 1], [0.7, 0.6, 1], [-0.5, 0.6, 1.0]])
    rng = np.random.default_rng(1)
    points = [np.array([*rng.uniform(-0.3, 0.3, 2), 0.0]) for _ in range(8)]
    mean_error = {}
    for R in (16, 64, 256):
        errors = []
        for p in points:
            h = 1e-3  # a tiny source triangle stands for the differential area at p
            source = np.array([p + [h, 0, 0], p + [-h / 2, h, 0], p + [-h / 2, -h, 0]])
            vertices = np.concatenate([source, rectangle[::-1]])  # the rectangle faces down
            mesh = Mesh(vertices, [[0, 1, 2], [3, 4, 5], [3, 5, 6]], [0, 1, 1], [0, 0, 0])
            ff = HemicubeRenderer(mesh, R)
            F = float(ff.from_element(0)[1:].sum())
            ff.close()
            reference = float(point_to_polygon(mesh.centroids[0], torch.tensor(Z), torch.tensor(rectangle)))
            errors.append(abs(F / reference - 1))
        mean_error[R] = np.mean(errors)
    assert mean_error[256] < 0.005
    assert mean_error[16] > 2 * mean_error[64] > 4 * mean_error[256]


def test_reciprocity_between_two_patches():
    # Two unequal, tilted patches facing each other: A_i F_ij = A_j F_ji.
    a = quad([0, 0, 0], [1.0, 0, 0], [0, 0.8, 0])
    b = quad([0.2, -0.1, 0.9], [0, 1.2, 0.1], [0.7, 0, 0.3])
    mesh = quads_mesh([a, b], [0.1, 0.1])
    n_a = int((mesh.surface == 0).sum())
    area_a, area_b = float(mesh.areas[:n_a].sum()), float(mesh.areas[n_a:].sum())
    ff = HemicubeRenderer(mesh, 128)
    try:
        F = torch.stack([ff.from_element(i) for i in range(mesh.num_elements)])
    finally:
        ff.close()
    areas = mesh.areas
    F_ab = float((areas[:n_a, None] * F[:n_a, n_a:]).sum()) / area_a
    F_ba = float((areas[n_a:, None] * F[n_a:, :n_a]).sum()) / area_b
    assert F_ab > 0.1 and F_ba > 0.1
    assert area_a * F_ab == pytest.approx(area_b * F_ba, rel=0.02)


def _rectangle_factor(source, receiver, points):
    """F from the quad ``source`` (4, 3) to the quad ``receiver``, each split into two
    triangles wound like the quad, by ``triangle_to_triangles``."""
    halves = [[0, 1, 2], [0, 2, 3]]
    s = torch.stack([source[h] for h in halves])
    r = torch.stack([receiver[h] for h in halves])
    pairs = triangle_to_triangles(s.repeat_interleave(2, 0), r.repeat(2, 1, 1), points)
    return float(pairs.sum() / 2)  # the two source halves have equal areas


@pytest.mark.parametrize("points,touching,apart", [(4, 3e-3, 5e-5), (8, 3e-4, 3e-9)])
def test_triangle_to_triangles_reproduces_the_rectangles_closed_forms(points, touching, apart):
    # Touching (two rectangles sharing an edge at a right angle) and apart (facing, parallel):
    # the contour integral against Howell's catalog, to the accuracy its Gauss points allow.
    for h, w, l in [(1, 1, 1), (0.25, 1, 1), (1, 2, 0.5)]:
        source = quad([0, 0, 0], [l, 0, 0], [0, w, 0])  # faces +z
        wall = quad([0, 0, 0], [0, 0, h], [l, 0, 0])  # faces +y, along the source's edge y = 0
        exact = float(perpendicular_rectangles(h, w, l))
        assert _rectangle_factor(source, wall, points) == pytest.approx(exact, rel=touching)
    for a, b, c in [(1, 1, 1), (2, 1, 1), (1, 1, 2)]:
        source = quad([0, 0, 0], [a, 0, 0], [0, b, 0])
        facing = quad([0, 0, c], [0, b, 0], [a, 0, 0])  # faces -z
        exact = float(parallel_rectangles(a, b, c))
        assert _rectangle_factor(source, facing, points) == pytest.approx(exact, rel=apart)


def test_one_rule_over_each_whole_edge_serves_pairs_apart():
    # The near field's pairs at least PIECES_GAP source sides apart take APART_POINTS along
    # each whole source edge (no kink for the pieces to resolve): against the closed form of
    # facing squares and against 8 points a piece on random pairs that far apart, including
    # pairs that straddle each other's planes (a receiver near a shooter's horizon).
    from hemirad.transport.nearfield import APART_POINTS, PIECES_GAP, _sides_centroids_radii

    for c in (1.5, 2.0, 4.0):
        source = quad([0, 0, 0], [1, 0, 0], [0, 1, 0])
        facing = quad([0, 0, c], [0, 1, 0], [1, 0, 0])
        halves = [[0, 1, 2], [0, 2, 3]]
        s = torch.stack([source[h] for h in halves]).repeat_interleave(2, 0)
        r = torch.stack([facing[h] for h in halves]).repeat(2, 1, 1)
        F = float(triangle_to_triangles(s, r, APART_POINTS, pieces=False).sum() / 2)
        assert F == pytest.approx(float(parallel_rectangles(1, 1, c)), rel=1e-5)
    g = torch.Generator().manual_seed(11)
    sources = torch.rand(400, 3, 3, generator=g, dtype=torch.float64)
    receivers = torch.rand(400, 3, 3, generator=g, dtype=torch.float64) + 3.0 * torch.nn.functional.normalize(
        torch.randn(400, 1, 3, generator=g, dtype=torch.float64), dim=2)
    side, centre, radius = _sides_centroids_radii(sources)
    _, receiver_centre, receiver_radius = _sides_centroids_radii(receivers)
    apart = (receiver_centre - centre).norm(dim=1) - radius - receiver_radius >= PIECES_GAP * side
    sources, receivers = sources[apart], receivers[apart]
    pieces = triangle_to_triangles(sources, receivers, 8)
    assert int((pieces > 1e-4).sum()) > 50  # enough pairs that see each other
    torch.testing.assert_close(triangle_to_triangles(sources, receivers, APART_POINTS, pieces=False), pieces,
                               rtol=2e-3, atol=1e-9)


def test_triangle_to_triangles_is_right_for_a_small_receiver_along_part_of_a_shared_edge():
    # A floor tile (a x w) in the corner where a wall strip (h x l, l >> a) meets the floor,
    # sharing the first a of the wall's foot: the shape refinement makes along a wall. With
    # w = h, swapping wall and floor maps the tile to the wall's first a and the wall's rest
    # to the floor's, so factor algebra over common-edge pairs (F_x: the closed form of
    # perpendicular rectangles sharing an edge of length x) gives it exactly:
    # A_tile F(tile -> wall) = G(a) + (G(l) - G(a) - G(l - a)) / 2, G(x) = w x F_x.
    h = w = 0.1
    l, a = 1.0, 0.1

    def common(length):
        return w * length * float(perpendicular_rectangles(h, w, length))
    exact = (common(a) + 0.5 * (common(l) - common(a) - common(l - a))) / (h * l)  # reciprocity: F(wall -> tile)
    wall = quad([0, 0, 0], [0, 0, h], [l, 0, 0])  # faces +y, its foot along x from 0 to l
    tile = quad([0, 0, 0], [a, 0, 0], [0, w, 0])  # faces +z, in the corner
    # (one Gauss rule over each whole source edge read it 53% high at 4 points)
    for points, tolerance in ((4, 0.05), (8, 3e-3)):
        assert _rectangle_factor(wall, tile, points) == pytest.approx(exact, rel=tolerance)


def test_triangle_to_triangles_clips_what_faces_away_and_matches_sampling():
    # Pairs of random triangles that face each other's centroids but may straddle each other's
    # planes, and the same receivers seen from behind, against Lambert's point factor averaged
    # over 48^2 points of the source, a point behind the receiver's plane lighting nothing.
    # Shifted along its own plane, a source lights nothing of its copy.
    from hemirad.transport.smallreceivers import sample_barycentrics

    g = torch.Generator().manual_seed(3)
    sources = torch.rand(40, 3, 3, generator=g, dtype=torch.float64)
    offset = torch.tensor([0.5, 0.3, 0.8], dtype=torch.float64)
    receivers = torch.rand(40, 3, 3, generator=g, dtype=torch.float64) + offset

    def unit_normals(triangles):
        return torch.nn.functional.normalize(
            torch.linalg.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]), dim=1)

    def facing(triangles, other):  # wound so that each faces the other's centroid
        away = ((other.mean(1) - triangles.mean(1)) * unit_normals(triangles)).sum(1) < 0
        return torch.where(away[:, None, None], triangles[:, [0, 2, 1]], triangles)

    def sampled(sources, receivers):
        points = torch.einsum("pc,mcd->mpd", sample_barycentrics(48), sources)  # (m, P, 3)
        normals, r_normals = unit_normals(sources), unit_normals(receivers)
        out = []
        for i in range(len(sources)):
            lambert = point_to_triangles(points[i][:, None, :], normals[i],
                                         receivers[i][None].expand(len(points[i]), 3, 3))
            out.append(float((lambert * (((points[i] - receivers[i, 0]) @ r_normals[i]) > 0)).mean()))
        return torch.tensor(out, dtype=torch.float64)

    sources, receivers = facing(sources, receivers), facing(receivers, sources)
    for r in (receivers, receivers[:, [0, 2, 1]]):
        F, expected = triangle_to_triangles(sources, r, 12), sampled(sources, r)
        assert bool((F >= 0).all())
        torch.testing.assert_close(F, expected, rtol=0.02, atol=2e-4)
    assert int((sampled(sources, receivers) > 1e-3).sum()) > 30
    beside = sources + (sources[:, 1] - sources[:, 0])[:, None]
    assert float(triangle_to_triangles(sources, beside).abs().max()) == 0.0


def test_small_receivers_factors_by_reciprocity_match_their_definition():
    # Receivers of about 1 cm radius at the foot of a 1 m wall triangle (on the floor) and
    # facing it (parallel), 2 to 200 of their radii away: A_s F(s -> r) is the integral over
    # the receiver of Lambert's factor to the source, here averaged over 24^2 of its points.
    # (The 4-point contour integral reads the nearest 6% low.) And floor triangles with an
    # edge along the wall's foot, against the contour integral at 48 points a piece.
    from hemirad.transport.smallreceivers import sample_barycentrics

    wall = torch.tensor([[0, 0, 0], [0, 0, 1], [1, 0, 0]], dtype=torch.float64)  # faces +y
    radius = 0.01
    apart = torch.tensor([2, 4, 8, 16, 32, 64, 200], dtype=torch.float64)

    def placed(corners, where):  # (3, 3) a shape of about ``radius``, centred at each of (m, 3)
        shape = torch.tensor(corners, dtype=torch.float64) * radius
        return shape - shape.mean(0) + where[:, None]

    away = apart * radius + radius
    on_floor = placed([[0, 0, 0], [1.2, 0, 0], [0, 1.2, 0]],  # faces +z
                      torch.stack([torch.full_like(away, 0.3), away, torch.zeros_like(away)], 1))
    facing = placed([[0, 0, 0], [1.2, 0, 0], [0, 0, 1.2]],  # faces -y
                    torch.stack([torch.full_like(away, 0.3), away, torch.full_like(away, 0.3)], 1))

    def area(t):
        return 0.5 * torch.linalg.vector_norm(torch.linalg.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), dim=1)
    for receivers in (on_floor, facing):
        normals = torch.nn.functional.normalize(
            torch.linalg.cross(receivers[:, 1] - receivers[:, 0], receivers[:, 2] - receivers[:, 0]), dim=1)
        points = torch.einsum("pc,mcd->mpd", sample_barycentrics(24), receivers)  # (m, P, 3)
        sources = wall[None].expand(len(receivers), 3, 3)
        exact = torch.stack([point_to_triangles(points[i][:, None], normals[i], sources[:1].expand(len(points[i]), 3, 3)
                                                ).mean() for i in range(len(receivers))]) * area(receivers) / area(sources)
        assert bool((exact > 1e-8).all())
        torch.testing.assert_close(small_triangle_factors(sources, receivers, 3), exact, rtol=1e-5, atol=0)
        far = apart >= 32
        torch.testing.assert_close(small_triangle_factors(sources[far], receivers[far], 1), exact[far], rtol=5e-4, atol=0)
    foot = torch.tensor([0.05, 0.3, 0.6], dtype=torch.float64)  # along the wall's foot (its edge is 0 to 1)
    touching = torch.stack([torch.tensor([[x, 0, 0], [x + 2 * radius, 0, 0], [x, 2 * radius, 0]], dtype=torch.float64)
                            for x in foot.tolist()])  # faces +z, an edge on the wall's plane
    sources = wall[None].expand(len(touching), 3, 3)
    torch.testing.assert_close(small_triangle_factors(sources, touching, 3), triangle_to_triangles(sources, touching, 48),
                               rtol=1e-3, atol=0)  # (the 4-point contour reads them 8-18% low)
