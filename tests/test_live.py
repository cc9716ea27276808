"""Live sessions against a real server on loopback, with the real asyncio client.

One producer streams a real .fap file to three viewers; the float32 frames they receive must equal
a batch render (``Animator.frame``, same face, same NumPy backend) exactly. Then the refusals (tokens,
roles, limits, bad frames) and vanishing peers.
"""

from __future__ import annotations

import asyncio
import json
import os
import time

import httpx
import numpy as np
import pytest
from conftest import live_server, run

from facecast.client.api import LiveError, SessionAdmin, produce, stream_fap, summary, watch
from facecast.protocol import frames
from facecast.protocol.errors import CloseCode
from facecast.protocol.fap_file import read_fap
from facecast.protocol.messages import ProducerHello

#: Face of the test sessions (override to run against another server face, e.g. one in FACECAST_FACES).
FACE = os.environ.get("FACECAST_TEST_LIVE_FACE", "default:2k")


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    s = live_server(
        tmp_path_factory.mktemp("live"),
        FACE,
        env={"FACECAST_MAX_SESSIONS": "6", "FACECAST_MAX_PRODUCER_FPS": "150"},
    )
    yield s
    s.stop()


async def _collect(url, sid, token, *, encoding="f32", until_end=True, limit=None, started=None):
    got = []
    async with watch(url, sid, token, encoding=encoding, until_producer_leaves=until_end) as w:
        if started is not None:
            started.set()
        async for f in w:
            got.append(f)
            if limit is not None and len(got) >= limit:
                break
    return got


@pytest.fixture(scope="module")
def joy(data_dir):
    return read_fap((data_dir / "xface/faps/joy.fap").read_text(), where="joy.fap")


@pytest.mark.slow
def test_one_producer_three_viewers_equal_batch_render(live, joy):
    from facecast.server.api.store import FaceStore
    from facecast.server.drivers.fap import to_animation
    from facecast.server.pipeline import Animator

    async def main():
        async with SessionAdmin(live.url, live.admin_key) as admin:
            s = await admin.create(face=FACE, input="fap", fps=float(joy.fps))
            ready = [asyncio.Event() for _ in range(3)]
            viewers = [
                asyncio.create_task(_collect(live.url, s.id, s.viewer_token, started=ev))
                for ev in ready
            ]
            await asyncio.gather(*(ev.wait() for ev in ready))
            async with produce(live.url, s.id, s.producer_token) as p:
                sent = await stream_fap(p, joy, speed=4.0)
                errors = list(p.errors)
            got = await asyncio.gather(*viewers)
            info = await admin.info(s.id)
            await admin.close(s.id)
            return s, sent, errors, got, info

    s, sent, errors, got, info = run(main())
    assert errors == [] and sent == len(joy.frames)
    animation = to_animation(joy)
    animator = Animator(FaceStore().face(FACE), backend="numpy")
    assert s.vertex_count == animator.face.n_vertices
    expected = {}
    for frames_ in got:
        assert frames_, "a viewer received no frames"
        assert (
            frames_[-1].frame.header.seq == len(joy.frames) - 1
        )  # the newest frame always arrives
        for f in frames_:
            h = f.frame.header
            assert h.kind is frames.Kind.VERTICES_F32 and f.frame.vertices.shape == (
                s.vertex_count,
                3,
            )
            assert h.t == pytest.approx(animation.states[h.seq].t)
            assert h.wall > 0 and f.latency is not None
            if h.seq not in expected:
                expected[h.seq] = animator.frame(animation.states[h.seq])
            np.testing.assert_array_equal(f.frame.vertices, expected[h.seq])
    assert info.stats.frames_in == sent and info.stats.states == sent
    # the frames differ over time (the face moves), so equality above is not trivial
    seqs = sorted(expected)
    assert any(not np.array_equal(expected[seqs[0]], expected[k]) for k in seqs)


