"""Layers in live sessions against a real server on loopback, with the real asyncio client.

Two producers on one session (speech as the primary, an expression producer with a scoped token),
the refusals of roles (a token without the role, a FAP outside the role, a taken role), the REST
layer calls (idle, an expression overlay, gaze, head) and their malformed requests, and the CLI.
"""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys

import httpx
import numpy as np
import pytest
from conftest import live_server, run
from hypothesis import given, settings
from hypothesis import strategies as st

from facecast.client.api import LiveError, SessionAdmin, produce, stream_pcm, watch
from facecast.protocol.errors import CloseCode
from facecast.protocol.layers import LayerList
from facecast.protocol.messages import ProducerHello

FACE = os.environ.get("FACECAST_TEST_LIVE_FACE", "default:2k")
#: Mouth corner raise the expression producer sends (FAPs 12, 13 inner, 59, 60 outer; FAPU).
SMILE = {12: 300.0, 13: 300.0, 59: 300.0, 60: 300.0}


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    s = live_server(tmp_path_factory.mktemp("layers"), FACE, env={"FACECAST_MAX_SESSIONS": "8"})
    yield s
    s.stop()


@pytest.fixture(scope="module")
def face():
    from facecast.server.api.store import FaceStore

    return FaceStore().face(FACE)


@pytest.fixture(scope="module")
def animator(face):
    from facecast.server.pipeline import Animator

    return Animator(face, backend="numpy")


def corners_y(face, vertices: np.ndarray) -> float:
    """Mean height (mm) of the mouth corners (feature points 8.3, 8.4)."""
    ids = [face.feature_points["8.3"], face.feature_points["8.4"]]
    return float(vertices[ids, 1].mean() * face.mm_per_unit)


def chin_y(face, vertices: np.ndarray) -> float:
    return float(vertices[face.feature_points["2.1"], 1] * face.mm_per_unit)


async def _session(url: str, key: str, **kw):
    async with SessionAdmin(url, key) as admin:
        return await admin.create(face=FACE, **kw)


async def _close(url: str, key: str, sid: str) -> None:
    async with SessionAdmin(url, key) as admin:
        await admin.close(sid)


async def _expect(coro, code: int) -> LiveError:
    with pytest.raises(LiveError) as e:
        await coro
    assert e.value.code == code, e.value
    return e.value


