"""The ``ObjectMesh`` message's mesh fields, encoded and decoded.

Vertices are little-endian float32 (x, y, z) in metres, triangles little-endian uint32 vertex
indices, both base64; perception encodes, the sim (and anyone else) decodes.
"""

from __future__ import annotations

import base64

import numpy as np


def encode_mesh(vertices: np.ndarray, triangles: np.ndarray) -> dict[str, str | int]:
    """``ObjectMesh`` fields: little-endian float32 vertices, uint32 triangles (base64)."""
    v, t = np.asarray(vertices, dtype=float), np.asarray(triangles)
    if v.ndim != 2 or v.shape[1] != 3 or not np.all(np.isfinite(v)):
        raise ValueError(f"vertices must be finite with shape (v, 3), got shape {v.shape}")
    if t.ndim != 2 or t.shape[1] != 3 or (t.size and (t.min() < 0 or t.max() >= len(v))):
        raise ValueError(f"triangles must have shape (t, 3) and index 0..{len(v) - 1}")
    return {"vertices_b64": base64.b64encode(v.astype("<f4").tobytes()).decode("ascii"),
            "triangles_b64": base64.b64encode(t.astype("<u4").tobytes()).decode("ascii"),
            "vertex_count": len(v), "triangle_count": len(t)}


def _decode(d: dict, name: str, count: str, dtype: str) -> np.ndarray:
    """Field `name` (base64 of `count` rows of 3 `dtype`) as an array, shape (count, 3)."""
    n = d.get(count)  # bool is an int subclass: refused too
    if not isinstance(n, int) or isinstance(n, bool) or not 0 <= n < 2**31:
        raise ValueError(f"{count} missing or not an integer in [0, 2**31): {n!r}")
    try:
        raw = base64.b64decode(d.get(name), validate=True)  # binascii.Error is a ValueError
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name} missing or not valid base64: {e}") from e
    if len(raw) != 12 * n:
        raise ValueError(f"{name} holds {len(raw)} bytes, {count} {n} needs {12 * n}")
    return np.frombuffer(raw, dtype).reshape(n, 3)


def decode_mesh(d: dict) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`encode_mesh`: vertices (v, 3) float32, triangles (t, 3) int32."""
    v = _decode(d, "vertices_b64", "vertex_count", "<f4")
    t = _decode(d, "triangles_b64", "triangle_count", "<u4")
    if not np.all(np.isfinite(v)):
        raise ValueError("vertices_b64 contains non-finite values")
    if t.size and t.max() >= len(v):
        raise ValueError(f"triangles_b64 indexes vertex {t.max()} of {len(v)}")
    return v.astype(np.float32), t.astype(np.int32)
