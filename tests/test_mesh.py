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

