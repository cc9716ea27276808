"""Live sessions: REST create/list/info/close (admin) and the producer and viewer WebSockets.

The handlers are shells: they check credentials and limits, decode with ``facecast.protocol``, hand
face states to ``server.live`` and send what it encoded. Every refusal on a WebSocket is one JSON
``error`` message, then a close with the same 4xxx code (``protocol/README.md`` lists them).
"""

from __future__ import annotations

import asyncio
import logging
import socket
import time
from typing import Any
from urllib.parse import quote

import numpy as np
from fastapi import APIRouter, Depends, Request, Response, WebSocket, status
from starlette.websockets import WebSocketDisconnect, WebSocketState

from ...protocol import frames
from ...protocol.encoding import parse_vertex_encoding
from ...protocol.errors import CloseCode, FrameError, MessageError
from ...protocol.messages import (
    ErrorMessage,
    FapMessage,
    ProducerHello,
    Ready,
    SessionCreate,
    SessionCreated,
    SessionInfo,
    SessionList,
    ViewerHello,
    dump_message,
    parse_message,
)
from ..errors import FacecastError
from ..live.budget import Budget, Limits, Verdict, producer_limits, viewer_limits
from ..live.wire import DirectSender, ViewerGone, find_protocol
from .security import require_admin, same, ws_token

log = logging.getLogger(__name__)

router = APIRouter(tags=["sessions"])

#: Seconds a producer has to send its hello.
HELLO_TIMEOUT = 10.0
#: Kernel send buffer of a viewer socket, in vertex frames (see ``_limit_send_buffer``).
VIEWER_SEND_BUFFER_FRAMES = 1
MIN_SEND_BUFFER = 64 * 1024
#: Kernel receive buffer of a producer socket: what one read hands the event loop at most (a read
#: of tiny frames is parsed in one go, so a flood's reads stay short); ample for 1 s audio chunks.
PRODUCER_RECEIVE_BUFFER = 64 * 1024
#: A receive loop yields to the event loop after this many messages: ``receive`` does not suspend
#: while messages are queued, so without it one flooding socket would hold the loop.
YIELD_EVERY = 8


def registry(app: Any):
    """The app's ``SessionRegistry`` (created on first use from ``app.state.config``)."""
    reg = getattr(app.state, "live", None)
    if reg is None:
        from ..live import SessionRegistry

        cfg = app.state.config
        reg = SessionRegistry(
            app.state.store,
            max_sessions=cfg.max_sessions,
            max_viewers=cfg.max_viewers_per_session,
            max_fps=cfg.max_producer_fps,
            metrics=getattr(app.state, "metrics", None),
            idle_seconds=cfg.session_idle_seconds,
        )
        app.state.live = reg
    return reg


# ------------------------------------------------------------------------------------------------ REST


@router.post(
    "/v1/sessions",
    status_code=status.HTTP_201_CREATED,
    response_model=SessionCreated,
    dependencies=[Depends(require_admin)],
    responses={
        401: {"description": "admin key missing or wrong"},
        404: {"description": "no such face"},
        429: {"description": "the server's session limit is reached"},
        503: {"description": "the driver for this input kind is not installed"},
    },
)
async def create_session(request: Request, body: SessionCreate | None = None) -> SessionCreated:
    """Open a live session; the answer's tokens are shown only once."""
    reg = registry(request.app)
    return reg.created(await reg.create(body or SessionCreate()))


@router.get("/v1/sessions", response_model=SessionList, dependencies=[Depends(require_admin)])
async def list_sessions(request: Request) -> SessionList:
    reg = registry(request.app)
    return SessionList(sessions=[reg.info(s) for s in reg.sessions.values()])


@router.get(
    "/v1/sessions/{session_id}", response_model=SessionInfo, dependencies=[Depends(require_admin)]
)
async def get_session(session_id: str, request: Request) -> SessionInfo:
    reg = registry(request.app)
    return reg.info(reg.get(session_id))


