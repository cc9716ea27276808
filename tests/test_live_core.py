"""The live core without sockets: producer and viewer state machines fed text and bytes.

A real ``LiveSession`` over a stand-in deformer (it records what it is asked to deform); the clock
is the test's. What the shell would send and the close it would make are read off the steps.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from facecast.protocol import frames
from facecast.protocol.errors import CloseCode, FrameError, MessageError
from facecast.protocol.messages import ProducerHello, dump_message
from facecast.server.errors import FacecastError, InputError, NotFound
from facecast.server.live import inputs as inputs_mod
from facecast.server.live import producer as producer_mod
from facecast.server.live.budget import FLOOD_BURST_SECONDS, MAX_TEXT_BYTES
from facecast.server.live.core import NOTHING, Event, Step, authorise, client_error
from facecast.server.live.inputs import BadHello, InputUnavailable
from facecast.server.live.producer import ProducerCore, State
from facecast.server.live.session import LiveSession, SessionSpec
from facecast.server.live.watch import ViewerCore

MAX_FPS = 100.0


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


class Deformer:
    """Stands in for a ``DeformBatcher``: records the states it is given, never answers."""

    def __init__(self, name: str = "own") -> None:
        self.animator = SimpleNamespace(name=name)
        self.states: list[Any] = []

    def submit_nowait(self, state, *, seq, wall, encodings, done, compact=None, mix=None) -> None:
        self.states.append((seq, state, wall))


class Slot:
    remote = True

    def __init__(self) -> None:
        self.ended: list[tuple[int, str]] = []

    async def end(self, code: int, error_json: str) -> None:
        self.ended.append((code, error_json))


class Animators:
    def __init__(self) -> None:
        self.built: list[np.ndarray] = []

    def animator_for(self, session, control_vertices):
        self.built.append(np.array(control_vertices))
        return SimpleNamespace(cv=np.array(control_vertices))

    def batcher_for(self, animator):
        return Deformer(name="mocap")


def _session(kind: str = "fap", max_viewers: int = 4) -> LiveSession:
    spec = SessionSpec(
        id="s1",
        face="default",
        input=kind,
        fps=60.0,
        engine="fp",
        max_viewers=max_viewers,
        producer_token="P",
        viewer_token="V",
    )
    face = SimpleNamespace(vertices=np.zeros((10, 3), np.float32), mm_per_unit=10.0)
    return LiveSession(spec, face, Deformer())


def _core(session: LiveSession, clock: Clock | None = None, animators=None) -> ProducerCore:
    return ProducerCore(
        session, Slot(), animators=animators or Animators(), max_fps=MAX_FPS, clock=clock or Clock()
    )


def carry_out(step: Step, sent: list[dict]) -> Step:
    """What the shell does: collect the messages, run the work inline, feed the results back."""
    while True:
        sent.extend(json.loads(t) for t in step.send)
        if step.work is None:
            return step
        step = step.work.then(step.work.run())


def _ready(session: LiveSession, **kw) -> tuple[ProducerCore, list[dict]]:
    core = _core(session, **kw)
    assert core.connect() is NOTHING
    sent: list[dict] = []
    step = core.receive_text(dump_message(ProducerHello(input=session.spec.input)))
    assert step.event is Event.HELLO and step.work is not None and core.state is State.OPENING
    step = carry_out(step, sent)
    assert step.event is Event.READY and step.close is None, step
    assert [m["type"] for m in sent] == ["ready"] and sent[0]["max_fps"] == MAX_FPS
    assert core.state is State.READY and session.producer is core.slot
    return core, sent


def _faps(seq: int, **kw) -> bytes:
    v = np.full(68, np.nan, np.float32)
    v[2] = float(seq)
    return frames.encode_faps(v, seq=seq, t=seq / 60, **kw)


# ------------------------------------------------------------------------------------- producers


def test_hello_then_frames_stream_into_the_session():
    session = _session()
    core, sent = _ready(session)
    for i in range(5):
        assert core.receive_bytes(_faps(i, wall=7.0)) is NOTHING  # the hot path allocates no step
    step = core.receive_text(json.dumps({"type": "fap", "seq": 5, "t": 0.1, "faps": {"3": 2.0}}))
    assert step is NOTHING and core.state is State.STREAMING
    stats = session.stats
    assert stats["frames_in"] == 6 and stats["states"] == 6 and stats["frames_rejected"] == 0
    assert session.seq == 6
    assert sent == [sent[0]]  # nothing but the ready message was answered


def test_prometheus_counts_every_frame_once_the_producer_leaves():
    """Frames taken reach the Prometheus counter in batches, all of them by the producer's exit."""
    from facecast.server.api.metrics import Metrics

    session = _session()
    session.metrics = metrics = Metrics()
    core, _ = _ready(session)

    def counted() -> float:
        return metrics.registry.get_sample_value("facecast_frames_received_total") or 0.0

    for i in range(45):
        core.receive_bytes(_faps(i))
        assert counted() <= session.stats["frames_in"] == i + 1
    core.close()  # the producer leaves
    assert counted() == 45


