"""Live sessions under hostile or careless clients, against a real server on loopback.

Budgets checked before decoding (a flooding producer is cut off with 1008 while another session
keeps streaming; an audio chunk over one second is refused with 1009), tokens in headers and
subprotocols (and masked in the access log when old clients put them in the query), idle sessions
expiring, and session requests with non-finite numbers refused with a 422.
"""

from __future__ import annotations

import asyncio
import json
import math
import time

import httpx
import numpy as np
import pytest
from conftest import live_server, run
from pydantic import ValidationError
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from facecast.client.api import LiveError, SessionAdmin, produce, watch, ws_url
from facecast.protocol import frames
from facecast.protocol.errors import CloseCode
from facecast.protocol.messages import ProducerHello, SessionCreate, dump_message
from facecast.server.live.budget import (
    FLOOD_BURST_SECONDS,
    FLOOD_FACTOR,
    MAX_AUDIO_CHUNK_SECONDS,
    Budget,
    Verdict,
    producer_limits,
)

FACE = "default:2k"
MAX_FPS = 100
IDLE = 3.0  # seconds; sessions the tests leave alone expire (closing them may then get a 404)


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    s = live_server(
        tmp_path_factory.mktemp("live-limits"),
        FACE,
        "--session-idle",
        str(IDLE),
        "--log-level",
        "info",
        env={"FACECAST_MAX_PRODUCER_FPS": str(MAX_FPS)},
    )
    yield s
    s.stop()


async def _session(srv, **kw):
    async with SessionAdmin(srv.url, srv.admin_key) as admin:
        return await admin.create(face=FACE, **kw)


def _exists(srv, sid: str) -> bool:
    r = httpx.get(f"{srv.url}/v1/sessions/{sid}", headers=srv.admin_headers, timeout=30)
    assert r.status_code in (200, 404), r.text
    return r.status_code == 200


def _close(srv, sid: str) -> None:
    """Close a session (it may have expired already)."""
    r = httpx.delete(f"{srv.url}/v1/sessions/{sid}", headers=srv.admin_headers, timeout=30)
    assert r.status_code in (204, 404), r.text


def _metric(srv, name: str) -> float:
    text = httpx.get(srv.url + "/metrics", timeout=30).text
    return sum(
        float(line.rsplit(" ", 1)[1])
        for line in text.splitlines()
        if line.startswith(name) and not line.startswith("#")
    )


# ------------------------------------------------------------------------------------ budgets (unit)


def test_budget_drops_over_the_rate_and_closes_a_flood():
    lim = producer_limits("fap", 100)
    b = Budget(lim, now=0.0)
    small = lim.max_binary // 2
    verdicts = [b.check(small, False, 0.0)[0] for _ in range(100)]
    assert verdicts == [Verdict.OK] * 100  # a second's burst
    assert b.check(small, False, 0.0)[0] is Verdict.DROP
    assert b.check(small, False, 0.02)[0] is Verdict.OK  # refilled at 100 a second
    # a flood: messages at once until the flood budget is used up, then the verdict is FLOOD
    b = Budget(lim, now=0.0)
    n = 0
    while b.check(small, False, 0.0)[0] is not Verdict.FLOOD:
        n += 1
        assert n <= FLOOD_BURST_SECONDS * 100 + 1
    assert n == FLOOD_BURST_SECONDS * 100
    # sending at twice the rate for a long time is dropped in part but never a flood
    b = Budget(lim, now=0.0)
    seen = {b.check(small, False, i / 200)[0] for i in range(200 * 60)}
    assert seen == {Verdict.OK, Verdict.DROP} and FLOOD_FACTOR > 2
    assert b.check(lim.max_binary + 1, False, 100.0)[0] is Verdict.TOO_BIG
    assert b.check(lim.max_text + 1, True, 100.0)[0] is Verdict.TOO_BIG


def test_audio_chunks_are_capped_at_one_second():
    lim = producer_limits("audio", 250, rate=16000, sample_format="i16")
    one_second = frames.encode_pcm(
        np.zeros(int(16000 * MAX_AUDIO_CHUNK_SECONDS), np.int16), rate=16000, sample_offset=0, seq=0
    )
    assert lim.too_big(len(one_second), False) is None
    assert "1 s of audio" in lim.too_big(len(one_second) + 2, False)
    f32 = producer_limits("audio", 250, rate=16000, sample_format="f32")
    assert f32.max_binary == 48 + 4 * 16000


