"""Checkpoints of a solve: written atomically, read without unpickling code, refused when
they belong to a different run.

A checkpoint is one ``torch.save`` file (a zip of tensors and a small pickle of plain
containers) holding::

    {"format": 1,
     "fingerprint": {name: value},   # what the result depends on, see ``fingerprint``
     "solver": {...},                # ProgressiveSolver.state_dict(): mesh, B, dB, ...
     "run": {"initial_elements": int, "seconds": {"mesh": s, "solve": s},
             "answer": {"refiner": {...}, "rounds": [...]}}}  # with refine.criterion answer

torch's format because the state is tensors (float64 kept bit for bit) and
``torch.load(weights_only=True)`` reads it back without executing anything a tampered
file might carry. It is written to a temporary file in the same folder and moved over the
old one with ``os.replace``, so a run killed while writing leaves the previous checkpoint.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from pathlib import Path

import torch

from hemirad.core.atomic import write_atomically
from hemirad.core.errors import HemiradInputError, bounded_repr
from hemirad.scene.meshfile import cached_contents
from hemirad.scene.model import MeshFile, Scene, resolved_reflector_resolution
from hemirad.transport import solver as solver_module

#: The version of the checkpoint file's layout (what ``write`` stores); bump it when that changes.
FORMAT = 1
FILENAME = "checkpoint.pt"

# Refine options that change which elements get split; view_surface only picks a picture.
_REFINE_FIELDS = ("pattern", "criterion", "threshold", "relative", "max_depth", "min_area", "max_elements",
                  "interior", "shadow_edges", "shots")


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _file_sha256(path: Path) -> str:
    try:
        return _sha256(Path(path).read_bytes())
    except OSError as exc:
        raise HemiradInputError(f"cannot read the mesh file {path} to fingerprint the run: "
                                f"{exc.strerror or exc}.") from exc


def _objects_digest(scene: Scene) -> str:
    """A hash of the objects as solved: every field, a mesh file by its content, not its path
    (so a moved project folder still resumes, and an edited mesh file does not). The values
    of the materials a mesh file gives are in ``fingerprint``'s materials, which lists them."""
    described = []
    for obj in scene.objects:
        d = dataclasses.asdict(obj)
        if isinstance(obj, MeshFile):
            del d["contents"]  # the arrays read at load; the file is hashed instead, below
            if not d["file_materials"]:  # as before file materials were read: the same fingerprint
                del d["file_materials"]
            contents = cached_contents(obj)
            d["path"] = contents.sha256 if contents is not None else _file_sha256(obj.path)
        described.append({"type": type(obj).__name__, **d})
    return _sha256(json.dumps(described, sort_keys=True, default=str).encode())


def fingerprint(scene: Scene) -> dict[str, object]:
    """What a solve's result depends on, keyed by the name a user knows it by.

    Materials and objects (imported mesh files by content) are hashed; the hemicube
    resolution and the refine options are kept as values, so a mismatch can say what
    changed. Stopping rules (max_shots, unshot_fraction), the camera and the ambient term
    are left out: a finished run may be continued with more shots, or shown differently.
    The checkpoint format and the solver's arithmetic version (``transport.solver.ARITHMETIC``)
    are in, so a checkpoint is not resumed by code that stores it or computes the shots
    differently; a release that changes neither resumes its predecessor's checkpoints.
    """
    materials = [dataclasses.asdict(m) for m in scene.materials]
    for described in materials:  # a material without a flux is described as before flux existed
        if described["flux"] is None:
            del described["flux"], described["colour"]
        else:  # its exitance depends on the length unit and on lumens or watts
            described.update(metres_per_unit=scene.metres_per_unit, units=scene.units)
    return {
        "checkpoint format": FORMAT,
        "solver arithmetic": solver_module.ARITHMETIC,
        "materials": _sha256(json.dumps(materials, sort_keys=True).encode()),
        "objects": _objects_digest(scene),
        "solver.resolution": scene.solver.resolution,
        "solver.reflector_resolution": resolved_reflector_resolution(scene.solver),
        "meshing.contacts": scene.meshes_contacts,
        "meshing.creases": scene.meshes_creases,
        "meshing.intersections": scene.meshing.intersections,
        **{f"solver.{k}": getattr(scene.solver, k)
           for k in ("patch_size", "overshoot", "sweeps", "shooter_split", "small_receivers")},
        **{f"refine.{k}": getattr(scene.refine, k) for k in _REFINE_FIELDS},
        # what the answer's later rounds split by (nothing to a run that does not refine so)
        "refine.importance": scene.refine_importance if scene.refines_by_answer else None,
    }


