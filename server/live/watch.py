"""A viewer connection as a sans-I/O state machine: admission, the hello, and what it may send.

The core decides whether a viewer may join (a known encoding, room under the session's limit), the
hello it is greeted with, the socket buffer sizes that keep a slow viewer skipping frames instead of
falling behind, and what happens to what it sends: viewers only listen, so messages are read and
ignored until a flood (1008) or an oversized one (1009) ends the connection. The shell
(``api.routes_sessions.watch``) sends and closes as the returned ``core.Step`` says.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, cast
from urllib.parse import quote

from ...protocol import frames
from ...protocol.encoding import parse_vertex_encoding
from ...protocol.errors import CloseCode, MessageError
from ...protocol.messages import Encoding, ViewerHello, dump_message
from .budget import viewer_limits
from .core import NOTHING, Close, Gate, Step, closing
from .session import LiveSession

#: Encodings a viewer may ask for.
#: Kernel send buffer of a viewer socket, in vertex frames (see ``send_buffer``).
VIEWER_SEND_BUFFER_FRAMES = 1
#: Smallest kernel send buffer asked for, bytes.
MIN_SEND_BUFFER = 64 * 1024
#: Smallest transport write buffer limit asked for (compact viewers), bytes.
MIN_WRITE_BUFFER = 4096


class ViewerCore:
    """One viewer connection of ``session`` asking for ``encoding``."""

    def __init__(
        self,
        session: LiveSession,
        encoding: str,
        *,
        metrics: Any = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.session = session
        self.encoding = encoding
        self.clock = clock
        self._joining = False
        self._gate = Gate(
            viewer_limits(),
            clock(),
            label=f"session {session.spec.id}: viewer",
            metrics=metrics,
            warn=False,
            prefix="viewers only listen: ",
        )

    def greet(self) -> Step:
        """Admit the viewer (its hello to send) or refuse it (4400 unknown encoding, 4429 full).
        An admitted viewer counts against the limit until ``greeted``."""
        s = self.session
        try:
            parse_vertex_encoding(self.encoding)  # the one vocabulary, protocol/encoding.py
        except MessageError as e:
            return closing(Close(e.close_code, str(e), where=e.where))
        if not s.has_room():
            return closing(
                Close(
                    CloseCode.TOO_MANY,
                    f"this session already has {len(s.viewers)} viewers, its limit",
                )
            )
        sp = s.spec
        hello = ViewerHello(
            session=sp.id,
            face=sp.face,
            topology_url=f"/v1/faces/{quote(sp.face, safe='')}/topology",
            vertex_count=s.vertex_count,
            encoding=cast(Encoding, self.encoding),
            fps=sp.fps,
            input=sp.input,
            producer_connected=bool(s.producers),
            tolerance=sp.tolerance / s.face.mm_per_unit if self.encoding == "compact" else None,
        )
        s.join()
        self._joining = True
        return Step(send=(dump_message(hello),))

    def greeted(self) -> Step:
        """The hello is out (or the viewer is gone): NOTHING, or a close if the session closed
        meanwhile."""
        if self._joining:
            self._joining = False
            self.session.joined()
        if self.session.closed:
            return closing(Close(CloseCode.SESSION_CLOSED, "the session was closed"))
        return NOTHING

    def send_buffer(self) -> int:
        """Bytes to cap the viewer socket's kernel send buffer at (about one frame).

        Loopback and LAN sockets auto-tune their buffers to megabytes, i.e. dozens of 25k-vertex
        frames: a viewer that reads too slowly would then see old frames (latency grows) instead of
        skipped ones. With a small buffer the backlog stays in the viewer's one-frame slot, where
        a newer frame replaces it.
        """
        n = self.session.vertex_count
        if self.encoding == "compact":  # a key frame is about a byte per vertex, a delta a fifth
            frame_bytes = n
        else:
            kind = frames.Kind.VERTICES_I16 if self.encoding == "i16" else frames.Kind.VERTICES_F32
            frame_bytes = frames.frame_size(frames.Header(kind, 0, n, 0.0))
        return max(MIN_SEND_BUFFER, VIEWER_SEND_BUFFER_FRAMES * frame_bytes)

    def write_buffer(self) -> int | None:
        """Bytes of the transport's write buffer above which writing pauses, or None (the
        default). asyncio's default, 64 KiB, is dozens of compact frames: a slow viewer would fall
        behind instead of skipping."""
        if self.encoding != "compact":
            return None
        return max(MIN_WRITE_BUFFER, VIEWER_SEND_BUFFER_FRAMES * self.session.vertex_count)

    def receive(self, nbytes: int, text: bool) -> Step:
        """A message from the viewer (``nbytes`` long): ignored, unless it floods or is too big."""
        over = self._gate.check(nbytes, text, self.clock())
        return NOTHING if over is None else over