@pytest.mark.parametrize(
    ("first", "words"),
    [
        (b"\x00garbage", "not a binary frame"),
        ("[]", ""),
        ("null", ""),
        ('{"type": "nope"}', ""),
        ('{"type": "hello", "role": "producer", "protocol": 99}', "protocol version 99"),
        ("x" * 300_000, "limit"),
        (dump_message(ProducerHello(input="audio", rate=16000)), "takes 'fap'"),
    ],
)
def test_garbage_instead_of_a_hello_closes_with_4400(first, words):
    session = _session()
    core = _core(session)
    core.connect()
    step = core.receive_bytes(first) if isinstance(first, bytes) else core.receive_text(first)
    step = carry_out(step, [])
    assert step.event is Event.CLOSED and step.close is not None
    assert step.close.code == CloseCode.BAD_REQUEST and words in step.close.message
    error = json.loads(step.close.error)
    assert error["type"] == "error" and error["code"] == 4400 and error["fatal"]
    assert len(step.close.reason.encode()) <= 123
    assert core.state is State.CLOSED and not core.open
    core.close()
    assert session.producer is None


def test_bad_frames_are_answered_and_dropped_but_the_stream_goes_on():
    session = _session()
    core, _ = _ready(session)
    sent: list[dict] = []
    good = _faps(7)
    pcm = frames.encode_pcm(np.zeros(160, np.int16), rate=16000, sample_offset=0, seq=9)
    for bad in (good + b"\x00", good[:-3], b"\x00" * 40, pcm):
        step = core.receive_bytes(bad)
        assert step.event is Event.REJECTED and step.close is None
        carry_out(step, sent)
    for bad in ('{"type": "hello", "role": "producer"}', "{", '{"type": "fap", "t": "x"}'):
        carry_out(core.receive_text(bad), sent)
    assert all(m["code"] == 4400 and not m["fatal"] for m in sent)
    assert all(m["message"].startswith("frame dropped: ") for m in sent)
    assert [m["seq"] for m in sent[:2]] == [7, 7] and sent[3]["seq"] == 9  # named when readable
    assert "producers send 'fap' messages" in sent[4]["message"] and sent[4]["where"] == "type"
    assert core.receive_bytes(_faps(8)) is NOTHING  # still streaming
    assert session.stats["frames_rejected"] == 7 and session.stats["frames_in"] == 1


def test_a_second_producer_is_refused_with_4409_until_the_first_leaves():
    session = _session()
    first, _ = _ready(session)
    second = _core(session)
    assert second.connect() is NOTHING  # the role's slot is taken at the hello
    step = second.receive_text(dump_message(ProducerHello()))
    assert step.close is not None and step.close.code == CloseCode.CONFLICT
    assert "already has a 'primary' producer" in step.close.message
    second.close()  # a refused producer's close leaves the slot alone
    assert session.producer is first.slot
    first.close()
    first.close()  # idempotent
    assert session.producer is None
    third, _ = _ready(session)
    assert session.producer is third.slot


def test_a_flood_is_dropped_with_one_warning_then_closed_with_1008():
    session = _session()
    clock = Clock()
    core, _ = _ready(session, clock=clock)
    frame = _faps(1)
    events, sent = [], []
    for _ in range(10_000):  # all at the same instant: a second's burst, then drops, then a flood
        step = core.receive_bytes(frame)
        events.append(step.event)
        sent.extend(json.loads(t) for t in step.send)
        if step.close is not None:
            break
    assert events[: int(MAX_FPS)] == [Event.NONE] * int(MAX_FPS)
    assert events[-1] is Event.CLOSED and set(events[int(MAX_FPS) : -1]) == {Event.DROPPED}
    assert len(events) == FLOOD_BURST_SECONDS * MAX_FPS + 1
    assert [m["code"] for m in sent] == [CloseCode.TOO_MANY]  # one warning a second at most
    close = step.close
    assert close.code == CloseCode.POLICY_VIOLATION and close.cut_off
    assert "far faster" in close.message and "100 per second" in close.message
    assert core.state is State.CLOSED and core.receive_bytes(frame) is NOTHING
    clock.now += 1.0  # a later warning would be due, but the connection is closed
    assert session.stats["frames_rejected"] == len(events) - MAX_FPS


