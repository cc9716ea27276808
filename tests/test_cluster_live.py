"""Live sessions across cluster nodes: real ``redis-server``, real ``facecast serve --redis`` nodes.

A session created on node A, produced into on node B, watched on A and C gets the frames of the
single-process path; the owner killed with SIGKILL mid-stream, another node takes the session
over and its viewers, still connected, see frames again (a gap, never a wrong face); Redis
restarted under load, the nodes recover. No timed assertions: every wait has a generous deadline.
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time

import httpx
import numpy as np
import pytest
from cluster_support import FACE, cluster_node, running, wait_for
from conftest import RunningServer, run

from facecast.client.api import LiveError, SessionAdmin, produce, stream_fap, watch
from facecast.protocol import frames
from facecast.protocol.fap_file import read_fap
from facecast.protocol.messages import ProducerHello
from facecast.server.harness import RedisServer, free_port

FPS = 60.0

pytestmark = pytest.mark.skipif(
    not RedisServer.available(), reason="redis-server is not installed (bash .ci/setup)"
)


def node(redis_url: str, tmp_path, name: str) -> RunningServer:
    """One node process (``--workers 1``), not started."""
    return cluster_node(tmp_path / name, redis_url, "--job-workers", "0")


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """Redis and three nodes A, B, C (the module's last test kills A)."""
    tmp = tmp_path_factory.mktemp("cluster")
    redis = RedisServer()
    nodes = [node(redis.url, tmp, name) for name in "abc"]
    with running(redis, nodes, ready=True):
        yield redis, nodes


def view(srv: RunningServer) -> dict:
    r = httpx.get(srv.url + "/v1/cluster", headers=srv.admin_headers, timeout=10)
    assert r.status_code == 200, r.text
    return r.json()


def fap_vector(i: int) -> np.ndarray:
    """FAPs 3..68 of frame ``i``, all sent (FAPs 1 and 2 travel apart): a complete state per frame."""
    v = np.full(68, np.nan, np.float32)
    v[2:] = 150.0 * np.sin(i / 9.0 + np.arange(66) / 7.0)
    return v


def expected_vertices(animator, t: float, i: int) -> np.ndarray:
    """What the single-process path makes of ``fap_vector(i)`` at ``t`` (its own input class)."""
    from facecast.server.live.inputs import FapInput

    frame = frames.decode(frames.encode_faps(fap_vector(i), seq=i, t=t, wall=0.0))
    (state,) = FapInput().push_frame(frame)
    return animator.frame(state)


@pytest.fixture(scope="module")
def joy(data_dir):
    return read_fap((data_dir / "xface/faps/joy.fap").read_text(), where="joy.fap")


def all3(v: dict) -> dict | None:
    return v if len(v["nodes"]) == 3 else None


async def until(check, what: str, timeout: float = 60.0) -> None:
    """Wait (polling) until ``check()`` is true; fail with ``what`` after ``timeout`` s."""
    for _ in range(int(timeout / 0.05)):
        if check():
            return
        await asyncio.sleep(0.05)
    assert check(), what


def test_cluster_view_lists_every_node_and_marks_self(cluster):
    _, nodes = cluster
    ids = set()
    for srv in nodes:
        v = wait_for(lambda s=srv: all3(view(s)))
        me = [n for n in v["nodes"] if n["self"]]
        assert len(me) == 1 and me[0]["id"] == v["self"] and me[0]["url"] == srv.url
        assert v["broker"] == "up"
        ids.add(v["self"])
        assert httpx.get(srv.url + "/readyz").status_code == 200
        metrics = httpx.get(srv.url + "/metrics").text
        assert f'facecast_cluster_broker_up{{node="{v["self"]}"}} 1.0' in metrics
    assert len(ids) == 3
    assert httpx.get(nodes[0].url + "/v1/cluster").status_code == 401  # admin only


def test_session_made_on_a_produced_on_b_watched_on_a_and_c_equals_batch_render(cluster, joy):
    from facecast.server.api.store import FaceStore
    from facecast.server.drivers.fap import to_animation
    from facecast.server.pipeline import Animator

    _, (a, b, c) = cluster

    async def collect(srv, sid, token, started, encoding="f32"):
        got = []
        async with watch(srv.url, sid, token, encoding=encoding, until_producer_leaves=True) as w:
            started.set()
            async for f in w:
                got.append(f)
        return got

    async def main():
        async with SessionAdmin(a.url, a.admin_key) as admin:
            s = await admin.create(face=FACE, input="fap", fps=float(joy.fps))
        owner = [n for n in view(b)["nodes"] if s.id in n["sessions"]]
        ready = [asyncio.Event() for _ in range(3)]
        viewers = [
            asyncio.create_task(collect(srv, s.id, s.viewer_token, ev, enc))
            for srv, ev, enc in ((a, ready[0], "f32"), (c, ready[1], "f32"), (c, ready[2], "i16"))
        ]
        await asyncio.gather(*(ev.wait() for ev in ready))
        await asyncio.sleep(0.5)  # C's wish for frames reaches A (no frame is lost meanwhile)
        async with produce(b.url, s.id, s.producer_token) as p:
            sent = await stream_fap(p, joy, speed=2.0)
            errors = list(p.errors)
        got = await asyncio.wait_for(asyncio.gather(*viewers), 60)
        async with SessionAdmin(c.url, c.admin_key) as admin:  # another node answers for A
            for _ in range(600):
                info = await admin.info(s.id)  # the owner's counters, written every second
                if info.stats.frames_in == sent:
                    break
                await asyncio.sleep(0.1)
            listed = [x.id for x in await admin.list()]
            await admin.close(s.id)  # closed from another node
        return s, owner, sent, errors, got, info, listed

    s, owner, sent, errors, got, info, listed = run(main())
    assert info.stats.frames_in == sent and info.vertex_count == s.vertex_count
    assert s.id in listed
    assert [o["url"] for o in owner] == [a.url]
    assert errors == [] and sent == len(joy.frames)
    animation = to_animation(joy)
    animator = Animator(FaceStore().face(FACE), backend="numpy")
    for frames_ in got:
        assert frames_, "a viewer received no frames"
        assert frames_[-1].frame.header.seq == len(joy.frames) - 1  # the newest frame arrives
        for f in frames_:
            h = f.frame.header
            exp = animator.frame(animation.states[h.seq])
            if h.kind is frames.Kind.VERTICES_F32:
                np.testing.assert_array_equal(f.frame.vertices, exp)  # bit for bit
            else:
                assert h.kind is frames.Kind.VERTICES_I16
                np.testing.assert_allclose(f.positions(), exp, atol=2 * f.frame.scale.max())
    assert len(got[1]) > len(joy.frames) // 2  # the other node's viewers saw most frames
    wait_for(lambda: all(s.id not in n["sessions"] for n in view(a)["nodes"]), what="the close")


def test_node_without_admin_key_adopts_the_clusters(cluster, tmp_path):
    redis, (a, _, _) = cluster
    d = cluster_node(
        tmp_path / "d", redis.url, "--job-workers", "0", env={"FACECAST_ADMIN_KEY": ""}
    )
    d.admin_key = ""
    d.start()
    try:
        assert d.admin_key == a.admin_key
        r = httpx.get(d.url + "/v1/cluster", headers=a.admin_headers)
        assert r.status_code == 200 and len(r.json()["nodes"]) == 4
    finally:
        d.stop()


def test_two_nodes_claiming_one_session_the_lease_decides(cluster):
    from facecast.server.cluster import leases

    redis, _ = cluster

    async def main():
        import redis.asyncio as aioredis

        clients = [aioredis.Redis.from_url(redis.url) for _ in range(2)]
        try:
            got = await asyncio.gather(
                *(
                    leases.acquire(r, "claimed", f"node{i}", ttl_ms=60_000)
                    for i, r in enumerate(clients)
                )
            )
            again = await leases.acquire(clients[0], "claimed", "node0")
            holder = await leases.holders(clients[0], ["claimed"])
        finally:
            for r in clients:
                await r.aclose()
        return got, again, holder

    got, again, holder = run(main())
    assert sorted(x > 0 for x in got) == [False, True]  # exactly one took it
    winner = f"node{[x > 0 for x in got].index(True)}"
    assert holder == {"claimed": winner}
    assert again == (-1 if winner == "node0" else 0)


def test_unreachable_redis_at_start_is_a_clear_error(tmp_path):
    port = free_port()
    r = subprocess.run(
        [sys.executable, "-m", "facecast.server.cli", "serve", "--data-dir", str(tmp_path)]
        + ["--redis", f"redis://127.0.0.1:{port}/0", "--workers", "1"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2
    assert "cannot reach the cluster's Redis" in r.stderr and str(port) in r.stderr


def test_several_node_processes_need_redis(tmp_path):
    r = subprocess.run(
        [sys.executable, "-m", "facecast.server.cli", "serve", "--data-dir", str(tmp_path)]
        + ["--workers", "2"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2 and "--redis" in r.stderr and "--workers" in r.stderr


def test_refusals_on_a_node_that_does_not_own_the_session(cluster):
    """Tokens are checked from the shared record (scoped ones by the owner, which minted them); a
    second producer is refused by the owner."""
    from facecast.protocol.errors import CloseCode

    _, (a, b, c) = cluster

    async def refused(coro) -> int | None:
        try:
            async with coro:
                await asyncio.sleep(0.2)
        except LiveError as e:
            return e.code
        return None

    async def main():
        async with SessionAdmin(a.url, a.admin_key) as admin:
            s = await admin.create(face=FACE, fps=FPS)
        codes = {
            "viewer, wrong token": await refused(watch(c.url, s.id, "wrong")),
            "producer, viewer token": await refused(produce(b.url, s.id, s.viewer_token)),
            "producer, no session": await refused(produce(b.url, "0" * 16, s.producer_token)),
            "viewer, no session": await refused(watch(c.url, "0" * 16, s.viewer_token)),
        }
        async with produce(b.url, s.id, s.producer_token):
            codes["second producer"] = await refused(produce(c.url, s.id, s.producer_token))
        async with SessionAdmin(a.url, a.admin_key) as admin:  # a scoped token, minted on the owner
            gaze = (await admin.token(s.id, ["gaze"])).token
        as_expression = ProducerHello(input="fap", role="expression")
        codes["scoped, its role"] = await refused(
            produce(b.url, s.id, gaze, ProducerHello(input="fap", role="gaze"))
        )
        codes["scoped, another role"] = await refused(produce(b.url, s.id, gaze, as_expression))
        async with SessionAdmin(a.url, a.admin_key) as admin:
            await admin.close(s.id)
        return codes

    codes = run(main())
    assert codes == {
        "viewer, wrong token": CloseCode.UNAUTHORIZED,
        "producer, viewer token": CloseCode.FORBIDDEN,
        "producer, no session": CloseCode.NOT_FOUND,
        "viewer, no session": CloseCode.NOT_FOUND,
        "second producer": CloseCode.CONFLICT,
        "scoped, its role": None,  # the owner knows the session's scoped tokens and their roles
        "scoped, another role": CloseCode.FORBIDDEN,
    }


def test_a_forwarded_producers_bad_frames_get_errors_and_good_ones_still_come(cluster):
    """A producer on a node that does not own its session: each bad binary frame (taken by the
    owner as it arrives, or queued behind another) is answered with a non-fatal 4400 naming it,
    in order, and the good frames around them reach a viewer on the owner."""
    from facecast.protocol.errors import CloseCode

    _, (a, b, _) = cluster

    async def main():
        async with SessionAdmin(a.url, a.admin_key) as admin:
            s = await admin.create(face=FACE, fps=FPS)
        got: list = []
        started = asyncio.Event()

        async def collect():
            async with watch(a.url, s.id, s.viewer_token, encoding="f32") as w:
                started.set()
                async for f in w:
                    got.append(f.frame.header.seq)
                    if f.frame.header.seq == 5:
                        return

        viewer = asyncio.create_task(collect())
        await started.wait()
        async with produce(b.url, s.id, s.producer_token) as p:
            for i in range(6):
                good = frames.encode_faps(fap_vector(i), seq=i, t=i / FPS, wall=time.time())
                await p.send_raw(good)
                await asyncio.sleep(0.05)  # the owner waits again: the next frame is taken at once
                await p.send_raw(good[:-3])  # truncated: a 4400 naming seq i
                await asyncio.sleep(0.05)
            await until(lambda: len(p.errors) >= 6, "six errors")
            errors = list(p.errors)
            await asyncio.wait_for(viewer, 60)
        async with SessionAdmin(a.url, a.admin_key) as admin:
            await admin.close(s.id)
        return errors, got

    errors, got = run(main())
    assert [(e.code, e.fatal, e.seq) for e in errors] == [
        (CloseCode.BAD_REQUEST, False, i) for i in range(6)
    ]
    assert got and got[-1] == 5


def test_info_url_shows_the_cluster(cluster):
    _, (a, b, _) = cluster
    r = subprocess.run(
        [sys.executable, "-m", "facecast.server.cli", "info", "--url", b.url]
        + ["--admin-key", b.admin_key],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    assert "3 node(s), broker up" in r.stdout and a.url in r.stdout
    assert next(line for line in r.stdout.splitlines() if line.startswith(" *")).count(b.url) == 1
    r = subprocess.run(
        [sys.executable, "-m", "facecast.server.cli", "info", "--url", b.url],
        capture_output=True,
        text=True,
        timeout=60,
        env={k: v for k, v in os.environ.items() if k != "FACECAST_ADMIN_KEY"},
    )
    assert r.returncode == 2 and "401" in r.stderr and "--admin-key" in r.stderr


def test_workers_n_runs_n_nodes_on_one_port(cluster, tmp_path):
    redis, _ = cluster
    srv = cluster_node(tmp_path / "w", redis.url, "--job-workers", "0", workers=2).start()
    try:
        seen: set[str] = set()

        def both() -> bool:  # new connections land on either process (SO_REUSEPORT)
            v = view(srv)
            seen.add(v["self"])
            return len(seen) == 2 and sum(n["url"] == srv.url for n in v["nodes"]) == 2

        wait_for(both, what="two node processes on one port")
        # no FACECAST_RESULTS_DIR: the parent says so once, not each node process
        assert srv.tail(100_000).count("FACECAST_RESULTS_DIR is unset") == 1, srv.tail()
        # a node process that dies is started again: the machine keeps its two nodes
        pids = {n["pid"] for n in view(srv)["nodes"] if n["url"] == srv.url}
        os.kill(next(iter(pids)), signal.SIGKILL)

        def replaced() -> bool:
            try:  # a connection the killed process had queued is reset: ask again
                nodes = view(srv)["nodes"]
            except httpx.HTTPError:
                return False
            now = {n["pid"] for n in nodes if n["url"] == srv.url}
            return len(now) == 2 and now != pids

        wait_for(replaced, what="the killed node process started again")
    finally:
        srv.stop()
    try:
        wait_for(
            lambda: sum(n["url"] == srv.url for n in view(cluster[1][1])["nodes"]) == 0,
            what="the node processes leaving",
        )
    except AssertionError:
        print(srv.tail(), view(cluster[1][1]))
        raise


def test_killing_the_owner_moves_the_session_and_viewers_see_a_gap_not_a_wrong_face(cluster):
    """Last of the module: kills node A."""
    from facecast.server.api.store import FaceStore
    from facecast.server.pipeline import Animator

    _, (a, b, c) = cluster
    killed = {}

    async def main():
        async with SessionAdmin(a.url, a.admin_key) as admin:
            s = await admin.create(face=FACE, input="fap", fps=FPS, tolerance=0.1)
        got: list = []
        stop = asyncio.Event()

        async def viewer():
            async with watch(c.url, s.id, s.viewer_token, encoding="compact") as w:
                async for f in w:
                    got.append(f)
                    if stop.is_set():
                        return

        async def producer():  # reconnects by itself, to the nodes still alive
            i, reconnects = 0, 0
            targets = [b, c]
            while not stop.is_set():
                try:
                    async with produce(targets[reconnects % 2].url, s.id, s.producer_token) as p:
                        while not stop.is_set():
                            await p.send_faps(fap_vector(i), i / FPS)
                            i += 1
                            await asyncio.sleep(1 / FPS)
                except (LiveError, OSError):
                    reconnects += 1
                    await asyncio.sleep(0.1)
            return reconnects

        v = asyncio.create_task(viewer())
        pr = asyncio.create_task(producer())
        await until(lambda: len(got) >= 30, "no frames before the kill")
        await asyncio.get_running_loop().run_in_executor(None, a.kill)
        killed["at"] = time.time()
        before = len(got)
        await until(
            lambda: sum(f.received > killed["at"] for f in got[before:]) >= 30,
            "the session did not resume on another node",
        )
        stop.set()
        reconnects = await asyncio.wait_for(pr, 30)
        v.cancel()  # the viewer waits for frames that no longer come
        await asyncio.gather(v, return_exceptions=True)
        return s, got, reconnects

    s, got, reconnects = run(main())
    after = [f for f in got if f.received > killed["at"]]
    assert len(after) >= 30, "the session did not resume on another node"
    assert reconnects >= 1
    last_before = max(f.received for f in got if f.received <= killed["at"])
    gap = min(f.received for f in after) - last_before
    print(f"failover gap at the viewer: {gap:.2f} s")
    animator = Animator(FaceStore().face(FACE), backend="numpy")
    tol = 0.1 / animator.face.mm_per_unit
    for f in got:  # every frame shown is the face of its input, before and after the move
        i = round(f.frame.header.t * FPS)
        exp = expected_vertices(animator, i / FPS, i)
        err = np.abs(f.positions() - exp).max()
        assert err <= tol * 1.01 + 1e-6, (f.frame.header.seq, err, tol)
    owners = wait_for(lambda: [n for n in view(b)["nodes"] if s.id in n["sessions"]])
    assert owners[0]["url"] in (b.url, c.url)


def test_redis_restarted_under_load_nodes_recover(tmp_path):
    redis = RedisServer()
    a, b = node(redis.url, tmp_path, "a"), node(redis.url, tmp_path, "b")
    with running(redis, [a, b], ready=True):

        async def main():
            async with SessionAdmin(a.url, a.admin_key) as admin:
                s = await admin.create(face=FACE, input="fap", fps=FPS)
                t = await admin.create(face=FACE, input="fap", fps=FPS)  # produced through B
            local: list = []
            remote: list = []
            forwarded: list = []
            stop = asyncio.Event()

            async def viewer(srv, out, session=s):
                async with watch(srv.url, session.id, session.viewer_token) as w:
                    async for f in w:
                        out.append(f)
                        if stop.is_set():
                            return

            async def producer():
                i = 0
                async with produce(a.url, s.id, s.producer_token) as p:
                    while not stop.is_set():
                        await p.send_faps(fap_vector(i), i / FPS)
                        i += 1
                        await asyncio.sleep(1 / FPS)

            async def forwarded_producer():  # reconnects by itself, as clients do
                i = 0
                while not stop.is_set():
                    try:
                        async with produce(b.url, t.id, t.producer_token) as p:
                            while not stop.is_set():
                                await p.send_faps(fap_vector(i), i / FPS)
                                i += 1
                                await asyncio.sleep(1 / FPS)
                    except (LiveError, OSError):
                        await asyncio.sleep(0.2)

            tasks = [
                asyncio.create_task(viewer(a, local)),
                asyncio.create_task(viewer(b, remote)),
                asyncio.create_task(producer()),
                asyncio.create_task(viewer(a, forwarded, t)),
                asyncio.create_task(forwarded_producer()),
            ]

            await until(lambda: len(remote) >= 20, "no frames on the other node")
            loop = asyncio.get_running_loop()
            await loop.run_in_executor(None, redis.kill)
            await until(lambda: httpx.get(a.url + "/readyz").status_code == 503, "readyz stays 200")
            async with httpx.AsyncClient() as h:
                r = await h.post(a.url + "/v1/sessions", headers=a.admin_headers, json={})
            n_local = len(local)
            await until(lambda: len(local) >= n_local + 20, "local viewers stopped")
            await loop.run_in_executor(None, redis.start)
            await until(
                lambda: all(httpx.get(x.url + "/readyz").status_code == 200 for x in (a, b)),
                "nodes did not reconnect",
            )
            n_remote, n_forwarded = len(remote), len(forwarded)
            await until(lambda: len(remote) >= n_remote + 20, "remote viewers did not resume")
            await until(
                lambda: len(forwarded) >= n_forwarded + 20,
                "the producer on the other node was not taken again (its old slot held?)",
            )
            stop.set()
            await asyncio.wait_for(asyncio.gather(tasks[2], tasks[4]), 30)
            for task in (tasks[0], tasks[1], tasks[3]):
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            async with SessionAdmin(b.url, b.admin_key) as admin:
                s2 = await admin.create(face=FACE, input="fap", fps=FPS)
            return r, s2

        refused, s2 = run(main())
        assert refused.status_code == 503 and "Redis" in refused.json()["error"]
        assert s2.id
        v = view(a)
        assert len(v["nodes"]) == 2 and sum(len(n["sessions"]) for n in v["nodes"]) == 3


def test_scoped_tokens_and_rest_layers_survive_the_owners_death(tmp_path):
    """A scoped producer token minted and a REST layer set on the owner work on the node that
    takes the session over after the owner is killed (they were kept in Redis)."""
    import redis as redis_sync

    broker = RedisServer()
    a, b = node(broker.url, tmp_path, "a"), node(broker.url, tmp_path, "b")
    with running(broker, [a, b], ready=True):

        async def before():
            async with SessionAdmin(a.url, a.admin_key) as admin:
                s = await admin.create(face=FACE, input="fap", fps=FPS)
                scoped = await admin.token(s.id, ["expression"])
                await admin.set_layer(s.id, "smile", {"kind": "expression", "expression": "joy"})
            return s, scoped

        s, scoped = run(before())
        r = redis_sync.Redis.from_url(broker.url)
        try:  # the owner writes them at its heartbeat
            wait_for(lambda: b"smile" in (r.get(f"facecast:extras:{s.id}") or b""), what="extras")
        finally:
            r.close()
        a.kill()
        wait_for(lambda: s.id in next(n for n in view(b)["nodes"] if n["url"] == b.url)["sessions"])

        async def after():
            async with SessionAdmin(b.url, b.admin_key) as admin:
                layers = await admin.layers(s.id)
            hello = ProducerHello(role="expression")
            async with produce(b.url, s.id, scoped.token, hello) as p:
                await p.send_faps(fap_vector(0), 0.0)
            with pytest.raises(LiveError):  # a token the session never had is still refused
                async with produce(b.url, s.id, "not-" + scoped.token, hello):
                    pass
            return layers

        layers = run(after())
        smile = [x for x in layers.layers if x.name == "smile"]
        assert smile and smile[0].source == "rest" and smile[0].spec["expression"] == "joy"


# -- without servers: the mirror's rules and the envelopes ------------------------------------------


class _Outbox:
    """A viewer outbox that records what it is offered."""

    def __init__(self, encoding: str) -> None:
        self.encoding, self.sent, self.got = encoding, 0, []

    def offer(self, frame) -> int:
        self.got.append(bytes(frame[0]))
        return 0

    def say(self, text: str) -> None:
        pass

    def end(self, code: int, error_json: str) -> None:
        self.ended = code


def test_a_mirror_never_lets_a_delta_through_against_another_owners_key():
    """After a change of owner (a newer epoch), compact deltas wait for the new owner's key frame;
    frames of an older owner are dropped; every frame the viewer gets decodes to its face."""
    from facecast.protocol.compact import CompactDecoder, CompactEncoder
    from facecast.server.api.store import FaceStore
    from facecast.server.cluster import envelope
    from facecast.server.cluster.mirror import MirrorSession
    from facecast.server.cluster.records import SessionRecord
    from facecast.server.live.wire import ws_binary_frame

    face = FaceStore().face(FACE)
    rec = SessionRecord(
        id="s",
        face=FACE,
        input="fap",
        fps=FPS,
        engine="fp",
        max_viewers=4,
        producer_token="p",
        viewer_token="v",
        created=0.0,
        tolerance=0.1,
    )
    wishes = []
    m = MirrorSession(rec.spec(), face, lambda mirror, key: wishes.append(key))
    out = _Outbox("compact")
    m.viewers.add(out)
    rng = np.random.default_rng(1)
    tol = 0.1 / face.mm_per_unit

    def owner():
        """An owner's compact stream: ``frame(seq, epoch, key)`` -> the published message."""
        enc = CompactEncoder(face.vertices, face.rigid_group, tolerance=tol, key_interval=1000)
        shapes = {}

        def frame(seq: int, epoch: int, key: bool = False) -> bytes:
            v = face.vertices + rng.normal(0, 0.002, face.vertices.shape).astype(np.float32)
            shapes[seq] = v
            data = enc.encode(v, seq=seq, t=seq / FPS, key=key)
            return envelope.frame(epoch, seq, "compact", ws_binary_frame(data))

        return frame, shapes

    old, old_shapes = owner()
    new, new_shapes = owner()  # numbered from 0 too: only the epoch tells the owners apart
    for i in range(5):
        m.receive(old(i, 1))
    n_old = len(out.got)
    m.receive(envelope.with_json(envelope.OWNER, {"epoch": 2, "node": "n2"}))
    new(0, 2)  # the new owner's first (key) frame, lost on the way
    for i in range(1, 4):  # its deltas: held back until a key frame comes
        m.receive(new(i, 2))
    m.receive(old(5, 1))  # the old owner, cut off but still sending: dropped
    assert len(out.got) == n_old and wishes  # and the change of owner asked for a key frame
    m.receive(new(4, 2, key=True))
    m.receive(new(5, 2))
    assert len(out.got) == n_old + 2
    shapes = [old_shapes] * n_old + [new_shapes] * 2
    # the owner's producer shows in this node's viewers' hellos; taken over, the slot is free
    status = b'S{"type":"status","producer_connected":true,"viewers":1}'
    m.receive(status)
    assert m.producer is not None and not m.claim(object())  # type: ignore[arg-type]
    m.promote()
    assert m.producer is None and m.owned
    dec = CompactDecoder(face.vertices, face.rigid_group)
    for payload, source in zip(out.got, shapes):
        got = dec.decode(payload)
        assert got is not None  # every frame offered is decodable, against its own owner's key
        h, verts = got
        np.testing.assert_allclose(verts, source[h.seq], atol=tol * 1.01 + 1e-6)


@pytest.mark.parametrize(
    "data", [b"", b"F", b"F\x00\x00", b"F" + bytes(9) + b"\x82", b"P12", b"Rxx"]
)
def test_envelopes_refuse_garbage_with_valueerror(data):
    from facecast.server.cluster import envelope

    parse = envelope.parse_conn if data[:1] in (b"P", b"R") else envelope.parse_frame
    with pytest.raises(ValueError):
        parse(data)
