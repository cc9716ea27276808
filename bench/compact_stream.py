"""Compact vertex streams against int16 and well-kept alternative coders, on the same streams.

    python bench/compact_stream.py [--faces default ict] [--tolerance-mm 0.1] [--seconds 8]

Streams (rendered with the batch pipeline, ``pipeline.Animator``, NumPy backend, at their own frame
rate): every Xface FAP file, speech through the lip-sync (``../shared/data/speech``), and a generated
mocap take (``mocap.synthetic``: 60 markers, 0.5 mm noise, gaps, head motion) through the batch
mocap driver; each on the built-in head and on ICT FaceKit. Per stream and coder:

- ``i16``: today's ``VERTICES_I16`` frames (56 + 6·V bytes; error half a per-frame step);
- ``compact``: ``VERTICES_COMPACT`` as the server sends it (deflate with the Z_RLE strategy, by
  zlib-ng when installed, as in ``protocol/compact.py``),
  and ``compact-lz4`` with zlib's default LZ77 search at level 4 (same format, other encoder choice);
- ``zstd-3`` / ``zstd-9``: the same residual byte planes as ``compact``, zstd instead of deflate;

meshoptimizer's vertex codec is left out: its PyPI wrapper (0.2.30a0, an alpha) corrupts the heap
("free(): corrupted unsorted chunks") round-tripping one 25k-vertex int32 buffer.

Reported: bytes per vertex per frame (whole frames, headers and transforms included), the largest
decoded error (mm, over every vertex of every frame; compact's decoder only), and CPU time per
frame on one thread (``time.thread_time``): encoding (for alternatives, their entropy stage next
to compact's zlib stage) and decoding in Python, and compact.js's decoding under Node (V8, the
engine of Chromium; ``DecompressionStream`` included). Keys every 250 ms of the stream's fps. The machine's
load average goes into the JSON: the times are CPU times but contend for caches with other work.
Writes ``bench/out/compact_stream.json`` and prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
import zlib
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parent / "out" / "compact_stream.json"


def streams(face, data: Path, seconds: float):
    """Yields ``(name, fps, vertices (T, V, 3) float32, transforms (T, G, 3, 4) float32)``."""
    from facecast.server.drivers import load_animation
    from facecast.server.mocap.io import write_take
    from facecast.server.mocap.synthetic import synthetic_take
    from facecast.server.pipeline import Animator

    def render(anim):
        anim.states = anim.states[: max(2, int(seconds * anim.fps))]
        a = Animator(face, backend="numpy", control_vertices=anim.control_vertices)
        _, tr = a.solve_batch(anim.states)
        return float(anim.fps), a.render(anim), tr

    for fap in sorted((data / "xface" / "faps").glob("*.fap")):
        yield ("fap:" + fap.stem, *render(load_animation(fap, face)))
    for wav in sorted((data / "speech").glob("*.wav")):
        yield ("speech:" + wav.stem, *render(load_animation(wav, face)))
    syn = synthetic_take(
        face, n_markers=60, seconds=seconds, fps=60.0, seed=7, noise_mm=0.5, gaps=True
    )
    with tempfile.TemporaryDirectory() as tmp:
        take = write_take(syn.take, Path(tmp) / "take.trc")
        (Path(tmp) / "take.layout.json").write_text(json.dumps(syn.layout))
        yield ("mocap:synthetic", *render(load_animation(take, face)))


def measure(
    name: str, fps: float, frames: np.ndarray, transforms: np.ndarray, face, tol_mm: float
) -> dict:
    import zstandard

    from facecast.protocol import compact as cp
    from facecast.protocol import frames as fr

    n, nv = len(frames), face.n_vertices
    tol = tol_mm / face.mm_per_unit
    key = max(1, round(0.25 * fps))
    clock = time.thread_time
    res: dict = {"stream": name, "fps": fps, "frames": n, "vertices": nv, "key_interval": key}

    t0 = clock()
    i16 = [fr.encode_vertices_i16(v, seq=i, t=0) for i, v in enumerate(frames)]
    t1 = clock()
    err16 = max(
        float(np.linalg.norm(fr.decode(b).positions() - v, axis=1).max())
        for b, v in zip(i16, frames)
    )
    res["i16"] = {
        "bpvf": sum(map(len, i16)) / n / nv,
        "max_err_mm": err16 * face.mm_per_unit,
        "enc_ms": (t1 - t0) / n * 1e3,
    }

    for label, level, strategy in (
        ("compact", 1, zlib.Z_RLE),
        ("compact-lz4", 4, zlib.Z_DEFAULT_STRATEGY),
    ):
        enc = cp.CompactEncoder(
            face.vertices,
            face.rigid_group,
            tolerance=tol,
            key_interval=key,
            level=level,
            strategy=strategy,
        )
        t0 = clock()
        wire = [
            enc.encode(v, tr, seq=i, t=i / fps) for i, (v, tr) in enumerate(zip(frames, transforms))
        ]
        enc_s = clock() - t0
        dec = cp.CompactDecoder(face.vertices, face.rigid_group)
        err, dec_s = 0.0, 0.0
        for b, v in zip(wire, frames):
            t0 = clock()
            _, x = dec.decode(b)
            dec_s += clock() - t0
            err = max(err, float(np.linalg.norm(x.astype(np.float64) - v, axis=1).max()))
        keys = [b for b in wire if cp.parse_compact(b).key]
        res[label] = {
            "bpvf": sum(map(len, wire)) / n / nv,
            "max_err_mm": err * face.mm_per_unit,
            "within_tolerance": err <= tol,
            "enc_ms": enc_s / n * 1e3,
            "dec_ms": dec_s / n * 1e3,
            "key_bpv": sum(map(len, keys)) / len(keys) / nv,
            "delta_bpv": (sum(map(len, wire)) - sum(map(len, keys))) / max(1, n - len(keys)) / nv,
        }
        if label == "compact":
            main = wire

    # Alternatives on the same residuals: the compact frames' own payloads, re-coded.
    raws, heads = [], []
    for b in main:
        f = cp.parse_compact(b)
        raw = zlib.decompress(f.payload)
        raws.append(raw)
        heads.append(len(b) - len(f.payload))
    t0 = clock()
    zl = []
    for r in raws:
        zc = getattr(cp, "_deflate", zlib).compressobj(1, zlib.DEFLATED, 15, 9, zlib.Z_RLE)
        zl.append(zc.compress(r) + zc.flush())
    res["compact"]["entropy_ms"] = (clock() - t0) / n * 1e3
    for label, level in (("zstd-3", 3), ("zstd-9", 9)):
        c = zstandard.ZstdCompressor(level=level)
        d = zstandard.ZstdDecompressor()
        t0 = clock()
        out = [c.compress(r) for r in raws]
        t1 = clock()
        for o in out:
            d.decompress(o)
        t2 = clock()
        res[label] = {
            "bpvf": (sum(heads) + sum(map(len, out))) / n / nv,
            "entropy_ms": (t1 - t0) / n * 1e3,
            "entropy_dec_ms": (t2 - t1) / n * 1e3,
        }
    del zl
    res["compact"]["js_dec"] = js_decode_ms(face, main)
    return res


CODERS = ("i16", "compact", "compact-lz4", "zstd-3", "zstd-9")

JS = Path(__file__).resolve().parents[1] / "client" / "web" / "js" / "compact.js"
NODE_RUNNER = """
import { readFileSync } from 'node:fs';
import { CompactDecoder } from './compact.mjs';
const dir = process.argv[2];
const load = (n) => {
  const b = readFileSync(`${dir}/${n}`);
  return b.buffer.slice(b.byteOffset, b.byteOffset + b.length);
};
const all = load('frames.bin'), sizes = JSON.parse(readFileSync(`${dir}/sizes.json`));
const frames = []; let o = 0;
for (const n of sizes) { frames.push(all.slice(o, o + n)); o += n; }
const dec = new CompactDecoder(new Float32Array(load('rest.bin')), new Uint8Array(load('groups.bin')));
const out = new Float32Array(new Float32Array(load('rest.bin')).length);
for (const f of frames.slice(0, 8)) await dec.decode(f, out);  // warm-up (JIT)
const t0 = performance.now(), c0 = process.cpuUsage();
for (const f of frames) await dec.decode(f, out);
const c = process.cpuUsage(c0);
console.log(JSON.stringify({ wall_ms: (performance.now() - t0) / frames.length,
                             cpu_ms: (c.user + c.system) / 1000 / frames.length }));
