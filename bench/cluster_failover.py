"""Cluster live sessions: producer→viewer latency across nodes, and failover after ``kill -9``.

    python bench/cluster_failover.py [--nodes 3] [--seconds 10] [--sessions 4] [--rounds 3]

A real ``redis-server`` and ``--nodes`` real ``facecast serve --redis URL --workers 1`` processes
on loopback (built-in face ``default:2k``, NumPy backend), all on this machine:

- **latency**: ``--sessions`` sessions created on node A at 60 fps, each produced into on A (its
  owner) with generated FAP frames for ``--seconds``, each watched (``--encoding``) on A and on
  another node; producer→viewer latency is the viewer's receipt minus the frame's send time (one
  clock). Reported per side: p50 / p95 / max, frames received per viewer and fps.
- **failover**: ``--rounds`` times: a session on one node, its producer on a second one (it
  reconnects by itself, to the nodes still alive, as the Python client does), a viewer on a
  third; the owner is killed with SIGKILL mid-stream. Reported: seconds from the kill to the
  viewer's first frame of the new owner (``resume_s``) and the viewer's longest gap between two
  frames (``gap_s``); the killed node is started again for the next round.

Machine load (load average, cores) and the CPU each process used during the latency run (the
viewers decode in this one process: with many sessions it is the first to saturate) go into
the JSON. Writes ``bench/out/cluster_failover.json``
and prints a markdown table.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from facecast.client.api import LiveError, SessionAdmin, produce, watch
from facecast.server.harness import LocalServer, RedisServer

OUT = Path(__file__).resolve().parent / "out" / "cluster_failover.json"
FACE = "default:2k"
FPS = 60.0
KEY = "bench-cluster-key"


def fap_vector(i: int) -> np.ndarray:
    v = np.full(68, np.nan, np.float32)
    v[2:] = 150.0 * np.sin(i / 9.0 + np.arange(66) / 7.0)
    return v


def start_node(redis_url: str, root: Path, name: str) -> LocalServer:
    return LocalServer(
        root / name,
        "--face",
        FACE,
        "--backend",
        "numpy",
        "--job-workers",
        "0",
        "--workers",
        "1",
        "--redis",
        redis_url,
        admin_key=KEY,
        env={"FACECAST_MAX_SESSIONS": "256"},
    ).start(ready=True)


def pct(xs: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(xs), q)) if xs else float("nan")


async def stream(url: str, sid: str, token: str, stop: asyncio.Event) -> int:
    sent = 0
    async with produce(url, sid, token) as p:
        t0 = time.monotonic()
        while not stop.is_set():
            await p.send_faps(fap_vector(sent), sent / FPS)
            sent += 1
            await asyncio.sleep(max(0.0, t0 + sent / FPS - time.monotonic()))
    return sent


ENCODING = {"name": "compact"}  # --encoding


async def view(url: str, sid: str, token: str, out: list, stop: asyncio.Event) -> None:
    async with watch(url, sid, token, encoding=ENCODING["name"]) as w:
        async for f in w:
            out.append((f.received, f.latency))
            if stop.is_set():
                return


async def latency(nodes: list[LocalServer], sessions: int, seconds: float) -> dict:
    a, others = nodes[0], nodes[1:]
    async with SessionAdmin(a.url, KEY) as admin:
        made = [await admin.create(face=FACE, fps=FPS) for _ in range(sessions)]
    stop = asyncio.Event()
    local: list[list] = [[] for _ in made]
    remote: list[list] = [[] for _ in made]
    viewers = [
        asyncio.create_task(view(srv.url, s.id, s.viewer_token, out[i], stop))
        for i, s in enumerate(made)
        for srv, out in ((a, local), (others[i % len(others)], remote))
    ]
    await asyncio.sleep(1.0)
    producers = [asyncio.create_task(stream(a.url, s.id, s.producer_token, stop)) for s in made]
    cpu0 = [n.cpu_seconds() for n in nodes] + [time.process_time()]
    await asyncio.sleep(seconds)
    cpu1 = [n.cpu_seconds() for n in nodes] + [time.process_time()]
    stop.set()
    await asyncio.gather(*producers)
    for v in viewers:
        v.cancel()
    await asyncio.gather(*viewers, return_exceptions=True)
    async with SessionAdmin(a.url, KEY) as admin:
        for s in made:
            await admin.close(s.id)

    def side(runs: list[list]) -> dict:
        lat = [1000 * x[1] for r in runs for x in r[10:] if x[1] is not None]  # after warm-up
        fps = [len(r) / seconds for r in runs]
        return {
            "p50_ms": round(pct(lat, 50), 2),
            "p95_ms": round(pct(lat, 95), 2),
            "max_ms": round(max(lat), 2) if lat else None,
            "fps_mean": round(float(np.mean(fps)), 1),
            "frames": int(sum(len(r) for r in runs)),
        }

    busy = [round((b - a) / seconds, 2) for a, b in zip(cpu0, cpu1)]
    return {
        "owner_node_viewers": side(local),
        "other_node_viewers": side(remote),
        "cpu_cores_busy": {"owner": busy[0], "other_nodes": busy[1:-1], "bench_clients": busy[-1]},
    }


async def failover_round(nodes: list[LocalServer], k: int) -> dict:
    n = len(nodes)
    owner, prod, watcher = nodes[k % n], nodes[(k + 1) % n], nodes[(k + 2) % n]
    async with SessionAdmin(owner.url, KEY) as admin:
        s = await admin.create(face=FACE, fps=FPS)
    got: list = []
    stop = asyncio.Event()

    async def producer() -> int:
        reconnects, alive = 0, [x for x in nodes if x is not owner]
        while not stop.is_set():
            try:
                await stream(alive[reconnects % len(alive)].url, s.id, s.producer_token, stop)
            except (LiveError, OSError):
                reconnects += 1
                await asyncio.sleep(0.05)
        return reconnects

    v = asyncio.create_task(view(watcher.url, s.id, s.viewer_token, got, stop))
    p = asyncio.create_task(producer())
    for _ in range(600):
        if len(got) >= 60:
            break
        await asyncio.sleep(0.05)
    await asyncio.get_running_loop().run_in_executor(None, owner.kill)
    killed = time.time()
    for _ in range(1200):
        if sum(r > killed for r, _ in got) >= 60:
            break
        await asyncio.sleep(0.05)
    stop.set()
    reconnects = await p
    v.cancel()
    await asyncio.gather(v, return_exceptions=True)
    times = [r for r, _ in got]
    after = [r for r in times if r > killed]
    gaps = np.diff(times) if len(times) > 1 else np.zeros(1)
    await asyncio.get_running_loop().run_in_executor(None, lambda: owner.start(ready=True))
    async with SessionAdmin(prod.url, KEY) as admin:
        await admin.close(s.id)
    return {
        "resume_s": round(after[0] - killed, 3) if after else None,
        "gap_s": round(float(gaps.max()), 3),
        "producer_reconnects": reconnects,
        "frames_after": len(after),
    }


async def main_async(args: argparse.Namespace, nodes: list[LocalServer]) -> dict:
    lat = await latency(nodes, args.sessions, args.seconds)
    rounds = [await failover_round(nodes, k) for k in range(args.rounds)]
    return {"latency": lat, "failover": rounds}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--nodes", type=int, default=3)
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--sessions", type=int, default=4)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument(
        "--encoding",
        default="compact",
        choices=("compact", "i16", "f32"),
        help="viewers' encoding (the viewers decode in this process: with many sessions, f32 "
        "keeps their decoding from being what is measured)",
    )
    p.add_argument("--out", default=str(OUT))
    args = p.parse_args()
    ENCODING["name"] = args.encoding
    if args.nodes < 3:
        p.error("--nodes must be 3 or more (owner, producer's node, viewer's node)")
    load0 = os.getloadavg()
    redis = RedisServer().start()
    root = Path(tempfile.mkdtemp(prefix="facecast-cluster-bench-"))
    nodes: list[LocalServer] = []
    try:
        nodes = [start_node(redis.url, root, f"n{i}") for i in range(args.nodes)]
        result = asyncio.run(main_async(args, nodes))
    finally:
        for n in nodes:
            n.stop()
        redis.stop()
    result |= {
        "nodes": args.nodes,
        "sessions": args.sessions,
        "seconds": args.seconds,
        "face": FACE,
        "encoding": args.encoding,
        "cores": os.cpu_count(),
        "loadavg_start": load0,
        "loadavg_end": os.getloadavg(),
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    lat = result["latency"]
    print(
        f"| {args.encoding} viewers ({args.sessions} sessions, 60 fps) | p50 ms | p95 ms | max ms "
        "| fps |"
    )
    print("|---|---|---|---|---|")
    for name, side in (
        ("on the owner node", "owner_node_viewers"),
        ("on another node", "other_node_viewers"),
    ):
        r = lat[side]
        print(f"| {name} | {r['p50_ms']} | {r['p95_ms']} | {r['max_ms']} | {r['fps_mean']} |")
    cpu = lat["cpu_cores_busy"]
    print(
        f"\nCPU (cores busy): owner node {cpu['owner']}, other nodes {cpu['other_nodes']}, "
        f"this process (producers and viewers) {cpu['bench_clients']}"
    )
    print()
    print("| failover round | resume after kill -9 (s) | longest gap (s) | producer reconnects |")
    print("|---|---|---|---|")
    for i, r in enumerate(result["failover"]):
        print(f"| {i + 1} | {r['resume_s']} | {r['gap_s']} | {r['producer_reconnects']} |")
    print(
        f"\nload average {load0[0]:.2f} -> {result['loadavg_end'][0]:.2f} on {os.cpu_count()} cores"
    )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
