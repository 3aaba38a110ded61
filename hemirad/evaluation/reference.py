"""Path-traced ground truth for a scene, and the views of a solution that are compared with it.

A reference is the scene's own initial mesh (``meshing.build_mesh``: the very triangles the
solver starts from) rendered by Mitsuba 3's unbiased path tracer: every surface a one-sided
Lambertian BSDF with its material's reflectance, every emitting surface also a one-sided
area light, the camera the scene's. Mitsuba is an optional dependency (``pip install
hemirad[reference]``); only making a reference needs it, reading one does not.

Units. hemirad's radiosity B is an exitance (power per area). Mitsuba's pixels are
radiance L (power per area per steradian). A Lambertian surface of exitance B has radiance
L = B / pi in every direction, so:

* an emitter of emission E (exitance) is given to Mitsuba as radiance E / pi;
* a solution is compared as ``radiance_view``: its display radiosity (B plus the ambient
  term) as its picture shades it (``Result.shading``), drawn by ``render.render_view`` with
  no exposure and no sRGB, then divided by pi;
* both are linear RGB in the scene's units; neither depends on the unit of length.

What differs by construction is only the discretisation under test: constant radiosity per
element, its reconstruction over the surfaces (vertex fits and shading), the hemicube's
point-sampled form factors and the unshot energy. Both images box-filter each pixel (Mitsuba with a box
reconstruction filter, hemirad by supersampling), and compared views are supersampled 8x so
that edge aliasing stays well below the errors measured.
"""
from __future__ import annotations

import dataclasses
import json
import math
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from hemirad.core.errors import HemiradInputError
from hemirad.geometry.mesh import Mesh
from hemirad.lighting.photometry import emission_table
from hemirad.output import display
from hemirad.output.render import render_view
from hemirad.output.shading import Shading
from hemirad.scene.meshing import build_mesh
from hemirad.scene.model import Camera, Scene

#: Mitsuba variants tried in order: the JIT-compiled LLVM one is 10-30x faster, but needs
#: an LLVM that Dr.Jit accepts (Debian: libllvm19); the scalar one works everywhere.
VARIANTS = ("llvm_ad_rgb", "scalar_rgb")

#: Height in pixels of the stored references; the width follows the camera's aspect.
REFERENCE_HEIGHT = 128

#: Supersampling of the views compared against a reference (``render_view``'s maximum).
COMPARE_SUPERSAMPLE = 8


# ----------------------------------------------------------------------------------------
# Cameras and views of a solution (OpenGL; no Mitsuba)


def reference_camera(camera: Camera, height: int = REFERENCE_HEIGHT) -> Camera:
    """The scene's camera at ``height`` pixels high, same vertical fov and (rounded) aspect.

    The fov is vertical, so the image's vertical extent is exactly the scene camera's; a
    rounded width changes only how far the view reaches sideways, identically for both
    renderers, which always share this camera.
    """
    width = max(1, round(height * camera.width / camera.height))
    return dataclasses.replace(camera, width=width, height=height, supersample=COMPARE_SUPERSAMPLE)


def radiance_view(mesh: Mesh, shading: Shading, camera: Camera) -> np.ndarray:
    """A solution as the reference sees it: linear radiance per pixel.

    Args:
        mesh: the solved mesh (T-vertices allowed).
        shading: its display radiosity as drawn, e.g. ``Result.shading()`` (or
            ``shading.gouraud_shading(mesh, vertex_radiosity)``).
        camera: the view, normally ``reference_camera(scene.camera)``.

    Returns:
        (H, W, 3) float32 radiance L = B / pi, no exposure and no tone mapping, drawn exactly
        as ``Result.image`` draws it.
    """
    radiosity = render_view(mesh, shading.values, camera, triangles=shading.triangles, positions=shading.positions)
    return (radiosity / math.pi).astype(np.float32)