@router.delete(
    "/v1/sessions/{session_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    dependencies=[Depends(require_admin)],
)
async def close_session(session_id: str, request: Request) -> Response:
    """Close a session: its producer and viewers get an error 4000 and are disconnected."""
    await registry(request.app).close(session_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


# ------------------------------------------------------------------------------------------- WebSocket


def _error(
    code: int, message: str, *, where: str = "", fatal: bool = False, seq: int | None = None
) -> str:
    return dump_message(
        ErrorMessage(code=int(code), message=message, where=where, fatal=fatal, seq=seq)
    )


def _reason(message: str) -> str:
    """``message`` cut to fit a close frame's reason (123 bytes of UTF-8)."""
    raw = message.encode("utf-8", "replace")
    return raw.decode() if len(raw) <= 123 else raw[:120].decode("utf-8", "ignore") + "..."


async def _refuse(ws: WebSocket, code: int, message: str, where: str = "") -> None:
    """Send one fatal error message and close with ``code`` (the message, cut, is the reason)."""
    try:
        await ws.send_text(_error(code, message, where=where, fatal=True))
        await ws.close(int(code), _reason(message))
    except Exception:  # the peer is already gone
        pass


#: Close code of a budget verdict that ends the connection.
_CLOSE = {Verdict.TOO_BIG: CloseCode.TOO_BIG, Verdict.FLOOD: CloseCode.POLICY_VIOLATION}
#: Seconds a flooding client has to read its close frame before its connection is dropped.
CUT_OFF_GRACE = 1.0


def _transport(ws: WebSocket) -> Any:
    """The asyncio transport under a live connection, or None (ASGI servers other than uvicorn)."""
    return getattr(find_protocol(getattr(ws, "_send", None)), "transport", None)


def _cut_off(ws: WebSocket) -> None:
    """Stop reading a flooding connection now (its queued bytes are never parsed) and drop it after
    ``CUT_OFF_GRACE`` seconds, whether or not it answers the close frame. Best effort."""
    transport = _transport(ws)
    if transport is None or transport.is_closing():
        return
    try:
        transport.pause_reading()
    except RuntimeError:  # pragma: no cover - already closing
        return
    asyncio.get_running_loop().call_later(CUT_OFF_GRACE, transport.abort)


async def _accept(ws: WebSocket, query_token: str | None) -> str | None:
    """Accept the handshake (with the ``facecast.v1`` subprotocol if offered); the token sent."""
    token, subprotocol = ws_token(ws.headers, ws.scope.get("subprotocols") or [], query_token)
    await ws.accept(subprotocol=subprotocol)
    return token


async def _authorise(ws: WebSocket, session_id: str, token: str | None, role: str):
    """The session if ``token`` is its ``role`` token; else refuse and return None."""
    reg = registry(ws.app)
    session = reg.sessions.get(session_id)
    if session is None:
        await _refuse(
            ws,
            CloseCode.NOT_FOUND,
            f"no live session {session_id!r}; it was closed or never existed",
        )
        return None
    mine, other = (
        (session.spec.producer_token, session.spec.viewer_token)
        if role == "producer"
        else (session.spec.viewer_token, session.spec.producer_token)
    )
    if same(token, mine):
        return session
    if same(token, other):
        await _refuse(
            ws,
            CloseCode.FORBIDDEN,
            f"this token is the session's {'viewer' if role == 'producer' else 'producer'}"
            f" token; {role}s need the {role} token",
            where="token",
        )
    else:
        await _refuse(
            ws,
            CloseCode.UNAUTHORIZED,
            f"missing or wrong {role} token: send 'Authorization: Bearer <{role}_token from "
            "POST /v1/sessions>' (browsers: the subprotocols 'facecast.v1' and "
            f"'facecast.token.<{role}_token>')",
            where="token",
        )
    return None


class _Producer:
    """The connected producer, as the session sees it (so an admin close can end it)."""

    remote = True  # a client's producer: the session is in use (``LiveSession.busy``)

    def __init__(self, ws: WebSocket) -> None:
        self.ws = ws

    async def end(self, code: int, error_json: str) -> None:
        try:
            await self.ws.send_text(error_json)
            await self.ws.close(int(code))
        except Exception:
            pass


@router.websocket("/v1/sessions/{session_id}/produce")
async def produce(ws: WebSocket, session_id: str, token: str | None = None) -> None:
    """Producer: hello, then FAP frames / PCM chunks / marker frames (``protocol/README.md``).

    The token: ``Authorization: Bearer``, a ``facecast.token.<token>`` subprotocol, or ``?token=``.
    """
    token = await _accept(ws, token)
    session = await _authorise(ws, session_id, token, "producer")
    if session is None:
        return
    if session.producer is not None:
        await _refuse(
            ws,
            CloseCode.CONFLICT,
            "this session already has a producer; only one may send at a time "
            "(connect again once it has disconnected)",
        )
        return
    reg = registry(ws.app)
    _set_buffer(ws, socket.SO_RCVBUF, PRODUCER_RECEIVE_BUFFER)
    me = _Producer(ws)
    session.producer = me  # claim before any await, so a second producer is refused
    metrics = reg.metrics
    if metrics:
        metrics.producers.inc()
    loop = asyncio.get_running_loop()
    try:
        hello = await _producer_hello(ws, session, reg, loop)
        if hello is None:
            return
        inp, limits = hello
        session.set_producer(me)  # tells viewers
        await _producer_loop(ws, session, reg, inp, limits)
    except (WebSocketDisconnect, OSError):  # the producer went away mid-send
        pass
    except Exception:
        log.exception("session %s: producer failed", session_id)
        await _refuse(ws, CloseCode.INTERNAL, "internal error; the server log has the details")
    finally:
        if session.producer is me:
            session.set_producer(None)
        if metrics:
            metrics.producers.dec()


async def _producer_hello(ws: WebSocket, session, reg, loop):
    """Wait for the hello; ``(input, limits)``, or None (after refusing) if it is unusable."""
    from ..live.inputs import BadHello, InputUnavailable, make_input

    try:
        msg = await asyncio.wait_for(ws.receive(), HELLO_TIMEOUT)
    except asyncio.TimeoutError:
        await _refuse(
            ws,
            CloseCode.TIMEOUT,
            f"no hello within {HELLO_TIMEOUT:g} s; send "
            '{"type": "hello", "role": "producer", "input": ...} first',
        )
        return None
    if msg["type"] == "websocket.disconnect":
        return None
    text = msg.get("text")
    try:
        if text is None:
            raise MessageError("the first message must be a JSON hello, not a binary frame")
        hello = parse_message(text)
        if not isinstance(hello, ProducerHello):
            raise MessageError(f"the first message must be a producer hello, got '{hello.type}'")
        if hello.protocol != frames.VERSION:
            raise MessageError(
                f"protocol version {hello.protocol} is not supported (server speaks {frames.VERSION})",
                where="hello.protocol",
            )
        inp = await loop.run_in_executor(
            reg.executor, make_input, session.spec.input, session.face, hello, session.spec.fps
        )
        await _follow_controls(session, reg, inp)
    except (MessageError, BadHello) as e:
        await _refuse(ws, CloseCode.BAD_REQUEST, str(e), where=getattr(e, "where", ""))
        return None
    except InputUnavailable as e:
        await _refuse(ws, CloseCode.UNAVAILABLE, str(e))
        return None
    except FacecastError as e:
        await _refuse(ws, CloseCode.BAD_REQUEST, str(e), where=e.where)
        return None
    await ws.send_text(
        dump_message(
            Ready(
                session=session.spec.id,
                input=session.spec.input,
                fps=session.spec.fps,
                max_fps=reg.max_fps,
                vertex_count=session.vertex_count,
            )
        )
    )
    limits = producer_limits(
        session.spec.input,
        reg.max_fps,
        rate=hello.rate,
        sample_format=hello.sample_format,
        markers=len(hello.markers or ()),
    )
    return inp, limits


async def _follow_controls(session, reg, inp) -> None:
    """Give the session an animator for the input's explicit control vertices (mocap), once known."""
    cv = inp.control_vertices
    current = getattr(session, "control_vertices", None)
    if cv is None or (current is not None and np.array_equal(cv, current)):
        return
    loop = asyncio.get_running_loop()
    animator = await loop.run_in_executor(reg.executor, reg.animator_for, session, cv)
    session.batcher = reg.batcher_for(animator)
    session.control_vertices = np.array(cv)


async def _producer_loop(ws: WebSocket, session, reg, inp, limits: Limits) -> None:
    """Receive frames until the producer leaves; raw messages meet the budget before decoding."""
    loop = asyncio.get_running_loop()
    budget = Budget(limits)
    inline = session.spec.input == "fap"  # audio / mocap drivers do real work: run them in a thread
    metrics = reg.metrics
    received = 0
    while not session.closed:
        msg = await ws.receive()
        if msg["type"] == "websocket.disconnect":
            tail = await loop.run_in_executor(reg.executor, inp.flush)  # states held for look-ahead
            if tail:
                session.submit(tail, wall=time.time())
            return
        received += 1
        if received % YIELD_EVERY == 0:
            await asyncio.sleep(0)
        data, text = msg.get("bytes"), msg.get("text")
        size = len(data) if data is not None else len(text or "")
        now = time.monotonic()
        verdict, why = budget.check(size, data is None, now)
        if verdict is not Verdict.OK:
            session.stats["frames_rejected"] += 1
            if metrics:
                metrics.live_refused.labels(verdict.name.lower()).inc()
            if verdict is Verdict.DROP:
                if budget.warn_now(now):
                    await ws.send_text(_error(CloseCode.TOO_MANY, why))
                continue
            code = _CLOSE[verdict]
            log.warning("session %s: producer disconnected (%d): %s", session.spec.id, code, why)
            await _refuse(ws, code, why)
            _cut_off(ws)
            return
        seq: int | None = None
        try:
            if data is not None:
                frame = frames.decode(data, kinds=inp.kinds)
                seq, wall = frame.header.seq, frame.header.wall
                states = (
                    inp.push_frame(frame)
                    if inline
                    else await loop.run_in_executor(reg.executor, inp.push_frame, frame)
                )
            else:
                m = parse_message(text or "")
                if not isinstance(m, FapMessage):
                    raise MessageError(
                        f"producers send 'fap' messages or binary frames after the hello, "
                        f"not '{m.type}'",
                        where="type",
                    )
                seq, wall = m.seq, m.wall
                states = inp.push_message(m)
        except (
            FrameError,
            MessageError,
            ValueError,
            FacecastError,
        ) as e:  # the frame's fault, not ours
            session.stats["frames_rejected"] += 1
            if seq is None and data is not None:
                try:  # name the offending frame when its header is readable
                    seq = frames.parse_header(data).seq
                except FrameError:
                    pass
            await ws.send_text(
                _error(
                    CloseCode.BAD_REQUEST,
                    f"frame dropped: {e}",
                    where=getattr(e, "where", ""),
                    seq=seq,
                )
            )
            continue
        except Exception:
            log.exception(
                "session %s: the %s driver failed on a frame", session.spec.id, session.spec.input
            )
            session.stats["frames_rejected"] += 1
            await ws.send_text(
                _error(
                    CloseCode.INTERNAL,
                    "frame dropped: the driver failed (see the server log)",
                    seq=seq,
                )
            )
            continue
        session.stats["frames_in"] += 1
        if metrics:
            metrics.frames_in.inc()
        if not inline:
            await _follow_controls(session, reg, inp)
        session.submit(states, wall)


@router.websocket("/v1/sessions/{session_id}/watch")
async def watch(
    ws: WebSocket, session_id: str, token: str | None = None, encoding: str = "f32"
) -> None:
    """Viewer: a JSON hello, then binary vertex frames (newest only for a slow viewer).

    The token: ``Authorization: Bearer``, a ``facecast.token.<token>`` subprotocol, or ``?token=``.
    """
    from ..live.session import Viewer

    token = await _accept(ws, token)
    session = await _authorise(ws, session_id, token, "viewer")
    if session is None:
        return
    try:
        encoding = parse_vertex_encoding(encoding)
    except MessageError as e:
        await _refuse(ws, e.close_code, str(e), where=e.where)
        return
    if len(session.viewers) + session.joining >= session.spec.max_viewers:
        await _refuse(
            ws,
            CloseCode.TOO_MANY,
            f"this session already has {len(session.viewers)} viewers, its limit",
        )
        return
    sp = session.spec
    session.joining += 1  # counts against the limit while the hello is on its way
    try:
        await ws.send_text(
            dump_message(
                ViewerHello(
                    session=sp.id,
                    face=sp.face,
                    topology_url=f"/v1/faces/{quote(sp.face, safe='')}/topology",
                    vertex_count=session.vertex_count,
                    encoding=encoding,
                    fps=sp.fps,
                    input=sp.input,
                    producer_connected=session.producer is not None,
                    tolerance=sp.tolerance / session.face.mm_per_unit if encoding == "compact" else None,
                )
            )
        )
    except Exception:
        return  # gone already
    finally:
        session.joining -= 1
    if session.closed:
        await _refuse(ws, CloseCode.SESSION_CLOSED, "the session was closed")
        return
    frame_bytes = frames.frame_size(
        frames.Header(
            frames.Kind.VERTICES_I16 if encoding == "i16" else frames.Kind.VERTICES_F32,
            0,
            session.vertex_count,
            0.0,
        )
    )
    if encoding == "compact":  # a key frame is about a byte per vertex, a delta a fifth of that
        frame_bytes = session.vertex_count
        _limit_write_buffer(ws, VIEWER_SEND_BUFFER_FRAMES * frame_bytes)
    _limit_send_buffer(ws, VIEWER_SEND_BUFFER_FRAMES * frame_bytes)
    viewer = Viewer(encoding, DirectSender.attach(ws))  # pre-framed bytes straight to the transport
    session.add_viewer(viewer)
    sender = asyncio.create_task(_send_loop(ws, session, viewer))
    receiver = asyncio.create_task(_drain(ws, session, registry(ws.app).metrics))
    try:
        await asyncio.wait({sender, receiver}, return_when=asyncio.FIRST_COMPLETED)
    finally:
        session.remove_viewer(viewer)
        for task in (sender, receiver):
            task.cancel()
        await asyncio.gather(sender, receiver, return_exceptions=True)
        if (
            ws.application_state == WebSocketState.CONNECTED
            and ws.client_state == WebSocketState.CONNECTED
        ):
            try:
                await ws.close()
            except Exception:
                pass


def _set_buffer(ws: WebSocket, option: int, nbytes: int) -> None:
    """Set a socket buffer size (``SO_SNDBUF`` / ``SO_RCVBUF``) of the connection; best effort."""
    try:
        transport = _transport(ws)
        sock = transport.get_extra_info("socket") if transport is not None else None
        if sock is not None:
            sock.setsockopt(socket.SOL_SOCKET, option, int(nbytes))
    except (OSError, AttributeError):  # pragma: no cover - depends on the ASGI server
        log.debug("cannot set a socket buffer of a live connection", exc_info=True)


def _limit_send_buffer(ws: WebSocket, nbytes: int) -> None:
    """Cap the kernel send buffer of a viewer's socket at about ``nbytes``.

    Loopback and LAN sockets auto-tune their buffers to megabytes, i.e. dozens of 25k-vertex frames:
    a viewer that reads too slowly would then see old frames (latency grows) instead of skipped
    ones. With a small buffer the backlog stays in the viewer's one-frame slot, where a newer frame
    replaces it. Best effort: servers that hide the transport keep their defaults.
    """
    _set_buffer(ws, socket.SO_SNDBUF, max(MIN_SEND_BUFFER, int(nbytes)))


def _limit_write_buffer(ws: WebSocket, nbytes: int) -> None:
    """Pause writing to a viewer once about ``nbytes`` wait in its transport (asyncio's default,
    64 KiB, is dozens of compact frames: a slow viewer would fall behind instead of skipping)."""
    try:
        transport = _transport(ws)
        if transport is not None:
            transport.set_write_buffer_limits(high=max(4096, int(nbytes)))
    except (AttributeError, NotImplementedError, ValueError):  # pragma: no cover - ASGI server
        log.debug("cannot set the write buffer limit of a viewer", exc_info=True)


async def _send_loop(ws: WebSocket, session, viewer) -> None:
    unsent = 0
    direct = viewer.direct
    log.debug(
        "session %s: viewer frames go %s", session.spec.id, "direct" if direct else "through ASGI"
    )
    try:
        while True:
            kind, payload = await viewer.next()
            if kind == "bytes":
                if direct is not None:
                    await direct.send(payload[1])
                else:
                    await ws.send_bytes(bytes(payload[0]))
                viewer.sent += 1
                unsent += 1
                if (
                    unsent >= 32
                ):  # count in batches: a Prometheus counter update per send is measurable
                    session.count_sent(unsent)
                    unsent = 0
            elif kind == "text":
                await ws.send_text(payload)
            else:
                code, text = payload
                await ws.send_text(text)
                await ws.close(int(code))
                return
    except (WebSocketDisconnect, RuntimeError, OSError, ViewerGone):
        return  # the viewer went away
    finally:
        session.count_sent(unsent)


async def _drain(ws: WebSocket, session, metrics) -> None:
    """Read (and ignore) what the viewer sends, so its departure is noticed at once; a viewer that
    floods or sends an oversized message is disconnected (1008 / 1009)."""
    budget = Budget(viewer_limits())
    received = 0
    try:
        while True:
            msg = await ws.receive()
            if msg["type"] == "websocket.disconnect":
                return
            received += 1
            if received % YIELD_EVERY == 0:
                await asyncio.sleep(0)
            data, text = msg.get("bytes"), msg.get("text")
            verdict, why = budget.check(
                len(data) if data is not None else len(text or ""), data is None, time.monotonic()
            )
            if verdict in (Verdict.FLOOD, Verdict.TOO_BIG):
                if metrics:
                    metrics.live_refused.labels(verdict.name.lower()).inc()
                code = _CLOSE[verdict]
                log.warning("session %s: viewer disconnected (%d): %s", session.spec.id, code, why)
                await _refuse(ws, code, f"viewers only listen: {why}")
                _cut_off(ws)
                return
    except (WebSocketDisconnect, RuntimeError, OSError):
        return