def test_concurrent_sessions_of_one_face_get_their_own_frames(live, joy, data_dir):
    """Sessions of the same face are deformed in shared batches; each still gets exactly its frames."""
    from facecast.server.api.store import FaceStore
    from facecast.server.drivers.fap import to_animation
    from facecast.server.pipeline import Animator

    anger = read_fap((data_dir / "xface/faps/anger.fap").read_text(), where="anger.fap")
    takes = [
        type(joy)(fps=joy.fps, frames=joy.frames[:40]),
        type(anger)(fps=anger.fps, frames=anger.frames[:40]),
    ]

    async def one(take):
        s = await _session(live)
        started = asyncio.Event()
        viewer = asyncio.create_task(_collect(live.url, s.id, s.viewer_token, started=started))
        await started.wait()
        async with produce(live.url, s.id, s.producer_token) as p:
            await stream_fap(p, take, speed=4.0)
        got = await viewer
        await _close(live, s.id)
        return got

    async def main():
        return await asyncio.gather(*(one(t) for t in takes))

    results = run(main())
    animator = Animator(FaceStore().face(FACE), backend="numpy")
    for take, got in zip(takes, results):
        states = to_animation(take).states
        assert got and got[-1].frame.header.seq == len(states) - 1
        for f in got:
            np.testing.assert_array_equal(
                f.frame.vertices, animator.frame(states[f.frame.header.seq])
            )


def test_int16_viewer_and_json_fap_frames(live, joy):
    from facecast.server.api.store import FaceStore
    from facecast.server.drivers.fap import to_animation
    from facecast.server.pipeline import Animator

    async def main():
        async with SessionAdmin(live.url, live.admin_key) as admin:
            s = await admin.create(face=FACE)
            started = asyncio.Event()
            viewer = asyncio.create_task(
                _collect(live.url, s.id, s.viewer_token, encoding="i16", started=started)
            )
            await started.wait()
            short = type(joy)(fps=joy.fps, frames=joy.frames[:20])
            async with produce(live.url, s.id, s.producer_token) as p:
                await stream_fap(p, short, speed=4.0, binary=False)
            got = await viewer
            await admin.close(s.id)
            return got

    got = run(main())
    animator = Animator(FaceStore().face(FACE), backend="numpy")
    states = to_animation(joy).states
    assert got and got[-1].frame.header.seq == 19
    for f in got:
        assert (
            f.frame.header.kind is frames.Kind.VERTICES_I16
            and f.size == 56 + 6 * f.frame.header.count
        )
        want = animator.frame(states[f.frame.header.seq])
        assert np.all(
            np.abs(f.positions() - want) <= f.frame.scale * 0.5 + 1e-5 * np.abs(want).max()
        )


def _expect_refusal(coro, code: int) -> LiveError:
    with pytest.raises(LiveError) as e:
        run(coro)
    assert e.value.code == code, str(e.value)
    return e.value


async def _session(live, **kw):
    async with SessionAdmin(live.url, live.admin_key) as admin:
        return await admin.create(face=FACE, **kw)


async def _close(live, sid):
    async with SessionAdmin(live.url, live.admin_key) as admin:
        await admin.close(sid)


def test_tokens_and_roles(live):
    s = run(_session(live))

    async def produce_with(token):
        async with produce(live.url, s.id, token):
            pass

    async def watch_with(token, **kw):
        async with watch(live.url, s.id, token, **kw):
            pass

    err = _expect_refusal(produce_with(s.viewer_token), CloseCode.FORBIDDEN)
    assert "viewer token" in str(err)
    _expect_refusal(produce_with("wrong"), CloseCode.UNAUTHORIZED)
    _expect_refusal(produce_with(""), CloseCode.UNAUTHORIZED)
    _expect_refusal(watch_with("wrong"), CloseCode.UNAUTHORIZED)
    _expect_refusal(watch_with(s.producer_token), CloseCode.FORBIDDEN)
    err = _expect_refusal(watch_with(s.viewer_token, encoding="f16"), CloseCode.BAD_REQUEST)
    assert "unknown encoding 'f16'; use f32, i16 or compact" in str(err)

    async def other_session():
        async with watch(live.url, "nope", s.viewer_token):
            pass

    _expect_refusal(other_session(), CloseCode.NOT_FOUND)

    async def wrong_hello():
        async with produce(
            live.url, s.id, s.producer_token, ProducerHello(input="audio", rate=16000)
        ):
            pass

    assert "takes 'fap'" in str(_expect_refusal(wrong_hello(), CloseCode.BAD_REQUEST))

    async def second_producer():
        async with produce(live.url, s.id, s.producer_token):
            async with produce(live.url, s.id, s.producer_token):
                pass

    _expect_refusal(second_producer(), CloseCode.CONFLICT)
    run(_close(live, s.id))