def test_log_lines_mask_token_values():
    import logging

    from facecast.server.api.redact import SecretFilter, mask

    line = '127.0.0.1:1 - "POST /v1/sessions/ab/play?token=Zq-_9x&x=1 HTTP/1.1" 200'
    assert mask(line) == '127.0.0.1:1 - "POST /v1/sessions/ab/play?token=***&x=1 HTTP/1.1" 200'
    assert mask("watch?encoding=i16&token=a") == "watch?encoding=i16&token=***"
    assert (
        mask("producer_token=a admin_key=b monkey=c") == "producer_token=*** admin_key=*** monkey=c"
    )
    record = logging.LogRecord(
        "uvicorn.error", 20, "", 0, '%s - "WebSocket %s"', ("h", "/w?token=s"), None
    )
    SecretFilter().filter(record)
    assert record.getMessage() == 'h - "WebSocket /w?token=***"'


def test_session_create_refuses_non_finite_fps():
    for bad in (math.nan, math.inf, -math.inf):
        with pytest.raises(ValidationError, match="finite"):
            SessionCreate(fps=bad)


# ------------------------------------------------------------------------------- real server: budgets


def test_a_flooding_producer_is_cut_off_while_another_session_keeps_streaming(srv):
    """One producer sends binary and JSON FAP frames as fast as it can; it is closed with 1008, and
    the victim session's viewer gets its frames (counts, not timing: generous margins)."""

    async def main():
        victim, attacker = await _session(srv), await _session(srv)
        got = []
        started = asyncio.Event()

        async def viewer():
            async with watch(
                srv.url, victim.id, victim.viewer_token, until_producer_leaves=True
            ) as w:
                started.set()
                async for f in w:
                    got.append(f)

        async def flood(msg: bytes | str) -> tuple[int, LiveError]:
            for _ in range(100):  # the previous flooder's slot is freed as it is cut off
                try:
                    p = await produce(srv.url, attacker.id, attacker.producer_token).__aenter__()
                    break
                except LiveError as e:
                    assert e.code == CloseCode.CONFLICT, e
                    await asyncio.sleep(0.05)
            sent = 0
            with pytest.raises(LiveError) as e:  # noqa: PT012 - sends until the server cuts it off
                for _ in range(200_000):
                    await p.send_raw(msg)
                    sent += 1
                    if sent % 256 == 0:
                        await asyncio.sleep(0)  # let the client read the close frame
            await p.close()
            return sent, e.value

        async def floods():
            binary = await flood(frames.encode_faps(np.zeros(68, np.float32), seq=0, t=0.0))
            as_json = await flood(json.dumps({"type": "fap", "t": 0.0, "faps": {"3": 1.0}}))
            return binary, as_json

        task = asyncio.create_task(viewer())
        await started.wait()
        async with produce(srv.url, victim.id, victim.producer_token) as p:
            flooding = asyncio.create_task(floods())
            i = 0
            while i < 120 or not flooding.done():  # 60 fps while the floods last, 2 s at least
                await p.send_faps({3: float(i)}, i / 60)
                i += 1
                await asyncio.sleep(1 / 60)
            binary, json_flood = await flooding
            victim_errors = list(p.errors)
        await asyncio.wait_for(task, 60)
        for sid in (victim.id, attacker.id):
            _close(srv, sid)
        return binary, json_flood, got, i, victim_errors

    binary, json_flood, got, sent, victim_errors = run(main())
    for flooded, err in (binary, json_flood):
        assert err.code == CloseCode.POLICY_VIOLATION, err
        assert "far faster" in str(err) and f"{MAX_FPS} per second" in str(err)
        assert flooded < 200_000
    assert victim_errors == []
    assert got[-1].frame.header.seq == sent - 1  # the newest frame always arrives
    assert len(got) >= sent // 2, f"the victim's viewer got only {len(got)} of {sent} frames"
    assert _metric(srv, 'facecast_live_messages_refused_total{reason="drop"}') > 0
    assert httpx.get(srv.url + "/healthz", timeout=30).status_code == 200
    assert _metric(srv, 'facecast_live_messages_refused_total{reason="flood"}') >= 2