def test_an_oversized_message_closes_with_1009():
    session = _session()
    core, _ = _ready(session)
    step = core.receive_text("x" * (MAX_TEXT_BYTES + 1))
    assert step.close is not None and step.close.code == CloseCode.TOO_BIG and step.close.cut_off
    assert f"limit of {MAX_TEXT_BYTES} bytes" in step.close.message


def test_no_hello_in_time_and_internal_faults():
    session = _session()
    core = _core(session)
    core.connect()
    step = core.timeout()
    assert step.close.code == CloseCode.TIMEOUT and "no hello within" in step.close.message
    step = _core(session).failed(RuntimeError("/secret/path"))
    assert step.close.code == CloseCode.INTERNAL and "secret" not in step.close.error


def test_a_driver_that_fails_costs_one_frame_not_the_connection(monkeypatch, caplog):
    def boom(self, frame):
        raise RuntimeError("driver bug at /secret/path")

    monkeypatch.setattr(inputs_mod.FapInput, "push_frame", boom)
    session = _session()
    core, _ = _ready(session)
    with caplog.at_level(logging.ERROR):
        step = core.receive_bytes(_faps(3))
    message = json.loads(step.send[0])
    assert message["code"] == CloseCode.INTERNAL and not message["fatal"] and message["seq"] == 3
    assert "secret" not in message["message"] and "driver failed" in caplog.text
    assert step.close is None and core.open


def test_a_missing_driver_is_4503(monkeypatch):
    audio = dataclasses.replace(
        inputs_mod.DRIVERS["audio"], live=("facecast.no_such_module", "Driver")
    )
    monkeypatch.setitem(inputs_mod.DRIVERS, "audio", audio)
    session = _session("audio")
    core = _core(session)
    core.connect()
    step = carry_out(core.receive_text(dump_message(ProducerHello(input="audio", rate=16000))), [])
    assert step.close.code == CloseCode.UNAVAILABLE and "not available" in step.close.message


class _MocapInput:
    """A marker input whose control vertices are known from its second frame on."""

    kinds = frozenset({frames.Kind.FAPS})

    def __init__(self) -> None:
        self.control_vertices = None
        self.pushed = 0

    def push_frame(self, frame):
        self.pushed += 1
        if self.pushed >= 2:
            self.control_vertices = np.array([1, 2, 3], np.int32)
        return [SimpleNamespace(t=frame.header.t)]

    def push_message(self, msg):
        raise MessageError("binary only")

    def flush(self):
        return [SimpleNamespace(t=99.0)]


def test_the_animator_follows_the_inputs_control_vertices_once(monkeypatch):
    """Off-loop work for a mocap input: each push is work; new control vertices build an animator
    (work too) and swap the session's deformer before the frame's states are submitted."""
    monkeypatch.setattr(producer_mod, "make_input", lambda *a: _MocapInput())
    session = _session("markers")
    own = session.batcher
    animators = Animators()
    core, _ = _ready(session, animators=animators)
    steps = []
    for i in range(4):
        step = core.receive_bytes(_faps(i))
        assert step.work is not None and step.work.offload  # the driver runs in a thread
        steps.append(carry_out(step, []))
    assert [len(a) for a in animators.built] == [3]  # built once, at the second frame
    assert session.batcher is not own and session.batcher.animator.name == "mocap"
    assert np.array_equal(session.control_vertices, [1, 2, 3])
    assert len(own.states) == 0 and len(session.batcher.states) == 0  # nobody watches: skipped
    assert session.stats["frames_in"] == 4 and session.seq == 4
    # leaving flushes the input's held states into the session
    carry_out(core.disconnected(), [])
    assert session.seq == 5 and core.state is State.CLOSED


# ------------------------------------------------------------------------------------- viewers


def test_viewers_are_admitted_greeted_and_refused():
    session = _session(max_viewers=1)
    core = ViewerCore(session, "f16")
    step = core.greet()
    assert step.close.code == CloseCode.BAD_REQUEST and step.close.where == "encoding"
    first = ViewerCore(session, "compact")
    hello = json.loads(first.greet().send[0])
    assert hello["type"] == "hello" and hello["encoding"] == "compact"
    assert hello["tolerance"] == pytest.approx(0.01) and not hello["producer_connected"]
    assert session.joining == 1
    second = ViewerCore(session, "i16")  # the joining viewer counts against the limit
    assert second.greet().close.code == CloseCode.TOO_MANY
    assert first.greeted() is NOTHING and session.joining == 0
    assert first.write_buffer() == 4096 and first.send_buffer() == 64 * 1024
    assert ViewerCore(session, "f32").write_buffer() is None


