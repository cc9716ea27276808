"""The envelopes of the messages nodes exchange on Redis channels (pure; ``docs/CLUSTER.md``).

Each message is one byte naming its kind, then its body: the protocol's own bytes (a vertex frame
already framed as a WebSocket binary message, a producer's raw text or bytes, a JSON text for
viewers) or a small JSON object. Nothing is pickled. ``parse_*`` raise ``ValueError`` on a
message that does not fit (a node of another version): the caller logs and drops it.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from typing import Any

# -- down: from a session's owner to the nodes that mirror it ------------------------------------
FRAME, TEXT, OWNER, END = b"F", b"S", b"N", b"E"
# -- up: to a session's owner ---------------------------------------------------------------------
WANT, PRODUCER, CLOSE = b"W", b"P", b"X"
# -- inbox: to one node ---------------------------------------------------------------------------
REPLY = b"R"

#: What a forwarded producer message is (``PRODUCER``): open, text, bytes, hello timeout, gone.
OPEN, P_TEXT, P_BYTES, P_TIMEOUT, P_GONE = b"O", b"T", b"B", b"H", b"D"
#: What a reply to a forwarded producer is (``REPLY``): a text to send, the close decision.
R_TEXT, R_CLOSE = b"T", b"C"

CONN_LEN = 16  #: a forwarded connection's id: 16 ASCII hex digits
_FRAME_HEAD = struct.Struct("<IIB")  # epoch, seq, length of the encoding's name


def frame(epoch: int, seq: int, encoding: str, framed: bytes | bytearray | memoryview) -> bytes:
    """A vertex frame (``framed``: the WebSocket binary message) of owner generation ``epoch``."""
    name = encoding.encode("ascii")
    return b"".join(
        (FRAME, _FRAME_HEAD.pack(epoch & 0xFFFFFFFF, seq & 0xFFFFFFFF, len(name)), name, framed)
    )


@dataclass(frozen=True, slots=True)
class Frame:
    epoch: int
    seq: int
    encoding: str
    framed: memoryview  #: the WebSocket binary message
    payload: memoryview  #: the frame itself (``protocol/frames.py``), inside ``framed``


def ws_header_length(framed: memoryview) -> int:
    """Length of an unmasked server WebSocket frame's header (2, 4 or 10 bytes)."""
    if len(framed) < 2:
        raise ValueError("a WebSocket frame has at least 2 bytes")
    n = framed[1] & 0x7F
    return 2 if n < 126 else 4 if n == 126 else 10


def parse_frame(data: bytes) -> Frame:
    view = memoryview(data)
    at = 1 + _FRAME_HEAD.size
    if len(view) < at:
        raise ValueError("frame envelope too short")
    epoch, seq, n = _FRAME_HEAD.unpack_from(view, 1)
    encoding = bytes(view[at : at + n]).decode("ascii")
    framed = view[at + n :]
    head = ws_header_length(framed)
    if len(framed) <= head:
        raise ValueError("frame envelope without a frame")
    return Frame(epoch, seq, encoding, framed, framed[head:])


def with_json(kind: bytes, obj: dict[str, Any]) -> bytes:
    return kind + json.dumps(obj, separators=(",", ":")).encode()


def parse_json(data: bytes) -> dict[str, Any]:
    obj = json.loads(data[1:])
    if not isinstance(obj, dict):
        raise ValueError("envelope body is not a JSON object")
    return obj


def producer(conn: str, kind: bytes, body: bytes = b"") -> bytes:
    """A forwarded producer message of connection ``conn``."""
    return b"".join((PRODUCER, conn.encode("ascii"), kind, body))


def reply(conn: str, kind: bytes, body: bytes = b"") -> bytes:
    """A reply to forwarded producer connection ``conn``."""
    return b"".join((REPLY, conn.encode("ascii"), kind, body))


def parse_conn(data: bytes) -> tuple[str, bytes, bytes]:
    """``(conn, kind, body)`` of a ``PRODUCER`` or ``REPLY`` message."""
    if len(data) < 2 + CONN_LEN:
        raise ValueError("connection envelope too short")
    conn = data[1 : 1 + CONN_LEN].decode("ascii")
    return conn, data[1 + CONN_LEN : 2 + CONN_LEN], data[2 + CONN_LEN :]