def test_speech_moves_the_jaw_while_an_expression_producer_raises_the_corners(
    live, data_dir, face, animator
):
    """Viewers see both producers: the primary's speech (its jaw, frame by frame as the same
    driver gives it) and the expression producer's smile over it, mixed into every frame."""
    import soundfile as sf

    from facecast.server.audio.live import AudioLiveDriver

    samples, rate = sf.read(str(data_dir / "speech/mary.wav"), dtype="int16")
    samples = samples[: rate * 2] if samples.ndim == 1 else samples[: rate * 2, 0].copy()
    fps = 30.0

    async def main():
        s = await _session(live.url, live.admin_key, input="audio", fps=fps)
        async with SessionAdmin(live.url, live.admin_key) as admin:
            scoped = await admin.token(s.id, ["expression"])
        got = []
        started, speaking, smiling = asyncio.Event(), asyncio.Event(), asyncio.Event()

        async def viewer():
            async with watch(
                live.url, s.id, s.viewer_token, encoding="f32", until_producer_leaves=True
            ) as w:
                started.set()
                async for f in w:  # until both producers have left
                    got.append((f, smiling.is_set() and not done.is_set()))
                    speaking.set()

        async def expression():
            await speaking.wait()  # the speech is on: it clocks the frames
            hello = ProducerHello(role="expression")
            async with produce(live.url, s.id, scoped.token, hello) as p:
                assert p.ready.role == "expression" and p.ready.input == "fap"
                await p.send_faps(SMILE, 0.0)
                await asyncio.sleep(0.3)  # the smile reaches the server before the frames judged
                smiling.set()
                await done.wait()
                return list(p.errors)

        done = asyncio.Event()
        v = asyncio.create_task(viewer())
        await started.wait()
        e = asyncio.create_task(expression())
        hello = ProducerHello(input="audio", rate=rate, sample_format="i16")
        async with produce(live.url, s.id, s.producer_token, hello) as p:
            await stream_pcm(p, samples, rate, chunk=0.04)
            primary_errors = list(p.errors)
        done.set()
        expression_errors = await e
        await asyncio.wait_for(v, 60)
        await _close(live.url, live.admin_key, s.id)
        return primary_errors, expression_errors, got

    primary_errors, expression_errors, got = run(main())
    assert primary_errors == [] and expression_errors == []
    # the speech alone, as the same driver gives it here, frame by frame (by media time)
    local = AudioLiveDriver(face, rate, fps=fps)
    x = samples.astype(np.float32) / 32768
    n = int(0.04 * rate)
    states = [st for i in range(0, len(x), n) for st in local.push(x[i : i + n], i / rate)]
    states += local.flush()
    by_t = {round(st.t, 6): st for st in states}
    smiled = [f for f, on in got if on and round(f.frame.header.t, 6) in by_t]
    assert len(smiled) >= 10, f"{len(smiled)} frames with the smile on, of {len(got)}"
    raise_mm, jaw_mm, chins = [], [], []
    for f in smiled:
        speech_only = animator.frame(by_t[round(f.frame.header.t, 6)])
        seen = f.positions()
        raise_mm.append(corners_y(face, seen) - corners_y(face, speech_only))
        jaw_mm.append(chin_y(face, seen) - chin_y(face, speech_only))
        chins.append(chin_y(face, seen))
    # the corners are up over the speech in every frame; the jaw is the speech's own
    assert min(raise_mm) > 1.0, [
        (round(r, 2), f.frame.header.t) for r, f in zip(raise_mm, smiled) if r < 1
    ]
    assert max(abs(j) for j in jaw_mm) < 0.5, jaw_mm
    assert max(chins) - min(chins) > 2.0  # and the speech moves it


def test_roles_a_token_lacks_or_fapS_outside_the_role_are_refused(live):
    async def main():
        s = await _session(live.url, live.admin_key, input="fap", fps=30)
        async with SessionAdmin(live.url, live.admin_key) as admin:
            scoped = await admin.token(s.id, ["expression"])
        out = {}
        for role in ("gaze", "primary"):
            out[role] = await _expect(
                produce(live.url, s.id, scoped.token, ProducerHello(role=role)).__aenter__(),
                CloseCode.FORBIDDEN,
            )
        out["audio"] = await _expect(
            produce(
                live.url,
                s.id,
                s.producer_token,
                ProducerHello(role="expression", input="audio", rate=16000),
            ).__aenter__(),
            CloseCode.FORBIDDEN,
        )
        async with produce(live.url, s.id, scoped.token, ProducerHello(role="expression")) as p:
            await p.send_faps({23: 400.0}, 0.0)  # the eyeballs are the gaze role's
            await p.send_faps({12: 100.0}, 0.0, binary=False)
            await p.send_faps({31: 100.0}, 0.1, viseme=(1, 0, 63))
            for _ in range(100):
                if len(p.errors) >= 2:
                    break
                await asyncio.sleep(0.05)
            errors = list(p.errors)
        await _close(live.url, live.admin_key, s.id)
        return out, errors

    out, errors = run(main())
    assert "may drive the role(s) expression, not 'gaze'" in str(out["gaze"])
    assert "not 'primary'" in str(out["primary"])
    assert "sends FAP frames (input 'fap'), not audio" in str(out["audio"])
    assert len(errors) == 2 and all(e.code == CloseCode.FORBIDDEN and not e.fatal for e in errors)
    assert "may not drive FAP 23" in errors[0].message
    assert "may not send visemes" in errors[1].message


