"""Writing results: PNG images, OpenEXR (HDR) images, PLY meshes with vertex colours and
radiosity, JSON stats, CSV tables.

Output-path problems (a missing permission, a directory where a file should go) are the
user's to fix, so they surface as ``HemiradInputError`` with the path named.
"""
from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np
import OpenEXR
import torch
import trimesh
from PIL import Image

from hemirad.core.atomic import write_atomically, write_atomically_by_name
from hemirad.core.errors import HemiradInputError
from hemirad.geometry.mesh import Mesh

# Extra per-vertex PLY properties carrying the linear radiosity next to the display colour.
RADIOSITY_PROPERTIES = ("radiosity_r", "radiosity_g", "radiosity_b")


def _as_numpy(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def _write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically: a failed write leaves the previous file, or none."""
    path = Path(path)
    try:
        write_atomically(path, lambda f: f.write(data))
    except OSError as exc:
        raise HemiradInputError(f"could not write {path}: {exc.strerror or exc}.") from exc


def write_png(path, rgb8: np.ndarray) -> None:
    """Write an (H, W, 3) uint8 sRGB image as PNG."""
    rgb8 = _as_numpy(rgb8)
    if rgb8.dtype != np.uint8 or rgb8.ndim != 3 or rgb8.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) uint8 image, got {rgb8.shape} {rgb8.dtype}")
    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb8)).save(buffer, format="PNG")
    _write_bytes(path, buffer.getvalue())


def write_exr(path, linear_rgb) -> None:
    """Write an (H, W, 3) linear RGB image as OpenEXR: 32-bit float channels R, G, B, ZIP
    compressed, first row at the top, no transfer curve; any finite values (no clipping).

    OpenEXR's ``File.write`` takes a file name (a stream only in its newest releases), so
    the temporary file is handed over by name.
    """
    rgb = np.ascontiguousarray(_as_numpy(linear_rgb), dtype=np.float32)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[0] < 1 or rgb.shape[1] < 1:
        raise ValueError(f"expected an (H, W, 3) image, got {rgb.shape}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    image = OpenEXR.File(header, {"RGB": rgb})
    path = Path(path)
    try:
        write_atomically_by_name(path, lambda tmp: image.write(str(tmp)))
    except (OSError, RuntimeError) as exc:
        raise HemiradInputError(f"could not write {path}: {getattr(exc, 'strerror', None) or exc}.") from exc


def read_exr(path) -> tuple[np.ndarray, dict]:
    """(H, W, 3) float32 R, G, B of an OpenEXR file written by ``write_exr``, and the file's
    pixel type per channel (``{"R": OpenEXR.FLOAT, ...}``, from its header)."""
    image = OpenEXR.File(str(path), separate_channels=True)
    channels = image.channels()
    rgb = np.stack([np.asarray(channels[name].pixels) for name in "RGB"], axis=-1)
    return rgb, {name: channels[name].type() for name in "RGB"}


def ply_mesh(mesh: Mesh, vertex_radiosity, vertex_rgb8) -> trimesh.Trimesh:
    """The trimesh object ``write_ply`` writes: colours as RGBA, radiosity as attributes.

    Args:
        mesh: the solved mesh (vertex order and triangles are kept as they are).
        vertex_radiosity: (V, 3) linear radiosity per vertex.
        vertex_rgb8: (V, 3) uint8 display colour per vertex (sRGB, exposed).
    """
    vertices = _as_numpy(mesh.vertices).astype(np.float64)
    radiosity = _as_numpy(vertex_radiosity).astype(np.float32).reshape(-1, 3)
    rgb8 = _as_numpy(vertex_rgb8)
    if rgb8.dtype != np.uint8:
        raise ValueError(f"vertex_rgb8 must be uint8, got {rgb8.dtype}")
    rgb8 = rgb8.reshape(-1, 3)
    if not (len(radiosity) == len(rgb8) == len(vertices)):
        raise ValueError(
            f"need one radiosity and one colour per vertex ({len(vertices)}), "
            f"got {len(radiosity)} and {len(rgb8)}")
    rgba = np.concatenate([rgb8, np.full((len(rgb8), 1), 255, dtype=np.uint8)], axis=1)
    # process=False: merging duplicate positions would join surfaces that are kept apart
    # on purpose (creases, objects) and reorder vertices away from the solver's indices.
    out = trimesh.Trimesh(
        vertices=vertices,
        faces=_as_numpy(mesh.triangles).astype(np.int64),
        vertex_colors=rgba,
        process=False,
        validate=False,
    )
    for channel, name in enumerate(RADIOSITY_PROPERTIES):
        out.vertex_attributes[name] = np.ascontiguousarray(radiosity[:, channel])
    return out


def write_ply(path, mesh: Mesh, vertex_radiosity, vertex_rgb8) -> None:
    """Write a binary PLY with per-vertex colours and linear radiosity.

    Vertex properties: x, y, z (float32), red, green, blue, alpha (uint8; Blender and
    trimesh read these as vertex colours) and radiosity_r, radiosity_g, radiosity_b
    (float32, linear). Faces are the mesh's triangles, in order.
    """
    data = ply_mesh(mesh, vertex_radiosity, vertex_rgb8).export(
        file_type="ply", encoding="binary", include_attributes=True)
    _write_bytes(path, data)


def read_ply_radiosity(path) -> np.ndarray:
    """(V, 3) float32 radiosity read back from a PLY written by ``write_ply``.

    trimesh does not turn unknown PLY properties into ``vertex_attributes`` when loading;
    it keeps the parsed vertex records in ``metadata['_ply_raw']``.
    """
    loaded = trimesh.load(path, file_type="ply", process=False)
    records = loaded.metadata["_ply_raw"]["vertex"]["data"]
    return np.stack([np.asarray(records[name], dtype=np.float32) for name in RADIOSITY_PROPERTIES], axis=1)


def _plain(value, key: str):
    """``value`` as JSON-native types; numpy/torch scalars become Python numbers."""
    if isinstance(value, dict):
        return {str(k): _plain(v, f"{key}.{k}" if key else str(k)) for k, v in value.items()}
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    if isinstance(value, np.ndarray):
        value = value.item() if value.ndim == 0 else value.tolist()
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, (list, tuple)):
        return [_plain(v, f"{key}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"stats value {key} is {value}; JSON has no representation for it")
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    raise TypeError(f"stats value {key} has type {type(value).__name__}, which JSON cannot hold")


def write_stats(path, stats: dict) -> None:
    """Write run statistics as JSON (indent 2, sorted keys, trailing newline).

    numpy and torch scalars (and small arrays) become Python numbers (lists); NaN and
    infinities are refused with the offending key named, since JSON cannot hold them.
    """
    text = json.dumps(_plain(stats, ""), indent=2, sort_keys=True, allow_nan=False)
    _write_bytes(path, (text + "\n").encode("utf-8"))


def write_csv(path, header, rows) -> None:
    """Write a CSV table (a header line, then one line per row of strings), atomically."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    _write_bytes(path, buffer.getvalue().encode("utf-8"))