def test_rest_admin_and_limits(live):
    r = httpx.post(live.url + "/v1/sessions", json={})
    assert r.status_code == 401 and "admin key" in r.json()["error"]
    r = httpx.post(live.url + "/v1/sessions", json={"input": "video"}, headers=live.admin_headers)
    assert r.status_code == 422
    r = httpx.post(
        live.url + "/v1/sessions", json={"face": "no-such-face"}, headers=live.admin_headers
    )
    assert r.status_code == 404 and "no-such-face" in r.json()["error"]
    assert (
        httpx.delete(live.url + "/v1/sessions/nope", headers=live.admin_headers).status_code == 404
    )

    s = run(_session(live, max_viewers=1))
    listed = httpx.get(live.url + "/v1/sessions", headers=live.admin_headers).json()["sessions"]
    assert s.id in [x["id"] for x in listed] and all("token" not in json.dumps(x) for x in listed)

    async def two_viewers():
        async with watch(live.url, s.id, s.viewer_token):
            async with watch(live.url, s.id, s.viewer_token):
                pass

    _expect_refusal(two_viewers(), CloseCode.TOO_MANY)

    # session limit (FACECAST_MAX_SESSIONS=6 on this server)
    made = []
    while True:
        r = httpx.post(
            live.url + "/v1/sessions", json={"face": FACE}, headers=live.admin_headers, timeout=60
        )
        if r.status_code != 201:
            break
        made.append(r.json()["id"])
        assert len(made) <= 6
    assert r.status_code == 429 and "limit" in r.json()["error"]
    for sid in made + [s.id]:
        assert (
            httpx.delete(f"{live.url}/v1/sessions/{sid}", headers=live.admin_headers).status_code
            == 204
        )


def test_closing_a_session_ends_its_connections(live):
    async def main():
        s = await _session(live)
        async with produce(live.url, s.id, s.producer_token) as p:
            async with watch(live.url, s.id, s.viewer_token) as w:
                await _close(live, s.id)
                with pytest.raises(LiveError) as e:
                    async for _ in w:
                        pass
                assert e.value.code == CloseCode.SESSION_CLOSED

            async def send_until_refused() -> None:
                for i in range(50):  # the server closed us; sending fails soon
                    await p.send_faps({3: 1.0}, i / 60)
                    await asyncio.sleep(0.02)

            with pytest.raises(LiveError):
                await send_until_refused()

    run(main())


def test_bad_frames_get_errors_while_another_session_streams(live, joy):
    async def main():
        a, b = await _session(live), await _session(live)
        started = asyncio.Event()
        b_viewer = asyncio.create_task(_collect(live.url, b.id, b.viewer_token, started=started))
        a_viewer = asyncio.create_task(_collect(live.url, a.id, a.viewer_token, until_end=True))
        await started.wait()
        async with (
            produce(live.url, b.id, b.producer_token) as pb,
            produce(live.url, a.id, a.producer_token) as pa,
        ):
            b_task = asyncio.create_task(stream_fap(pb, joy, speed=3.0))
            good = frames.encode_faps(np.zeros(68), seq=0, t=0.0, wall=1.0)
            bad = [
                b"garbage!" * 8,
                good[:-3],
                good + b"x",
                good[:5] + b"\x09" + good[6:],
                frames.encode_vertices_f32(
                    np.zeros((3, 3)), seq=5, t=0.0
                ),  # a kind producers may not send
                frames.encode_pcm(np.zeros(10, np.int16), rate=16000, sample_offset=0, seq=6),
                "not json",
                json.dumps({"type": "fap", "t": 0.1, "faps": {"1": 3}}),
                json.dumps({"type": "hello", "role": "producer"}),
                json.dumps({"type": "fap"}),
            ]
            for msg in bad:
                await pa.send_raw(msg)
            await pa.send_faps({3: 100.0}, 0.5)  # the session still works after all that
            await asyncio.sleep(0.5)
            errors = list(pa.errors)
            await b_task
        got_a, got_b = await asyncio.gather(a_viewer, b_viewer)
        for sid in (a.id, b.id):
            await _close(live, sid)
        return errors, got_a, got_b

    errors, got_a, got_b = run(main())
    assert len(errors) == 10 and all(
        e.code == CloseCode.BAD_REQUEST and not e.fatal for e in errors
    )
    text = " | ".join(e.message for e in errors)
    for phrase in (
        "magic",
        "truncated",
        "trailing",
        "unknown frame kind",
        "not accepted",
        "not JSON",
        "low-level FAP",
        "not 'hello'",
    ):
        assert phrase in text, phrase
    assert [e.seq for e in errors][4:6] == [5, 6]  # the offending frame is named
    assert got_a and got_a[-1].frame.header.seq == 0  # the one good frame came through
    assert len(got_b) > 0 and got_b[-1].frame.header.seq == len(joy.frames) - 1


