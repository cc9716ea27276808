"""Batch jobs on one node and on a cluster of nodes sharing Redis, in one run: wall time, load, and
whether every cluster result is the single node's.

Phase **single**: one ``facecast serve`` (SQLite jobs, one job worker, the default), ``--jobs``
jobs submitted at once, waited for. Phase **cluster**: ``--nodes`` node processes with one worker
each, a real ``redis-server`` and one shared ``FACECAST_RESULTS_DIR``; the same jobs submitted
round-robin over the nodes and polled round-robin; once ``--kill-after`` jobs are done, one busy
worker process is killed (SIGKILL), so its job is run again. Every cluster result must be
byte-identical to the single node's result of the same input (the glb of the same input, face,
backend and file names is deterministic); the script exits 1 otherwise.

Inputs: the FAP files of ``<shared data>/xface/faps``, each repeated 1-4 times over (distinct inputs,
0.2-0.9 s of rendering each on the 2k face). Reports wall time per phase, jobs per minute, the speed-up,
attempts (one more than the jobs when the kill landed), the machine's CPU use over each phase
(``/proc/stat``), the CPU seconds of the nodes, their workers and Redis,
and load averages. Writes ``bench/out/cluster_jobs.json`` and prints a table.

    python bench/cluster_jobs.py --jobs 20 --nodes 3
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import signal
import sys
import tempfile
import time
from pathlib import Path

import httpx
from serve import machine_cpu  # bench/serve.py: (busy, total) CPU s of the machine

from facecast.protocol.fap_file import read_fap, write_fap
from facecast.server.harness import (
    LocalServer,
    RedisServer,
    process_cpu_seconds,
    spawned_children,
)
from facecast.server.paths import shared_data

OUT = Path(__file__).resolve().parent / "out"
FACE = "default:2k"
ADMIN_KEY = "bench-cluster-jobs"
DEADLINE = 900.0


def load() -> dict:
    one, five, _ = os.getloadavg()
    return {"loadavg_1m": round(one, 2), "loadavg_5m": round(five, 2), "cpus": os.cpu_count()}


def inputs(n: int) -> list[tuple[str, bytes]]:
    """``n`` distinct FAP inputs: the xface files, each repeated 1, 2, 3, 4 times over."""
    data = shared_data()
    if data is None:
        sys.exit("needs ../shared/data (the xface FAP files)")
    files = sorted((data / "xface" / "faps").glob("*.fap"))
    out = []
    for i in range(n):
        src, repeat = files[i % len(files)], 1 + (i // len(files)) % 4
        fap = read_fap(src.read_text())
        body = write_fap(dataclasses.replace(fap, frames=list(fap.frames) * repeat)).encode()
        out.append((f"{src.stem}-x{repeat}.fap", body))
    return out


def submit(srv: LocalServer, name: str, body: bytes) -> str:
    r = httpx.post(
        srv.url + "/v1/jobs",
        files={"file": (name, body)},
        data={"face": FACE, "format": "glb"},
        headers=srv.admin_headers,
        timeout=120,
    )
    r.raise_for_status()
    return str(r.json()["id"])


def worker_pids(srv: LocalServer) -> list[int]:
    """The job worker processes of a server (its ``spawn``-ed children)."""
    return spawned_children(srv.proc.pid) if srv.proc is not None else []


def run_phase(
    nodes: list[LocalServer],
    jobs: list[tuple[str, bytes]],
    kill_after: int | None,
    broker_pid: int | None = None,
) -> dict:
    """Submit ``jobs`` round-robin, wait for all; kill one busy worker after ``kill_after`` done.
    ``broker_pid``: Redis, whose CPU time counts with the nodes'."""
    busy0, total0 = machine_cpu()
    own = [n.proc.pid for n in nodes if n.proc] + ([broker_pid] if broker_pid else [])
    # per process: the job workers may have started (and spent CPU) before the phase
    cpu0 = {
        pid: process_cpu_seconds(pid) for pid in own + [p for n in nodes for p in worker_pids(n)]
    }
    t0 = time.perf_counter()
    ids = [submit(nodes[i % len(nodes)], name, body) for i, (name, body) in enumerate(jobs)]
    t_submitted = time.perf_counter() - t0
    states: dict[str, dict] = {}
    killed = None
    deadline = time.monotonic() + DEADLINE
    i = 0
    while len([s for s in states.values() if s["status"] in ("done", "failed")]) < len(ids):
        if time.monotonic() > deadline:
            raise SystemExit(f"jobs did not finish in {DEADLINE} s: {states}")
        job_id = ids[i % len(ids)]
        srv = nodes[i % len(nodes)]
        i += 1
        if states.get(job_id, {}).get("status") in ("done", "failed"):
            continue
        states[job_id] = httpx.get(
            f"{srv.url}/v1/jobs/{job_id}", headers=srv.admin_headers, timeout=60
        ).json()
        done = sum(s["status"] == "done" for s in states.values())
        if kill_after is not None and killed is None and done >= kill_after:
            running = [s for s in states.values() if s["status"] == "running"]
            for n in nodes:
                pids = worker_pids(n)
                if pids and running:
                    os.kill(pids[0], signal.SIGKILL)
                    killed = {"node": n.url, "pid": pids[0], "after_done": done}
                    break
        time.sleep(0.02)
    wall = time.perf_counter() - t0
    busy1, total1 = machine_cpu()
    # the nodes', Redis's and the live workers' CPU seconds (a killed worker's are lost)
    own_cpu = sum(
        process_cpu_seconds(pid) - cpu0.get(pid, 0.0)
        for pid in own + [p for n in nodes for p in worker_pids(n)]
    )
    results = {}
    for k, job_id in enumerate(ids):
        srv = nodes[(k + 1) % len(nodes)]  # fetched from another node than the one it was sent to
        r = httpx.get(f"{srv.url}/v1/jobs/{job_id}/result", headers=srv.admin_headers, timeout=120)
        results[job_id] = r.content if r.status_code == 200 else b""
    return {
        "ids": ids,
        "wall_s": round(wall, 2),
        "submit_s": round(t_submitted, 2),
        "jobs_per_min": round(60 * len(ids) / wall, 1),
        "done": sum(s["status"] == "done" for s in states.values()),
        "failed": [s for s in states.values() if s["status"] != "done"],
        "attempts": sum(int(s["attempts"]) for s in states.values()),
        "machine_cpu_busy": round((busy1 - busy0) / max(total1 - total0, 1.0), 3),
        "facecast_cpu_s": round(own_cpu, 1),
        "killed": killed,
        "load_end": load(),
        "_results": results,
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--jobs", type=int, default=20)
    p.add_argument("--nodes", type=int, default=3)
    p.add_argument("--kill-after", type=int, default=5, help="jobs done before a worker is killed")
    p.add_argument("--claim-seconds", type=float, default=5.0)
    args = p.parse_args()
    jobs = inputs(args.jobs)
    report: dict = {"jobs": args.jobs, "nodes": args.nodes, "face": FACE, "load_start": load()}
    with tempfile.TemporaryDirectory(prefix="facecast-bench-jobs-") as tmp:
        root = Path(tmp)
        single = LocalServer(
            root / "single",
            "--face",
            FACE,
            "--backend",
            "numpy",
            env={"FACECAST_JOB_WORKERS": "1"},
            admin_key=ADMIN_KEY,
        )
        with single.start(ready=True):
            report["single"] = run_phase([single], jobs, None)
        with RedisServer() as redis:
            env = {
                "FACECAST_REDIS_URL": redis.url,
                "FACECAST_RESULTS_DIR": str(root / "shared"),
                "FACECAST_JOB_CLAIM_SECONDS": str(args.claim_seconds),
                "FACECAST_JOB_WORKERS": "1",
            }
            nodes = [
                LocalServer(
                    root / f"node{k}",
                    "--face",
                    FACE,
                    "--backend",
                    "numpy",
                    "--workers",
                    "1",  # one process per node: its job worker is its child, killed as such
                    env=env,
                    admin_key=ADMIN_KEY,
                )
                for k in range(args.nodes)
            ]
            try:
                for n in nodes:
                    n.start(ready=True)
                report["cluster"] = run_phase(
                    nodes, jobs, args.kill_after, redis.proc.pid if redis.proc else None
                )
            finally:
                for n in nodes:
                    n.stop()
    one, many = report["single"], report["cluster"]
    same = [
        one["_results"][a] == many["_results"][b] and len(one["_results"][a]) > 0
        for a, b in zip(one["ids"], many["ids"])
    ]
    report["identical"] = sum(same)
    report["identity"] = "byte-identical glb (same input, face, backend and file names)"
    report["speedup"] = round(one["wall_s"] / many["wall_s"], 2)
    for ph in (one, many):
        ph.pop("_results")
        ph.pop("ids")
    OUT.mkdir(exist_ok=True)
    (OUT / "cluster_jobs.json").write_text(json.dumps(report, indent=2))
    print(
        "| phase | nodes | jobs done | attempts | wall s | jobs/min | facecast CPU s "
        "| machine CPU busy | load 1m at end |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for name, ph, n in (("single", one, 1), ("cluster", many, args.nodes)):
        print(
            f"| {name} | {n} | {ph['done']}/{args.jobs} | {ph['attempts']} | {ph['wall_s']} | "
            f"{ph['jobs_per_min']} | {ph['facecast_cpu_s']} | {ph['machine_cpu_busy']:.0%} | "
            f"{ph['load_end']['loadavg_1m']} |"
        )
    print(
        f"\nspeed-up {report['speedup']}x; {report['identical']}/{args.jobs} cluster results "
        f"byte-identical to the single node's; worker killed: {many['killed']}; "
        f"load at start {report['load_start']}"
    )
    ok = report["identical"] == args.jobs and many["done"] == args.jobs and many["killed"]
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
