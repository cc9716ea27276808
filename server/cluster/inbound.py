"""The owner's side of a producer connected to another node: its raw messages, fed to a core.

The node the producer reached (``api.routes_cluster``) forwards each message it receives, as is,
on the session's ``up`` channel; here, on the owner, one ``RemoteProducer`` per forwarded
connection feeds them in order to a ``ProducerCore`` (the same state machine as a local producer:
the producer slot, the hello, budgets, drivers) and sends what the core says back to that node's
``inbox``: texts to send, and the close decision.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections import deque
from collections.abc import Callable
from typing import Any

from ..live.core import Close, Step
from ..live.producer import ProducerCore
from ..live.registry import SessionRegistry
from ..live.session import LiveSession
from . import envelope

log = logging.getLogger(__name__)

#: Forwarded messages waiting for the core, per connection; beyond this they are dropped.
MAX_QUEUED = 256
#: The queue's mark of a frame ``feed`` took itself: what is left of it follows (a step, an error).
HANDED = b"handed"


def close_body(code: int, error: str, reason: str = "", cut_off: bool = False) -> bytes:
    obj = {"code": int(code), "error": error, "reason": reason, "cut_off": cut_off}
    return json.dumps(obj).encode()


def close_reply(c: Close) -> bytes:
    """The ``R_CLOSE`` body of a close decision."""
    return close_body(c.code, c.error, c.reason, c.cut_off)


class RemoteProducer:
    """A producer connected to node ``node`` through forwarded connection ``conn``.

    ``send(body)``: publishes a reply (``envelope.reply`` bytes) to that node's inbox.
    """

    remote = True  # a client's producer: the session is in use

    def __init__(
        self,
        registry: SessionRegistry,
        session: LiveSession,
        conn: str,
        node: str,
        send: Callable[[bytes], None],
        roles: frozenset[str] = frozenset(),
    ) -> None:
        self.conn, self.node, self.session = conn, node, session
        self._send = send
        self.core = ProducerCore(
            session,
            self,
            animators=registry,
            max_fps=registry.max_fps,
            metrics=registry.metrics,
            roles=roles,
        )
        self._executor = registry.executor
        #: forwarded messages (kind, body), or (``HANDED``, what a frame taken in ``feed`` left)
        self._queue: deque[tuple[bytes, Any]] = deque()
        self._wake = asyncio.Event()
        self._waiting = False  # the loop waits for ``_wake`` with nothing queued
        self.task: asyncio.Task[None] | None = None
        self.done = False

    def start(self) -> bool:
        """Take the producer slot (or refuse, 4409) and start feeding; False if refused."""
        step = self.core.connect()
        if step.close is not None:
            self._close_reply(step)
            self.done = True
            return False
        self.task = asyncio.get_running_loop().create_task(self._run())
        return True

    def feed(self, kind: bytes, body: bytes) -> None:
        """A forwarded message (``envelope.P_TEXT``, ``P_BYTES``, ``P_TIMEOUT``, ``P_GONE``)."""
        if self.done:
            return
        if len(self._queue) >= MAX_QUEUED and kind in (envelope.P_TEXT, envelope.P_BYTES):
            self.session.count_rejected()
            return
        if kind == envelope.P_BYTES and self._waiting and not self._queue:
            # the loop waits with nothing queued: take the frame now, not after a task wake-up
            # (as ``api.transport.DirectReceiver`` does for a local producer)
            step: Step | Exception | None
            try:
                step = self.core.take_bytes(body)
            except Exception as e:  # noqa: BLE001 - the loop's to handle, as if it had taken it
                step = e
            if step is None:
                return
            self._queue.append((HANDED, step))
        else:
            self._queue.append((kind, body))
        self._waiting = False
        self._wake.set()

    def stop(self) -> None:
        """The producer's node is gone: free the slot."""
        self.done = True
        if self.task is not None:
            self.task.cancel()
        self.core.close()

    async def end(self, code: int, error_json: str) -> None:
        """The session is closing (``ProducerSlot``): tell the producer's node to close."""
        self._send(envelope.reply(self.conn, envelope.R_CLOSE, close_body(code, error_json)))
        self.stop()

    # -- the feeding loop ---------------------------------------------------------------------------
    async def _run(self) -> None:
        core = self.core
        try:
            while not self.done:
                if not self._queue:
                    self._wake.clear()
                    self._waiting = True
                    await self._wake.wait()
                    continue
                kind, body = self._queue.popleft()
                if kind is HANDED:
                    if isinstance(body, BaseException):
                        raise body
                    step = body
                elif kind == envelope.P_BYTES:
                    step = core.receive_bytes(body)
                elif kind == envelope.P_TEXT:
                    step = core.receive_text(body.decode("utf-8", "replace"))
                elif kind == envelope.P_TIMEOUT:
                    step = core.timeout()
                else:  # P_GONE: the producer left; its input's held-back states still go out
                    await self._carry_out(core.disconnected())
                    return
                if not await self._carry_out(step) or not core.open:
                    return
        except asyncio.CancelledError:
            raise
        except Exception as e:  # noqa: BLE001 - a fault of this shell: the core answers 4500
            self._close_reply(core.failed(e))
        finally:
            self.done = True
            self._waiting = False
            core.close()

    async def _carry_out(self, step: Step) -> bool:
        loop = asyncio.get_running_loop()
        while True:
            for text in step.send:
                self._send(envelope.reply(self.conn, envelope.R_TEXT, text.encode()))
            if step.close is not None:
                self._close_reply(step)
                return False
            work = step.work
            if work is None:
                return True
            result = (
                await loop.run_in_executor(self._executor, work.run) if work.offload else work.run()
            )
            step = work.then(result)

    def _close_reply(self, step: Step) -> None:
        c = step.close
        assert c is not None
        for text in step.send:
            self._send(envelope.reply(self.conn, envelope.R_TEXT, text.encode()))
        self._send(envelope.reply(self.conn, envelope.R_CLOSE, close_reply(c)))


def parse_close(body: bytes) -> dict[str, Any]:
    obj = json.loads(body)
    if not isinstance(obj, dict):
        raise ValueError("close reply is not a JSON object")
    return obj