def test_viewer_and_producer_vanishing(live, joy):
    async def main():
        s = await _session(live)
        started = [asyncio.Event()]
        last_t = 10 + 59 / 30

        async def steady_viewer():
            got = []
            async with watch(live.url, s.id, s.viewer_token) as w:
                started[0].set()
                async for f in w:
                    got.append(f)
                    if f.frame.header.t >= last_t - 1e-9:
                        return got
            return got  # the stream ended early: the assertions below say what arrived

        steady = asyncio.create_task(steady_viewer())
        await started[0].wait()
        async with watch(live.url, s.id, s.viewer_token) as doomed:
            async with produce(live.url, s.id, s.producer_token) as p:
                streaming = asyncio.create_task(stream_fap(p, joy, speed=2.0))
                n = 0
                async for _ in doomed:
                    n += 1
                    if n == 5:  # vanish without a close handshake
                        doomed.ws.transport.abort()
                        break
                # the producer vanishes too, mid-stream
                await asyncio.sleep(0.3)
                streaming.cancel()
                p.ws.transport.abort()
        # a new producer may connect: the old one is gone, not "already connected"
        await asyncio.sleep(0.3)
        async with produce(live.url, s.id, s.producer_token) as p2:
            for i in range(60):
                await p2.send_faps({3: float(i)}, 10 + i / 30)
                await asyncio.sleep(1 / 60)
        got = await steady
        async with SessionAdmin(live.url, live.admin_key) as admin:
            info = await admin.info(s.id)
            await admin.close(s.id)
        return got, info

    got, info = run(main())
    assert got[-1].frame.header.t == pytest.approx(10 + 59 / 30)
    assert info.stats.viewers == 0 and not info.stats.producer_connected
    assert info.stats.states >= 60 + 5


def test_slow_viewer_gets_the_newest_frame_and_a_gap(live):
    async def main():
        s = await _session(live)
        async with watch(live.url, s.id, s.viewer_token, encoding="f32") as w:  # frames > buffers
            async with produce(live.url, s.id, s.producer_token) as p:
                for i in range(120):  # the viewer reads nothing meanwhile
                    await p.send_faps({3: float(i)}, i / 100)
                    await asyncio.sleep(0.005)
                await asyncio.sleep(1.0)
                got = []
                async for f in w:
                    got.append(f)
                    if f.frame.header.seq == 119:
                        break
        async with SessionAdmin(live.url, live.admin_key) as admin:
            info = await admin.info(s.id)
            await admin.close(s.id)
        return got, info

    got, info = run(main())
    seqs = [f.frame.header.seq for f in got]
    assert seqs == sorted(seqs) and seqs[-1] == 119
    assert (
        len(seqs) < 120 and info.stats.frames_skipped > 0
    )  # frames were replaced in the viewer's slot
    assert summary(got)["dropped"] == 120 - len(seqs) - seqs[0]


def test_producer_rate_limit(live):
    async def main():
        s = await _session(live)
        async with produce(live.url, s.id, s.producer_token) as p:
            assert p.ready.max_fps == 150
            # bursts of 200 frames a second apart: over the rate (150 a second, one second's
            # burst), so some are dropped, but never a flood (which would close the connection)
            for i in range(1000):
                await p.send_faps({3: 1.0}, i / 1000)
                if i % 200 == 199:
                    await asyncio.sleep(1.0)
            await p.send_faps({3: 2.0}, 2.0)
            await asyncio.sleep(0.5)
            errors = list(p.errors)
        async with SessionAdmin(live.url, live.admin_key) as admin:
            info = await admin.info(s.id)
            await admin.close(s.id)
        return errors, info

    errors, info = run(main())
    assert errors and all(e.code == CloseCode.TOO_MANY and not e.fatal for e in errors)
    assert "150 per second" in errors[0].message
    assert (
        info.stats.frames_rejected > 0 and info.stats.frames_in + info.stats.frames_rejected == 1001
    )


