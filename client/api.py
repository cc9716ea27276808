"""The asyncio client of facecast live sessions.

REST (httpx): ``SessionAdmin(url, admin_key)`` creates, lists and closes sessions; with the admin
key or a session's producer token it also mints scoped producer tokens and sets the session's
layers (``token``, ``layers``, ``set_layer``, ``patch_layer``, ``remove_layer``).
WebSocket (websockets, per-message deflate off; the session token travels in an
``Authorization: Bearer`` header, never in the URL):

- ``produce(url, session, token, hello)`` -> ``Producer``: ``send_faps`` / ``send_pcm`` /
  ``send_markers`` stamp each frame with the sender's wall clock (for end-to-end latency);
  errors the server sends back are collected in ``Producer.errors``.
- ``watch(url, session, token, encoding=...)`` -> ``Watcher``: an async iterator of
  ``WatchedFrame`` (decoded vertex frame + receive time + size); ``hello``, ``status``, ``stats``
  and ``errors`` hold the control messages.

Both are async context managers. With ``retry=Retry()`` either one survives its node going away:
when an established connection drops (connection lost, server restarting, session briefly unknown
during a failover) it reconnects by itself, with exponential backoff from 50 ms, capped and
jittered, until it is back or ``Retry.give_up`` seconds have passed; refusals that another try
would not change (a wrong token, a closed session) still raise at once. Nothing here imports the
server.
"""

from __future__ import annotations

import asyncio
import logging
import random
import socket
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any
from urllib.parse import quote, urlencode, urlsplit, urlunsplit

import httpx
import numpy as np
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, InvalidStatus, WebSocketException

from ..protocol import frames
from ..protocol.errors import FrameError, UpstreamError
from ..protocol.layers import LayerInfo, LayerList, TokenCreated
from ..protocol.messages import (
    ErrorMessage,
    FapMessage,
    ProducerHello,
    Ready,
    SessionCreate,
    SessionCreated,
    SessionInfo,
    SessionList,
    Stats,
    Status,
    ViewerHello,
    dump_message,
    parse_message,
)
from ..protocol.urls import server_url

if TYPE_CHECKING:
    from typing_extensions import Self

log = logging.getLogger(__name__)

#: Largest message a client accepts (a 500k-vertex float32 frame is 6 MB).
MAX_MESSAGE = 64 * 1024 * 1024


class LiveError(UpstreamError):
    """The server refused a request or ended a connection with an error.

    ``code`` is the HTTP status or the WebSocket close code (``protocol.errors.CloseCode``), 0 if the
    server could not be reached.
    """


def ws_url(url: str, path: str, **query: Any) -> str:
    """``http://h:p`` + ``/path`` + query -> ``ws://h:p/path?query`` (``https`` -> ``wss``)."""
    parts = urlsplit(url)
    scheme = {"http": "ws", "https": "wss"}.get(parts.scheme, parts.scheme)
    q = urlencode({k: v for k, v in query.items() if v is not None})
    return urlunsplit((scheme, parts.netloc, parts.path.rstrip("/") + path, q, ""))


def _http_error(resp: httpx.Response, what: str) -> LiveError:
    try:
        body = resp.json()
        text = body.get("error") or body.get("detail") or body if isinstance(body, dict) else body
    except ValueError:
        text = resp.text.strip()[:300]
    hint = " (set FACECAST_ADMIN_KEY to the server's admin key)" if resp.status_code == 401 else ""
    return LiveError(f"{what}: HTTP {resp.status_code}: {text}{hint}", resp.status_code)


