"""The files other tools read: the PLY loads back in trimesh with one vertex, colour and
radiosity per solved vertex, the binary glTF with the picture as drawn; the Python API
writes them all."""
from __future__ import annotations

import dataclasses
import json
import struct
from pathlib import Path

import numpy as np
import pytest
import trimesh

import hemirad
from hemirad.output import display, gltf
from hemirad.output.export import read_ply_radiosity

SMALL_ROOM = Path(__file__).parent / "data" / "small_room.yaml"


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """A small solve with refinement (so the mesh has T-vertices), written by the Python API."""
    scene = hemirad.load_scene(SMALL_ROOM)
    scene.solver = dataclasses.replace(scene.solver, max_shots=8)
    scene.refine = dataclasses.replace(scene.refine, pattern="pattern2", criterion="gradient",
                                        threshold=1e-3, max_depth=1)
    result = hemirad.solve(scene)
    paths = result.write(tmp_path_factory.mktemp("out"))
    return result, paths


def test_write_makes_every_output(written):
    result, paths = written
    assert {k: p.name for k, p in paths.items()} == {
        "image": "image.png", "HDR image": "image.exr", "luminance": "luminance.png", "mesh view": "mesh.png",
        "mesh": "mesh.ply", "glTF": "mesh.glb", "stats": "stats.json"}
    assert all(p.stat().st_size > 0 for p in paths.values())
    stats = json.loads(paths["stats"].read_text())
    assert stats["elements"] == result.mesh.num_elements and stats["resumed_from_shot"] is None


def test_ply_loads_back_with_colours_and_radiosity(written):
    result, paths = written
    vertex = result.vertex_radiosity().numpy()
    ply = trimesh.load(paths["mesh"], process=False)
    assert len(ply.vertices) == len(result.mesh.vertices) and len(ply.faces) == result.mesh.num_elements
    assert np.array_equal(ply.visual.vertex_colors[:, :3], display.to_srgb8(vertex, result.exposure()))
    assert np.array_equal(read_ply_radiosity(paths["mesh"]), vertex.astype(np.float32))


def test_glb_loads_back_as_the_picture_draws_it(written):
    """The glTF is the picture as drawn (``Result.shading``), its colours and radiosity at
    every point, so a viewer elsewhere shows what image.png shows."""
    result, paths = written
    shading = result.shading()
    assert shading.levels > 0 and len(shading.triangles) == 4 ** shading.levels * len(shading.pieces)
    scene = trimesh.load(paths["glTF"], process=False)
    (mesh,) = scene.geometry.values()
    assert np.array_equal(mesh.faces, shading.triangles.numpy())
    assert np.allclose(mesh.vertices, shading.positions.numpy(), rtol=1e-6, atol=1e-6)
    # the unlit material makes trimesh keep COLOR_0 beside it, as a vertex attribute
    color = np.asarray(mesh.visual.vertex_attributes["color"])
    expected = np.clip(shading.values.numpy() * result.exposure(), 0, 1).astype(np.float32)
    assert np.array_equal(color, expected)
    assert color.max() == 1.0 and len(np.unique(color, axis=0)) > 10  # the lamp saturates; walls vary
    assert np.array_equal(mesh.vertex_attributes[gltf.RADIOSITY_ATTRIBUTE], shading.values.numpy().astype(np.float32))
    # the mesh's own vertices come first, with the values the PLY gives them
    V = len(result.mesh.vertices)
    assert np.array_equal(mesh.vertex_attributes[gltf.RADIOSITY_ATTRIBUTE][:V], read_ply_radiosity(paths["mesh"]))


def test_glb_container_follows_the_spec(written):
    result, paths = written
    data = paths["glTF"].read_bytes()
    magic, version, length = struct.unpack_from("<III", data)
    assert (magic, version, length) == (0x46546C67, 2, len(data)) and length % 4 == 0
    json_length, json_type = struct.unpack_from("<II", data, 12)
    assert json_type == 0x4E4F534A and json_length % 4 == 0
    doc = json.loads(data[20:20 + json_length])
    bin_length, bin_type = struct.unpack_from("<II", data, 20 + json_length)
    assert bin_type == 0x004E4942 and bin_length == doc["buffers"][0]["byteLength"]
    primitive = doc["meshes"][0]["primitives"][0]
    assert set(primitive["attributes"]) == {"POSITION", "COLOR_0", "_RADIOSITY"}
    position = doc["accessors"][primitive["attributes"]["POSITION"]]
    lo, hi = (v.numpy().tolist() for v in result.mesh.bounding_box())
    assert np.allclose(position["min"], lo) and np.allclose(position["max"], hi)
    assert all(view["byteOffset"] % 4 == 0 for view in doc["bufferViews"])
    assert "KHR_materials_unlit" in doc["materials"][primitive["material"]]["extensions"]


def test_write_glb_alone(written, tmp_path):
    result, _ = written
    path = result.write_glb(tmp_path / "alone.glb")
    mesh = trimesh.load(path, force="mesh", process=False)
    assert len(mesh.vertices) == len(result.shading().positions)


def test_glb_refuses_colours_outside_0_1(written):
    result, _ = written
    vertex = result.vertex_radiosity()
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        gltf.glb_bytes(result.mesh.vertices, result.mesh.triangles, vertex, vertex.numpy() * 1e6)
