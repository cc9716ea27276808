"""Server-side producers on a real server: the demo performance, file playback, session tokens."""

from __future__ import annotations

import asyncio
import json

import httpx
import numpy as np
import pytest

from facecast.client.api import watch
from facecast.protocol.messages import ProducerHello


def create(server, **body) -> dict:
    r = httpx.post(
        server.url + "/v1/sessions",
        json={"input": "fap", "fps": 30, **body},
        headers=server.admin_headers,
        timeout=120,
    )
    r.raise_for_status()
    return r.json()


async def collect(server, session: dict, n: int, timeout: float = 60.0) -> list:
    got = []

    async def run():
        async with watch(server.url, session["id"], session["viewer_token"]) as w:
            async for f in w:
                got.append(f)
                if len(got) >= n:
                    return

    await asyncio.wait_for(run(), timeout)
    return got


def test_demo_drives_the_face_until_stopped_then_frees_the_producer_slot(server):
    s = create(server)
    r = httpx.post(
        f"{server.url}/v1/sessions/{s['id']}/demo?token={s['producer_token']}", timeout=30
    )
    assert r.status_code == 202, r.text
    frames = asyncio.run(collect(server, s, 30))
    ts = [f.frame.header.t for f in frames]
    assert ts == sorted(ts) and ts[-1] > ts[0]
    pos = np.stack([f.positions() for f in frames])
    assert np.abs(pos - pos[0]).max() > 0.5, "the demo did not move the face (mm)"
    # A WebSocket producer is refused while the demo holds the slot, and accepted after it stops.
    from facecast.client.api import LiveError, produce

    async def try_produce():
        async with produce(server.url, s["id"], s["producer_token"], ProducerHello(input="fap")):
            return True

    with pytest.raises(LiveError, match="already"):
        asyncio.run(try_produce())
    assert (
        httpx.delete(
            f"{server.url}/v1/sessions/{s['id']}/demo", headers=server.admin_headers, timeout=30
        ).status_code
        == 204
    )
    assert asyncio.run(try_produce())


def test_playing_a_fap_file_streams_its_frames_at_its_rate(server, data_dir):
    s = create(server)
    fap = data_dir / "xface" / "faps" / "joy.fap"
    with open(fap, "rb") as fh:
        r = httpx.post(
            f"{server.url}/v1/sessions/{s['id']}/play",
            headers=server.admin_headers,
            files={"file": ("joy.fap", fh)},
            timeout=120,
        )
    assert r.status_code == 202, r.text
    info = r.json()
    assert info["kind"] == "fap" and info["fps"] == 25 and info["frames"] == 108
    frames = asyncio.run(collect(server, s, 20))
    t = np.array([f.frame.header.t for f in frames])
    steps = np.diff(t) * 25  # media times are the file's frame times (a viewer may skip some)
    assert np.all(steps >= 1 - 1e-6) and np.allclose(steps, np.round(steps), atol=1e-6)


def test_playback_needs_a_credential_and_refuses_bad_files(server, tmp_path):
    s = create(server)
    url = f"{server.url}/v1/sessions/{s['id']}/play"
    r = httpx.post(url, files={"file": ("a.fap", b"2.1 x 25 1\n")}, timeout=30)
    assert r.status_code == 401 and "producer token" in r.json()["error"]
    r = httpx.post(
        url + f"?token={s['viewer_token']}", files={"file": ("a.fap", b"2.1 x 25 1\n")}, timeout=30
    )
    assert r.status_code == 401
    bad = b"2.1 broken 25 2\n" + b"1 " * 68 + b"\n0 1 2\n"
    r = httpx.post(
        url + f"?token={s['producer_token']}", files={"file": ("broken.fap", bad)}, timeout=30
    )
    assert r.status_code == 400, r.text
    assert "broken" not in r.json()["error"] or "line" in r.json()["error"]
    r = httpx.post(
        url + f"?token={s['producer_token']}", files={"file": ("x.mp3", b"ID3....")}, timeout=30
    )
    assert r.status_code in (400, 415), r.text
    # The session still works for a good file.
    good = b"2.1 ok 25 1\n" + b" ".join([b"0", b"0", b"1"] + [b"0"] * 65) + b"\n0 300\n"
    r = httpx.post(
        url + f"?token={s['producer_token']}", files={"file": ("ok.fap", good)}, timeout=30
    )
    assert r.status_code == 202, r.text


def test_tokens_are_for_the_admin_only(server):
    s = create(server)
    url = f"{server.url}/v1/sessions/{s['id']}/tokens"
    assert httpx.get(url, timeout=30).status_code == 401
    got = httpx.get(url, headers=server.admin_headers, timeout=30).json()
    assert got["viewer_token"] == s["viewer_token"] and got["producer_token"] == s["producer_token"]
    assert (
        httpx.get(
            f"{server.url}/v1/sessions/nope/tokens", headers=server.admin_headers, timeout=30
        ).status_code
        == 404
    )