class SessionAdmin:
    """Create, list and close live sessions (needs the admin key)."""

    def __init__(self, url: str, admin_key: str | None, *, timeout: float = 120.0) -> None:
        headers = {"Authorization": f"Bearer {admin_key}"} if admin_key else {}
        self.http = httpx.AsyncClient(base_url=url, headers=headers, timeout=timeout)

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.http.aclose()

    async def _call(self, method: str, path: str, what: str, **kw: Any) -> httpx.Response:
        try:
            resp = await self.http.request(method, path, **kw)
        except httpx.HTTPError as e:
            raise LiveError(f"{what}: cannot reach {self.http.base_url}: {e}") from None
        if resp.status_code >= 400:
            raise _http_error(resp, what)
        return resp

    async def create(
        self,
        *,
        face: str | None = None,
        input: str = "fap",
        fps: float = 60.0,
        engine: str = "fp",
        max_viewers: int | None = None,
        tolerance: float = 0.1,
    ) -> SessionCreated:
        body = SessionCreate(
            face=face,
            input=input,
            fps=fps,
            engine=engine,
            max_viewers=max_viewers,
            tolerance=tolerance,
        )
        resp = await self._call(
            "POST",
            "/v1/sessions",
            "cannot create a session",
            json=body.model_dump(exclude_none=True),
        )
        return SessionCreated.model_validate(resp.json())

    async def list(self) -> list[SessionInfo]:
        resp = await self._call("GET", "/v1/sessions", "cannot list sessions")
        return SessionList.model_validate(resp.json()).sessions

    async def info(self, session: str) -> SessionInfo:
        resp = await self._call(
            "GET", f"/v1/sessions/{quote(session, safe='')}", "cannot read the session"
        )
        return SessionInfo.model_validate(resp.json())

    async def close(self, session: str) -> None:
        await self._call(
            "DELETE", f"/v1/sessions/{quote(session, safe='')}", f"cannot close session {session}"
        )

    # -- layers (the admin key or the session's producer token) -----------------------------------
    async def token(self, session: str, roles: list[str]) -> TokenCreated:
        """A producer token of ``session`` that may drive only ``roles`` (expression, gaze...)."""
        resp = await self._call(
            "POST",
            f"/v1/sessions/{quote(session, safe='')}/tokens",
            "cannot make a producer token",
            json={"roles": list(roles)},
        )
        return TokenCreated.model_validate(resp.json())

    def _layer_path(self, session: str, name: str | None = None) -> str:
        path = f"/v1/sessions/{quote(session, safe='')}/layers"
        return path if name is None else f"{path}/{quote(name, safe='')}"

    async def layers(self, session: str) -> LayerList:
        resp = await self._call("GET", self._layer_path(session), "cannot list the layers")
        return LayerList.model_validate(resp.json())

    async def set_layer(self, session: str, name: str, spec: dict[str, Any]) -> LayerInfo:
        """Set layer ``name`` to ``spec`` (``{"kind": "idle", ...}``, ``protocol.layers``)."""
        resp = await self._call(
            "PUT", self._layer_path(session, name), f"cannot set layer {name}", json=spec
        )
        return LayerInfo.model_validate(resp.json())

    async def patch_layer(self, session: str, name: str, changes: dict[str, Any]) -> LayerInfo:
        resp = await self._call(
            "PATCH", self._layer_path(session, name), f"cannot change layer {name}", json=changes
        )
        return LayerInfo.model_validate(resp.json())

    async def remove_layer(self, session: str, name: str | None = None) -> None:
        """Remove layer ``name`` (None: every layer set over REST)."""
        await self._call(
            "DELETE", self._layer_path(session, name), f"cannot remove layer {name or '(all)'}"
        )


#: Messages a viewer's client library may hold before it stops reading the socket. Every frame
#: buffered between the server's slot and the consumer adds one frame interval of latency when
#: the consumer is slow, so viewers buffer little and let the server skip frames instead.
VIEWER_MAX_QUEUE = 2
#: Receive buffer of a viewer socket, bytes (the kernel doubles it).
VIEWER_RECEIVE_BUFFER = 128 * 1024


async def _socket(url: str, rcvbuf: int | None) -> socket.socket | None:
    """A connected TCP socket with a capped receive buffer (set before connecting), or None."""
    if rcvbuf is None:
        return None
    parts = urlsplit(url)
    port = parts.port or (443 if parts.scheme == "wss" else 80)
    loop = asyncio.get_running_loop()
    infos = await loop.getaddrinfo(parts.hostname, port, type=socket.SOCK_STREAM)
    family, type_, proto, _, addr = infos[0]
    sock = socket.socket(family, type_, proto)
    sock.setblocking(False)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    try:
        await asyncio.wait_for(loop.sock_connect(sock, addr), 30)
    except BaseException:
        sock.close()
        raise
    return sock


def _auth(token: str | None) -> dict[str, str]:
    """The handshake header carrying a session token (kept out of URLs, which servers log)."""
    return {"Authorization": f"Bearer {token}"} if token else {}


