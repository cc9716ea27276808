"""What Redis pub/sub sustains for facecast's frames on this machine: ``python bench/redis_pubsub.py``.

A cluster node publishes each encoded frame of a session it owns once, on the session's channel;
Redis delivers it to every other node with viewers of that session (one subscription per session
per node). So Redis carries, per second, ``sessions x fps`` messages in and ``sessions x fps x
subscriber nodes`` out, each a frame: compact (~4-5 KB for the 25k-vertex head), int16
(``56 + 6 x vertices``: 149 KB for 25k, 12 KB for 2k), or a small compact 2k frame.

Starts a real ``redis-server`` (``facecast.server.harness.RedisServer``), then for each frame size
and subscriber count: ``--publishers`` processes publish as fast as Redis answers (pipelines of
``--pipeline`` PUBLISH commands, prebuilt RESP, over many session channels, as the node's
publisher does), ``S`` subscriber processes (PSUBSCRIBE to every session channel) read what is
delivered. Both sides are raw sockets that do not parse payloads, so the numbers are Redis's and
the loopback's, not a Python client's. Reports messages/s and MB/s in and out, Redis's CPU, and
what that means: sessions at 60 fps one Redis carries for that fan-out.

Writes ``bench/out/redis_pubsub.json`` and prints a markdown table. Loopback only.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import socket
import sys
import time
from pathlib import Path

from facecast.server.harness import RedisServer, process_cpu_seconds

#: Frame sizes, bytes: (name, size).
SIZES = {
    "compact-2k": 1_200,
    "compact-25k": 4_600,
    "i16-2k": 56 + 6 * 1968,
    "i16-25k": 56 + 6 * 24848,
}
CHANNELS = 64  #: session channels the publishers spread over


def _resp(*parts: bytes) -> bytes:
    out = [b"*%d\r\n" % len(parts)]
    for p in parts:
        out += [b"$%d\r\n" % len(p), p, b"\r\n"]
    return b"".join(out)


def _channel(i: int) -> bytes:
    return b"facecast:bench:%04d" % (i % CHANNELS)


def _publisher(port: int, size: int, pipeline: int, seconds: float, start, out) -> None:
    """Publish pipelines of ``pipeline`` frames of ``size`` bytes for ``seconds``; put the count."""
    payload = os.urandom(size)
    batch = b"".join(_resp(b"PUBLISH", _channel(i), payload) for i in range(pipeline))
    s = socket.create_connection(("127.0.0.1", port))
    start.wait()
    n, t_end = 0, time.monotonic() + seconds
    while time.monotonic() < t_end:
        s.sendall(batch)
        lines = 0
        while lines < pipeline:  # one ":<receivers>\r\n" per PUBLISH
            lines += s.recv(65536).count(b"\r\n")
        n += pipeline
    s.close()
    out.put(("pub", n, False))


def _subscriber(port: int, seconds: float, ready, start, out) -> None:
    """PSUBSCRIBE to the session channels; count bytes delivered during the publishers' window."""
    s = socket.create_connection(("127.0.0.1", port))
    s.sendall(_resp(b"PSUBSCRIBE", b"facecast:bench:*"))
    s.recv(4096)  # the subscription's confirmation
    s.settimeout(0.2)
    ready.set()
    start.wait()
    buf = bytearray(1 << 20)
    got, dropped, t_end = 0, False, time.monotonic() + seconds
    while time.monotonic() < t_end:
        try:
            n = s.recv_into(buf)
        except TimeoutError:
            continue
        if n == 0:  # Redis closed a subscriber that fell behind (client-output-buffer-limit)
            dropped = True
            break
        got += n
    s.close()
    out.put(("sub", got, dropped))


