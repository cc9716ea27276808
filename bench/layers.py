"""Face layers: what mixing costs per frame and session, next to the solve it sits on.

    python bench/layers.py [--frames 3000] [--repeats 5]

The primary is real speech (``../shared/data/speech``: mary and bobby through the audio driver,
low-level FAPs at 25 fps, tiled to ``--frames``) on the built-in head. Per frame, in the same
run: the solve as today (``FapRig.solve_batch`` in chunks of 32 as ``Animator.render``, and one
state at a time as a lone live session), and ``Mixer.mix`` with 0-3 layers (an expression
overlay, the idle layer, gaze at a point) and with three layers over a FAP 1 (viseme) primary;
then the live path's batched mix (``layers.mix_batch``: one state of each of B sessions with the
three layers, mixed together as the deform thread does, B = 1, 4, 8, 16, 32), and the solve of the
mixed states (what the layers cost the solve). Times are thread CPU time
(``time.thread_time``; the machine is shared), median over repeats; wall time beside it.
Writes ``bench/out/layers.json`` and a markdown table; the load average is in both.

    python bench/layers.py --serve-pairs 4 [--sessions 25] [--seconds 6] [--encoding i16]

instead measures what layers cost a real server (``bench/serve.py``'s server and load points:
``--sessions`` sessions, one FAP producer at 60 fps and one viewer each): points without layers
(A) and with ``--layers`` (default 3: idle, a smile, gaze at the camera; B) on the same server
process, in ABBA order, ``--serve-pairs`` pairs. Per point the server's CPU per session-frame;
the difference B - A of each pair, their mean, standard deviation and standard error, and the
ratio. Writes ``bench/out/layers_serve.json``.

    python bench/layers.py --capacity 60,70 [--seconds 8] [--encoding i16]

instead measures what a user of ``bench/serve.py`` sees, on one real server: at each session
count a point without layers and one with ``--layers``, frame rates, p95 latency, whether the
target holds (every viewer at 95 % of 60 fps, p95 within 50 ms) and the server's CPU per
session-frame. Writes ``bench/out/layers_capacity.json``.

    python bench/layers.py --against REF [--repeats 7] [--scenario bench|serve]

instead times the live path's mix (``mix_batch``, three layers, B sessions a batch) of the code at
git ``REF`` (its ``server/layers`` loaded beside the working tree's) against the working tree's,
interleaved in the same process (thread CPU time, median of ``--repeats``): the ratio of the two
holds on a loaded machine where the absolute times do not. ``--scenario serve`` mixes
``bench/serve.py``'s layers (idle, joy at 0.5, gaze at the camera, from their REST bodies) over its
producer's FAP frames instead of this bench's over speech. Both outputs are compared too (their
largest difference, FAPU). Writes ``bench/out/layers_against_<scenario>.json``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from facecast.server.state import FaceState

BENCH = str(Path(__file__).parent)  # the sibling benches' folder: serve, serve_load
if BENCH not in sys.path:
    sys.path.insert(0, BENCH)


def per_frame(fn, n: int, repeats: int, clock=time.thread_time) -> tuple[float, float]:
    """Median (CPU by ``clock``, wall) seconds per frame of ``fn()`` over ``repeats`` runs of ``n``
    frames."""
    cpu, wall = [], []
    for _ in range(repeats):
        c, w = clock(), time.perf_counter()
        fn()
        cpu.append((clock() - c) / n)
        wall.append((time.perf_counter() - w) / n)
    return statistics.median(cpu), statistics.median(wall)


def mixer_of(geo, layers):
    """A session's ``Mixer`` over ``geo`` holding ``layers`` ((name, layer) pairs)."""
    from facecast.server.layers import Mixer

    mixer = Mixer(geo)
    for name, layer in layers:
        mixer.set(name, layer)
    return mixer


