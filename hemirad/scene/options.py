"""The loader's checks of a scene's camera, solver and refine blocks."""
from __future__ import annotations

import numpy as np

from hemirad.core.device import DEVICE_NAMES, is_device_name
from hemirad.geometry.patterns import PATTERN_CHOICES
from hemirad.scene.keys import Checker
from hemirad.scene.model import (CRITERION_NAMES, FINAL_GATHER_CHOICES, IMPORTANCE_CHOICES, RECONSTRUCTION_CHOICES,
                                 SMALL_RECEIVER_CHOICES, Camera, MeshingOptions, RefineOptions, SolverOptions)

#: The most ``solver.emitter_eyes`` levels: 256 hemicubes per emitting element.
MAX_EYE_LEVEL = 4
#: Refuse scenes whose estimated initial triangle count exceeds this.
MAX_TRIANGLES = 5_000_000
#: The most ``solver.cache_mb`` and ``refine.round_growth`` may be (the command line's bounds too).
MAX_CACHE_MB = 1e7
MAX_ROUND_GROWTH = 100.0

_CAMERA_KEYS = ("position", "look_at", "up", "fov", "width", "height", "exposure", "supersample")
_SOLVER_KEYS = ("max_shots", "unshot_fraction", "resolution", "reflector_resolution", "ambient", "device",
                "patch_size", "overshoot", "sweeps", "shooter_split", "emitter_eyes", "cache_mb", "small_receivers",
                "error_samples", "picture_error_samples", "reconstruction", "final_gather")
_MESHING_KEYS = ("contacts", "creases", "intersections")
_REFINE_KEYS = ("pattern", "criterion", "threshold", "relative", "max_depth", "min_area", "max_elements",
                "interior", "shadow_edges", "view_surface", "shots", "tolerance", "rounds", "round_growth",
                "importance")


def read_camera(check: Checker, v) -> Camera:
    m = check.section(v, "camera", check.required_what["camera"], _CAMERA_KEYS, ("position", "look_at"))
    position, look_at = check.point(m["position"], "camera.position"), check.point(m["look_at"], "camera.look_at")
    up = check.vec3(m["up"], "camera.up") if "up" in m else (0.0, 1.0, 0.0)
    view = np.subtract(look_at, position)
    if np.linalg.norm(view) <= 1e-12 * max(np.abs(position).max(), np.abs(look_at).max()):
        check.fail("camera.look_at", "a point different from camera.position", list(look_at))
    if not any(up):
        check.fail("camera.up", "a non-zero direction", list(up))
    # Compared as unit vectors: the lengths (1e-200 or 1e300) must not underflow or overflow.
    view, up_dir = view / np.abs(view).max(), np.divide(up, np.abs(up).max())
    if np.linalg.norm(np.cross(view, up_dir)) <= 1e-9 * np.linalg.norm(view) * np.linalg.norm(up_dir):
        check.fail("camera.up", "a direction not parallel to the viewing direction", list(up))
    cam = Camera(position, look_at, up)
    if "fov" in m:
        cam.fov = check.bounded(m["fov"], "camera.fov", "a vertical field of view in degrees, 0 < fov < 180",
                                lambda x: 0 < x < 180)
    for k in ("width", "height"):
        if k in m:
            setattr(cam, k, check.integer(m[k], f"camera.{k}", "a whole number of pixels, 1 to 16384", 1, 16384))
    if "supersample" in m:
        cam.supersample = check.integer(m["supersample"], "camera.supersample", "a whole number from 1 to 8", 1, 8)
    if "exposure" in m and m["exposure"] != "auto":
        cam.exposure = check.bounded(m["exposure"], "camera.exposure", "'auto' or a positive number",
                                     lambda x: x > 0)
    return cam