def test_one_producer_per_role(live):
    async def main():
        s = await _session(live.url, live.admin_key, input="fap", fps=30)
        async with (
            produce(
                live.url, s.id, s.producer_token, ProducerHello(role="expression")
            ) as expression,
            produce(live.url, s.id, s.producer_token, ProducerHello(role="gaze")),
            produce(live.url, s.id, s.producer_token),  # the primary, an old client's hello
        ):
            err = await _expect(
                produce(
                    live.url, s.id, s.producer_token, ProducerHello(role="expression")
                ).__aenter__(),
                CloseCode.CONFLICT,
            )
            await expression.send_faps({31: 100.0}, 0.0)  # its layer is in once it sends
            async with SessionAdmin(live.url, live.admin_key) as admin:
                for _ in range(100):
                    layers = await admin.layers(s.id)
                    if layers.layers:
                        break
                    await asyncio.sleep(0.05)
        await _close(live.url, live.admin_key, s.id)
        return err, layers

    err, layers = run(main())
    assert "already has a 'expression' producer" in str(err)
    assert [(x.name, x.source) for x in layers.layers] == [("expression", "producer")]


def test_rest_layers_drive_a_session_without_a_producer(live, face):
    """Idle alone makes frames at the session's rate; an expression overlay raises the corners;
    PATCH changes it, DELETE removes it, and with no layer left the frames stop."""

    async def frames_now(s, n):
        out = []
        async with watch(live.url, s.id, s.viewer_token, encoding="f32") as w:
            async for f in w:
                out.append(f)
                if len(out) >= n:
                    break
        return out

    async def main():
        s = await _session(live.url, live.admin_key, input="fap", fps=30)
        async with SessionAdmin(live.url, live.admin_key) as admin:
            await admin.set_layer(s.id, "idle", {"kind": "idle", "seed": 3})
            idle = await frames_now(s, 20)
            info = await admin.set_layer(s.id, "smile", {"kind": "expression", "expression": "joy"})
            await admin.remove_layer(s.id, "idle")  # its sway would move the corners too
            await asyncio.sleep(0.1)
            joy = await frames_now(s, 5)
            await admin.patch_layer(s.id, "smile", {"amount": 0.0})
            await asyncio.sleep(0.1)
            off = await frames_now(s, 5)
            listed = await admin.layers(s.id)
            await admin.set_layer(s.id, "idle", {"kind": "idle", "seed": 3})
            look = {"kind": "gaze", "target": {"direction": [0.34, 0.0, 0.94]}}
            await admin.set_layer(s.id, "look", look)
            nod = {"kind": "head", "gesture": "nod", "repetitions": 2}
            await admin.set_layer(s.id, "nod", nod)
            await admin.remove_layer(s.id, "smile")
            after = await admin.layers(s.id)
            async with watch(live.url, s.id, s.viewer_token, encoding="f32"):  # one watches
                await asyncio.sleep(0.3)
                info_layers = await admin.info(s.id)
                await asyncio.sleep(0.3)
                info_later = await admin.info(s.id)
                assert info_later.stats.states > info_layers.stats.states  # layers make frames
                await admin.remove_layer(s.id)  # all
                empty = await admin.layers(s.id)
                await asyncio.sleep(0.3)
                info_end = await admin.info(s.id)
                await asyncio.sleep(0.5)
                info_later = await admin.info(s.id)
        await _close(live.url, live.admin_key, s.id)
        return idle, info, joy, off, listed, after, empty, info_end, info_later

    idle, info, joy, off, listed, after, empty, info_end, info_later = run(main())
    assert info.kind == "expression" and info.spec["expression"] == "joy"
    # idle moves the face on its own (sway, saccades), frame after frame
    assert any(not np.array_equal(idle[0].positions(), f.positions()) for f in idle)
    assert corners_y(face, joy[-1].positions()) - corners_y(face, off[-1].positions()) > 1.0
    assert [x.name for x in listed.layers] == ["smile"] and listed.layers[0].spec["amount"] == 0.0
    assert sorted(x.name for x in after.layers) == ["idle", "look", "nod"]
    assert empty.layers == []
    assert info_later.stats.states == info_end.stats.states  # no layer: no more frames


