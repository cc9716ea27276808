"""Transport tricks of the live WebSockets, in one place: reaching the connection under
Starlette's ``WebSocket``, socket buffer sizes, cutting a flooding peer off, and sending pre-framed
vertex frames straight to a viewer's transport.

Everything here is best effort and specific to uvicorn's sans-I/O WebSocket protocol (uvicorn's
default with ``websockets`` installed): under another ASGI server ``protocol_of`` finds nothing,
the helpers do nothing, ``DirectSender.attach`` returns None and frames go through
``WebSocket.send_bytes``. The live core (``server.live``) knows none of this.
"""

from __future__ import annotations

import asyncio
import logging
import socket
from collections.abc import Callable
from typing import Any

from starlette.websockets import WebSocket

log = logging.getLogger(__name__)

#: Kernel receive buffer of a producer socket: what one read hands the event loop at most (a read
#: of tiny frames is parsed in one go, so a flood's reads stay short); ample for 1 s audio chunks.
PRODUCER_RECEIVE_BUFFER = 64 * 1024
#: Seconds a flooding client has to read its close frame before its connection is dropped.
CUT_OFF_GRACE = 1.0


def find_protocol(send: Any, depth: int = 4) -> Any:
    """The uvicorn protocol object behind an ASGI ``send`` callable (a bound method of it, possibly
    wrapped in Starlette's closures), or None."""
    owner = getattr(send, "__self__", None)
    if owner is not None and hasattr(owner, "transport"):
        return owner
    if depth > 0:
        for cell in getattr(send, "__closure__", None) or ():
            try:
                value = cell.cell_contents
            except ValueError:
                continue
            if callable(value):
                found = find_protocol(value, depth - 1)
                if found is not None:
                    return found
    return None


def protocol_of(ws: WebSocket) -> Any:
    """The uvicorn protocol object of a connection, or None."""
    return find_protocol(getattr(ws, "_send", None))


def transport_of(ws: WebSocket) -> Any:
    """The asyncio transport under a connection, or None (ASGI servers other than uvicorn)."""
    return getattr(protocol_of(ws), "transport", None)


def cut_off(ws: WebSocket, grace: float = CUT_OFF_GRACE) -> None:
    """Stop reading a flooding connection now (its queued bytes are never parsed) and drop it after
    ``grace`` seconds, whether or not it answers the close frame."""
    transport = transport_of(ws)
    if transport is None or transport.is_closing():
        return
    try:
        transport.pause_reading()
    except RuntimeError:  # pragma: no cover - already closing
        return
    asyncio.get_running_loop().call_later(grace, transport.abort)


def set_buffer(ws: WebSocket, option: int, nbytes: int) -> None:
    """Set a socket buffer size (``SO_SNDBUF`` / ``SO_RCVBUF``) of the connection."""
    try:
        transport = transport_of(ws)
        sock = transport.get_extra_info("socket") if transport is not None else None
        if sock is not None:
            sock.setsockopt(socket.SOL_SOCKET, option, int(nbytes))
    except (OSError, AttributeError):  # pragma: no cover - depends on the ASGI server
        log.debug("cannot set a socket buffer of a live connection", exc_info=True)


def limit_receive_buffer(ws: WebSocket, nbytes: int = PRODUCER_RECEIVE_BUFFER) -> None:
    """Cap the kernel receive buffer of a producer's socket at ``nbytes``."""
    set_buffer(ws, socket.SO_RCVBUF, nbytes)


def limit_send_buffer(ws: WebSocket, nbytes: int) -> None:
    """Cap the kernel send buffer of a viewer's socket at about ``nbytes``."""
    set_buffer(ws, socket.SO_SNDBUF, nbytes)


def limit_write_buffer(ws: WebSocket, nbytes: int) -> None:
    """Pause writing to a connection once about ``nbytes`` wait in its transport."""
    try:
        transport = transport_of(ws)
        if transport is not None:
            transport.set_write_buffer_limits(high=int(nbytes))
    except (AttributeError, NotImplementedError, ValueError):  # pragma: no cover - ASGI server
        log.debug("cannot set the write buffer limit of a viewer", exc_info=True)


class ViewerGone(ConnectionError):
    """The viewer's connection is closing or closed."""