def read_solver(check: Checker, v) -> SolverOptions:
    m = check.section(v, "solver", "a mapping of solver options", _SOLVER_KEYS)
    opts = SolverOptions()
    if "max_shots" in m:
        opts.max_shots = check.integer(m["max_shots"], "solver.max_shots", "a whole number >= 1", 1)
    if "unshot_fraction" in m:
        opts.unshot_fraction = check.bounded(m["unshot_fraction"], "solver.unshot_fraction", "a number in [0, 1)",
                                             lambda x: 0 <= x < 1)
    if "resolution" in m:
        opts.resolution = _hemicube_resolution(check, m["resolution"], "solver.resolution",
                                               "an even whole number >= 8")
    if "reflector_resolution" in m and m["reflector_resolution"] != "auto":
        opts.reflector_resolution = _hemicube_resolution(check, m["reflector_resolution"], "solver.reflector_resolution",
                                                         "auto or an even whole number >= 8")
    if "ambient" in m:
        opts.ambient = check.boolean(m["ambient"], "solver.ambient")
    if "device" in m:
        if not is_device_name(m["device"]):
            check.fail("solver.device", "one of " + ", ".join(DEVICE_NAMES), m["device"],
                       "cuda needs PyTorch with CUDA and an NVIDIA GPU; auto picks it when there is one.")
        opts.device = m["device"]
    if "patch_size" in m:
        opts.patch_size = read_patch_size(check, m["patch_size"], "solver.patch_size")
    if "overshoot" in m:
        opts.overshoot = check.boolean(m["overshoot"], "solver.overshoot")
    if "sweeps" in m:
        opts.sweeps = check.boolean(m["sweeps"], "solver.sweeps")
    if "shooter_split" in m:
        value = m["shooter_split"]
        opts.shooter_split = None if value in (None, "none") else check.bounded(
            value, "solver.shooter_split", "a number > 0 or none", lambda x: x > 0)
    if "emitter_eyes" in m and m["emitter_eyes"] != "auto":
        opts.emitter_eyes = check.integer(m["emitter_eyes"], "solver.emitter_eyes",
                                          f"auto or a whole number from 0 to {MAX_EYE_LEVEL} (4**n eyes per emitting "
                                          "element)", 0, MAX_EYE_LEVEL)
    if "cache_mb" in m:
        opts.cache_mb = check.bounded(m["cache_mb"], "solver.cache_mb", "a number of megabytes >= 0",
                                      lambda x: 0 <= x <= MAX_CACHE_MB)
    if "small_receivers" in m:
        opts.small_receivers = check.choice(m["small_receivers"], "solver.small_receivers", SMALL_RECEIVER_CHOICES)
    if "reconstruction" in m:
        opts.reconstruction = check.choice(m["reconstruction"], "solver.reconstruction", RECONSTRUCTION_CHOICES)
    if "final_gather" in m:
        opts.final_gather = check.choice(m["final_gather"], "solver.final_gather", FINAL_GATHER_CHOICES)
    if "error_samples" in m:
        opts.error_samples = check.integer(m["error_samples"], "solver.error_samples", "a whole number >= 0", 0)
    if "picture_error_samples" in m:
        opts.picture_error_samples = check.integer(m["picture_error_samples"], "solver.picture_error_samples",
                                                   "a whole number >= 0", 0)
    return opts


def _hemicube_resolution(check: Checker, value, key: str, expected: str) -> int:
    r = check.integer(value, key, expected, 8)
    if r % 2:
        check.fail(key, expected, r, "The hemicube's side faces are resolution / 2 pixels high.")
    return r


def read_meshing(check: Checker, v) -> MeshingOptions:
    m = check.section(v, "meshing", "a mapping of meshing options", _MESHING_KEYS)
    opts = MeshingOptions()
    for key in ("contacts", "creases"):
        if key in m:
            if m[key] != "auto" and not isinstance(m[key], bool):
                check.fail(f"meshing.{key}", "true, false or auto", m[key])
            setattr(opts, key, m[key])
    if "intersections" in m:
        opts.intersections = check.boolean(m["intersections"], "meshing.intersections")
    return opts


def read_patch_size(check: Checker, value, key: str) -> float | str:
    """``auto``, ``none`` (every element shoots) or a side length > 0."""
    if value in ("auto", "none"):
        return value
    return check.bounded(value, key, "auto, none or a length > 0", lambda x: 0 < x < 1e15)


def read_refine(check: Checker, v) -> RefineOptions:
    m = check.section(v, "refine", "a mapping of refinement options", _REFINE_KEYS)
    opts = RefineOptions()
    if "pattern" in m:
        opts.pattern = check.choice(m["pattern"], "refine.pattern", PATTERN_CHOICES)
    if "criterion" in m:
        opts.criterion = check.choice(m["criterion"], "refine.criterion", CRITERION_NAMES)
    if "threshold" in m:
        opts.threshold = check.bounded(m["threshold"], "refine.threshold", "a number > 0", lambda x: x > 0)
    for key in ("relative", "interior", "shadow_edges"):
        if key in m:
            setattr(opts, key, check.boolean(m[key], f"refine.{key}"))
    if "max_depth" in m:
        opts.max_depth = check.integer(m["max_depth"], "refine.max_depth", "a whole number from 0 to 16", 0, 16)
    if "min_area" in m:
        opts.min_area = check.bounded(m["min_area"], "refine.min_area", "a number >= 0 (scene units squared)",
                                      lambda x: x >= 0)
    if "max_elements" in m:
        opts.max_elements = check.integer(m["max_elements"], "refine.max_elements",
                                          f"a whole number from 1 to {MAX_TRIANGLES:,}", 1, MAX_TRIANGLES)
    if "view_surface" in m:
        if not isinstance(m["view_surface"], str):
            check.fail("refine.view_surface", "a surface name such as room.floor", m["view_surface"])
        opts.view_surface = m["view_surface"]
    if "shots" in m:
        opts.shots = None if m["shots"] in (None, "none") else check.integer(
            m["shots"], "refine.shots", "a whole number >= 1 or none", 1)
    if "tolerance" in m:
        opts.tolerance = check.bounded(m["tolerance"], "refine.tolerance",
                                       "a relative error in (0, 1), such as 0.01", lambda x: 0 < x < 1)
    if "rounds" in m:
        opts.rounds = check.integer(m["rounds"], "refine.rounds", "a whole number from 0 to 16", 0, 16)
    if "round_growth" in m:
        opts.round_growth = check.bounded(m["round_growth"], "refine.round_growth",
                                          f"a number above 1 and at most {MAX_ROUND_GROWTH:g}, such as 2.5",
                                          lambda x: 1 < x <= MAX_ROUND_GROWTH)
    if "importance" in m:
        opts.importance = check.choice(m["importance"], "refine.importance", IMPORTANCE_CHOICES)
    if not (opts.interior or opts.shadow_edges):
        check.fail("refine.interior", "at least one of interior and shadow_edges to be true", False)
    return opts