def test_playing_a_marker_take_with_its_layout_moves_the_face(server, tmp_path):
    from facecast.protocol.markers_file import write_trc
    from facecast.server.faces import load_face
    from facecast.server.mocap.synthetic import synthetic_take

    syn = synthetic_take(load_face("default"), n_markers=16, seconds=1.0, fps=60.0, seed=3)
    s = create(server)
    url = f"{server.url}/v1/sessions/{s['id']}/play?token={s['producer_token']}"
    trc = write_trc(syn.take).encode()
    r = httpx.post(url, files={"file": ("take.trc", trc)}, timeout=120)
    assert r.status_code == 400 and "layout" in r.json()["error"], (
        r.text
    )  # no layout: says what is missing
    r = httpx.post(
        url, files={"file": ("take.trc", trc)}, data={"layout": json.dumps(syn.layout)}, timeout=120
    )
    assert r.status_code == 202, r.text
    assert r.json()["kind"] == "markers" and r.json()["frames"] == 60
    frames = asyncio.run(collect(server, s, 20))
    pos = np.stack([f.positions() for f in frames])
    assert np.isfinite(pos).all() and np.abs(pos - pos[0]).max() > 0.1


def test_play_never_opens_a_file_the_client_names(server, tmp_path):
    from facecast.protocol.markers_file import write_trc
    from facecast.server.faces import load_face
    from facecast.server.mocap.synthetic import synthetic_take

    syn = synthetic_take(load_face("default"), n_markers=16, seconds=0.5, fps=60.0, seed=4)
    trc = write_trc(syn.take).encode()
    secret = tmp_path / "secret.json"
    secret.write_text(json.dumps({"zz_secret_key": 1, "markers": {"zz_marker": {}}}))
    s = create(server)
    url = f"{server.url}/v1/sessions/{s['id']}/play?token={s['producer_token']}"
    for value in (
        json.dumps(str(secret)),
        json.dumps("/etc/passwd"),
        str(secret),
        "/etc/passwd",
        "[1]",
    ):
        r = httpx.post(url, files={"file": ("take.trc", trc)}, data={"layout": value}, timeout=120)
        assert r.status_code == 400, (value, r.text)
        assert "layout" in r.json()["error"]
        assert "zz_" not in r.text and "root:" not in r.text and str(tmp_path) not in r.text
    # The layout as a file part (curl -F layout=@take.layout.json) plays the take.
    r = httpx.post(
        url,
        files={"file": ("take.trc", trc), "layout": ("take.layout.json", json.dumps(syn.layout))},
        timeout=120,
    )
    assert r.status_code == 202, r.text
    assert r.json()["kind"] == "markers" and r.json()["frames"] == 30


def test_play_errors_name_no_server_path_and_uploads_live_in_the_data_dir(server):
    s = create(server)
    url = f"{server.url}/v1/sessions/{s['id']}/play?token={s['producer_token']}"
    bad = b"2.1 broken 25 2\n" + b"1 " * 68 + b"\n0 " + b"9" * 4301 + b"\n"  # a 4,301-digit integer
    r = httpx.post(url, files={"file": ("huge.fap", bad)}, timeout=60)
    assert 400 <= r.status_code < 500 and r.json()["error"], r.text
    for private in ("/tmp", str(server.data_dir), "facecast-play"):
        assert private not in r.text, r.text
    r = httpx.post(
        url, files={"file": ("mine.fap", b"2.1 x 25 1\n\xff\xfe not text\n")}, timeout=60
    )
    assert r.status_code == 400 and "mine.fap" in r.json()["error"], (
        r.text
    )  # the client's name, not ours
    assert "/tmp" not in r.text and str(server.data_dir) not in r.text
    assert (server.data_dir / "tmp").is_dir() and not list((server.data_dir / "tmp").iterdir())
    big_fap = b"2.1 big 25 1\n" + b"0 " * (5 * 1024 * 1024)  # 10 MiB: over the 8 MiB FAP limit
    r = httpx.post(url, files={"file": ("big.fap", big_fap)}, timeout=60)
    assert r.status_code == 413 and "FACECAST_MAX_FAP_BYTES" in r.json()["error"], r.text


def test_play_answers_503_with_retry_after_when_every_decode_slot_is_busy(tmp_path):
    import threading

    from fastapi.testclient import TestClient

    from facecast.server.api.app import create_app
    from facecast.server.api.config import ServerConfig

    app = create_app(
        ServerConfig(
            data_dir=tmp_path,
            admin_key="k",
            job_workers=0,
            face="default:2k",
            backend="numpy",
            max_concurrent_decodes=1,
        )
    )
    client = TestClient(app)
    s = client.post(
        "/v1/sessions", json={"input": "fap", "fps": 30}, headers={"Authorization": "Bearer k"}
    ).json()
    app.state.decode_slots = threading.Semaphore(0)  # as if one decode were running
    good = b"2.1 ok 25 1\n" + b" ".join([b"0", b"0", b"1"] + [b"0"] * 65) + b"\n0 300\n"
    r = client.post(
        f"/v1/sessions/{s['id']}/play?token={s['producer_token']}", files={"file": ("ok.fap", good)}
    )
    assert (
        r.status_code == 503 and r.headers["retry-after"] == "2" and "retry" in r.json()["error"]
    ), r.text
    app.state.decode_slots = threading.Semaphore(1)
    r = client.post(
        f"/v1/sessions/{s['id']}/play?token={s['producer_token']}", files={"file": ("ok.fap", good)}
    )
    assert r.status_code == 202, r.text
    slots = app.state.decode_slots
    assert slots.acquire(blocking=False)  # the decode gave its slot back
    slots.release()
    r = client.post(
        f"/v1/sessions/{s['id']}/play?token={s['producer_token']}",
        files={"file": ("bad.fap", b"2.1 bad 25 1\nnot a mask\n")},
    )
    assert r.status_code == 400, r.text
    assert slots.acquire(blocking=False)  # so did the failed one