def test_audio_session_streams_pcm(live, data_dir):
    import soundfile as sf

    from facecast.client.api import stream_pcm

    samples, rate = sf.read(str(data_dir / "speech/mary.wav"), dtype="int16")
    samples = samples[: rate * 2] if samples.ndim == 1 else samples[: rate * 2, 0].copy()

    async def main():
        s = await _session(live, input="audio", fps=50)
        started = asyncio.Event()
        viewer = asyncio.create_task(
            _collect(live.url, s.id, s.viewer_token, encoding="i16", started=started)
        )
        await started.wait()
        async with produce(
            live.url,
            s.id,
            s.producer_token,
            ProducerHello(input="audio", rate=rate, sample_format="i16"),
        ) as p:
            chunks = await stream_pcm(p, samples, rate, chunk=0.04, speed=4.0)
            bad = frames.encode_pcm(samples[:100], rate=rate + 1, sample_offset=0, seq=999)
            await p.send_raw(bad)
            for _ in range(200):  # the driver works through the queued chunks first
                if p.errors:
                    break
                await asyncio.sleep(0.05)
            errors = list(p.errors)
        got = await viewer
        await _close(live, s.id)
        return chunks, errors, got

    _chunks, errors, got = run(main())
    assert len(errors) == 1 and "sample rate" in errors[0].message and errors[0].seq == 999
    assert got, "no vertex frames from audio"
    ts = [f.frame.header.t for f in got]
    assert ts == sorted(ts) and ts[-1] <= 2.0 + 1e-6
    # the driver's look-ahead is flushed when the producer leaves: the last state is the one the
    # same driver gives locally after its end-of-stream flush (without it, ~40 ms of states are lost)
    from facecast.server.api.store import FaceStore
    from facecast.server.audio.live import AudioLiveDriver

    local = AudioLiveDriver(FaceStore().face(FACE), rate, fps=50)
    x = samples.astype(np.float32) / 32768
    n = int(0.04 * rate)
    for i in range(0, len(x), n):
        local.push(x[i : i + n], i / rate)
    assert ts[-1] == pytest.approx(local.flush()[-1].t), ts[-5:]
    # the mouth moves: frames differ
    assert any(not np.array_equal(got[0].positions(), f.positions()) for f in got)


def _marker_session(live, seconds: float, take_fps: float, session_fps: float, seed: int):
    """A synthetic take streamed (at twice real time) into a marker session of ``session_fps``.
    Returns ``(face, errors, frames watched, the same driver run here, its states)``."""
    from facecast.client.api import stream_markers
    from facecast.server.api.store import FaceStore
    from facecast.server.mocap.live import MarkerLiveDriver
    from facecast.server.mocap.synthetic import synthetic_take

    face = FaceStore().face(FACE)
    syn = synthetic_take(face, n_markers=16, seconds=seconds, fps=take_fps, seed=seed)
    take = syn.take
    xyz = take.xyz.astype(np.float32)

    async def main():
        s = await _session(live, input="markers", fps=session_fps)
        started = asyncio.Event()
        viewer = asyncio.create_task(_collect(live.url, s.id, s.viewer_token, started=started))
        await started.wait()
        hello = ProducerHello(
            input="markers", markers=list(take.names), layout=syn.layout, units=take.units
        )
        async with produce(live.url, s.id, s.producer_token, hello) as p:
            await stream_markers(p, xyz, take.fps, speed=2.0)
            errors = list(p.errors)
        got = await viewer
        await _close(live, s.id)
        return errors, got

    errors, got = run(main())
    driver = MarkerLiveDriver(face, list(take.names), syn.layout, units=take.units, fps=session_fps)
    states = [st for i in range(len(xyz)) for st in driver.push(xyz[i], i / take.fps)]
    return face, errors, got, driver, states


def test_marker_session_equals_the_live_driver_run_locally(live):
    """Marker frames -> the server's mocap live driver -> vertices, equal to the same driver and an
    animator with the driver's control vertices run here (same face, NumPy backend)."""
    from facecast.server.pipeline import Animator

    face, errors, got, driver, states = _marker_session(live, 0.5, 60.0, 60.0, seed=5)
    assert errors == [] and got
    animator = Animator(face, backend="numpy", control_vertices=driver.control_vertices)
    assert got[-1].frame.header.seq == len(states) - 1
    for f in got:
        np.testing.assert_array_equal(f.frame.vertices, animator.frame(states[f.frame.header.seq]))
    assert any(not np.array_equal(got[0].frame.vertices, f.frame.vertices) for f in got)


