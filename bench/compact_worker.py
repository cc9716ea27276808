"""The live worker's whole job per session-frame, ``compact`` against ``i16``, in one process:

    python bench/compact_worker.py [--batches 1,2,3,4,6,8,12] [--rounds 5] [--frames 60]

What ``bench/serve.py --encoding i16,compact`` compares, without the network and its noise: the
batcher's job (``DeformBatcher._work``: solve, deform, encode; the compact frames' deflate on the
compact pool, as the server runs them) on ``bench/serve_load.py``'s FAP frames, ``n`` sessions a
batch (each from another phase, its own ``CompactEncoder`` as a session makes it), for each batch
size ``n`` in ``--batches``. Per session-frame: process CPU (all threads, PoCL's and the pool's)
of i16 batches and of compact batches, alternating batch by batch so that both see the same
load. Writes ``bench/out/compact_worker.json`` and prints a table with the ratios and the load.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

OUT = Path(__file__).resolve().parent / "out" / "compact_worker.json"
sys.path.insert(0, str(Path(__file__).resolve().parent))


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--face", default="default")
    p.add_argument("--batches", default="1,2,3,4,6,8,12")
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--frames", type=int, default=60, help="frames of each session a round")
    p.add_argument(
        "--compact-threads", type=int, help="the compact pool's threads (default: the server's)"
    )
    p.add_argument(
        "--device-min",
        type=int,
        help="compact frames on the device from this many a batch (default: the batcher's)",
    )
    a = p.parse_args(argv)

    from serve_load import faps

    from facecast.server.api.store import FaceStore
    from facecast.server.live import batcher as batcher_module
    from facecast.server.live.batcher import DeformBatcher, _Job
    from facecast.server.live.session import compact_encoder
    from facecast.server.live.settings import LiveSettings
    from facecast.server.state import FaceState, zero_faps

    if a.device_min is not None:
        batcher_module.DEVICE_COMPACT_MIN_FRAMES = a.device_min
    animator = FaceStore(default=a.face, backend="auto").animator(a.face)
    face = animator.face
    settings = LiveSettings(compact_threads=a.compact_threads)
    batcher = DeformBatcher(animator, None, settings=settings)  # type: ignore[arg-type]
    work = batcher._work  # noqa: SLF001 - white-box: the worker's job, synchronously
    fps = 60.0

    def state(i: int) -> FaceState:
        v = zero_faps()
        for k, x in faps(i, fps).items():
            v[k] = x
        return FaceState(t=i / fps, faps=v)

    states = [state(i) for i in range(600)]
    sizes = [int(x) for x in a.batches.split(",")]
    res: dict[str, dict[str, float]] = {}
    for n in sizes:
        encs = [compact_encoder(face, 0.1, fps) for _ in range(n)]
        phase = [(s * 97) % len(states) for s in range(n)]

        def jobs(i: int, enc: str) -> list[_Job]:
            return [
                _Job(
                    states[(i + phase[s]) % len(states)],
                    i,
                    0.0,
                    frozenset({enc}),
                    None,  # type: ignore[arg-type]
                    None,  # type: ignore[arg-type]
                    encs[s] if enc == "compact" else None,
                )
                for s in range(n)
            ]

        for i in range(3):  # warm up (kernels built, pools started)
            work(jobs(i, "i16"))
            work(jobs(i, "compact"))
        cpu = {"i16": 0.0, "compact": 0.0}
        count = 0
        for rnd in range(a.rounds):
            for i in range(a.frames):
                order = ("i16", "compact") if (i + rnd) % 2 == 0 else ("compact", "i16")
                for enc in order:
                    js = jobs(rnd * a.frames + i, enc)
                    c0 = time.process_time()
                    out = work(js)
                    cpu[enc] += time.process_time() - c0
                    if not all(isinstance(r, tuple) and enc in r[0] for r in out):
                        print(f"a {enc} frame failed: {out}", file=sys.stderr)
                        return 1
                count += n
        res[str(n)] = {
            "i16_us": cpu["i16"] / count * 1e6,
            "compact_us": cpu["compact"] / count * 1e6,
            "ratio": cpu["compact"] / cpu["i16"],
        }
    load = os.getloadavg()
    out = {"face": a.face, "vertices": int(face.n_vertices), "loadavg": load, "batches": res}
    OUT.parent.mkdir(exist_ok=True)
    OUT.write_text(json.dumps(out, indent=1))
    print(f"\n{a.face} ({face.n_vertices} vertices), load {load[0]:.1f}\n")
    print("| sessions a batch | i16 us | compact us | compact / i16 |")
    print("|---|---|---|---|")
    for n, r in res.items():
        print(f"| {n} | {r['i16_us']:.0f} | {r['compact_us']:.0f} | {r['ratio']:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
