"""Materials from mesh files: glTF 2.0 (baseColorFactor, emissiveFactor x
KHR_materials_emissive_strength) and OBJ + MTL (Kd, Ke), per face, exact, overridable by
name from the scene file, and refused with one paragraph naming the file and material.

The files are written here: a closed unit box seen from inside, its ceiling split in two
halves, the x < 0.5 half a lamp. The same geometry as glTF and as OBJ + MTL meshes the same
way, so the radiosities are compared bit for bit.
"""
from __future__ import annotations

import json
import struct
import zlib

import numpy as np
import pytest
import torch

from hemirad import checkpoint
from hemirad.cli import main
from hemirad.pipeline import solve
from hemirad.scene.filematerials import _unique_names, parse_mtl
from hemirad.scene.loader import load_scene
from hemirad.scene.meshfile import read_mesh_file
from hemirad.scene.meshing import box_face_corners, build_mesh

WHITE = (0.7, 0.71, 0.123456789)  # not a multiple of 1/255: an 8-bit colour would show
EMISSIVE_FACTOR, STRENGTH = (1.0, 0.8, 0.6), 5.0
LAMP_EMISSION = tuple(f * STRENGTH for f in EMISSIVE_FACTOR)  # (5, 4, 3): what KHR_materials_emissive_strength makes
LAMP_AREA = 0.5  # the ceiling's x < 0.5 half of the unit box


def room_quads() -> list[tuple[np.ndarray, str]]:
    """(corners (4, 3), material) of each quad of the unit box seen from inside, the walls
    and floor white, the ceiling's halves lamp (x < 0.5) and white, all facing inward."""
    quads = [(box_face_corners((0, 0, 0), (1, 1, 1), face, inward=True).numpy(), "white")
             for face in ("floor", "x_min", "x_max", "z_min", "z_max")]
    for x0, x1, material in ((0.0, 0.5, "lamp"), (0.5, 1.0, "white")):  # facing down (-y)
        quads.append((np.array([[x0, 1, 0], [x1, 1, 0], [x1, 1, 1], [x0, 1, 1]], dtype=np.float64), material))
    return quads


def triangles_by_material(order: tuple[str, ...]) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The box's vertices (shared by position, so the ceiling's halves meet along an edge) and
    (T, 3) triangles (each quad as 012, 023) for each material, in ``order``."""
    vertices: list[tuple] = []
    out = {m: [] for m in order}
    for corners, material in room_quads():
        ids = []
        for c in map(tuple, corners.tolist()):
            if c not in vertices:
                vertices.append(c)
            ids.append(vertices.index(c))
        out[material] += [[ids[0], ids[1], ids[2]], [ids[0], ids[2], ids[3]]]
    return np.array(vertices), {m: np.array(out[m], dtype=np.int64) for m in order}


def write_glb(path, white=WHITE + (1.0,), emissive_strength=STRENGTH, order=("white", "lamp"), lamp_material=True,
              textured=False):
    """The box as binary glTF (or, for a ``.gltf`` path, JSON beside a ``.bin`` buffer): one
    mesh, a primitive per material (its own positions and indices), the lamp's emission made
    by KHR_materials_emissive_strength."""
    vertices, by_material = triangles_by_material(order)
    blob, views, accessors, primitives = b"", [], [], []
    for material in order:
        used, local = np.unique(by_material[material], return_inverse=True)
        positions = vertices[used].astype(np.float32)  # the box's coordinates are exact in float32
        bounds = {"min": positions.min(0).tolist(), "max": positions.max(0).tolist()}  # glTF requires them
        for data, kind, component, extra in (
                (positions.tobytes(), "VEC3", 5126, bounds),
                (local.astype(np.uint32).tobytes(), "SCALAR", 5125, {})):
            views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)})
            count = len(positions) if kind == "VEC3" else local.size
            accessors.append({"bufferView": len(views) - 1, "componentType": component, "count": count,
                              "type": kind, **extra})
            blob += data
        primitive = {"attributes": {"POSITION": len(accessors) - 2}, "indices": len(accessors) - 1, "mode": 4}
        if material == "white" or lamp_material:
            primitive["material"] = ["white", "lamp"].index(material)
        primitives.append(primitive)
    doc = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
        "meshes": [{"name": "room", "primitives": primitives}],
        "materials": [
            {"name": "white", "pbrMetallicRoughness": {"baseColorFactor": list(white)}},
            {"name": "lamp", "pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1]},
             "emissiveFactor": list(EMISSIVE_FACTOR),
             "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": emissive_strength}}},
        ],
        "extensionsUsed": ["KHR_materials_emissive_strength"],
        "buffers": [{"byteLength": len(blob)}], "bufferViews": views, "accessors": accessors,
    }
    if textured:
        doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] = {"index": 0}
    if path.suffix == ".gltf":
        doc["buffers"][0]["uri"] = path.with_suffix(".bin").name
        path.with_suffix(".bin").write_bytes(blob)
        path.write_text(json.dumps(doc))
        return path
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    blob += b"\0" * (-len(blob) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(blob), 0x004E4942) + blob
    path.write_bytes(struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body)
    return path


MTL = f"""# the box's materials
newmtl white
Kd {WHITE[0]!r} {WHITE[1]!r} {WHITE[2]!r}
newmtl lamp
Kd 0 0 0
Ke {LAMP_EMISSION[0]!r} {LAMP_EMISSION[1]!r} {LAMP_EMISSION[2]!r}
"""


def write_obj(path, order=("white", "lamp"), mtl: str | None = MTL, mtllib: str = "room.mtl", first_usemtl=True):
    """The box as OBJ: a usemtl block per material in ``order``, the MTL beside it."""
    vertices, by_material = triangles_by_material(order)
    lines = [f"mtllib {mtllib}"] + [f"v {x!r} {y!r} {z!r}" for x, y, z in vertices.tolist()]
    for k, material in enumerate(order):
        if k or first_usemtl:
            lines.append(f"usemtl {material}")
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in by_material[material].tolist()]
    path.write_text("\n".join(lines) + "\n")
    if mtl is not None:
        (path.parent / "room.mtl").write_text(mtl)
    return path


def write_scene(folder, file: str, materials: str = "", material: str | None = None, name: str = "room"):
    """A scene of the one mesh object (no YAML material unless given); camera inside the box."""
    text = f"""