def test_malformed_layer_requests_are_4xx_with_a_message(live):
    s = run(_session(live.url, live.admin_key, input="fap", fps=30))
    base = f"{live.url}/v1/sessions/{s.id}"
    admin = live.admin_headers
    producer = {"Authorization": f"Bearer {s.producer_token}"}
    r = httpx.post(base + "/tokens", json={"roles": ["expression"]}, headers=producer)
    assert r.status_code == 201
    scoped = {"Authorization": f"Bearer {r.json()['token']}"}
    cases = [
        ("PUT", "/layers/idle", None, b"{not json", 400, "not JSON"),
        ("PUT", "/layers/idle", None, b"[" * 60_000, 400, "nests too deeply"),
        ("PUT", "/layers/idle", None, {"kind": "sleep"}, 400, "'kind'"),
        ("PUT", "/layers/idle", None, {"kind": "idle", "amount": 2}, 400, "amount"),
        ("PUT", "/layers/x", None, {"kind": "expression"}, 400, "'expression'"),
        ("PUT", "/layers/x", None, {"kind": "expression", "faps": {"3": 1e9}}, 400, "FAP 3"),
        ("PUT", "/layers/x", None, {"kind": "gaze", "target": "moon"}, 400, "target"),
        ("PUT", "/layers/x", None, {"kind": "head"}, 400, "'gesture' or a 'pose'"),
        ("PUT", "/layers/x", None, {"kind": "idle", "envelope": {}}, 400, "envelope"),
        (
            "PUT",
            "/layers/x",
            None,
            {"kind": "expression", "faps": {"12": 1}, "envelope": {"start": 2, "end": 1}},
            400,
            "start <= attack_peak",
        ),
        ("PUT", "/layers/x", None, [1, 2], 400, "JSON object"),
        ("PUT", "/layers/bad%20name", None, {"kind": "idle"}, 400, "layer name"),
        ("PUT", "/layers/x", None, {"kind": "idle", "x" * 70_000: 1}, 413, "at most"),
        ("PATCH", "/layers/none", None, {"amount": 1}, 404, "no layer 'none'"),
        ("DELETE", "/layers/none", None, None, 404, "no layer 'none'"),
        ("GET", "/layers", {}, None, 401, "producer token"),
        ("PUT", "/layers/x", {"Authorization": "Bearer nope"}, {"kind": "idle"}, 401, "token"),
        ("PUT", "/layers/x", scoped, {"kind": "idle"}, 403, "'idle' layer"),
        ("POST", "/tokens", scoped, {"roles": ["gaze"]}, 403, "cannot mint"),
        ("POST", "/tokens", None, {"roles": ["king"]}, 400, "roles"),
        ("POST", "/tokens", None, {"roles": []}, 400, "roles"),
        ("POST", "/tokens", None, {"roles": ["gaze", "gaze"]}, 400, "once"),
    ]
    for method, path, headers, body, status, words in cases:
        kw = {"content": body} if isinstance(body, bytes) else {"json": body}
        r = httpx.request(method, base + path, headers=admin if headers is None else headers, **kw)
        assert r.status_code == status, (method, path, body, r.status_code, r.text[:300])
        assert words in r.json()["error"], (method, path, r.json())
    # a patch cannot change a layer's kind; a scoped token reaches its own kind's layers
    assert httpx.put(base + "/layers/idle", json={"kind": "idle"}, headers=admin).status_code == 200
    r = httpx.patch(base + "/layers/idle", json={"kind": "gaze"}, headers=admin)
    assert r.status_code == 400 and "kind cannot change" in r.json()["error"]
    r = httpx.put(
        base + "/layers/s", json={"kind": "expression", "expression": "joy"}, headers=scoped
    )
    assert r.status_code == 200
    assert httpx.delete(base + "/layers/idle", headers=scoped).status_code == 403
    assert httpx.get(base + "/layers", headers=scoped).status_code == 200
    run(_close(live.url, live.admin_key, s.id))


