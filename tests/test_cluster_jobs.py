"""Batch jobs across nodes: real ``redis-server``, real ``facecast serve`` processes sharing
FACECAST_REDIS_URL and a FACECAST_RESULTS_DIR. A job submitted on one node runs and is served on
another; a worker or a whole node killed mid-job leaves the job to be done again, once, with the
result of a single-node render; Redis restarted; malformed queue entries never stick."""

from __future__ import annotations

import dataclasses
import hashlib
import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from cluster_support import (
    DEADLINE,
    FACE,
    add_job,
    cluster_node,
    running,
    status,
    submit,
    wait,
    wait_for,
)
from conftest import RunningServer

from facecast.server.harness import RedisServer, spawned_children

#: Seconds an unrenewed job waits before another node takes it (small, to keep tests short).
CLAIM_SECONDS = "3"


def node(root: Path, name: str, redis: RedisServer, shared: Path, workers: int) -> RunningServer:
    """A node (not started) that finds Redis and the shared results folder in its environment."""
    env = {
        "FACECAST_REDIS_URL": redis.url,
        "FACECAST_RESULTS_DIR": str(shared),
        "FACECAST_JOB_CLAIM_SECONDS": CLAIM_SECONDS,
        "FACECAST_JOB_WORKERS": str(workers),
    }
    return cluster_node(root / name, None, env=env)


def result(srv: RunningServer, job: dict) -> bytes:
    r = httpx.get(srv.url + job["result_url"], headers=srv.admin_headers, timeout=60)
    assert r.status_code == 200, r.text
    return r.content


def long_fap(data_dir: Path, repeat: int) -> bytes:
    """joy.fap with its frames ``repeat`` times over: a job that takes a while to render."""
    from facecast.protocol.fap_file import read_fap, write_fap

    fap = read_fap((data_dir / "xface" / "faps" / "joy.fap").read_text())
    return write_fap(dataclasses.replace(fap, frames=list(fap.frames) * repeat)).encode()


def single_node_render(tmp_path: Path, content: bytes) -> bytes:
    """The same input rendered in this process, as one server's worker would (NumPy backend)."""
    from facecast.server.render import render_file

    folder = tmp_path / "single"  # named as in a job's folder: the names go into the glTF
    folder.mkdir(exist_ok=True)
    src, dst = folder / "input.fap", folder / "result.glb"
    src.write_bytes(content)
    render_file(src, dst, face=FACE, backend="numpy")
    return dst.read_bytes()


def assert_same_render(got: bytes, expected: bytes, tmp_path: Path) -> None:
    """``got`` is the single-node render ``expected``: the same bytes, or (a render's last float bits
    may depend on the BLAS threads of the process that made it) the same animation within the
    files' recorded tolerance. Compares digests first: a byte diff of two .glb files is no message."""
    if got == expected:
        return
    from test_gltf_verify import read_back

    a, b = tmp_path / "got.glb", tmp_path / "expected.glb"
    a.write_bytes(got)
    b.write_bytes(expected)
    ga, gb = read_back(a), read_back(b)
    digests = f"sha256 {hashlib.sha256(got).hexdigest()[:12]} != {hashlib.sha256(expected).hexdigest()[:12]}"
    what = ("frames", "fps", "source", "face", "tolerance_mm")  # not the basis nor measured errors
    same = all(ga["record"][k] == gb["record"][k] for k in what)
    assert same and np.array_equal(ga["times"], gb["times"]), f"{digests}: {ga['record']}"
    worst = 0.0
    for s in range(0, len(ga["times"]), 16):
        shown = [
            g["rest"] + np.einsum("tm,mvc->tvc", g["weights"][s : s + 16], g["targets"])
            for g in (ga, gb)
        ]
        worst = max(worst, float(np.linalg.norm(shown[0] - shown[1], axis=2).max()))
    mm = worst * (ga["scale"] or [1.0])[0] * 1000  # the node scales mesh units to metres
    # each file is within its tolerance of the frames it was made from: two, of each other's
    assert mm <= 2 * ga["tolerance_mm"], f"{digests}: frames differ by up to {mm:g} mm"


def workers_of(srv: RunningServer) -> list[int]:
    """Pids of the job worker processes of a server (its ``spawn``-ed children)."""
    assert srv.proc is not None
    return spawned_children(srv.proc.pid)


