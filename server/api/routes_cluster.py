"""Cluster routes and shells: ``GET /v1/cluster`` (admin), and the WebSocket side of a producer
connected to this node for a session another node owns (its messages forwarded there as they come;
``server/cluster``). Without a broker ``/v1/cluster`` lists one node: this process.
"""

from __future__ import annotations

import asyncio
import json
import os
import secrets
import socket
from functools import partial
from typing import Any

from fastapi import APIRouter, Depends, Request, WebSocket
from starlette.websockets import WebSocketDisconnect

from ..cluster import envelope
from ..cluster.records import ClusterView, NodeView
from ..live.core import INTERNAL, Close, authorise
from ..live.producer import HELLO_TIMEOUT
from . import transport
from .security import require_admin

router = APIRouter(tags=["cluster"])

#: As in ``routes_sessions``: a receive loop yields to the event loop after this many messages.
YIELD_EVERY = 8


def cluster_of(app: Any) -> Any:
    """The app's ``cluster.node.Cluster``, or None (one process, no broker)."""
    return getattr(app.state, "cluster", None)


@router.get(
    "/v1/cluster",
    response_model=ClusterView,
    response_model_by_alias=True,
    dependencies=[Depends(require_admin)],
    responses={503: {"description": "the cluster's Redis is unreachable"}},
)
async def cluster_view(request: Request) -> ClusterView:
    """The nodes, the live sessions each owns, and which node answered (``"self": true``)."""
    cluster = cluster_of(request.app)
    if cluster is not None:
        view: ClusterView = await cluster.view()
        return view
    st = request.app.state
    node_id = getattr(st, "node_id", None) or secrets.token_hex(4)
    st.node_id = node_id
    cfg = st.config
    live = getattr(st, "live", None)
    me = NodeView(
        id=node_id,
        url=f"http://{cfg.host}:{cfg.port}",
        host=socket.gethostname(),
        pid=os.getpid(),
        started=getattr(st, "started", 0.0),
        version=request.app.version,
        sessions=sorted(live.sessions) if live is not None else [],
        is_self=True,
    )
    return ClusterView(self_id=node_id, broker="none", nodes=[me])


async def forward_producer(ws: WebSocket, cluster: Any, session_id: str, token: str | None) -> None:
    """A producer on this node of a session another node owns: forward its token (the owner
    authorises it), then what it sends, and carry out the owner's replies."""
    from .routes_sessions import _refuse

    try:
        rec = await cluster.record(session_id)
    except Exception as e:  # Unavailable (the broker is down): mapped to its close
        await _refuse(ws, Close(getattr(e, "close_code", 4503), str(e)))
        return
    if rec is None:  # the token is the owner's to check (it knows every token of the session)
        await _refuse(ws, authorise(session_id, False, token, "", "", "producer") or INTERNAL)
        return
    from ..cluster.node import OWNER_GONE

    fwd = await cluster.forward_open(session_id, token)
    if fwd is None:
        await _refuse(ws, Close(4503, OWNER_GONE))
        return
    transport.limit_receive_buffer(ws)
    pump = asyncio.create_task(_forward_in(ws, cluster, fwd))
    gone = True
    try:
        while True:
            kind, body = await fwd.replies.get()
            if kind == envelope.R_TEXT:
                await ws.send_text(body.decode("utf-8", "replace"))
            elif kind == envelope.R_CLOSE:
                gone = False
                c = json.loads(body)
                try:
                    await ws.send_text(str(c["error"]))
                    await ws.close(int(c["code"]), str(c.get("reason") or ""))
                except Exception:  # the peer is already gone
                    pass
                if c.get("cut_off"):
                    transport.cut_off(ws)
                return
            else:  # the producer left (``_forward_in``)
                return
    except (WebSocketDisconnect, OSError, RuntimeError):
        return
    finally:
        pump.cancel()
        await asyncio.gather(pump, return_exceptions=True)
        cluster.forward_done(fwd, gone)


async def _forward_in(ws: WebSocket, cluster: Any, fwd: Any) -> None:
    """Forward what the producer sends, as is; its hello within ``HELLO_TIMEOUT`` s."""
    try:
        msg = await asyncio.wait_for(ws.receive(), HELLO_TIMEOUT)
    except asyncio.TimeoutError:
        cluster.forward(fwd, envelope.P_TIMEOUT)
        return
    except (WebSocketDisconnect, OSError, RuntimeError):
        msg = {"type": "websocket.disconnect"}
    received = 0
    # binary messages forwarded from the connection's callback while this waits
    direct = transport.DirectReceiver.attach(
        ws, partial(cluster.forward, fwd, envelope.P_BYTES), cluster.reg.settings.direct
    )
    try:
        while True:
            if msg["type"] == "websocket.disconnect":
                break
            data = msg.get("bytes")
            if data is not None:
                cluster.forward(fwd, envelope.P_BYTES, data)
            else:
                cluster.forward(fwd, envelope.P_TEXT, (msg.get("text") or "").encode())
            received += 1
            if received % YIELD_EVERY == 0:
                await asyncio.sleep(0)
            msg = await transport.receive(ws, direct)
    except (WebSocketDisconnect, OSError, RuntimeError):
        pass
    finally:
        if direct is not None:
            direct.detach()
    fwd.replies.put_nowait((b"Z", b""))  # the producer left: end the shell
