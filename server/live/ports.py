"""The seams of the live path, as ``typing.Protocol`` types: what a session needs of its deformer,
its producer and its viewers' transport, and what a producer connection needs of its input.

Structural types only (no behaviour): the real classes (``DeformBatcher``, ``inputs.FapInput``...,
``api.transport.DirectSender``) satisfy them without naming them, and a test can pass a small
stand-in of its own.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from ...protocol import frames
from ...protocol.messages import FapMessage
from ..state import FaceState


class Deformer(Protocol):
    """Deforms and encodes one face state off the event loop (``batcher.DeformBatcher``)."""

    @property
    def animator(self) -> Any: ...

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
        """Later, on the caller's loop: ``done((encoded, seconds))`` or ``done(exception)``;
        ``mix``: the session's ``SessionMix`` to mix the state with first."""


class Animators(Protocol):
    """Builds animators over explicit control vertices and their batchers
    (``registry.SessionRegistry``)."""

    def animator_for(self, session: Any, control_vertices: Any) -> Any:
        """An animator of the session's face over ``control_vertices``; blocking (seconds)."""

    def batcher_for(self, animator: Any) -> Deformer:
        """The one batcher of ``animator`` (call on the event loop)."""


class Input(Protocol):
    """A producer's input: decoded frames -> the face states that became final, oldest first
    (``inputs.FapInput``, ``AudioInput``, ``MarkerInput``). Not thread-safe; may block."""

    @property
    def kinds(self) -> frozenset[frames.Kind]:
        """The binary frame kinds it takes."""

    @property
    def control_vertices(self) -> np.ndarray | None:
        """Explicit control vertices its states drive (mocap), once known; else None."""

    def push_frame(self, frame: frames.Frame) -> list[FaceState]: ...

    def push_message(self, msg: FapMessage) -> list[FaceState]: ...

    def flush(self) -> list[FaceState]:
        """End of input: the states held back (look-ahead)."""


class ProducerSlot(Protocol):
    """Whoever holds a session's producer slot: a client's connection or a server-side task."""

    @property
    def remote(self) -> bool:
        """A client's producer (the session is in use) rather than a server-side one."""

    async def end(self, code: int, error_json: str) -> None:
        """The session is closing: send ``error_json`` and close with ``code`` (or stop)."""


class DirectWriter(Protocol):
    """Writes pre-framed WebSocket binary frames straight to one viewer's transport
    (``api.transport.DirectSender``)."""

    def try_write(self, framed: bytes | bytearray | memoryview) -> bool:
        """Write now if there is room and the connection is open; False otherwise."""

    async def send(self, framed: bytes | bytearray | memoryview) -> None:
        """Write, waiting while the transport's buffer is full; ``ConnectionError`` once closed."""


class Outbox(Protocol):
    """One viewer as a session sees it (``session.Viewer``): a bounded outbox."""

    @property
    def encoding(self) -> str: ...

    @property
    def sent(self) -> int: ...

    def offer(self, frame: tuple[Any, Any]) -> int:
        """Offer ``(payload, websocket frame)``: ``Viewer.SENT``, ``QUEUED`` or ``REPLACED``."""

    def say(self, text: str) -> None: ...

    def end(self, code: int, error_json: str) -> None: ...


class Relay(Protocol):
    """Where a session's frames and viewer texts also go: other nodes of a cluster
    (``cluster.node``); called on the event loop, never blocks."""

    def frame(self, seq: int, encoded: dict[str, tuple[Any, Any]]) -> None:
        """A frame, per encoding ``(payload, websocket frame)``."""

    def text(self, text: str) -> None:
        """A JSON text for every viewer (status, stats)."""