def running_worker(front: RunningServer, srv: RunningServer, job_id: str) -> int:
    """The pid of ``srv``'s worker once it runs ``job_id`` (as ``front`` reports it)."""
    deadline = time.monotonic() + DEADLINE
    while time.monotonic() < deadline:
        job = status(front, job_id)
        pids = workers_of(srv)
        if job["status"] == "running" and len(pids) == 1 and status(front, job_id) == job:
            return pids[0]
        if job["status"] == "done":
            pytest.skip("the job finished before its worker could be seen (machine too fast)")
        assert job["status"] in ("queued", "running"), job
        time.sleep(0.01)
    raise AssertionError(f"job {job_id} never ran on {srv.url}")


def eventually(check, what: str) -> None:
    """Wait until ``check()`` is true (a node acknowledges an entry just after the verdict it
    records, and counts are refreshed at its next tick), within the generous deadline."""
    wait_for(check, what=what, poll=0.05)


def queue_is_empty(redis: RedisServer) -> bool:
    """Nothing pending in the group and nothing left in the stream."""
    import redis as redis_client

    from facecast.server.jobs.redis_queue import GROUP, STREAM

    r = redis_client.Redis.from_url(redis.url)
    try:
        return r.xpending(STREAM, GROUP)["pending"] == 0 and r.xlen(STREAM) == 0
    finally:
        r.close()


@pytest.fixture(scope="module")
def cluster(tmp_path_factory) -> Iterator[tuple[RedisServer, RunningServer, RunningServer, Path]]:
    """Redis, node A (no workers: it only takes and answers) and node B (one worker), one shared
    results folder."""
    if not RedisServer.available():
        pytest.skip("redis-server is not installed (bash .ci/setup)")
    root = tmp_path_factory.mktemp("cluster")
    shared = root / "results"
    redis = RedisServer()
    a = node(root, "a", redis, shared, workers=0)
    b = node(root, "b", redis, shared, workers=1)
    with running(redis, [a, b]):
        yield redis, a, b, shared


def test_a_job_submitted_on_one_node_runs_and_is_served_on_another(cluster, data_dir, tmp_path):
    redis, a, b, shared = cluster
    content = (data_dir / "xface" / "faps" / "joy.fap").read_bytes()
    r = submit(a, "joy.fap", content)
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    assert (shared / job_id / "input.fap").read_bytes() == content  # where every node finds it
    done = wait(b, job_id)  # A has no worker: B's ran it
    assert done["status"] == "done" and done["attempts"] == 1 and done["progress"] == 1.0, done
    assert status(a, job_id) == done  # the same state from either node
    body = result(a, done)
    assert body == result(b, done)  # one file, served by either node
    assert_same_render(body, single_node_render(tmp_path, content), tmp_path)
    assert len(body) == done["result_bytes"]
    assert job_id in [
        j["id"] for j in httpx.get(a.url + "/v1/jobs", headers=a.admin_headers).json()["jobs"]
    ]
    assert not [p for p in (shared / job_id).iterdir() if p.name.startswith(".")]
    eventually(lambda: queue_is_empty(redis), "the queue kept an entry")
    # a damaged input fails with the decoder's message on whichever node asks, and runs once
    bad = submit(a, "bad.fap", b"2.1 x 25 3\nnot numbers at all\n")
    assert bad.status_code == 202, bad.text
    failed = wait(a, bad.json()["id"])
    assert failed["status"] == "failed" and failed["attempts"] == 1 and "bad.fap" in failed["error"]
    assert str(shared) not in failed["error"]
    # cancelling from the node that does not run it
    r = submit(b, "joy.fap", content)
    cancelled = httpx.delete(f"{a.url}/v1/jobs/{r.json()['id']}", headers=a.admin_headers)
    if cancelled.status_code == 409:  # B's worker was quicker
        assert wait(b, r.json()["id"])["status"] == "done"
    else:
        assert cancelled.status_code == 200 and cancelled.json()["status"] == "cancelled"
        assert wait(b, r.json()["id"])["status"] == "cancelled"
        eventually(lambda: queue_is_empty(redis), "the queue kept an entry")


