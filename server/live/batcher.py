"""Deform the frames of all sessions that share an animator together, in one batch per launch.

Sessions of the same face share one ``Animator``. Each session hands over a face state with a
callback (``submit_nowait``); a worker thread takes every state waiting at that moment, solves
them together (``Animator.solve_batch``, vectorised), deforms them with one ``deform_batch`` call
(one OpenCL launch instead of one per frame: about 4x less CPU per frame on PoCL for the
25k-vertex head) and writes each frame once, already framed for WebSocket, into one buffer per
batch. On a host-memory OpenCL device the int16 quantisation of batches of 2 frames or more runs
on the device too (``quantize_cl``), outside the GIL; elsewhere in NumPy
(``quantize.quantize_int16``). There too, the residual planes of a batch's ``compact`` frames (2 or
more) are computed in one launch (``backends.opencl.compact``) and deflated in the same thread.
The callbacks then run on their event loop, all of a batch in one wake-up. Under light load a
batch holds one frame and adds no delay; under heavy load batches grow by themselves.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...protocol import frames, quantize
from ..backends.opencl import DeviceQuantizer, aligned_empty
from ..state import FaceState
from .settings import LiveSettings
from .wire import ws_binary_header

log = logging.getLogger(__name__)

#: Most frames deformed in one launch.
MAX_BATCH = 32
#: Fewest frames quantised on the device at once: a launch costs PoCL 0.1-0.2 ms of CPU, so a
#: single frame was 0.03-0.1 ms cheaper in NumPy (4 of 5 bench runs); from 2 frames on, the device.
DEVICE_MIN_FRAMES = 2
#: A drain about to start a batch of fewer frames than ``LiveSettings.coalesce_frames``, while more
#: sessions than that have been submitting (within ``ACTIVE_WINDOW`` seconds), waits up to
#: ``LiveSettings.coalesce_ms`` for more. A batch has a fixed cost (two OpenCL launches and the
#: solve's NumPy calls: ~0.6 ms of CPU against ~0.15 ms per frame, ``bench/compact_worker.py``),
#: so on a quiet machine, where 20 sessions at 60 fps may make batches of 1-2 frames, and on a
#: cluster node, which holds a share of a machine's sessions, waiting saves CPU.
ACTIVE_WINDOW = 0.1
#: Compact frames of a batch on the device too, when the int16 quantiser runs there
#: (``backends.opencl.compact``: the same bytes, one launch instead of a dozen NumPy passes each),
#: from this many compact frames in the batch (the frames are then deformed into the aligned
#: buffer even when the int16 quantiser would not run). With the AVX-512 kernel, the worker's job
#: per session-frame (``bench/compact_worker.py --device-min``, 25k head, load 8): 2 frames 716-748
#: against 743-809 us on the host, 3 frames 524-558 against 652-688; 1 frame stays cheaper on the
#: host (the launch's fixed cost).
DEVICE_COMPACT_MIN_FRAMES = 2

#: encoding -> (payload, websocket frame). The payload is a view into the frame's buffer: both
#: are written once and then only read (the same bytes serve every viewer).
Encoded = dict[str, tuple[memoryview, bytearray]]


@dataclass(slots=True)
class _Job:
    state: FaceState
    seq: int
    wall: float
    encodings: frozenset[str]
    done: Callable[[Any], None]
    loop: asyncio.AbstractEventLoop
    compact: Any = None  # the session's ``CompactEncoder`` when a viewer asked for ``compact``
    mix: Any = None  # the session's ``SessionMix`` when its layers are to be mixed in (``mixing``)


def _framed_buffer(encoding: str, n_vertices: int) -> tuple[bytearray, int]:
    """A buffer for one WebSocket-framed vertex frame, its WebSocket header already written, and
    where the vertex frame starts in it."""
    size = frames.vertex_frame_size(encoding, n_vertices)
    head = ws_binary_header(size)
    buf = bytearray(len(head) + size)
    buf[: len(head)] = head
    return buf, len(head)


def encode_batch(
    verts: np.ndarray,
    jobs: list[tuple[int, float, float, frozenset[str]]],
    quantizer: DeviceQuantizer | None = None,
) -> list[Encoded]:
    """Encode frames ``verts (T, V, 3) float32``; ``jobs[i] = (seq, t, wall, encodings)`` of frame i.

    Each encoding of each frame is written once, into a buffer that holds its WebSocket frame
    (header + payload): the bytes every viewer is sent, without further copies. With a
    ``quantizer`` the int16 frames are quantised on its device, all in one buffer (``verts``
    must then be C-contiguous and ``quantize_cl.ALIGN``-aligned, as the batcher's buffer is).
    """
    n = verts.shape[1]
    out: list[Encoded] = [{} for _ in jobs]
    sub = frames.HEADER_SIZE + 24  # header + offset/scale of an int16 frame
    i16 = [i for i, job in enumerate(jobs) if "i16" in job[3]]
    if i16 and quantizer is not None:
        _encode_i16_device(verts, jobs, i16, quantizer, out)
    else:
        for i in i16:  # frame by frame: one frame's temporaries stay in the CPU cache
            seq, t, wall, _ = jobs[i]
            buf, h = _framed_buffer("i16", n)
            q, offset, scale = quantize.quantize_int16(verts[i])
            buf[h : h + sub] = frames.vertex_frame_header(
                "i16", n, seq=seq, t=t, wall=wall, offset=offset, scale=scale
            )
            buf[h + sub :] = memoryview(q).cast("B")
            out[i]["i16"] = (memoryview(buf)[h:], buf)
    for i, (seq, t, wall, encodings) in enumerate(jobs):
        if "f32" in encodings:
            buf, h = _framed_buffer("f32", n)
            buf[h : h + frames.HEADER_SIZE] = frames.vertex_frame_header(
                "f32", n, seq=seq, t=t, wall=wall
            )
            v = np.ascontiguousarray(verts[i], dtype="<f4")
            buf[h + frames.HEADER_SIZE :] = memoryview(v).cast("B")
            out[i]["f32"] = (memoryview(buf)[h:], buf)
    return out


def _encode_i16_device(
    verts: np.ndarray,
    jobs: list[tuple[int, float, float, frozenset[str]]],
    which: list[int],
    quantizer: DeviceQuantizer,
    out: list[Encoded],
) -> None:
    """The int16 frames of ``jobs[i]`` for ``i`` in ``which``, quantised on the device straight
    into one buffer: frame k at ``pad + k * stride`` (WebSocket header, vertex frame header,
    then the int16 data, which starts 64-byte aligned)."""
    n = verts.shape[1]
    size = frames.vertex_frame_size("i16", n)
    head = ws_binary_header(size)
    lead = len(head) + size - 6 * n  # bytes before the int16 data
    pad = -lead % 64
    stride = -(-(pad + lead + 6 * n) // 64) * 64
    src = verts if len(which) == len(jobs) else _aligned_rows(verts, which)
    buf = aligned_empty((len(which) * stride,), np.uint8)
    offsets, scales = quantizer.quantize_into(src, buf, pad + lead, stride)
    mv = memoryview(buf)
    for k, i in enumerate(which):
        seq, t, wall, _ = jobs[i]
        a = pad + k * stride
        d = a + lead
        mv[a : a + len(head)] = head
        mv[a + len(head) : d] = frames.vertex_frame_header(
            "i16", n, seq=seq, t=t, wall=wall, offset=offsets[k], scale=scales[k]
        )
        out[i]["i16"] = (mv[a + len(head) : d + 6 * n], mv[a : d + 6 * n])


def _aligned_rows(verts: np.ndarray, rows: list[int]) -> np.ndarray:
    out = aligned_empty((len(rows),) + verts.shape[1:], np.float32)
    out[...] = verts[rows]
    return out


def encode(
    vertices: np.ndarray, encodings: frozenset[str], *, seq: int, t: float, wall: float
) -> Encoded:
    """``{encoding: (payload, websocket frame)}`` of one frame: the same bytes serve every viewer."""
    v = np.asarray(vertices, dtype=np.float32)
    return encode_batch(v[None], [(seq, t, wall, encodings)])[0]


_compact_pool: ThreadPoolExecutor | None = None
_compact_pool_lock = threading.Lock()


def _compact_executor(n: int) -> ThreadPoolExecutor | None:
    """The process's pool of ``n`` compact encoding threads, made on first use (None for one
    thread: encode inline). The encoder spends most of its time in NumPy passes and deflate,
    outside the GIL, so the frames of different sessions overlap instead of queueing behind one
    another in the drain thread."""
    global _compact_pool
    if n < 2:
        return None
    with _compact_pool_lock:
        if _compact_pool is None:
            _compact_pool = ThreadPoolExecutor(n, thread_name_prefix="facecast-compact")
        return _compact_pool


def _encode_compact(job: _Job, v: np.ndarray, T: Any) -> tuple[memoryview, bytearray] | None:
    """``job``'s frame ``v (V, 3)`` with rigid poses ``T (G, 3, 4)`` by its session's stateful
    ``CompactEncoder``, WebSocket-framed; None when that frame cannot be encoded."""
    try:
        data: bytes | ValueError = job.compact.encode(
            v, T, seq=job.seq, t=job.state.t, wall=job.wall
        )
    except ValueError as e:
        data = e
    return _frame(job, data)


def _frame(job: _Job, data: bytes | ValueError) -> tuple[memoryview, bytearray] | None:
    """A compact frame's bytes WebSocket-framed, or None (and a key asked for) when encoding it
    failed."""
    if isinstance(data, ValueError):  # this frame only (non-finite vertices); the next is a key
        log.warning("compact encoding of frame %d failed: %s", job.seq, data)
        job.compact.request_key()
        return None
    buf = bytearray(ws_binary_header(len(data)) + data)
    return memoryview(buf)[len(buf) - len(data) :], buf


def _encode_compact_device(
    deformer: Any,
    verts: np.ndarray,
    todo: list[tuple[int, _Job]],
    T: Any,
) -> list[tuple[memoryview, bytearray] | None]:
    """``_encode_compact`` of the ``todo`` frames (``(k, job)``: frame k of ``verts``, aligned),
    their residual planes computed on the deformer's OpenCL device in one launch
    (``backends.opencl.compact``: the same bytes), deflated in this thread; on the host where the
    device fails."""
    from ..backends.opencl.compact import device_compact, encode_batch

    device = device_compact(deformer)
    if device is not None:
        try:
            frames = [(j.compact, k, T[k], j.seq, j.state.t, j.wall) for k, j in todo]
            encoded = encode_batch(device, verts, frames)
            return [_frame(j, d) for (_, j), d in zip(todo, encoded)]
        except Exception:  # the host encoder serves this batch
            log.warning("compact encoding on the device failed", exc_info=True)
    return [_encode_compact(j, verts[k], T[k]) for k, j in todo]


class DeformBatcher:
    """Batches ``animator`` work across sessions (thread-safe; up to ``parallel`` batches at once)."""

    def __init__(
        self,
        animator: Any,
        executor: Executor,
        max_batch: int = MAX_BATCH,
        parallel: int | None = None,
        settings: LiveSettings | None = None,
    ) -> None:
        settings = settings or LiveSettings()
        self.settings = settings
        self.animator = animator
        self.executor = executor
        self.max_batch = max_batch
        self._pending: list[_Job] = []
        self._lock = threading.Lock()
        self._more = threading.Condition(self._lock)  # a job arrived (for a coalescing drain)
        self._waiting = 0  # drains waiting on ``_more``
        self._want = 1  # ... until this many jobs wait
        self._sources: dict[Any, float] = {}  # who submitted (session) -> when (monotonic)
        self.coalesce = settings.coalesce_seconds
        self.coalesce_frames = min(max_batch, settings.coalesce_frames)
        self._running = 0  # drains at work
        self._delivering = False  # ``_deliver`` is running callbacks (event loop side)
        #: Batches worked on at once: the solve and the int16 encoding of one batch overlap with the
        #: deformation of the next (the deformer itself runs one launch at a time).
        self.parallel = max(1, parallel if parallel is not None else settings.batch_threads)
        self.batches = 0
        self.frames = 0
        self._quantizer: DeviceQuantizer | bool | None = False  # False: not looked up yet
        self._local = threading.local()  # per drain thread: its buffer of deformed frames
        if executor is not None:  # build the quantiser before the first frames need it
            executor.submit(lambda: self.quantizer)

    def submit_nowait(
        self,
        state: FaceState,
        *,
        seq: int,
        wall: float,
        encodings: frozenset[str],
        done: Callable[[Any], None],
        compact: Any = None,
        mix: Any = None,
    ) -> None:
        """Deform and encode one state; later, on this event loop, ``done((frames, seconds))`` (the
        frames and the seconds of work they cost) or ``done(exception)``. Call on the event loop.
        ``compact``: the session's ``CompactEncoder`` (stateful: one state per session at a time).
        ``mix``: the session's ``SessionMix``: the state is mixed with its layers first, in the
        thread, together with the batch's other layered states (``mixing.mix_jobs``)."""
        job = _Job(state, seq, wall, encodings, done, asyncio.get_running_loop(), compact, mix)
        with self._lock:
            self._pending.append(job)
            if self.coalesce > 0:  # who is active: only a coalescing drain asks (and prunes)
                self._sources[getattr(done, "__self__", done)] = time.monotonic()
            if self._waiting and len(self._pending) >= self._want:
                self._more.notify()
        if not self._delivering:  # else ``_deliver`` starts the work once all callbacks have run
            self._kick()

    def _kick(self) -> None:
        """Start drains for the waiting jobs: up to ``parallel``, at most one per waiting job."""
        with self._lock:
            n = min(self.parallel - self._running, len(self._pending))
            self._running += max(0, n)
        for _ in range(n):
            self.executor.submit(self._drain)

    def _deliver(self, done: list[tuple[Callable[[Any], None], Any]]) -> None:
        """Run a batch's callbacks on their loop; the states they submit form the next batch."""
        self._delivering = True
        try:
            for callback, result in done:
                try:
                    callback(result)
                except Exception:  # one session's failure must not starve the others
                    log.exception("delivering a live frame failed")
        finally:
            self._delivering = False
            self._kick()

    async def submit(
        self, state: FaceState, *, seq: int, wall: float, encodings: frozenset[str]
    ) -> tuple[Encoded, float]:
        """``submit_nowait`` as a coroutine: returns the frames and the seconds of work."""
        future = asyncio.get_running_loop().create_future()

        def done(result: Any) -> None:
            if future.done():
                return
            if isinstance(result, BaseException):
                future.set_exception(result)
            else:
                future.set_result(result)

        self.submit_nowait(state, seq=seq, wall=wall, encodings=encodings, done=done)
        return await future

    def _coalesce(self) -> None:
        """Wait (up to ``coalesce`` seconds) until ``coalesce_frames`` jobs, or one per recently
        active source, are waiting. Call with ``_lock`` held."""
        if self.coalesce <= 0 or len(self._pending) >= self.coalesce_frames:
            return
        now = time.monotonic()
        stale = [k for k, t in self._sources.items() if now - t > ACTIVE_WINDOW]
        for k in stale:
            del self._sources[k]
        want = self._want = min(self.coalesce_frames, len(self._sources))
        deadline = now + self.coalesce
        self._waiting += 1
        try:
            while len(self._pending) < want:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._more.wait(left)
        finally:
            self._waiting -= 1

    def _drain(self) -> None:
        while True:
            with self._lock:  # share the waiting jobs with the other drains
                self._coalesce()
                take = min(self.max_batch, -(-len(self._pending) // max(1, self._running)))
                jobs = self._pending[:take]
                del self._pending[:take]
                if not jobs:
                    self._running -= 1
                    return
            try:
                results = self._work(jobs)
            except Exception as e:  # the deformer failed: fail this batch, keep serving the next
                log.exception("deforming a batch of %d frames failed", len(jobs))
                results = [e] * len(jobs)
            by_loop: dict[asyncio.AbstractEventLoop, list] = {}
            for j, r in zip(jobs, results):
                by_loop.setdefault(j.loop, []).append((j.done, r))
            for loop, done in by_loop.items():  # one wake-up of the event loop per batch
                try:
                    loop.call_soon_threadsafe(self._deliver, done)
                except RuntimeError:  # that loop is closed (server shutting down)
                    pass

    @property
    def quantizer(self) -> DeviceQuantizer | None:
        """The device quantiser of the animator's deformer (built on first use), or None."""
        if self._quantizer is False:  # (``device_quantizer`` builds one per context, locked)
            self._quantizer = device_quantizer(
                self.animator.deformer, enabled=self.settings.device_quantize
            )
        return self._quantizer  # type: ignore[return-value]

    def _frame_buffer(self, n: int) -> np.ndarray:
        """This thread's ``(n, V, 3) float32`` aligned buffer for deformed frames (reused)."""
        V = int(self.animator.face.n_vertices)
        buf = getattr(self._local, "frames", None)
        if buf is None or buf.shape[0] < n or buf.shape[1] != V:
            buf = self._local.frames = aligned_empty((max(n, self.max_batch), V, 3), np.float32)
        return buf[:n]

    def _solve(self, jobs: list[_Job], results: list[Any]) -> tuple[list[int], Any, Any]:
        """Solve the jobs' states together; a state that fails (or gives non-finite numbers)
        fails alone. Returns the indices that worked and their ``D``, ``T``."""
        a = self.animator
        todo = [i for i, r in enumerate(results) if r is None]  # (not failed before the solve)
        if not todo:
            return [], None, None
        try:
            D, T = a.solve_batch([jobs[i].state for i in todo])
            ok = todo
        except Exception:  # noqa: BLE001 - find the bad state(s): one at a time
            ok, solved = [], []
            for i in todo:
                j = jobs[i]
                try:
                    solved.append(a.solve_batch([j.state]))
                    ok.append(i)
                except Exception as e:  # noqa: BLE001 - it fails alone: its job gets the error
                    results[i] = e
            if not ok:
                return [], None, None
            D = np.concatenate([d for d, _ in solved])
            T = np.concatenate([t for _, t in solved])
        finite = np.isfinite(D).all(axis=(1, 2)) & np.isfinite(T).all(axis=(1, 2, 3))
        if not finite.all():  # the deformer would refuse the whole batch
            from ..errors import InputError

            for k in np.flatnonzero(~finite):
                results[ok[k]] = InputError(
                    "control displacements and transforms must be finite", where="face state"
                )
            ok = [i for i, f in zip(ok, finite) if f]
            D, T = D[finite], T[finite]
        return ok, D, T

    def _work(self, jobs: list[_Job]) -> list[Any]:
        t0 = time.perf_counter()
        a = self.animator
        results: list[Any] = [None] * len(jobs)
        if any(j.mix is not None for j in jobs):  # layers: mixed here, the batch at once
            from .mixing import mix_jobs

            for i, e in mix_jobs(jobs).items():
                results[i] = e
        ok, D, T = self._solve(jobs, results)
        if not ok:
            return results
        quantizer = self.quantizer if len(ok) >= DEVICE_MIN_FRAMES else None
        # compact: only for sessions with a compact viewer; a session has one state in a batch
        # at most, so its encoder is used by one thread at a time
        todo = [
            (k, jobs[i])
            for k, i in enumerate(ok)
            if jobs[i].compact is not None and "compact" in jobs[i].encodings
        ]
        on_device = len(todo) >= DEVICE_COMPACT_MIN_FRAMES and self.quantizer is not None
        if quantizer is not None or on_device:  # an aligned buffer the device reads in place
            verts = a.deformer.deform_batch(D, T, out=self._frame_buffer(len(ok)))
        elif len(ok) == 1:
            verts = np.asarray(a.deformer.deform(D[0], T[0]), dtype=np.float32)[None]
        else:
            verts = np.asarray(a.deformer.deform_batch(D, T), dtype=np.float32)
        a.add_shapes(verts, [jobs[i].state for i in ok], T)  # per-vertex shapes (mocap prior)
        meta = [(jobs[i].seq, jobs[i].state.t, jobs[i].wall, jobs[i].encodings) for i in ok]
        try:
            encoded = encode_batch(verts, meta, quantizer)
        except Exception:
            if quantizer is None:
                raise
            log.warning("int16 quantisation on the device failed; NumPy from now on", exc_info=True)
            self._quantizer = None
            encoded = encode_batch(verts, meta)
        pool = (
            _compact_executor(self.settings.compact_pool_threads)
            if len(todo) > 1 and not on_device
            else None
        )
        if on_device:  # deflated here: the pool's hand-overs cost more CPU than they overlap
            done = _encode_compact_device(a.deformer, verts, todo, T)
        elif pool is not None:
            done = list(pool.map(lambda kj: _encode_compact(kj[1], verts[kj[0]], T[kj[0]]), todo))
        else:
            done = [_encode_compact(j, verts[k], T[k]) for k, j in todo]
        for (k, _), c in zip(todo, done):
            if c is not None:
                encoded[k]["compact"] = c
        dt = (time.perf_counter() - t0) / len(jobs)
        for i, e in zip(ok, encoded):
            results[i] = (e, dt)
        self.batches += 1
        self.frames += len(ok)
        if self.batches % 500 == 0:
            log.debug(
                "live batches: %d frames in %d batches (%.1f per batch)",
                self.frames,
                self.batches,
                self.frames / self.batches,
            )
        return results


def device_quantizer(deformer: Any, enabled: bool = True) -> DeviceQuantizer | None:
    """The ``DeviceQuantizer`` for ``deformer``'s OpenCL context (one per context), or None: a
    NumPy or copying deformer, not ``enabled`` (``FACECAST_LIVE_DEVICE_QUANTIZE=0``), or a device
    that fails."""
    if not enabled:
        return None
    return DeviceQuantizer.shared(
        deformer, "int16 quantisation on the device failed to build; using NumPy"
    )
