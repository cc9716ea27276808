"""WebSocket framing of vertex frames, done once per frame for every viewer.

A server-to-client WebSocket message is not masked, so its bytes on the wire (frame header +
payload) are the same for every viewer: the batcher writes each encoded frame after its WebSocket
header, once, and ``api.transport.DirectSender`` writes those bytes straight to each viewer's
transport. Pure functions (RFC 6455 §5.2); no I/O.
"""

from __future__ import annotations

import struct

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