def test_the_cli_streams_a_layer_and_sets_layers(live, data_dir, tmp_path):
    s = run(_session(live.url, live.admin_key, input="fap", fps=30))
    env = dict(os.environ, FACECAST_ADMIN_KEY=live.admin_key)
    cli = [sys.executable, "-m", "facecast.server.cli"]

    def facecast(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(
            [*cli, *args], env=env, capture_output=True, text=True, timeout=120, check=False
        )

    r = facecast("session", "token", s.id, "--roles", "expression", "--url", live.url)
    assert r.returncode == 0, r.stderr
    token = json.loads(r.stdout)["token"]
    r = facecast("session", "layer", "set", s.id, "idle", "kind=idle", "seed=4", "--url", live.url)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["spec"]["seed"] == 4
    r = facecast("session", "layer", "patch", s.id, "idle", "amount=0.5", "--url", live.url)
    assert r.returncode == 0 and json.loads(r.stdout)["spec"]["amount"] == 0.5, r.stderr
    r = facecast("session", "layer", "set", s.id, "idle", "kind=nap", "--url", live.url)
    assert r.returncode == 2 and "kind" in r.stderr
    joy = data_dir / "xface/faps/joy.fap"
    r = facecast(
        "stream", str(joy), "--url", live.url, "--session", s.id, "--token", token,
        "--role", "expression", "--speed", "4",
    )  # fmt: skip
    # joy.fap moves eyeballs and the head too: those frames are refused, the rest stream
    report = json.loads(r.stdout)
    assert report["role"] == "expression" and report["frames_sent"] > 0, r.stderr
    assert all("may not drive FAP" in e for e in report["errors"])
    r = facecast(
        "stream", str(joy), "--url", live.url, "--session", s.id, "--token", token,
        "--role", "gaze",
    )  # fmt: skip
    assert r.returncode == 2 and "'gaze'" in r.stderr
    r = facecast("session", "layers", s.id, "--url", live.url, "--token", token)
    assert r.returncode == 0 and [x["name"] for x in json.loads(r.stdout)["layers"]] == ["idle"]
    run(_close(live.url, live.admin_key, s.id))


@pytest.mark.browser
def test_the_page_mixes_a_smile_and_idle_over_a_streamed_voice(live, data_dir, face, artifacts):
    """The page watches an audio session that ``facecast stream`` speaks into; its 'joy' button
    and idle toggle become layers over the voice: the corners go up while the lips keep talking.
    Screenshot: tests/artifacts/layers_voice_joy_idle.png."""
    from test_web import ARGS, CHROMIUM, open_page, wait_for

    if not os.path.exists(CHROMIUM):
        pytest.skip("Debian chromium not installed")
    from playwright.sync_api import sync_playwright

    s = run(_session(live.url, live.admin_key, input="audio", fps=30))
    speech = data_dir / "speech/mary.wav"
    stream = subprocess.Popen(
        [
            sys.executable, "-m", "facecast.server.cli", "stream", str(speech), "--url", live.url,
            "--session", s.id, "--loop", "12",
        ],
        env=dict(os.environ, FACECAST_TOKEN=s.producer_token),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    fp = face.feature_points
    # mouth corners over the nose tip (mm): the head's sway moves both
    corners = (
        f"(facecast.renderer.vertex({fp['8.3']})[1] + facecast.renderer.vertex({fp['8.4']})[1]) / 2"
        f" - facecast.renderer.vertex({fp['9.3']})[1]"
    )
    gap = f"facecast.renderer.vertex({fp['2.2']})[1] - facecast.renderer.vertex({fp['2.3']})[1]"

    def sample(page, n=15):
        out = []
        for _ in range(n):
            page.wait_for_timeout(100)
            out.append((page.evaluate(corners), page.evaluate(gap)))
        return np.array(out) * face.mm_per_unit

    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            page, problems = open_page(
                browser,
                f"{live.url}/#session={s.id}&token={s.viewer_token}&producer={s.producer_token}",
            )
            wait_for(page, "window.facecast.viewer.stats.frames >= 10", timeout=90)
            before = sample(page)
            page.click("#expressions button:text('joy')")
            wait_for(page, "document.getElementById('layer-info').textContent.includes('joy')")
            page.wait_for_timeout(600)  # the smile's attack
            joy = sample(page)
            page.click("#idle")
            wait_for(page, "document.getElementById('layer-info').textContent.includes('idle on')")
            page.wait_for_timeout(1500)
            page.screenshot(path=str(artifacts / "layers_voice_joy_idle.png"))
            with_idle = sample(page, 10)
            page.evaluate("""() => {
              const brows = document.querySelector('#sliders input[data-fap="31,32,33,34,35,36"]');
              brows.value = 300; brows.dispatchEvent(new Event('input'));
            }""")  # the sliders stream as an 'expression' producer over the voice
            wait_for(
                page, "window.facecast.state.layerProducer && facecast.state.layerProducer.open"
            )
            page.wait_for_timeout(500)
            r = httpx.get(f"{live.url}/v1/sessions/{s.id}/layers", headers=live.admin_headers)
            browser.close()

        listed = LayerList.model_validate(r.json())
    finally:
        stream.kill()
        stream.communicate(timeout=30)
        run(_close(live.url, live.admin_key, s.id))
    assert not problems, problems
    assert sorted((x.name, x.source) for x in listed.layers) == [
        ("expression", "producer"),
        ("expression", "rest"),
        ("idle", "rest"),
    ]
    # the smile raises the corners; the voice still opens and closes the lips under it
    assert joy[:, 0].mean() - before[:, 0].mean() > 1.0, (before[:, 0], joy[:, 0])
    assert np.ptp(joy[:, 1]) > 0.5 and np.ptp(with_idle[:, 1]) > 0.5, (joy[:, 1], with_idle[:, 1])


# -------------------------------------------------------------------------------- pure pieces

_json = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=12),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=10), inner, max_size=4)
    ),
    max_leaves=12,
)
_KEYS = ["kind", "seed", "amount", "expression", "faps", "envelope", "regions", "blink_rate",
         "target", "pose", "gesture", "repetitions", "blinks"]  # fmt: skip