@pytest.mark.parametrize("samples", [24_000, 1 << 20])
def test_an_audio_chunk_over_one_second_is_refused_with_1009(srv, samples):
    """1.5 s of 16 kHz audio: refused by the session's budget (with the reason); 1 Mi samples (2 MiB):
    refused by the WebSocket layer itself (over the server's message size), never buffered."""

    async def main():
        s = await _session(srv, input="audio", fps=50)
        hello = ProducerHello(input="audio", rate=16000, sample_format="i16")
        async with produce(srv.url, s.id, s.producer_token, hello) as p:
            await p.send_pcm(np.zeros(16000, np.int16), rate=16000, sample_offset=0)  # 1 s: fine
            async with SessionAdmin(srv.url, srv.admin_key) as admin:
                for _ in range(
                    600
                ):  # taken before the next (a read with a bad frame is lost whole)
                    if (await admin.info(s.id)).stats.frames_in:
                        break
                    await asyncio.sleep(0.05)
            with pytest.raises(LiveError) as e:  # noqa: PT012 - the refusal comes with a later send
                await p.send_pcm(np.zeros(samples, np.int16), rate=16000, sample_offset=16000)
                for _ in range(200):  # the refusal arrives with a later send
                    await asyncio.sleep(0.05)
                    await p.send_pcm(np.zeros(160, np.int16), rate=16000, sample_offset=0)
            errors = list(p.errors)
        async with SessionAdmin(srv.url, srv.admin_key) as admin:
            info = await admin.info(s.id)
        _close(srv, s.id)
        return e.value, errors, info

    err, errors, info = run(main())
    assert err.code == CloseCode.TOO_BIG, err
    if samples < 1 << 20:
        assert "1 s of audio" in str(err)
        assert [e.code for e in errors] == [CloseCode.TOO_BIG] and errors[0].fatal
    assert info.stats.frames_in == 1  # the one-second chunk was taken


def test_a_viewer_that_floods_is_disconnected(srv):
    async def main():
        s = await _session(srv)
        async with watch(srv.url, s.id, s.viewer_token) as w:
            try:
                for _ in range(100_000):
                    await w.ws.send("hello?")
                    await asyncio.sleep(0)
            except ConnectionClosed:
                pass
            with pytest.raises(LiveError) as e:
                async for _ in w:
                    pass
        _close(srv, s.id)
        return e.value

    err = run(main())
    assert err.code == CloseCode.POLICY_VIOLATION and "viewers only listen" in str(err)


# --------------------------------------------------------------------------------- real server: tokens


def test_tokens_travel_in_headers_or_subprotocols_and_never_reach_the_log(srv):
    s = run(_session(srv))

    async def hello_via(url: str, **kw) -> tuple[str, str | None]:
        async with connect(url, compression=None, **kw) as ws:
            return json.loads(await ws.recv())["type"], ws.subprotocol

    watch_path = ws_url(srv.url, f"/v1/sessions/{s.id}/watch")
    # the Python client's way: Authorization header
    assert (
        run(
            hello_via(watch_path, additional_headers={"Authorization": f"Bearer {s.viewer_token}"})
        )[0]
        == "hello"
    )
    # a browser's way: subprotocols; the server picks facecast.v1 (never echoes the token)
    kind, chosen = run(
        hello_via(watch_path, subprotocols=["facecast.v1", f"facecast.token.{s.viewer_token}"])
    )
    assert (kind, chosen) == ("hello", "facecast.v1")
    # old clients: ?token= still works
    assert (
        run(hello_via(ws_url(srv.url, f"/v1/sessions/{s.id}/watch", token=s.viewer_token)))[0]
        == "hello"
    )
    # a wrong header token is refused even with a right query token (the header wins)
    kind, _ = run(
        hello_via(
            ws_url(srv.url, f"/v1/sessions/{s.id}/watch", token=s.viewer_token),
            additional_headers={"Authorization": "Bearer wrong"},
        )
    )
    assert kind == "error"

    async def producer_via_subprotocol():
        async with connect(
            ws_url(srv.url, f"/v1/sessions/{s.id}/produce"),
            compression=None,
            subprotocols=["facecast.v1", f"facecast.token.{s.producer_token}"],
        ) as ws:
            await ws.send(dump_message(ProducerHello()))
            return json.loads(await ws.recv())["type"]

    assert run(producer_via_subprotocol()) == "ready"
    # HTTP with a token in the query (the access log prints queries)
    httpx.delete(f"{srv.url}/v1/sessions/{s.id}/demo?token={s.producer_token}", timeout=30)
    _close(srv, s.id)
    time.sleep(0.5)  # let the server flush its log lines
    log = srv.log.read_text(errors="replace")
    assert f"/v1/sessions/{s.id}/watch" in log and "token=***" in log  # the access log is on
    for token in (s.producer_token, s.viewer_token):
        assert token not in log


