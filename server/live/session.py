"""One live session: its tokens, its producer, its viewers, and the deform-once/encode-once fan-out.

Frame path: the producer's connection turns input into ``FaceState``s and calls ``submit``; they
are numbered (``seq``) and queued in a short bounded queue (oldest dropped if deformation lags).
One state per session at a time goes to the ``DeformBatcher`` (deformed in a thread, encoded once
per encoding some viewer asked for); its completion callback, on the event loop, offers the same
bytes to every viewer and hands over the next state. No task per session: a frame costs the event
loop one callback, not task wake-ups. Each viewer has a one-frame slot: a newer frame replaces an
unsent one, so memory stays bounded and a slow viewer sees a gap in ``seq``.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ...protocol.compact import KEY, CompactEncoder
from ...protocol.messages import InputKind, Stats, Status, dump_message
from ..state import FaceState
from . import ports
from .mixing import SessionMix
from .ports import Deformer, DirectWriter, Outbox, ProducerSlot
from .roles import Grants

log = logging.getLogger(__name__)

#: Offset of the (low byte of the) flags in a frame header (``protocol/frames.py``: bytes 6-7, little-endian).
FLAGS_BYTE = 6

#: Face states waiting for deformation per session; beyond this the oldest is dropped. Each state
#: is complete (not a delta), so under overload it is better to skip states than to let latency
#: grow by one frame interval per queued state.
MAX_PENDING = 2
#: Control messages (status, stats) waiting for one viewer; beyond this the oldest is dropped.
MAX_CONTROL = 16
#: Seconds between ``stats`` messages to viewers.
STATS_INTERVAL = 2.0
#: Frames taken and sent are added to the Prometheus counters this many at a time (an update takes
#: a lock: once per frame it was a measurable share of the event loop's time per frame), and when
#: the producer comes or goes, at each ``stats`` message and when the session closes.
METER_EVERY = 32


class Viewer:
    """One viewer's outbox: a latest-frame slot plus a few control messages (both bounded).

    Frames and control messages leave in the order they were put in, except that a newer frame
    replaces an unsent one. With a ``direct`` sender (``wire.DirectSender``), a frame offered while
    the viewer's sender task is idle and its transport has room is written at once, without waking
    the task (that is most frames, for a viewer that keeps up).
    """

    QUEUED, REPLACED, SENT = 0, 1, 2

    def __init__(self, encoding: str, direct: DirectWriter | None = None) -> None:
        self.encoding = encoding
        self.direct = direct
        self.slot: tuple[int, tuple[bytes, bytes]] | None = (
            None  # (order, (payload, websocket frame))
        )
        self.control: deque[tuple[int, str]] = deque(maxlen=MAX_CONTROL)
        #: compact: an unsent key frame a newer delta replaced in the slot; it goes out first, so a
        #: slow viewer can decode the deltas it gets (``protocol/compact.py``).
        self.held: tuple[int, tuple[bytes, bytes]] | None = None
        self.wake = asyncio.Event()
        self.idle = False  # the sender task waits in ``next`` with nothing in flight
        self._n = 0  # order of offer/say calls
        self.sent = 0
        self.skipped = 0
        self.closing: tuple[int, str] | None = (
            None  # (close code, JSON error) when the server ends it
        )

    def offer(self, frame: tuple[bytes, bytes]) -> int:
        """Send ``frame`` now if possible (``SENT``), else put it in the slot (``QUEUED``, or
        ``REPLACED`` if it replaced an unsent one: a skipped frame)."""
        if (
            self.idle
            and self.direct is not None
            and self.slot is None
            and self.held is None
            and not self.control
            and self.closing is None
            and self.direct.try_write(frame[1])
        ):
            self.sent += 1
            return self.SENT
        slot = self.slot
        replaced = slot is not None
        if self.encoding == "compact":
            if frame[0][FLAGS_BYTE] & KEY:  # a key frame supersedes any held one
                self.held = None
            elif slot is not None and slot[1][0][FLAGS_BYTE] & KEY:
                self.held = slot
        self._n += 1
        self.slot = (self._n, frame)
        if replaced:
            self.skipped += 1
        self.wake.set()
        return self.REPLACED if replaced else self.QUEUED

    def say(self, text: str) -> None:
        self._n += 1
        self.control.append((self._n, text))
        self.wake.set()

    def end(self, code: int, error_json: str) -> None:
        self.closing = (code, error_json)
        self.wake.set()

    async def next(self) -> tuple[str, Any]:
        """The next thing to send: ``("text", str)``, ``("bytes", (payload, websocket frame))`` or
        ``("close", (code, json))``."""
        while True:
            if self.closing is not None:
                return "close", self.closing
            if self.held is not None:
                frame, self.held = self.held[1], None
                return "bytes", frame
            if self.slot is not None and (not self.control or self.slot[0] < self.control[0][0]):
                frame, self.slot = self.slot[1], None
                return "bytes", frame
            if self.control:
                return "text", self.control.popleft()[1]
            self.wake.clear()
            self.idle = True
            try:
                await self.wake.wait()
            finally:
                self.idle = False


@dataclass
class SessionSpec:
    id: str
    face: str  # the name clients use (topology URL)
    input: InputKind
    fps: float
    engine: str
    max_viewers: int
    producer_token: str
    viewer_token: str
    created: float = field(default_factory=time.time)
    tolerance: float = 0.1  # mm: largest error of a decoded vertex in the ``compact`` encoding


def compact_encoder(face: Any, tolerance_mm: float, fps: float) -> CompactEncoder:
    """A session's ``CompactEncoder`` of ``face``: ``tolerance_mm`` (mm), a key frame every 250 ms
    of frames at ``fps`` (frames/s) and of wall time."""
    return CompactEncoder(
        face.vertices,
        face.rigid_group,
        tolerance=tolerance_mm / face.mm_per_unit,
        key_interval=max(1, int(0.25 * fps)),
        key_seconds=0.25,
    )


class LiveSession:
    """A live session. Create through ``SessionRegistry.create``; all methods run on the event loop.
    Deformation and encoding run in the registry's threads, through the ``DeformBatcher`` of the
    session's animator (shared by the sessions of the same face)."""

    def __init__(
        self, spec: SessionSpec, face: Any, batcher: Deformer, metrics: Any = None
    ) -> None:
        self.spec = spec
        self.face = face
        self._batcher = batcher  # replaced when a mocap producer brings its own control vertices
        self._control_vertices: np.ndarray | None = None  # explicit controls of its animator
        self.vertex_count = int(face.vertices.shape[0])
        self.metrics = metrics
        self.viewers: set[Outbox] = set()
        self._joining = 0  # viewers being greeted (count against the limit)
        self._producers: dict[str, ProducerSlot] = {}  # role -> who holds its slot
        self.grants = Grants(spec.producer_token)  # producer tokens and their roles
        self.mix = SessionMix(self)  # secondary producers' and REST layers, mixed into each state
        #: (seq, state, wall, mix: the deform thread mixes the layers in, with its batch)
        self.pending: deque[tuple[int, FaceState, float, bool]] = deque()
        self._busy = False  # a state of this session is with the batcher
        self._in_flight = 0  # its seq
        self._encodings: dict[str, int] = {}  # encoding -> viewers that asked for it
        self.compact: Any = None  # ``CompactEncoder``, made for the first ``compact`` viewer
        self.seq = 0
        self.last_seq: int | None = None
        self._stats = dict.fromkeys(
            (
                "frames_in",
                "frames_rejected",
                "states",
                "frames_deformed",
                "frames_dropped",
                "frames_sent",
                "frames_skipped",
            ),
            0,
        )
        self._deform_total = 0.0
        self._unmetered_in = self._unmetered_sent = 0  # not yet added to the Prometheus counters
        self._last_stats = time.monotonic()
        self.closed = False
        self._status_due = False
        self.last_active = time.monotonic()  # last time a peer was seen (``busy``); for idle expiry
        #: Cluster (``server/cluster``): where frames and viewer texts also go (other nodes' viewers)
        #: and the encodings those viewers want; None and empty in one process.
        self.relay: ports.Relay | None = None
        self.remote_encodings: frozenset[str] = frozenset()

    # -- state, read-only outside this class -------------------------------------------------------
    @property
    def producer(self) -> ProducerSlot | None:
        """Who holds the primary producer slot (``claim``), or None."""
        return self._producers.get("primary")

    @property
    def producers(self) -> dict[str, ProducerSlot]:
        """A copy of role -> who holds that producer slot."""
        return dict(self._producers)

    @property
    def batcher(self) -> Deformer:
        """The deformer of the session's frames (``deform_with`` swaps it)."""
        return self._batcher

    @property
    def control_vertices(self) -> np.ndarray | None:
        """The explicit control vertices of the deformer's animator (None: the face's own)."""
        return self._control_vertices

    @property
    def joining(self) -> int:
        """Viewers being greeted (``join``): they count against the viewer limit."""
        return self._joining

    @property
    def stats(self) -> dict[str, int]:
        """A copy of the session's counters."""
        return dict(self._stats)

    def busy(self) -> bool:
        """A viewer is connected (or joining) or a client's producer is: the session is in use. A
        server-side producer (demo, playback) alone does not count: nobody asked for it any more."""
        remote = any(p.remote for p in self._producers.values())
        return bool(self.viewers) or self._joining > 0 or remote

    def idle_for(self, now: float) -> float:
        """Seconds (monotonic ``now``) since a peer was last seen; 0 while ``busy`` (seen now)."""
        if self.busy():
            self.last_active = now
            return 0.0
        return now - self.last_active

    # -- the producer slot and the control set ------------------------------------------------------
    def claim(self, producer: ProducerSlot, role: str = "primary") -> bool:
        """Take the ``role`` producer slot for ``producer`` if it is free (True); viewers hear of
        it at ``announce``. Call before any await, so that a second producer is refused."""
        if role in self._producers:
            return False
        self._producers[role] = producer
        return True

    def announce(self, producer: ProducerSlot) -> None:
        """``producer`` (holding a slot) is ready: tell the viewers."""
        if any(p is producer for p in self._producers.values()):
            self._set_producer(producer)

    def release(self, producer: ProducerSlot) -> None:
        """``producer`` leaves: free its slot if it holds one (idempotent); a secondary
        producer's layer leaves the mix."""
        for role, p in list(self._producers.items()):
            if p is producer:
                del self._producers[role]
                if role != "primary":
                    self.mix.drop(role)
                self._set_producer(None)

    def needs_controls(self, control_vertices: np.ndarray | None) -> bool:
        """True if ``control_vertices`` (an input's explicit controls) are not those deformed now."""
        cv, current = control_vertices, self._control_vertices
        return cv is not None and (current is None or not np.array_equal(cv, current))

    def deform_with(
        self, batcher: Deformer, control_vertices: np.ndarray | None
    ) -> tuple[Deformer, np.ndarray | None]:
        """Deform with ``batcher`` (an animator over ``control_vertices``) from the next state on;
        the previous pair, for ``restore``. The one place a session's control set changes."""
        previous = (self._batcher, self._control_vertices)
        self._batcher = batcher
        self._control_vertices = None if control_vertices is None else np.array(control_vertices)
        return previous

    def restore(self, previous: tuple[Deformer, np.ndarray | None]) -> None:
        """Put back a deformation ``deform_with`` replaced."""
        self._batcher, self._control_vertices = previous

    # -- viewers joining, counters ------------------------------------------------------------------
    def has_room(self) -> bool:
        """A viewer more fits under the session's limit (counting those being greeted)."""
        return len(self.viewers) + self._joining < self.spec.max_viewers

    def join(self) -> None:
        """A viewer is being greeted: it counts against the limit until ``joined``."""
        self._joining += 1

    def joined(self) -> None:
        self._joining -= 1

    def count_in(self) -> None:
        """A producer frame was taken."""
        self._stats["frames_in"] += 1
        if self.metrics:
            self._unmetered_in += 1
            if self._unmetered_in >= METER_EVERY:
                self.meter()

    def count_rejected(self) -> None:
        """A producer frame was refused (over the budget, malformed, or the driver failed)."""
        self._stats["frames_rejected"] += 1

    # -- producer side -----------------------------------------------------------------------------
    def submit(self, states: list[FaceState], wall: float, role: str = "primary") -> None:
        """Number ``states`` and queue them for deformation (oldest dropped beyond ``MAX_PENDING``).

        The primary producer's states clock the frames: with layers in the mix, each is mixed
        with them in the deform thread (states dropped under load cost no mixing). A
        secondary producer's (``role``) newest state becomes its layer.
        """
        mix = self.mix
        if role != "primary":
            if states:
                mix.put(role, states[-1])
            return
        if states:
            mix.held(states[-1])  # layers mix over it when no primary state comes
        self.queue(states, wall, mix.active)

    def queue(self, states: list[FaceState], wall: float, mix: bool = False) -> None:
        """Number ``states`` and queue them for deformation (``mix``: with the layers)."""
        for s in states:
            if len(self.pending) >= MAX_PENDING:
                self.pending.popleft()
                self._stats["frames_dropped"] += 1
                if self.metrics:
                    self.metrics.frames_dropped.inc()
            self.pending.append((self.seq, s, wall, mix))
            self.seq = (self.seq + 1) & 0xFFFFFFFF
            self._stats["states"] += 1
        if states and not self._busy:
            self._pump()

    def _set_producer(self, producer: ProducerSlot | None) -> None:
        """A producer connected (tell viewers now) or left (tell them once its frames are out)."""
        self.last_active = time.monotonic()
        self.meter()
        if producer is not None:
            self.broadcast_status()
        else:
            self._status_due = True
            if not self._busy:
                self._pump()

    # -- viewers -----------------------------------------------------------------------------------
    def add_viewer(self, viewer: Outbox) -> None:
        self.viewers.add(viewer)
        self._encodings[viewer.encoding] = self._encodings.get(viewer.encoding, 0) + 1
        if viewer.encoding == "compact":
            self._compact_encoder().request_key()  # the new viewer starts at the next frame
        if self.metrics:
            self.metrics.viewers.inc()

    def _compact_encoder(self) -> Any:
        """The session's ``CompactEncoder`` (made on first use)."""
        if self.compact is None:
            self.compact = compact_encoder(self.face, self.spec.tolerance, self.spec.fps)
        return self.compact

    def set_remote_encodings(self, encodings: frozenset[str], key: bool = False) -> None:
        """Cluster: other nodes' viewers want ``encodings`` too (``key``: a new compact viewer
        there needs a key frame). Each counts as one viewer of its encoding while wanted."""
        for enc in self.remote_encodings - encodings:
            left = self._encodings[enc] - 1
            if left:
                self._encodings[enc] = left
            else:
                del self._encodings[enc]
        for enc in encodings - self.remote_encodings:
            self._encodings[enc] = self._encodings.get(enc, 0) + 1
        self.remote_encodings = encodings
        if "compact" in encodings and (key or self.compact is None):
            self._compact_encoder().request_key()

    def remove_viewer(self, viewer: Outbox) -> None:
        self.last_active = time.monotonic()
        if viewer in self.viewers:
            self.viewers.discard(viewer)
            left = self._encodings[viewer.encoding] - 1
            if left:
                self._encodings[viewer.encoding] = left
            else:
                del self._encodings[viewer.encoding]
            self._stats["frames_sent"] += viewer.sent
            if self.metrics:
                self.metrics.viewers.dec()
                self.meter()

    def broadcast_status(self) -> None:
        text = dump_message(
            Status(
                producer_connected=bool(self._producers),
                viewers=len(self.viewers),
                last_seq=self.last_seq,
            )
        )
        for v in self.viewers:
            v.say(text)
        if self.relay is not None:
            self.relay.text(text)

    def snapshot(self) -> Stats:
        n = self._stats["frames_deformed"]
        counts: dict[str, Any] = dict(
            self._stats, frames_sent=self._stats["frames_sent"] + sum(v.sent for v in self.viewers)
        )
        return Stats.model_validate(
            counts
            | {
                "deform_ms_mean": round(1000 * self._deform_total / n, 3) if n else 0.0,
                "viewers": len(self.viewers),
                "producer_connected": bool(self._producers),
            }
        )

    # -- the frame path -----------------------------------------------------------------------------
    def _pump(self) -> None:
        """Hand the oldest pending state to the batcher (one at a time per session); with nothing
        pending, send a status that was waiting for the frames to be out."""
        while self.pending and not self.closed:
            seq, state, wall, mix = self.pending.popleft()
            if not self._encodings:
                continue  # nobody watches: skip the work, the numbering still advances
            self._busy = True
            self._in_flight = seq
            try:
                self._batcher.submit_nowait(
                    state,
                    seq=seq,
                    wall=wall,
                    encodings=frozenset(self._encodings),
                    done=self._done,
                    compact=self.compact,
                    mix=self.mix if mix else None,  # mixed with the batch, in its thread
                )
            except Exception:
                self._busy = False
                log.exception("session %s: queueing frame %d failed", self.spec.id, seq)
                self._stats["frames_dropped"] += 1
                continue
            return
        if self._status_due and not self.closed:
            self._status_due = False
            self.broadcast_status()

    def _done(self, result: Any) -> None:
        """The batcher's answer for this session's state: offer the frames, then the next state."""
        self._busy = False
        if self.closed:
            return
        try:
            if isinstance(result, BaseException):
                log.error("session %s: deforming a frame failed: %r", self.spec.id, result)
                self._stats["frames_dropped"] += 1
            else:
                self._fan_out(*result)
        finally:
            self._pump()

    def _fan_out(self, encoded: dict[str, tuple[Any, Any]], dt: float) -> None:
        self._stats["frames_deformed"] += 1
        self.last_seq = self._in_flight
        self._deform_total += dt
        if self.metrics:
            self.metrics.deform_seconds.observe(dt)
        sent_now = skipped = 0
        for viewer in list(self.viewers):
            frame = encoded.get(viewer.encoding)
            if frame is None:  # joined while we were deforming, with another encoding
                continue
            outcome = viewer.offer(frame)
            if outcome == Viewer.SENT:
                sent_now += 1
            elif outcome == Viewer.REPLACED:
                skipped += 1
        if skipped:
            self._stats["frames_skipped"] += skipped
            if self.metrics:
                self.metrics.frames_dropped.inc(skipped)
        self.count_sent(sent_now)
        if self.relay is not None:
            self.relay.frame(self._in_flight, encoded)
        now = time.monotonic()
        if now - self._last_stats >= STATS_INTERVAL:
            self._last_stats = now
            self.meter()
            text = dump_message(self.snapshot())
            for viewer in self.viewers:
                viewer.say(text)
            if self.relay is not None:
                self.relay.text(text)

    def count_sent(self, n: int) -> None:
        """Add ``n`` sent frames to the Prometheus counter (the session's own count is per viewer)."""
        if self.metrics and n:
            self._unmetered_sent += n
            if self._unmetered_sent >= METER_EVERY:
                self.meter()

    def meter(self) -> None:
        """Add the frames taken and sent since the last call to the Prometheus counters."""
        m = self.metrics
        if m:
            if self._unmetered_in:
                m.frames_in.inc(self._unmetered_in)
                self._unmetered_in = 0
            if self._unmetered_sent:
                m.frames_sent.inc(self._unmetered_sent)
                self._unmetered_sent = 0

    async def close(self, code: int, error_json: str) -> Callable[[], None] | None:
        """Stop the worker and tell every connection to end with ``code``."""
        self.closed = True
        self.meter()
        self.pending.clear()
        self.mix.stop()
        for v in list(self.viewers):
            v.end(code, error_json)
        for p in list(self._producers.values()):
            await p.end(code, error_json)
        return None
