import math

import pytest
import torch

from hemirad.geometry.mesh import Mesh
from hemirad.geometry.patterns import CHILDREN, PATTERNS
from hemirad.geometry.split import angle_quality, child_containing, largest_angles, split_triangles
from hemirad.scene.meshing import grid_quad


def _triangle() -> Mesh:
    """One scalene triangle in general position (not axis-aligned, off the origin)."""
    vertices = [[0.3, -1.2, 2.0], [2.1, 0.4, 1.5], [0.9, 1.7, 3.1]]
    return Mesh(vertices, [[0, 1, 2]], [3], [2], ["a", "b", "c", "tri"], [2])


def _square() -> Mesh:
    """Unit square in z = 0 as two triangles sharing the diagonal 0-2."""
    vertices = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]
    return Mesh(vertices, [[0, 1, 2], [0, 2, 3]], [0, 0], [0, 0])


def _jittered_grid(seed: int = 0, cells: int = 6, jitter: float = 0.05) -> Mesh:
    """A unit square gridded into cells^2 x 2 triangles, interior vertices moved at random
    by up to ``jitter`` cells: a mesh of many slightly different shapes."""
    g = torch.Generator().manual_seed(seed)
    corners = torch.tensor([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=torch.float64)
    v, t = grid_quad(corners, 1.0 / cells)
    inner = (v[:, :2] > 1e-9).all(dim=1) & (v[:, :2] < 1 - 1e-9).all(dim=1)
    shift = (torch.rand(len(v), 2, generator=g, dtype=torch.float64) - 0.5) * (2 * jitter / cells)
    v[inner, :2] += shift[inner]
    return Mesh(v, t, torch.zeros(len(t)), torch.zeros(len(t)))


def _sorted_sides(mesh: Mesh) -> torch.Tensor:
    c = mesh.corners
    sides = torch.stack([(c[:, 1] - c[:, 0]).norm(dim=1), (c[:, 2] - c[:, 1]).norm(dim=1),
                         (c[:, 0] - c[:, 2]).norm(dim=1)], dim=1)
    return sides.sort(dim=1).values


def _sorted_angles(mesh: Mesh) -> torch.Tensor:
    c = mesh.corners
    to_next, to_prev = c[:, [1, 2, 0]] - c, c[:, [2, 0, 1]] - c
    cos = (to_next * to_prev).sum(-1) / (to_next.norm(dim=-1) * to_prev.norm(dim=-1))
    return torch.rad2deg(torch.acos(cos.clamp(-1, 1))).sort(dim=1).values


@pytest.mark.parametrize("pattern, children", [("pattern1", 3), ("pattern2", 4)])
def test_children_inherit_and_conserve(pattern, children):
    mesh = _triangle()
    new, parent = split_triangles(mesh, torch.tensor([True]), pattern)
    assert new.num_elements == children
    assert parent.tolist() == [0] * children
    assert new.surface.tolist() == [3] * children and new.material.tolist() == [2] * children
    assert new.level.tolist() == [3] * children
    assert new.surface_names == mesh.surface_names
    # Winding preserved: every child faces the parent's way.
    torch.testing.assert_close(new.normals, mesh.normals.expand(children, 3), rtol=0, atol=1e-12)
    assert abs(float(new.areas.sum()) / float(mesh.areas.sum()) - 1) < 1e-12
    # The old vertices keep their indices.
    assert torch.equal(new.vertices[:3], mesh.vertices)


def test_pattern1_centroid_children():
    mesh = _triangle()
    new, _ = split_triangles(mesh, torch.tensor([True]), "pattern1")
    assert len(new.vertices) == 4
    torch.testing.assert_close(new.vertices[3], mesh.centroids[0], rtol=0, atol=1e-15)
    assert new.triangles.tolist() == [[0, 1, 3], [1, 2, 3], [2, 0, 3]]
    assert new.edge_parents[3].tolist() == [-1, -1]  # not on any edge: never a T-vertex
    torch.testing.assert_close(new.areas, mesh.areas.expand(3) / 3, rtol=1e-12, atol=0)


def test_pattern2_children_similar_to_parent():
    mesh = _triangle()
    new, _ = split_triangles(mesh, torch.tensor([True]), "pattern2")
    assert len(new.vertices) == 6
    ratios = _sorted_sides(new) / _sorted_sides(mesh)
    torch.testing.assert_close(ratios, torch.full((4, 3), 0.5, dtype=torch.float64), rtol=1e-12, atol=0)
    # New midpoints record their edge, ends sorted.
    assert sorted(new.edge_parents[3:].tolist()) == [[0, 1], [0, 2], [1, 2]]
    assert (new.edge_parents[:3] == -1).all()
    for v, (a, b) in zip(range(3, 6), new.edge_parents[3:].tolist()):
        torch.testing.assert_close(new.vertices[v], 0.5 * (mesh.vertices[a] + mesh.vertices[b]))


@pytest.mark.parametrize("pattern", ["pattern1", "pattern2"])
def test_parent_carries_values_and_power(pattern):
    mesh = _jittered_grid(seed=3)
    g = torch.Generator().manual_seed(5)
    values = torch.rand(mesh.num_elements, 3, generator=g, dtype=torch.float64)
    selected = torch.rand(mesh.num_elements, generator=g) < 0.4
    new, parent = split_triangles(mesh, selected, pattern)

    T = mesh.num_elements
    unsplit = torch.nonzero(~selected).reshape(-1)
    per = 3 if pattern == "pattern1" else 4
    # Every old element keeps its index (a split one's holds its first child); the other
    # children follow, grouped by parent.
    assert torch.equal(parent[:T], torch.arange(T))
    assert torch.equal(parent[T:], torch.nonzero(selected).reshape(-1).repeat_interleave(per - 1))
    assert torch.equal(new.triangles[unsplit], mesh.triangles[unsplit])
    assert torch.equal(new.level, mesh.level[parent] + selected[parent].long())

    power = (values * mesh.areas[:, None]).sum(dim=0)
    new_power = (values[parent] * new.areas[:, None]).sum(dim=0)
    torch.testing.assert_close(new_power, power, rtol=1e-12, atol=0)
    torch.testing.assert_close(new.normals, mesh.normals[parent], rtol=0, atol=1e-12)
    # Children of one parent tile it exactly.
    child_area = torch.zeros(mesh.num_elements, dtype=torch.float64).index_add_(0, parent, new.areas)
    torch.testing.assert_close(child_area, mesh.areas, rtol=1e-12, atol=0)


def test_pattern2_shares_midpoint_in_one_call():
    new, _ = split_triangles(_square(), torch.tensor([True, True]), "pattern2")
    # 4 corners and one midpoint per distinct edge: 6 triangle edges, the diagonal shared.
    assert len(new.vertices) == 4 + 5
    positions = {tuple(p) for p in new.vertices.tolist()}
    assert len(positions) == len(new.vertices)  # no duplicate at the shared diagonal


def test_pattern2_reuses_midpoint_across_calls():
    square = _square()
    once, _ = split_triangles(square, torch.tensor([True, True]), "pattern2")
    first, parent = split_triangles(square, torch.tensor([True, False]), "pattern2")
    assert len(first.vertices) == 4 + 3
    # The unsplit second triangle keeps its index; split it too.
    assert parent.tolist()[:2] == [0, 1] and first.level.tolist()[1] == 0
    second, _ = split_triangles(first, first.level == 0, "pattern2")
    # Only the two outer edges of the second triangle get new midpoints.
    assert len(second.vertices) == len(once.vertices) == 9
    assert len({tuple(p) for p in second.vertices.tolist()}) == 9
    # Same triangles as splitting both at once, up to order.
    as_sets = lambda m: sorted(tuple(sorted(m.vertices[t].flatten().tolist())) for t in m.triangles)  # noqa: E731
    assert as_sets(second) == as_sets(once)


def test_split_nothing_and_bad_arguments():
    mesh = _square()
    new, parent = split_triangles(mesh, torch.tensor([False, False]), "pattern2")
    assert torch.equal(new.triangles, mesh.triangles) and parent.tolist() == [0, 1]
    assert len(new.vertices) == 4
    with pytest.raises(ValueError, match="pattern"):
        split_triangles(mesh, torch.tensor([True, False]), "pattern3")
    with pytest.raises(ValueError, match="one flag per element"):
        split_triangles(mesh, torch.tensor([True]), "pattern1")


def test_largest_angles_and_quality():
    h = math.sqrt(3) / 2
    # Equilateral, right isosceles, and isosceles with a 120 degree apex.
    mesh = Mesh([[0, 0, 0], [1, 0, 0], [0.5, h, 0], [0, 1, 0], [-1, 0, 0], [0, 1 / math.sqrt(3), 0]],
                [[0, 1, 2], [0, 1, 3], [4, 1, 5]], [0, 0, 0], [0, 0, 0])
    angles = largest_angles(mesh)
    torch.testing.assert_close(angles, torch.tensor([60.0, 90.0, 120.0], dtype=torch.float64), rtol=0, atol=1e-9)
    q = angle_quality(mesh)
    assert q["mean"] == pytest.approx(90.0)
    assert q["variance"] == pytest.approx(600.0)  # population variance of 60, 90, 120


def test_largest_angle_of_a_sliver_is_accurate():
    eps = 1e-7
    mesh = Mesh([[0, 0, 0], [2, 0, 0], [1, eps, 0]], [[0, 1, 2]], [0], [0])
    expected = 180.0 - 2 * math.degrees(math.atan(eps))
    assert float(largest_angles(mesh)[0]) == pytest.approx(expected, abs=1e-9)


def _refine(mesh: Mesh, pattern: str, rounds: int, seed: int) -> tuple[Mesh, torch.Tensor]:
    """Split a random half of the elements each round; returns the mesh and each element's
    ancestor in the input mesh."""
    g = torch.Generator().manual_seed(seed)
    root = torch.arange(mesh.num_elements)
    for _ in range(rounds):
        selected = torch.rand(mesh.num_elements, generator=g) < 0.5
        mesh, parent = split_triangles(mesh, selected, pattern)
        root = root[parent]
    return mesh, root


def test_pattern2_keeps_shapes_pattern1_degrades():
    base = _jittered_grid(seed=0)
    q0 = angle_quality(base)
    p1, _ = _refine(base, "pattern1", 5, seed=100)
    p2, root = _refine(base, "pattern2", 5, seed=100)
    q1, q2 = angle_quality(p1), angle_quality(p2)

    # Pattern 2 only makes copies of the initial shapes: same angles as the ancestor.
    torch.testing.assert_close(_sorted_angles(p2), _sorted_angles(base)[root], rtol=0, atol=1e-7)
    # So the statistics move only with how many copies each shape got.
    assert 0.5 * q0["variance"] < q2["variance"] < 2.0 * q0["variance"]
    assert abs(q2["mean"] - q0["mean"]) < 2.0
    # Pattern 1 makes slivers: the largest angle grows towards 180 degrees.
    assert q1["variance"] > 10 * q2["variance"]
    assert q1["mean"] > q0["mean"] + 30
    # Both stay exact tilings of the square.
    for m in (p1, p2):
        assert abs(float(m.areas.sum()) - 1.0) < 1e-12
        assert (m.normals[:, 2] > 0).all()


@pytest.mark.parametrize("pattern", ["pattern1", "pattern2"])
def test_midpoint_index_carried_through_splits_is_the_one_built_afresh(pattern):
    from hemirad.geometry.edges import MIDPOINT_INDEX, midpoint_index

    g = torch.Generator().manual_seed(5)
    mesh = _jittered_grid()
    midpoint_index(mesh)  # built once; every split below carries it over
    for _ in range(4):
        mesh, _ = split_triangles(mesh, torch.rand(mesh.num_elements, generator=g) < 0.3, pattern)
    assert mesh.cache.contains(MIDPOINT_INDEX)
    carried = mesh.cache.get(MIDPOINT_INDEX)
    fresh = Mesh(mesh.vertices, mesh.triangles, mesh.surface, mesh.material, level=mesh.level,
                 edge_parents=mesh.edge_parents)
    built = midpoint_index(fresh)
    assert (len(built[0]) > 0) == (pattern == "pattern2")
    assert torch.equal(carried[0], built[0]) and torch.equal(carried[1], built[1])


@pytest.mark.parametrize("pattern", ["pattern1", "pattern2"])
def test_geometry_handed_over_by_a_split_is_the_one_computed_afresh(pattern):
    from hemirad.geometry.split import inherit

    g = torch.Generator().manual_seed(7)
    mesh = _jittered_grid(seed=1)
    values = torch.rand(mesh.num_elements, 3, generator=g, dtype=torch.float64)
    for _ in range(3):
        mesh.normals, mesh.areas, mesh.centroids  # computed, so that the split hands them over
        mesh, parent = split_triangles(mesh, torch.rand(mesh.num_elements, generator=g) < 0.3, pattern)
        values_before, values = values, inherit(values, parent)
        assert torch.equal(values, values_before[parent])
    assert all(mesh.cache.contains(k) for k in ("centroids", "areas", "normals"))
    handed = {k: mesh.cache.get(k) for k in ("centroids", "areas", "normals")}
    fresh = Mesh(mesh.vertices, mesh.triangles, mesh.surface, mesh.material)
    for name, value in handed.items():
        assert torch.equal(value, getattr(fresh, name)), name
    rows = torch.tensor([0, 5, mesh.num_elements - 1])
    assert torch.equal(mesh.corners_of(rows), fresh.corners[rows])
    assert torch.equal(mesh.corners_of(3), fresh.corners[3])


@pytest.mark.parametrize("pattern", ["pattern1", "pattern2"])
def test_split_rounds_give_what_a_chain_of_splits_gives(pattern):
    """Rounds write into shared buffers and look midpoints up in an index of their own until
    ``result``: a later round must still reuse the midpoints an earlier one made."""
    from hemirad.geometry.edges import MIDPOINT_INDEX, midpoint_index
    from hemirad.geometry.split import SplitRounds

    g = torch.Generator().manual_seed(11)
    start = _jittered_grid(seed=2)
    start.normals, start.areas, start.centroids, midpoint_index(start)  # computed: handed over
    rounds, chained, chained_parent = SplitRounds(start, pattern), start, torch.arange(start.num_elements)
    for _ in range(3):
        selected = torch.rand(rounds.num_elements, generator=g) < 0.3
        rounds.split(torch.nonzero(selected).reshape(-1))
        chained, parent = split_triangles(chained, selected, pattern)
        chained_parent = chained_parent[parent]
    mesh, parent = rounds.result()
    assert torch.equal(parent, chained_parent)
    for name in ("vertices", "triangles", "surface", "material", "level", "edge_parents"):
        assert torch.equal(getattr(mesh, name), getattr(chained, name)), name
    for name in ("centroids", "areas", "normals", MIDPOINT_INDEX):
        assert mesh.cache.contains(name) and chained.cache.contains(name), name
        ours, theirs = mesh.cache.get(name), chained.cache.get(name)
        assert all(torch.equal(a, b) for a, b in zip(ours, theirs)) if name == MIDPOINT_INDEX else \
            torch.equal(ours, theirs), name


def test_a_leaf_beside_twice_split_neighbours_is_unbalanced():
    from hemirad.geometry.split import unbalanced

    square = _square()  # triangles 0 (0 1 2) and 1 (0 2 3) share the diagonal 0-2
    once, _ = split_triangles(square, torch.tensor([True, False]), "pattern2")
    assert unbalanced(once).tolist() == []  # one midpoint on the diagonal: 2:1 holds
    # the child of triangle 0 at corner 0 has the half-diagonal 0-m on its border
    at_corner = int(torch.nonzero((once.triangles == 0).any(1) & (once.level == 1))[0])
    twice, _ = split_triangles(once, torch.arange(once.num_elements) == at_corner, "pattern2")
    assert unbalanced(twice).tolist() == [1]  # triangle 1's edge now holds nested midpoints
    near = torch.zeros(len(twice.vertices), dtype=torch.bool)
    assert unbalanced(twice, near).tolist() == []  # only triangles touching ``near`` are examined
    near[0] = True
    assert unbalanced(twice, near).tolist() == [1]


@pytest.mark.parametrize("pattern", PATTERNS)
def test_a_split_makes_the_children_its_pattern_names(pattern):
    mesh, _ = split_triangles(_triangle(), torch.tensor([True]), pattern)
    assert mesh.num_elements == CHILDREN[pattern]


@pytest.mark.parametrize("pattern", PATTERNS)
def test_the_child_containing_a_descendant_is_the_one_the_split_made(pattern):
    # split a triangle, then every child again: each grandchild's centroid finds, in the
    # triangle, the child it was split from (corners in the split's order and winding)
    mesh = _triangle()
    children, _ = split_triangles(mesh, torch.tensor([True]), pattern)
    grandchildren, parent = split_triangles(children, torch.ones(children.num_elements, dtype=torch.bool), pattern)
    found, number = child_containing(mesh.corners.expand(grandchildren.num_elements, 3, 3), grandchildren.centroids,
                                     pattern)
    torch.testing.assert_close(found, children.corners[parent], rtol=0, atol=1e-12)
    # and the numbers tell the siblings apart, one for each child
    assert len(torch.unique(torch.stack([parent, number]), dim=1).T) == CHILDREN[pattern]