element_size: 0.5
{materials}
objects:
  - {{type: mesh, name: {name}, file: {file}{', material: ' + material if material else ''}}}
camera: {{position: [0.5, 0.5, 0.05], look_at: [0.5, 0.5, 1.0], fov: 90, width: 32, height: 24, supersample: 1}}
solver: {{resolution: 32, max_shots: 25}}
"""
    path = folder / f"{file.rsplit('.', 1)[0]}_{zlib.crc32(text.encode()):08x}.yaml"
    path.write_text(text)
    return path


YAML_MATERIALS = f"""materials:
  white: {{reflectance: [{WHITE[0]!r}, {WHITE[1]!r}, {WHITE[2]!r}]}}
  lamp: {{reflectance: 0, emission: [{LAMP_EMISSION[0]!r}, {LAMP_EMISSION[1]!r}, {LAMP_EMISSION[2]!r}]}}
"""


def element_materials(scene, mesh) -> tuple[torch.Tensor, torch.Tensor]:
    """(T, 3) reflectance and emission of each element."""
    return scene.reflectance_table()[mesh.material], scene.emission_table()[mesh.material]


def centroids(mesh) -> np.ndarray:
    return mesh.vertices[mesh.triangles].mean(dim=1).numpy()


# ----------------------------------------------------------------------------------------
# reading


def test_gltf_materials_are_read_exactly_per_face(tmp_path):
    contents = read_mesh_file(write_glb(tmp_path / "room.glb"))
    names = [m.name for m in contents.materials.materials]
    assert names == ["white", "lamp"] and contents.materials.problem is None
    white, lamp = contents.materials.materials
    assert white.reflectance == WHITE  # not trimesh's 8-bit 179/255
    assert lamp.reflectance == (0.0, 0.0, 0.0) and lamp.emission == LAMP_EMISSION  # factor x strength
    # the lamp's faces are the two triangles at y = 1 with x <= 0.5
    corners = contents.vertices[contents.faces]
    is_lamp = (corners[:, :, 1] == 1).all(axis=1) & (corners[:, :, 0] <= 0.5).all(axis=1)
    assert is_lamp.sum() == 2
    assert np.array_equal(contents.face_materials, np.where(is_lamp, 1, 0))


def test_a_gltf_with_its_buffer_beside_it(tmp_path):
    glb, gltf = read_mesh_file(write_glb(tmp_path / "room.glb")), read_mesh_file(write_glb(tmp_path / "room.gltf"))
    assert np.array_equal(glb.vertices, gltf.vertices) and np.array_equal(glb.faces, gltf.faces)
    assert np.array_equal(glb.face_materials, gltf.face_materials) and glb.materials == gltf.materials
    # the buffer holds the geometry: the checkpoint's hash of the file covers it
    (tmp_path / "room.bin").write_bytes((tmp_path / "room.bin").read_bytes()[:-4] + b"\0\0\0\0")
    assert read_mesh_file(tmp_path / "room.gltf").sha256 != gltf.sha256


def test_a_texture_is_ignored_with_a_warning(tmp_path):
    from hemirad.core.errors import HemiradWarning

    write_glb(tmp_path / "room.glb", textured=True)
    with pytest.warns(HemiradWarning, match="'white' of room.glb has a texture, which is ignored"):
        scene = load_scene(write_scene(tmp_path, "room.glb"))
    assert scene.materials[0].reflectance == WHITE


def test_obj_mtl_materials_are_read_exactly_per_face(tmp_path):
    contents = read_mesh_file(write_obj(tmp_path / "room.obj"))
    by_name = {m.name: m for m in contents.materials.materials}
    assert by_name["white"].reflectance == WHITE and by_name["white"].emission == (0.0, 0.0, 0.0)
    assert by_name["lamp"].emission == LAMP_EMISSION
    corners = contents.vertices[contents.faces]
    is_lamp = (corners[:, :, 1] == 1).all(axis=1) & (corners[:, :, 0] <= 0.5).all(axis=1)
    names = [contents.materials.materials[i].name for i in contents.face_materials]
    assert names == ["lamp" if x else "white" for x in is_lamp] and is_lamp.sum() == 2


def test_mtl_parsing():
    mtl = parse_mtl("newmtl a  # a comment\nKd 0.5\nKE 1 2 3\nillum 2\nnewmtl b\nNs 10\n")
    assert mtl["a"].reflectance == (0.5, 0.5, 0.5) and mtl["a"].emission == (1.0, 2.0, 3.0)
    assert mtl["b"].reflectance is None and mtl["b"].emission == (0.0, 0.0, 0.0)  # no Kd: refused if used
    for bad, says in (("Kd 1 2\n", "line 2"), ("Kd spectral x.rfl\n", "spectral"), ("Ke nan 0 0\n", "finite")):
        with pytest.raises(ValueError, match=says):
            parse_mtl("newmtl a\n" + bad)
    with pytest.raises(ValueError, match="before any newmtl"):
        parse_mtl("Kd 1 1 1\n")


def test_gltf_names_unnamed_and_shared_materials_by_index():
    assert _unique_names(["a", None, "a", "", "b"]) == ["material0", "material1", "material2", "material3", "b"]
    assert _unique_names(["material1", None]) == ["material0", "material1"]


# ----------------------------------------------------------------------------------------
# the same answer three ways


@pytest.fixture(scope="module")
def three_ways(tmp_path_factory):
    folder = tmp_path_factory.mktemp("three_ways")
    write_glb(folder / "room.glb")
    # trimesh gathers an OBJ's faces by material, the last material first: usemtl blocks in the
    # opposite order give the glTF primitives' order of faces, and so the same meshing
    write_obj(folder / "room.obj", order=("lamp", "white"))
    scenes = {
        "glTF": load_scene(write_scene(folder, "room.glb")),
        "OBJ + MTL": load_scene(write_scene(folder, "room.obj")),
        # the YAML's materials replace the file's by name: what a scene without file materials says
        "YAML": load_scene(write_scene(folder, "room.glb", YAML_MATERIALS)),
    }
    return {k: (scene, solve(scene)) for k, scene in scenes.items()}


def test_file_materials_are_named_after_their_object(three_ways):
    scene, _ = three_ways["glTF"]
    assert [m.name for m in scene.materials] == ["room.white", "room.lamp"]
    assert scene.objects[0].file_materials == {"white": "room.white", "lamp": "room.lamp"}
    yaml_scene, _ = three_ways["YAML"]
    assert [m.name for m in yaml_scene.materials] == ["white", "lamp"]  # the file's own are not added


def test_glTF_OBJ_and_YAML_mesh_alike_and_give_the_same_radiosity(three_ways):
    (gltf, a), (obj, b), (yaml, c) = three_ways["glTF"], three_ways["OBJ + MTL"], three_ways["YAML"]
    for scene, result in ((obj, b), (yaml, c)):
        assert torch.equal(result.mesh.vertices, a.mesh.vertices)
        assert torch.equal(result.mesh.triangles, a.mesh.triangles)
        for mine, theirs in zip(element_materials(scene, result.mesh), element_materials(gltf, a.mesh)):
            assert torch.equal(mine, theirs)
        assert result.stats["shots"] == a.stats["shots"] == 25
        assert torch.equal(result.radiosity, a.radiosity)
    assert a.radiosity.abs().max() > 0


def test_each_face_has_its_files_material(three_ways):
    scene, result = three_ways["glTF"]
    rho, emission = element_materials(scene, result.mesh)
    c = centroids(result.mesh)
    is_lamp = np.isclose(c[:, 1], 1.0) & (c[:, 0] < 0.5)
    assert is_lamp.any() and (~is_lamp).any()
    assert (emission[is_lamp] == torch.tensor(LAMP_EMISSION, dtype=torch.float64)).all()
    assert (rho[is_lamp] == 0).all() and (emission[~is_lamp] == 0).all()
    assert (rho[~is_lamp] == torch.tensor(WHITE, dtype=torch.float64)).all()
    # the ceiling's two halves meet along x = 0.5 but are separate surfaces: a surface has one material
    for s in range(len(result.mesh.surface_names)):
        assert len(torch.unique(result.mesh.material[result.mesh.surface == s])) == 1
    assert len(result.mesh.surface_names) == 7  # five walls and two ceiling halves


def test_the_emitted_power_is_the_file_emission_times_the_lamp_area(three_ways):
    for scene, result in three_ways.values():
        emitted = np.array(result.stats["emitted_power"])
        assert emitted == pytest.approx(np.array(LAMP_EMISSION) * LAMP_AREA, rel=1e-12)
        # a closed box: what is emitted is absorbed or still unshot
        parts = sum(np.array(result.stats[k]) for k in ("absorbed_power", "escaped_power", "unshot_power"))
        assert parts == pytest.approx(emitted, rel=1e-9)


# ----------------------------------------------------------------------------------------
# overrides


def test_a_yaml_material_overrides_by_name_the_objects_name_first(tmp_path):
    write_glb(tmp_path / "room.glb")
    materials = "materials:\n  white: {reflectance: 0.2}\n  room.white: {reflectance: 0.3}\n"
    scene = load_scene(write_scene(tmp_path, "room.glb", materials))
    assert scene.objects[0].file_materials == {"white": "room.white", "lamp": "room.lamp"}
    assert [m.name for m in scene.materials] == ["white", "room.white", "room.lamp"]
    rho, emission = element_materials(scene, build_mesh(scene))
    assert set(rho[:, 0].tolist()) == {0.3, 0.0}  # the unqualified white is unused here
    other = load_scene(write_scene(tmp_path, "room.glb", materials, name="box"))
    assert other.objects[0].file_materials == {"white": "white", "lamp": "box.lamp"}
    assert set(element_materials(other, build_mesh(other))[0][:, 0].tolist()) == {0.2, 0.0}


def test_an_objects_material_is_every_faces(tmp_path):
    write_glb(tmp_path / "room.glb")
    materials = "materials:\n  grey: {reflectance: 0.5, emission: 1}\n"
    scene = load_scene(write_scene(tmp_path, "room.glb", materials, material="grey"))
    assert [m.name for m in scene.materials] == ["grey"] and scene.objects[0].file_materials == {}
    assert (build_mesh(scene).material == 0).all()
    # a missing material library does not matter then: the file's materials are not read
    write_obj(tmp_path / "room.obj", mtl=None, mtllib="gone.mtl")
    scene = load_scene(write_scene(tmp_path, "room.obj", materials, material="grey"))
    assert (build_mesh(scene).material == 0).all()


def test_a_file_material_replaced_by_name_is_not_checked(tmp_path):
    write_glb(tmp_path / "room.glb", white=(1.0, 1.0, 1.0, 1.0))  # glTF's default base colour: refused alone
    scene = load_scene(write_scene(tmp_path, "room.glb", "materials:\n  white: {reflectance: 0.5}\n"))
    assert scene.objects[0].file_materials["white"] == "white"


def test_the_fingerprint_follows_the_mtl(tmp_path):
    write_obj(tmp_path / "room.obj")
    path = write_scene(tmp_path, "room.obj")
    before = checkpoint.fingerprint(load_scene(path))
    assert checkpoint.fingerprint(load_scene(path)) == before
    (tmp_path / "room.mtl").write_text(MTL.replace("Kd 0 0 0", "Kd 0.1 0 0"))
    after = checkpoint.fingerprint(load_scene(path))
    assert after["materials"] != before["materials"] and after["objects"] == before["objects"]


# ----------------------------------------------------------------------------------------
# refused, exit code 2, one paragraph naming the file and the material


def one_paragraph_error(capsys, scene, tmp_path) -> str:
    assert main([str(scene), "-o", str(tmp_path / "out"), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("hemirad: error: ") and "Traceback" not in err and "\n" not in err, err
    assert not (tmp_path / "out" / "stats.json").exists()
    return err


@pytest.mark.parametrize("case, says", [
    ("glTF reflectance 1", ["objects[0].file", "room.glb", "'white'", "reflectance", "[1.0, 1.0, 1.0]"]),
    ("MTL reflectance 1.2", ["objects[0].file", "room.obj", "'white'", "reflectance", "1.2"]),
    ("MTL without Kd", ["objects[0].file", "room.obj", "'white'", "no Kd"]),
    ("missing MTL", ["objects[0].file", "room.obj", "'room.mtl'", "not in the OBJ's folder"]),
    ("undefined usemtl", ["objects[0].file", "room.obj", "'lamp'", "does not define"]),
    ("OBJ face without a material", ["objects[0].material", "room.obj", "usemtl", "12 of the 14 faces"]),
    ("glTF primitive without a material", ["objects[0].material", "room.glb", "primitive", "2 of the 14"]),
    ("PLY without a material", ["objects[0].material", "room.ply", "only glTF and OBJ"]),
    ("negative emission", ["objects[0].file", "room.glb", "'lamp'", "emission", "-5.0"]),
])
def test_bad_file_materials_are_refused(tmp_path, capsys, case, says):
    file = {
        "glTF reflectance 1": lambda: write_glb(tmp_path / "room.glb", white=(1.0, 1.0, 1.0, 1.0)),
        "MTL reflectance 1.2": lambda: write_obj(tmp_path / "room.obj", mtl=MTL.replace(f"Kd {WHITE[0]!r}", "Kd 1.2")),
        "MTL without Kd": lambda: write_obj(tmp_path / "room.obj", mtl=MTL.replace(f"Kd {WHITE[0]!r}", "# Kd")),
        "missing MTL": lambda: write_obj(tmp_path / "room.obj", mtl=None),
        "undefined usemtl": lambda: write_obj(tmp_path / "room.obj", mtl=MTL.split("newmtl lamp")[0]),
        "OBJ face without a material": lambda: write_obj(tmp_path / "room.obj", first_usemtl=False),
        "glTF primitive without a material": lambda: write_glb(tmp_path / "room.glb", lamp_material=False),
        "PLY without a material": lambda: _write_ply(tmp_path / "room.ply"),
        "negative emission": lambda: write_glb(tmp_path / "room.glb", emissive_strength=-STRENGTH),
    }[case]()
    err = one_paragraph_error(capsys, write_scene(tmp_path, file.name), tmp_path)
    assert all(s in err for s in says), err
    assert ".yaml: objects[0]" in err


def _write_ply(path):
    import trimesh

    vertices, by_material = triangles_by_material(("white", "lamp"))
    trimesh.Trimesh(vertices, np.concatenate(list(by_material.values())), process=False).export(path)
    return path


def test_a_scene_of_file_materials_needs_no_materials_block(tmp_path):
    write_glb(tmp_path / "room.glb")
    scene = load_scene(write_scene(tmp_path, "room.glb"))
    assert "materials" not in write_scene(tmp_path, "room.glb").read_text()
    assert any(max(m.emission) > 0 for m in scene.materials)
