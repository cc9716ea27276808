"""``api.transport.DirectReceiver`` under a real uvicorn (sans-I/O WebSockets) on loopback with a real
``websockets`` client: binary messages are taken in the protocol's callback while the app waits,
every message keeps its order, and what a taken message leaves to do reaches the app's task."""

from __future__ import annotations

import asyncio
import contextlib
import socket

import uvicorn
from starlette.applications import Starlette
from starlette.routing import WebSocketRoute
from starlette.websockets import WebSocket
from websockets.asyncio.client import connect

from facecast.server.api.transport import HANDED, DirectReceiver, receive


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


async def _until(cond, what: str, seconds: float = 20.0) -> None:
    for _ in range(int(seconds / 0.01)):
        if cond():
            return
        await asyncio.sleep(0.01)
    raise AssertionError(f"never: {what}")


@contextlib.asynccontextmanager
async def _serving(route, done: asyncio.Event):
    """A real uvicorn (sans-I/O WebSockets) on a free loopback port serving ``route`` at ``/ws``:
    yields its URL; on exit waits for the route to end (``done``) and stops the server."""
    port = _free_port()
    app = Starlette(routes=[WebSocketRoute("/ws", route)])
    server = uvicorn.Server(
        uvicorn.Config(app, host="127.0.0.1", port=port, ws="websockets-sansio", log_level="error")
    )
    serving = asyncio.create_task(server.serve())
    await _until(lambda: server.started, "the server started")
    try:
        yield f"ws://127.0.0.1:{port}/ws"
    finally:
        await asyncio.wait_for(done.wait(), 20)
        server.should_exit = True
        await serving


def test_binary_messages_are_taken_in_the_callback_in_order():
    log: list[tuple[str, object]] = []
    receivers: list[DirectReceiver] = []
    done = asyncio.Event()

    async def route(ws: WebSocket) -> None:
        await ws.accept()

        def take(data):
            log.append(("direct", bytes(data)))
            if data == b"step":
                return "work"
            if data == b"boom":
                raise ValueError("boom")
            return None

        rx = DirectReceiver.attach(ws, take)
        assert rx is not None
        receivers.append(rx)
        try:
            while True:
                rx.waiting = True
                msg = await ws.receive()
                rx.waiting = False
                if msg["type"] == "websocket.disconnect":
                    break
                if HANDED in msg:
                    h = msg[HANDED]
                    log.append(("handed", type(h).__name__ if isinstance(h, Exception) else h))
                    await asyncio.sleep(0.05)  # the task is busy: messages meanwhile are queued
                elif msg.get("text") is not None:
                    log.append(("text", msg["text"]))
                else:
                    log.append(("queued", msg["bytes"]))
        finally:
            rx.detach()
            assert "handle_bytes" not in rx.proto.__dict__
            done.set()

    async def main() -> None:
        async with _serving(route, done) as url, connect(url) as c:
            seen = lambda n: sum(how != "handed" for how, _ in log) >= n  # noqa: E731
            waiting = lambda: bool(receivers) and receivers[0].waiting  # noqa: E731
            await _until(waiting, "the app waits")
            await c.send(b"a")
            await _until(lambda: seen(1), "a taken")
            for m in (b"b", "t", b"c"):
                await c.send(m)
            await _until(lambda: seen(4) and waiting(), "b, t, c seen")
            for m in (b"step", b"d", b"e"):
                await c.send(m)
            await _until(lambda: seen(7) and waiting(), "step, d, e seen")
            for m in (b"boom", b"f"):
                await c.send(m)
            await _until(lambda: seen(9), "boom, f seen")

    asyncio.run(asyncio.wait_for(main(), 60))
    assert log[0] == ("direct", b"a")
    payloads = [p for how, p in log if how != "handed"]
    assert payloads == [b"a", b"b", "t", b"c", b"step", b"d", b"e", b"boom", b"f"]
    # what a taken message left comes right after it, before any later message
    i = log.index(("direct", b"step"))
    assert log[i + 1] == ("handed", "work")
    # while the task was busy with it, later messages were queued for it, not taken
    assert log[i + 2] == ("queued", b"d")
    # an exception of ``take`` reaches the task in its place
    j = log.index(("direct", b"boom"))
    assert log[j + 1] == ("handed", "ValueError")
    assert log[j + 2] == ("queued", b"f")


def test_a_disabled_receiver_is_none():
    assert DirectReceiver.attach(None, lambda d: None, enabled=False) is None  # type: ignore[arg-type]


def test_a_burst_is_taken_at_most_take_per_wait_messages_per_wait_of_the_task():
    """One read can hold a flood of small frames: the callback takes at most ``TAKE_PER_WAIT`` of
    them per wait of the task, the rest go to the task (which yields between them), in order."""
    log: list[tuple[str, bytes]] = []
    done = asyncio.Event()
    ready = asyncio.Event()
    n = 200

    async def route(ws: WebSocket) -> None:
        await ws.accept()
        rx = DirectReceiver.attach(ws, lambda data: log.append(("direct", bytes(data))))
        assert rx is not None
        ready.set()
        try:
            while True:
                msg = await receive(ws, rx)
                if msg["type"] == "websocket.disconnect":
                    break
                log.append(("task", msg["bytes"]))
        finally:
            rx.detach()
            done.set()

    async def main() -> None:
        async with _serving(route, done) as url, connect(url) as c:
            await asyncio.wait_for(ready.wait(), 20)
            await asyncio.sleep(0.05)  # the task waits in ``receive``
            await c.send((0).to_bytes(2, "big"))
            for i in range(1, n):  # one burst: the client's writes coalesce on loopback
                c.protocol.send_binary(i.to_bytes(2, "big"))
            c.send_data()
            await _until(lambda: len(log) >= n, "every message seen")

    asyncio.run(asyncio.wait_for(main(), 60))
    assert [int.from_bytes(p, "big") for _, p in log] == list(range(n))
    run = longest = 0
    for how, _ in log:
        run = run + 1 if how == "direct" else 0
        longest = max(longest, run)
    assert longest <= DirectReceiver.TAKE_PER_WAIT
    assert any(how == "task" for how, _ in log)  # the burst went through the task too