async def _connect(
    url: str,
    *,
    token: str | None = None,
    rcvbuf: int | None = None,
    max_queue: int = 16,
    keepalive: float | None = None,
) -> ClientConnection:
    """Open a WebSocket; ``keepalive`` (s): ping that often and drop a connection whose pong does
    not come back within as long (a node that vanished without closing its sockets)."""
    try:
        sock = await _socket(url, rcvbuf)
        return await connect(
            url,
            additional_headers=_auth(token),
            compression=None,
            max_size=MAX_MESSAGE,
            open_timeout=30,
            ping_interval=keepalive,
            ping_timeout=keepalive,
            max_queue=max_queue,
            sock=sock,
        )
    except (OSError, asyncio.TimeoutError) as e:
        raise LiveError(f"cannot connect to {url.split('?', maxsplit=1)[0]}: {e}") from None
    except InvalidStatus as e:  # a load balancer with no node behind it answers 502/503
        raise LiveError(
            f"WebSocket handshake with {url.split('?', maxsplit=1)[0]} failed: {e}",
            e.response.status_code,
        ) from None
    # the handshake refused (an HTTP status instead of 101) or a URL websockets cannot use
    except (WebSocketException, ValueError) as e:
        raise LiveError(
            f"WebSocket handshake with {url.split('?', maxsplit=1)[0]} failed: {e}"
        ) from None


def _closed_error(ws: ClientConnection, last_error: ErrorMessage | None) -> LiveError | None:
    """A ``LiveError`` for an error close, or None for a normal end."""
    code = ws.close_code or 0
    if code in (1000, 1001, 0) and last_error is None:
        return None
    if last_error is not None:
        return LiveError(
            f"server: {last_error.message}"
            + (
                f" ({last_error.where})"
                if last_error.where and last_error.where not in last_error.message
                else ""
            ),
            last_error.code,
        )
    if code in (1000, 1001):
        return None
    return LiveError(f"connection closed with code {code} {ws.close_reason or ''}".strip(), code)


# ----------------------------------------------------------------------------------------------- retry

#: Close codes and HTTP statuses after which the same request may succeed a moment later: the
#: connection was lost (0, 1006), the node is going away or restarting (1001, 1012, 1013), a load
#: balancer has no node behind it yet (502-504), the server has not yet seen this producer's
#: previous connection go (4409), a node fault (1011, 4500, 4502, 4503). An unknown session (4404,
#: 404: a node that lost it, or it is being taken over) is retried for ``Retry.missing`` seconds
#: only. Anything else (a wrong token, a closed session, a bad hello, a flood) is final.
RETRYABLE = frozenset(
    {0, 1001, 1006, 1011, 1012, 1013, 1014, 409, 500, 502, 503, 504} | {4409, 4500, 4502, 4503}
)
NOT_FOUND = frozenset({404, 4404})


@dataclass(frozen=True, slots=True)
class Retry:
    """How a producer or viewer reconnects after its connection dropped.

    Attributes:
        first: seconds before the first new try (doubles each failed try).
        cap: longest wait between two tries, seconds.
        give_up: seconds without a connection after which the last error is raised (None: never).
        missing: seconds an unknown session (4404) is retried: long enough for another node to
            take a session over, short enough to end a client whose session is gone.
        keepalive: ping interval and pong timeout, seconds: a connection to a node that vanished
            without closing it is dropped (and retried) after at most twice this.
    """

    first: float = 0.05
    cap: float = 1.0
    give_up: float | None = 60.0
    missing: float = 5.0
    keepalive: float | None = 5.0

    def delays(self, rng: random.Random | None = None) -> Iterator[float]:
        """Waits before each try: ``first * 2**n`` capped at ``cap``, each scaled by a random
        factor in [0.5, 1] so that the clients of one node do not all come back at once."""
        r = rng or random.Random()
        n = 0
        while True:
            yield min(self.cap, self.first * 2**n) * r.uniform(0.5, 1.0)
            n = min(n + 1, 30)


def retryable(err: LiveError) -> bool:
    """Whether ``err`` may go away by itself (``RETRYABLE``, or for a while ``NOT_FOUND``)."""
    return err.code in RETRYABLE or err.code in NOT_FOUND


async def reconnect(
    retry: Retry, open_: Callable[[], Awaitable[Any]], what: str, first_error: LiveError
) -> Any:
    """Call ``open_()`` after each of ``retry``'s delays until it returns; raise the last error
    when it is final or ``retry.give_up`` seconds have passed since the connection was lost."""
    t0, err = time.monotonic(), first_error
    missing_since: float | None = None
    for delay in retry.delays():
        if not retryable(err):
            raise err
        if err.code in NOT_FOUND:
            missing_since = missing_since or time.monotonic()
            if time.monotonic() + delay - missing_since > retry.missing:
                raise err
        else:
            missing_since = None
        if retry.give_up is not None and time.monotonic() + delay - t0 > retry.give_up:
            raise LiveError(
                f"{what}: gave up reconnecting after {retry.give_up:g} s: {err}", err.code
            )
        await asyncio.sleep(delay)
        try:
            return await open_()
        except LiveError as e:
            log.debug("%s: reconnecting: %s", what, e)
            err = e
    raise AssertionError("unreachable")  # pragma: no cover (delays() never ends)