_KINDS = st.sampled_from(["idle", "expression", "gaze", "head", "sleep", 3, None])


@settings(max_examples=300, deadline=None)
@given(
    body=st.dictionaries(st.sampled_from(_KEYS), _json, max_size=6) | _json,
    kind=_KINDS,
    changes=st.dictionaries(st.sampled_from(_KEYS), _json, max_size=3) | _json,
)
def test_layer_bodies_parse_or_raise_only_message_errors(body, kind, changes):
    from facecast.protocol.errors import MessageError
    from facecast.protocol.layers import parse_layer, patch_layer

    if isinstance(body, dict) and kind is not None:
        body = {**body, "kind": kind}
    try:
        spec = parse_layer(body)
    except MessageError as e:
        assert str(e)
        return
    try:
        patched = patch_layer(spec, changes)
    except MessageError:
        return
    assert patched.kind == spec.kind


def test_scoped_tokens_carry_their_roles_only_and_are_bounded():
    from facecast.protocol.errors import TooMany
    from facecast.server.live.roles import ALL_ROLES, MAX_SCOPED_TOKENS, Grants

    g = Grants("full")
    assert (
        g.roles_of("full") == ALL_ROLES and g.roles_of("nope") is None and g.roles_of(None) is None
    )
    t = g.mint(["gaze", "head"])
    assert g.roles_of(t) == {"gaze", "head"} and t != "full"
    with pytest.raises(ValueError, match="roles"):
        g.mint(["king"])
    for _ in range(MAX_SCOPED_TOKENS - 1):
        g.mint(["idle"])
    with pytest.raises(TooMany) as e:
        g.mint(["idle"])
    assert e.value.status == 429


def test_a_deeply_nested_control_message_is_a_message_error():
    """``json`` raises RecursionError past ~1000 levels (a 60 kB hello): it was a server fault."""
    from facecast.protocol.errors import MessageError
    from facecast.protocol.messages import parse_message

    with pytest.raises(MessageError, match="nests too deeply"):
        parse_message("[" * 60_000)