class DirectSender:
    """Writes pre-framed binary messages (``live.wire.ws_binary_frame``) to one viewer's transport,
    with the protocol's backpressure.

    A server-to-client WebSocket message is not masked, so its bytes on the wire are the same for
    every viewer: they are built once per vertex frame, and written here without, per viewer, the
    ASGI round trip and the two copies of the payload that framing it again would cost (measured:
    the largest share of the server's CPU time with many viewers). Control messages (JSON text)
    always go through the ASGI interface.
    """

    def __init__(self, proto: Any) -> None:
        from websockets.protocol import State

        self.proto = proto
        self._open = State.OPEN

    @classmethod
    def attach(cls, ws: WebSocket, enabled: bool = True) -> DirectSender | None:
        """A sender for ``ws``, or None (``enabled`` false: ``FACECAST_LIVE_DIRECT=0``; another
        ASGI server; or a negotiated extension, e.g. deflate, that changes the framing)."""
        if not enabled:
            return None
        proto = protocol_of(ws)
        needed = ("conn", "transport", "writable", "disconnected", "close_sent")
        if proto is None or not all(hasattr(proto, a) for a in needed) or proto.conn.extensions:
            return None
        try:
            return cls(proto)
        except ImportError:  # pragma: no cover
            return None

    def try_write(self, framed: bytes | bytearray | memoryview) -> bool:
        """Write now if the transport has room and the connection is open; False otherwise."""
        p = self.proto
        if (
            not p.writable.is_set()
            or p.disconnected
            or p.close_sent
            or p.conn.state is not self._open
            or p.transport.is_closing()
        ):
            return False
        p.transport.write(framed)
        return True

    async def send(self, framed: bytes | bytearray | memoryview) -> None:
        """Write one frame; waits while the transport's buffer is full."""
        p = self.proto
        await p.writable.wait()
        if (
            p.disconnected
            or p.close_sent
            or p.conn.state is not self._open
            or p.transport.is_closing()
        ):
            raise ViewerGone("viewer connection closed")
        p.transport.write(framed)


#: The key of a message ``DirectReceiver`` queues for the app: what a message taken in the
#: protocol's callback left to do (a step to carry out, or the exception it raised).
HANDED = "facecast.handed"


class DirectReceiver:
    """Takes a producer's binary messages in the connection's ``data_received`` callback, by
    ``take(data)``, instead of queueing each for the app's task.

    Through ASGI each message costs the event loop a queue hand-over, a wake-up of the app's task,
    a pause and a resume of the socket's reading and Starlette's checks: more than the decoding and
    queueing of a FAP frame itself. Here, while the app's task waits for the next message
    (``waiting``, set around its ``ws.receive()`` by ``receive``) and nothing is queued ahead of it (so the
    order of messages holds), a complete binary message goes to ``take`` at once. What ``take``
    returns other than None (work for the task: a reply to send, a close), or the exception it
    raises, is queued for the task under ``HANDED``, and ``waiting`` stays false until the task
    waits again: meanwhile messages are queued as before. Text messages are always queued. At most
    ``TAKE_PER_WAIT`` messages are taken per wait of the task: one read can hold hundreds of small
    frames, and a flood must not hold the event loop longer than the task's own cadence would.
    """

    #: Messages taken in callbacks while the task waits once (the producer loops' ``YIELD_EVERY``).
    TAKE_PER_WAIT = 8

    def __init__(self, proto: Any, take: Callable[[Any], object | None]) -> None:
        self.proto = proto
        self.take = take
        self.waiting = False
        self.taken = 0  # messages taken since the task last started waiting
        self._queue_it = proto.handle_bytes
        proto.handle_bytes = self._handle  # this connection's: the instance's attribute

    @classmethod
    def attach(
        cls, ws: WebSocket, take: Callable[[Any], object | None], enabled: bool = True
    ) -> DirectReceiver | None:
        """A receiver for ``ws``, or None (``enabled`` false: ``FACECAST_LIVE_DIRECT=0``; an ASGI
        server other than uvicorn's sans-I/O one)."""
        if not enabled:
            return None
        proto = protocol_of(ws)
        needed = ("queue", "handle_bytes", "close_sent")
        if proto is None or not all(hasattr(proto, a) for a in needed):
            return None
        return cls(proto, take)

    def detach(self) -> None:
        """Queue every message again (idempotent)."""
        self.waiting = False
        if self.proto.__dict__.get("handle_bytes") == self._handle:
            del self.proto.handle_bytes

    def _handle(self, event: Any) -> None:
        p = self.proto
        if not self.waiting or not event.fin or p.close_sent or not p.queue.empty():
            self._queue_it(event)
            return
        try:
            handed = self.take(event.data)
        except Exception as e:  # the task raises it, as if it had taken the message
            handed = e
        self.taken += 1
        if self.taken >= self.TAKE_PER_WAIT:  # the rest through the task, which yields
            self.waiting = False
        if handed is not None:
            self.waiting = False
            p.queue.put_nowait({"type": "websocket.receive", HANDED: handed})


async def receive(ws: WebSocket, direct: DirectReceiver | None) -> Any:
    """``ws.receive()``, with ``direct`` (if any) taking binary messages in the callback meanwhile;
    the exception a message taken there raised is raised here, as if this had taken it."""
    if direct is None:
        return await ws.receive()
    direct.waiting, direct.taken = True, 0
    msg = await ws.receive()
    direct.waiting = False
    handed = msg.get(HANDED)
    if isinstance(handed, BaseException):
        raise handed
    return msg