# ---------------------------------------------------------------------------------------------- producer


class Producer:
    """A connected producer. Use ``produce(...)``; frames carry the sender's wall clock.

    With a ``retry`` policy (``produce(..., retry=Retry())``), a send that finds the connection
    lost reconnects (same hello) and drops that frame: live input is not worth sending late.
    ``reconnects`` counts the new connections, ``outages`` their lengths (s), ``dropped`` the frames
    that found no connection.
    """

    def __init__(
        self,
        ws: ClientConnection,
        ready: Ready,
        *,
        retry: Retry | None = None,
        reopen: Callable[[], Awaitable[tuple[ClientConnection, Ready]]] | None = None,
    ) -> None:
        self.ws = ws
        self.ready = ready
        self.seq = 0
        self.errors: list[ErrorMessage] = []
        #: errors the server closed a connection with, after which the producer reconnected
        self.recovered: list[ErrorMessage] = []
        self.retry, self._reopen = retry, reopen
        self.reconnects = 0
        self.outages: list[float] = []
        self.dropped = 0
        self._closing = False
        self._errors_before = 0  # errors of earlier connections (``errors`` keeps them all)
        self._reader = asyncio.get_running_loop().create_task(self._read(ws))

    async def _read(self, ws: ClientConnection) -> None:
        try:
            async for msg in ws:
                if isinstance(msg, str):
                    try:
                        m = parse_message(msg)
                    except ValueError:
                        continue
                    if isinstance(m, ErrorMessage):
                        self.errors.append(m)
                        log.warning("server: %s", m.message)
        except ConnectionClosed:
            pass

    def _next(self) -> int:
        s = self.seq
        self.seq = (self.seq + 1) & 0xFFFFFFFF
        return s

    async def _send(self, data: str | bytes) -> None:
        try:
            await self.ws.send(data)
            return
        except ConnectionClosed:
            await asyncio.sleep(0)  # let the reader take the error message sent before the close
            mine = self.errors[self._errors_before :]
            err = _closed_error(self.ws, mine[-1] if mine else None)
            if self.retry is None or self._reopen is None or self._closing:
                raise err or LiveError("the server closed the connection") from None
            if err is None:  # a normal close: 1001 (going away) is worth a new try, 1000 is the end
                if (self.ws.close_code or 0) == 1000:
                    raise LiveError("the server ended the stream") from None
                err = LiveError("the server is going away", self.ws.close_code or 1001)
        await self._reconnect(err, mine[-1] if mine else None)

    async def _reconnect(self, err: LiveError, cause: ErrorMessage | None = None) -> None:
        """New connection (same hello) after ``err``; the frame being sent is dropped. ``cause``,
        the error message the server closed with, moves from ``errors`` to ``recovered``."""
        assert self.retry is not None and self._reopen is not None
        t0 = time.monotonic()
        log.warning("producer: connection lost (%s); reconnecting", err)
        self._reader.cancel()
        ws, ready = await reconnect(self.retry, self._reopen, "producer", err)
        self.ws, self.ready = ws, ready
        if cause is not None and cause in self.errors:
            self.errors.remove(cause)
            self.recovered.append(cause)
        self._errors_before = len(self.errors)
        self._reader = asyncio.get_running_loop().create_task(self._read(ws))
        self.reconnects += 1
        self.dropped += 1
        self.outages.append(time.monotonic() - t0)
        log.warning("producer: reconnected after %.2f s", self.outages[-1])

    async def send_faps(
        self,
        faps: dict[int, float] | np.ndarray,
        t: float,
        *,
        viseme: tuple | None = None,
        expression: tuple | None = None,
        binary: bool = True,
    ) -> None:
        """One FAP frame at media time ``t``: ``{fap: value}`` (3..68) or a ``(68,)``/``(69,)`` vector
        (NaN = not sent); as a binary ``FAPS`` frame or, with ``binary=False``, a JSON ``fap`` message."""
        seq, wall = self._next(), time.time()
        if binary:
            if isinstance(faps, dict):
                v = np.full(frames.N_FAP_VALUES, np.nan, np.float32)
                for k, x in faps.items():
                    v[int(k) - 1] = x
            else:
                v = np.asarray(faps, np.float32)
            await self._send(
                frames.encode_faps(v, seq=seq, t=t, wall=wall, viseme=viseme, expression=expression)
            )
        else:
            if not isinstance(faps, dict):
                arr = np.asarray(faps, np.float64)
                arr = arr[1:] if arr.shape == (69,) else arr
                faps = {k + 1: float(x) for k, x in enumerate(arr) if k >= 2 and not np.isnan(x)}
            msg = FapMessage(
                seq=seq, t=t, wall=wall, faps=faps, viseme=viseme, expression=expression
            )
            await self._send(dump_message(msg))

    async def send_pcm(self, samples: np.ndarray, *, rate: int, sample_offset: int) -> None:
        """One mono chunk (int16 or float32) starting at ``sample_offset``."""
        await self._send(
            frames.encode_pcm(
                samples, rate=rate, sample_offset=sample_offset, seq=self._next(), wall=time.time()
            )
        )

    async def send_markers(self, markers: np.ndarray, t: float) -> None:
        """One ``(M, 3)`` marker frame (hello's name order, NaN = occluded) at media time ``t``."""
        await self._send(frames.encode_markers(markers, seq=self._next(), t=t, wall=time.time()))

    async def send_raw(self, data: str | bytes) -> None:
        """Send anything (tests of the server's error handling)."""
        await self._send(data)

    async def close(self) -> None:
        self._closing = True
        await self.ws.close()
        await asyncio.gather(self._reader, return_exceptions=True)


