"""The compact residual kernel (``backends/opencl/compact.py``) against git REF's, interleaved in
one process on the same frames: a before/after that holds on a loaded machine.

    python bench/compact_kernel.py [--ref main] [--face default] [--fap joy] [--sessions 10]
                                   [--rounds 5] [--frames 60]

A FAP file rendered on the face (NumPy backend), ``--sessions`` sessions of it (each from another
start) encoded a batch per frame as the live server does (keys every 250 ms). Per frame of a
session, for REF's module and the working tree's, alternating launch by launch: wall time of
``DeviceCompact.residuals`` (the kernel launch and its wait), and process CPU (PoCL's threads too)
of ``residuals`` and of the whole ``encode_batch`` (prepare, kernel, payload, deflate inline).
Both must give the same bytes on every frame (each side's first launches, where PoCL compiles
the kernel, are untimed). Writes ``bench/out/compact_kernel.json`` and prints
a table with the ratios and the machine's load.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parent / "out" / "compact_kernel.json"
ROOT = Path(__file__).resolve().parents[1]


def load_ref(ref: str):
    """REF's ``backends/opencl/compact.py`` as a module of the package, building REF's kernel."""
    from facecast.server.backends.opencl import host
    from facecast.server.bench.history import module_at

    src = subprocess.run(
        ["git", "show", f"{ref}:server/backends/opencl/compact.cl"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    name = "facecast.server.backends.opencl._compact_ref"
    mod = module_at(ROOT, ref, "server/backends/opencl/compact.py", name)
    real = host.cl_source

    def build(ctx):
        host.cl_source = lambda n: src if n == "compact" else real(n)
        try:
            return mod.DeviceCompact(ctx)
        finally:
            host.cl_source = real

    return mod, build


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--ref", default="main")
    p.add_argument("--face", default="default")
    p.add_argument("--fap", default="joy")
    p.add_argument("--sessions", type=int, default=10)
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--frames", type=int, default=60)
    a = p.parse_args(argv)

    from facecast.protocol.compact import CompactEncoder
    from facecast.server.backends.opencl import aligned_empty, default_context
    from facecast.server.backends.opencl import compact as new
    from facecast.server.drivers import load_animation
    from facecast.server.faces import load_face
    from facecast.server.paths import shared_data
    from facecast.server.pipeline import Animator

    ctx = default_context()
    if ctx is None:
        print("no OpenCL device", file=sys.stderr)
        return 1
    face = load_face(a.face)
    data = shared_data()
    if data is None:
        print("no shared data (../shared/data)", file=sys.stderr)
        return 1
    anim = load_animation(data / "xface" / "faps" / f"{a.fap}.fap", face)
    anim.states = anim.states[: a.frames]
    an = Animator(face, backend="numpy", control_vertices=anim.control_vertices)
    _, poses = an.solve_batch(anim.states)
    frames = np.asarray(an.render(anim), np.float32)
    fps, n, S = float(anim.fps), len(frames), a.sessions
    tol, key = 0.1 / face.mm_per_unit, max(1, round(0.25 * anim.fps))
    old, build_old = load_ref(a.ref)
    sides = {"ref": (old, build_old(ctx)), "new": (new, new.DeviceCompact(ctx))}

    def encoders():
        return [
            CompactEncoder(face.vertices, face.rigid_group, tolerance=tol, key_interval=key)
            for _ in range(S)
        ]

    encs = {k: encoders() for k in sides}
    buf = aligned_empty((S,) + frames.shape[1:], np.float32)
    starts = [(s * n) // S for s in range(S)]
    acc = {k: {"wall": 0.0, "kcpu": 0.0, "cpu": 0.0} for k in sides}
    timed: dict = {}
    same = True
    for mod, dev in sides.values():  # PoCL compiles a kernel at its first launch: untimed
        warm = encoders()
        buf[:] = frames[:S] if n >= S else frames[0]
        for i in range(2):
            mod.encode_batch(
                dev, buf, [(e, s, poses[s % n], i, i / fps, 0.0) for s, e in enumerate(warm)]
            )
    for k, (_, dev) in sides.items():  # residuals timed inside encode_batch: wrap the method
        orig = dev.residuals

        def wrapped(*args, _o=orig, _k=k):
            w0, c0 = time.perf_counter(), time.process_time()
            r = _o(*args)
            timed[_k] = (time.perf_counter() - w0, time.process_time() - c0)
            return r

        dev.residuals = wrapped
    for rnd in range(a.rounds):
        for i in range(n):
            idx = [(i + o) % n for o in starts]
            buf[:] = frames[idx]
            outs = {}
            order = list(sides) if (i + rnd) % 2 == 0 else list(sides)[::-1]
            for k in order:
                mod, dev = sides[k]
                batch = [(e, s, poses[idx[s]], i, i / fps, 0.0) for s, e in enumerate(encs[k])]
                c0 = time.process_time()
                outs[k] = mod.encode_batch(dev, buf, batch)
                acc[k]["cpu"] += time.process_time() - c0
                acc[k]["wall"] += timed[k][0]
                acc[k]["kcpu"] += timed[k][1]
            same = same and outs["ref"] == outs["new"]
    per = a.rounds * n * S
    res = {
        k: {
            "kernel_wall_us": v["wall"] / per * 1e6,
            "kernel_cpu_us": v["kcpu"] / per * 1e6,
            "encode_cpu_us": v["cpu"] / per * 1e6,
        }
        for k, v in acc.items()
    }
    out = {
        "ref": a.ref,
        "face": a.face,
        "vertices": face.n_vertices,
        "fap": a.fap,
        "sessions": S,
        "frames": n,
        "rounds": a.rounds,
        "same_bytes": same,
        "loadavg": os.getloadavg(),
        **res,
    }
    OUT.parent.mkdir(exist_ok=True)
    OUT.write_text(json.dumps(out, indent=1))
    print(
        f"\n{a.face} ({face.n_vertices} vertices), {a.fap}.fap, {S} sessions a batch, "
        f"{a.rounds}x{n} frames; load {os.getloadavg()[0]:.1f}; same bytes: {same}\n"
    )
    print(f"| per session-frame (us) | {a.ref} | working tree | ratio |")
    print("|---|---|---|---|")
    for m in ("kernel_wall_us", "kernel_cpu_us", "encode_cpu_us"):
        r, w = res["ref"][m], res["new"][m]
        print(f"| {m} | {r:.1f} | {w:.1f} | {w / r:.2f} |")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
