"""Deform the frames of all sessions that share an animator together, in one batch per launch.

Sessions of the same face share one ``Animator``. Each session hands over a face state with a
callback (``submit_nowait``); a worker thread takes every state waiting at that moment, solves
them, deforms them with one ``deform_batch`` call (one OpenCL launch instead of one per frame:
about 4x less CPU per frame on PoCL for the 25k-vertex head) and writes each frame once, already
framed for WebSocket, into its own buffer.
The callbacks then run on their event loop, all of a batch in one wake-up. Under light load a
batch holds one frame and adds no delay; under heavy load batches grow by themselves.
"""

from __future__ import annotations

import asyncio
import logging
import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...protocol import frames
from ..state import FaceState
from .wire import ws_binary_header

log = logging.getLogger(__name__)

#: Most frames deformed in one launch.
MAX_BATCH = 32

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


def _framed_buffer(encoding: str, n_vertices: int) -> tuple[bytearray, int]:
    """A buffer for one WebSocket-framed vertex frame, its WebSocket header already written, and
    where the vertex frame starts in it."""
    size = frames.vertex_frame_size(encoding, n_vertices)
    head = ws_binary_header(size)
    buf = bytearray(len(head) + size)
    buf[: len(head)] = head
    return buf, len(head)


def encode_batch(
    verts: np.ndarray, jobs: list[tuple[int, float, float, frozenset[str]]]
) -> list[Encoded]:
    """Encode frames ``verts (T, V, 3) float32``; ``jobs[i] = (seq, t, wall, encodings)`` of frame i.

    Each encoding of each frame is written once, into a buffer that holds its WebSocket frame
    (header + payload): the bytes every viewer is sent, without further copies.
    """
    n = verts.shape[1]
    out: list[Encoded] = [{} for _ in jobs]
    sub = frames.HEADER_SIZE + 24  # header + offset/scale of an int16 frame
    for i, (seq, t, wall, encodings) in enumerate(jobs):
        if "i16" in encodings:  # frame by frame: one frame's temporaries stay in the CPU cache
            buf, h = _framed_buffer("i16", n)
            q, offset, scale = frames.quantize_int16_fast(verts[i])
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


def encode(
    vertices: np.ndarray, encodings: frozenset[str], *, seq: int, t: float, wall: float
) -> Encoded:
    """``{encoding: (payload, websocket frame)}`` of one frame: the same bytes serve every viewer."""
    v = np.asarray(vertices, dtype=np.float32)
    return encode_batch(v[None], [(seq, t, wall, encodings)])[0]


def batch_threads() -> int:
    """Batches of one animator worked on at once: ``FACECAST_LIVE_BATCHES``, default 1.

    Measured on 2 cores with PoCL (20 sessions): a second concurrent batch splits the frames into
    smaller launches and adds GIL contention; it cost more CPU per frame than it saved.
    """
    env = os.environ.get("FACECAST_LIVE_BATCHES")
    return max(1, int(env)) if env else 1


class DeformBatcher:
    """Batches ``animator`` work across sessions (thread-safe; up to ``parallel`` batches at once)."""

    def __init__(
        self,
        animator: Any,
        executor: Executor,
        max_batch: int = MAX_BATCH,
        parallel: int | None = None,
    ) -> None:
        self.animator = animator
        self.executor = executor
        self.max_batch = max_batch
        self._pending: list[_Job] = []
        self._lock = threading.Lock()
        self._running = 0  # drains at work
        self._delivering = False  # ``_deliver`` is running callbacks (event loop side)
        #: Batches worked on at once: the solve and the int16 encoding of one batch overlap with the
        #: deformation of the next (the deformer itself runs one launch at a time).
        self.parallel = max(1, parallel if parallel is not None else batch_threads())
        self.batches = 0
        self.frames = 0

    def submit_nowait(
        self,
        state: FaceState,
        *,
        seq: int,
        wall: float,
        encodings: frozenset[str],
        done: Callable[[Any], None],
    ) -> None:
        """Deform and encode one state; later, on this event loop, ``done((frames, seconds))`` (the
        frames and the seconds of work they cost) or ``done(exception)``. Call on the event loop."""
        job = _Job(state, seq, wall, encodings, done, asyncio.get_running_loop())
        with self._lock:
            self._pending.append(job)
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

    def _drain(self) -> None:
        while True:
            with self._lock:  # share the waiting jobs with the other drains
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

    def _work(self, jobs: list[_Job]) -> list[Any]:
        t0 = time.perf_counter()
        a = self.animator
        results: list[Any] = [None] * len(jobs)
        solved, ok = [], []
        for i, j in enumerate(jobs):
            try:  # one bad state fails alone
                solved.append(a.solve(j.state))
                ok.append(i)
            except Exception as e:
                results[i] = e
        if not ok:
            return results
        if len(ok) == 1:
            verts = np.asarray(a.deformer.deform(*solved[0]), dtype=np.float32)[None]
        else:
            D = np.stack([d for d, _ in solved])
            T = np.stack([t for _, t in solved])
            verts = np.asarray(a.deformer.deform_batch(D, T), dtype=np.float32)
        encoded = encode_batch(
            verts, [(jobs[i].seq, jobs[i].state.t, jobs[i].wall, jobs[i].encodings) for i in ok]
        )
        dt = (time.perf_counter() - t0) / len(jobs)
        for i, e in zip(ok, encoded):
            results[i] = (e, dt)
        self.batches += 1
        self.frames += len(ok)
        return results