async def _open_producer(
    url: str, token: str, hello: ProducerHello, keepalive: float | None = None
) -> tuple[ClientConnection, Ready]:
    """Connect to ``url`` (a ``/produce`` WebSocket URL), send ``hello`` and wait for ``ready``;
    ``LiveError`` (with the server's close code) when the server refuses."""
    ws = await _connect(url, token=token, keepalive=keepalive)
    try:
        await ws.send(dump_message(hello))
    except ConnectionClosed:
        pass  # refused at once: the error message is still waiting to be read
    try:
        first = await ws.recv()
    except ConnectionClosed:
        first = None
    m = parse_message(first) if isinstance(first, str) else None
    if isinstance(m, Ready):
        return ws, m
    if first is not None and not isinstance(m, ErrorMessage):
        await ws.close()
    try:
        await asyncio.wait_for(ws.wait_closed(), 5)
    except asyncio.TimeoutError:
        pass
    raise _closed_error(ws, m if isinstance(m, ErrorMessage) else None) or LiveError(
        "the server did not accept the producer", ws.close_code or 0
    )


class produce:
    """``async with produce(url, session, token, ProducerHello(...)) as p:`` -> a ``Producer``.

    ``retry``: reconnect when an established connection drops (``Retry``); the first connection
    is not retried, so a wrong URL or token fails at once.
    """

    def __init__(
        self,
        url: str,
        session: str,
        token: str,
        hello: ProducerHello | None = None,
        *,
        retry: Retry | None = None,
    ) -> None:
        self.url = ws_url(url, f"/v1/sessions/{quote(session, safe='')}/produce")
        self.token = token
        self.hello = hello or ProducerHello()
        self.retry = retry
        self.producer: Producer | None = None

    def _open(self) -> Awaitable[tuple[ClientConnection, Ready]]:
        keepalive = self.retry.keepalive if self.retry else None
        return _open_producer(self.url, self.token, self.hello, keepalive)

    async def __aenter__(self) -> Producer:
        ws, ready = await self._open()
        self.producer = Producer(ws, ready, retry=self.retry, reopen=self._open)
        return self.producer

    async def __aexit__(self, *exc: object) -> None:
        if self.producer is not None:
            await self.producer.close()


# ------------------------------------------------------------------------------------------------ viewer


@dataclass(frozen=True, slots=True)
class WatchedFrame:
    """A received vertex frame.

    Attributes:
        frame: the decoded ``VertexFrame`` (header: ``seq``, ``t`` media s, ``wall`` producer send time).
        received: the viewer's wall clock at receipt (Unix seconds).
        size: bytes on the wire (payload of the WebSocket message).
        connection: which connection of the viewer brought it (0, then 1 after a reconnect, ...).
    """

    frame: frames.VertexFrame
    received: float
    size: int
    connection: int = 0

    @property
    def latency(self) -> float | None:
        """Seconds from the producer sending the input to this frame's receipt (same clock)."""
        w = self.frame.header.wall
        return self.received - w if w > 0 else None

    def positions(self) -> np.ndarray:
        return self.frame.positions()


