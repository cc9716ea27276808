"""A session owned by another node, as this node's viewers see it: frames come over pub/sub.

A ``MirrorSession`` is a ``LiveSession`` that never deforms: its viewers join and leave as on the
owner (the same ``ViewerCore``, ``Viewer`` and fan-out rules), and each frame the owner publishes
(``envelope.FRAME``) is offered to the viewers of its encoding. Frames carry the owner's generation
(``epoch``): frames of an older owner are dropped, and after a change of owner ``compact`` deltas
wait for the new owner's first key frame, so a viewer never decodes a delta against another
owner's key (a gap, never a wrong face). When this node takes the session over, the mirror becomes
the session itself (``SessionRegistry.restore``): its viewers stay connected.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

from ...protocol.compact import KEY
from ...protocol.messages import Status, parse_message
from ..live.session import FLAGS_BYTE, LiveSession, SessionSpec, Viewer
from ..state import FaceState
from . import envelope

log = logging.getLogger(__name__)


class _NoDeformer:
    """The deformer of a mirror: it has none (its frames come deformed from the owner)."""

    animator = None

    def submit_nowait(self, state: FaceState, **_: Any) -> None:  # ``ports.Deformer``'s
        raise RuntimeError("a mirror session does not deform; its owner node does")


class _ProducerElsewhere:
    """The producer slot of a mirror while the owner says a producer is connected."""

    remote = False  # it keeps the owner's session in use, not this copy

    async def end(self, code: int, error_json: str) -> None:
        return None


_THERE = _ProducerElsewhere()


class MirrorSession(LiveSession):
    """Viewers on this node of a session another node owns.

    ``wants``: called when the encodings its viewers want change (``key``: a new compact viewer).
    """

    def __init__(
        self,
        spec: SessionSpec,
        face: Any,
        wants: Callable[[MirrorSession, bool], None],
        metrics: Any = None,
    ) -> None:
        super().__init__(spec, face, _NoDeformer(), metrics)
        self._wants = wants
        self.owned = False  # this node took it over: frames are deformed here now
        self.epoch = 0
        self.need_key = True  # compact: no key frame of the current owner yet
        self.frames_relayed = 0
        self.quiet_since = time.monotonic()

    def promote(self) -> None:
        """This node takes the session over: from now on its frames are deformed here, and the
        producer slot is free for the producer that reconnects."""
        self.owned = True
        if self._producers.get("primary") is _THERE:
            del self._producers["primary"]

    def encodings(self) -> frozenset[str]:
        return frozenset(v.encoding for v in self.viewers)

    def add_viewer(self, viewer: Any) -> None:
        super().add_viewer(viewer)
        if not self.owned:
            self._wants(self, viewer.encoding == "compact")

    def remove_viewer(self, viewer: Any) -> None:
        super().remove_viewer(viewer)
        if not self.viewers:
            self.quiet_since = time.monotonic()
        if not self.owned:
            self._wants(self, False)

    def idle(self, now: float, after: float) -> bool:
        """No viewer (nor one joining) for ``after`` seconds."""
        return not self.viewers and self.joining == 0 and now - self.quiet_since >= after

    # -- what the owner sends -----------------------------------------------------------------------
    def receive(self, data: bytes) -> bool:
        """One message of the session's ``down`` channel; False once the session has ended."""
        kind = data[:1]
        if kind == envelope.FRAME:
            self.deliver(envelope.parse_frame(data))
        elif kind == envelope.TEXT:
            text = data[1:].decode("utf-8", "replace")
            if text.startswith('{"type":"status"'):  # the owner's producer, for viewers' hellos
                status = parse_message(text)
                if isinstance(status, Status):
                    if status.producer_connected:
                        self._producers["primary"] = _THERE
                    else:
                        self._producers.pop("primary", None)
            for v in self.viewers:
                v.say(text)
        elif kind == envelope.OWNER:
            self.new_owner(int(envelope.parse_json(data)["epoch"]))
        elif kind == envelope.END:
            end = envelope.parse_json(data)
            self.closed = True
            for v in list(self.viewers):
                v.end(int(end["code"]), str(end["error"]))
            return False
        return True

    def new_owner(self, epoch: int) -> None:
        """Another node owns the session now (generation ``epoch``): wait for its key frame."""
        if epoch != self.epoch:
            self.epoch, self.need_key = epoch, True
        self._wants(self, True)

    def deliver(self, f: envelope.Frame) -> None:
        """Offer one published frame to the viewers of its encoding."""
        if self.owned or f.epoch < self.epoch:
            return  # an older owner's frame (it lost its lease)
        if f.epoch > self.epoch:
            self.epoch, self.need_key = f.epoch, True
        if f.encoding == "compact":
            if not f.payload[FLAGS_BYTE] & KEY:
                if self.need_key:
                    return
            else:
                self.need_key = False
        frame = (f.payload, f.framed)
        sent = skipped = 0
        for v in list(self.viewers):
            if v.encoding != f.encoding:
                continue
            outcome = v.offer(frame)
            if outcome == Viewer.SENT:
                sent += 1
            elif outcome == Viewer.REPLACED:
                skipped += 1
        self.last_seq = f.seq
        self.frames_relayed += 1
        self.count_sent(sent)
        if skipped and self.metrics:
            self.metrics.frames_dropped.inc(skipped)