def test_a_marker_session_sends_frames_at_its_own_rate(live):
    """120 Hz marker frames into a 30 fps session: every marker frame is filtered, a quarter of
    them go out, a session period apart, each the driver's state at its time."""
    from facecast.server.pipeline import Animator

    face, errors, got, driver, states = _marker_session(live, 1.0, 120.0, 30.0, seed=6)
    assert errors == []
    by_frame = {round(st.t * 120.0): st for st in states}
    assert len(by_frame) > 100
    times = np.array([f.frame.header.t for f in got])
    assert abs(len(got) - len(by_frame) / 4) <= 2, (len(got), len(by_frame))
    assert np.diff(times).min() >= 0.8 / 30.0 - 1e-6
    animator = Animator(face, backend="numpy", control_vertices=driver.control_vertices)
    for f in got[::5]:
        st = by_frame[round(f.frame.header.t * 120.0)]
        np.testing.assert_array_equal(f.frame.vertices, animator.frame(st))


@pytest.mark.parametrize("suffix", [".trc", ".c3d"])
def test_stream_command_sends_a_take_with_its_layout(live, tmp_path, suffix):
    """``facecast stream take.trc|c3d`` (in process): the layout beside the take goes in the hello."""
    import argparse

    from facecast.client.commands import stream as stream_cmd
    from facecast.server.api.store import FaceStore
    from facecast.server.mocap.io import write_take
    from facecast.server.mocap.synthetic import synthetic_take

    syn = synthetic_take(FaceStore().face(FACE), n_markers=12, seconds=0.4, fps=60.0, seed=2)
    take_path = write_take(syn.take, tmp_path / f"take{suffix}")
    (tmp_path / "take.layout.json").write_text(json.dumps(syn.layout))

    async def main():
        s = await _session(live, input="markers")
        started = asyncio.Event()
        viewer = asyncio.create_task(_collect(live.url, s.id, s.viewer_token, started=started))
        await started.wait()
        args = argparse.Namespace(
            input=take_path,
            url=live.url,
            session=s.id,
            token=s.producer_token,
            speed=4.0,
            loop=1,
            json_frames=False,
            chunk=0.02,
            layout=None,
        )
        report = await stream_cmd._main(args)
        got = await viewer
        await _close(live, s.id)
        return report, got

    report, got = run(main())
    assert (
        report["kind"] == "markers"
        and report["frames_sent"] == syn.take.n_frames
        and not report["errors"]
    )
    assert got and got[-1].frame.header.t == pytest.approx((syn.take.n_frames - 1) / 60.0)
    args = argparse.Namespace(input=tmp_path / "nolayout" / "t.trc", layout=None)
    with pytest.raises(stream_cmd.StreamError, match="layout"):
        stream_cmd._read_layout(args)


def test_marker_hello_without_layout_is_refused(live):
    async def main():
        s = await _session(live, input="markers")
        try:
            async with produce(
                live.url, s.id, s.producer_token, ProducerHello(input="markers", markers=["A", "B"])
            ):
                pass
        finally:
            await _close(live, s.id)

    assert "layout" in str(_expect_refusal(main(), CloseCode.BAD_REQUEST))


def test_mocap_is_read_as_markers_in_rest_and_in_the_producer_hello(live):
    """One input registry: ``markers`` is the kind's name; ``mocap`` (the batch jobs' old name)
    is accepted wherever a client sends a kind, raw JSON included."""
    from websockets.asyncio.client import connect

    from facecast.client.api import ws_url

    r = httpx.post(
        live.url + "/v1/sessions", json={"input": "mocap", "face": FACE}, headers=live.admin_headers
    )
    assert r.status_code == 201 and r.json()["input"] == "markers", r.text
    s = r.json()

    async def main():
        url = ws_url(live.url, f"/v1/sessions/{s['id']}/produce", token=s["producer_token"])
        async with connect(url) as ws:
            await ws.send(
                json.dumps(
                    {"type": "hello", "role": "producer", "input": "mocap", "markers": ["A", "B"]}
                )
            )
            return json.loads(await ws.recv())

    try:
        msg = run(main())
    finally:
        run(_close(live, s["id"]))
    # matched as a marker hello (not "input does not match the session"): refused for its layout
    assert msg["type"] == "error" and msg["where"] == "hello.layout", msg