class Watcher:
    """A connected viewer: ``async for f in watcher`` yields ``WatchedFrame``s until the connection
    ends (``LiveError`` if it ends with an error) or, with ``until_producer_leaves``, until the
    producer disconnects after frames were seen.

    With a ``retry`` policy (``watch(..., retry=Retry())``) a lost connection is opened again and
    the frames go on (``WatchedFrame.connection`` says which connection brought each);
    ``reconnects`` counts the new connections and ``outages`` their lengths (s).
    """

    def __init__(
        self,
        ws: ClientConnection,
        hello: ViewerHello,
        until_producer_leaves: bool = False,
        *,
        retry: Retry | None = None,
        reopen: Callable[[], Awaitable[tuple[ClientConnection, ViewerHello]]] | None = None,
    ) -> None:
        self.ws = ws
        self.hello = hello
        self.status: Status | None = None
        self.stats: Stats | None = None
        self.errors: list[ErrorMessage] = []
        self.until_producer_leaves = until_producer_leaves
        self._seen_frames = False
        self.compact: Any = (
            None  # ``CompactDecoder`` for the ``compact`` encoding (set by ``watch``)
        )
        self.waited = 0  # compact frames not shown: their key frame had not arrived
        self.bytes_received = 0  # binary bytes, all frames
        self.retry, self._reopen = retry, reopen
        self.reconnects = 0
        self.outages: list[float] = []
        self._errors_before = 0
        self._closing = False

    def __aiter__(self) -> AsyncIterator[WatchedFrame]:
        return self._frames()

    async def _lost(self) -> bool:
        """The connection ended: False (a normal end), ``LiveError``, or True once reconnected
        (``retry``)."""
        mine = self.errors[self._errors_before :]
        err = _closed_error(self.ws, mine[-1] if mine else None)
        if self.retry is None or self._reopen is None or self._closing:
            if err:
                raise err
            return False
        if err is None:
            if (self.ws.close_code or 0) == 1000:  # the server ended the stream
                return False
            err = LiveError("the server is going away", self.ws.close_code or 1001)
        t0 = time.monotonic()
        log.warning("viewer: connection lost (%s); reconnecting", err)
        self.ws, self.hello = await reconnect(self.retry, self._reopen, "viewer", err)
        self._errors_before = len(self.errors)
        self.reconnects += 1
        self.outages.append(time.monotonic() - t0)
        log.warning("viewer: reconnected after %.2f s", self.outages[-1])
        return True

    async def _frames(self) -> AsyncIterator[WatchedFrame]:
        while True:
            try:
                msg = await self.ws.recv()
            except ConnectionClosed:
                if await self._lost():
                    continue
                return
            if isinstance(msg, bytes):
                now = time.time()
                self.bytes_received += len(msg)
                if (
                    len(msg) > 5
                    and msg[5] == frames.Kind.VERTICES_COMPACT
                    and self.compact is not None
                ):
                    try:
                        out = self.compact.decode(msg)
                    except FrameError as e:
                        raise LiveError(f"bad compact frame from the server: {e}") from None
                    if out is None:
                        self.waited += 1
                        continue
                    self._seen_frames = True
                    yield WatchedFrame(
                        frames.VertexFrame(out[0], out[1]), now, len(msg), self.reconnects
                    )
                    continue
                f = frames.decode(msg)
                if not isinstance(f, frames.VertexFrame):
                    raise LiveError(f"unexpected {f.header.kind.name} frame from the server")
                self._seen_frames = True
                yield WatchedFrame(f, now, len(msg), self.reconnects)
                continue
            m = parse_message(msg)
            if isinstance(m, Status):
                self.status = m
                if self.until_producer_leaves and self._seen_frames and not m.producer_connected:
                    return
            elif isinstance(m, Stats):
                self.stats = m
            elif isinstance(m, ErrorMessage):
                self.errors.append(m)

    async def close(self) -> None:
        self._closing = True
        await self.ws.close()


