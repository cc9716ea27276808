"""CPU a node spends per frame crossing Redis: ``python bench/cluster_pubsub_cost.py``.

A frame watched on another node than its owner is published by the owner and read by the other
node, each through the ``redis`` Python client. This measures the client side of that, per
message, for the ways a node has done it, in one run against a real ``redis-server``: the owner's
``Publisher`` (a pipeline of ``PUBLISH``, or one Lua script call per batch: ``PUBLISH_MANY``) and
the other node's reader (``get_message`` with a 0.5 s timeout, or blocking), with the client's
pure-Python reply parser or ``hiredis``. Publisher and subscriber run in one process, so each
number is the sum of both sides (what a pair of nodes spends per crossing frame). Messages are
``--size`` bytes (a 25k-vertex ``compact`` frame is ~3,600), in batches of ``--batch`` (the
frames of one deformation batch), over 20 session channels.

Writes ``bench/out/cluster_pubsub_cost.json`` and prints a table.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

CHANNELS = 20


async def _one(url: str, *, publish: str, read: str, parser: Any, n: int, size: int, batch: int):
    """CPU µs per message (publish + receive) and messages a second, for one way of doing it."""
    import redis.asyncio as aioredis

    from facecast.server.cluster.publisher import CHUNK, PUBLISH_MANY

    pub = aioredis.Redis.from_url(url, parser_class=parser)
    sub = aioredis.Redis.from_url(url, parser_class=parser)
    ps = sub.pubsub()
    names = [f"facecast:down:bench{k}" for k in range(CHANNELS)]
    await ps.subscribe(*names)
    script = pub.register_script(PUBLISH_MANY)
    data = b"F" + os.urandom(size - 1)
    got = 0
    done = asyncio.Event()

    async def reader() -> None:
        nonlocal got
        timeout = 0.5 if read == "timeout" else None
        while got < n:
            msg = await ps.get_message(ignore_subscribe_messages=True, timeout=timeout)
            if msg is not None and msg["type"] == "message":
                got += 1
        done.set()

    task = asyncio.create_task(reader())
    c0, t0 = time.process_time(), time.perf_counter()
    for at in range(0, n, batch):
        msgs = [(names[(at + j) % CHANNELS], data) for j in range(min(batch, n - at))]
        if publish == "pipeline":
            pipe = pub.pipeline(transaction=False)
            for channel, body in msgs:
                pipe.publish(channel, body)
            await pipe.execute()
        else:
            for k in range(0, len(msgs), CHUNK):
                await script(args=[x for pair in msgs[k : k + CHUNK] for x in pair])
        # keep the reader close behind, as a real pair of nodes is (yield to it)
        while got < at - 4 * batch:  # noqa: ASYNC110
            await asyncio.sleep(0)
    await asyncio.wait_for(done.wait(), 60)
    c1, t1 = time.process_time(), time.perf_counter()
    await task
    await ps.aclose()
    await pub.aclose()
    await sub.aclose()
    return 1e6 * (c1 - c0) / n, n / (t1 - t0)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--messages", type=int, default=20000, help="messages per way and repeat")
    p.add_argument("--size", type=int, default=3600, help="bytes per message")
    p.add_argument("--batch", type=int, default=20, help="messages published together")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", type=Path, default=Path("bench/out/cluster_pubsub_cost.json"))
    args = p.parse_args(argv)

    from redis._parsers import _AsyncHiredisParser, _AsyncRESP2Parser
    from redis.utils import HIREDIS_AVAILABLE

    from facecast.server.harness import RedisServer

    if not RedisServer.available():
        print("redis-server is not installed (bash .ci/setup installs it)", file=sys.stderr)
        return 2
    parsers = {"python": _AsyncRESP2Parser}
    if HIREDIS_AVAILABLE:
        parsers["hiredis"] = _AsyncHiredisParser
    ways = [
        (publish, read, parser)
        for parser in parsers
        for publish, read in (("pipeline", "timeout"), ("script", "blocking"))
    ]
    load_before = os.getloadavg()
    rows: dict[tuple[str, str, str], list[tuple[float, float]]] = {w: [] for w in ways}
    redis = RedisServer().start()
    try:
        for _ in range(args.repeats):  # interleaved: each way meets the machine's load alike
            for publish, read, parser in ways:
                rows[(publish, read, parser)].append(
                    asyncio.run(
                        _one(
                            redis.url,
                            publish=publish,
                            read=read,
                            parser=parsers[parser],
                            n=args.messages,
                            size=args.size,
                            batch=args.batch,
                        )
                    )
                )
    finally:
        redis.stop()
    load = os.getloadavg()
    out = {
        "bench": "cluster_pubsub_cost",
        "messages": args.messages,
        "size": args.size,
        "batch": args.batch,
        "results": [
            {
                "publish": w[0],
                "read": w[1],
                "parser": w[2],
                "cpu_us_per_message": [round(c, 1) for c, _ in rows[w]],
                "messages_per_s": [round(r) for _, r in rows[w]],
            }
            for w in ways
        ],
        "cpus": os.cpu_count(),
        "loadavg_before": [round(x, 2) for x in load_before],
        "loadavg_after": [round(x, 2) for x in load],
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2))
    print(
        f"## Client CPU per frame crossing Redis (publish + receive, {args.size} B, "
        f"batches of {args.batch})\n"
    )
    print("| publish | read | parser | CPU µs per message (each repeat) | median |")
    print("|---|---|---|---|---|")
    for r in out["results"]:
        cs = sorted(r["cpu_us_per_message"])
        print(
            f"| {r['publish']} | {r['read']} | {r['parser']} | "
            f"{', '.join(f'{c:g}' for c in r['cpu_us_per_message'])} | {cs[len(cs) // 2]:g} |"
        )
    print(
        f"\nLoad average before/after: {load_before[0]:.2f}/{load[0]:.2f} on {os.cpu_count()} "
        f"CPUs. JSON: {args.out}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
