"""Compact vertex streams against int16 and well-kept alternative coders, on the same streams.

    python bench/compact_stream.py [--faces default ict] [--tolerance-mm 0.1] [--seconds 8]
                                   [--baseline REF]

Streams (rendered with the batch pipeline, ``pipeline.Animator``, NumPy backend, at their own frame
rate): every Xface FAP file, speech through the lip-sync (``../shared/data/speech``), and a generated
mocap take (``mocap.synthetic``: 60 markers, 0.5 mm noise, gaps, head motion) through the batch
mocap driver; each on the built-in head and on ICT FaceKit. Per stream and coder:

- ``i16``: today's ``VERTICES_I16`` frames (56 + 6·V bytes; error half a per-frame step);
- ``compact``: ``VERTICES_COMPACT`` (format 2: bitmaps of the non-zero residuals, then those) as
  the server sends it (deflated by ISA-L, level 1, as in ``protocol/compact.py``),
  and ``compact-lz4`` with zlib-ng's default LZ77 search at level 4 (same format, other encoder);
- ``zstd-3`` / ``zstd-9``: the same payloads as ``compact`` before deflate, zstd instead;
- ``compact-zng``: the same payloads deflated by zlib-ng (level 1, Z_RLE; ``protocol/compact.py``'s
  fall-back without ISA-L): still a zlib stream (same format, every decoder);

meshoptimizer's vertex codec is left out: its PyPI wrapper (0.2.30a0, an alpha) corrupts the heap
("free(): corrupted unsorted chunks") round-tripping one 25k-vertex int32 buffer.

Reported: bytes per vertex per frame (whole frames, headers and transforms included), the largest
decoded error (mm, over every vertex of every frame; compact's decoder only), and CPU time per
frame on one thread (``time.thread_time``): encoding (for alternatives, their entropy stage next
to compact's zlib stage) and decoding in Python; compact.js's decoding under Node (V8) and in
headless Chromium (the page's engine: wall time per frame and the renderer's CPU per frame, see
``chromium_decode_ms``); and, as the live server encodes a batch of sessions, process CPU per frame
of 8 sessions by the NumPy encoder and with the residual planes on the OpenCL device
(``batch_encode_ms``; the device's bytes must equal the NumPy encoder's). Keys every 250 ms of
the stream's fps. ``--baseline REF``: compact.py and compact.js of commit REF too, stream by
stream in the same run (a before/after table). The machine's load average goes into the JSON: the
times are CPU times but contend for caches with other work. Writes ``bench/out/compact_stream.json``
and prints markdown tables.
"""

from __future__ import annotations

