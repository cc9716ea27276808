"""Compact frames of a batch on the deformer's OpenCL device: ``protocol.compact.CompactEncoder``'s
payload before deflate (the residuals' bitmaps and non-zero values), bit for bit, computed where
the deformed frames already are (kernel ``compact.cl``), in one launch for all the sessions of a
batch; only joining its pieces and deflate stay on the host.

The encoder's NumPy passes (local frame, offset from the reference, keep-or-round, difference
along the vertex order, zigzag, bitmaps, packing the non-zero values: about a dozen passes over
the frame) become one pass of vectorised CPU code on PoCL, outside the GIL. Each work-item packs
the non-zero values of its own run of vertices where that run's values would start; after a
barrier the work-group joins the runs behind the bitmaps, so a frame's payload is one slice of
host memory (joining ~48 slices in Python cost ~10 us a frame of the GIL's time). The local frame is computed as NumPy's
float32 matmul computes it with OpenBLAS on x86-64 (a fused multiply-add chain): where a BLAS
rounds otherwise the frames stay exactly as valid (the decoder reconstructs from the integer
cells the frame carries, the tolerance holds with the encoder's margin) but may differ from the
NumPy encoder's bytes in the last bit of a rounding tie. A frame with a bad vertex (not finite,
out of the grid) or a residual over 16 bits is encoded by the NumPy encoder instead (which
refuses the first with ``ValueError``). Only for host-memory devices (``deformer.zero_copy``).

Measured on the 2-core shared machine (PoCL, 25k-vertex head, load 3-5): process CPU per frame of
8 sessions a batch, mean over the 16 streams of ``bench/compact_stream.py``, 0.357 ms against
0.405 ms for the NumPy encoder (the same bytes on every stream); in-process live batches of 10
sessions (solve + deform + encode) 0.43-0.45 against 0.48-0.53 ms. One work-item per vertex
(PoCL's vectoriser across work-items) cost 2-3x the NumPy passes; float16 code per 16 vertices
in a loop per work-item, one work-group per frame, is what pays. Deflate was then most of a
frame's cost (0.1-0.3 ms of every residual); format 2 deflates only the bitmaps and the non-zero
values, by ISA-L: process CPU per frame of 10 sessions a batch with the deflate pool, as the
server runs it, 0.25-0.30 ms against format 1's 0.32-0.48 ms (FAP, speech and mocap streams on
the 25k head, two runs alternating with the previous commit's, load 10; ``bench/compact_stream.py``
reports it as ``batch_device_cpu_ms``). Reference cells stay in slots on the device
across launches (copied once per key frame, not once per frame: 0.24 -> 0.20 ms of the calling
thread's CPU per frame, 0.375 -> 0.314 ms of the process's, 8 sessions a batch, FAP stream).
The kernel without compare masks or a 16-gather branch, its runs joined on the device: kernel
CPU 0.93-0.95x, whole ``encode_batch`` 0.95x of the previous kernel per session-frame (five FAP
files, 10 sessions a batch, load 6, ``bench/compact_kernel.py --ref``). Where the device has
AVX-512 (PoCL builds for the host CPU), each axis's bitmap of a unit is one compare into a mask
register and its non-zero values one compress into a register and one store (instead of an
or-reduction of 16 lanes and 16 scalar stores), and the vertices are de-interleaved by two
``__builtin_shufflevector`` each (PoCL's ``shuffle2`` became 24 scalar loads and inserts):
kernel CPU 0.74x, ``encode_batch`` 0.85x (joy, 10 sessions a batch, load 8); the same bytes,
and ``-DCOMPACT_PORTABLE=1`` (tested) keeps the portable code. A launch's fixed cost is most
of a small batch's: each thread's outputs and parameter rows are kept with their buffers, and
the kernel's arguments set only when one changes (pyopencl's per-call setting cost ~50 us of CPU,
fresh megabytes their page faults): kernel CPU per session-frame 0.82x at 1 session a batch,
0.93x at 10 (``bench/compact_kernel.py --ref`` of the previous commit, load 7).
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Any

import numpy as np

from ....protocol.compact import CompactEncoder, bitmap_size, rigid_motions, world_to_cells
from .host import ALIGN, HostKernel, aligned_empty

log = logging.getLogger(__name__)

#: Work-items per frame (one work-group), each a contiguous run of its units of 16 vertices.
WG = 8


@dataclass(frozen=True, slots=True)
class Residuals:
    """``DeviceCompact.residuals`` of ``J`` frames of ``V`` vertices (views of the calling
    thread's scratch memory: valid until its next ``residuals``): ``packed (J, 3 NB + 6 V)
    uint8`` (``NB = ceil(V / 8)``) each frame's payload before deflate (its bitmaps of non-zero
    values, those values' bytes 0, then their bytes 1 where flag bit 2 is set); ``nnz (J,)``
    their number; ``new_keys (J, 3, V) float32`` (row j the new key's cells where frame j is a
    key frame; None without key frames); ``flags (J,) uint32`` (bit 0: a bad vertex, bit 1: a
    residual over 16 bits: rows with either are not valid; bit 2: a zigzagged value over 8 bits,
    the frame needs both planes)."""

    packed: np.ndarray
    head: int  #: bytes of the bitmaps, 3 NB
    nnz: list[int]
    new_keys: np.ndarray | None
    flags: np.ndarray

    def payload(self, j: int, planes: int) -> tuple[int, memoryview]:
        """Frame ``j``'s ``(nnz, raw)`` as ``protocol.compact.pack_payload`` gives them, with
        ``planes`` (1 or 2) bytes a value (``raw``: a view of ``packed``)."""
        n = self.nnz[j]
        return n, self.packed[j, : self.head + planes * n].data


@dataclass(frozen=True, slots=True)
class _Scratch:
    """One thread's kernel outputs for up to ``J`` frames of ``V`` vertices, with their device
    buffers (over the same host memory): ``packed (J, 3 NB + 6 V) uint8``, ``counts (J, 3, WG)
    uint32``, and ``out`` (the staged values, then the new keys from byte ``keys_at``)."""

    J: int
    V: int
    G: int
    packed: np.ndarray
    counts: np.ndarray
    out: np.ndarray
    keys_at: int
    param: np.ndarray  #: (J, 5 + 12 G) uint32: the kernel's rows of parameters
    packed_buf: Any
    counts_buf: Any
    out_buf: Any
    param_buf: Any

    @staticmethod
    def make(kernel: HostKernel, J: int, V: int, G: int) -> _Scratch:
        packed = aligned_empty((J, 3 * bitmap_size(V) + 6 * V), np.uint8)
        counts = aligned_empty((J, 3, WG), np.uint32)
        keys_at = -(-J * 6 * V // ALIGN) * ALIGN  # bytes: the new keys start aligned
        out = aligned_empty((keys_at + J * 12 * V,), np.uint8)
        param = aligned_empty((J, 5 + 12 * G), np.uint32)
        mf = kernel._cl.mem_flags  # noqa: SLF001 - the kernel's own module
        return _Scratch(
            J,
            V,
            G,
            packed,
            counts,
            out,
            keys_at,
            param,
            kernel._host(packed, mf.WRITE_ONLY),  # noqa: SLF001
            kernel._host(counts, mf.WRITE_ONLY),  # noqa: SLF001
            kernel._host(out, mf.WRITE_ONLY),  # noqa: SLF001
            kernel._host(param, mf.READ_WRITE),  # noqa: SLF001
        )


class DeviceCompact(HostKernel):
    """Residual planes of compact frames on one OpenCL context (thread-safe)."""

    SOURCE, KERNEL, DEFINES = "compact", "compact_frames", {"WG": WG}

    def __init__(self, context: Any) -> None:
        super().__init__(context)
        self._group_bufs: dict[int, tuple[np.ndarray, Any, np.ndarray]] = {}
        # reference cells of recent frames, one slot each, kept across launches: a reference (a
        # key frame's cells, the rest mesh's) is copied in once, not once per frame (copying
        # 12 V bytes a frame cost ~35 us of memory traffic each on the 25k head)
        self._pool = np.empty((0, 3, 0), np.float32)
        self._pool_buf: Any = None
        self._slots: OrderedDict[int, tuple[np.ndarray, int]] = OrderedDict()  # id -> (ref, slot)
        self._local = threading.local()  # per calling thread: its ``_Scratch``
        self._verts: OrderedDict[int, tuple[Any, int]] = OrderedDict()  # start -> (buffer, bytes)
        self._args: tuple[Any, ...] | None = None  # the kernel's arguments as last set

    def _ref_slots(self, refs: list[np.ndarray], V: int) -> list[int]:
        """The pool slot of each reference (``(3, V) float32``), copied into a free or the least
        recently used slot when not there yet; the pool grows when the batch needs more slots.
        Call with ``_lock`` held (a kernel reading the pool runs under it too). References are
        known by identity: an encoder's reference array is replaced, never written to."""
        need = len({id(r) for r in refs})
        if self._pool.shape[2] != V or self._pool.shape[0] < need:
            cap = max(16, 2 * need, self._pool.shape[0] if self._pool.shape[2] == V else 0)
            self._pool = aligned_empty((cap, 3, V), np.float32)
            self._pool_buf = self._host(self._pool, self._cl.mem_flags.READ_ONLY)
            self._slots.clear()
        used: set[int] = set()
        out = []
        for r in refs:
            hit = self._slots.get(id(r))
            if hit is not None and hit[0] is r:
                self._slots.move_to_end(id(r))
            else:
                if hit is not None:  # a dead array's id, reused
                    del self._slots[id(r)]
                if len(self._slots) < self._pool.shape[0]:
                    taken = {slot for _, slot in self._slots.values()}
                    slot = next(k for k in range(self._pool.shape[0]) if k not in taken)
                else:  # the least recently used slot not used by this batch
                    old = next(k for k, (_, sl) in self._slots.items() if sl not in used)
                    slot = self._slots.pop(old)[1]
                self._pool[slot] = r
                self._slots[id(r)] = hit = (r, slot)
            used.add(hit[1])
            out.append(hit[1])
        return out

    def residuals(
        self,
        verts: np.ndarray,
        frame_of: list[int],
        groups: np.ndarray,
        mats: list[np.ndarray],
        refs: list[np.ndarray],
        keys: list[bool],
        keep2: list[float],
    ) -> Residuals:
        """Compact frame ``j`` of ``verts (T, V, 3)`` frame ``frame_of[j]`` (C-contiguous,
        ``ALIGN``-aligned float32), with ``mats[j] (G, 3, 4)`` and ``refs[j] (3, V)`` float32
        of ``CompactEncoder.prepare``, its encoder's ``keep2[j]`` (squared tolerance, cells), all
        of one face (``groups (V,) uint8``). A reference is copied to the device's slots once and
        then known by identity: an array passed here must not be written to afterwards (an
        encoder replaces its reference, never writes into it).
        Returns the frames' ``Residuals``."""
        if verts.dtype != np.float32 or not verts.flags.c_contiguous or verts.ctypes.data % ALIGN:
            raise ValueError("verts must be C-contiguous, aligned float32")
        J, V = len(frame_of), verts.shape[1]
        if not (J == len(mats) == len(refs) == len(keys) == len(keep2)) or groups.shape != (V,):
            raise ValueError("one matrix set, reference and key flag per frame; a group per vertex")
        nb = bitmap_size(V)
        if J == 0 or V == 0:
            packed = np.zeros((J, 3 * nb + 6 * V), np.uint8)
            return Residuals(packed, 3 * nb, [0] * J, None, np.zeros(J, np.uint32))
        if not all(0 <= f < verts.shape[0] for f in frame_of):
            raise ValueError("frame_of names a frame verts does not have")
        G = mats[0].shape[0]
        if int(groups.max()) >= G:
            raise ValueError("a vertex's group has no matrix")
        sc = self._scratch_for(J, V, G)
        packed, counts, rows = sc.packed[:J], sc.counts[:J], sc.param[:J]
        rows[:, 0] = frame_of
        rows[:, 1] = keys
        rows[:, 2] = np.asarray(keep2, np.float32).view(np.uint32)
        rows[:, 3] = 0
        rows[:, 5:] = np.asarray(mats, np.float32).reshape(J, -1).view(np.uint32)
        any_key = any(keys)
        keys_at, out = sc.keys_at, sc.out
        with self._lock:
            rows[:, 4] = self._ref_slots(refs, V)
            args = (
                np.uint32(V),
                np.uint32(G),
                self._verts_buffer(verts),
                self._groups(groups),
                sc.param_buf,
                self._pool_buf,
                sc.out_buf,
                np.uint32(keys_at // 4),
                sc.packed_buf,
                sc.counts_buf,
            )
            if self._args is None or any(
                a is not b and not (isinstance(a, np.uint32) and a == b)
                for a, b in zip(args, self._args)
            ):  # kernel arguments stay set between launches (setting all cost ~50 us of CPU)
                self._kernel.set_args(*args)
                self._args = args
            self._cl.enqueue_nd_range_kernel(
                self.queue,
                self._kernel,
                (WG, J),
                (WG, 1),  # one work-group per frame
            ).wait()
        new_keys = out[keys_at:].view(np.float32)[: J * 3 * V].reshape(J, 3, V) if any_key else None
        nnz = counts.reshape(J, -1).sum(axis=1).tolist()
        return Residuals(packed, 3 * nb, nnz, new_keys, rows[:, 3].copy())

    def _scratch_for(self, J: int, V: int, G: int) -> _Scratch:
        """This thread's ``_Scratch`` for ``J`` frames of ``V`` vertices in ``G`` groups (made,
        or grown, on first need; then reused: fresh megabytes each launch cost their page faults,
        ~20-40 us a frame, and fresh buffers their set-up)."""
        sc: _Scratch | None = getattr(self._local, "scratch", None)
        if sc is None or sc.V != V or sc.G != G or sc.J < J:
            keep = sc.J if sc is not None and (sc.V, sc.G) == (V, G) else 0
            sc = self._local.scratch = _Scratch.make(self, max(J, keep), V, G)
        return sc

    def _verts_buffer(self, verts: np.ndarray) -> Any:
        """A read-only buffer over ``verts``' memory, kept (a few, most recent first) for callers
        that pass views of one reused array (the batcher's frame buffer): a buffer over the same
        start and at least as many bytes serves again. Call with ``_lock`` held."""
        ptr, size = verts.ctypes.data, verts.nbytes
        hit = self._verts.get(ptr)
        if hit is None or hit[1] < size:
            hit = (self._host(verts, self._cl.mem_flags.READ_ONLY), size)
            self._verts[ptr] = hit  # (the buffer holds verts: its memory stays this array's)
            while len(self._verts) > 4:
                self._verts.popitem(last=False)
        self._verts.move_to_end(ptr)
        return hit[0]

    def _groups(self, groups: np.ndarray) -> Any:
        """A read-only buffer of ``groups``, kept for the face (one per array object)."""
        hit = self._group_bufs.get(id(groups))
        if hit is None or hit[0] is not groups:
            g = aligned_empty(groups.shape, np.uint8)
            g[:] = groups
            if len(self._group_bufs) > 8:
                self._group_bufs.clear()
            hit = self._group_bufs[id(groups)] = (
                groups,
                self._host(g, self._cl.mem_flags.READ_ONLY),
                g,
            )
        return hit[1]


def encode_batch(
    device: DeviceCompact,
    verts: np.ndarray,
    frames: list[tuple[CompactEncoder, int, np.ndarray, int, float, float]],
    pool: Executor | None = None,
) -> list[bytes | ValueError]:
    """Compact frames of ``verts (T, V, 3)`` (aligned, as ``DeviceCompact.residuals`` wants):
    ``frames[j] = (encoder, frame index, transforms (G, 3, 4), seq, t, wall)``, one frame per
    encoder, encoders of one face. Returns each frame's bytes (``encoder.encode``'s) or the
    ``ValueError`` its encoder raised (the encoder's state then stays as it was). With a
    ``pool``, half the frames are deflated on one of its threads (outside the GIL) while this
    thread deflates the other half (a task per frame cost ~15-20 us of CPU a frame in hand-overs:
    ``bench/compact_worker.py --compact-threads 1`` against 2)."""
    out: list[bytes | ValueError] = [ValueError()] * len(frames)
    todo: list[int] = []
    preps: list[tuple[np.ndarray, np.ndarray, np.ndarray, bool, np.ndarray]] = []
    ok = _rigid(frames)
    for j, (enc, f, T, _seq, t, _wall) in enumerate(frames):
        try:
            preps.append(enc.prepare(verts[f], T, t=t, matrices=False, checked=bool(ok[j])))
            todo.append(j)
        except ValueError as e:
            out[j] = e
    if not todo:
        return out
    first = frames[todo[0]][0]
    # all frames' maps in one call: the same bits as one by one, a tenth of the NumPy overhead
    steps = np.array([frames[j][0].step for j in todo], np.float64)[:, None, None, None]
    mats = world_to_cells(np.stack([p[1] for p in preps]), steps)
    res = device.residuals(
        verts,
        [frames[j][1] for j in todo],
        first.groups,
        list(mats),
        [p[4] for p in preps],
        [p[3] for p in preps],
        [frames[j][0].keep2 for j in todo],
    )

    def finish(n: int) -> bytes | ValueError:
        enc, f, T, seq, t, wall = frames[todo[n]]
        _, tr, _, is_key, _ = preps[n]
        try:
            flags = int(res.flags[n])
            if flags & 3:  # a bad vertex (the encoder says which) or large residuals: host
                return enc.encode(verts[f], T, seq=seq, t=t, wall=wall)
            planes = 2 if flags & 4 else 1  # a value over 8 bits: both planes
            nnz, raw = res.payload(n, planes)
            new_keys = res.new_keys
            key = new_keys[n].copy() if is_key and new_keys is not None else None
            return enc.finish(tr, is_key, planes, nnz, raw, key, seq=seq, t=t, wall=wall)
        except ValueError as e:
            return e

    def run(ns: range) -> list[bytes | ValueError]:
        return [finish(n) for n in ns]

    n = len(todo)
    if pool is not None and n > 1:  # half on the pool, half here: one hand-over, not one a frame
        later = pool.submit(run, range(n // 2, n))
        done = run(range(n // 2)) + later.result()
    else:
        done = run(range(n))
    for j, r in zip(todo, done):
        out[j] = r
    return out


def _rigid(frames: list[tuple[CompactEncoder, int, np.ndarray, int, float, float]]) -> np.ndarray:
    """``(J,) bool``: frame j's transforms are finite rigid motions, checked for the whole batch
    at once (False where they are not, or not as its encoder wants them: its ``prepare`` then
    checks, and says what is wrong)."""
    J = len(frames)
    if J == 0:
        return np.zeros(0, bool)
    g = frames[0][0].n_groups
    trs = [np.asarray(T, np.float32) for _, _, T, _, _, _ in frames]
    if any(e.n_groups != g for e, *_ in frames) or any(
        tr.ndim != 3 or tr.shape[0] < g or tr.shape[1:] != (3, 4) for tr in trs
    ):
        return np.zeros(J, bool)
    return rigid_motions(np.stack([tr[:g] for tr in trs]))


def device_compact(deformer: Any) -> DeviceCompact | None:
    """The ``DeviceCompact`` of ``deformer``'s OpenCL context (one per context, built on first
    use), or None: not a zero-copy OpenCL deformer, or a device that fails to build it."""
    return DeviceCompact.shared(deformer, "compact encoding on the device failed to build")
