"""Binary glTF 2.0 (``.glb``) of a solved scene's picture: triangles with per-vertex colours
and linear radiosity (a run writes the picture as drawn, ``output.shading``: each element
cut as the picture shades it, so a viewer shows what ``image.png`` shows).

One mesh, one primitive, triangles. Vertex attributes:

- ``POSITION``  float VEC3, scene units (glTF assumes metres; nothing is rescaled);
- ``COLOR_0``   float VEC3, the display colour in [0, 1]: exposure * radiosity, clipped;
- ``_RADIOSITY`` float VEC3, the linear radiosity itself (an application-specific
  attribute: the spec requires the leading underscore).

Why ``COLOR_0`` is linear and float, unlike the PLY's sRGB bytes: the glTF spec defines
vertex colours as *linear* multipliers, and viewers (Blender, three.js, model-viewer)
apply the sRGB transfer function themselves on output. Storing sRGB-encoded bytes there
would be encoded twice and look washed out; storing linear values in 8 bits would band
in the shadows, so they are float32.

The material is ``KHR_materials_unlit``: the lighting is already in the colours, and a
viewer that lit them again would darken faces turned from its own lights.

trimesh exports GLB too, but only with 8-bit colours, hence this small writer.
"""
from __future__ import annotations

import json
import struct

import numpy as np

from hemirad.output.export import _as_numpy, _write_bytes

RADIOSITY_ATTRIBUTE = "_RADIOSITY"

_FLOAT, _UINT32 = 5126, 5125  # accessor component types
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963  # buffer view targets
_GLB_MAGIC, _GLB_VERSION = 0x46546C67, 2  # b"glTF"
_CHUNK_JSON, _CHUNK_BIN = 0x4E4F534A, 0x004E4942  # b"JSON", b"BIN\0"


def _padded(data: bytes, fill: bytes) -> bytes:
    """``data`` padded to a multiple of 4 bytes (GLB chunks and accessors must be aligned)."""
    return data + fill * (-len(data) % 4)


def glb_bytes(vertices, triangles, vertex_radiosity, vertex_color) -> bytes:
    """The ``.glb`` file's content.

    Args:
        vertices: (V, 3) positions; triangles: (M, 3) indices into them, kept as they are.
        vertex_radiosity: (V, 3) linear radiosity per vertex.
        vertex_color: (V, 3) linear display colour per vertex, in [0, 1].
    Returns:
        A GLB container: a 12-byte header, a JSON chunk and a binary chunk.
    """
    positions = np.ascontiguousarray(_as_numpy(vertices), dtype="<f4").reshape(-1, 3)
    indices = np.ascontiguousarray(_as_numpy(triangles), dtype="<u4").reshape(-1, 3)
    radiosity = np.ascontiguousarray(_as_numpy(vertex_radiosity), dtype="<f4").reshape(-1, 3)
    color = np.ascontiguousarray(_as_numpy(vertex_color), dtype="<f4").reshape(-1, 3)
    V = len(positions)
    if len(radiosity) != V or len(color) != V:
        raise ValueError(f"need one radiosity and one colour per vertex ({V}), got {len(radiosity)} and {len(color)}")
    if not (np.isfinite(color).all() and color.min(initial=0.0) >= 0.0 and color.max(initial=0.0) <= 1.0):
        raise ValueError("vertex colours must be finite and in [0, 1]")

    blobs = [(positions, "VEC3", _FLOAT, _ARRAY_BUFFER), (color, "VEC3", _FLOAT, _ARRAY_BUFFER),
             (radiosity, "VEC3", _FLOAT, _ARRAY_BUFFER),
             (indices.reshape(-1), "SCALAR", _UINT32, _ELEMENT_ARRAY_BUFFER)]
    binary, views, accessors = b"", [], []
    for i, (array, kind, component, target) in enumerate(blobs):
        data = array.tobytes()
        views.append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(data), "target": target})
        accessors.append({"bufferView": i, "componentType": component, "count": len(array), "type": kind})
        binary += _padded(data, b"\0")
    if V:  # the spec requires POSITION's bounds
        accessors[0]["min"] = positions.min(axis=0).tolist()
        accessors[0]["max"] = positions.max(axis=0).tolist()

    document = {
        "asset": {"version": "2.0", "generator": "hemirad"},
        "extensionsUsed": ["KHR_materials_unlit"],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "radiosity"}],
        "meshes": [{"name": "radiosity", "primitives": [{
            "attributes": {"POSITION": 0, "COLOR_0": 1, RADIOSITY_ATTRIBUTE: 2},
            "indices": 3, "material": 0, "mode": 4}]}],
        "materials": [{"name": "precomputed lighting",
                       "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1], "metallicFactor": 0.0},
                       "extensions": {"KHR_materials_unlit": {}}}],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": len(binary)}],
    }
    text = _padded(json.dumps(document, separators=(",", ":")).encode("utf-8"), b" ")
    total = 12 + 8 + len(text) + 8 + len(binary)
    return b"".join([struct.pack("<III", _GLB_MAGIC, _GLB_VERSION, total),
                     struct.pack("<II", len(text), _CHUNK_JSON), text,
                     struct.pack("<II", len(binary), _CHUNK_BIN), binary])


def write_glb(path, vertices, triangles, vertex_radiosity, vertex_color) -> None:
    """Write ``glb_bytes(vertices, triangles, vertex_radiosity, vertex_color)`` to ``path``."""
    _write_bytes(path, glb_bytes(vertices, triangles, vertex_radiosity, vertex_color))


def display_color(vertex_radiosity, exposure: float) -> np.ndarray:
    """(V, 3) float32 ``clip(exposure * radiosity, 0, 1)``, NaN as black: linear display colour."""
    scaled = _as_numpy(vertex_radiosity).astype(np.float64) * exposure
    return np.clip(np.nan_to_num(scaled, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0).astype(np.float32)
