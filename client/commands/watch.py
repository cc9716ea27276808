"""``facecast watch --url URL --session ID --token T``: subscribe to a live session and report.

Reports frames per second, end-to-end latency p50/p95 (viewer receive time minus the producer's
send time carried in each frame; both clocks must agree, e.g. the same machine), bytes per frame
and bits per second, dropped frames (gaps in the frame numbers) and the longest time between two
frames (``max_gap_s``: a node going away, a failover). Stops after ``--frames`` or ``--seconds``,
or when the producer leaves (after frames were seen). ``--json`` prints one JSON object at the end.
When its connection drops, the viewer reconnects by itself (``--reconnect-for``).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import time

from ...protocol.encoding import VERTEX_ENCODINGS
from . import add_reconnect_argument, add_session_arguments, until_signal


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_session_arguments(p, "viewer")
    p.add_argument(
        "--encoding",
        choices=VERTEX_ENCODINGS,
        default="compact",
        help="vertex encoding (default compact: within the session's tolerance, a few %% of i16)",
    )
    p.add_argument(
        "--save",
        metavar="OUT.npz",
        help="write the decoded frames: seq, t (s), vertices (frames, V, 3) face units",
    )
    stop = p.add_mutually_exclusive_group()
    stop.add_argument("--frames", type=int, help="stop after this many frames")
    stop.add_argument("--seconds", type=float, help="stop after this many seconds")
    p.add_argument(
        "--json", action="store_true", help="print one JSON object at the end (else a short table)"
    )
    add_reconnect_argument(p)


async def _main(args: argparse.Namespace) -> dict:
    from ..api import Retry, WatchedFrame, summary, watch

    got: list[WatchedFrame] = []
    deadline = None if args.seconds is None else time.monotonic() + args.seconds
    until_end = args.frames is None and args.seconds is None
    retry = Retry(give_up=args.reconnect_for) if args.reconnect_for > 0 else None
    async with watch(
        args.url,
        args.session,
        args.token,
        encoding=args.encoding,
        until_producer_leaves=until_end,
        retry=retry,
    ) as w:
        hello = w.hello

        async def consume() -> None:
            async for f in w:
                got.append(f)
                if args.frames is not None and len(got) >= args.frames:
                    return

        try:
            if deadline is None:
                interrupted = await until_signal(consume())
            else:
                timeout = max(0.0, deadline - time.monotonic())
                interrupted = await until_signal(asyncio.wait_for(consume(), timeout))
        except asyncio.TimeoutError:
            interrupted = False
        stats = w.stats
        waited = w.waited
        reconnects, outages = w.reconnects, w.outages
    report = summary(got)
    report["interrupted"] = interrupted
    report["reconnects"] = reconnects
    report["max_outage_s"] = round(max(outages), 3) if outages else 0.0
    if args.encoding == "compact":
        report["frames_waiting_for_key"] = waited
    if args.save:
        report["saved"] = _save(args.save, got)
    report.update(
        {
            "session": hello.session,
            "face": hello.face,
            "vertex_count": hello.vertex_count,
            "encoding": hello.encoding,
        }
    )
    if stats is not None:
        report["server"] = stats.model_dump(exclude={"type"})
    return report


def _save(path: str, got: list) -> str:
    """Write ``seq (n,) u32``, ``t (n,) f64`` and ``vertices (n, V, 3) f32`` to ``path`` atomically."""
    import numpy as np

    from ..files import atomic_path

    out = path if path.endswith(".npz") else path + ".npz"
    V = got[0].positions().shape[0] if got else 0
    with atomic_path(out) as tmp, open(tmp, "wb") as fh:
        np.savez(
            fh,
            seq=np.array([f.frame.header.seq for f in got], np.uint32),
            t=np.array([f.frame.header.t for f in got], np.float64),
            vertices=np.stack([f.positions() for f in got])
            if got
            else np.zeros((0, V, 3), np.float32),
        )
    return out


def _table(r: dict) -> str:
    rows = [
        ("frames", r.get("frames")),
        ("fps", r.get("fps")),
        ("latency p50 (ms)", r.get("latency_ms_p50")),
        ("latency p95 (ms)", r.get("latency_ms_p95")),
        ("bytes/frame", r.get("bytes_per_frame")),
        ("bits/s", r.get("bits_per_second")),
        ("dropped", r.get("dropped")),
        ("longest gap (s)", r.get("max_gap_s")),
        ("reconnects", r.get("reconnects")),
        ("encoding", r.get("encoding")),
        ("vertices", r.get("vertex_count")),
    ]
    return "\n".join(["| metric | value |", "|---|---|"] + [f"| {k} | {v} |" for k, v in rows])


def run(args: argparse.Namespace) -> int:
    import logging

    from ..api import LiveError

    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per request is noise here

    try:
        report = asyncio.run(_main(args))
    except LiveError as e:
        print(f"facecast: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    print(json.dumps(report) if args.json else _table(report))
    return 0
