"""glTF (.glb) encoding time and peak memory against clip length: the streaming two-pass morph basis
(``server/output/gltf.py``) against the previous ``T x T`` Gram-matrix SVD, measured in the same run.

    python bench/gltf_encode.py [--face default] [--frames 100 400 1500 6000] [--old-max 1500]
                                [--stream 6000] [--threads N] [--repeats 1] [--baseline REV]

Frames: the five XFace ``.fap`` files (``../shared/data/xface/faps``) played one after the other and
looped, every loop after the first with smooth random per-FAP gains (seeded) so that the clip does
not simply repeat, rendered through ``pipeline.Animator(load_face(face), backend="numpy")`` at 25 fps.

Measured per method and length: ``encode_glb`` wall time (the whole .glb: basis, verification,
normals, packing) on frames already in memory and of the morph basis alone (no normals), the
encode's peak traced allocation (``tracemalloc``; the input
frames are allocated before and not counted, their size is given separately), the target count,
the measured max vertex error and the file size. The old method is ``gltf.py`` taken from git
history at ``--baseline`` (default ``BASELINE``, the last ``T x T`` Gram-matrix encoder; any later
revision compares against that one instead), run for ``T <= --old-max``. ``--stream T`` also encodes a
clip of ``T`` frames from a chunk source that renders them anew on each pass (as ``render_file``
does for long clips): wall time then includes the rendering, memory is everything.

Writes ``bench/out/gltf_encode.json`` and prints a markdown table with the old/new ratios.

``--check default:200k default:500k`` instead runs ``glb_check`` per face (``facecast render joy.fap -o
x.glb --face SPEC`` in a subprocess, then the file read back independently and compared with the
renderer's float vertices) and writes ``bench/out/gltf_check.json`` and a table.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "bench" / "out" / "gltf_encode.json"
#: The last commit with the T x T Gram-matrix encoder (the default ``--baseline``).
BASELINE = "bfb3ea5"
#: Old source text -> today's, for the APIs of the current package an old ``gltf.py`` calls: the third
#: positional argument of ``vertex_normals`` was the incidence matrix, it is now the vertex count.
BASELINE_COMPAT = {"vertex_normals(v, tri, inc)": "vertex_normals(v, tri, incidence=inc)"}


def parse(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--face", default="default")
    p.add_argument("--frames", type=int, nargs="+", default=[100, 400, 1500, 6000])
    p.add_argument("--old-max", type=int, default=1500, help="longest clip for the old method")
    p.add_argument(
        "--stream", type=int, nargs="*", default=[6000], help="clip lengths also encoded streamed"
    )
    p.add_argument(
        "--threads", type=int, default=None, help="BLAS threads (sets OPENBLAS/OMP/MKL_NUM_THREADS)"
    )
    p.add_argument("--repeats", type=int, default=1, help="best of this many runs per point")
    p.add_argument(
        "--baseline", default=BASELINE, help=f"git revision of the old gltf.py (default {BASELINE})"
    )
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--out", type=Path, default=OUT, help="JSON output")
    p.add_argument(
        "--check",
        nargs="+",
        metavar="FACE",
        default=None,
        help="instead: glb_check each face spec (e.g. default:200k default:500k)",
    )
    return p.parse_args(argv)


_RUNNER = """
import json, resource, sys
from facecast.server.cli import main
code = main(sys.argv[2:])
with open(sys.argv[1], "w") as f:
    json.dump({"code": code, "peak_rss_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}, f)
"""


def _reader():
    """The independent .glb reader of ``tests/test_gltf_verify.py`` (pygltflib + numpy, none of the
    writer's code): ``(read_back, max_error_mm)``."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "_glb_read_back", ROOT / "tests" / "test_gltf_verify.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.read_back, mod.max_error_mm


def glb_check(face_spec: str, *, fap: str | Path | None = None, backend: str = "auto") -> dict:
    """Render ``fap`` (default: XFace ``joy.fap``) to a .glb on ``face_spec`` as a user does (``facecast
    render``, its own process: ``seconds`` is its wall time with the face build and rendering, and
    ``peak_rss_mb`` its peak resident memory), then read the file back independently and measure the
    largest vertex distance (mm) from the renderer's float vertices (``max_error_mm``) against the
    tolerance the file records. A refused render gives ``refused: True`` and its ``message``.

    Returns ``face, vertices, frames, targets, method, tolerance_mm, recorded_max_error_mm,
    max_error_mm, within_tolerance, bytes, peak_rss_mb, seconds, load_avg``.
    """
    import subprocess
    import tempfile
    import time

    from facecast.server.drivers.fap import load as load_fap
    from facecast.server.faces import load_face
    from facecast.server.paths import shared_data
    from facecast.server.pipeline import Animator

    src = Path(fap) if fap else shared_data() / "xface" / "faps" / "joy.fap"
    with tempfile.TemporaryDirectory(prefix="glb-check-") as tmp:
        out, stats = Path(tmp) / "out.glb", Path(tmp) / "stats.json"
        load0 = os.getloadavg()
        t0 = time.perf_counter()
        r = subprocess.run(
            [
                sys.executable,
                "-c",
                _RUNNER,
                str(stats),
                "render",
                str(src),
                "-o",
                str(out),
                "--face",
                face_spec,
                "--backend",
                backend,
            ],
            capture_output=True,
            text=True,
            check=False,
        )
        seconds = time.perf_counter() - t0
        run = (
            json.loads(stats.read_text())
            if stats.is_file()
            else {"code": r.returncode, "peak_rss_kb": 0}
        )
        row = {
            "face": face_spec,
            "seconds": seconds,
            "peak_rss_mb": run["peak_rss_kb"] / 1024,
            "exit": run["code"],
            "load_avg": [round((a + b) / 2, 2) for a, b in zip(load0, os.getloadavg())],
        }
        if run["code"] != 0 or not out.is_file():
            lines = r.stderr.strip().splitlines()
            return {**row, "refused": True, "message": lines[-1] if lines else ""}
        read_back, max_error_mm = _reader()
        glb = read_back(out)
        face = load_face(face_spec)
        frames = Animator(face, backend=backend).render(load_fap(src, face))
        err = max_error_mm(glb, frames, face.mm_per_unit)
        return {
            **row,
            "refused": False,
            "vertices": face.n_vertices,
            "frames": len(frames),
            "targets": len(glb["targets"]),
            "method": glb["record"]["method"],
            "tolerance_mm": glb["tolerance_mm"],
            "recorded_max_error_mm": glb["max_error_mm"],
            "max_error_mm": err,
            "within_tolerance": bool(err <= glb["tolerance_mm"]),
            "bytes": out.stat().st_size,
        }


def check_markdown(rows: list[dict]) -> str:
    lines = [
        (
            "| face | vertices | frames | targets | tolerance (mm) | max error read back (mm) | within "
            "| .glb (MB) | peak RSS (MB) | wall (s) | load |"
        ),
        "|---|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        if r["refused"]:
            lines.append(
                f"| {r['face']} | refused: {r['message']} | | | | | | | {r['peak_rss_mb']:.0f} | "
                f"{r['seconds']:.0f} | {r['load_avg'][0]:.1f} |"
            )
            continue
        lines.append(
            f"| {r['face']} | {r['vertices']} | {r['frames']} | {r['targets']} | {r['tolerance_mm']} | "
            f"{r['max_error_mm']:.4f} | {'yes' if r['within_tolerance'] else 'NO'} | {r['bytes'] / 1e6:.1f} | "
            f"{r['peak_rss_mb']:.0f} | {r['seconds']:.0f} | {r['load_avg'][0]:.1f} |"
        )
    return "\n".join(lines)


def baseline_module(rev: str = BASELINE):
    """``facecast.server.output.gltf`` at git revision ``rev`` as a module of the same package (its
    calls adapted to today's APIs, ``BASELINE_COMPAT``)."""
    from facecast.server.bench.history import module_at

    return module_at(
        ROOT,
        rev,
        "server/output/gltf.py",
        "facecast.server.output._gltf_baseline",
        BASELINE_COMPAT,
    )


def basis_options(mod) -> dict:
    """Keyword arguments of ``mod.morph_basis`` for the basis alone: no normals where it computes
    them (the current encoder and later baselines), none for the old encoder that never did."""
    import inspect

    return {"normals": None} if "normals" in inspect.signature(mod.morph_basis).parameters else {}


def clip(face, n_frames: int, seed: int):
    """The looped XFace animation (``Animation``) of ``n_frames`` frames, see the module docstring."""
    from dataclasses import replace

    import numpy as np

    from facecast.server.drivers.fap import load as load_fap
    from facecast.server.paths import shared_data
    from facecast.server.state import Animation

    files = sorted((shared_data() / "xface" / "faps").glob("*.fap"))
    clips = [load_fap(f, None) for f in files]
    rng = np.random.default_rng(seed)
    states, loop = [], 0
    while len(states) < n_frames:
        for c in clips:
            n = len(c.states)
            if loop == 0:
                gain = np.ones((n, 69))
            else:  # smooth gains in [0.6, 1.4] per FAP: two random sinusoids over the clip
                t = np.arange(n)[:, None] / n
                f, ph = rng.uniform(0.5, 2.0, (2, 69)), rng.uniform(0, 2 * np.pi, (2, 69))
                gain = (
                    1
                    + 0.2 * np.sin(2 * np.pi * f[0] * t + ph[0])
                    + 0.2 * np.sin(2 * np.pi * f[1] * t + ph[1])
                )
            states.extend(replace(s, faps=s.faps * g) for s, g in zip(c.states, gain))
        loop += 1
    return Animation(
        25.0, [replace(s, t=i / 25.0) for i, s in enumerate(states[:n_frames])], source="xface-loop"
    )


def measure(fn, repeats: int) -> tuple[float, float, object]:
    """Best wall time (s) and largest traced peak (bytes) over ``repeats`` calls, and the last result."""
    import gc
    import time
    import tracemalloc

    best, peak, out = float("inf"), 0, None
    for _ in range(repeats):
        out = None
        gc.collect()
        tracemalloc.start()
        t0 = time.perf_counter()
        out = fn()
        dt = time.perf_counter() - t0
        peak = max(peak, tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
        best = min(best, dt)
    return best, peak, out


def encode_row(
    frames: int,
    face,
    method: str,
    seconds: float,
    peak: int,
    data: bytes,
    rec: dict,
    input_mb: float,
) -> dict:
    """One row of the table: an encoding of ``frames`` frames of ``face`` by ``method``, which took
    ``seconds`` and ``peak`` bytes and gave ``data`` (the .glb) and ``rec`` (its record)."""
    return {
        "frames": frames,
        "vertices": face.n_vertices,
        "method": method,
        "targets": rec["targets"],
        "max_error_mm": rec["max_error_mm"],
        "seconds": seconds,
        "peak_mb": peak / 2**20,
        "glb_mb": len(data) / 1e6,
        "input_mb": input_mb,
        "capped": rec.get("capped"),
        "passes": rec.get("passes"),
    }


def markdown(rows: list[dict]) -> str:
    lines = [
        (
            "| frames | method | targets | max err (mm) | encode (s) | basis only (s) | peak (MB) "
            "| .glb (MB) | old/new encode | old/new basis | old/new peak |"
        ),
        "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['frames']} | {r['method']} | {r['targets']} | {r['max_error_mm']:.4f} | "
            f"{r['seconds']:.2f} | {r.get('basis_seconds', float('nan')):.2f} | {r['peak_mb']:.0f} | "
            f"{r['glb_mb']:.1f} | {r.get('time_ratio', float('nan')):.1f} | "
            f"{r.get('basis_ratio', float('nan')):.1f} | {r.get('peak_ratio', float('nan')):.1f} |"
        )
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    args = parse(argv)
    if args.threads:
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ[var] = str(args.threads)
    if args.check:
        rows = []
        for spec in args.check:
            rows.append(glb_check(spec))
            print(json.dumps(rows[-1]), file=sys.stderr)
        out = args.out.with_name("gltf_check.json") if args.out == OUT else args.out
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({"rows": rows, "cpus": os.cpu_count()}, indent=1) + "\n")
        print(check_markdown(rows))
        print(
            f"\nload average (1 min) at the end {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs; wrote {out}"
        )
        return 0 if all(not r["refused"] and r["within_tolerance"] for r in rows) else 1

    from facecast.server.faces import load_face
    from facecast.server.output import gltf
    from facecast.server.pipeline import Animator
    from facecast.server.render import _frame_chunks

    face = load_face(args.face)
    animator = Animator(face, backend="numpy")
    old = baseline_module(args.baseline)
    n_max = max(args.frames)
    anim = clip(face, max(n_max, *(args.stream or [0])), args.seed)
    import time

    t0 = time.perf_counter()
    full = animator.render(type(anim)(anim.fps, anim.states[:n_max], source=anim.source))
    render_s = time.perf_counter() - t0
    print(
        f"{args.face}: {face.n_vertices} vertices; rendered {n_max} frames in {render_s:.1f} s "
        f"({1e3 * render_s / n_max:.1f} ms/frame)",
        file=sys.stderr,
    )
    opts = {"mm_per_unit": face.mm_per_unit}
    rows: list[dict] = []
    for T in sorted(args.frames):
        frames = full[:T]
        results = {}
        for method, mod in (("old", old), ("new", gltf)):
            if method == "old" and args.old_max < T:
                continue
            sec, peak, (data, rec) = measure(
                lambda mod=mod, frames=frames: mod.encode_glb(
                    frames, face.vertices, face.triangles, 25.0, **opts
                ),
                args.repeats,
            )
            row = encode_row(T, face, method, sec, peak, data, rec, frames.nbytes / 2**20)
            bsec, _, _ = measure(
                lambda mod=mod, frames=frames: mod.morph_basis(
                    frames, face.vertices, 0.01 / face.mm_per_unit, **basis_options(mod)
                ),
                1,
            )
            row["basis_seconds"] = bsec
            results[method] = row
            print(
                f"  T={T} {method}: {sec:.2f} s (basis {bsec:.2f} s), peak {peak / 2**20:.0f} MB, "
                f"{rec['targets']} targets, max err {rec['max_error_mm']:.4f} mm",
                file=sys.stderr,
            )
        if "old" in results:
            results["new"]["time_ratio"] = results["old"]["seconds"] / results["new"]["seconds"]
            results["new"]["peak_ratio"] = results["old"]["peak_mb"] / results["new"]["peak_mb"]
            results["new"]["basis_ratio"] = (
                results["old"]["basis_seconds"] / results["new"]["basis_seconds"]
            )
        rows.extend(results.values())
    del full
    for T in sorted(args.stream or []):
        sub = type(anim)(anim.fps, anim.states[:T], source=anim.source)
        sec, peak, (data, rec) = measure(
            lambda sub=sub: gltf.encode_glb(
                _frame_chunks(animator, sub, None), face.vertices, face.triangles, 25.0, **opts
            ),
            1,
        )
        rows.append(
            encode_row(T, face, "new, streamed (incl. rendering)", sec, peak, data, rec, 0.0)
        )
        print(f"  T={T} streamed: {sec:.2f} s, peak {peak / 2**20:.0f} MB", file=sys.stderr)
    info = {
        "face": args.face,
        "vertices": face.n_vertices,
        "threads": args.threads,
        "baseline": args.baseline,
        "render_ms_per_frame": 1e3 * render_s / n_max,
        "load_avg": os.getloadavg(),
        "rows": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(info, indent=1) + "\n")
    print(markdown(rows))
    print(
        f"\nload average {os.getloadavg()[0]:.1f}; BLAS threads: {args.threads or 'default'}; "
        f"peak = tracemalloc peak of the encoder (input frames not counted); wrote {args.out}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
