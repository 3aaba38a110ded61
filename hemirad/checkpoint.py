"""Checkpoints of a solve: written atomically, read without unpickling code, refused when
they belong to a different run.

A checkpoint is one ``torch.save`` file (a zip of tensors and a small pickle of plain
containers) holding::

    {"format": 1,
     "fingerprint": {name: value},   # what the result depends on, see ``fingerprint``
     "solver": {...},                # ProgressiveSolver.state_dict(): mesh, B, dB, ...
     "run": {"initial_elements": int, "seconds": {"mesh": s, "solve": s}}}

torch's format because the state is tensors (float64 kept bit for bit) and
``torch.load(weights_only=True)`` reads it back without executing anything a tampered
file might carry. It is written to a temporary file in the same folder and moved over the
old one with ``os.replace``, so a run killed while writing leaves the previous checkpoint.
"""
from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
from pathlib import Path

import torch

from hemirad.core.errors import HemiradInputError
from hemirad.scene.meshfile import cached_contents
from hemirad.scene.model import MeshFile, Scene
from hemirad.transport import solver as solver_module

#: The version of the checkpoint file's layout (what ``write`` stores); bump it when that changes.
FORMAT = 1
FILENAME = "checkpoint.pt"

# Refine options that change which elements get split; view_surface only picks a picture.
_REFINE_FIELDS = ("pattern", "criterion", "threshold", "relative", "max_depth", "min_area", "max_elements",
                  "interior", "shadow_edges")


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
    (so a moved project folder still resumes, and an edited mesh file does not)."""
    described = []
    for obj in scene.objects:
        d = dataclasses.asdict(obj)
        if isinstance(obj, MeshFile):
            del d["contents"]  # the arrays read at load; the file is hashed instead, below
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
    return {
        "checkpoint format": FORMAT,
        "solver arithmetic": solver_module.ARITHMETIC,
        "materials": _sha256(json.dumps(materials, sort_keys=True).encode()),
        "objects": _objects_digest(scene),
        "solver.resolution": scene.solver.resolution,
        **{f"refine.{k}": getattr(scene.refine, k) for k in _REFINE_FIELDS},
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
    # Beside the target (os.replace is atomic only within one file system); the process id
    # keeps two runs from sharing one; opened normally so the file gets the usual permissions.
    tmp = path.parent / f".{path.name}.{os.getpid()}.tmp"
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as f:
            torch.save(payload, f)
            f.flush()
            os.fsync(f.fileno())  # the data must be on disk before the rename makes it the checkpoint
        os.replace(tmp, path)
        tmp = None
    except OSError as exc:
        raise HemiradInputError(f"could not write the checkpoint {path}: {exc.strerror or exc}.") from exc
    finally:
        if tmp is not None:  # interrupted or failed: the previous checkpoint stays as it was
            with contextlib.suppress(OSError):
                tmp.unlink()


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
    return payload["solver"], payload["run"]


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