def write(path, fingerprint: dict, solver_state: dict, run: dict) -> None:
    """Write a checkpoint atomically: a temporary file beside ``path``, then ``os.replace``.

    Args:
        path: the checkpoint file, e.g. ``out/checkpoint.pt``.
        fingerprint: ``fingerprint(scene)``.
        solver_state: ``ProgressiveSolver.state_dict()``.
        run: the pipeline's own bookkeeping (initial element count, seconds so far).
    """
    path = Path(path)
    payload = {"format": FORMAT, "fingerprint": fingerprint, "solver": solver_state, "run": run}
    try:
        write_atomically(path, lambda f: torch.save(payload, f))
    except OSError as exc:
        raise HemiradInputError(f"could not write the checkpoint {path}: {exc.strerror or exc}.") from exc


def read(path, fingerprint: dict) -> tuple[dict, dict]:
    """Read a checkpoint made for this run.

    Returns:
        (solver_state, run) as given to ``write``.
    Raises:
        HemiradInputError: no file, not a checkpoint, another format, or another run (the
            message names what differs).
    """
    path = Path(path)
    restart = "Start without --resume to begin afresh (the checkpoint will be overwritten)."
    if not path.is_file():
        raise HemiradInputError(f"cannot resume: there is no checkpoint {path}. Start without --resume to "
                                f"begin afresh, and with --checkpoint-every N to write one.")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # zip, pickle and torch errors alike: the file is not usable
        raise HemiradInputError(f"cannot resume from {path}: it is not a readable hemirad checkpoint "
                                f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}). "
                                f"{restart}") from exc
    if not isinstance(payload, dict) or payload.get("format") != FORMAT or not all(
            isinstance(payload.get(k), dict) for k in ("fingerprint", "solver", "run")):
        found = payload.get("format") if isinstance(payload, dict) else None
        raise HemiradInputError(f"cannot resume from {path}: it is not a hemirad checkpoint of format {FORMAT} "
                                f"(found {found!r}). {restart}")
    differences = describe_differences(payload["fingerprint"], fingerprint)
    if differences:
        raise HemiradInputError(f"cannot resume from {path}: it was written for a different run "
                                f"({'; '.join(differences)}). Resume with the same scene and options, "
                                f"or start without --resume to begin afresh.")
    problem = content_problem(payload["solver"], payload["run"])
    if problem:
        raise HemiradInputError(f"cannot resume from {path}: its content is damaged ({problem}). {restart}")
    return payload["solver"], payload["run"]


def _tensor_problem(value, name: str, shape: tuple, dtype: torch.dtype, ok=None, what: str = "") -> str | None:
    """What is wrong with a stored tensor: its type, shape (None: any length), dtype, a
    non-finite value, or a value for which ``ok`` (elementwise) fails (``what`` says the range)."""
    if not isinstance(value, torch.Tensor):
        return f"{name} is a {type(value).__name__}, not a tensor"
    if value.dtype != dtype or value.dim() != len(shape) or any(
            n is not None and m != n for m, n in zip(value.shape, shape)):
        return f"{name} is a {tuple(value.shape)} {value.dtype} tensor, not {shape} {dtype}"
    if value.is_floating_point() and not bool(torch.isfinite(value).all()):
        return f"{name} holds NaN or infinite values"
    if ok is not None and value.numel() and not bool(ok(value).all()):
        return f"{name} holds values outside {what}"
    return None


def _number_problem(value, name: str, lo: float, integer: bool = False) -> str | None:
    kinds = (int,) if integer else (int, float)
    if isinstance(value, bool) or not isinstance(value, kinds) or not math.isfinite(value) or value < lo:
        return f"{name} is {bounded_repr(value)}, not {'an integer' if integer else 'a finite number'} >= {lo:g}"
    return None


