"""Compact vertex streams through a real server on loopback: every frame a compact viewer shows is
within the session's tolerance of the float32 frame another viewer got, slow and late viewers
included, and the CLI records a session to .npz."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys

import numpy as np
import pytest
from conftest import live_server, run

from facecast.client.api import LiveError, SessionAdmin, produce, stream_fap, watch
from facecast.protocol import frames
from facecast.protocol.fap_file import read_fap

FACE = "default:2k"


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    s = live_server(
        tmp_path_factory.mktemp("live-compact"), FACE, env={"FACECAST_MAX_PRODUCER_FPS": "150"}
    )
    yield s
    s.stop()


@pytest.fixture(scope="module")
def joy(data_dir):
    return read_fap((data_dir / "xface/faps/joy.fap").read_text(), where="joy.fap")


async def _collect(url, sid, token, encoding, started, out, *, slow_until=None):
    small = {"receive_buffer": 2048, "max_queue": 1} if slow_until is not None else {}
    async with watch(url, sid, token, encoding=encoding, until_producer_leaves=True, **small) as w:
        out["hello"] = w.hello
        started.set()
        if slow_until is not None:
            await slow_until.wait()  # reads nothing meanwhile: the server skips frames for it
        async for f in w:
            out.setdefault("frames", []).append(f)
        out["waited"] = w.waited


def test_compact_viewers_fast_slow_and_late_see_only_correct_faces(live, joy):
    async def main():
        async with SessionAdmin(live.url, live.admin_key) as admin:
            s = await admin.create(face=FACE, input="fap", fps=60.0, tolerance=0.1)
        ref, fast, slow, late = {}, {}, {}, {}
        evs = [asyncio.Event() for _ in range(3)]
        release = asyncio.Event()
        tasks = [
            asyncio.create_task(
                _collect(live.url, s.id, s.viewer_token, enc, ev, out, slow_until=rel)
            )
            for enc, ev, out, rel in (
                ("f32", evs[0], ref, None),
                ("compact", evs[1], fast, None),
                ("compact", evs[2], slow, release),
            )
        ]
        await asyncio.gather(*(e.wait() for e in evs))
        late_started = asyncio.Event()
        async with produce(live.url, s.id, s.producer_token) as p:
            streaming = asyncio.create_task(stream_fap(p, joy, speed=2.0))
            await asyncio.sleep(0.8)
            tasks.append(
                asyncio.create_task(
                    _collect(live.url, s.id, s.viewer_token, "compact", late_started, late)
                )
            )
            await asyncio.sleep(0.5)
            release.set()
            await streaming
        await asyncio.gather(*tasks)
        async with SessionAdmin(live.url, live.admin_key) as admin:
            await admin.close(s.id)
        return ref, fast, slow, late

    ref, fast, slow, late = run(main())
    assert ref["hello"].encoding == "f32" and fast["hello"].encoding == "compact"
    tol = fast["hello"].tolerance
    assert tol == pytest.approx(0.1)  # the built-in head is in millimetres
    truth = {f.frame.header.seq: f.positions() for f in ref["frames"]}
    for name, got in (("fast", fast), ("slow", slow), ("late", late)):
        shown = got.get("frames", [])
        assert shown, f"the {name} compact viewer showed nothing"
        for f in shown:
            seq = f.frame.header.seq
            if seq in truth:
                err = np.linalg.norm(f.positions().astype(np.float64) - truth[seq], axis=1).max()
                assert err <= tol, (name, seq, err)
    assert len(fast["frames"]) >= 0.9 * len(ref["frames"])
    assert fast["waited"] == 0  # it had every key frame
    assert {f.frame.header.seq for f in fast["frames"]} <= set(truth) | {max(truth) + 1}
    size = np.mean([f.size for f in fast["frames"]])
    assert size < frames.vertex_frame_size("i16", fast["hello"].vertex_count) / 10
    # the slow viewer (which may skip frames) ends on the newest one, as does the late one
    assert slow["frames"][-1].frame.header.seq == max(truth) == late["frames"][-1].frame.header.seq
    assert late["frames"][0].frame.header.seq > 0


def test_cli_watch_saves_the_decoded_frames(live, joy, tmp_path):
    async def main():
        async with SessionAdmin(live.url, live.admin_key) as admin:
            s = await admin.create(face=FACE, input="fap", fps=60.0)
        out = tmp_path / "rec.npz"
        cmd = [
            sys.executable,
            "-m",
            "facecast.server.cli",
            "watch",
            "--url",
            live.url,
            "--session",
            s.id,
            "--token",
            s.viewer_token,
            "--json",
            "--save",
            str(out),
        ]
        proc = await asyncio.create_subprocess_exec(
            *cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE
        )
        await asyncio.sleep(3.0)  # the CLI connects (imports take a while on a loaded machine)
        async with produce(live.url, s.id, s.producer_token) as p:
            await stream_fap(p, joy, speed=3.0)
        stdout, stderr = await asyncio.wait_for(proc.communicate(), 60)
        assert proc.returncode == 0, stderr.decode()
        return json.loads(stdout), out

    report, out = run(main())
    assert report["encoding"] == "compact" and report["bits_per_second"] > 0
    z = np.load(out)
    n = report["frames"]
    assert n > 10 and z["vertices"].shape[0] == n == len(z["seq"]) == len(z["t"])
    assert z["vertices"].shape[2] == 3 and z["vertices"].dtype == np.float32
    assert np.all(np.diff(z["t"]) > 0)


def test_a_slow_viewer_gets_the_key_frame_before_the_deltas_that_replaced_it():
    from test_protocol_compact import synthetic_stream

    from facecast.protocol.compact import CompactDecoder, CompactEncoder
    from facecast.server.live.session import Viewer

    rest, groups, vs, trs = synthetic_stream(n_vertices=200, n_frames=8, seed=2)
    enc = CompactEncoder(rest, groups, tolerance=0.1, key_interval=4)
    wire = [enc.encode(v, tr, seq=i, t=i) for i, (v, tr) in enumerate(zip(vs, trs))]

    async def main():
        viewer = Viewer("compact")
        for b in wire[:3]:  # key 0, then deltas 1 and 2 replace each other in the slot
            viewer.offer((memoryview(b), b))
        first = await viewer.next()
        second = await viewer.next()
        viewer.offer((memoryview(wire[3]), wire[3]))
        viewer.offer((memoryview(wire[4]), wire[4]))  # key 4 supersedes: delta 3 is dropped
        third = await viewer.next()
        return [first[1][1], second[1][1], third[1][1]]

    got = asyncio.run(main())
    assert got == [wire[0], wire[2], wire[4]]
    dec = CompactDecoder(rest, groups)
    assert all(dec.decode(b) is not None for b in got)


def test_tolerance_is_validated_and_reaches_the_hello(live):
    import httpx

    for bad in (0, -1, 1000, "x"):
        r = httpx.post(
            f"{live.url}/v1/sessions", json={"tolerance": bad}, headers=live.admin_headers
        )
        assert r.status_code == 422, (bad, r.text)

    async def main():
        async with SessionAdmin(live.url, live.admin_key) as admin:
            s = await admin.create(face=FACE, input="fap", tolerance=0.5)
        async with watch(live.url, s.id, s.viewer_token) as w:
            hello = w.hello
        async with watch(live.url, s.id, s.viewer_token, encoding="i16") as w:
            other = w.hello
        return hello, other

    hello, other = run(main())
    assert hello.encoding == "compact" and hello.tolerance == pytest.approx(0.5)
    assert other.encoding == "i16" and other.tolerance is None


def test_a_tolerance_no_float32_grid_can_keep_is_refused_at_create(live):
    """Was accepted, then every compact viewer's connection failed (1006, a traceback)."""

    async def main():
        async with SessionAdmin(live.url, live.admin_key) as admin:
            with pytest.raises(LiveError, match="HTTP 400.*too small"):
                await admin.create(face=FACE, input="fap", fps=60.0, tolerance=1e-6)

    run(main())