def coverage(mesh: Mesh, emitting: torch.Tensor, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Which pixels see geometry, and which see an emitter, as fractions of the pixel.

    Args:
        mesh: any mesh of the scene (only its surfaces matter).
        emitting: (T,) bool per element.
        camera: the view.

    Returns:
        geometry, emitter: (H, W) float32 in [0, 1], the supersampled fraction of each
        pixel covered by any surface, and by an emitting surface in front of everything.
    """
    emitting = torch.as_tensor(emitting, dtype=torch.float64)
    # Vertices are shared only within a surface and an emitter is a whole surface, so the
    # incident elements of an emitter's vertex all emit: the indicator is exact per vertex.
    indicator = display.vertex_values(mesh, emitting)
    colours = torch.stack([torch.ones_like(indicator), indicator, torch.zeros_like(indicator)], dim=1)
    image = render_view(mesh, colours, camera)
    return image[..., 0], image[..., 1]


# ----------------------------------------------------------------------------------------
# Stored references (numpy + JSON; no Mitsuba)


@dataclass
class Reference:
    """A path-traced image and how it was made.

    Attributes:
        radiance: (H, W, 3) float32 linear RGB radiance.
        info: JSON-able facts: scene, camera, sample count, variant, noise estimate, and a
            summary of the geometry it was made from (see ``geometry_summary``).
    """

    radiance: np.ndarray
    info: dict

    @property
    def camera(self) -> Camera:
        """The camera it was rendered with (supersampled like every compared view)."""
        return Camera(**{**self.info["camera"], "exposure": None, "supersample": COMPARE_SUPERSAMPLE})

    def save(self, folder, name: str) -> tuple[Path, Path]:
        """Write ``<name>.npz`` (float16 radiance, compressed) and ``<name>.json``."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        image_path, info_path = folder / f"{name}.npz", folder / f"{name}.json"
        # float16 keeps 11 significant bits (relative step 5e-4), far below the noise.
        np.savez_compressed(image_path, radiance=self.radiance.astype(np.float16))
        text = json.dumps(self.info, indent=2)
        # One line per list of numbers: [0.7, 0.7, 0.7] rather than a line per number.
        text = re.sub(r"\[\s+([^\[\]{}\"]*?)\s+\]", lambda m: "[" + ", ".join(
            x.strip() for x in m.group(1).split(",")) + "]", text)
        info_path.write_text(text + "\n")
        return image_path, info_path

    @classmethod
    def load(cls, folder, name: str) -> "Reference":
        folder = Path(folder)
        with np.load(folder / f"{name}.npz") as data:
            radiance = data["radiance"].astype(np.float32)
        return cls(radiance, json.loads((folder / f"{name}.json").read_text()))


def geometry_summary(scene: Scene) -> dict:
    """What a reference was made from, to notice a scene changed since: the camera, the
    materials (a flux with the exitance it makes), the triangle count and the total
    surface area (6 significant digits) of the surfaces as the scene describes them (meshed
    without contact meshing and without cutting at intersections, which leave out only what
    nothing can see, so a path tracer renders the same image either way)."""
    described = dataclasses.replace(scene, meshing=dataclasses.replace(scene.meshing, contacts=False,
                                                                       intersections=False))
    mesh = build_mesh(described)
    camera = dataclasses.asdict(scene.camera)
    emission = emission_table(scene, mesh).tolist()
    materials = {}
    for m, emitted in zip(scene.materials, emission):
        materials[m.name] = {"reflectance": list(m.reflectance), "emission": emitted}
        if m.flux is not None:
            materials[m.name]["flux"] = m.flux
    summary = {
        "triangles": mesh.num_elements,
        "surface_area": float(f"{float(mesh.areas.sum()):.6g}"),
        "materials": materials,
        "camera": {k: camera[k] for k in ("position", "look_at", "up", "fov")},
    }
    return json.loads(json.dumps(summary))  # as it reads back from the file: lists, not tuples


# ----------------------------------------------------------------------------------------
# Rendering with Mitsuba (imported lazily)


def _import_mitsuba():
    try:
        import mitsuba
    except ImportError as exc:
        raise HemiradInputError(
            "making a path-traced reference needs Mitsuba 3, an optional dependency: "
            "pip install 'hemirad[reference]' (or pip install mitsuba).") from exc
    return mitsuba


def _variant_works(variant: str) -> bool:
    """Try a variant in a child process: with an LLVM that Dr.Jit rejects, the LLVM
    variants abort the process instead of raising."""
    probe = "\n".join([
        "import mitsuba as mi",
        f"mi.set_variant({variant!r})",
        "film = {'type': 'hdrfilm', 'width': 4, 'height': 4}",
        "scene = mi.load_dict({'type': 'scene', 'integrator': {'type': 'path'}, 'shape': {'type': 'sphere'},",
        "                      'light': {'type': 'constant'}, 'sensor': {'type': 'perspective', 'film': film}})",
        "assert mi.render(scene, spp=4).shape == (4, 4, 3)",
    ])
    try:
        done = subprocess.run([sys.executable, "-c", probe], capture_output=True, timeout=300)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return done.returncode == 0


def select_variant(preferred: str | None = None) -> str:
    """Set and return a Mitsuba variant: ``preferred``, else the first of ``VARIANTS`` that runs."""
    mi = _import_mitsuba()
    candidates = (preferred,) if preferred else VARIANTS
    for variant in candidates:
        if variant in mi.variants() and _variant_works(variant):
            mi.set_variant(variant)
            return variant
    raise HemiradInputError(f"no usable Mitsuba variant among {', '.join(candidates)}; "
                            f"installed: {', '.join(mi.variants())}.")


def _rgb(value) -> dict:
    return {"type": "rgb", "value": [float(v) for v in value]}


def _mitsuba_mesh(mi, name: str, vertices: np.ndarray, triangles: np.ndarray, bsdf: dict, emitter: dict | None):
    """One Mitsuba mesh with face normals (no vertex normals: flat shading, as the
    triangles are), a BSDF and optionally an area emitter."""
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf)
    if emitter is not None:
        props["emitter"] = mi.load_dict(emitter)
    shape = mi.Mesh(name, len(vertices), len(triangles), has_vertex_normals=False,
                    has_vertex_texcoords=False, props=props)
    params = mi.traverse(shape)
    # The buffers' own types differ between the scalar and the JIT variants.
    params["vertex_positions"] = type(params["vertex_positions"])(np.ravel(vertices).astype(np.float32))
    params["faces"] = type(params["faces"])(np.ravel(triangles).astype(np.uint32))
    params.update()
    return shape


