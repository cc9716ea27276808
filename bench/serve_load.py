"""The cheap load generator of ``bench/serve.py``: producers and viewers on raw sockets, one event loop.

A benchmark of a server on a 2-core machine must not spend the cores it measures. The real client
(``facecast.client.api``: websockets, per-frame parsing, one task per connection) costs about as
much CPU per frame as the server; this generator costs a few microseconds:

- a **producer** is an ``asyncio.Protocol`` that sends the hello, waits for ``ready``, then writes
  pre-encoded ``FAPS`` frames (a table of ``TABLE`` frames made once, the sequence number and the
  wall clock patched in) as WebSocket frames masked with a zero key (RFC 6455 allows any key;
  zero makes masking a no-op), each on its own timer at ``fps``, the producers' phases spread
  over the frame period as independent clients' would be;
- a **viewer** reads each server frame's 2-10 byte header and, for binary frames, the frame
  header's ``seq`` and ``wall`` (bytes 8-12 and 24-32 of every facecast frame), and skips the
  payload without decoding or copying it out (server frames are never masked or fragmented,
  RFC 6455 §5.1); it records ``(receive wall time, seq, wall, size)``.

Both reconnect by themselves (after 0.1 s) when a connection drops, as the real clients do: on a
cluster a starved node may lose a session to another. ``run_generator`` is the body of one
generator process (``uvloop`` when installed); ``bench/serve.py`` starts it, tells it when to
start producing and when to stop over a pipe, and reads its CPU time from ``/proc``.
"""

from __future__ import annotations

import asyncio
import math
import socket
import struct
import time
from dataclasses import dataclass
from typing import Any
from urllib.parse import quote, urlencode, urlsplit

#: Frames in the producers' table (10 s at 60 fps); the motion repeats after that.
TABLE = 600
RETRY_SECONDS = 0.1
_SEQ, _T, _WALL = 8, 16, 24  # offsets in a facecast frame header (protocol/frames.py)


@dataclass(frozen=True)
class ProducerSeat:
    """A session's producer: the node it connects to (``url``: ``http://host:port``)."""

    slot: int
    session: str
    token: str
    url: str


@dataclass(frozen=True)
class ViewerSeat:
    """One viewer: its record ``slot``, its session, the node it watches on."""

    slot: int
    session: str
    token: str
    url: str


def faps(i: int, fps: float) -> dict[int, float]:
    """The bench's FAP values at frame ``i``: jaw, lips, brows and a blink, moving."""
    t = i / fps
    return {
        3: 400 + 400 * math.sin(2 * math.pi * 0.7 * t),
        5: 150 * math.sin(2 * math.pi * 1.3 * t),
        12: 200 * math.sin(2 * math.pi * 0.4 * t),
        13: 200 * math.sin(2 * math.pi * 0.4 * t),
        19: 500 * max(0.0, math.sin(2 * math.pi * 0.25 * t)) ** 8,
    }


def fap_table(fps: float, n: int = TABLE) -> list[bytes]:
    """``n`` binary ``FAPS`` frames (seq, t and wall zero: patched when sent)."""
    import numpy as np

    from facecast.protocol import frames

    out = []
    for i in range(n):
        v = np.full(frames.N_FAP_VALUES, np.nan, np.float32)
        for k, x in faps(i, fps).items():
            v[k - 1] = x
        out.append(frames.encode_faps(v, seq=0, t=0.0))
    return out


def client_frame(payload: bytes | bytearray, opcode: int) -> bytes:
    """A client WebSocket frame (FIN, masked with the key 0, so the payload goes as is)."""
    n = len(payload)
    if n < 126:
        head = struct.pack("!BB", 0x80 | opcode, 0x80 | n)
    elif n < 1 << 16:
        head = struct.pack("!BBH", 0x80 | opcode, 0x80 | 126, n)
    else:
        head = struct.pack("!BBQ", 0x80 | opcode, 0x80 | 127, n)
    return head + b"\0\0\0\0" + bytes(payload)