"""


def js_decode_ms(face, wire: list[bytes]) -> dict | None:
    """Per-frame decode time of ``client/web/js/compact.js`` under Node (V8, as in Chromium), or None."""
    import shutil
    import subprocess

    node = shutil.which("node")
    if node is None:
        return None
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        shutil.copy(JS, d / "compact.mjs")
        (d / "run.mjs").write_text(NODE_RUNNER)
        (d / "rest.bin").write_bytes(np.ascontiguousarray(face.vertices, "<f4").tobytes())
        (d / "groups.bin").write_bytes(np.ascontiguousarray(face.rigid_group, np.uint8).tobytes())
        (d / "frames.bin").write_bytes(b"".join(wire))
        (d / "sizes.json").write_text(json.dumps([len(b) for b in wire]))
        r = subprocess.run(
            [node, str(d / "run.mjs"), str(d)],
            capture_output=True,
            text=True,
            timeout=600,
            check=False,
        )
        return json.loads(r.stdout) if r.returncode == 0 else None


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--faces", nargs="+", default=["default", "ict"])
    p.add_argument("--tolerance-mm", type=float, default=0.1)
    p.add_argument("--seconds", type=float, default=8.0, help="longest stretch of each stream")
    p.add_argument("--out", default=str(OUT))
    a = p.parse_args(argv)

    from facecast.server.faces import load_face
    from facecast.server.paths import shared_data

    data = shared_data()
    if data is None:
        print("../shared/data is missing: nothing to measure", file=sys.stderr)
        return 2
    load0 = os.getloadavg()
    rows = []
    for spec in a.faces:
        path = str(data / "ict-facekit" / "generic_neutral_mesh.obj") if spec == "ict" else spec
        face = load_face(path)
        for name, fps, frames, tr in streams(face, data, a.seconds):
            r = measure(name, fps, frames, tr, face, a.tolerance_mm)
            r["face"] = spec
            rows.append(r)
            print(
                f"{spec:8s} {name:22s} compact {r['compact']['bpvf']:.3f} B/v/f, "
                f"err {r['compact']['max_err_mm']:.4f} mm, enc {r['compact']['enc_ms']:.2f} ms, "
                f"dec {r['compact']['dec_ms']:.2f} ms",
                file=sys.stderr,
            )
    summary = {c: {"bpvf_mean": float(np.mean([r[c]["bpvf"] for r in rows]))} for c in CODERS}
    for c in ("i16", "compact", "compact-lz4"):
        summary[c]["enc_ms_mean"] = float(np.mean([r[c]["enc_ms"] for r in rows]))
    for c in ("compact", "compact-lz4"):
        summary[c]["dec_ms_mean"] = float(np.mean([r[c]["dec_ms"] for r in rows]))
        summary[c]["max_err_mm"] = max(r[c]["max_err_mm"] for r in rows)
        summary[c]["all_within_tolerance"] = all(r[c]["within_tolerance"] for r in rows)
    js = [r["compact"]["js_dec"] for r in rows if r["compact"].get("js_dec")]
    if js:
        summary["compact"]["js_dec_cpu_ms_mean"] = float(np.mean([j["cpu_ms"] for j in js]))
        summary["compact"]["js_dec_wall_ms_mean"] = float(np.mean([j["wall_ms"] for j in js]))
    for c in ("compact", "zstd-3", "zstd-9"):
        summary[c]["entropy_ms_mean"] = float(np.mean([r[c]["entropy_ms"] for r in rows]))
    result = {
        "tolerance_mm": a.tolerance_mm,
        "loadavg_start": load0,
        "loadavg_end": os.getloadavg(),
        "cpus": os.cpu_count(),
        "streams": rows,
        "summary": summary,
    }
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))

    print(
        f"\nVertex streams at {a.tolerance_mm} mm, {len(rows)} streams; load average "
        f"{load0[0]:.1f} -> {result['loadavg_end'][0]:.1f} on {os.cpu_count()} CPUs\n"
    )
    print(
        "| face | stream | fps | i16 | compact | compact lz77-4 | zstd-3 | zstd-9 "
        "| max err mm | enc ms | dec ms |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['face']} | {r['stream']} | {r['fps']:g} | "
            + " | ".join(f"{r[c]['bpvf']:.3f}" for c in CODERS)
            + f" | {r['compact']['max_err_mm']:.4f} | {r['compact']['enc_ms']:.2f} | {r['compact']['dec_ms']:.2f} |"
        )
    s = summary
    print(
        "| **mean** | | | "
        + " | ".join(f"**{s[c]['bpvf_mean']:.3f}**" for c in CODERS)
        + f" | {s['compact']['max_err_mm']:.4f} | {s['compact']['enc_ms_mean']:.2f}"
        + f" | {s['compact']['dec_ms_mean']:.2f} |"
    )
    if "js_dec_cpu_ms_mean" in s["compact"]:
        print(
            f"\ncompact.js decode under Node: {s['compact']['js_dec_cpu_ms_mean']:.2f} ms CPU, "
            f"{s['compact']['js_dec_wall_ms_mean']:.2f} ms wall per frame (mean over streams)"
        )
    print(
        "\nbytes per vertex per frame; entropy stage ms/frame (same residuals): "
        + ", ".join(f"{c} {s[c]['entropy_ms_mean']:.2f}" for c in ("compact", "zstd-3", "zstd-9"))
    )
    return 0 if s["compact"]["all_within_tolerance"] else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