import argparse
import importlib.util
import inspect
import json
import os
import subprocess
import sys
import tempfile
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

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
    name: str,
    fps: float,
    frames: np.ndarray,
    transforms: np.ndarray,
    face,
    tol_mm: float,
    base: Baseline | None = None,
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

    coders: list[tuple[str, ModuleType, int | None, int]] = [
        ("compact", cp, None, zlib.Z_RLE),
        ("compact-lz4", cp, 4, zlib.Z_DEFAULT_STRATEGY),
    ]
    if base is not None:  # the earlier commit's encoder and decoder, right after this one's
        coders.insert(1, ("compact-base", base.module, base.level, zlib.Z_RLE))
    wires: dict[str, list[bytes]] = {}
    for label, mod, level, strategy in coders:
        enc = mod.CompactEncoder(
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
        dec = mod.CompactDecoder(face.vertices, face.rigid_group)
        err, dec_s = 0.0, 0.0
        for b, v in zip(wire, frames):
            t0 = clock()
            _, x = dec.decode(b)
            dec_s += clock() - t0
            err = max(err, float(np.linalg.norm(x.astype(np.float64) - v, axis=1).max()))
        keys = [b for b in wire if b[6] & 1]  # header flag bit 0: a key frame (both formats)
        res[label] = {
            "bpvf": sum(map(len, wire)) / n / nv,
            "max_err_mm": err * face.mm_per_unit,
            "within_tolerance": err <= tol,
            "enc_ms": enc_s / n * 1e3,
            "dec_ms": dec_s / n * 1e3,
            "key_bpv": sum(map(len, keys)) / len(keys) / nv,
            "delta_bpv": (sum(map(len, wire)) - sum(map(len, keys))) / max(1, n - len(keys)) / nv,
        }
        wires[label] = wire
    main = wires["compact"]

    # Alternatives on the same residuals: the compact frames' own payloads, re-coded.
    raws, heads = [], []
    for b in main:
        f = cp.parse_compact(b)
        raw = zlib.decompress(f.payload)
        raws.append(raw)
        heads.append(len(b) - len(f.payload))
    coder = cp.CompactEncoder(face.vertices[:1], face.rigid_group[:1], tolerance=tol)
    t0 = clock()
    zl = [coder.deflate(r) for r in raws]
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
    res["compact-zng"] = zng_row(raws, heads, n, nv)
    res["compact"]["batch"] = batch_encode_ms(face, fps, frames, transforms, tol, key, main)
    res["compact"]["js_dec"] = js_decode_ms(face, main)
    res["compact"]["chromium_dec"] = chromium_decode_ms(face, main)
    if base is not None:
        res["compact-base"]["chromium_dec"] = chromium_decode_ms(
            face, wires["compact-base"], base.js
        )
    return res


def zng_row(raws: list[bytes], heads: list[int], n: int, nv: int) -> dict | None:
    """The same compact frames with their payloads deflated by zlib-ng (level 1, Z_RLE:
    ``protocol/compact.py``'s coder without ISA-L) instead of ISA-L: the same format (a zlib
    stream every decoder reads, checked here), the other encoder's speed and size; None without
    ``zlib_ng``."""
    try:
        from zlib_ng import zlib_ng
    except ImportError:
        return None

    def deflate(r: bytes) -> bytes:
        zc = zlib_ng.compressobj(1, zlib.DEFLATED, 15, 9, zlib.Z_RLE)
        return zc.compress(r) + zc.flush()

    clock = time.thread_time
    t0 = clock()
    out = [deflate(r) for r in raws]
    t1 = clock()
    same = all(zlib.decompress(o) == r for o, r in zip(out, raws))
    return {
        "bpvf": (sum(heads) + sum(map(len, out))) / n / nv,
        "entropy_ms": (t1 - t0) / n * 1e3,
        "zlib_decodes_it": same,
    }


#: Sessions encoded together in ``batch_encode_ms`` (as a server's batch of busy sessions).
BATCH = 8


def batch_encode_ms(face, fps, frames, transforms, tol, key, wire) -> dict | None:
    """Process CPU per frame (all threads: PoCL's too) of ``BATCH`` sessions of the stream (each
    from another start) encoded a batch at a time as the live server does: by the NumPy encoder
    (``host_cpu_ms``), and with the residual planes on the OpenCL device
    (``backends.opencl.compact``, ``device_cpu_ms``); ``same_bytes``: the device's frames of the
    first session equal ``wire``, the host encoder's. None without an OpenCL device."""
    try:
        from facecast.server.backends.opencl import aligned_empty, default_context
        from facecast.server.backends.opencl.compact import DeviceCompact, encode_batch
    except ImportError:
        return None
    ctx = default_context()
    if ctx is None:
        return None
    from facecast.protocol.compact import CompactEncoder

    device = DeviceCompact(ctx)
    n = len(frames)

    def encoders():
        return [
            CompactEncoder(face.vertices, face.rigid_group, tolerance=tol, key_interval=key)
            for _ in range(BATCH)
        ]

    buf = aligned_empty((BATCH,) + frames.shape[1:], np.float32)
    starts = [(s * n) // BATCH for s in range(BATCH)]
    host, dev, first = encoders(), encoders(), []
    host_s = dev_s = 0.0
    for i in range(n):
        idx = [(i + a) % n for a in starts]
        buf[:] = frames[idx]
        t0 = time.process_time()
        for s, e in enumerate(host):
            e.encode(buf[s], transforms[idx[s]], seq=i, t=i / fps)
        t1 = time.process_time()
        out = encode_batch(
            device, buf, [(e, s, transforms[idx[s]], i, i / fps, 0.0) for s, e in enumerate(dev)]
        )
        dev_s += time.process_time() - t1
        host_s += t1 - t0
        first.append(out[0])
    return {
        "sessions": BATCH,
        "host_cpu_ms": host_s / n / BATCH * 1e3,
        "device_cpu_ms": dev_s / n / BATCH * 1e3,
        "same_bytes": first == wire,
    }


@dataclass
class Baseline:
    """``protocol/compact.py`` and ``client/web/js/compact.js`` of an earlier commit, measured
    on the same streams in the same run (its frames decoded by its own decoders)."""

    ref: str
    module: ModuleType
    js: Path
    level: int | None  #: the encoder's default deflate level (format 1 took 1, format 2 None)

    @staticmethod
    def load(ref: str, tmp: Path) -> Baseline:
        root = Path(__file__).resolve().parents[1]

        def show(path: str) -> str:
            return subprocess.run(
                ["git", "show", f"{ref}:{path}"],
                cwd=root,
                capture_output=True,
                text=True,
                check=True,
            ).stdout

        (tmp / "compact_base.py").write_text(show("protocol/compact.py"))
        (tmp / "compact_base.js").write_text(show("client/web/js/compact.js"))
        name = "facecast.protocol._compact_base"  # in the package: its relative imports work
        spec = importlib.util.spec_from_file_location(name, tmp / "compact_base.py")
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
        default = inspect.signature(module.CompactEncoder).parameters["level"].default
        return Baseline(ref, module, tmp / "compact_base.js", default)


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
for (let k = 0; k < 2; k++) for (const f of frames) await dec.decode(f, out);  // warm-up (JIT)
// whole passes (a key opens each), at least 3 and 1 s; each frame timed alone: the median
const times = [], t0 = performance.now(), c0 = process.cpuUsage();
while (times.length < 3 * frames.length || performance.now() - t0 < 1000) {
  for (const f of frames) {
    const t = performance.now();
    dec.decode(f, out);
    times.push(performance.now() - t);
  }
}
const c = process.cpuUsage(c0);
times.sort((a, b) => a - b);
console.log(JSON.stringify({ wall_ms: times[times.length >> 1],
                             cpu_ms: (c.user + c.system) / 1000 / times.length }));
"""


def write_decode_inputs(d: Path, face, wire: list[bytes]) -> None:
    """The files a JS decoder run reads from ``d``: ``rest.bin`` (rest vertices, (n, 3) <f4),
    ``groups.bin`` (rigid groups, (n,) u8), ``frames.bin`` (the wire frames back to back) and
    ``sizes.json`` (each frame's byte length)."""
    (d / "rest.bin").write_bytes(np.ascontiguousarray(face.vertices, "<f4").tobytes())
    (d / "groups.bin").write_bytes(np.ascontiguousarray(face.rigid_group, np.uint8).tobytes())
    (d / "frames.bin").write_bytes(b"".join(wire))
    (d / "sizes.json").write_text(json.dumps([len(b) for b in wire]))


def js_decode_ms(face, wire: list[bytes]) -> dict | None:
    """Per-frame decode time of ``client/web/js/compact.js`` under Node (V8, as in Chromium), or
    None: ``wall_ms`` the median frame (each timed alone, over passes of at least a second after
    two of warm-up), ``cpu_ms`` the process's CPU time per frame over those passes."""
    import shutil
    import subprocess

    node = shutil.which("node")
    if node is None:
        return None
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        shutil.copy(JS, d / "compact.mjs")
        (d / "run.mjs").write_text(NODE_RUNNER)
        write_decode_inputs(d, face, wire)
        r = subprocess.run(
            [node, str(d / "run.mjs"), str(d)],
            capture_output=True,
            text=True,
            timeout=600,
            check=False,
        )
        return json.loads(r.stdout) if r.returncode == 0 else None


CHROMIUM_PAGE = """<!doctype html><meta charset=utf-8><title>compact decode</title>
<script type=module>
import { CompactDecoder } from './compact.js';
const get = async (n) => (await fetch(n)).arrayBuffer();
let frames, dec, out;
window.setup = async () => {  // apart from run: the renderer's CPU time is read around run alone
  const [rest, groups, all] = await Promise.all(['rest.bin', 'groups.bin', 'frames.bin'].map(get));
  const sizes = await (await fetch('sizes.json')).json();
  frames = []; let o = 0;
  for (const n of sizes) { frames.push(all.slice(o, o + n)); o += n; }
  dec = new CompactDecoder(new Float32Array(rest), new Uint8Array(groups));
  out = new Float32Array(new Float32Array(rest).length);
  for (let k = 0; k < 2; k++) for (const f of frames) await dec.decode(f, out);  // warm-up (JIT)
};
window.run = async (minMs) => {
  // each frame timed alone (decode's work is synchronous: it awaits nothing), in whole passes (a
  // key opens each): the median frame is robust to the preemptions of a loaded machine, which
  // land on a few frames, where a pass's mean is not
  const times = [], start = performance.now();
  while (times.length < 3 * frames.length || performance.now() - start < minMs) {
    for (const f of frames) {
      const t0 = performance.now();
      dec.decode(f, out);
      times.push(performance.now() - t0);
    }
  }
  const wall = performance.now() - start;
  times.sort((a, b) => a - b);
  const q = (p) => times[Math.min(times.length - 1, Math.floor(p * times.length))];
  return { wall_ms: q(0.5), wall_ms_p10: q(0.1), wall_ms_p90: q(0.9),
           wall_ms_mean: wall / times.length, decoded: times.length,
           isolated: self.crossOriginIsolated };  // isolated: performance.now() to 5 us, not 100
};
window.ready = true;
</script>"""


def chromium_decode_ms(face, wire: list[bytes], js: Path = JS, seconds: float = 2.0) -> dict | None:
    """Per-frame decode time of ``compact.js`` in the page's engine: headless Chromium
    (``/usr/bin/chromium``, ``--no-sandbox --disable-gpu``, driven by playwright), the module and
    the recorded frames served from loopback, decoded in passes over the stream for ``seconds``:
    ``wall_ms`` the median of every frame's own decode time (``wall_ms_p10``, ``wall_ms_p90``
    around it; ``wall_ms_mean``: wall time over frames, with the loop and any preemption), timed
    in a cross-origin isolated page (``isolated``: ``performance.now()`` to 5 us, not 100 us):
    what a frame costs the page, robust to a loaded machine, where a pass's mean is not;
    ``cpu_ms`` the renderer processes' CPU time (/proc) per decoded frame (all the page's work:
    the loop, timers, garbage collection); None without Chromium/playwright."""
    import functools
    import http.server
    import shutil
    import threading

    from web_viewer import process_cpu  # CPU seconds of this process's Chromium, by type

    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        return None
    if not Path("/usr/bin/chromium").exists():
        return None
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        shutil.copy(js, d / "compact.js")
        (d / "index.html").write_text(CHROMIUM_PAGE)
        write_decode_inputs(d, face, wire)

        class Quiet(http.server.SimpleHTTPRequestHandler):
            def log_message(self, *a) -> None:
                pass

            def end_headers(self) -> None:  # cross-origin isolated: a finer performance.now()
                self.send_header("Cross-Origin-Opener-Policy", "same-origin")
                self.send_header("Cross-Origin-Embedder-Policy", "require-corp")
                super().end_headers()

        srv = http.server.ThreadingHTTPServer(
            ("127.0.0.1", 0), functools.partial(Quiet, directory=str(d))
        )
        threading.Thread(target=srv.serve_forever, daemon=True).start()
        try:
            with sync_playwright() as p:
                browser = p.chromium.launch(
                    executable_path="/usr/bin/chromium", args=["--no-sandbox", "--disable-gpu"]
                )
                try:
                    page = browser.new_page()
                    page.goto(f"http://127.0.0.1:{srv.server_address[1]}/index.html")
                    page.wait_for_function("window.ready === true")
                    page.evaluate("() => window.setup()")
                    cpu0 = process_cpu().get("renderer", 0.0)
                    r = page.evaluate("(ms) => window.run(ms)", 1000 * seconds)
                    r["cpu_ms"] = 1000 * (process_cpu().get("renderer", 0.0) - cpu0) / r["decoded"]
                    return r
                finally:
                    browser.close()
        finally:
            srv.shutdown()
            srv.server_close()


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--faces", nargs="+", default=["default", "ict"])
    p.add_argument("--tolerance-mm", type=float, default=0.1)
    p.add_argument("--seconds", type=float, default=8.0, help="longest stretch of each stream")
    p.add_argument(
        "--baseline",
        metavar="REF",
        help="also measure protocol/compact.py and compact.js of this git commit (e.g. HEAD~3), "
        "stream by stream right after this checkout's: before/after in one run",
    )
    p.add_argument("--out", default=str(OUT))
    a = p.parse_args(argv)
    tmp = tempfile.TemporaryDirectory()
    base = Baseline.load(a.baseline, Path(tmp.name)) if a.baseline else None

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
            r = measure(name, fps, frames, tr, face, a.tolerance_mm, base)
            r["face"] = spec
            rows.append(r)
            print(
                f"{spec:8s} {name:22s} compact {r['compact']['bpvf']:.3f} B/v/f, "
                f"err {r['compact']['max_err_mm']:.4f} mm, enc {r['compact']['enc_ms']:.2f} ms, "
                f"dec {r['compact']['dec_ms']:.2f} ms",
                file=sys.stderr,
            )
    summary = {c: {"bpvf_mean": float(np.mean([r[c]["bpvf"] for r in rows]))} for c in CODERS}
    compacts = ("compact", "compact-lz4") + (("compact-base",) if base else ())
    if base:
        summary["compact-base"] = {
            "bpvf_mean": float(np.mean([r["compact-base"]["bpvf"] for r in rows]))
        }
    for c in ("i16", *compacts):
        summary[c]["enc_ms_mean"] = float(np.mean([r[c]["enc_ms"] for r in rows]))
    for c in compacts:
        summary[c]["dec_ms_mean"] = float(np.mean([r[c]["dec_ms"] for r in rows]))
        summary[c]["max_err_mm"] = max(r[c]["max_err_mm"] for r in rows)
        summary[c]["all_within_tolerance"] = all(r[c]["within_tolerance"] for r in rows)
    for c in ("compact", "compact-base"):
        ch = [r[c]["chromium_dec"] for r in rows if r.get(c, {}).get("chromium_dec")]
        if ch:
            summary[c]["chromium_dec_wall_ms_mean"] = float(np.mean([x["wall_ms"] for x in ch]))
            summary[c]["chromium_dec_cpu_ms_mean"] = float(np.mean([x["cpu_ms"] for x in ch]))
    js = [r["compact"]["js_dec"] for r in rows if r["compact"].get("js_dec")]
    if js:
        summary["compact"]["js_dec_cpu_ms_mean"] = float(np.mean([j["cpu_ms"] for j in js]))
        summary["compact"]["js_dec_wall_ms_mean"] = float(np.mean([j["wall_ms"] for j in js]))
    bt = [r["compact"]["batch"] for r in rows if r["compact"].get("batch")]
    if bt:
        for k in ("host_cpu_ms", "device_cpu_ms"):
            summary["compact"][f"batch_{k}_mean"] = float(np.mean([b[k] for b in bt]))
        summary["compact"]["batch_same_bytes"] = all(b["same_bytes"] for b in bt)
    for c in ("compact", "zstd-3", "zstd-9"):
        summary[c]["entropy_ms_mean"] = float(np.mean([r[c]["entropy_ms"] for r in rows]))
    result = {
        "tolerance_mm": a.tolerance_mm,
        "baseline": a.baseline,
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
    if "batch_host_cpu_ms_mean" in s["compact"]:
        print(
            f"\ncompact encoding, {BATCH} sessions a batch (process CPU per frame, mean over "
            f"streams): NumPy {s['compact']['batch_host_cpu_ms_mean']:.3f} ms, residuals on the "
            f"OpenCL device {s['compact']['batch_device_cpu_ms_mean']:.3f} ms; same bytes: "
            f"{s['compact']['batch_same_bytes']}"
        )
    if "js_dec_cpu_ms_mean" in s["compact"]:
        print(
            f"\ncompact.js decode under Node: {s['compact']['js_dec_cpu_ms_mean']:.2f} ms CPU, "
            f"{s['compact']['js_dec_wall_ms_mean']:.2f} ms wall per frame (mean over streams)"
        )
    if "chromium_dec_wall_ms_mean" in s["compact"]:
        print(
            f"compact.js decode in headless Chromium: {s['compact']['chromium_dec_wall_ms_mean']:.2f}"
            f" ms wall, {s['compact']['chromium_dec_cpu_ms_mean']:.2f} ms renderer CPU per frame"
        )
    if base:
        print(f"\nBefore ({a.baseline}) -> after, per frame (mean over streams):\n")
        print("| face | stream | B/v/f | enc ms | Python dec ms | Chromium dec ms (wall / CPU) |")
        print("|---|---|---|---|---|---|")
        for r in rows + [{"face": "**mean**", "stream": "", "m": 1}]:
            if "m" in r:
                b, c = s["compact-base"], s["compact"]
                vals = [(b[k], c[k]) for k in ("bpvf_mean", "enc_ms_mean", "dec_ms_mean")]
                ch = [
                    (b.get(k, float("nan")), c.get(k, float("nan")))
                    for k in ("chromium_dec_wall_ms_mean", "chromium_dec_cpu_ms_mean")
                ]
            else:
                b, c = r["compact-base"], r["compact"]
                vals = [(b[k], c[k]) for k in ("bpvf", "enc_ms", "dec_ms")]
                bc, cc = b.get("chromium_dec") or {}, c.get("chromium_dec") or {}
                ch = [
                    (bc.get(k, float("nan")), cc.get(k, float("nan")))
                    for k in ("wall_ms", "cpu_ms")
                ]
            print(
                f"| {r['face']} | {r['stream']} | "
                + " | ".join(f"{x:.3f} -> {y:.3f}" for x, y in vals)
                + f" | {ch[0][0]:.2f} / {ch[1][0]:.2f} -> {ch[0][1]:.2f} / {ch[1][1]:.2f} |"
            )
    zng = [r["compact-zng"] for r in rows if r.get("compact-zng")]
    if zng:
        summary["compact-zng"] = {
            "bpvf_mean": float(np.mean([x["bpvf"] for x in zng])),
            "entropy_ms_mean": float(np.mean([x["entropy_ms"] for x in zng])),
            "zlib_decodes_it": all(x["zlib_decodes_it"] for x in zng),
        }
        print(
            f"\ncompact deflated by zlib-ng level 1 Z_RLE instead (same format; zlib decodes it: "
            f"{summary['compact-zng']['zlib_decodes_it']}): "
            f"{summary['compact-zng']['bpvf_mean']:.3f} B/v/f mean against "
            f"{s['compact']['bpvf_mean']:.3f}, deflate {summary['compact-zng']['entropy_ms_mean']:.3f}"
            f" ms/frame against {s['compact']['entropy_ms_mean']:.3f}"
        )
    print(
        "\nbytes per vertex per frame; entropy stage ms/frame (same residuals): "
        + ", ".join(f"{c} {s[c]['entropy_ms_mean']:.2f}" for c in ("compact", "zstd-3", "zstd-9"))
    )
    ok = s["compact"]["all_within_tolerance"] and s["compact"].get("batch_same_bytes", True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