def test_malformed_queue_entries_never_leave_the_queue_stuck(cluster, data_dir):
    import redis as redis_client

    from facecast.server.jobs.redis_queue import PREFIX, STREAM

    redis, a, b, _shared = cluster
    r = redis_client.Redis.from_url(redis.url)
    broken = "ab" * 16  # a job hash facecast did not write: no fields it needs, bad attempts
    r.hset(f"{PREFIX}:job:{broken}", mapping={"status": "queued", "attempts": "many"})
    half = "cd" * 16  # one with a status but nothing else
    r.hset(f"{PREFIX}:job:{half}", mapping={"status": "queued"})
    for fields in (
        {"junk": "x"},
        {"id": "../../etc/passwd"},
        {"id": "0" * 32},  # no such job
        {"id": broken},
        {"id": half},
        {"id": "ef" * 16, "extra": "y" * 1000},
    ):
        r.xadd(STREAM, fields)
    content = (data_dir / "xface" / "faps" / "joy.fap").read_bytes()
    job = submit(a, "joy.fap", content).json()
    assert wait(b, job["id"])["status"] == "done"
    eventually(lambda: queue_is_empty(redis), "malformed entries stuck in the queue")
    for job_id in (broken, half):  # unknown to the API, never a 500
        got = httpx.get(f"{a.url}/v1/jobs/{job_id}", headers=a.admin_headers)
        assert got.status_code in (200, 404), got.text
    listed = httpx.get(a.url + "/v1/jobs", headers=a.admin_headers)
    assert listed.status_code == 200
    r.close()


def test_a_killed_worker_or_node_leaves_the_job_to_be_done_again_once(
    redis_server, data_dir, tmp_path
):
    """kill -9 of a worker mid-job: its node runs the job again. kill -9 of the whole node
    mid-job: another node takes the job once its entry is idle. Each result is byte-identical to a
    single-node render, the job is done once, and nothing stays pending."""
    shared = tmp_path / "results"
    front = node(tmp_path, "front", redis_server, shared, workers=0).start()
    a = node(tmp_path, "a", redis_server, shared, workers=1).start()
    b = node(tmp_path, "b", redis_server, shared, workers=1)
    content = long_fap(data_dir, 48)
    expected = single_node_render(tmp_path, content)
    try:
        # 1. the worker dies mid-job; its node (the only one with a worker) runs it again
        job_id = submit(front, "long.fap", content).json()["id"]
        os.kill(running_worker(front, a, job_id), signal.SIGKILL)
        done = wait(front, job_id)
        assert done["status"] == "done", done
        if done["attempts"] == 1:
            pytest.skip("the job finished before its worker could be killed (machine too fast)")
        assert done["attempts"] == 2, done
        assert_same_render(result(front, done), expected, tmp_path)
        # 2. the whole node dies mid-job; a node started afterwards takes the job over
        job_id = submit(front, "long.fap", content).json()["id"]
        running_worker(front, a, job_id)
        a.kill()
        if status(front, job_id)["status"] == "done":
            pytest.skip("the job finished before its node could be killed (machine too fast)")
        assert status(front, job_id)["status"] == "running"
        b.start()
        done = wait(front, job_id)
        assert done["status"] == "done" and done["attempts"] == 2, done
        assert result(b, done) == result(front, done)  # one file, served by either node
        assert_same_render(result(b, done), expected, tmp_path)
        assert not [p for p in (shared / job_id).iterdir() if p.name.startswith(".")]
        eventually(lambda: queue_is_empty(redis_server), "the queue kept an entry")

        def counted() -> bool:
            jobs = httpx.get(front.url + "/healthz", timeout=30).json()["jobs"]
            return bool(jobs.get("done") == 2 and not jobs.get("running"))

        eventually(counted, "/healthz never counted the two jobs done")
    finally:
        for s in (front, a, b):
            s.stop()


def test_redis_restarted_while_idle(redis_server, data_dir, tmp_path):
    """Redis away: submitting and polling answer 503 with a clear message, health stays up. Redis
    back empty: nodes make the group again, new jobs run, and finished jobs still answer from the
    shared folder's records."""
    shared = tmp_path / "results"
    a = node(tmp_path, "a", redis_server, shared, workers=0).start()
    b = node(tmp_path, "b", redis_server, shared, workers=1).start()
    content = (data_dir / "xface" / "faps" / "joy.fap").read_bytes()
    try:
        first = wait(a, submit(a, "joy.fap", content).json()["id"])
        assert first["status"] == "done"
        redis_server.kill()
        r = submit(a, "joy.fap", content)
        assert r.status_code == 503, r.text
        assert "Redis" in r.json()["error"] and "try again" in r.json()["error"]
        assert not [p for p in shared.iterdir() if p.name != first["id"]]  # nothing half-made
        got = httpx.get(f"{b.url}/v1/jobs/{first['id']}", headers=b.admin_headers, timeout=30)
        assert got.status_code == 503
        assert httpx.get(a.url + "/healthz", timeout=30).status_code == 200
        redis_server.start()
        deadline = time.monotonic() + DEADLINE
        while (r := submit(a, "joy.fap", content)).status_code == 503:
            assert time.monotonic() < deadline, r.text
            time.sleep(0.2)
        assert r.status_code == 202, r.text
        second = wait(b, r.json()["id"])
        assert second["status"] == "done" and result(b, second) == result(b, first)
        assert status(b, first["id"])["status"] == "done"  # from its folder's record
    finally:
        a.stop()
        b.stop()