# ------------------------------------------------------------------------------- real server: expiry


def test_idle_sessions_expire_and_watched_ones_do_not(srv):
    before = _metric(srv, "facecast_sessions_expired_total")
    idle, watched = run(_session(srv)), run(_session(srv))

    async def keep_watching(stop: asyncio.Event):
        async with watch(srv.url, watched.id, watched.viewer_token):
            await stop.wait()

    async def main():
        stop = asyncio.Event()
        task = asyncio.create_task(keep_watching(stop))
        deadline = time.monotonic() + 60
        while await asyncio.to_thread(_exists, srv, idle.id):  # polls, generously bounded
            assert time.monotonic() < deadline, "an idle session did not expire"
            await asyncio.sleep(0.2)
        # the watched one outlived the idle one by several idle times
        await asyncio.sleep(2 * IDLE)
        alive = await asyncio.to_thread(_exists, srv, watched.id)
        stop.set()
        await task
        return alive

    assert run(main())
    deadline = time.monotonic() + 60
    while _exists(srv, watched.id):
        assert time.monotonic() < deadline, "a session left idle did not expire"
        time.sleep(0.2)
    assert _metric(srv, "facecast_sessions_expired_total") >= before + 2
    with pytest.raises(LiveError) as e:  # noqa: PT012 - the viewer is refused as it connects

        async def late_viewer():
            async with watch(srv.url, idle.id, idle.viewer_token):
                pass

        run(late_viewer())
    assert e.value.code == CloseCode.NOT_FOUND


# ------------------------------------------------------------------------------ real server: 500s -> 4xx


@pytest.mark.parametrize(
    "body", ['{"fps": NaN}', '{"fps": Infinity}', '{"fps": 1e309}', '{"face": "\\ud800"}']
)
def test_session_create_with_non_finite_or_broken_text_is_a_422(srv, body):
    r = httpx.post(
        srv.url + "/v1/sessions",
        content=body,
        timeout=30,
        headers={**srv.admin_headers, "content-type": "application/json"},
    )
    assert r.status_code == 422 and r.headers["content-type"].startswith("application/json")
    assert r.json()["status"] == 422


# --------------------------------------------------------------------------- real server: garbage


@pytest.mark.parametrize(
    "first",
    [
        b"\x00garbage",
        "x" * 300_000,
        "[]",
        "null",
        '{"type": "nope"}',
        '{"type": "hello", "role": "producer", "protocol": 99}',
    ],
)
def test_garbage_instead_of_a_hello_is_a_4400(srv, first):
    s = run(_session(srv))

    async def main():
        async with connect(
            ws_url(srv.url, f"/v1/sessions/{s.id}/produce"),
            compression=None,
            additional_headers={"Authorization": f"Bearer {s.producer_token}"},
        ) as ws:
            await ws.send(first)
            msg = json.loads(await ws.recv())
            with pytest.raises(ConnectionClosed):
                await ws.recv()
            return msg, ws.close_code

    msg, code = run(main())
    assert msg["type"] == "error" and msg["code"] == code == CloseCode.BAD_REQUEST and msg["fatal"]
    assert httpx.get(srv.url + "/healthz", timeout=30).status_code == 200
    _close(srv, s.id)


def test_an_oversized_viewer_message_is_a_1009(srv):
    s = run(_session(srv))

    async def main():
        async with watch(srv.url, s.id, s.viewer_token) as w:
            await w.ws.send(b"\x00" * 100_000)
            with pytest.raises(LiveError) as e:
                async for _ in w:
                    pass
        return e.value

    err = run(main())
    assert err.code == CloseCode.TOO_BIG and "4096 bytes" in str(err)
    _close(srv, s.id)