def upgrade_request(url: str, path: str, token: str, **query: str) -> tuple[str, int, bytes]:
    """``(host, port, HTTP request)`` opening a WebSocket on ``url`` + ``path``."""
    u = urlsplit(url)
    target = path + (f"?{urlencode(query)}" if query else "")
    req = (
        f"GET {target} HTTP/1.1\r\nHost: {u.netloc}\r\nUpgrade: websocket\r\n"
        "Connection: Upgrade\r\nSec-WebSocket-Key: ZmFjZWNhc3QtYmVuY2gtMQ==\r\n"
        f"Sec-WebSocket-Version: 13\r\nAuthorization: Bearer {token}\r\n\r\n"
    )
    return u.hostname or "127.0.0.1", u.port or 80, req.encode()


class _Reader(asyncio.Protocol):
    """The server side of a WebSocket: the upgrade answer, then frame headers; payloads of
    binary frames are skipped after their first ``keep`` bytes (the rest of a payload that spans
    reads is dropped as it comes, never copied). Subclasses handle frames. ``rcvbuf``: the
    socket's receive buffer in bytes (None: the system's)."""

    keep = 32

    def __init__(self, request: bytes, rcvbuf: int | None = None) -> None:
        self.request = request
        self.rcvbuf = rcvbuf
        self.buf = bytearray()
        self.upgraded = False
        self.transport: Any = None
        self.lost = asyncio.get_running_loop().create_future()
        self.skip = 0  # bytes of the current binary payload still to drop
        self.pending = (b"", 0)  # that frame's first ``keep`` bytes and its size

    def connection_made(self, transport: Any) -> None:
        self.transport = transport
        sock = transport.get_extra_info("socket")
        if self.rcvbuf is not None and sock is not None:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self.rcvbuf)
        transport.write(self.request)

    def connection_lost(self, exc: BaseException | None) -> None:
        if not self.lost.done():
            self.lost.set_result(None)

    def data_received(self, data: bytes) -> None:
        rest: bytes | memoryview = data
        if self.skip:  # inside a binary payload whose first bytes were kept
            take = min(self.skip, len(data))
            self.skip -= take
            if self.skip:
                return
            head, n = self.pending
            self.binary(head, 0, n)
            rest = memoryview(data)[take:]
        buf = self.buf
        buf += rest
        if not self.upgraded:
            end = buf.find(b"\r\n\r\n")
            if end < 0:
                return
            if not buf.startswith(b"HTTP/1.1 101"):
                self.transport.close()
                return
            self.upgraded = True
            del buf[: end + 4]
        at, size = 0, len(buf)
        while size - at >= 2:
            b0, b1 = buf[at], buf[at + 1] & 0x7F
            head = 2 if b1 < 126 else 4 if b1 == 126 else 10
            if size - at < head:
                break
            n = b1 if b1 < 126 else int.from_bytes(buf[at + 2 : at + head], "big")
            opcode, body = b0 & 0x0F, at + head
            if size - body < n:
                if opcode == 2 and size - body >= self.keep:  # keep its head, drop the rest
                    self.pending = (bytes(buf[body : body + self.keep]), n)
                    self.skip = n - (size - body)
                    at = size
                break
            if opcode == 2:
                self.binary(buf, body, n)
            else:
                self.control(opcode, bytes(buf[body : body + n]))
            at = body + n
        if at:
            del buf[:at]

    def binary(self, buf: bytes | bytearray, at: int, n: int) -> None:
        pass

    def control(self, opcode: int, body: bytes) -> None:
        if opcode == 8:
            self.transport.close()