class watch:
    """``async with watch(url, session, token) as w: async for f in w: ...``.

    ``encoding``: ``compact`` (default; within the session's tolerance, decoded here with the
    face's topology), ``i16`` or ``f32`` (exact).

    ``receive_buffer`` (bytes; None = the OS default, which grows to megabytes) and ``max_queue``
    (messages) bound what waits between the server and the consumer: small values keep latency low
    when the consumer is slow (the server skips frames instead) at some CPU cost per frame.

    ``retry``: reconnect when an established connection drops (``Retry``); the first connection is
    not retried.
    """

    def __init__(
        self,
        url: str,
        session: str,
        token: str,
        *,
        encoding: str = "compact",
        until_producer_leaves: bool = False,
        receive_buffer: int | None = VIEWER_RECEIVE_BUFFER,
        max_queue: int = VIEWER_MAX_QUEUE,
        retry: Retry | None = None,
    ) -> None:
        self.url = ws_url(url, f"/v1/sessions/{quote(session, safe='')}/watch", encoding=encoding)
        self.token = token
        self.http_url = url
        self.until = until_producer_leaves
        self.receive_buffer = receive_buffer
        self.max_queue = max_queue
        self.retry = retry
        self.watcher: Watcher | None = None
        self._topologies: dict[str, Any] = {}  # topology URL -> decoded topology
        self._decoder: Any = None  # the first connection's compact decoder

    async def _open(self) -> tuple[ClientConnection, ViewerHello]:
        """Connect, read the viewer hello and (compact) make a fresh decoder for its face."""
        ws = await _connect(
            self.url,
            token=self.token,
            rcvbuf=self.receive_buffer,
            max_queue=self.max_queue,
            keepalive=self.retry.keepalive if self.retry else None,
        )
        try:
            first = await ws.recv()
        except ConnectionClosed:
            raise _closed_error(ws, None) or LiveError(
                "the server closed the connection", ws.close_code or 0
            ) from None
        m = parse_message(first) if isinstance(first, str) else None
        if not isinstance(m, ViewerHello):
            try:
                await asyncio.wait_for(ws.wait_closed(), 5)
            except asyncio.TimeoutError:
                await ws.close()
            raise _closed_error(ws, m if isinstance(m, ErrorMessage) else None) or LiveError(
                f"expected a viewer hello, got {first!r:.100}"
            )
        if m.encoding == "compact":
            try:
                decoder = await self._compact_decoder(m.topology_url)
            except BaseException:
                await ws.close()
                raise
            if self.watcher is not None:
                self.watcher.compact = decoder
            else:
                self._decoder = decoder
        return ws, m

    async def _compact_decoder(self, topology_url: str) -> Any:
        """A new ``CompactDecoder`` for the face whose topology is at ``topology_url`` (fetched
        once per URL)."""
        from ..protocol.compact import CompactDecoder

        topo = self._topologies.get(topology_url)
        if topo is None:
            topo = self._topologies[topology_url] = await _topology(self.http_url, topology_url)
        return CompactDecoder(topo.vertices, topo.rigid_group)

    async def __aenter__(self) -> Watcher:
        ws, hello = await self._open()
        self.watcher = Watcher(ws, hello, self.until, retry=self.retry, reopen=self._open)
        self.watcher.compact = self._decoder
        return self.watcher

    async def __aexit__(self, *exc: object) -> None:
        if self.watcher is not None:
            await self.watcher.close()


async def _topology(url: str, topology_url: str) -> Any:
    """The decoded face topology at ``topology_url`` (relative to ``url``)."""
    from ..protocol.topology import decode_topology

    try:
        async with httpx.AsyncClient(timeout=60.0) as c:
            r = await c.get(server_url(url) + topology_url)
    except httpx.HTTPError as e:
        raise LiveError(f"fetching the face topology: cannot reach {url}: {e}") from None
    if r.status_code != 200:
        raise _http_error(r, "fetching the face topology for compact frames")
    try:
        return decode_topology(r.content)
    except ValueError as e:
        raise LiveError(f"the server's face topology is malformed: {e}") from None


