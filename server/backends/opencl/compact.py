"""Compact frames of a batch on the deformer's OpenCL device: ``protocol.compact.CompactEncoder``'s
residual planes, bit for bit, computed where the deformed frames already are (kernel
``compact.cl``), in one launch for all the sessions of a batch; only deflate stays on the host.

The encoder's NumPy passes (local frame, offset from the reference, keep-or-round, difference
along the vertex order, zigzag, byte planes: about a dozen passes over the frame) become one
pass of vectorised CPU code on PoCL, outside the GIL. The local frame is computed as NumPy's
float32 matmul computes it with OpenBLAS on x86-64 (a fused multiply-add chain): where a BLAS
rounds otherwise the frames stay exactly as valid (the decoder reconstructs from the integer
cells the frame carries, the tolerance holds with the encoder's margin) but may differ from the
NumPy encoder's bytes in the last bit of a rounding tie. A frame with a bad vertex (not finite,
out of the grid) or a residual over 16 bits is encoded by the NumPy encoder instead (which
refuses the first with ``ValueError``). Only for host-memory devices (``deformer.zero_copy``).
"""

from __future__ import annotations

import logging
import threading
from typing import Any, Protocol

import numpy as np

from .host import ALIGN, aligned_empty
from .kernels import build, cl_source

log = logging.getLogger(__name__)

#: Work-items per frame (one work-group), each a contiguous run of its units of 16 vertices.
WG = 8


class Encoder(Protocol):  # ``protocol.compact.CompactEncoder``'s halves used here
    groups: np.ndarray

    @property
    def keep2(self) -> float: ...

    def prepare(
        self,
        vertices: np.ndarray,
        transforms: np.ndarray | None = ...,
        *,
        t: float,
        key: bool = ...,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool, np.ndarray]: ...

    def finish(
        self,
        tr: np.ndarray,
        is_key: bool,
        planes: int,
        raw: np.ndarray,
        new_key: np.ndarray | None,
        *,
        seq: int,
        t: float,
        wall: float = ...,
    ) -> bytes: ...

    def encode(
        self,
        vertices: np.ndarray,
        transforms: np.ndarray | None = ...,
        *,
        seq: int,
        t: float,
        wall: float = ...,
        key: bool = ...,
    ) -> bytes: ...