def live_worker(face, geo, states, layers, repeats: int, row) -> dict:
    """The live deform worker's whole job per frame (``DeformBatcher._work``: mix, solve, deform,
    int16 encode; CPU of all the process' threads, OpenCL's included) in batches of B sessions'
    states, without layers and with the three layers mixed in the thread (``mixing.mix_jobs``)."""
    from types import SimpleNamespace

    from facecast.server.live.batcher import DeformBatcher, _Job
    from facecast.server.pipeline import Animator

    animator = Animator(face)
    batcher = DeformBatcher(animator, None)
    n = len(states)
    out = {}
    for b in (1, 8, 25):
        mixes = [mixer_of(geo, layers) for _ in range(b)]

        def run(with_layers: bool, b: int = b, mixes: list = mixes):
            def go():
                for s in range(0, n, b):
                    jobs = [
                        _Job(st, i, 0.0, frozenset({"i16"}), print, None)
                        for i, st in enumerate(states[s : s + b])
                    ]
                    if with_layers:
                        for job, mixer in zip(jobs, mixes):
                            job.mix = SimpleNamespace(
                                mixer=mixer, now=lambda t=job.state.t: t, mixed=0
                            )
                    batcher._work(jobs)  # noqa: SLF001 - the worker alone, no threads

            return go

        run(True)()  # warm up (OpenCL buffers, the quantiser)
        plain = row(f"live worker, batch of {b}, no layers", run(False), time.process_time, n)
        mixed = row(f"live worker, batch of {b}, 3 layers", run(True), time.process_time, n)
        out[b] = {"plain": plain["cpu_ms"], "layers3": mixed["cpu_ms"]}
    return out


def serve_server(args: argparse.Namespace, sessions: str):
    """``(serve, sargs, server)``: ``bench/serve.py`` (its server, load point and viewer
    processes), its arguments for ``sessions`` (``N`` or ``N,M``) and this bench's ``--encoding``,
    ``--warmup`` and ``--seconds``, and its server, started (the caller stops it)."""
    import logging

    import serve

    logging.basicConfig(level=logging.WARNING)
    p = argparse.ArgumentParser()
    serve.add_arguments(p)
    sargs = p.parse_args(
        ["--sessions", sessions, "--viewers", "", "--encoding", args.encoding]
        + ["--warmup", str(args.warmup), "--seconds", str(args.seconds)]
    )
    sargs.encoding = sargs.encoding[0]
    warm_kernel()  # (compiled here, cached on disk: the server loads it, not compiles it)
    server = serve._server(sargs.face, sargs.backend)  # noqa: SLF001 - the bench's own server
    server.start(300, ready=True)
    return serve, sargs, server


def warm_kernel(package: str = "facecast.server.layers") -> None:
    """Compile the layers' mix kernel (``server/layers/kernel.py`` of ``package``) and wait: it
    is compiled in a thread on first use, the NumPy path mixing meanwhile, and cached on disk; a
    bench measures the compiled one. (A tree without it: nothing.)"""
    try:
        kernel = importlib.import_module(package + ".kernel")
    except ImportError:
        return
    kernel.warm(block=True)


def serve_capacity(args: argparse.Namespace) -> int:
    """``--capacity N,M``: what a user of ``bench/serve.py`` sees with and without layers, on one
    real server: at each session count, a point without layers and one with ``--layers`` (their
    order alternating), each viewer's frame rate, p95 latency, whether the point holds the
    target (every viewer at 95 % of 60 fps, p95 within 50 ms) and the server's CPU per
    session-frame. Writes ``bench/out/layers_capacity.json``."""
    import asyncio

    counts = [int(x) for x in args.capacity.split(",") if x.strip()]
    load0 = os.getloadavg()
    serve, sargs, server = serve_server(args, ",".join(map(str, counts)))
    key = "server_cpu_us_per_session_frame"
    points: list[dict] = []
    try:

        async def go() -> None:
            for k, sessions in enumerate(counts):
                for n in (0, args.layers) if k % 2 == 0 else (args.layers, 0):
                    sargs.layers = n
                    r = await serve.run_point(
                        server, server.url, sessions=sessions, viewers=1, args=sargs
                    )
                    held = serve._ok(r, sargs)  # noqa: SLF001 - serve.py's own target
                    r.update(layers=n, held=held, loadavg=os.getloadavg()[0])
                    points.append(r)
                    print(
                        f"{sessions} sessions, layers {n}: fps {r['fps_mean']} (min "
                        f"{r['fps_min']}), p95 {r['latency_ms_p95']} ms, {r[key]} us per "
                        f"session-frame, load {r['loadavg']:.1f}",
                        file=sys.stderr,
                    )

        asyncio.run(go())
    finally:
        server.stop()
    load1 = os.getloadavg()
    result = {
        "encoding": args.encoding,
        "layers": args.layers,
        "loadavg_start": load0,
        "loadavg_end": load1,
        "cpus": os.cpu_count(),
        "points": points,
    }
    write_json(args.out, "layers_capacity.json", result)
    print(
        f"\n{args.encoding}, 0 and {args.layers} layers per session, one server; load "
        f"{load0[0]:.1f} -> {load1[0]:.1f} on {os.cpu_count()} CPUs\n"
    )
    print("| sessions | layers | fps mean | fps min | p95 ms | held | server µs/session-frame |")
    print("|---|---|---|---|---|---|---|")
    for q in sorted(points, key=lambda q: (q["sessions"], q["layers"])):
        print(
            f"| {q['sessions']} | {q['layers']} | {q['fps_mean']} | {q['fps_min']} | "
            f"{q['latency_ms_p95']} | {'yes' if q['held'] else 'no'} | {q[key]} |"
        )
    return 0