def content_problem(state, run) -> str | None:
    """The first thing wrong with a checkpoint's solver state and run record, checked after
    unpickling (a file can unpickle safely and still hold a list where a tensor belongs, a
    negative level or NaN radiosity); None when the content is sound."""
    if not isinstance(state.get("mesh"), dict):
        return "the mesh is missing"
    mesh = state["mesh"]
    vertices, triangles = mesh.get("vertices"), mesh.get("triangles")
    problem = (_tensor_problem(vertices, "mesh.vertices", (None, 3), torch.float64)
               or _tensor_problem(triangles, "mesh.triangles", (None, 3), torch.int64))
    if problem:
        return problem
    V, T = len(vertices), len(triangles)
    names = mesh.get("surface_names")
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        return "mesh.surface_names is not a list of names"
    checks = [
        (triangles, "mesh.triangles", (T, 3), torch.int64, lambda t: (t >= 0) & (t < V), f"[0, {V})"),
        (mesh.get("surface"), "mesh.surface", (T,), torch.int64, lambda t: (t >= 0) & (t < len(names)),
         f"[0, {len(names)})"),
        (mesh.get("material"), "mesh.material", (T,), torch.int64, lambda t: t >= 0, ">= 0"),
        (mesh.get("level"), "mesh.level", (T,), torch.int64, lambda t: (t >= 0) & (t <= 16), "[0, 16]"),
        (mesh.get("edge_parents"), "mesh.edge_parents", (V, 2), torch.int64, lambda t: (t >= -1) & (t < V),
         f"[-1, {V})"),
        (state.get("reflectance"), "reflectance", (T, 3), torch.float64, lambda t: (t >= 0) & (t < 1), "[0, 1)"),
        (state.get("emission"), "emission", (T, 3), torch.float64, lambda t: t >= 0, ">= 0"),
        (state.get("radiosity"), "radiosity", (T, 3), torch.float64, None, ""),
        (state.get("unshot"), "unshot", (T, 3), torch.float64, None, ""),
        (state.get("absorbed"), "absorbed", (3,), torch.float64, None, ""),
        (state.get("escaped"), "escaped", (3,), torch.float64, None, ""),
        (state.get("emitted_power"), "emitted_power", (3,), torch.float64, lambda t: t >= 0, ">= 0"),
    ]
    for check in checks:
        problem = _tensor_problem(*check)
        if problem:
            return problem
    if not bool((state["emitted_power"] > 0).any()):
        return "emitted_power is zero: nothing emits"
    problem = _number_problem(state.get("shots"), "shots", 0, integer=True)
    refiner = state.get("refiner")
    if not problem and refiner is not None:
        if not isinstance(refiner, dict):
            return f"refiner is a {type(refiner).__name__}, not a mapping"
        problem = (_number_problem(refiner.get("splits"), "refiner.splits", 0, integer=True)
                   or _number_problem(refiner.get("threshold"), "refiner.threshold", 0))
    patches = state.get("patches")
    if not problem and patches is not None:
        problem = _patches_problem(patches, T)
    timings = state.get("timings")
    if not problem and (not isinstance(timings, dict) or not all(
            isinstance(k, str) and _number_problem(v, k, 0) is None for k, v in timings.items())):
        return "timings is not a mapping of phases to seconds"
    seconds = run.get("seconds")
    if not problem and not isinstance(seconds, dict):
        return "run.seconds is not a mapping"
    return problem or _number_problem(run.get("initial_elements"), "run.initial_elements", 1, integer=True) or \
        _number_problem(seconds.get("mesh"), "run.seconds.mesh", 0) or \
        _number_problem(seconds.get("solve"), "run.seconds.solve", 0)


def _patches_problem(patches, T: int) -> str | None:
    """What is wrong with a solver state's ``patches`` (``PatchShooters.state_dict``), or None."""
    if not isinstance(patches, dict):
        return f"patches is a {type(patches).__name__}, not a mapping"
    checks = [(patches.get("leaf"), "patches.leaf", (T,), torch.int64, lambda t: t >= 0, ">= 0"),
              (patches.get("patch"), "patches.patch", (T,), torch.int64, lambda t: t >= 0, ">= 0")]
    checks += [(patches.get(k), f"patches.{k}", (None,), torch.int64, lambda t: t >= 0, ">= 0")
               for k in ("cut_patches", "cut_sizes", "cut_nodes")]
    checks += [(patches.get(k), f"patches.{k}", (None, 3), torch.float64, None, "")
               for k in ("sent", "sent_by_leaf")]
    for check in checks:
        problem = _tensor_problem(*check)
        if problem:
            return problem
    return _number_problem(patches.get("shooter_splits"), "patches.shooter_splits", 0, integer=True)


def describe_differences(saved: dict, current: dict) -> list[str]:
    """One phrase per fingerprint entry that differs, e.g. ``"solver.resolution: 32 there, 64 here"``."""
    out = []
    for key in list(current) + [k for k in saved if k not in current]:
        a, b = saved.get(key, "missing"), current.get(key, "missing")
        if a == b:
            continue
        if key in ("materials", "objects"):
            out.append(f"the scene's {key} differ")
        else:
            out.append(f"{key}: {a!r} there, {b!r} here")
    return out


def saved_shots(path) -> int | None:
    """The shot count a checkpoint holds, or None when there is none (or it cannot be read)."""
    try:
        return int(torch.load(path, map_location="cpu", weights_only=True)["solver"]["shots"])
    except Exception:  # any unreadable file means "no usable checkpoint" here
        return None
