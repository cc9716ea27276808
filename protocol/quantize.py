"""int16 quantisation of vertex positions for the wire (pure NumPy): the one host quantiser.

``frames.encode_vertices_i16`` and the live batcher both use ``quantize_int16``; the OpenCL
device quantiser computes the same formula bit for bit.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["dequantize_int16", "quantize_int16"]

#: Rows per block: a ``(V, 3)`` array is processed as ``(V / 256, 768)``.
_QBLOCK = 256


def quantize_int16(
    vertices: npt.ArrayLike,
) -> tuple[npt.NDArray[np.int16], npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """Per-frame int16 quantisation of ``(V, 3)`` positions for the wire.

    Returns ``(q, offset, scale)``: ``q (V, 3) int16`` (little-endian), ``offset (3,) float32``
    (the box centre), ``scale (3,) float32``, with ``vertices ~= offset + q * scale``; per axis
    ``q = clip(rint((v - offset) / scale), -32767, 32767)`` in float32, where
    ``scale = max((max - min) / 65534, 1e-12)``, so the error is at most ``scale / 2`` (half a
    step). ``V = 0`` gives an empty ``q``, offset 0 and scale 1.

    NumPy applies a ``(3,)`` offset to ``(V, 3)`` rows slowly (an inner loop of length 3), so the
    rows are viewed as blocks ``(V / 256, 768)`` with the offset and scale tiled to 768 values;
    the same float32 operations on the same values give the same bits as the plain broadcast.

    Raises:
        ValueError: ``vertices`` is not ``(V, 3)``.
    """
    v = np.ascontiguousarray(vertices, dtype="<f4")
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must be (V, 3), got {v.shape}")
    n = v.shape[0]
    if n == 0:  # nothing to quantise; any positive scale is valid
        return np.zeros((0, 3), "<i2"), np.zeros(3, np.float32), np.ones(3, np.float32)
    m = _QBLOCK
    n_main = (n // m) * m
    main, tail = v[:n_main].reshape(-1, 3 * m), v[n_main:]
    parts_lo, parts_hi = [], []
    if n_main:
        parts_lo.append(main.min(axis=0).reshape(m, 3).min(axis=0))
        parts_hi.append(main.max(axis=0).reshape(m, 3).max(axis=0))
    if len(tail):
        parts_lo.append(tail.min(axis=0))
        parts_hi.append(tail.max(axis=0))
    lo = np.min(parts_lo, axis=0).astype(np.float32)
    hi = np.max(parts_hi, axis=0).astype(np.float32)
    offset = ((lo + hi) / 2).astype(np.float32)
    scale = np.maximum((hi - lo) / np.float32(65534.0), np.float32(1e-12)).astype(np.float32)
    out = np.empty_like(v)
    if n_main:
        block = out[:n_main].reshape(-1, 3 * m)
        np.subtract(main, np.tile(offset, m), out=block)
        np.divide(block, np.tile(scale, m), out=block)
    if len(tail):
        np.subtract(tail, offset, out=out[n_main:])
        np.divide(out[n_main:], scale, out=out[n_main:])
    np.rint(out, out=out)
    np.clip(out, -32767, 32767, out=out)
    return out.astype("<i2"), offset, scale


def dequantize_int16(
    q: npt.NDArray[np.int16], offset: npt.ArrayLike, scale: npt.ArrayLike
) -> npt.NDArray[np.float32]:
    """Inverse of ``quantize_int16``: ``offset + q * scale``, ``(V, 3) float32``."""
    o = np.asarray(offset, dtype=np.float32)
    s = np.asarray(scale, dtype=np.float32)
    out: npt.NDArray[np.float32] = o + q.astype(np.float32) * s
    return out