def mitsuba_scene_dict(scene: Scene, camera: Camera, mesh: Mesh | None = None, max_depth: int = -1) -> dict:
    """The scene as a Mitsuba scene dictionary (the variant must be set).

    One mesh per material, built from ``mesh`` (default: ``build_mesh(scene)``), with the
    same triangles in the same winding: Mitsuba's front side, like hemirad's, is where the
    corners run counter-clockwise, and both its ``diffuse`` BSDF and its ``area`` emitter
    are one-sided, like hemirad's elements. The path tracer has no depth limit (Russian
    roulette ends paths without bias); the film box-filters each pixel.
    """
    mi = _import_mitsuba()
    mesh = build_mesh(scene) if mesh is None else mesh
    vertices = mesh.vertices.numpy()
    # Mitsuba's look_at builds the frame (left, up, forward): its images are not mirrored
    # with respect to OpenGL's (right, up, -forward); the tests check both agree.
    sensor = {
        "type": "perspective",
        "fov": float(camera.fov),
        "fov_axis": "y",  # hemirad's fov is vertical; Mitsuba's default axis is x
        "near_clip": 1e-4 * float(mesh.vertices.abs().max()),
        "to_world": mi.ScalarTransform4f().look_at(origin=list(map(float, camera.position)),
                                                   target=list(map(float, camera.look_at)),
                                                   up=list(map(float, camera.up))),
        "film": {"type": "hdrfilm", "width": int(camera.width), "height": int(camera.height),
                 "pixel_format": "rgb", "rfilter": {"type": "box"}},
        "sampler": {"type": "independent"},
    }
    out = {"type": "scene", "integrator": {"type": "path", "max_depth": int(max_depth)}, "sensor": sensor}
    emission = emission_table(scene, mesh).tolist()  # a flux made an exitance, as the solver has it
    for index, material in enumerate(scene.materials):
        mine = (mesh.material == index).numpy()
        if not mine.any():
            continue
        triangles = mesh.triangles.numpy()[mine]
        used, compact = np.unique(triangles, return_inverse=True)
        emitter = None
        if any(e > 0 for e in emission[index]):
            emitter = {"type": "area", "radiance": _rgb([e / math.pi for e in emission[index]])}
        bsdf = {"type": "diffuse", "reflectance": _rgb(material.reflectance)}
        out[f"material_{index}"] = _mitsuba_mesh(mi, material.name, vertices[used],
                                                 compact.reshape(-1, 3), bsdf, emitter)
    return out


def render_reference(scene: Scene, camera: Camera, spp: int, seed: int = 0, spp_per_pass: int = 256,
                     mesh: Mesh | None = None, progress=None) -> np.ndarray:
    """Path-trace the scene (the Mitsuba variant must be set).

    Args:
        scene: the scene; camera: the view (normally ``reference_camera(scene.camera)``).
        spp: samples per pixel in all; rendered in passes of ``spp_per_pass`` with seeds
            ``seed * 1_000_003 + k`` (independent across passes and across ``seed``).
        progress: called with the number of samples done after each pass.

    Returns:
        (H, W, 3) float32 linear radiance, the mean of the passes.
    """
    mi = _import_mitsuba()
    loaded = mi.load_dict(mitsuba_scene_dict(scene, camera, mesh))
    total = np.zeros((int(camera.height), int(camera.width), 3), dtype=np.float64)
    done = 0
    for k in range(math.ceil(spp / spp_per_pass)):
        n = min(spp_per_pass, spp - done)
        image = np.asarray(mi.render(loaded, spp=n, seed=seed * 1_000_003 + k), dtype=np.float64)
        total += image[..., :3] * n
        done += n
        if progress is not None:
            progress(done)
    return (total / done).astype(np.float32)