class Viewer(_Reader):
    """Records ``(received, seq, wall, size)`` of each binary frame; ``ready`` at the hello."""

    def __init__(
        self, request: bytes, out: list[tuple[float, int, float, int]], rcvbuf: int | None = None
    ) -> None:
        super().__init__(request, rcvbuf)
        self.out = out
        self.ready = asyncio.get_running_loop().create_future()

    def binary(self, buf: bytes | bytearray, at: int, n: int) -> None:
        if n >= 32:
            seq = struct.unpack_from("<I", buf, at + _SEQ)[0]
            wall = struct.unpack_from("<d", buf, at + _WALL)[0]
            self.out.append((time.time(), seq, wall, n))

    def control(self, opcode: int, body: bytes) -> None:
        if opcode == 1 and not self.ready.done():
            self.ready.set_result(None)
        super().control(opcode, body)


class Producer(_Reader):
    """Sends the hello; ``ready`` when the server answers; ``send(i, t)`` writes frame ``i``."""

    def __init__(self, request: bytes, hello: bytes) -> None:
        super().__init__(request)
        self.hello = hello
        self.ready = asyncio.get_running_loop().create_future()

    def data_received(self, data: bytes) -> None:
        was = self.upgraded
        super().data_received(data)
        if self.upgraded and not was:
            self.transport.write(client_frame(self.hello, 1))

    def control(self, opcode: int, body: bytes) -> None:
        if opcode == 1 and not self.ready.done() and b'"ready"' in body:
            self.ready.set_result(None)
        super().control(opcode, body)


class _Stream:
    """One producer's connection (reconnected when it drops) and timer."""

    def __init__(self, seat: ProducerSeat, table: list[bytes], hello: bytes, fps: float) -> None:
        self.seat, self.table, self.hello, self.fps = seat, table, hello, fps
        path = f"/v1/sessions/{quote(seat.session, safe='')}/produce"
        self.host, self.port, self.request = upgrade_request(seat.url, path, seat.token)
        self.proto: Producer | None = None
        self.sent = 0
        self.reconnects = 0
        self.stopped = False

    async def connect(self) -> None:
        loop = asyncio.get_running_loop()
        while not self.stopped:
            try:
                _, proto = await loop.create_connection(
                    lambda: Producer(self.request, self.hello), self.host, self.port
                )
                await asyncio.wait_for(asyncio.shield(proto.ready), 30)
                self.proto = proto
                return
            except (OSError, asyncio.TimeoutError):
                await asyncio.sleep(RETRY_SECONDS)

    def send(self, i: int, t: float) -> None:
        p = self.proto
        if p is None or p.lost.done():
            return
        frame = bytearray(self.table[i % len(self.table)])
        struct.pack_into("<I", frame, _SEQ, i & 0xFFFFFFFF)
        struct.pack_into("<dd", frame, _T, t, time.time())
        p.transport.write(_FRAME_HEAD + frame)
        self.sent += 1

    async def follow(self) -> None:
        """Reconnect whenever the connection drops, until stopped."""
        while not self.stopped:
            p = self.proto
            if p is None:
                await self.connect()
                continue
            await p.lost
            if self.stopped:
                return
            self.proto = None
            self.reconnects += 1
            await asyncio.sleep(RETRY_SECONDS)


#: The header of a masked binary client frame of a ``FAPS`` frame's 312 bytes (key 0).
_FRAME_HEAD = struct.pack("!BBH", 0x82, 0x80 | 126, 312) + b"\0\0\0\0"


async def _watch(
    seat: ViewerSeat, encoding: str, out: list, ready: asyncio.Future, stop: asyncio.Event
) -> int:
    """One viewer until ``stop``, reconnecting when dropped; its reconnections."""
    loop = asyncio.get_running_loop()
    path = f"/v1/sessions/{quote(seat.session, safe='')}/watch"
    host, port, req = upgrade_request(seat.url, path, seat.token, encoding=encoding)
    reconnects = -1
    while not stop.is_set():
        try:
            transport, proto = await loop.create_connection(lambda: Viewer(req, out), host, port)
        except OSError:
            await asyncio.sleep(RETRY_SECONDS)
            continue
        reconnects += 1
        try:
            await asyncio.wait_for(asyncio.shield(proto.ready), 60)
        except asyncio.TimeoutError:
            transport.close()
            continue
        if not ready.done():
            ready.set_result(None)
        lost = asyncio.ensure_future(proto.lost)
        stopped = asyncio.ensure_future(stop.wait())
        await asyncio.wait({lost, stopped}, return_when=asyncio.FIRST_COMPLETED)
        stopped.cancel()
        transport.close()
        if not stop.is_set():
            await asyncio.sleep(RETRY_SECONDS)
    return max(0, reconnects)


