"""Set-ups the cluster and jobs tests share: cluster nodes, Redis with its nodes started and stopped
together, and the job calls (submit, status, wait for an end state)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
from conftest import RunningServer

from facecast.server.harness import RedisServer

FACE = "default:2k"
#: Generous deadline for anything the tests wait for (seconds): the machine may be busy.
DEADLINE = 300.0
JOB_ENDS = ("done", "failed", "cancelled")


def cluster_node(
    root: Path,
    redis_url: str | None,
    *extra: str,
    workers: int = 1,
    env: dict | None = None,
) -> RunningServer:
    """A cluster node, not started: ``facecast serve`` with ``FACE``, the NumPy backend (frames
    comparable with a batch render), ``--workers`` node processes (one: its job workers are its own
    children, and a kill -9 of it is a node's death) and ``--redis redis_url`` (None: ``env``
    names the Redis); ``extra`` CLI options."""
    redis = ("--redis", redis_url) if redis_url else ()
    return RunningServer(
        root,
        *("--face", FACE, "--backend", "numpy", "--workers", str(workers), *redis, *extra),
        env=env,
    )


@contextmanager
def running(
    redis: RedisServer, nodes: list[RunningServer], *, ready: bool = False
) -> Iterator[None]:
    """Start ``redis`` then ``nodes`` (``ready``: each once its health says ready); stop the
    nodes, then Redis, at the end, whatever happened."""
    try:
        redis.start()
        for n in nodes:
            n.start(ready=ready)
        yield
    finally:
        for n in nodes:
            n.stop()
        redis.stop()


def submit(srv: RunningServer, name: str, content: bytes, **options: str) -> httpx.Response:
    """``POST /v1/jobs`` of ``content`` named ``name``, for ``FACE`` and ``options``."""
    return httpx.post(
        srv.url + "/v1/jobs",
        files={"file": (name, content)},
        data={"face": FACE, **options},
        headers=srv.admin_headers,
        timeout=60,
    )


def status(srv: RunningServer, job_id: str) -> dict:
    r = httpx.get(f"{srv.url}/v1/jobs/{job_id}", headers=srv.admin_headers, timeout=30)
    assert r.status_code == 200, r.text
    return r.json()


def wait(
    srv: RunningServer, job_id: str, until: tuple[str, ...] = JOB_ENDS, poll: float = 0.02
) -> dict:
    """The job's status once it is in ``until``, polled every ``poll`` s for ``DEADLINE`` s."""
    deadline = time.monotonic() + DEADLINE
    while time.monotonic() < deadline:
        job = status(srv, job_id)
        if job["status"] in until:
            return job
        time.sleep(poll)
    raise AssertionError(f"job {job_id} never reached {until}: {job}")


def wait_for(check, timeout: float = DEADLINE, what: str = "the cluster", poll: float = 0.1):
    """``check()``'s first true answer, polled every ``poll`` s for ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        got = check()
        if got:
            return got
        time.sleep(poll)
    raise AssertionError(f"{what} did not settle within {timeout:g} s")


def add_job(
    store,
    content: bytes = b"x",
    *,
    name: str = "a.fap",
    kind: str = "fap",
    result: str = "result.glb",
    options: dict | None = None,
    job_id: str | None = None,
) -> str:
    """A queued job in ``store`` (a ``JobStore`` or a ``RedisJobStore``), its input ``content`` in
    its folder as ``input`` + the suffix of ``name``; its id (``job_id``, or a new one)."""
    from facecast.server.jobs.store import new_job_id

    job_id = job_id or new_job_id()
    folder = store.folder(job_id)
    folder.mkdir(parents=True, exist_ok=True)
    input_file = "input" + Path(name).suffix
    (folder / input_file).write_bytes(content)
    store.add(
        job_id,
        input_name=name,
        input_kind=kind,
        input_file=input_file,
        input_bytes=1,
        result_file=result,
        options=options or {},
    )
    return job_id
