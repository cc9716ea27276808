"""int16 quantisation of vertex positions for the wire (pure NumPy)."""
from __future__ import annotations

import numpy as np


def quantize_int16(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-frame int16 quantisation of ``(V, 3)`` positions for the wire.

    Returns ``(q, offset, scale)``: ``q (V, 3) int16``, ``offset (3,) float32`` (the box centre),
    ``scale (3,) float32``, with ``vertices ~= offset + q * scale``. The error per axis is at most
    ``scale / 2`` (half a step), where ``scale = (max - min) / 65534``.
    """
    v = np.asarray(vertices, dtype=np.float32)
    lo, hi = v.min(axis=0), v.max(axis=0)
    offset = ((lo + hi) / 2).astype(np.float32)
    scale = np.maximum((hi - lo) / np.float32(65534.0), np.float32(1e-12)).astype(np.float32)
    q = np.clip(np.rint((v - offset) / scale), -32767, 32767).astype(np.int16)
    return q, offset, scale


def dequantize_int16(q: np.ndarray, offset: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Inverse of ``quantize_int16``: ``(V, 3) float32``."""
    return offset.astype(np.float32) + q.astype(np.float32) * scale.astype(np.float32)