async def generate(
    producers: list[ProducerSeat],
    viewers: list[ViewerSeat],
    *,
    fps: float,
    encoding: str,
    control: Any,
) -> dict[str, Any]:
    """Connect ``viewers``, say ``ready`` on ``control`` (a pipe end), wait for ``go``, produce
    at ``fps`` until ``stop``; the records of each viewer slot and the producers' counts."""
    loop = asyncio.get_running_loop()
    from facecast.protocol.messages import ProducerHello, dump_message

    hello = dump_message(ProducerHello()).encode()
    table = fap_table(fps)
    stop = asyncio.Event()
    records: dict[int, list] = {v.slot: [] for v in viewers}
    readies = [loop.create_future() for _ in viewers]
    watchers = [
        asyncio.create_task(_watch(v, encoding, records[v.slot], r, stop))
        for v, r in zip(viewers, readies)
    ]
    await asyncio.wait_for(asyncio.gather(*readies), 120)

    async def ask(what: str) -> None:  # the parent's word (a blocking pipe, read off the loop)
        got = await asyncio.to_thread(control.recv)
        if got != what:
            raise RuntimeError(f"generator: expected {what!r} from the bench, got {got!r}")

    control.send("ready")
    await ask("go")
    streams = [_Stream(s, table, hello, fps) for s in producers]
    await asyncio.wait_for(asyncio.gather(*(s.connect() for s in streams)), 120)
    followers = [asyncio.create_task(s.follow()) for s in streams]
    period = 1.0 / fps
    t0 = loop.time() + 0.05
    timers: list[asyncio.TimerHandle] = []

    def tick(k: int, i: int) -> None:  # producer k's frame i, then its next one
        s = streams[k]
        if s.stopped:
            return
        s.send(i, i * period)
        timers[k] = loop.call_at(t0 + (i + 1 + k / n) * period, tick, k, i + 1)

    n = max(1, len(streams))
    for k in range(len(streams)):  # phases spread over the period, as independent clients'
        timers.append(loop.call_at(t0 + k / n * period, tick, k, 0))
    control.send("producing")
    await ask("stop")
    for s in streams:
        s.stopped = True
        if s.proto is not None:
            s.proto.transport.close()
    for h in timers:
        h.cancel()
    stop.set()
    reconnects = await asyncio.gather(*watchers, return_exceptions=True)
    for f in followers:
        f.cancel()
    await asyncio.gather(*followers, return_exceptions=True)
    return {
        "records": records,
        "sent": sum(s.sent for s in streams),
        "producer_reconnects": sum(s.reconnects for s in streams),
        "viewer_reconnects": sum(r for r in reconnects if isinstance(r, int)),
        "viewer_failures": [repr(r) for r in reconnects if isinstance(r, BaseException)][:3],
    }


def run_generator(
    producers: list[ProducerSeat],
    viewers: list[ViewerSeat],
    fps: float,
    encoding: str,
    control: Any,
) -> None:
    """A generator process's body: ``generate`` on uvloop (when installed); the result goes back
    on ``control`` (or ``{"error": ...}``)."""
    try:
        import uvloop

        runner: Any = uvloop.run
    except ImportError:
        runner = asyncio.run
    try:
        out = runner(generate(producers, viewers, fps=fps, encoding=encoding, control=control))
    except BaseException as e:  # noqa: BLE001 - reported to the bench, which fails the point
        out = {"error": repr(e)}
    control.send(out)
    control.close()
