"""Finding the element under a surface point, for point references (``scripts/peer_room.py``)."""
import torch

from hemirad.evaluation.surface_points import elements_at

from patches import closed_box


def test_every_centroid_finds_its_own_element_and_a_point_off_the_surface_none():
    mesh = closed_box(element_size=0.25)
    # a point exactly on a shared edge or corner may belong to either side; centroids do not
    found = elements_at(mesh, mesh.centroids, mesh.normals)
    assert torch.equal(found, torch.arange(mesh.num_elements))
    away = mesh.centroids[:3] + 0.1 * mesh.normals[:3]  # inside the box, off every wall
    assert (elements_at(mesh, away, mesh.normals[:3]) == -1).all()
    # the same point with the opposite normal is on no element facing that way
    assert (elements_at(mesh, mesh.centroids[:3], -mesh.normals[:3]) == -1).all()