def test_websocket_frames_built_once_match_the_websockets_library():
    from websockets.frames import Frame, Opcode

    from facecast.server.live.wire import ws_binary_frame

    for n in (0, 125, 126, 65535, 65536, 200_000):
        payload = bytes(range(256)) * (n // 256) + bytes(n % 256)
        assert ws_binary_frame(payload) == Frame(Opcode.BINARY, payload).serialize(mask=False)


@pytest.mark.slow
def test_asgi_send_path_gives_the_same_frames(joy, tmp_path):
    """With the direct-to-transport path off, viewers get the same frames through ASGI."""
    from facecast.server.api.store import FaceStore
    from facecast.server.drivers.fap import to_animation
    from facecast.server.pipeline import Animator

    plain = live_server(tmp_path, FACE, env={"FACECAST_LIVE_DIRECT": "0"})
    short = type(joy)(fps=joy.fps, frames=joy.frames[:15])

    async def main():
        async with SessionAdmin(plain.url, plain.admin_key) as admin:
            s = await admin.create(face=FACE)
        started = asyncio.Event()
        viewer = asyncio.create_task(_collect(plain.url, s.id, s.viewer_token, started=started))
        await started.wait()
        async with produce(plain.url, s.id, s.producer_token) as p:
            await stream_fap(p, short, speed=2.0)
        return await viewer

    try:
        got = run(main())
    finally:
        plain.stop()
    animator = Animator(FaceStore().face(FACE), backend="numpy")
    states = to_animation(short).states
    assert got[-1].frame.header.seq == 14
    for f in got:
        np.testing.assert_array_equal(f.frame.vertices, animator.frame(states[f.frame.header.seq]))


@pytest.mark.slow
def test_cli_session_stream_watch_close(live, data_dir):
    import subprocess
    import sys

    env = {**os.environ, "FACECAST_ADMIN_KEY": live.admin_key}
    cli = [sys.executable, "-m", "facecast.server.cli"]
    out = subprocess.run(
        cli + ["session", "create", "--url", live.url, "--face", FACE],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    s = json.loads(out.stdout)
    assert {"id", "producer_token", "viewer_token"} <= set(s)
    watcher = subprocess.Popen(
        cli
        + [
            "watch",
            "--url",
            live.url,
            "--session",
            s["id"],
            "--token",
            s["viewer_token"],
            "--encoding",
            "i16",
            "--json",
        ],
        env=env,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        for _ in range(600):  # wait until the viewer is connected
            info = httpx.get(f"{live.url}/v1/sessions/{s['id']}", headers=live.admin_headers).json()
            if info["stats"]["viewers"] == 1:
                break
            time.sleep(0.05)
        fap = data_dir / "xface/faps/joy.fap"
        streamed = subprocess.run(
            cli
            + [
                "stream",
                str(fap),
                "--url",
                live.url,
                "--session",
                s["id"],
                "--token",
                s["producer_token"],
                "--speed",
                "4",
            ],
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert streamed.returncode == 0, streamed.stderr
        assert json.loads(streamed.stdout)["frames_sent"] == 108
        report = json.loads(watcher.communicate(timeout=60)[0])
    finally:
        watcher.kill()
    assert report["frames"] > 0 and report["last_seq"] == 107 and report["encoding"] == "i16"
    assert report["bytes_per_frame"] == 56 + 6 * report["vertex_count"]
    assert (
        report["latency_ms_p95"] is not None
        and report["dropped"] + report["frames"] == 108 - report["first_seq"]
    )
    bad = subprocess.run(
        cli + ["stream", str(fap), "--url", live.url, "--session", s["id"], "--token", "nope"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert (
        bad.returncode == 2 and "token" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
    )
    closed = subprocess.run(
        cli + ["session", "close", "--url", live.url, s["id"]],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert closed.returncode == 0
    assert (
        httpx.get(f"{live.url}/v1/sessions/{s['id']}", headers=live.admin_headers).status_code
        == 404
    )


def test_summary_counts_gaps():
    class F:
        def __init__(self, seq, t):
            self.frame = frames.decode(
                frames.encode_vertices_f32(np.zeros((1, 3)), seq=seq, t=0, wall=t - 0.01)
            )
            self.received, self.size = t, 44

        latency = property(lambda self: self.received - self.frame.header.wall)

    s = summary([F(0, 1.0), F(1, 1.1), F(4, 1.2), F(5, 1.3)])
    assert (
        s["dropped"] == 2
        and s["fps"] == pytest.approx(10.0)
        and s["latency_ms_p50"] == pytest.approx(10.0)
    )