def serve_pairs(args: argparse.Namespace) -> int:
    """``--serve-pairs``: layers on and off, ABBA, on one real server (see the module)."""
    import asyncio

    load0 = os.getloadavg()
    serve, sargs, server = serve_server(args, str(args.sessions))
    key = "server_cpu_us_per_session_frame"
    points: list[dict] = []
    try:

        async def go() -> None:
            for pair in range(args.serve_pairs):
                order = (0, args.layers) if pair % 2 == 0 else (args.layers, 0)
                for n in order:
                    sargs.layers = n
                    r = await serve.run_point(
                        server, server.url, sessions=args.sessions, viewers=1, args=sargs
                    )
                    r.update(layers=n, pair=pair, loadavg=os.getloadavg()[0])
                    points.append(r)
                    print(
                        f"pair {pair} layers {n}: {r[key]} us per session-frame, "
                        f"fps {r['fps_mean']}, p95 {r['latency_ms_p95']} ms, "
                        f"load {r['loadavg']:.1f}",
                        file=sys.stderr,
                    )

        asyncio.run(go())
    finally:
        server.stop()
    load1 = os.getloadavg()
    a = {q["pair"]: q[key] for q in points if q["layers"] == 0}
    b = {q["pair"]: q[key] for q in points if q["layers"] == args.layers}
    diffs = [b[k] - a[k] for k in sorted(a) if k in b]
    mean = statistics.mean(diffs)
    sd = statistics.stdev(diffs) if len(diffs) > 1 else float("nan")
    se = sd / len(diffs) ** 0.5
    base = statistics.mean(a.values())
    result = {
        "sessions": args.sessions,
        "encoding": args.encoding,
        "layers": args.layers,
        "pairs": args.serve_pairs,
        "loadavg_start": load0,
        "loadavg_end": load1,
        "cpus": os.cpu_count(),
        "us_per_session_frame_without": list(a.values()),
        "us_per_session_frame_with": list(b.values()),
        "diff_us": diffs,
        "diff_mean_us": mean,
        "diff_sd_us": sd,
        "diff_se_us": se,
        "diff_median_us": statistics.median(diffs),
        "ratio": statistics.mean(b.values()) / base,
        "points": points,
    }
    write_json(args.out, "layers_serve.json", result)
    print(
        f"\n{args.sessions} sessions, {args.encoding}, {args.layers} layers, ABBA pairs; load "
        f"{load0[0]:.1f} -> {load1[0]:.1f} on {os.cpu_count()} CPUs\n"
    )
    print("| pair | without µs | with µs | with - without |")
    print("|---|---|---|---|")
    for k, d in zip(sorted(a), diffs):
        print(f"| {k} | {a[k]:.1f} | {b[k]:.1f} | {d:+.1f} |")
    print(
        f"\nlayers cost {mean:+.1f} µs per session-frame (sd {sd:.1f}, se {se:.1f}; "
        f"{100 * mean / base:+.1f} % of {base:.1f} µs); median pair {statistics.median(diffs):+.1f} µs"
    )
    return 0


DEFAULT_OUT = Path(__file__).parent / "out" / "layers.json"


def write_json(out_arg: str, default_name: str, result: dict) -> None:
    """Writes ``result`` to ``--out``, or to ``default_name`` beside the default output."""
    out = Path(out_arg)
    if out == DEFAULT_OUT:
        out = DEFAULT_OUT.with_name(default_name)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))