def test_the_redis_store_changes_state_by_compare_and_set(redis_server, tmp_path):
    """Claims count attempts; progress and verdicts of a superseded, cancelled or finished attempt
    record nothing; 'done' is set once; every record is JSON in Redis and in the job's folder."""
    import json

    import redis as redis_client

    from facecast.server.jobs.redis_queue import RedisJobStore

    store = RedisJobStore(redis_server.url, tmp_path)
    assert store.ensure_group() and not store.ensure_group()

    def add() -> str:
        return add_job(store, options={"format": "glb"})

    job = add()
    assert store.get(job).status == "queued" and store.refresh_counts() == {"queued": 1}
    first = store.claim(job)
    second = store.claim(job)  # the first attempt's node died: taken again
    assert (first, second) == (1, 2)
    assert not store.progress(job, first, 0.5) and store.progress(job, second, 0.5)
    assert not store.finish(job, first, "failed", "stale")  # a superseded attempt's failure
    assert store.finish(job, first, "done")  # its result is the same bytes: done counts
    assert not store.finish(job, second, "done") and not store.progress(job, second, 0.9)
    done = store.get(job)
    assert done.status == "done" and done.progress == 1.0 and done.attempts == 2
    assert store.claim(job) is None and not store.cancel(job) and not store.fail(job, "x")
    on_disk = json.loads((store.folder(job) / "job.json").read_text())
    assert on_disk["status"] == "done" and json.loads(on_disk["options"]) == {"format": "glb"}
    other = add()
    attempt = store.claim(other)
    assert store.cancel(other) and not store.progress(other, attempt, 0.1)
    assert not store.finish(other, attempt, "done") and store.get(other).status == "cancelled"
    assert store.refresh_counts() == {"done": 1, "cancelled": 1}
    assert [j.id for j in store.list()] == [other, job] and store.list("bogus") == []
    raw = redis_client.Redis.from_url(redis_server.url)
    assert all(v.decode().isprintable() for v in raw.hgetall(store.key(job)).values())
    raw.close()
    # Redis loses everything: the record answers, and a queued job is queued again
    queued = add()
    redis_server.kill()
    redis_server.start()
    assert store.get(job).status == "done" and store.get(queued).status == "queued"
    assert store.ensure_group() and store.recover() == [queued]
    assert store.claim(queued) == 1
    store.close()


def test_the_results_dir_holds_job_folders_without_redis_too(data_dir, tmp_path):
    """One process, SQLite jobs: FACECAST_RESULTS_DIR still says where inputs and results go."""
    shared = tmp_path / "results"
    env = {"FACECAST_RESULTS_DIR": str(shared), "FACECAST_JOB_WORKERS": "1"}
    srv = RunningServer(tmp_path / "data", "--face", FACE, "--backend", "numpy", env=env).start()
    try:
        content = (data_dir / "xface" / "faps" / "joy.fap").read_bytes()
        done = wait(srv, submit(srv, "joy.fap", content).json()["id"])
        assert done["status"] == "done"
        assert (shared / done["id"] / "result.glb").read_bytes() == result(srv, done)
        assert not (tmp_path / "data" / "jobs").exists()
        assert (tmp_path / "data" / "jobs.sqlite").is_file()
    finally:
        srv.stop()


def test_a_node_that_does_not_share_the_results_dir_fails_the_job_clearly(redis_server, tmp_path):
    """Nodes misconfigured with folders of their own: the job fails with what to fix, not with a
    decoder's 'file not found' about a path of the server."""
    from collections import OrderedDict

    from facecast.server.jobs import worker
    from facecast.server.jobs.redis_queue import RedisJobStore

    here = RedisJobStore(redis_server.url, tmp_path / "a")
    there = RedisJobStore(redis_server.url, tmp_path / "b")
    job_id = add_job(here, options={"format": "glb", "face_spec": FACE})
    attempt = there.claim(job_id)
    worker.run_job(there, job_id, attempt, "numpy", None, None, OrderedDict())  # type: ignore[arg-type]
    failed = here.get(job_id)
    assert failed.status == "failed" and "FACECAST_RESULTS_DIR" in failed.error
    assert str(tmp_path) not in failed.error
    here.close()
    there.close()
