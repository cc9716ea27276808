"""A flooding producer against a healthy session: does the victim keep its frame rate?

Starts a real ``facecast serve`` on a free loopback port (server defaults: 250 frames/s per
producer, ``--face`` default the 25k-vertex ``default``), then three phases of ``--seconds`` each:

- **baseline**: the victim session alone: a producer sending FAP frames at 60 fps (real time) and
  one viewer (int16 frames) measuring frames per second and end-to-end latency (viewer receive
  wall time minus the producer's send wall time carried in each frame);
- **control**: the same, while a niced process burns one CPU without talking to the server (this
  machine is shared: it tells what the flooder's own CPU use costs the victim, server aside);
- **flood**: the same, while a second session's producer (in its own niced process) sends FAP
  frames (binary, or JSON with ``--json``) as fast as it can, reconnecting whenever the server
  closes it.

The three phases repeat ``--rounds`` times, interleaved; each number is the median over rounds.
Reports the victim's fps and latency p50/p95 in each phase, the flood's messages per second (sent
by the client; ``flood_msgs_per_s_open`` counts only time the flooder was connected), how the server
ended the flooding connections (close codes), server CPU seconds per second, and the machine's load.
Writes ``bench/out/flood.json`` and prints a markdown table.

    python bench/flood.py --seconds 10
    from flood import run_flood; run_flood(10)   # from another script in bench/
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing
import os
import sys
import time
from pathlib import Path

#: The flooded server's admin key (a server of its own, on loopback).
ADMIN_KEY = "bench-flood-key"

OUT = Path(__file__).resolve().parent / "out"
VICTIM_FPS = 60.0


def _load() -> dict:
    one, five, _ = os.getloadavg()
    return {"loadavg_1m": round(one, 2), "loadavg_5m": round(five, 2), "cpus": os.cpu_count()}


async def _victim(url: str, admin_key: str, seconds: float, face: str) -> dict:
    """Stream 60 fps FAP frames into a fresh session for ``seconds`` while one viewer measures."""
    from facecast.client.api import LiveError, SessionAdmin, produce, summary, watch

    async with SessionAdmin(url, admin_key) as admin:
        s = await admin.create(face=face, fps=VICTIM_FPS)
    got = []
    ready = asyncio.Event()
    stop = asyncio.Event()

    async def viewer() -> None:
        async with watch(url, s.id, s.viewer_token, encoding="i16") as w:
            ready.set()
            async for f in w:
                got.append(f)
                if stop.is_set():
                    return

    task = asyncio.create_task(viewer())
    await asyncio.wait_for(ready.wait(), 60)
    async with produce(url, s.id, s.producer_token) as p:
        t0 = time.monotonic()
        i = 0
        while time.monotonic() - t0 < seconds:
            await p.send_faps({3: 200.0 * ((i % 60) / 60), 19: 50.0}, i / VICTIM_FPS)
            i += 1
            delay = t0 + i / VICTIM_FPS - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
        sent = i
    stop.set()
    try:
        await asyncio.wait_for(task, 5)
    except (asyncio.TimeoutError, LiveError):  # the viewer is stopped either way
        task.cancel()
    async with SessionAdmin(url, admin_key) as admin:
        await admin.close(s.id)
    # the first second is the pipeline filling; measure the steady part
    steady = [f for f in got if f.received - got[0].received >= 1.0] if got else []
    out = summary(steady)
    return {
        "frames_sent": sent,
        "frames_received": len(got),
        "fps": out.get("fps"),
        "p50_ms": out.get("latency_ms_p50"),
        "p95_ms": out.get("latency_ms_p95"),
        "max_ms": out.get("latency_ms_max"),
        "dropped": out.get("dropped"),
    }


def _burner(stop, nice: int = 10) -> None:
    """Child process: burn one CPU (niced like the flooder) until ``stop`` is set."""
    os.nice(nice)
    while not stop.is_set():
        sum(range(10_000))


def _flooder(
    url: str,
    session: str,
    token: str,
    json_frames: bool,
    stop,
    conn,
    query_token: bool = False,
    nice: int = 10,
) -> None:
    """Child process: flood ``session`` with FAP frames until ``stop`` is set; reports via ``conn``.
    Niced: on a real attack the flooder's CPU is not the server's (here they share the machine)."""
    os.nice(nice)
    asyncio.run(_flood(url, session, token, json_frames, stop, conn, query_token))


async def _flood(
    url: str, session: str, token: str, json_frames: bool, stop, conn, query_token: bool
) -> None:
    import numpy as np
    from websockets.asyncio.client import connect
    from websockets.exceptions import ConnectionClosed, InvalidHandshake

    from facecast.client.api import ws_url
    from facecast.protocol import frames
    from facecast.protocol.messages import FapMessage, ProducerHello, dump_message

    if json_frames:
        msg: bytes | str = dump_message(FapMessage(seq=1, t=0.0, wall=time.time(), faps={3: 100.0}))
    else:
        msg = frames.encode_faps(np.zeros(68, np.float32), seq=1, t=0.0, wall=time.time())
    sent = connections = 0
    open_seconds = 0.0
    codes: dict[str, int] = {}
    target = ws_url(url, f"/v1/sessions/{session}/produce", token=token if query_token else None)
    while not stop.is_set():
        try:
            ws = await connect(
                target,
                additional_headers={"Authorization": f"Bearer {token}"},
                compression=None,
                ping_interval=None,
                open_timeout=10,
            )
        except (OSError, asyncio.TimeoutError, InvalidHandshake):  # the server is busy: again
            await asyncio.sleep(0.05)
            continue
        connections += 1
        t_open = time.monotonic()
        try:
            await ws.send(dump_message(ProducerHello()))
            await ws.recv()  # ready (or an error: the previous connection still holds the slot)
            while not stop.is_set():
                for _ in range(64):
                    await ws.send(msg)
                sent += 64
                await asyncio.sleep(0)  # let the connection read (a close frame, say)
        except ConnectionClosed:
            pass
        finally:
            open_seconds += time.monotonic() - t_open
            await ws.close()
            code = str(ws.close_code)
            codes[code] = codes.get(code, 0) + 1
    conn.send(
        {
            "sent": sent,
            "connections": connections,
            "open_seconds": open_seconds,
            "close_codes": codes,
        }
    )


def _median_phase(runs: list[dict]) -> dict:
    """Per-field medians of several runs of one phase (the machine is shared: phases are noisy)."""
    import statistics

    out = {}
    for k in runs[0]:
        vals = [r[k] for r in runs if r.get(k) is not None]
        out[k] = round(statistics.median(vals), 2) if vals else None
    out["rounds"] = runs
    return out


def run_flood(
    seconds: int = 10,
    *,
    rounds: int = 3,
    face: str = "default",
    backend: str = "auto",
    json_frames: bool = False,
    query_token: bool = False,
    nice: int = 10,
) -> dict:
    """Against a fresh server, ``rounds`` rounds of three ``seconds``-long phases (baseline, control,
    flood); per phase the median over rounds. The numbers as a dict (``fps_victim``,
    ``p95_ms_victim``, ``flood_msgs_per_s``, ``baseline``, ``control``, ``flood``, ``load``, ...).
    ``query_token``: the flooder sends its token as ``?token=`` (to measure servers older than
    header tokens the same way); ``nice``: of the flooder and the control's CPU burner."""
    import httpx

    from facecast.server.harness import LocalServer

    ctx = multiprocessing.get_context("spawn")
    phases: dict[str, list[dict]] = {"baseline": [], "control": [], "flood": []}
    floods, loads, cpu = [], [], []
    server = LocalServer(
        None,
        "--face",
        face,
        "--backend",
        backend,
        "--job-workers",
        "0",
        admin_key=ADMIN_KEY,
        env={"FACECAST_MAX_SESSIONS": "256", "FACECAST_MAX_PRODUCER_FPS": "250"},
    )
    try:
        server.start(300, ready=True)
        url = server.url
        for _ in range(rounds):
            loads.append(_load())
            phases["baseline"].append(asyncio.run(_victim(url, ADMIN_KEY, seconds, face)))
            stop = ctx.Event()
            burner = ctx.Process(target=_burner, args=(stop, nice))
            burner.start()
            phases["control"].append(asyncio.run(_victim(url, ADMIN_KEY, seconds, face)))
            stop.set()
            burner.join(10)
            attacker = httpx.post(
                url + "/v1/sessions",
                json={"face": face},
                headers={"Authorization": f"Bearer {ADMIN_KEY}"},
                timeout=120,
            ).json()
            stop = ctx.Event()
            parent, child = ctx.Pipe()
            proc = ctx.Process(
                target=_flooder,
                args=(
                    url,
                    attacker["id"],
                    attacker["producer_token"],
                    json_frames,
                    stop,
                    child,
                    query_token,
                    nice,
                ),
            )
            cpu0, t0 = server.cpu_seconds(), time.monotonic()
            proc.start()
            time.sleep(0.5)  # the flood is on before the victim starts
            phases["flood"].append(asyncio.run(_victim(url, ADMIN_KEY, seconds, face)))
            stop.set()
            flood = parent.recv() if parent.poll(30) else {}
            proc.join(10)
            wall = time.monotonic() - t0
            cpu.append((server.cpu_seconds() - cpu0) / wall)
            floods.append({**flood, "seconds": wall})
            httpx.delete(
                f"{url}/v1/sessions/{attacker['id']}",
                headers={"Authorization": f"Bearer {ADMIN_KEY}"},
                timeout=30,
            )
        healthy = httpx.get(url + "/healthz", timeout=5).status_code == 200
        metrics = httpx.get(url + "/metrics", timeout=5).text
    finally:
        server.stop()
    refused = {
        line.split("{")[1].split("}")[0]: float(line.rsplit(" ", 1)[1])
        for line in metrics.splitlines()
        if line.startswith("facecast_live_messages_refused_total{")
    }
    base, control, flooded = (_median_phase(phases[k]) for k in ("baseline", "control", "flood"))
    sent = sum(f.get("sent", 0) for f in floods)
    codes: dict[str, int] = {}
    for f in floods:
        for k, v in (f.get("close_codes") or {}).items():
            codes[k] = codes.get(k, 0) + v
    return {
        "face": face,
        "backend": backend,
        "seconds": seconds,
        "rounds": rounds,
        "flood_kind": "json" if json_frames else "binary",
        "flooder_nice": nice,
        "fps_victim": flooded["fps"],
        "p50_ms_victim": flooded["p50_ms"],
        "p95_ms_victim": flooded["p95_ms"],
        "flood_msgs_per_s": round(sent / sum(f["seconds"] for f in floods), 1),
        "flood_msgs_per_s_open": round(
            sent / max(sum(f.get("open_seconds", 0) for f in floods), 1e-9), 1
        ),
        "flood_connections": sum(f.get("connections", 0) for f in floods),
        "flood_close_codes": codes,
        "server_refused": refused,
        "server_cpu_per_s": round(sorted(cpu)[len(cpu) // 2], 3),
        "healthz_after": healthy,
        "baseline": base,
        "control": control,
        "flood": flooded,
        "load": {
            "loadavg_1m": round(sum(x["loadavg_1m"] for x in loads) / len(loads), 2),
            "cpus": os.cpu_count(),
            "rounds": loads,
        },
        "ok": bool(
            flooded["fps"]
            and flooded["fps"] >= 57
            and flooded["p95_ms"] is not None
            and flooded["p95_ms"] <= 50
        ),
    }


def _table(r: dict) -> str:
    b, c, f = r["baseline"], r["control"], r["flood"]
    rows = [
        (f"victim {k}", b[key], c[key], f[key])
        for k, key in (
            ("fps", "fps"),
            ("latency p50 (ms)", "p50_ms"),
            ("latency p95 (ms)", "p95_ms"),
            ("latency max (ms)", "max_ms"),
            ("frames dropped", "dropped"),
        )
    ]
    rows += [
        (
            "flood messages/s (sent; while connected)",
            "-",
            "-",
            f"{r['flood_msgs_per_s']}; {r['flood_msgs_per_s_open']}",
        ),
        (
            "flood connections (close codes)",
            "-",
            "-",
            f"{r['flood_connections']} {r['flood_close_codes']}",
        ),
        ("server CPU s/s (flood phase)", "-", "-", r["server_cpu_per_s"]),
    ]
    head = (
        f"flood ({r['flood_kind']} FAP frames), face {r['face']}, {r['seconds']} s per phase, "
        f"median of {r['rounds']} rounds, flooder nice {r['flooder_nice']}, mean load {r['load']['loadavg_1m']} on "
        f"{r['load']['cpus']} CPUs; target: victim >= 57 fps, "
        f"p95 <= 50 ms: {'met' if r['ok'] else 'NOT met'}"
    )
    return "\n".join(
        [head, "", "| | baseline | control (CPU burner) | flood |", "|---|---|---|---|"]
        + ["| " + " | ".join(str(x) for x in row) + " |" for row in rows]
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=int, default=10, help="seconds per phase (default 10)")
    p.add_argument("--rounds", type=int, default=3, help="rounds of the three phases (default 3)")
    p.add_argument("--face", default="default", help="face of both sessions (default: default)")
    p.add_argument("--backend", default="auto", choices=("auto", "numpy", "opencl"))
    p.add_argument("--json", action="store_true", help="flood with JSON 'fap' messages")
    p.add_argument(
        "--query-token",
        action="store_true",
        help="the flooder sends ?token= (to measure a server from before header tokens)",
    )
    p.add_argument(
        "--nice", type=int, default=10, help="niceness of the flooder and CPU burner (default 10)"
    )
    p.add_argument("--out", default=None, help="JSON file name in bench/out (default flood.json)")
    args = p.parse_args(argv)
    r = run_flood(
        args.seconds,
        rounds=args.rounds,
        face=args.face,
        backend=args.backend,
        json_frames=args.json,
        query_token=args.query_token,
        nice=args.nice,
    )
    OUT.mkdir(exist_ok=True)
    name = args.out or ("flood-json.json" if args.json else "flood.json")
    (OUT / name).write_text(json.dumps(r, indent=2))
    print(_table(r))
    return 0


if __name__ == "__main__":
    sys.exit(main())