def point(redis: RedisServer, size: int, subscribers: int, args) -> dict:
    mp = multiprocessing.get_context("fork")
    start, out = mp.Event(), mp.Queue()
    readies = [mp.Event() for _ in range(subscribers)]
    procs = [
        mp.Process(target=_subscriber, args=(redis.port, args.seconds, r, start, out))
        for r in readies
    ]
    procs += [
        mp.Process(
            target=_publisher, args=(redis.port, size, args.pipeline, args.seconds, start, out)
        )
        for _ in range(args.publishers)
    ]
    for p in procs:
        p.start()
    for r in readies:
        r.wait(30)
    assert redis.proc is not None
    cpu0, t0 = process_cpu_seconds(redis.proc.pid), time.monotonic()
    start.set()
    results = [out.get(timeout=args.seconds + 60) for _ in procs]
    cpu1, t1 = process_cpu_seconds(redis.proc.pid), time.monotonic()
    for p in procs:
        p.join(10)
    window = min(args.seconds, t1 - t0)
    published = sum(n for kind, n, _ in results if kind == "pub")
    delivered_bytes = sum(n for kind, n, _ in results if kind == "sub")
    cut_off = sum(d for kind, _, d in results if kind == "sub")
    # a delivered message: "*4 pmessage <pattern> <channel> <payload>" in RESP
    per = len(_resp(b"pmessage", b"facecast:bench:*", _channel(0), b"x" * size))
    pub_rate = published / window
    cpu = (cpu1 - cpu0) / (t1 - t0)
    delivered = delivered_bytes / per / window
    return {
        "frame_bytes": size,
        "subscribers": subscribers,
        "published_per_s": round(pub_rate),
        "delivered_per_s": round(delivered),
        "mb_in_per_s": round(pub_rate * size / 1e6, 1),
        "mb_out_per_s": round(delivered_bytes / window / 1e6, 1),
        "redis_cpu": round(cpu, 2),
        # Redis CPU per message in plus its deliveries: robust to a shared machine's load, where
        # rates are not; one core of Redis carries about 1e6 / this messages (with fan-out) a second
        "redis_us_per_published": round(1e6 * cpu / pub_rate, 2) if pub_rate else None,
        "redis_gb_out_per_cpu_s": round(delivered_bytes / window / 1e9 / cpu, 2) if cpu else None,
        "subscribers_cut_off": cut_off,
        # sessions at 60 fps this Redis carries when each frame goes to `subscribers` other nodes
        # (what was delivered: a subscriber cut off for falling behind got nothing more)
        "sessions_at_60fps": int(min(pub_rate, delivered / subscribers) / 60),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench/redis_pubsub.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", default=",".join(SIZES), help=f"frame kinds: {', '.join(SIZES)}")
    p.add_argument("--subscribers", default="1,2,4", help="subscriber nodes per point")
    p.add_argument("--publishers", type=int, default=1, help="publishing processes (nodes)")
    p.add_argument("--pipeline", type=int, default=16, help="PUBLISH commands per round trip")
    p.add_argument("--seconds", type=float, default=3.0, help="seconds per point")
    p.add_argument("--out", type=Path, default=Path("bench/out/redis_pubsub.json"))
    args = p.parse_args(argv)
    load0 = os.getloadavg()
    points = []
    with RedisServer() as redis:
        for name in args.sizes.split(","):
            for subs in (int(x) for x in args.subscribers.split(",")):
                r = {"frame": name, **point(redis, SIZES[name], subs, args)}
                print(json.dumps(r), file=sys.stderr)
                points.append(r)
    load1 = os.getloadavg()
    report = {
        "bench": "redis_pubsub",
        "redis": "redis-server (Debian), loopback, no persistence",
        "publishers": args.publishers,
        "pipeline": args.pipeline,
        "points": points,
        "cpus": os.cpu_count(),
        "loadavg_before": [round(x, 2) for x in load0],
        "loadavg_after": [round(x, 2) for x in load1],
        "note": "publishers, subscribers and Redis share this machine's CPUs",
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2))
    print(
        "| frame | bytes | subscriber nodes | published/s | delivered/s | MB/s in | MB/s out "
        "| Redis CPU | Redis µs/published | GB out per Redis CPU-s | subscribers cut off "
        "| sessions at 60 fps |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in points:
        print(
            f"| {r['frame']} | {r['frame_bytes']} | {r['subscribers']} | {r['published_per_s']} "
            f"| {r['delivered_per_s']} | {r['mb_in_per_s']} | {r['mb_out_per_s']} "
            f"| {r['redis_cpu']} | {r['redis_us_per_published']} | {r['redis_gb_out_per_cpu_s']} "
            f"| {r['subscribers_cut_off']} | {r['sessions_at_60fps']} |"
        )
    print(
        f"\nLoad average before/after: {load0[0]:.2f}/{load1[0]:.2f} on {os.cpu_count()} CPUs. "
        f"JSON: {args.out}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
