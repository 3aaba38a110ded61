"""Mesh is immutable and keeps what it derives in an explicit cache."""
import dataclasses

import pytest
import torch

from hemirad.geometry.mesh import DerivedCache, Mesh


def _square() -> Mesh:
    vertices = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]
    return Mesh(vertices, [[0, 1, 2], [0, 2, 3]], [0, 0], [0, 0], ["square"])


@pytest.mark.parametrize("name", ["vertices", "triangles", "surface", "material", "surface_names", "level",
                                  "edge_parents", "cache", "areas", "normals", "centroids", "plane_ids"])
def test_assigning_an_attribute_raises(name):
    mesh = _square()
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(mesh, name, None)


def test_replace_makes_a_new_mesh_with_a_cache_of_its_own():
    mesh = _square()
    assert float(mesh.areas.sum()) == 0.5 + 0.5 and mesh.cache.contains("areas")
    moved = dataclasses.replace(mesh, vertices=mesh.vertices * 2)
    assert not moved.cache.contains("areas")
    assert float(moved.areas.sum()) == 4.0 and float(mesh.areas.sum()) == 1.0
    assert moved.surface_names == ["square"] and torch.equal(moved.triangles, mesh.triangles)


def test_derived_values_are_computed_once_and_kept():
    mesh = _square()
    assert not any(mesh.cache.contains(k) for k in ("centroids", "areas", "normals", "plane_ids"))
    normals = mesh.normals
    assert mesh.cache.contains("normals") and mesh.normals is normals
    assert torch.equal(normals, torch.tensor([[0.0, 0, 1], [0, 0, 1]], dtype=torch.float64))
    assert mesh.plane_ids.tolist() == [0, 0] and mesh.cache.get("plane_ids") is mesh.plane_ids


def test_derived_cache_get_put_contains():
    cache = DerivedCache()
    assert cache.get("x") is None and not cache.contains("x") and "x" not in cache
    calls = []
    assert cache.get("x", lambda: calls.append(1) or 7) == 7
    assert cache.get("x", lambda: calls.append(1) or 8) == 7 and calls == [1]
    assert cache.put("y", 3) == 3 and cache.contains("y") and "y" in cache and cache.get("y") == 3


def test_equality_is_identity():
    mesh = _square()
    assert mesh == mesh and mesh != _square()
    assert len({mesh, mesh, _square()}) == 2


def test_edge_keys_and_unique_edges():
    from hemirad.geometry.edges import (KEY_BASE, contains, edge_keys, key_ends, search, triangle_edges,
                                        unique_edge_keys, unique_edges)

    a, b = torch.tensor([3, 0, 5]), torch.tensor([1, 4, 5])
    keys = edge_keys(a, b)
    assert torch.equal(keys, edge_keys(b, a))
    assert keys.tolist() == [1 * KEY_BASE + 3, 0 * KEY_BASE + 4, 5 * KEY_BASE + 5]
    lo, hi = key_ends(keys)
    assert lo.tolist() == [1, 0, 5] and hi.tolist() == [3, 4, 5]
    triangles = torch.tensor([[0, 1, 2], [0, 2, 3]])
    start, end = triangle_edges(triangles)
    assert start.tolist() == [0, 1, 2, 0, 2, 3] and end.tolist() == [1, 2, 0, 2, 3, 0]
    assert unique_edges(triangles).tolist() == [[0, 1], [0, 2], [0, 3], [1, 2], [2, 3]]
    sorted_keys = unique_edge_keys(triangles)
    assert contains(sorted_keys, edge_keys(torch.tensor([2, 1, 3]), torch.tensor([0, 3, 2]))).tolist() == \
        [True, False, True]
    assert contains(sorted_keys[:0], keys).tolist() == [False] * 3
    values = torch.arange(10, 15)
    assert search(sorted_keys, values, edge_keys(torch.tensor([3, 1]), torch.tensor([2, 3]))).tolist() == [14, -1]
    assert search(sorted_keys[:0], values[:0], keys).tolist() == [-1] * 3