def test_a_deform_batch_mixes_its_sessions_states_together_each_as_alone(animator):
    """The deform thread mixes a batch's layered states at once (``mixing.mix_jobs``): each job
    gets what its session's mixer gives its state alone, keeps its media time; a job without
    layers is left alone; a session whose layer fails fails its own frame only."""
    from types import SimpleNamespace

    from facecast.server.layers import (
        Contribution,
        ExpressionLayer,
        GazeLayer,
        GazeTarget,
        IdleLayer,
        Mixer,
        Role,
    )
    from facecast.server.live.mixing import geometry_of, mix_jobs
    from facecast.server.state import FaceState

    geo = geometry_of(animator.rig)
    assert geometry_of(animator.rig) is geo  # one per rig: the sessions of a face mix together

    class Broken:
        role, end = Role.IDLE, None

        def sample(self, t: float) -> Contribution:
            raise RuntimeError("a broken layer")

    def session(k: int, broken: bool = False) -> SimpleNamespace:
        m = Mixer(geo)
        m.set("idle", IdleLayer(seed=k))
        m.set("smile", ExpressionLayer(1, amount=0.5))
        m.set("gaze", GazeLayer(GazeTarget(point=np.array([10.0 * k, 0.0, 500.0]))))
        if broken:
            m.set("broken", Broken())
        return SimpleNamespace(mixer=m, now=lambda: 2.0 + k, mixed=0)

    rng = np.random.default_rng(5)
    mixes = [session(k, broken=k == 3) for k in range(8)]
    states = [FaceState(t=0.04 * k, faps=rng.normal(0, 80, 69)) for k in range(9)]
    jobs = [SimpleNamespace(state=s, mix=m) for s, m in zip(states, mixes)]
    jobs.append(SimpleNamespace(state=states[8], mix=None))
    failed = mix_jobs(jobs)
    assert list(failed) == [3] and "broken" in str(failed[3])
    assert jobs[8].state is states[8]  # no layers: not mixed
    for k, (job, m) in enumerate(zip(jobs[:8], mixes)):
        if k == 3:
            assert job.state is states[3] and m.mixed == 0
            continue
        want = m.mixer.mix(states[k], 2.0 + k)
        assert job.state.t == states[k].t and m.mixed == 1
        np.testing.assert_allclose(job.state.faps, want.faps, rtol=1e-9, atol=1e-6)
        assert not np.allclose(job.state.faps, states[k].faps)  # the layers did move it


def test_the_layer_clock_s_neutral_frames_are_mixed_in_the_deform_thread_as_no_primary(animator):
    """Frames the layer clock makes without a primary reach the deform thread unmixed
    (``Neutral``) and are mixed there as ``mix`` mixes no primary: no closures to keep, so an
    overlay may open the lips; the frame keeps its time."""
    from types import SimpleNamespace

    from facecast.server.layers import ExpressionLayer, Mixer
    from facecast.server.live.mixing import Neutral, geometry_of, mix_jobs
    from facecast.server.state import FaceState

    m = Mixer(geometry_of(animator.rig))
    m.set("open", ExpressionLayer(0, faps=np.eye(69)[5] * -400.0))  # the lower lip down
    jobs = [
        SimpleNamespace(
            state=Neutral(t=7.0), mix=SimpleNamespace(mixer=m, now=lambda: 1.0, mixed=0)
        ),
        SimpleNamespace(
            state=FaceState(t=7.0), mix=SimpleNamespace(mixer=m, now=lambda: 1.0, mixed=0)
        ),
    ]
    assert mix_jobs(jobs) == {}
    neutral, closed = jobs[0].state, jobs[1].state
    assert type(neutral) is FaceState and neutral.t == 7.0 and jobs[0].mix.mixed == 1
    np.testing.assert_allclose(neutral.faps, m.mix(None, 1.0).faps)
    assert neutral.faps[5] == -400.0  # opened: no primary holds the lips
    assert closed.faps[5] > -400.0  # a primary's closed lips keep the overlay from opening them


def test_a_rig_s_geometry_is_shared_while_it_lives_and_forgotten_with_it(face):
    import gc

    from facecast.server.live import mixing
    from facecast.server.mpeg4.rig import FapRig

    rig = FapRig(face)
    geo = mixing.geometry_of(rig)
    assert mixing.geometry_of(rig) is geo and id(rig) in mixing._geometries
    key = id(rig)
    del rig
    gc.collect()
    assert key not in mixing._geometries
