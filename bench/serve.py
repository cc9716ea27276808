"""Live-session throughput and end-to-end latency on loopback: ``python bench/serve.py [options]``.

Run from a checkout with facecast installed (``.venv/bin/python bench/serve.py --help``); it was
``facecast bench serve`` before the load generator left the server package.

Starts a real ``facecast serve`` on a free loopback port (25k-vertex ``default`` face), then two
sweeps, each point bounded in time (``--warmup`` + ``--seconds``):

- **sessions**: N concurrent sessions, one producer (FAP frames at ``--fps``) and one viewer each;
- **viewers**: one session, one producer, M viewers.

``--cluster N`` then measures the sessions sweep again, same encoding, on a cluster on this
machine: a real ``redis-server`` and N ``facecast serve --redis`` nodes, session k created on (and
produced into) node k mod N and watched on node k + 1 mod N, so that every frame crosses Redis to
reach its viewer (the producer->viewer latency is the cross-node one). Both are reported side by
side with the largest session count each holds at the target (every viewer at 95 % of ``--fps``,
p95 within ``--latency-target``) and their ratio (issue 15's target: 1.5 on two cores).

Viewers use the real asyncio client (``facecast.client.api.watch``) with int16 frames (``--encoding``),
spread over ``--viewer-processes`` client processes (default one per CPU: in a single Python process
100 viewers, 6000 frames/s, saturate its core and the benchmark would measure itself).
Latency is end to end: viewer receive wall time minus the producer's send wall time carried in the
frame (same machine, same clock). Per point it reports the sustained frame rate per viewer (mean and
minimum), latency p50/p95/max, frames skipped (gaps in ``seq``), the server's mean deform+encode
time per frame, and CPU seconds per second of the server process and of the client processes:
that is where the time goes. Server CPU is also given per delivered frame and per *session-frame*
(a frame deformed and encoded once, whatever its viewers): robust to a shared machine's load,
where frame rates and latencies are not. The in-process part also measures the live worker's
whole job per frame (solve + deform + encode, CPU of all threads) in batches of 1 and 20, with
int16 quantisation on the OpenCL device and in NumPy. The baseline is the first point of each sweep (one session, one
viewer), measured in the same run; ``*_ratio`` columns compare against it. In-process costs of
one frame (rig solve, deformation, int16/float32 encoding, decoding) are measured first.

Writes ``bench/out/serve.json`` and prints markdown tables. Loopback only; nothing is downloaded.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import math
import multiprocessing
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from facecast.server.harness import LocalServer, RedisServer, process_cpu_seconds

log = logging.getLogger(__name__)

ADMIN_KEY = "bench-serve-key"
_VIEWER_OPTS: dict = {}  # --viewer-rcvbuf / --viewer-queue
_SERVER_ENV: dict[str, str] = {}  # every server's (single and cluster nodes alike): --coalesce-ms


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--face", default="default", help="face of the sessions (default: the 25k-vertex default)"
    )
    p.add_argument(
        "--backend", default="auto", choices=("auto", "numpy", "opencl"), help="server backend"
    )
    p.add_argument("--fps", type=float, default=60.0, help="producer frame rate")
    p.add_argument(
        "--encoding",
        default="i16",
        type=_encodings,
        help="viewers' encoding: i16, f32 or compact; several, comma-separated (i16,compact), "
        "are swept one after the other against the same server, in the same run",
    )
    p.add_argument(
        "--sessions", default="1,5,10,20,25", help="session counts to sweep (comma-separated)"
    )
    p.add_argument(
        "--viewers", default="1,25,50,100,120", help="viewer counts of one session to sweep"
    )
    p.add_argument(
        "--warmup", type=float, default=1.0, help="seconds before measuring at each point"
    )
    p.add_argument("--seconds", type=float, default=3.0, help="seconds measured at each point")
    p.add_argument("--latency-target", type=float, default=50.0, help="p95 target, ms")
    p.add_argument(
        "--url", help="use this running server instead of starting one (needs FACECAST_ADMIN_KEY)"
    )
    p.add_argument(
        "--server-pid",
        type=int,
        help="with --url: the server's process id, to measure its CPU time (Linux /proc)",
    )
    p.add_argument(
        "--viewer-kind",
        choices=("client", "light"),
        default="client",
        help="viewers: the real asyncio client (default; end to end) or a minimal reader that skips "
        "payloads (measures the server without the Python client's parsing cost)",
    )
    p.add_argument(
        "--generator",
        choices=("light", "client"),
        default="light",
        help="load generator: raw-socket producers and viewers in --generator-processes processes "
        "on uvloop (default: a few µs of CPU per frame, bench/serve_load.py), or the real asyncio "
        "client (producers in this process, viewers per --viewer-kind over --viewer-processes; "
        "about as much CPU per frame as the server)",
    )
    p.add_argument(
        "--generator-processes",
        type=int,
        default=1,
        help="light generator: processes the producers and viewers are spread over (default 1)",
    )
    p.add_argument(
        "--viewer-processes",
        type=int,
        default=os.cpu_count() or 1,
        help="spread the viewers over this many client processes (default: one per CPU); in one "
        "Python process, 100 real-client viewers (6000 frames/s) saturate its core",
    )
    p.add_argument(
        "--viewer-rcvbuf",
        type=int,
        default=None,
        help="viewer socket receive buffer, bytes (0 = OS default; default: the client's)",
    )
    p.add_argument(
        "--viewer-queue",
        type=int,
        default=None,
        help="messages a viewer's client library buffers (default: the client's)",
    )
    p.add_argument(
        "--compare-asgi",
        action="store_true",
        help="also run the viewers sweep with frames sent through ASGI (FACECAST_LIVE_DIRECT=0), "
        "the baseline of the direct-to-transport path",
    )
    p.add_argument(
        "--baseline-python",
        metavar="PYTHON",
        help="also measure a server run by this interpreter (e.g. the .venv/bin/python of a checkout of "
        "an earlier commit), point by point alternately with this checkout's, in the same run; "
        "reported side by side, with the ratio of server CPU per session-frame",
    )
    p.add_argument(
        "--layers",
        type=int,
        default=0,
        choices=range(len(LAYERS) + 1),
        help="REST layers per session mixed into every frame (1: idle, 2: and a smile, 3: and gaze "
        "at the camera; default 0)",
    )
    p.add_argument(
        "--cluster",
        type=int,
        default=0,
        metavar="N",
        help="also run the sessions sweep on Redis and N cluster nodes (viewers on another node "
        "than their session's producer), reported side by side with the single process",
    )
    p.add_argument(
        "--cluster-viewers",
        choices=("other", "owner", "spread"),
        default="other",
        help="cluster: each session's viewer on another node than its owner (default: every frame "
        "crosses Redis), on the owner, or half of each (what a round-robin balancer gives 2 nodes)",
    )
    p.add_argument(
        "--cluster-pin",
        choices=("auto", "off"),
        default="auto",
        help="cluster: place the nodes as `facecast serve --workers N` does (auto: each on its "
        "own cores, its PoCL pool sized to them, when N <= CPUs) or leave them unpinned (off)",
    )
    p.add_argument(
        "--cluster-sessions",
        help="session counts of the cluster sweep (default: --sessions)",
    )
    p.add_argument(
        "--coalesce-ms",
        type=float,
        default=None,
        help="FACECAST_LIVE_COALESCE_MS of every server measured, the single process and the "
        "cluster's nodes alike: how long a deformation batch may wait for more frames (a node "
        "holding 1/N of the sessions makes smaller batches by itself)",
    )
    p.add_argument(
        "--cluster-coalesce-ms",
        type=float,
        default=None,
        help="the cluster nodes' FACECAST_LIVE_COALESCE_MS (default: --coalesce-ms): a node "
        "holding 1/N of the sessions fills a batch N times slower",
    )
    p.add_argument(
        "--cluster-coalesce-frames",
        type=int,
        default=None,
        help="the cluster nodes' FACECAST_LIVE_COALESCE_FRAMES (default: the server's, 8)",
    )
    p.add_argument("--out", type=Path, default=Path("bench/out/serve.json"))


#: The layers ``--layers N`` sets on each session (the first N), over its producer's FAP frames.
LAYERS = (
    ("idle", {"kind": "idle", "seed": 1}),
    ("smile", {"kind": "expression", "expression": "joy", "amount": 0.5}),
    ("gaze", {"kind": "gaze", "target": "camera"}),
)


def _encodings(text: str) -> list[str]:
    names = [x.strip() for x in text.split(",") if x.strip()]
    bad = [x for x in names if x not in ("i16", "f32", "compact")]
    if bad or not names:
        raise argparse.ArgumentTypeError(f"encodings are i16, f32 or compact, got {text!r}")
    return names


# ------------------------------------------------------------------------------------ server process


def _server(
    face: str,
    backend: str,
    env: dict[str, str] | None = None,
    python: str = sys.executable,
    extra: tuple[str, ...] = (),
) -> LocalServer:
    """A ``facecast serve`` of the bench's own (temporary data dir, no job workers, generous limits),
    run by ``python`` (another checkout's interpreter for ``--baseline-python``); ``extra``: more
    options (``--redis URL``)."""
    limits = {
        "FACECAST_MAX_SESSIONS": "256",
        "FACECAST_MAX_VIEWERS_PER_SESSION": "1024",
        "FACECAST_MAX_PRODUCER_FPS": "1000",
        **_SERVER_ENV,
    }
    return LocalServer(
        None,
        "--face",
        face,
        "--backend",
        backend,
        "--job-workers",
        "0",
        *extra,
        admin_key=ADMIN_KEY,
        env={**limits, **(env or {})},
        python=python,
    )


class _Cluster:
    """A real ``redis-server`` and ``n`` ``facecast serve --redis`` nodes on this machine, each with
    its own port and data dir and the bench's admin key; CPU time is theirs summed."""

    def __init__(
        self, n: int, face: str, backend: str, pin: bool = True, env: dict[str, str] | None = None
    ) -> None:
        from facecast.server.cluster.workers import placement

        self.redis = RedisServer()
        extra = ("--redis", self.redis.url, "--workers", "1")  # one process per node, measured
        # placed as ``facecast serve --workers n`` places its node processes (pinned to their
        # own cores, PoCL sized to them), unless ``pin`` is off
        self.placement = [placement(k, n) if pin else (None, {}) for k in range(n)]
        self.nodes = [
            _server(face, backend, env={**(env or {}), **pocl}, extra=extra)
            for _, pocl in self.placement
        ]
        self.admin_key = ADMIN_KEY
        self.urls = [s.url for s in self.nodes]
        self.url = self.urls[0]
        self.health: dict = {}

    def start(self, timeout: float = 300, *, ready: bool = True) -> _Cluster:
        self.redis.start()
        for node, (cpus, _) in zip(self.nodes, self.placement):
            mine = os.sched_getaffinity(0) if cpus else None
            if cpus:  # the node process inherits this thread's CPUs (as --workers' preexec_fn)
                os.sched_setaffinity(0, cpus)
            try:
                node.start(timeout, ready=ready)
            finally:
                if mine:
                    os.sched_setaffinity(0, mine)
        self.health = self.nodes[0].health
        return self

    def stop(self) -> None:
        for node in self.nodes:
            node.stop()
        self.redis.stop()

    def cpu_seconds(self) -> float:
        procs = [n.proc.pid for n in self.nodes if n.proc] + [self.redis.proc.pid]
        return sum(process_cpu_seconds(pid) for pid in procs)

    def node_cpu_seconds(self) -> list[float]:
        return [process_cpu_seconds(n.proc.pid) if n.proc else float("nan") for n in self.nodes]

    def redis_cpu_seconds(self) -> float:
        return process_cpu_seconds(self.redis.proc.pid) if self.redis.proc else float("nan")


class _External:
    """A server started elsewhere (``--url``), measured through ``--server-pid``."""

    def __init__(self, pid: int) -> None:
        self.pid = pid

    def cpu_seconds(self) -> float:
        return process_cpu_seconds(self.pid)


# ----------------------------------------------------------------------------------------- in-process


def frame_costs(face_name: str, backend: str, repeats: int = 30) -> dict:
    """Milliseconds per frame of each server step, in this process (no network)."""
    from facecast.protocol import frames
    from facecast.server.api.store import FaceStore
    from facecast.server.state import FaceState, zero_faps

    store = FaceStore(default=face_name, backend=backend)
    animator = store.animator(face_name)
    states = [_state(i, 60.0, FaceState, zero_faps) for i in range(repeats)]
    out: dict = {
        "vertices": int(animator.face.n_vertices),
        "backend": getattr(animator.deformer, "name", type(animator.deformer).__name__),
    }
    animator.frame(states[0])

    def timed(fn) -> float:
        t0 = time.perf_counter()
        for s in states:
            fn(s)
        return round(1000 * (time.perf_counter() - t0) / len(states), 3)

    out["solve_ms"] = timed(animator.solve)
    out["solve_batch_ms"] = round(_cpu_ms(lambda: animator.solve_batch(states)) / len(states), 3)
    solved = [animator.solve(s) for s in states]
    it = iter(range(len(states)))
    out["deform_ms"] = timed(lambda s: animator.deformer.deform(*solved[next(it)]))
    v = animator.frame(states[0])
    out["encode_i16_ms"] = timed(lambda s: frames.encode_vertices_i16(v, seq=0, t=s.t))
    out["encode_f32_ms"] = timed(lambda s: frames.encode_vertices_f32(v, seq=0, t=s.t))
    # compact, as a session encodes it (0.1 mm, keys every 250 ms at 60 fps), process CPU
    from facecast.protocol.compact import CompactEncoder

    face = animator.face
    enc = CompactEncoder(
        face.vertices, face.rigid_group, tolerance=0.1 / face.mm_per_unit, key_interval=15
    )
    vs = [np.asarray(animator.deformer.deform(*x), np.float32) for x in solved]

    def compact_all() -> None:
        for k, (s, x) in enumerate(zip(states, vs)):
            enc.encode(x, solved[k][1], seq=k, t=s.t)

    out["encode_compact_ms"] = round(_cpu_ms(compact_all, 3) / len(states), 3)
    # what the live server does: int16 frames of a batch quantised together, WebSocket-framed
    from facecast.server.live.batcher import encode_batch

    vb = np.repeat(v[None], 8, axis=0)
    jobs = [(i, 0.0, 0.0, frozenset({"i16"})) for i in range(len(vb))]
    out["encode_i16_batched_ms"] = round(timed(lambda s: encode_batch(vb, jobs)) / len(vb), 3)
    # the live worker's whole job (solve, deform, encode) per frame, CPU of all threads: batches
    # of 1 (light load) and of 20 (20 busy sessions), with and without device quantisation
    from facecast.server.live.batcher import DeformBatcher, _Job

    batcher = DeformBatcher(animator, None)  # type: ignore[arg-type]
    # white-box: the worker's job is timed synchronously, with and without the device quantiser,
    # which the batcher has no public way to run or switch off
    work = batcher._work  # noqa: SLF001
    for n in (1, 20):
        js = [
            _Job(states[i % len(states)], i, 0.0, frozenset({"i16"}), None, None) for i in range(n)
        ]  # type: ignore[arg-type]
        reps = max(20, 200 // n)
        out[f"worker_cpu_ms_batch{n}"] = round(_cpu_ms(lambda js=js: work(js), reps) / n, 3)
        if batcher.quantizer is not None:
            q, batcher._quantizer = batcher._quantizer, None  # noqa: SLF001
            out[f"worker_cpu_ms_batch{n}_numpy_quantize"] = round(
                _cpu_ms(lambda js=js: work(js), reps) / n, 3
            )
            batcher._quantizer = q  # noqa: SLF001
    blob = frames.encode_vertices_i16(v, seq=0, t=0.0)
    out["decode_i16_ms"] = timed(lambda s: frames.decode(blob))
    out["bytes_i16"] = len(blob)
    out["bytes_f32"] = len(frames.encode_vertices_f32(v, seq=0, t=0.0))
    return out


def _cpu_ms(fn, repeats: int = 20, rounds: int = 3) -> float:
    """Process CPU milliseconds (all threads) of one ``fn()`` call: the best of ``rounds``."""
    fn()
    best = math.inf
    for _ in range(rounds):
        c0 = time.process_time()
        for _ in range(repeats):
            fn()
        best = min(best, (time.process_time() - c0) / repeats)
    return 1000 * best


def _state(i: int, fps: float, FaceState, zero_faps):
    faps = zero_faps()
    t = i / fps
    faps[3] = 400 + 400 * math.sin(2 * math.pi * 0.7 * t)  # open jaw
    faps[5] = 150 * math.sin(2 * math.pi * 1.3 * t)  # lower lip
    faps[12] = faps[13] = 200 * math.sin(2 * math.pi * 0.4 * t)  # lip corners
    faps[19] = faps[20] = 500 * max(0.0, math.sin(2 * math.pi * 0.25 * t)) ** 8  # blinks
    return FaceState(t=t, faps=faps)


# ------------------------------------------------------------------------------------------ load points


async def _producer(
    url: str, s, fps: float, stop: asyncio.Event, sent: list[int], retry: bool = False
) -> None:
    """Send FAP frames at ``fps`` until ``stop``; ``retry``: reconnect as a cluster's clients do
    (a session may change owner when a starved node misses its lease)."""
    from serve_load import faps

    from facecast.client.api import Pacer, Retry, produce

    async with produce(url, s.id, s.producer_token, retry=Retry() if retry else None) as p:
        pacer = Pacer(1.0)
        i = 0
        while not stop.is_set():
            await pacer.until(i / fps)
            await p.send_faps(faps(i, fps), i / fps)
            i += 1
        sent.append(i)


async def _viewer(
    url: str,
    s,
    encoding: str,
    stop: asyncio.Event,
    ready: asyncio.Event,
    out: list[tuple[float, int, float, int]],
) -> None:
    from facecast.client import api
    from facecast.client.api import watch

    opts = {}
    if _VIEWER_OPTS.get("rcvbuf") is not None:
        opts["receive_buffer"] = _VIEWER_OPTS["rcvbuf"] or None
    opts["max_queue"] = _VIEWER_OPTS.get("queue") or api.VIEWER_MAX_QUEUE
    if _VIEWER_OPTS.get("retry"):  # a cluster's viewers follow a session that changes owner
        opts["retry"] = api.Retry()

    async def receive(w: Any) -> None:
        async for f in w:
            h = f.frame.header
            out.append((f.received, h.seq, h.wall, f.size))

    async with watch(url, s.id, s.viewer_token, encoding=encoding, **opts) as w:
        ready.set()
        # Wait for frames as long as it takes (producers start once every viewer is connected, which
        # may take seconds): a timeout around the frame iterator would end it, and the viewer with it.
        frames, stopped = asyncio.create_task(receive(w)), asyncio.create_task(stop.wait())
        await asyncio.wait({frames, stopped}, return_when=asyncio.FIRST_COMPLETED)
        for task in (frames, stopped):
            task.cancel()
        await asyncio.gather(frames, stopped, return_exceptions=True)
        error = None if frames.cancelled() else frames.exception()
        if error is not None:
            raise error


async def _light_viewer(
    url: str, s, encoding: str, stop: asyncio.Event, ready: asyncio.Event, out: list
) -> None:
    """A minimal viewer for load generation (``serve_load.Viewer``: it reads each server frame's
    length and the seq and wall time of binary ones, and skips the rest without copying it), so
    the benchmark measures the server rather than the Python client's parser (``--viewer client``
    uses the real client)."""
    from urllib.parse import quote

    from serve_load import Viewer, upgrade_request

    from facecast.client.api import VIEWER_RECEIVE_BUFFER

    path = f"/v1/sessions/{quote(s.id, safe='')}/watch"
    host, port, request = upgrade_request(url, path, s.viewer_token, encoding=encoding)
    loop = asyncio.get_running_loop()
    transport, proto = await loop.create_connection(
        lambda: Viewer(request, out, VIEWER_RECEIVE_BUFFER), host, port
    )
    try:
        await proto.ready  # the viewer hello
        ready.set()
        await stop.wait()
    finally:
        transport.close()


@dataclass(frozen=True)
class _Seat:
    """What a viewer in another process needs of its session (``url``: the node it watches on)."""

    id: str
    viewer_token: str
    url: str


def _viewer_process(url, seats, kind, encoding, opts, ready, stop, conn) -> None:
    """Child process: watch ``seats`` (slot -> ``_Seat``) until ``stop``; send back slot -> records."""
    _VIEWER_OPTS.update(opts)

    async def main() -> dict:
        local_stop = asyncio.Event()
        fn = _light_viewer if kind == "light" else _viewer
        recs = {slot: [] for slot in seats}
        evs = [asyncio.Event() for _ in seats]
        tasks = [
            asyncio.create_task(fn(seat.url or url, seat, encoding, local_stop, ev, recs[slot]))
            for (slot, seat), ev in zip(seats.items(), evs)
        ]
        await asyncio.wait_for(asyncio.gather(*(e.wait() for e in evs)), 120)
        ready.set()
        # ``stop`` is a multiprocessing.Event (the parent process sets it): asyncio cannot await it
        while not stop.is_set():  # noqa: ASYNC110
            await asyncio.sleep(0.05)
        local_stop.set()
        await asyncio.wait_for(asyncio.gather(*tasks, return_exceptions=True), 60)
        return recs

    conn.send(asyncio.run(main()))
    conn.close()


def machine_cpu() -> tuple[float, float]:
    """``(busy, total)`` CPU seconds of the whole machine so far (``/proc/stat``), or NaNs."""
    try:
        f = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    except (OSError, ValueError):
        return float("nan"), float("nan")
    tick = os.sysconf("SC_CLK_TCK")
    idle = f[3] + (f[4] if len(f) > 4 else 0)
    return (sum(f) - idle) / tick, sum(f) / tick


def _cpu_snapshot(server, clients_cpu) -> dict:
    """CPU seconds so far of the server (each node and Redis on a cluster), of the load generator
    and of the whole machine."""
    busy, total = machine_cpu()
    snap = {
        "server": server.cpu_seconds() if server else float("nan"),
        "clients": clients_cpu(),
        "bench": time.process_time(),
        "machine_busy": busy,
        "machine_total": total,
    }
    if isinstance(server, _Cluster):
        snap["nodes"] = server.node_cpu_seconds()
        snap["redis"] = server.redis_cpu_seconds()
    return snap


def _cpu_use(w: dict) -> dict:
    """Cores each party used in window ``w`` (CPU seconds per second)."""
    a, b, dt = w["cpu"], w["cpu1"], w["t1"] - w["t0"]
    ncpu = os.cpu_count() or 1
    machine = (
        ncpu * (b["machine_busy"] - a["machine_busy"]) / (b["machine_total"] - a["machine_total"])
        if b["machine_total"] > a["machine_total"]
        else float("nan")
    )
    ours = (b["server"] - a["server"]) + (b["clients"] - a["clients"])
    out = {
        "server_cpu": round((b["server"] - a["server"]) / dt, 3),
        "generator_cpu": round((b["clients"] - a["clients"]) / dt, 3),
        "machine_cpu": round(machine, 3),
        # everything else on the machine: other work sharing it (its helpers, CI, ...)
        "others_cpu": round(machine - ours / dt, 3),
    }
    if "nodes" in a:
        out["node_cpu"] = [round((y - x) / dt, 3) for x, y in zip(a["nodes"], b["nodes"])]
        out["redis_cpu"] = round((b["redis"] - a["redis"]) / dt, 3)
    return out


async def _client_load(made, owner, nodes, watched_on, viewers, args, window, url):
    """The real asyncio client as load: producers in this process, viewers (``--viewer-kind``)
    spread over ``--viewer-processes`` processes. ``(records, window, failures)``."""
    stop = asyncio.Event()
    records: list[list] = []
    ready_events = []
    tasks = []
    n_proc = max(1, min(getattr(args, "viewer_processes", 1), len(made) * viewers))
    _VIEWER_OPTS["retry"] = len(nodes) > 1
    away: list[dict] = [{} for _ in range(n_proc - 1)]  # seats of the other processes
    for k, s in enumerate(s for s in made for _ in range(viewers)):
        rec: list = []
        records.append(rec)
        if k % n_proc:
            away[k % n_proc - 1][k] = _Seat(s.id, s.viewer_token, watched_on[s.id])
            continue
        ev = asyncio.Event()
        ready_events.append(ev)
        fn = _light_viewer if args.viewer_kind == "light" else _viewer
        tasks.append(asyncio.create_task(fn(watched_on[s.id], s, args.encoding, stop, ev, rec)))
    mp = multiprocessing.get_context("spawn")
    mp_stop, children = mp.Event(), []
    for seats in away:
        ready, (mine, theirs) = mp.Event(), mp.Pipe(duplex=False)
        proc = mp.Process(
            target=_viewer_process,
            daemon=True,
            args=(
                url,
                seats,
                args.viewer_kind,
                args.encoding,
                dict(_VIEWER_OPTS),
                ready,
                mp_stop,
                theirs,
            ),
        )
        proc.start()
        children.append((proc, ready, mine))
    await asyncio.wait_for(asyncio.gather(*(e.wait() for e in ready_events)), 120)
    for _proc, ready, _ in children:
        if not await asyncio.to_thread(ready.wait, 180):
            raise RuntimeError("a viewer process did not get its viewers connected")
    sent: list[int] = []
    tasks += [
        asyncio.create_task(
            _producer(nodes[owner[s.id]], s, args.fps, stop, sent, retry=len(nodes) > 1)
        )
        for s in made
    ]

    def clients_cpu() -> float:
        return time.process_time() + sum(process_cpu_seconds(p.pid) for p, _, _ in children)

    w = await window(clients_cpu)
    stop.set()
    mp_stop.set()
    results = await asyncio.wait_for(asyncio.gather(*tasks, return_exceptions=True), 60)
    for proc, _, conn in children:
        for k, rec in (await asyncio.to_thread(conn.recv)).items():
            records[k][:] = rec
        proc.join(10)
    failures = [r for r in results if isinstance(r, BaseException)]
    return records, w, failures


async def _light_load(made, owner, nodes, watched_on, viewers, args, window):
    """The cheap generator (``bench/serve_load.py``): producers and viewers spread over
    ``--generator-processes`` processes. ``(records, window, failures, generator info)``."""
    from serve_load import ProducerSeat, ViewerSeat, run_generator

    n_proc = max(1, args.generator_processes)
    prods: list[list] = [[] for _ in range(n_proc)]
    views: list[list] = [[] for _ in range(n_proc)]
    for k, s in enumerate(made):
        prods[k % n_proc].append(ProducerSeat(k, s.id, s.producer_token, nodes[owner[s.id]]))
    slot = 0
    for s in made:
        for _ in range(viewers):
            views[slot % n_proc].append(ViewerSeat(slot, s.id, s.viewer_token, watched_on[s.id]))
            slot += 1
    records: list[list] = [[] for _ in range(slot)]
    mp = multiprocessing.get_context("spawn")
    children = []
    try:
        for p, v in zip(prods, views):
            mine, theirs = mp.Pipe()
            proc = mp.Process(
                target=run_generator, daemon=True, args=(p, v, args.fps, args.encoding, theirs)
            )
            proc.start()
            children.append((proc, mine))

        async def hear(conn, what: str, timeout: float) -> Any:
            if not await asyncio.to_thread(conn.poll, timeout):
                raise RuntimeError(f"a load generator process did not say {what!r} in {timeout} s")
            got = conn.recv()
            if got != what:
                raise RuntimeError(f"a load generator process failed: {got!r}")
            return got

        for _, conn in children:  # every viewer connected
            await hear(conn, "ready", 180)
        for _, conn in children:
            conn.send("go")
        for _, conn in children:  # every producer connected and sending
            await hear(conn, "producing", 180)
        pids = [p.pid for p, _ in children]
        w = await window(lambda: sum(process_cpu_seconds(pid) for pid in pids))
        outs = []
        for _, conn in children:
            conn.send("stop")
        for _proc, conn in children:
            if not await asyncio.to_thread(conn.poll, 60):
                raise RuntimeError("a load generator process did not report its records")
            outs.append(conn.recv())
    finally:
        for proc, _ in children:
            proc.join(10)
            if proc.is_alive():
                proc.kill()
    failures: list = []
    gen = {"producer_reconnects": 0, "viewer_reconnects": 0, "frames_sent": 0}
    for out in outs:
        if "error" in out:
            failures.append(out["error"])
            continue
        for k, rec in out["records"].items():
            records[k] = rec
        failures += out["viewer_failures"]
        gen["producer_reconnects"] += out["producer_reconnects"]
        gen["viewer_reconnects"] += out["viewer_reconnects"]
        gen["frames_sent"] += out["sent"]
    return records, w, failures, gen


async def run_point(server, url: str, *, sessions: int, viewers: int, args) -> dict:
    """One load point: ``sessions`` sessions with ``viewers`` viewers each, for warmup + seconds.

    On a ``_Cluster``, session k is created on node k mod N (its owner, where its producer
    connects) and watched on node k + 1 mod N: every viewer is on another node than its producer.
    """
    from contextlib import AsyncExitStack

    from facecast.client.api import LiveError, SessionAdmin

    key = (
        server.admin_key
        if isinstance(server, (LocalServer, _Cluster))
        else os.environ.get("FACECAST_ADMIN_KEY", ADMIN_KEY)
    )
    nodes = server.urls if isinstance(server, _Cluster) else [url]
    async with AsyncExitStack() as stack:
        admins = [await stack.enter_async_context(SessionAdmin(u, key)) for u in nodes]
        made = [
            await admins[k % len(nodes)].create(face=args.face, fps=args.fps)
            for k in range(sessions)
        ]
        owner = {s.id: k % len(nodes) for k, s in enumerate(made)}
        for s in made:  # REST layers live on the session's owner
            for name, spec in LAYERS[: getattr(args, "layers", 0)]:
                await admins[owner[s.id]].set_layer(s.id, name, spec)

        async def info(sid: str) -> Any:
            """The session's info from its owner (it may have moved: then from the node that
            has it now, which answers for the sessions it owns)."""
            err: LiveError | None = None
            for k in _owner_first(owner[sid], len(nodes)):
                try:
                    return await admins[k].info(sid)
                except LiveError as e:
                    err = e
            assert err is not None
            raise err

        # a viewer's node against its session's owner (k): another, the owner, or half of each
        shift = {"other": lambda k: 1, "owner": lambda k: 0, "spread": lambda k: k // len(nodes)}
        away_by = shift[getattr(args, "cluster_viewers", "other")]
        watched_on = {s.id: nodes[(k + away_by(k)) % len(nodes)] for k, s in enumerate(made)}

        async def deformed() -> int:  # frames the server deformed and encoded, all sessions
            try:  # an overloaded server may not answer in time: the point is still measured
                infos = await asyncio.gather(*(info(s.id) for s in made))
            except LiveError as e:
                log.warning("cannot count the frames deformed: %s", e)
                return -1
            return sum(i.stats.frames_deformed for i in infos)

        async def window(clients_cpu) -> dict:
            """The measured window, after the warmup: times, CPU of everyone, frames deformed."""
            await asyncio.sleep(args.warmup)
            w: dict = {"deformed0": await deformed()}
            w.update(t0=time.time(), cpu=_cpu_snapshot(server, clients_cpu))
            await asyncio.sleep(args.seconds)
            w.update(t1=time.time(), cpu1=_cpu_snapshot(server, clients_cpu))
            w["deformed1"] = await deformed()
            return w

        if getattr(args, "generator", "client") == "light":
            records, w, failures, gen = await _light_load(
                made, owner, nodes, watched_on, viewers, args, window
            )
        else:
            records, w, failures = await _client_load(
                made, owner, nodes, watched_on, viewers, args, window, url
            )
            gen = {}
        for r in failures[:3]:
            log.warning("a client failed: %r", r)
        infos = []
        for s in made:
            try:
                infos.append(await info(s.id))
            except LiveError as e:
                log.warning("cannot read session %s after the point: %s", s.id, e)
        for s in made:
            for k in _owner_first(owner[s.id], len(nodes)):
                try:
                    await admins[k].close(s.id)
                    break
                except LiveError:
                    continue

    t0, t1, deformed0, deformed1 = w["t0"], w["t1"], w["deformed0"], w["deformed1"]
    cpu_s0, cpu_s1 = w["cpu"]["server"], w["cpu1"]["server"]
    cpu_c0, cpu_c1 = w["cpu"]["clients"], w["cpu1"]["clients"]
    window = t1 - t0
    rates, lat, skipped, sizes = [], [], 0, []
    produced: set[tuple[int, int]] = set()  # (session, seq) of frames some viewer received
    for k, rec in enumerate(records):
        inside = [r for r in rec if t0 <= r[0] < t1]
        produced.update((k // viewers, r[1]) for r in inside)
        rates.append(len(inside) / window)
        if len(inside) > 1:
            seqs = np.array([r[1] for r in inside], dtype=np.int64)
            d = np.diff(seqs) - 1
            # a new owner numbers its frames anew (from epoch << 20): no frames were skipped there
            skipped += int(d[(d > 0) & (d < 1 << 19)].sum())
        lat += [1000 * (r[0] - r[2]) for r in inside if r[2] > 0]
        sizes += [r[3] for r in inside]
    lat_a = np.array(lat) if lat else np.array([np.nan])
    deform = [i.stats.deform_ms_mean for i in infos if i.stats.frames_deformed]
    return {
        "sessions": sessions,
        "viewers_per_session": viewers,
        "viewers_total": sessions * viewers,
        "fps_target": args.fps,
        "fps_mean": round(float(np.mean(rates)), 2),
        "fps_min": round(float(np.min(rates)), 2),
        "latency_ms_p50": round(float(np.percentile(lat_a, 50)), 2),
        "latency_ms_p95": round(float(np.percentile(lat_a, 95)), 2),
        "latency_ms_max": round(float(np.max(lat_a)), 2),
        "frames_received": len(lat),
        "frames_skipped": skipped,
        "server_dropped_before_deform": int(sum(i.stats.frames_dropped for i in infos)),
        "bytes_per_frame": round(float(np.mean(sizes)), 1) if sizes else None,
        "server_deform_encode_ms": round(float(np.mean(deform)), 3) if deform else None,
        "server_cpu": round((cpu_s1 - cpu_s0) / window, 2),
        "client_cpu": round((cpu_c1 - cpu_c0) / window, 2),
        # CPU per delivered frame: comparable across points even when the machine is shared
        "server_cpu_us_per_frame": round(1e6 * (cpu_s1 - cpu_s0) / len(lat), 1) if lat else None,
        # ... and per session-frame (each deformed and encoded frame, whatever its viewers)
        "server_cpu_us_per_session_frame": round(1e6 * (cpu_s1 - cpu_s0) / len(produced), 1)
        if produced
        else None,
        # ... and per frame the server deformed and encoded (counted just outside the window):
        # what the server's work costs even when starved viewers skip frames
        "server_cpu_us_per_deformed_frame": round(
            1e6 * (cpu_s1 - cpu_s0) / (deformed1 - deformed0), 1
        )
        if deformed1 > deformed0 >= 0
        else None,
        "server_frames_deformed_per_s": round((deformed1 - deformed0) / window, 1)
        if min(deformed0, deformed1) >= 0
        else None,
        "client_cpu_us_per_frame": round(1e6 * (cpu_c1 - cpu_c0) / len(lat), 1) if lat else None,
        "client_failures": len(failures),
        "generator": getattr(args, "generator", "client"),
        **gen,
        # cores used in the window: server (per node and Redis on a cluster), the load
        # generator, the whole machine and what the rest of it ran (other work sharing it)
        **_cpu_use(w),
        "loadavg": [round(x, 2) for x in os.getloadavg()],
        "seconds": round(window, 2),
    }


def _owner_first(k: int, n: int) -> list[int]:
    """Node indices, ``k`` first."""
    return [k] + [i for i in range(n) if i != k]


def _ok(p: dict, args) -> bool:
    return p["fps_min"] >= 0.95 * args.fps and p["latency_ms_p95"] <= args.latency_target


def _table(title: str, points: list[dict], args) -> str:
    base = points[0] if points else None
    head = (
        "| sessions | viewers | fps mean | fps min | p50 ms | p95 ms | p95 ratio | skipped | deform+enc ms "
        "| server CPU | client CPU | server µs/frame | server µs/session-frame "
        "| deformed/s | server µs/deformed frame | client µs/frame | target |"
    )
    lines = [f"### {title}", "", head, "|" + "---|" * 17]
    for p in points:
        ratio = (
            p["latency_ms_p95"] / base["latency_ms_p95"]
            if base and base["latency_ms_p95"]
            else float("nan")
        )
        p["latency_p95_ratio"] = round(ratio, 2)
        errors = f" ({p['client_failures']} client errors)" if p["client_failures"] else ""
        lines.append(
            f"| {p['sessions']} | {p['viewers_total']} | {p['fps_mean']} | {p['fps_min']} | "
            f"{p['latency_ms_p50']} | {p['latency_ms_p95']} | {ratio:.2f} | {p['frames_skipped']} | "
            f"{p['server_deform_encode_ms']} | {p['server_cpu']} | {p['client_cpu']} | "
            f"{p['server_cpu_us_per_frame']} | {p['server_cpu_us_per_session_frame']} | "
            f"{p['server_frames_deformed_per_s']} | {p['server_cpu_us_per_deformed_frame']} | "
            f"{p['client_cpu_us_per_frame']} | "
            f"{'ok' if _ok(p, args) else 'miss'}{errors} |"
        )
    return "\n".join(lines)


async def _sweeps(server, url: str, args, baseline: LocalServer | None = None) -> dict:
    """Both sweeps; with ``baseline``, each point is measured on it too (``baseline_*``), the two
    servers going first in turn."""
    res: dict = {"sessions_sweep": [], "viewers_sweep": []}
    if baseline is not None:
        res.update(baseline_sessions_sweep=[], baseline_viewers_sweep=[])
    points = [("sessions_sweep", int(x), 1) for x in args.sessions.split(",") if x.strip()]
    points += [("viewers_sweep", 1, int(x)) for x in args.viewers.split(",") if x.strip()]
    for i, (sweep, n, m) in enumerate(points):
        log.info("%s: %d session(s), %d viewer(s) each", sweep, n, m)
        # With a baseline, the two servers take turns going first (ABBA...), so that neither
        # always meets the machine right after the other's load or always runs warm.
        order = (
            [(server, url, ""), (baseline, baseline.url, "baseline_")]
            if baseline
            else [(server, url, "")]
        )
        for srv, srv_url, prefix in order[:: -1 if baseline is not None and i % 2 else 1]:
            res[prefix + sweep].append(
                await run_point(srv, srv_url, sessions=n, viewers=m, args=args)
            )
            log.info("%s%s", prefix, res[prefix + sweep][-1])
    return res


def _cluster_sweeps(args, encodings: list[str], by_encoding: dict) -> dict:
    """The sessions sweep on a ``_Cluster`` of ``args.cluster`` nodes, per encoding:
    ``{encoding: {"nodes", "sessions_sweep", "redis_cpu", ...}}``."""
    out: dict = {}
    cluster = _Cluster(
        args.cluster,
        args.face,
        args.backend,
        pin=getattr(args, "cluster_pin", "auto") == "auto",
        env=_cluster_env(args),
    )
    sessions, viewers = args.sessions, args.viewers
    args.sessions, args.viewers = args.cluster_sessions or args.sessions, ""
    try:
        cluster.start(300, ready=True)
        for enc in encodings:
            args.encoding = enc
            r0 = cluster.redis_cpu_seconds()
            t0 = time.time()
            sweep = asyncio.run(_sweeps(cluster, cluster.url, args))["sessions_sweep"]
            out[enc] = {
                "nodes": args.cluster,
                "viewers_on": args.cluster_viewers,
                "node_cpus": [sorted(c) if c else None for c, _ in cluster.placement],
                "node_env": [
                    {k: v for k, v in n.env.items() if k.startswith(("FACECAST_LIVE", "POCL_"))}
                    for n in cluster.nodes
                ],
                "sessions_sweep": sweep,
                "redis_cpu_mean": round((cluster.redis_cpu_seconds() - r0) / (time.time() - t0), 3),
                "sessions_at_target": _at_target(sweep, args),
                "single_sessions_at_target": _at_target(by_encoding[enc]["sessions_sweep"], args),
            }
            single, multi = out[enc]["single_sessions_at_target"], out[enc]["sessions_at_target"]
            out[enc]["ratio_vs_single"] = round(multi / single, 2) if single else None
            log.info("cluster, %s: %s", enc, out[enc])
    finally:
        cluster.stop()
        args.sessions, args.viewers, args.encoding = sessions, viewers, encodings[0]
    return out


def _cluster_env(args) -> dict[str, str]:
    """The cluster nodes' own live settings (``--cluster-coalesce-*``), over ``_SERVER_ENV``."""
    env = {}
    if getattr(args, "cluster_coalesce_ms", None) is not None:
        env["FACECAST_LIVE_COALESCE_MS"] = f"{args.cluster_coalesce_ms:g}"
    if getattr(args, "cluster_coalesce_frames", None) is not None:
        env["FACECAST_LIVE_COALESCE_FRAMES"] = str(args.cluster_coalesce_frames)
    return env


def _at_target(points: list[dict], args) -> int:
    """The largest session count of a sweep at which every viewer met the target (0: none)."""
    return max((p["sessions"] for p in points if _ok(p, args)), default=0)


def _cluster_table(enc: str, single: list[dict], cluster: dict, args) -> str:
    """Single process and cluster side by side, point by point (same session counts where both
    were measured), with who used the machine's cores in each window."""
    by_n = {p["sessions"]: p for p in single}
    lines = [
        (
            f"### Sessions at {args.fps:g} fps: one process vs {cluster['nodes']} nodes + Redis, "
            f"{enc} (cluster viewers: {cluster.get('viewers_on', 'other')})"
        ),
        "",
        (
            "Cores used in each window (CPU-seconds per second): the server (each node, Redis), "
            "the load generator, and everything else on the machine (other work sharing it)."
        ),
        "",
        (
            "| sessions | single fps min | single p95 ms | single | cluster fps min | cluster p95 ms "
            "| cluster | single CPU | cluster nodes CPU | Redis | generator single / cluster "
            "| others single / cluster | µs/session-frame single / cluster |"
        ),
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def g(p: dict | None, k: str) -> Any:
        return "–" if p is None or p.get(k) is None else p[k]

    for p in cluster["sessions_sweep"]:
        s = by_n.get(p["sessions"])
        sv = (
            f"{s['fps_min']} | {s['latency_ms_p95']} | {'ok' if _ok(s, args) else 'miss'}"
            if s
            else "– | – | –"
        )
        nodes = " + ".join(f"{x:.2f}" for x in p.get("node_cpu") or [])
        lines.append(
            f"| {p['sessions']} | {sv} | {p['fps_min']} | {p['latency_ms_p95']} | "
            f"{'ok' if _ok(p, args) else 'miss'} | {g(s, 'server_cpu')} | {nodes} | "
            f"{g(p, 'redis_cpu')} | {g(s, 'generator_cpu')} / {g(p, 'generator_cpu')} | "
            f"{g(s, 'others_cpu')} / {g(p, 'others_cpu')} | "
            f"{g(s, 'server_cpu_us_per_session_frame')} / {g(p, 'server_cpu_us_per_session_frame')} |"
        )
    lines.append(
        f"\nSessions at target: single {cluster['single_sessions_at_target']}, cluster "
        f"{cluster['sessions_at_target']} (ratio {cluster['ratio_vs_single']}; target ≥ 1.5); "
        f"Redis CPU {cluster['redis_cpu_mean']} core(s) on average. Nodes' CPUs "
        f"{cluster.get('node_cpus')}, settings {cluster.get('node_env')}."
    )
    return "\n".join(lines)


def _ratios(points: list[dict], baseline: list[dict], key: str) -> list[float | None]:
    """``key`` of each point over the baseline's at the same point (None where one is missing)."""
    return [
        round(p[key] / b[key], 2) if p.get(key) and b.get(key) else None
        for p, b in zip(points, baseline)
    ]


def run(args: argparse.Namespace) -> int:
    logging.getLogger("httpx").setLevel(logging.WARNING)
    _VIEWER_OPTS.update(rcvbuf=args.viewer_rcvbuf, queue=args.viewer_queue)
    if args.coalesce_ms is not None:
        _SERVER_ENV["FACECAST_LIVE_COALESCE_MS"] = f"{args.coalesce_ms:g}"
    t_start = time.time()
    load_before = os.getloadavg()
    costs = frame_costs(args.face, args.backend)
    log.info("in-process costs per frame: %s", costs)
    server = None
    url = args.url
    if url is None:
        server = _server(args.face, args.backend)
    elif args.server_pid:
        server = _External(args.server_pid)
    baseline = None
    if args.baseline_python and url is None:
        baseline = _server(args.face, args.backend, python=args.baseline_python)
    try:
        health = server.start(300, ready=True).health if isinstance(server, LocalServer) else {}
        if baseline is not None:
            baseline.start(300, ready=True)
        encodings, by_encoding = list(args.encoding), {}
        for enc in encodings:
            args.encoding = enc
            by_encoding[enc] = asyncio.run(_sweeps(server, url or server.url, args, baseline))
        args.encoding = encodings[0]
        res = by_encoding[encodings[0]]
    finally:
        for srv in (server, baseline):
            if isinstance(srv, LocalServer):
                srv.stop()
    if baseline is not None:
        res["baseline_python"] = args.baseline_python
        for sweep in ("sessions_sweep", "viewers_sweep"):
            res[sweep + "_cpu_ratio_vs_baseline"] = _ratios(
                res[sweep], res["baseline_" + sweep], "server_cpu_us_per_session_frame"
            )
    if args.compare_asgi and url is None:
        server = _server(args.face, args.backend, env={"FACECAST_LIVE_DIRECT": "0"})
        try:
            server.start(300, ready=True)
            sessions, args.sessions = args.sessions, ""
            res["viewers_sweep_asgi"] = asyncio.run(_sweeps(server, server.url, args))[
                "viewers_sweep"
            ]
            args.sessions = sessions
        finally:
            server.stop()
        for d, a in zip(res["viewers_sweep"], res["viewers_sweep_asgi"]):
            if d["server_cpu_us_per_frame"] and a["server_cpu_us_per_frame"]:
                d["server_cpu_ratio_vs_asgi"] = round(
                    d["server_cpu_us_per_frame"] / a["server_cpu_us_per_frame"], 2
                )
    cluster = None
    if args.cluster and url is None:
        cluster = _cluster_sweeps(args, encodings, by_encoding)
    load = os.getloadavg()
    report = {
        "bench": "serve",
        "face": args.face,
        "vertices": costs["vertices"],
        "encoding": args.encoding,
        "by_encoding": by_encoding,
        "fps": args.fps,
        "layers": args.layers,
        "generator": args.generator,
        "coalesce_ms": args.coalesce_ms,
        "backend": health.get("backend", args.backend),
        "device": health.get("device"),
        "viewer_kind": args.viewer_kind,
        "viewer_rcvbuf": args.viewer_rcvbuf,
        "viewer_queue": args.viewer_queue,
        "frame_costs_ms": costs,
        "latency_target_ms": args.latency_target,
        **res,
        "cluster": cluster,
        "cpus": os.cpu_count(),
        "loadavg_before": [round(x, 2) for x in load_before],
        "loadavg_after": [round(x, 2) for x in load],
        "seconds_total": round(time.time() - t_start, 1),
        "note": "loopback, server and all clients on this machine; the machine may be shared (see loadavg)",
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2))
    c = costs
    print(
        f"## bench/serve.py — {args.face} ({c['vertices']} vertices), "
        f"{', '.join(by_encoding)} frames, "
        f"producers at {args.fps:g} fps, backend {report['backend']}\n"
    )
    print(
        f"In-process per frame: solve {c['solve_ms']} ms, deform {c['deform_ms']} ms ({c['backend']}), "
        f"encode i16 {c['encode_i16_ms']} ms (batched as in the server: "
        f"{c.get('encode_i16_batched_ms')} ms) / f32 {c['encode_f32_ms']} ms / "
        f"compact {c.get('encode_compact_ms')} ms (CPU), "
        f"decode i16 {c['decode_i16_ms']} ms; "
        f"{c['bytes_i16']} B (i16) / {c['bytes_f32']} B (f32) per frame.\n"
    )
    print(
        f"Live worker CPU per frame (solve + deform + encode, all threads): batch of 1 "
        f"{c['worker_cpu_ms_batch1']} ms, batch of 20 {c['worker_cpu_ms_batch20']} ms "
        f"(solve alone: {c['solve_ms']} ms one by one, {c['solve_batch_ms']} ms batched)"
        + (
            f"; int16 quantised in NumPy instead of on the device: "
            f"{c['worker_cpu_ms_batch1_numpy_quantize']} / {c['worker_cpu_ms_batch20_numpy_quantize']} ms"
            if "worker_cpu_ms_batch20_numpy_quantize" in c
            else ""
        )
        + ".\n"
    )
    for enc, r in by_encoding.items():
        if r["sessions_sweep"]:
            title = f"Concurrent sessions (1 producer + 1 viewer each), {enc}"
            print(_table(title, r["sessions_sweep"], args))
            print()
        if r["viewers_sweep"]:
            print(_table(f"Viewers of one session, {enc}", r["viewers_sweep"], args))
            print()
    for enc, r in by_encoding.items():
        for sweep, title in (
            ("sessions_sweep", "Concurrent sessions"),
            ("viewers_sweep", "Viewers of one session"),
        ):
            if r.get("baseline_" + sweep):
                print(
                    _table(
                        f"{title}, {enc}, baseline server ({args.baseline_python})",
                        r["baseline_" + sweep],
                        args,
                    )
                )
                ratios = _ratios(
                    r[sweep], r["baseline_" + sweep], "server_cpu_us_per_session_frame"
                )
                print(
                    f"\nServer CPU per session-frame, this checkout / baseline, point by point: {ratios}\n"
                )
    if cluster is not None:
        for enc in encodings:
            print(_cluster_table(enc, by_encoding[enc]["sessions_sweep"], cluster[enc], args))
            print()
    if "viewers_sweep_asgi" in res:
        print()
        print(
            _table(
                "Viewers of one session, frames sent through ASGI (baseline of the direct path)",
                res["viewers_sweep_asgi"],
                args,
            )
        )
        ratios = [d.get("server_cpu_ratio_vs_asgi") for d in res["viewers_sweep"]]
        print(f"\nServer CPU per frame, direct / ASGI: {ratios}")
    print(
        f"\nTarget: every viewer ≥ {0.95 * args.fps:g} fps and p95 ≤ {args.latency_target:g} ms. "
        "CPU columns are CPU-seconds per second (2.0 = two cores busy). "
        f"Load average before/after: {load_before[0]:.2f}/{load[0]:.2f} "
        f"on {os.cpu_count()} CPUs. JSON: {args.out}"
    )
    args.out.write_text(json.dumps(report, indent=2))
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench/serve.py", description=__doc__.split("\n\n")[0])
    add_arguments(p)
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    return run(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
