"""Live sessions: REST create/list/info/close (admin) and the producer and viewer WebSockets.

The WebSocket handlers are shells: they receive, feed the connection's sans-I/O core
(``live.producer.ProducerCore``, ``live.watch.ViewerCore``) and carry out the ``Step`` it returns:
send its messages, run its blocking work in a thread, close as it decided. Every refusal is one JSON
``error`` message, then a close with the same code (``protocol/README.md`` lists them). Transport
tricks (socket buffers, cutting a flood off, direct sends) are in ``transport``.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

from fastapi import APIRouter, Depends, Request, Response, WebSocket, status
from starlette.websockets import WebSocketDisconnect, WebSocketState

from ...protocol.messages import SessionCreate, SessionCreated, SessionInfo, SessionList
from ..errors import FacecastError
from ..live.core import NOTHING, Close, Step, authorise
from ..live.producer import HELLO_TIMEOUT, ProducerCore
from ..live.registry import SessionRegistry
from ..live.session import LiveSession, Viewer
from ..live.watch import ViewerCore
from . import transport
from .routes_cluster import cluster_of, forward_producer
from .security import require_admin, ws_token

log = logging.getLogger(__name__)

router = APIRouter(tags=["sessions"])

#: A receive loop yields to the event loop after this many messages: ``receive`` does not suspend
#: while messages are queued, so without it one flooding socket would hold the loop.
YIELD_EVERY = 8


def registry(app: Any) -> SessionRegistry:
    """The app's ``SessionRegistry`` (created on first use from ``app.state.config``)."""
    reg = getattr(app.state, "live", None)
    if reg is None:
        cfg = app.state.config
        reg = SessionRegistry(
            app.state.store,
            max_sessions=cfg.max_sessions,
            max_viewers=cfg.max_viewers_per_session,
            max_fps=cfg.max_producer_fps,
            metrics=getattr(app.state, "metrics", None),
            idle_seconds=cfg.session_idle_seconds,
            settings=cfg.live_settings(),
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
    cluster = cluster_of(request.app)
    if cluster is not None:
        cluster.require()  # 503 while the cluster's Redis is unreachable
    session = await reg.create(body or SessionCreate.model_validate({}))
    if cluster is not None:
        try:
            await cluster.register(session)
        except Exception:
            await reg.close(session.spec.id, "the cluster's Redis is unreachable")
            raise
    return reg.created(session)


@router.get("/v1/sessions", response_model=SessionList, dependencies=[Depends(require_admin)])
async def list_sessions(request: Request) -> SessionList:
    reg, cluster = registry(request.app), cluster_of(request.app)
    local = [reg.info(s) for s in reg.sessions.values()]
    if cluster is not None:  # the cluster's: the others with their owners' last counters
        local += [i for i in await cluster.infos() if i.id not in reg.sessions]
    return SessionList(sessions=local)


@router.get(
    "/v1/sessions/{session_id}", response_model=SessionInfo, dependencies=[Depends(require_admin)]
)
async def get_session(session_id: str, request: Request) -> SessionInfo:
    reg, cluster = registry(request.app), cluster_of(request.app)
    if cluster is not None and session_id not in reg.sessions:  # another node owns it
        found = await cluster.infos([session_id])
        if found:
            info: SessionInfo = found[0]
            return info
    return reg.info(reg.get(session_id))


@router.delete(
    "/v1/sessions/{session_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    dependencies=[Depends(require_admin)],
)
async def close_session(session_id: str, request: Request) -> Response:
    """Close a session: its producer and viewers get an error 4000 and are disconnected."""
    reg, cluster = registry(request.app), cluster_of(request.app)
    if cluster is not None and session_id not in reg.sessions:
        await cluster.close_remote(session_id, "the session was closed by an admin")
    else:
        await reg.close(session_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


# ------------------------------------------------------------------------------------------- WebSocket


async def _send_all(ws: WebSocket, texts: tuple[str, ...]) -> None:
    for text in texts:
        await ws.send_text(text)


async def _refuse(ws: WebSocket, close: Close) -> None:
    """Carry out a close decision: the fatal error message, the close frame (the message, cut, is
    the reason), and for a flood the cut-off. The peer may be gone already."""
    try:
        await ws.send_text(close.error)
        await ws.close(int(close.code), close.reason)
    except Exception:  # the peer is already gone
        pass
    if close.cut_off:
        transport.cut_off(ws)


async def _accept(ws: WebSocket, query_token: str | None) -> str | None:
    """Accept the handshake (with the ``facecast.v1`` subprotocol if offered); the token sent."""
    token, subprotocol = ws_token(ws.headers, ws.scope.get("subprotocols") or [], query_token)
    await ws.accept(subprotocol=subprotocol)
    return token


async def _authorise(
    ws: WebSocket, session_id: str, token: str | None, role: str
) -> LiveSession | None:
    """The session if ``token`` is its ``role`` token (for producers: any of its producer tokens,
    whatever its roles); else refuse and return None."""
    session = registry(ws.app).sessions.get(session_id)
    cluster = cluster_of(ws.app)
    if session is None and cluster is not None:  # another node's: this node's mirror of it
        try:
            session = await cluster.mirror(session_id)
        except FacecastError as e:  # the broker is down, or the face is unknown here
            await _refuse(ws, Close(e.close_code, str(e)))
            return None
    sp = session.spec if session is not None else None
    mine, other = (
        ("", "")
        if sp is None
        else (sp.producer_token, sp.viewer_token)
        if role == "producer"
        else (sp.viewer_token, sp.producer_token)
    )
    if session is not None and role == "producer" and session.grants.roles_of(token):
        mine = token or ""  # a scoped producer token
    refusal = authorise(session_id, session is not None, token, mine, other, role)
    if refusal is not None:
        await _refuse(ws, refusal)
        return None
    return session


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
    reg, cluster = registry(ws.app), cluster_of(ws.app)
    if cluster is not None and session_id not in reg.sessions:  # another node owns it
        await forward_producer(ws, cluster, session_id, token)
        return
    session = await _authorise(ws, session_id, token, "producer")
    if session is None:
        return
    core = ProducerCore(
        session,
        _Producer(ws),
        animators=reg,
        max_fps=reg.max_fps,
        metrics=reg.metrics,
        roles=session.grants.roles_of(token) or frozenset(),
    )
    step = core.connect()
    if step.close is not None:
        await _refuse(ws, step.close)
        return
    transport.limit_receive_buffer(ws)
    try:
        await _produce(ws, core, reg)
    except (WebSocketDisconnect, OSError):  # the producer went away mid-send
        pass
    except Exception as e:
        step = core.failed(e)
        if step.close is not None:
            await _refuse(ws, step.close)
    finally:
        core.close()


async def _produce(ws: WebSocket, core: ProducerCore, reg: SessionRegistry) -> None:
    """Receive until the producer leaves or the core closes; carry out each step. Binary messages
    are taken in the connection's callback while this waits (``transport.DirectReceiver``)."""
    try:
        msg = await asyncio.wait_for(ws.receive(), HELLO_TIMEOUT)
    except asyncio.TimeoutError:  # (TimeoutError itself from Python 3.11 on)
        await _carry_out(ws, core.timeout(), reg)
        return
    direct = transport.DirectReceiver.attach(ws, core.take_bytes, reg.settings.direct)
    received = 0
    try:
        while True:
            if msg["type"] == "websocket.disconnect":
                await _carry_out(ws, core.disconnected(), reg)
                return
            step = msg.get(transport.HANDED)  # what a message taken in the callback left to do
            if step is None:
                data = msg.get("bytes")
                step = (
                    core.receive_bytes(data)
                    if data is not None
                    else core.receive_text(msg.get("text") or "")
                )
            if step is not NOTHING and not await _carry_out(ws, step, reg):
                return
            if not core.open:
                return
            received += 1
            if received % YIELD_EVERY == 0:
                await asyncio.sleep(0)
            msg = await transport.receive(ws, direct)
    finally:
        if direct is not None:
            direct.detach()


async def _carry_out(ws: WebSocket, step: Step, reg: SessionRegistry) -> bool:
    """Do what ``step`` says: send, run its work (in a thread when offloaded) and feed the result
    back, close. False once the connection is closed."""
    loop = asyncio.get_running_loop()
    while True:
        if step.send:
            await _send_all(ws, step.send)
        if step.close is not None:
            await _refuse(ws, step.close)
            return False
        work = step.work
        if work is None:
            return True
        result = await loop.run_in_executor(reg.executor, work.run) if work.offload else work.run()
        step = work.then(result)


@router.websocket("/v1/sessions/{session_id}/watch")
async def watch(
    ws: WebSocket, session_id: str, token: str | None = None, encoding: str = "f32"
) -> None:
    """Viewer: a JSON hello, then binary vertex frames (newest only for a slow viewer).

    The token: ``Authorization: Bearer``, a ``facecast.token.<token>`` subprotocol, or ``?token=``.
    """
    token = await _accept(ws, token)
    session = await _authorise(ws, session_id, token, "viewer")
    if session is None:
        return
    reg = registry(ws.app)
    core = ViewerCore(session, encoding, metrics=reg.metrics)
    step = core.greet()  # counts against the viewer limit from now until greeted
    if step.close is not None:
        await _refuse(ws, step.close)
        return
    try:
        await _send_all(ws, step.send)
    except Exception:
        core.greeted()
        return  # gone already
    step = core.greeted()
    if step.close is not None:
        await _refuse(ws, step.close)
        return
    write_buffer = core.write_buffer()
    if write_buffer is not None:
        transport.limit_write_buffer(ws, write_buffer)
    transport.limit_send_buffer(ws, core.send_buffer())
    # pre-framed vertex frames straight to the transport (None: through ASGI)
    direct = transport.DirectSender.attach(ws, reg.settings.direct)
    viewer = Viewer(encoding, direct)
    session.add_viewer(viewer)
    sender = asyncio.create_task(_send_loop(ws, session, viewer, direct))
    receiver = asyncio.create_task(_drain(ws, core))
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


async def _send_loop(
    ws: WebSocket, session: LiveSession, viewer: Viewer, direct: transport.DirectSender | None
) -> None:
    unsent = 0
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
                if unsent >= 32:  # count in batches: a Prometheus update per send is measurable
                    session.count_sent(unsent)
                    unsent = 0
            elif kind == "text":
                await ws.send_text(payload)
            else:
                code, text = payload
                await ws.send_text(text)
                await ws.close(int(code))
                return
    except (WebSocketDisconnect, RuntimeError, OSError, transport.ViewerGone):
        return  # the viewer went away
    finally:
        session.count_sent(unsent)


async def _drain(ws: WebSocket, core: ViewerCore) -> None:
    """Read what the viewer sends and feed it to the core, so its departure is noticed at once and
    a flood or an oversized message ends it."""
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
            step = core.receive(len(data) if data is not None else len(text or ""), data is None)
            if step.close is not None:
                await _refuse(ws, step.close)
                return
    except (WebSocketDisconnect, RuntimeError, OSError):
        return