def summary(frames_: list[WatchedFrame], *, first_seq: int | None = None) -> dict:
    """fps, latency p50/p95 (ms), bytes per frame, dropped frames (gaps in ``seq`` within one
    connection) and the longest time between two frames received (``max_gap_s``: a node going
    away, a failover, a stall) of a run."""
    n = len(frames_)
    out: dict[str, Any] = {"frames": n}
    if n == 0:
        return out
    seqs = np.array([f.frame.header.seq for f in frames_], dtype=np.int64)
    conns = np.array([getattr(f, "connection", 0) for f in frames_], dtype=np.int64)
    received = np.array([f.received for f in frames_], dtype=np.float64)
    gaps = np.diff(seqs) % (1 << 32) - 1
    # a frame number going back (a session resumed elsewhere numbers anew) or a new connection
    # is not a drop
    counted = (gaps > 0) & (gaps < 1 << 31) & (np.diff(conns) == 0)
    dropped = int(gaps[counted].sum()) if n > 1 else 0
    span = frames_[-1].received - frames_[0].received
    lat = np.array([f.latency for f in frames_ if f.latency is not None], dtype=np.float64) * 1000
    out.update(
        {
            "fps": round((n - 1) / span, 2) if span > 0 else None,
            "latency_ms_p50": round(float(np.percentile(lat, 50)), 2) if lat.size else None,
            "latency_ms_p95": round(float(np.percentile(lat, 95)), 2) if lat.size else None,
            "latency_ms_max": round(float(lat.max()), 2) if lat.size else None,
            "max_gap_s": round(float(np.diff(received).max()), 3) if n > 1 else None,
            "bytes_per_frame": round(float(np.mean([f.size for f in frames_])), 1),
            "bits_per_second": round(8 * sum(f.size for f in frames_[1:]) / span)
            if span > 0
            else None,
            "dropped": dropped,
            "first_seq": int(seqs[0]),
            "last_seq": int(seqs[-1]),
            "seconds": round(span, 3),
        }
    )
    return out


# ---------------------------------------------------------------------------------------------- pacing


class Pacer:
    """Sleeps until media time ``t`` (seconds) is due on the wall clock, at ``speed`` x real time.

    ``late``: ``until`` returns False (skip this item) for an item already more than ``late``
    seconds overdue, e.g. after a reconnection, so that a live stream goes on from where the clock
    is instead of sending what it missed in a burst; None: never skip.
    """

    def __init__(self, speed: float = 1.0, *, late: float | None = None) -> None:
        self.speed = speed
        self.late = late
        self.t0 = time.monotonic()

    async def until(self, t: float) -> bool:
        if self.speed <= 0:  # as fast as possible
            await asyncio.sleep(0)
            return True
        delay = self.t0 + t / self.speed - time.monotonic()
        if delay > 0:
            await asyncio.sleep(delay)
        return self.late is None or -delay <= self.late


def fap_frames(fap: Any) -> list[tuple[float, dict[int, float], tuple | None, tuple | None]]:
    """A ``protocol.fap_file.FapFile`` -> ``(t, faps, viseme, expression)`` per frame (masked FAPs only;
    the server keeps unsent FAPs at their previous value, like the batch reader)."""
    fps = float(fap.fps)
    out = []
    for i, fr in enumerate(fap.frames):
        vis = exp = None
        if not fr.single_high_level:
            vis = tuple(int(x) for x in fr.viseme[:3]) if fr.viseme is not None else None
            exp = tuple(int(x) for x in fr.expression[:4]) if fr.expression is not None else None
        out.append((i / fps, {k: float(v) for k, v in fr.faps().items()}, vis, exp))
    return out


async def stream_fap(
    producer: Producer, fap: Any, *, speed: float = 1.0, binary: bool = True, t_offset: float = 0.0
) -> int:
    """Send every frame of a ``FapFile`` paced at its frame rate; returns the number of frames sent."""
    pacer = Pacer(speed)
    n = 0
    for t, faps, vis, exp in fap_frames(fap):
        await pacer.until(t)
        await producer.send_faps(faps, t + t_offset, viseme=vis, expression=exp, binary=binary)
        n += 1
    return n


async def stream_pcm(
    producer: Producer,
    samples: np.ndarray,
    rate: int,
    *,
    chunk: float = 0.02,
    speed: float = 1.0,
    sample_offset: int = 0,
) -> int:
    """Send mono int16/float32 ``samples`` in ``chunk``-second pieces at real time (the first at
    ``sample_offset``); returns chunks sent."""
    pacer = Pacer(speed)
    step = max(1, int(round(chunk * rate)))
    n = 0
    for start in range(0, len(samples), step):
        await pacer.until(start / rate)
        await producer.send_pcm(
            samples[start : start + step], rate=rate, sample_offset=sample_offset + start
        )
        n += 1
    return n


async def stream_markers(
    producer: Producer, xyz: np.ndarray, fps: float, *, t0: float = 0.0, speed: float = 1.0
) -> int:
    """Send ``(T, M, 3)`` marker positions frame by frame at ``fps``; returns frames sent."""
    pacer = Pacer(speed)
    for i in range(len(xyz)):
        t = t0 + i / fps
        await pacer.until(t - t0)
        await producer.send_markers(np.asarray(xyz[i], np.float32), t)
    return len(xyz)
