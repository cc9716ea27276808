"""Server-side producers of a live session: the demo performance and playback of an uploaded file.

A ``ServerProducer`` holds the session's producer slot while a task feeds it face states at their
rate; a client's WebSocket producer is refused (4409) meanwhile. Starting one replaces a running
server-side producer but never a client's (``Busy``, 409).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterable

import numpy as np

from ..errors import Conflict
from ..state import FaceState
from .ports import Deformer
from .session import LiveSession


class Busy(Conflict):
    """A client's producer is connected to the session (HTTP 409)."""

    status = 409


class ServerProducer:
    """Holds a session's producer slot while a server-side task feeds it.

    A marker take brings its own control vertices: ``deform_with`` swaps the session's batcher for
    one over them (``LiveSession.deform_with``), and ``release`` puts the session's own back.
    """

    remote = False  # a server-side producer: alone, it does not keep the session in use

    def __init__(self, session: LiveSession, kind: str) -> None:
        self.session = session
        self.kind = kind
        self.task: asyncio.Task[None] | None = None
        self._own: tuple[Deformer, np.ndarray | None] | None = None  # the session's, while swapped

    @classmethod
    def claim(cls, session: LiveSession, kind: str) -> ServerProducer:
        """Take ``session``'s producer slot for a server-side producer of ``kind``, stopping a
        running one; ``Busy`` if a client's producer holds it."""
        current = session.producer
        if isinstance(current, ServerProducer):
            current.stop()  # its deformation is undone now, before the new one swaps its own in
        elif current is not None:
            raise Busy(
                "a producer is connected to this session; it must disconnect first",
                where="producer",
            )
        producer = cls(session, kind)
        session.claim(producer)  # free: nothing awaited since the check above
        session.announce(producer)
        return producer

    @staticmethod
    def stop_in(session: LiveSession) -> None:
        """Stop ``session``'s server-side producer, if it has one."""
        if isinstance(session.producer, ServerProducer):
            session.producer.stop()

    def deform_with(self, batcher: Deformer, control_vertices: np.ndarray) -> None:
        self._own = self.session.deform_with(batcher, control_vertices)

    def play(self, states: Iterable[FaceState], fps: float, start_wall: float, name: str) -> None:
        """Feed ``states`` at ``fps`` from Unix time ``start_wall`` in a task; the slot is freed at
        the end."""
        self.task = asyncio.create_task(self._feed(states, fps, start_wall), name=name)

    async def _feed(self, states: Iterable[FaceState], fps: float, start_wall: float) -> None:
        """Submit ``states`` paced at ``fps``; a frame more than a second late (a stalled loop) is
        skipped rather than rushed out."""
        try:
            for i, state in enumerate(states):
                delay = start_wall + i / fps - time.time()
                if delay > 0:
                    await asyncio.sleep(delay)
                elif delay < -1.0:
                    continue
                self.session.submit([state], wall=time.time())
        except asyncio.CancelledError:
            pass
        finally:
            self.release()

    def release(self) -> None:
        """Give back the session's deformation and producer slot (idempotent)."""
        if self._own is not None:
            self.session.restore(self._own)
            self._own = None
        self.session.release(self)

    def stop(self) -> None:
        if self.task is not None:
            self.task.cancel()
        self.release()

    async def end(self, code: int, error_json: str) -> None:  # the session is closing
        self.stop()