def load_layers_at(ref: str):
    """The ``server/layers`` package of git ``ref`` as module ``facecast.server._layers_at``
    (written to a temporary directory; its relative imports resolve to the working tree's
    ``facecast.server``)."""
    import importlib.util
    import subprocess
    import tempfile

    root = Path(__file__).resolve().parents[1]
    names = subprocess.run(
        ["git", "ls-tree", "--name-only", ref, "server/layers/"],
        cwd=root,
        check=True,
        capture_output=True,
        text=True,
    ).stdout.split()
    where = Path(tempfile.mkdtemp(prefix="layers_at_"))
    for name in names:
        if name.endswith(".py"):
            text = subprocess.run(
                ["git", "show", f"{ref}:{name}"], cwd=root, check=True, capture_output=True
            ).stdout
            (where / Path(name).name).write_bytes(text)
    spec = importlib.util.spec_from_file_location(
        "facecast.server._layers_at", where / "__init__.py", submodule_search_locations=[str(where)]
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def speech_on_default():
    """``(face, FapRig, states)``: the built-in head, its rig and the FAP states of the shared
    speech files (mary, bobby); None, said on stderr, when ``../shared/data`` is absent."""
    from facecast.server.drivers import load_animation
    from facecast.server.faces import load_face
    from facecast.server.mpeg4.rig import FapRig
    from facecast.server.paths import shared_data

    data = shared_data()
    if data is None:
        print("../shared/data not found: the bench needs its speech", file=sys.stderr)
        return None
    face = load_face("default")
    speech = []
    for wav in ("mary.wav", "bobby_16bit_16khz.wav"):
        speech += load_animation(data / "speech" / wav, face).states
    return face, FapRig(face), speech


def scenario_layers(L, scenario: str, t0: float = 0.0) -> list:
    """``(name, layer)`` pairs of the layers package ``L``: ``bench`` (a smile rising at 1 s, idle,
    gaze at a point) or ``serve`` (``bench/serve.py``'s ``LAYERS``: idle, joy at 0.5, gaze at the
    camera, built from their REST bodies as the server does)."""
    if scenario == "serve":
        import serve

        spec = importlib.import_module(L.__name__ + ".spec")
        return [(name, spec.from_spec(body, t0)) for name, body in serve.LAYERS]
    return [
        (
            "smile",
            L.ExpressionLayer(1, amount=0.7, envelope=L.Envelope(start=1.0, attack_peak=1.5)),
        ),
        ("idle", L.IdleLayer(seed=1)),
        ("gaze", L.GazeLayer(L.GazeTarget(point=np.array([100.0, 50.0, 600.0])))),
    ]


def scenario_primary(scenario: str, n: int) -> list[FaceState] | None:
    """``n`` primary states: the shared speech at 25 fps (``bench``) or ``bench/serve.py``'s
    producer's FAP frames at 60 fps (``serve``: jaw, lips, brows and a blink); None without
    ``../shared/data`` for ``bench``."""
    if scenario == "serve":
        import serve_load

        out = []
        for i in range(n):
            f = np.zeros(69)
            for k, x in serve_load.faps(i, 60.0).items():
                f[k] = x
            out.append(FaceState(t=i / 60.0, faps=f))
        return out
    got = speech_on_default()
    if got is None:
        return None
    speech = got[2]
    return [FaceState(t=i / 25.0, faps=speech[i % len(speech)].faps) for i in range(n)]


def against(args: argparse.Namespace) -> int:
    """``--against REF``: the live path's mix at ``REF`` against the working tree's (module doc)."""
    from facecast.server.faces import load_face
    from facecast.server.mpeg4.rig import FapRig

    load0 = os.getloadavg()
    n = min(args.frames, 1200)
    primary = scenario_primary(args.scenario, n)
    if primary is None:
        return 2
    rig = FapRig(load_face("default"))
    old = load_layers_at(args.against)
    import facecast.server.layers as new

    warm_kernel()
    warm_kernel(old.__name__)

    def runner(L, batch, b: int):
        geo = L.Geometry.of_rig(rig)
        mixers = [mixer_of_module(L, geo, scenario_layers(L, args.scenario)) for _ in range(b)]

        def run():
            out = []
            for s in range(0, n, b):  # the sessions' clocks a little apart, as live
                out += batch.mix_batch(
                    [
                        (mixers[i - s], primary[i], primary[i].t + 0.003 * (i - s))
                        for i in range(s, min(n, s + b))
                    ]
                )
            return out

        return run

    rows = []
    for b in (1, 2, 4, 8, 12, 16, 25, 32):
        runs = {
            "ref": runner(old, importlib.import_module("facecast.server._layers_at.batch"), b),
            "tree": runner(new, importlib.import_module("facecast.server.layers.batch"), b),
        }
        outs = {k: fn() for k, fn in runs.items()}  # warm up, and the outputs compared
        diff = max(
            float(np.max(np.abs(np.asarray(x.faps) - np.asarray(y.faps))))
            for x, y in zip(outs["ref"], outs["tree"], strict=True)
        )
        times: dict[str, list[float]] = {"ref": [], "tree": []}
        for _ in range(args.repeats):
            for k, fn in runs.items():
                c = time.thread_time()
                fn()
                times[k].append((time.thread_time() - c) / n * 1e3)
        ref, tree = statistics.median(times["ref"]), statistics.median(times["tree"])
        rows.append(
            {
                "sessions": b,
                "ref_cpu_ms": ref,
                "tree_cpu_ms": tree,
                "ratio": tree / ref,
                "max_abs_diff_fapu": diff,
            }
        )
        print(
            f"{b} sessions: {args.against} {ref:.4f} ms, tree {tree:.4f} ms, "
            f"outputs differ by {diff:.2g} FAPU at most",
            file=sys.stderr,
        )
    load1 = os.getloadavg()
    result = {
        "ref": args.against,
        "scenario": args.scenario,
        "frames": n,
        "repeats": args.repeats,
        "cpus": os.cpu_count(),
        "loadavg_start": load0,
        "loadavg_end": load1,
        "rows": rows,
    }
    write_json(args.out, f"layers_against_{args.scenario}.json", result)
    print(
        f"\nlive mix (mix_batch, 3 layers, {args.scenario} scenario) per frame, thread CPU, median "
        f"of {args.repeats}; load {load0[0]:.1f} -> {load1[0]:.1f} on {os.cpu_count()} CPUs\n"
    )
    print(f"| sessions a batch | {args.against} ms | working tree ms | ratio | max abs diff FAPU |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['sessions']} | {r['ref_cpu_ms']:.4f} | {r['tree_cpu_ms']:.4f} | "
            f"{r['ratio']:.3f} | {r['max_abs_diff_fapu']:.2g} |"
        )
    return 0


def mixer_of_module(L, geo, layers):
    """``mixer_of`` with the ``Mixer`` of the layers package ``L``."""
    mixer = L.Mixer(geo)
    for name, layer in layers:
        mixer.set(name, layer)
    return mixer


def main(argv: list[str] | None = None) -> int:
    from facecast.server.layers import (
        Envelope,
        ExpressionLayer,
        GazeLayer,
        GazeTarget,
        Geometry,
        IdleLayer,
    )
    from facecast.server.layers.batch import mix_batch
    from facecast.server.pipeline import CHUNK

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=3000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument(
        "--worker-frames", type=int, default=800, help="frames per live worker case (deformed)"
    )
    ap.add_argument("--out", default=str(DEFAULT_OUT))
    ap.add_argument(
        "--serve-pairs",
        type=int,
        default=0,
        help="measure a real server instead: this many ABBA pairs of points without and with layers",
    )
    ap.add_argument("--sessions", type=int, default=25, help="--serve-pairs: sessions per point")
    ap.add_argument(
        "--capacity",
        default="",
        metavar="N,M",
        help="measure a real server instead: these session counts, without and with layers",
    )
    ap.add_argument("--layers", type=int, default=3, help="--serve-pairs: layers (bench/serve.py)")
    ap.add_argument("--encoding", default="i16", help="--serve-pairs: viewers' encoding")
    ap.add_argument("--warmup", type=float, default=2.0, help="--serve-pairs: seconds")
    ap.add_argument("--seconds", type=float, default=6.0, help="--serve-pairs: seconds measured")
    ap.add_argument(
        "--scenario",
        choices=("bench", "serve"),
        default="bench",
        help="--against: this bench's layers over speech, or bench/serve.py's over its FAP frames",
    )
    ap.add_argument(
        "--against",
        default=None,
        metavar="REF",
        help="time the live mix of git REF's server/layers against the working tree's instead",
    )
    args = ap.parse_args(argv)
    if args.serve_pairs:
        return serve_pairs(args)
    if args.capacity:
        return serve_capacity(args)
    if args.against:
        return against(args)
    load0 = os.getloadavg()
    got = speech_on_default()
    if got is None:
        return 2
    warm_kernel()
    face, rig, speech = got
    geo = Geometry.of_rig(rig)
    n = args.frames
    fps = 25.0
    primary = [FaceState(t=i / fps, faps=speech[i % len(speech)].faps) for i in range(n)]
    visemes = [FaceState(t=i / fps, viseme=(1 + i % 14, 0, 40)) for i in range(n)]
    layers = [
        ("smile", ExpressionLayer(1, amount=0.7, envelope=Envelope(start=1.0, attack_peak=1.5))),
        ("idle", IdleLayer(seed=1)),
        ("gaze", GazeLayer(GazeTarget(point=np.array([100.0, 50.0, 600.0])))),
    ]

    def solve_chunks(states):
        def run():
            for s in range(0, n, CHUNK):
                rig.solve_batch(states[s : s + CHUNK])

        return run

    def solve_single(states):
        def run():
            for st in states:
                rig.solve_batch([st])

        return run

    def mixing(k: int, states):
        m = mixer_of(geo, layers[:k])

        def run():
            for st in states:
                m.mix(st)

        return run

    rows = []

    def row(name: str, fn, clock=time.thread_time, frames: int | None = None) -> dict:
        cpu, wall = per_frame(fn, frames or n, args.repeats, clock)
        r = {"case": name, "cpu_ms": cpu * 1e3, "wall_ms": wall * 1e3}
        rows.append(r)
        print(f"{name:40s} {cpu * 1e3:8.4f} ms cpu {wall * 1e3:8.4f} ms wall", file=sys.stderr)
        return r

    base_chunk = row("solve, chunks of 32 (baseline)", solve_chunks(primary))
    base_one = row("solve, one state (baseline)", solve_single(primary))
    mixes = [row(f"mix, {k} layer(s)", mixing(k, primary)) for k in range(4)]
    mix_vis = row("mix, 3 layers, viseme primary", mixing(3, visemes))

    def batched(b: int):
        """``mix_batch`` of one state of each of ``b`` sessions (own mixers), ``n`` states in all."""
        mixers = [mixer_of(geo, layers) for _ in range(b)]

        def run():
            for s in range(0, n, b):
                mix_batch(
                    [(mixers[i - s], primary[i], primary[i].t) for i in range(s, min(n, s + b))]
                )

        return run

    sizes = (1, 4, 8, 16, 32)
    batch_rows = {b: row(f"live mix_batch, 3 layers, {b} sessions", batched(b)) for b in sizes}
    worker = live_worker(face, geo, primary[: args.worker_frames], layers, args.repeats, row)
    m = mixer_of(geo, layers)
    mixed = [m.mix(st) for st in primary]
    solved_mixed = row("solve of the mixed states, chunks of 32", solve_chunks(mixed))
    load1 = os.getloadavg()
    result = {
        "frames": n,
        "repeats": args.repeats,
        "face": "default",
        "vertices": face.n_vertices,
        "controls": rig.n_controls,
        "cpus": os.cpu_count(),
        "loadavg_start": load0,
        "loadavg_end": load1,
        "target_ms": 0.05,
        "mix3_cpu_ms": mixes[3]["cpu_ms"],
        "mix3_over_solve_chunk": mixes[3]["cpu_ms"] / base_chunk["cpu_ms"],
        "solve_mixed_extra_cpu_ms": solved_mixed["cpu_ms"] - base_chunk["cpu_ms"],
        "mix3_batched_cpu_ms": {b: r["cpu_ms"] for b, r in batch_rows.items()},
        "live_worker_cpu_ms": worker,
        "rows": rows,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    print(
        f"\nbuilt-in head ({face.n_vertices} vertices, {rig.n_controls} controls), {n} frames of "
        f"real speech, median of {args.repeats}; load average {load0[0]:.1f} -> {load1[0]:.1f} "
        f"on {os.cpu_count()} CPUs\n"
    )
    print("| per frame | CPU ms | wall ms |")
    print("|---|---|---|")
    for r in rows:
        print(f"| {r['case']} | {r['cpu_ms']:.4f} | {r['wall_ms']:.4f} |")
    print(
        f"\nthree layers: {mixes[3]['cpu_ms']:.4f} ms per frame (target 0.05) over a "
        f"{base_chunk['cpu_ms']:.4f} ms batched solve ({base_one['cpu_ms']:.4f} ms alone); "
        f"viseme primary {mix_vis['cpu_ms']:.4f} ms; batched as live (mix_batch): "
        + ", ".join(f"{b} sessions {r['cpu_ms']:.4f} ms" for b, r in batch_rows.items())
    )
    print(
        "live worker (mix + solve + deform + int16, all threads) per frame, no layers -> 3 layers: "
        + ", ".join(
            f"batch of {b} {w['plain']:.3f} -> {w['layers3']:.3f} ms" for b, w in worker.items()
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
