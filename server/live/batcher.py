"""Deform the frames of all sessions that share an animator together, in one batch per launch.

Sessions of the same face share one ``Animator``. Each session's worker submits a face state and
awaits its encoded frames; a worker thread takes every state waiting at that moment, solves them,
deforms them with one ``deform_batch`` call (one OpenCL launch instead of one per frame: about 4x
less CPU per frame on PoCL for the 25k-vertex head) and encodes each. Under light load a batch
holds one frame and adds no delay; under heavy load batches grow by themselves.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...protocol import frames
from ..state import FaceState
from .wire import ws_binary_frame

log = logging.getLogger(__name__)

#: Most frames deformed in one launch.
MAX_BATCH = 32

Encoded = dict[str, tuple[bytes, bytes]]  # encoding -> (payload, websocket frame)


@dataclass
class _Job:
    state: FaceState
    seq: int
    wall: float
    encodings: frozenset[str]
    future: asyncio.Future
    loop: asyncio.AbstractEventLoop


def encode(
    vertices: np.ndarray, encodings: frozenset[str], *, seq: int, t: float, wall: float
) -> Encoded:
    """``{encoding: (payload, websocket frame)}``: the same bytes then serve every viewer."""
    out = {}
    for e in sorted(encodings):
        payload = frames.encode_vertices(vertices, e, seq=seq, t=t, wall=wall)
        out[e] = (payload, ws_binary_frame(payload))
    return out


class DeformBatcher:
    """Batches ``animator`` work across sessions (thread-safe; one batch runs at a time)."""

    def __init__(self, animator: Any, executor: Executor, max_batch: int = MAX_BATCH) -> None:
        self.animator = animator
        self.executor = executor
        self.max_batch = max_batch
        self._pending: list[_Job] = []
        self._lock = threading.Lock()
        self._running = False
        self.batches = 0
        self.frames = 0

    async def submit(
        self, state: FaceState, *, seq: int, wall: float, encodings: frozenset[str]
    ) -> tuple[Encoded, float]:
        """Deform and encode one state; returns its frames and the seconds of work it cost."""
        loop = asyncio.get_running_loop()
        job = _Job(state, seq, wall, encodings, loop.create_future(), loop)
        with self._lock:
            self._pending.append(job)
            start = not self._running
            self._running = True
        if start:
            self.executor.submit(self._drain)
        return await job.future

    def _drain(self) -> None:
        while True:
            with self._lock:
                jobs = self._pending[: self.max_batch]
                del self._pending[: self.max_batch]
                if not jobs:
                    self._running = False
                    return
            try:
                results = self._work(jobs)
            except Exception as e:  # the deformer failed: fail this batch, keep serving the next
                log.exception("deforming a batch of %d frames failed", len(jobs))
                results = [e] * len(jobs)
            by_loop: dict[asyncio.AbstractEventLoop, list] = {}
            for j, r in zip(jobs, results):
                by_loop.setdefault(j.loop, []).append((j.future, r))
            for loop, done in by_loop.items():  # one wake-up of the event loop per batch
                loop.call_soon_threadsafe(_settle_all, done)

    def _work(self, jobs: list[_Job]) -> list[tuple[Encoded, float] | Exception]:
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
        if len(ok) == 1:
            verts = [a.deformer.deform(*solved[0])]
        elif ok:
            D = np.stack([d for d, _ in solved])
            T = np.stack([t for _, t in solved])
            verts = a.deformer.deform_batch(D, T)
        else:
            verts = []
        dt = (time.perf_counter() - t0) / len(jobs)
        for i, v in zip(ok, verts):
            j = jobs[i]
            v = np.asarray(v, dtype=np.float32)
            results[i] = (encode(v, j.encodings, seq=j.seq, t=j.state.t, wall=j.wall), dt)
        self.batches += 1
        self.frames += len(ok)
        return results


def _settle_all(done: list[tuple[asyncio.Future, Any]]) -> None:
    for future, result in done:
        if future.done():  # the session was closed meanwhile
            continue
        if isinstance(result, Exception):
            future.set_exception(result)
        else:
            future.set_result(result)