def test_a_viewer_greeted_into_a_closed_session_is_told():
    session = _session()
    core = ViewerCore(session, "i16")
    core.greet()
    session.closed = True
    assert core.greeted().close.code == CloseCode.SESSION_CLOSED


def test_a_viewer_that_talks_is_ignored_then_closed():
    clock = Clock()
    core = ViewerCore(_session(), "f32", clock=clock)
    assert core.receive(10, True) is NOTHING
    for _ in range(1000):
        step = core.receive(10, True)
        if step.close is not None:
            break
    assert step.close.code == CloseCode.POLICY_VIOLATION
    assert step.close.message.startswith("viewers only listen: ") and step.close.cut_off
    big = ViewerCore(_session(), "f32", clock=clock).receive(100_000, False)
    assert big.close.code == CloseCode.TOO_BIG and "4096 bytes" in big.close.message


def test_a_session_is_idle_only_while_nobody_uses_it():
    session = _session()
    start = session.last_active
    assert session.idle_for(start + 5) == 5
    session.join()  # a viewer being greeted: in use, and seen now
    assert session.idle_for(start + 7) == 0 and session.last_active == start + 7
    session.joined()
    assert session.idle_for(start + 9) == 2
    server_side = SimpleNamespace(remote=False)
    assert session.claim(server_side) and session.idle_for(start + 10) == 3  # alone: not in use


# ------------------------------------------------------------------------------ shared decisions


def test_errors_map_to_close_codes():
    assert client_error(InputUnavailable("x")) == (4503, "x", "")
    where = "hello.rate"
    assert client_error(BadHello("bad", where=where)) == (4400, f"{where}: bad", where)
    assert client_error(FrameError("short")) == (4400, "short", "")
    assert client_error(InputError("no", where="f")) == (4400, "f: no", "f")
    assert client_error(NotFound("gone")) == (4404, "gone", "")
    assert client_error(FacecastError("no device")) == (4500, "no device", "")  # this side's
    assert client_error(ValueError("nan")) is None  # outside the tree: a server fault
    assert client_error(RuntimeError("bug")) is None
    assert client_error(KeyError("k")) is None


def test_tokens_decide_who_may_connect():
    assert authorise("s", True, "P", "P", "V", "producer") is None
    assert authorise("s", False, "P", "", "", "producer").code == CloseCode.NOT_FOUND
    mixed = authorise("s", True, "V", "P", "V", "producer")
    assert mixed.code == CloseCode.FORBIDDEN and "viewer token" in mixed.message
    for wrong in (None, "", "p", "\ud800"):
        assert authorise("s", True, wrong, "V", "P", "viewer").code == CloseCode.UNAUTHORIZED


# ------------------------------------------------------------- the routes, in process (no server)


@pytest.fixture
def routed():
    """The sessions router over a registry holding one stand-in session (TestClient: in process,
    no socket; the transport helpers find no uvicorn and do nothing)."""
    from fastapi import FastAPI
    from starlette.testclient import TestClient

    from facecast.server.api import routes_sessions
    from facecast.server.live.registry import SessionRegistry

    app = FastAPI()
    app.include_router(routes_sessions.router)
    reg = SessionRegistry(None, max_sessions=4, max_viewers=4, max_fps=MAX_FPS, threads=1)
    session = _session()
    reg.sessions[session.spec.id] = session
    app.state.live = reg
    with TestClient(app) as client:
        yield client, session
    reg.executor.shutdown()
    reg.batch_executor.shutdown()


def _refused(ws) -> tuple[dict, int]:
    error = ws.receive_json()
    return error, ws.receive()["code"]


def test_routes_feed_the_core_and_carry_out_its_steps(routed):
    client, session = routed
    auth = {"Authorization": "Bearer P"}
    with client.websocket_connect("/v1/sessions/s1/produce", headers=auth) as producer:
        producer.send_text(dump_message(ProducerHello()))
        assert producer.receive_json()["type"] == "ready"
        for i in range(3):
            producer.send_bytes(_faps(i))
        producer.send_bytes(b"\x00garbage")
        error = producer.receive_json()  # the routes send what the core answered
        assert error["code"] == 4400 and not error["fatal"]
        with client.websocket_connect("/v1/sessions/s1/produce", headers=auth) as second:
            second.send_text(dump_message(ProducerHello()))
            error, code = _refused(second)
            assert code == error["code"] == CloseCode.CONFLICT and error["fatal"]
        with client.websocket_connect(
            "/v1/sessions/s1/watch?encoding=i16", headers={"Authorization": "Bearer V"}
        ) as viewer:
            hello = viewer.receive_json()
            assert hello["type"] == "hello" and hello["producer_connected"]
            viewer.close()
        producer.close()
    assert session.stats["frames_in"] == 3 and session.stats["frames_rejected"] == 1
    assert session.producer is None  # the route's finally freed the slot