class DeviceCompact:
    """Residual planes of compact frames on one OpenCL context (thread-safe)."""

    def __init__(self, context: Any) -> None:
        import pyopencl as cl

        self._cl = cl
        self.context = context
        self.queue = cl.CommandQueue(context)
        self._kernel = cl.Kernel(build(context, cl_source("compact"), {"WG": WG}), "compact_frames")
        self._lock = threading.Lock()

    @classmethod
    def for_deformer(cls, deformer: Any) -> DeviceCompact | None:
        """One on ``deformer``'s context if it is a zero-copy OpenCL deformer, else None."""
        ctx = getattr(deformer, "context", None)
        if ctx is None or not getattr(deformer, "zero_copy", False):
            return None
        return cls(ctx)

    def _host(self, arr: np.ndarray, flags: Any) -> Any:
        cl = self._cl
        return cl.Buffer(self.context, flags | cl.mem_flags.USE_HOST_PTR, hostbuf=arr)

    def residuals(
        self,
        verts: np.ndarray,
        frame_of: list[int],
        groups: np.ndarray,
        mats: list[np.ndarray],
        refs: list[np.ndarray],
        keys: list[bool],
        keep2: list[float],
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """Compact frame ``j`` of ``verts (T, V, 3)`` frame ``frame_of[j]`` (C-contiguous,
        ``ALIGN``-aligned float32), with ``mats[j] (G, 3, 4)`` and ``refs[j] (3, V)`` float32
        of ``CompactEncoder.prepare``, its encoder's ``keep2[j]`` (squared tolerance, cells), all
        of one face (``groups (V,) uint8``).
        Returns ``planes (J, 2, 3 V) uint8`` (zigzag bytes 0 and 1 of the residuals),
        ``new_keys (J, 3, V) float32`` (row j the new key's cells where ``keys[j]``; None
        without key frames) and ``flags (J,) uint32`` (bit 0: a bad vertex, bit 1: a residual
        over 16 bits; rows with a flag are not valid)."""
        cl = self._cl
        if verts.dtype != np.float32 or not verts.flags.c_contiguous or verts.ctypes.data % ALIGN:
            raise ValueError("verts must be C-contiguous, aligned float32")
        J, V = len(frame_of), verts.shape[1]
        if not (J == len(mats) == len(refs) == len(keys) == len(keep2)) or groups.shape != (V,):
            raise ValueError("one matrix set, reference and key flag per frame; a group per vertex")
        if J == 0 or V == 0:
            return np.zeros((J, 2, 3 * V), np.uint8), None, np.zeros(J, np.uint32)
        if not all(0 <= f < verts.shape[0] for f in frame_of):
            raise ValueError("frame_of names a frame verts does not have")
        G = mats[0].shape[0]
        m = aligned_empty((J, G, 12), np.float32)
        r = aligned_empty((J, 3, V), np.float32)
        for j in range(J):
            m[j] = mats[j].reshape(G, 12)
            r[j] = refs[j]
        idx = aligned_empty((J,), np.uint32)
        idx[:] = frame_of
        g = aligned_empty((V,), np.uint8)
        g[:] = groups
        if int(g.max()) >= G:
            raise ValueError("a vertex's group has no matrix")
        k = aligned_empty((J,), np.uint8)
        k[:] = keys
        k2 = aligned_empty((J,), np.float32)
        k2[:] = keep2
        any_key = bool(k.any())
        new_keys = aligned_empty((J if any_key else 1, 3, V), np.float32)
        planes = aligned_empty((J, 2, 3 * V), np.uint8)
        flags = aligned_empty((J,), np.uint32)
        flags[:] = 0
        mf = cl.mem_flags
        with self._lock:
            self._kernel(
                self.queue,
                (WG, J),  # one work-group per frame
                (WG, 1),
                np.uint32(V),
                np.uint32(G),
                self._host(k2, mf.READ_ONLY),
                self._host(verts, mf.READ_ONLY),
                self._host(idx, mf.READ_ONLY),
                self._host(g, mf.READ_ONLY),
                self._host(m, mf.READ_ONLY),
                self._host(r, mf.READ_ONLY),
                self._host(k, mf.READ_ONLY),
                self._host(new_keys, mf.WRITE_ONLY),
                self._host(planes, mf.WRITE_ONLY),
                self._host(flags, mf.READ_WRITE),
            ).wait()
        return planes, new_keys if any_key else None, flags


def encode_batch(
    device: DeviceCompact,
    verts: np.ndarray,
    frames: list[tuple[Encoder, int, np.ndarray, int, float, float]],
) -> list[bytes | ValueError]:
    """Compact frames of ``verts (T, V, 3)`` (aligned, as ``DeviceCompact.residuals`` wants):
    ``frames[j] = (encoder, frame index, transforms (G, 3, 4), seq, t, wall)``, one frame per
    encoder, encoders of one face. Returns each frame's bytes (``encoder.encode``'s) or the
    ``ValueError`` its encoder raised (the encoder's state then stays as it was)."""
    out: list[bytes | ValueError] = [ValueError()] * len(frames)
    todo: list[int] = []
    preps: list[tuple[np.ndarray, np.ndarray, np.ndarray, bool, np.ndarray]] = []
    for j, (enc, f, T, _seq, t, _wall) in enumerate(frames):
        try:
            preps.append(enc.prepare(verts[f], T, t=t))
            todo.append(j)
        except ValueError as e:
            out[j] = e
    if not todo:
        return out
    first = frames[todo[0]][0]
    planes, new_keys, flags = device.residuals(
        verts,
        [frames[j][1] for j in todo],
        first.groups,
        [p[2] for p in preps],
        [p[4] for p in preps],
        [p[3] for p in preps],
        [frames[j][0].keep2 for j in todo],
    )
    for n, (j, p) in enumerate(zip(todo, preps)):
        enc, f, T, seq, t, wall = frames[j]
        try:
            if flags[n]:  # a bad vertex (the encoder says which) or large residuals: on the host
                out[j] = enc.encode(verts[f], T, seq=seq, t=t, wall=wall)
                continue
            two = bool(planes[n, 1].any())
            raw = planes[n] if two else planes[n, 0]
            key = new_keys[n].copy() if p[3] and new_keys is not None else None
            out[j] = enc.finish(p[1], p[3], 2 if two else 1, raw, key, seq=seq, t=t, wall=wall)
        except ValueError as e:
            out[j] = e
    return out


_devices: dict[int, tuple[Any, DeviceCompact | None]] = {}
_devices_lock = threading.Lock()


def device_compact(deformer: Any) -> DeviceCompact | None:
    """The ``DeviceCompact`` of ``deformer``'s OpenCL context (one per context, built on first
    use), or None: not a zero-copy OpenCL deformer, or a device that fails to build it."""
    ctx = getattr(deformer, "context", None)
    if ctx is None or not getattr(deformer, "zero_copy", False):
        return None
    with _devices_lock:
        hit = _devices.get(id(ctx))
        if hit is None:
            try:
                d = DeviceCompact(ctx)
            except Exception:  # the host encoder serves instead
                log.warning("compact encoding on the device failed to build", exc_info=True)
                d = None
            hit = _devices[id(ctx)] = (ctx, d)  # holding ctx keeps id(ctx) unique
        return hit[1]
