"""Sending one vertex frame to many viewers cheaply.

A server-to-client WebSocket message is not masked, so its bytes on the wire (frame header +
payload) are the same for every viewer: ``ws_binary_frame`` builds them once per vertex frame and
``DirectSender`` writes them straight to each viewer's transport. This skips, per viewer, the
ASGI round trip and the two copies of the payload that framing it again would cost (measured:
the largest share of the server's CPU time with many viewers).

``DirectSender.attach`` works with uvicorn's sans-I/O WebSocket protocol (uvicorn's default with
``websockets`` installed) and returns None for anything else; callers then use
``WebSocket.send_bytes``. Control messages (JSON text) always go through the ASGI interface.
"""

from __future__ import annotations

import logging
import os
import struct
from typing import Any

log = logging.getLogger(__name__)

_OP_BINARY_FIN = 0x82


_HEAD_7 = struct.Struct("!BB")
_HEAD_16 = struct.Struct("!BBH")
_HEAD_64 = struct.Struct("!BBQ")


def ws_binary_header(n: int) -> bytes:
    """The header of an unmasked, unfragmented WebSocket binary frame (RFC 6455 §5.2) whose
    payload is ``n`` bytes long (2, 4 or 10 bytes)."""
    if n < 126:
        return _HEAD_7.pack(_OP_BINARY_FIN, n)
    if n < 1 << 16:
        return _HEAD_16.pack(_OP_BINARY_FIN, 126, n)
    return _HEAD_64.pack(_OP_BINARY_FIN, 127, n)


def ws_binary_frame(payload: bytes) -> bytes:
    """The unmasked, unfragmented WebSocket binary frame (RFC 6455 §5.2) carrying ``payload``."""
    return b"".join((ws_binary_header(len(payload)), payload))


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


class ViewerGone(ConnectionError):
    """The viewer's connection is closing or closed."""


class DirectSender:
    """Writes pre-framed binary messages to one viewer's transport, with the protocol's backpressure."""

    def __init__(self, proto: Any) -> None:
        from websockets.protocol import State

        self.proto = proto
        self._open = State.OPEN

    @classmethod
    def attach(cls, ws: Any) -> "DirectSender | None":
        """A sender for ``ws``, or None (other ASGI server, or ``FACECAST_LIVE_DIRECT=0``)."""
        if os.environ.get("FACECAST_LIVE_DIRECT", "1") == "0":
            return None
        proto = find_protocol(getattr(ws, "_send", None))
        needed = ("conn", "transport", "writable", "disconnected", "close_sent")
        if proto is None or not all(hasattr(proto, a) for a in needed) or proto.conn.extensions:
            return None  # another ASGI server, or a negotiated extension (deflate) that changes framing
        try:
            return cls(proto)
        except ImportError:  # pragma: no cover
            return None

    def try_write(self, framed: bytes) -> bool:
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

    async def send(self, framed: bytes) -> None:
        """Write one frame from ``ws_binary_frame``; waits while the transport's buffer is full."""
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
