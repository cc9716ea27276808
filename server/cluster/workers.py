"""``facecast serve --redis URL --workers N``: N node processes on one machine, one port.

The parent checks Redis and settles the admin key (``bootstrap``), holds the data directory's
lock, and starts N children (``facecast serve --node-of <parent pid>``) with its settings in their
environment. Each child is a full node (its own event loop, sessions and node id) that binds the
same port with ``SO_REUSEPORT``: the kernel spreads incoming connections over them, WebSockets
included, and a child that dies leaves the others serving (its sessions fail over to them). The
parent forwards SIGTERM/SIGINT to the children and exits when they have all ended. Children end
with the parent (``PR_SET_PDEATHSIG``: killed as the parent is), so ``kill -9`` of the parent is
that of a whole machine: their sessions fail over to other nodes.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from typing import Any

log = logging.getLogger(__name__)

#: Seconds node processes have to stop after SIGTERM before they are killed.
STOP_SECONDS = 8.0
#: A node process that dies this many times in a row, each within QUICK_SECONDS of its start,
#: is not started again.
QUICK_DEATHS, QUICK_SECONDS = 3, 10.0

#: ``FACECAST_PIN_NODES=0`` leaves node processes unpinned (``placement``).
PIN_ENV = "FACECAST_PIN_NODES"

#: Settings a child gets from its parent (flags become ``FACECAST_*`` variables).
PASSED = (
    "host",
    "port",
    "data_dir",
    "face",
    "backend",
    "device",
    "job_workers",
    "redis_url",
    "admin_key",
    "allow_remote",
    "session_idle_seconds",
)


def child_env(config: Any, index: int) -> dict[str, str]:
    """The environment of node process ``index``: the parent's, with its settings. Batch job
    workers run in the first node only (they share the data directory's job store). With no
    results folder set, each child is given the default one by name: the parent warned about it
    once (``supervise``), instead of each node process."""
    from ..jobs.store import results_root

    env = dict(os.environ)
    if config.redis_url and config.results_dir is None:
        env["FACECAST_RESULTS_DIR"] = str(results_root(config.data_dir))
    for name in PASSED:
        value = getattr(config, name)
        if name == "job_workers" and index > 0:
            value = 0
        if value is not None:
            env[f"FACECAST_{name.upper()}"] = str(int(value) if isinstance(value, bool) else value)
    return env


def placement(index: int, workers: int) -> tuple[set[int] | None, dict[str, str]]:
    """Where node process ``index`` of ``workers`` runs: ``(cpus, env)``, the CPUs it is pinned to
    (None: not pinned) and the variables that size its OpenCL (PoCL) thread pool to them.

    With no more nodes than the CPUs this process may use, node i gets its own ``k = cpus // n``
    of them and a PoCL pool of ``k`` threads; each PoCL otherwise starts one thread per CPU and
    pins thread j to CPU j, so every node's kernel launches wait for every core, and two nodes'
    launches for each other. Measured (``docs/SCALING.md``): pinned, each node on one core with
    one PoCL thread, two nodes on this 2-core machine held 50 sessions at p95 9.7-11 ms where
    unpinned they missed (p95 80-100 ms), in the same runs. More nodes than CPUs, or
    ``FACECAST_PIN_NODES=0``: no pinning, PoCL as it starts by itself.
    """
    if os.environ.get(PIN_ENV, "1").strip() in ("0", "false", "no", "off"):
        return None, {}
    try:
        mine = sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        return None, {}
    k = len(mine) // workers if workers > 1 else 0
    if k < 1:
        return None, {}
    # PoCL's own pinning (thread j to CPU j, ``backends.select.pin_pocl_workers``) would move
    # the pool of node i off its CPUs: off, the node's affinity holds its threads
    env = {"POCL_AFFINITY": "0"}
    if "POCL_MAX_PTHREAD_COUNT" not in os.environ:
        env["POCL_MAX_PTHREAD_COUNT"] = str(k)
    return set(mine[index * k : (index + 1) * k]), env


def _die_with_parent() -> None:  # pragma: no cover - runs in the child before exec
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def before_exec(cpus: set[int] | None) -> Callable[[], None]:
    """What a node process does before exec: die with its parent, run on ``cpus`` (if any; the
    affinity is inherited by all its threads, PoCL's included, which start after exec)."""

    def prepare() -> None:  # pragma: no cover - runs in the child before exec
        _die_with_parent()
        if cpus:
            os.sched_setaffinity(0, cpus)

    return prepare


def supervise(config: Any, workers: int, log_level: str | None) -> int:
    """Run ``workers`` node processes until SIGTERM/SIGINT ends them; exit status.

    A node process that dies (a crash, kill -9, the OOM killer) is started again, so the machine
    keeps its ``workers`` nodes (its sessions have moved to other nodes meanwhile); one that dies
    ``QUICK_DEATHS`` times in a row within ``QUICK_SECONDS`` of its start is not (it cannot run:
    its log says why), and the parent ends when no node process is left.
    """
    cmd = [sys.executable, "-m", "facecast.server.cli", "serve", "--node-of", str(os.getpid())]
    if log_level:
        cmd += ["--log-level", log_level]

    def start(i: int) -> subprocess.Popen[bytes]:
        cpus, pocl = placement(i, workers)
        env = {**child_env(config, i), **pocl}
        return subprocess.Popen(cmd, env=env, preexec_fn=before_exec(cpus))  # noqa: PLW1509

    if config.redis_url and config.results_dir is None:
        from ..jobs import RESULTS_DIR_UNSET, results_root

        log.warning(RESULTS_DIR_UNSET, results_root(config.data_dir))  # once for all its nodes
    children = [start(i) for i in range(workers)]
    started = [time.monotonic()] * workers
    quick = [0] * workers
    stopping = False

    def stop(signum: int, frame: Any) -> None:
        nonlocal stopping
        stopping = True
        for c in children:
            if c.poll() is None:
                c.send_signal(signal.SIGTERM)

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    status = 0
    while not stopping:
        time.sleep(0.2)
        for i, c in enumerate(children):
            if stopping or c.poll() in (None, 0) or quick[i] >= QUICK_DEATHS:
                continue
            status = 1
            lived = time.monotonic() - started[i]
            quick[i] = quick[i] + 1 if lived < QUICK_SECONDS else 0
            if quick[i] >= QUICK_DEATHS:
                log.error(
                    "node process %d died %d times within %g s of its start; not starting it again",
                    c.pid,
                    QUICK_DEATHS,
                    QUICK_SECONDS,
                )
                continue
            log.warning("node process %d ended with %s; starting another", c.pid, c.returncode)
            children[i], started[i] = start(i), time.monotonic()
        if all(c.poll() is not None for c in children):
            break
    deadline = time.monotonic() + STOP_SECONDS
    for c in children:
        try:
            c.wait(max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            log.warning("node process %d did not stop in %g s; killing it", c.pid, STOP_SECONDS)
            c.send_signal(signal.SIGUSR1)  # its stacks to the log first (faulthandler)
            time.sleep(0.5)
            c.kill()
    return 0 if stopping else status


def reuse_port_socket(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``host:port`` that other processes may bind too (SO_REUSEPORT)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
    sock.bind((host, port))
    sock.listen(2048)
    sock.set_inheritable(True)
    return sock


def serve_node(app: Any, config: Any, log_level: str | None, ws_max_size: int) -> None:
    """Serve ``app`` as one node process of a ``--workers`` parent, on the shared port."""
    import faulthandler

    import uvicorn

    faulthandler.register(signal.SIGUSR1)  # stack traces of a stuck node process, on demand
    uconfig = uvicorn.Config(
        app,
        ws_per_message_deflate=False,
        log_level=log_level or "warning",
        lifespan="on",
        timeout_graceful_shutdown=5,
        ws_max_size=ws_max_size,
    )
    uvicorn.Server(uconfig).run(sockets=[reuse_port_socket(config.host, config.port)])
