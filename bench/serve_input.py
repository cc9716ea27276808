"""Server CPU per producer frame, this checkout against another, alternately in one run:
``python bench/serve_input.py --baseline-python PYTHON [options]``.

What the event loop spends on a session's frames apart from deforming them: N sessions, each with
one producer sending FAP frames at ``--fps`` (``bench/serve_load.py``'s cheap generator), and
``--viewers`` viewers each (0 by default: a session nobody watches skips deformation, so the
server's CPU is its input path: WebSocket reads, decoding, budgets, FAP input, queueing). Frames
are counted by the server's ``/metrics`` at the window's two ends. Each
round starts a fresh server of each interpreter in turn (this one, then ``--baseline-python``'s,
e.g. a checkout of main run with its ``PYTHONPATH``), measures ``--seconds`` after ``--warmup``,
and reports server CPU µs per frame sent (``/proc``). Rounds alternate so that a shared machine's
load falls on both alike; the ratio of each round and their median are reported.

Writes ``bench/out/serve_input.json`` and prints a markdown table. Loopback only.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parent))

from facecast.server.harness import LocalServer, process_cpu_seconds

ADMIN_KEY = "bench-serve-input-key"


def _server(python: str, args: argparse.Namespace) -> LocalServer:
    env = {
        "FACECAST_MAX_SESSIONS": "256",
        "FACECAST_MAX_VIEWERS_PER_SESSION": "1024",
        "FACECAST_MAX_PRODUCER_FPS": "1000",
    }
    if args.coalesce_ms is not None:
        env["FACECAST_LIVE_COALESCE_MS"] = f"{args.coalesce_ms:g}"
    return LocalServer(
        None, "--face", args.face, "--job-workers", "0", admin_key=ADMIN_KEY, env=env, python=python
    )


async def _point(server: LocalServer, args: argparse.Namespace) -> dict[str, Any]:
    """One measurement on a running ``server``: sessions made, load generated, CPU read."""
    from serve_load import ProducerSeat, ViewerSeat, run_generator

    from facecast.client.api import SessionAdmin

    async with SessionAdmin(server.url, ADMIN_KEY) as admin:
        made = [await admin.create(face=args.face, fps=args.fps) for _ in range(args.sessions)]
        prods = [ProducerSeat(k, s.id, s.producer_token, server.url) for k, s in enumerate(made)]
        views = [
            ViewerSeat(k * args.viewers + j, s.id, s.viewer_token, server.url)
            for k, s in enumerate(made)
            for j in range(args.viewers)
        ]
        mine, theirs = multiprocessing.get_context("spawn").Pipe()
        proc = multiprocessing.get_context("spawn").Process(
            target=run_generator, daemon=True, args=(prods, views, args.fps, "compact", theirs)
        )
        proc.start()
        try:
            for word in ("ready", "producing"):
                if not await asyncio.to_thread(mine.poll, 180):
                    raise RuntimeError(f"the generator did not say {word!r}")
                got = mine.recv()
                if got != word:
                    raise RuntimeError(f"the generator failed: {got!r}")
                if word == "ready":
                    mine.send("go")
            await asyncio.sleep(args.warmup)
            pid = server.proc.pid if server.proc else 0
            auth = {"Authorization": f"Bearer {ADMIN_KEY}"}
            async with httpx.AsyncClient(timeout=30, headers=auth) as http:
                n0 = await _counters(http, server.url)
                c0, g0, t0 = process_cpu_seconds(pid), process_cpu_seconds(proc.pid), time.time()
                await asyncio.sleep(args.seconds)
                c1, g1, t1 = process_cpu_seconds(pid), process_cpu_seconds(proc.pid), time.time()
                n1 = await _counters(http, server.url)
            mine.send("stop")
            if not await asyncio.to_thread(mine.poll, 60):
                raise RuntimeError("the generator did not report")
            out = mine.recv()
        finally:
            proc.join(10)
            if proc.is_alive():
                proc.kill()
        if "error" in out:
            raise RuntimeError(f"the generator failed: {out['error']}")
        frames_in = n1["facecast_frames_received_total"] - n0["facecast_frames_received_total"]
        deformed = n1["facecast_deform_seconds_count"] - n0["facecast_deform_seconds_count"]
        seconds = t1 - t0
        return {
            "frames_in_per_s": round(frames_in / seconds, 1),
            "deformed_per_s": round(deformed / seconds, 1),
            "server_cpu": round((c1 - c0) / seconds, 3),
            "generator_cpu": round((g1 - g0) / seconds, 3),
            "server_us_per_frame_in": round(1e6 * (c1 - c0) / frames_in, 1) if frames_in else None,
            "loadavg": [round(x, 2) for x in os.getloadavg()],
        }


async def _counters(http: Any, url: str) -> dict[str, float]:
    """The server's Prometheus counters now (``/metrics``: one request, counted at once)."""
    r = await http.get(url + "/metrics")
    r.raise_for_status()
    out = {}
    for line in r.text.splitlines():
        name, _, value = line.partition(" ")
        if name in ("facecast_frames_received_total", "facecast_deform_seconds_count"):
            out[name] = float(value)
    return out


def _measure(python: str, args: argparse.Namespace) -> dict[str, Any]:
    server = _server(python, args)
    try:
        server.start(300, ready=True)
        return asyncio.run(_point(server, args))
    finally:
        server.stop()


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--baseline-python", required=True, help="the other checkout's interpreter")
    p.add_argument("--face", default="default")
    p.add_argument("--sessions", type=int, default=60)
    p.add_argument("--viewers", type=int, default=0, help="viewers per session (default 0)")
    p.add_argument("--fps", type=float, default=60.0)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--warmup", type=float, default=2.0)
    p.add_argument("--seconds", type=float, default=8.0)
    p.add_argument("--coalesce-ms", type=float, default=None)
    p.add_argument("--out", type=Path, default=Path("bench/out/serve_input.json"))
    args = p.parse_args()
    load0 = os.getloadavg()
    rounds = []
    for r in range(args.rounds):
        this = _measure(sys.executable, args)
        base = _measure(args.baseline_python, args)
        a, b = this["server_us_per_frame_in"], base["server_us_per_frame_in"]
        rounds.append(
            {"this": this, "baseline": base, "ratio": round(a / b, 3) if a and b else None}
        )
        print(f"round {r + 1}: this {this} / baseline {base}", flush=True)
    ratios = [x["ratio"] for x in rounds if x["ratio"]]
    report = {
        "bench": "serve_input",
        "args": {k: str(v) for k, v in vars(args).items()},
        "rounds": rounds,
        "ratio_median": statistics.median(ratios) if ratios else None,
        "loadavg_before": load0,
        "loadavg_after": os.getloadavg(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1))
    print(
        f"\n{args.sessions} sessions x {args.viewers} viewers, producers at {args.fps:g} fps\n\n"
        "| round | µs/frame in: this | baseline | ratio | server CPU this / baseline | "
        "deformed/s this / baseline | load |\n|---|---|---|---|---|---|---|"
    )
    for i, x in enumerate(rounds, 1):
        t, b = x["this"], x["baseline"]
        print(
            f"| {i} | {t['server_us_per_frame_in']} | {b['server_us_per_frame_in']} | "
            f"{x['ratio']} | {t['server_cpu']} / {b['server_cpu']} | "
            f"{t['deformed_per_s']} / {b['deformed_per_s']} | {b['loadavg'][0]} |"
        )
    print(
        f"\nmedian ratio {report['ratio_median']}; load {load0[0]:.2f} -> {os.getloadavg()[0]:.2f}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