@pytest.mark.parametrize(
    ("path", "token", "code"),
    [
        ("/v1/sessions/nope/produce", "P", CloseCode.NOT_FOUND),
        ("/v1/sessions/s1/produce", "V", CloseCode.FORBIDDEN),
        ("/v1/sessions/s1/watch", "wrong", CloseCode.UNAUTHORIZED),
        ("/v1/sessions/s1/watch?encoding=f16", "V", CloseCode.BAD_REQUEST),
    ],
)
def test_routes_refuse_with_the_cores_close(routed, path, token, code):
    client, _ = routed
    with client.websocket_connect(path, headers={"Authorization": f"Bearer {token}"}) as ws:
        error, closed = _refused(ws)
    assert closed == error["code"] == code and error["fatal"]


def test_the_core_imports_no_web_framework():
    import subprocess
    import sys

    code = (
        "import sys\n"
        "import facecast.server.live.producer, facecast.server.live.watch\n"
        "import facecast.server.live.server_producer, facecast.server.live.registry\n"
        "print(sorted({m.split('.')[0] for m in sys.modules} & {'fastapi', 'starlette', 'uvicorn'}))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_live_settings_are_read_once_from_the_environment(monkeypatch):
    from types import SimpleNamespace as NS

    from facecast.server.api import routes_sessions
    from facecast.server.api.config import ServerConfig
    from facecast.server.api.transport import DirectSender

    monkeypatch.setenv("FACECAST_LIVE_DIRECT", "0")
    monkeypatch.setenv("FACECAST_LIVE_BATCHES", "2")
    monkeypatch.setenv("FACECAST_LIVE_COALESCE_MS", "3")
    monkeypatch.setenv("FACECAST_LIVE_COALESCE_FRAMES", "24")
    app = NS(state=NS(config=ServerConfig(), store=None, metrics=None))
    monkeypatch.setenv("FACECAST_LIVE_BATCHES", "5")  # read once: later changes do nothing
    reg = routes_sessions.registry(app)
    try:
        s = reg.settings
        assert (s.direct, s.batches, s.coalesce_seconds) == (False, 2, 0.003)
        assert DirectSender.attach(NS(), s.direct) is None  # frames go through ASGI
        assert reg.batcher_for(NS(deformer=None)).coalesce == 0.003
        assert reg.batcher_for(NS(deformer=None)).coalesce_frames == 24
    finally:
        reg.executor.shutdown()
        reg.batch_executor.shutdown()
    defaults = ServerConfig.model_construct().live_settings()
    assert (defaults.direct, defaults.batch_threads, defaults.device_quantize) == (True, 1, True)
    assert defaults.coalesce_frames == 8
    monkeypatch.setenv("FACECAST_LIVE_THREADS", "many")
    with pytest.raises(ValueError, match="live_threads"):
        ServerConfig()


def test_a_session_closed_while_the_hello_is_handled_gets_no_ready():
    session = _session()
    core = _core(session)
    core.connect()
    step = core.receive_text(dump_message(ProducerHello()))
    session.closed = True  # an admin closed it while the input was being made
    assert step.work.then(step.work.run()) is NOTHING
    assert core.state is State.CLOSED and not core.open


def test_metrics_count_every_frame_taken_while_the_producer_streams(routed):
    """``/metrics`` brings the sessions' batched frame counts up to date before it renders: every
    frame taken so far is counted while the producer still streams (fewer than a batch of 32)."""
    from facecast.server.api import routes_health
    from facecast.server.api.metrics import Metrics

    client, session = routed
    session.metrics = metrics = Metrics()
    client.app.include_router(routes_health.router)
    client.app.state.metrics = metrics
    with client.websocket_connect(
        "/v1/sessions/s1/produce", headers={"Authorization": "Bearer P"}
    ) as producer:
        producer.send_text(dump_message(ProducerHello()))
        assert producer.receive_json()["type"] == "ready"
        for i in range(5):
            producer.send_bytes(_faps(i))
        producer.send_text(dump_message(ProducerHello()))  # answered after the frames: all taken
        producer.receive_json()
        assert session.stats["frames_in"] == 5
        text = client.get("/metrics").text
        assert "facecast_frames_received_total 5.0" in text
        producer.close()
