"""The web viewer's speed in headless Chromium: draw rate and int16 decode time on the ICT head.

Starts a real ``facecast serve`` with the ICT FaceKit head, plays the server-side demo into a 60 fps
session and opens the page watching it (int16 by default) at full detail (every triangle, fixed render
quality: ``--scale 1 --shading vertex --lod 0`` unless told otherwise), once per *variant* and per
repeat, the variants interleaved so that a busy machine slows them alike:

- ``baseline``: the page with its draw-time savings switched off (triangles in mesh order, the
  mouth's interior drawn whole) in Chromium without the allocator switch (``ALLOC_RING``): the state
  before; ``page``: the page as it ships, in Chromium as this bench starts it; more in ``VARIANTS``
  (each saving alone switched off, Chromium switches, Mesa environment, WebGL context attributes),
  chosen with ``--variants``.

GL back-ends (``--gl``): ``llvmpipe``: ANGLE on Mesa's EGL (llvmpipe), software compositing (needs
libegl-mesa0 and libgl1-mesa-dri); ``swiftshader``: ANGLE on SwiftShader, ``--disable-gpu``.

Ceiling in the same run and browser (the most a page can draw here), once per repeat: the
requestAnimationFrame rate of an idle page, of a page that only clears a full-window WebGL2 canvas
every frame, and (first repeat, ``--sweep``) of that clear plus N small visible triangles.

Counts are honest: ``drawn fps`` is canvas draws per second that showed a new vertex frame (one draw
is one presented canvas update; the page never draws off-frame), ``raf fps`` the page's animation
frames, ``received fps`` the frames that arrived. CPU per drawn frame is measured from /proc for each
Chromium process type (the GPU process rasterises in software GL) and the server. The load average is
recorded for every run. Writes bench/out/web_viewer.json and prints markdown tables.

    python bench/web_viewer.py [--seconds 8] [--repeats 3] [--variants baseline,page] [--gl llvmpipe]
                               [--encodings i16] [--scale 1] [--shading vertex] [--lod 0]
                               [--width 1280 --height 720] [--chromium-arg ARG] [--screenshot DIR]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time
from pathlib import Path

import httpx

from facecast.server.harness import LocalServer, descendants, process_cpu_seconds

ROOT = Path(__file__).resolve().parents[1]
ICT = ROOT.parent / "shared" / "data" / "ict-facekit" / "generic_neutral_mesh.obj"
COMMON = [
    "--no-sandbox",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
#: PartitionAlloc (Chromium's malloc, which Mesa's allocations go through too) keeps more emptied slot
#: spans committed: llvmpipe allocates and frees its vertex and bin buffers every draw, and with the default
#: ring they were decommitted (madvise) and faulted in again every frame (~16 % of the GPU process's CPU).
ALLOC_RING = "--enable-features=PartitionAllocLargeEmptySlotSpanRing"
GL_ARGS = {
    "llvmpipe": [
        "--use-gl=angle",
        "--use-angle=gl-egl",
        "--ignore-gpu-blocklist",
        "--disable-gpu-compositing",
        ALLOC_RING,
    ],
    "swiftshader": [
        "--disable-gpu",
        "--use-gl=angle",
        "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader",
    ],
}

#: A page whose only work is clearing a full-window WebGL2 canvas (or nothing: mode 'idle') every frame.
CEILING_HTML = """<!doctype html><html><body style="margin:0;overflow:hidden">
<canvas id=c style="width:100vw;height:100vh;display:block"></canvas></body></html>"""
CEILING_JS = """([mode, ms, tris]) => new Promise((done) => {
  const c = document.getElementById('c'); c.width = c.clientWidth; c.height = c.clientHeight;
  const gl = mode === 'idle' ? null : c.getContext('webgl2', { antialias: false });
  if (gl && tris > 0) {  // a grid of small, visible, lit-free triangles over the middle half of the window
    const sh = (t, src) => { const x = gl.createShader(t); gl.shaderSource(x, src); gl.compileShader(x); return x; };
    const p = gl.createProgram();
    gl.attachShader(p, sh(gl.VERTEX_SHADER, `#version 300 es
layout(location = 0) in vec2 a; void main() { gl_Position = vec4(a, 0.5, 1.0); }`));
    gl.attachShader(p, sh(gl.FRAGMENT_SHADER, `#version 300 es
precision mediump float; out vec4 o; void main() { o = vec4(0.86, 0.64, 0.53, 1.0); }`));
    gl.linkProgram(p); gl.useProgram(p);
    const side = Math.ceil(Math.sqrt(tris / 2)), d = 1.4 / side, v = new Float32Array(6 * tris);
    for (let k = 0, i = 0; i < side; i++) for (let j = 0; j < side; j++) {
      const x = -0.7 + d * i, y = -0.7 + d * j;
      if (k < v.length) { v.set([x, y, x + d, y, x, y + d], k); k += 6; }
      if (k < v.length) { v.set([x + d, y, x + d, y + d, x, y + d], k); k += 6; }
    }
    gl.bindBuffer(gl.ARRAY_BUFFER, gl.createBuffer()); gl.bufferData(gl.ARRAY_BUFFER, v, gl.STATIC_DRAW);
    gl.enableVertexAttribArray(0); gl.vertexAttribPointer(0, 2, gl.FLOAT, false, 0, 0);
  }
  let n = 0; const t0 = performance.now();
  const tick = () => {
    if (gl) {
      gl.viewport(0, 0, c.width, c.height); gl.clearColor((n % 60) / 60, 0.1, 0.1, 1); gl.clear(gl.COLOR_BUFFER_BIT);
      if (tris > 0) gl.drawArrays(gl.TRIANGLES, 0, 3 * tris);
    }
    n++;
    if (performance.now() - t0 < ms) requestAnimationFrame(tick);
    else done({ frames: n, fps: 1000 * n / (performance.now() - t0), size: [c.width, c.height],
                renderer: gl ? gl.getParameter(gl.RENDERER) : null });
  };
  requestAnimationFrame(tick);
})"""

COUNTERS_JS = """() => { const c = facecast.counters, s = facecast.viewer.stats;
  return { t: performance.now(), rafs: c.rafs, draws: c.draws, fresh: c.newFrameDraws, received: s.frames,
           superseded: s.superseded, dropped: s.dropped, decode: [...s.decodeMs] }; }"""


def process_cpu() -> dict[str, float]:
    """CPU seconds (user + system) of this process's Chromium descendants, summed by process type."""
    out: dict[str, float] = {}
    for pid in descendants(os.getpid()):
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_text().replace("\0", " ").split()
        except OSError:
            continue
        if not cmd or "chrom" not in Path(cmd[0]).name:
            continue
        seconds = process_cpu_seconds(pid)
        if math.isnan(seconds):  # gone meanwhile
            continue
        kind = next((a.split("=", 1)[1] for a in cmd if a.startswith("--type=")), "browser")
        out[kind] = out.get(kind, 0.0) + seconds
    return out


def ceiling(browser, width: int, height: int, ms: int, sweep: tuple[int, ...] = ()) -> dict:
    """rAF rate (and GPU-process CPU per frame) of an idle page, of a full-window WebGL2 clear and,
    for each count in `sweep`, of a clear plus that many small visible triangles (keys "tris:N")."""
    page = browser.new_page(viewport={"width": width, "height": height})
    out = {}
    for mode in ("idle", "clear", *(f"tris:{n}" for n in sweep)):
        page.set_content(CEILING_HTML)  # a fresh canvas each time
        c0 = process_cpu()
        r = page.evaluate(CEILING_JS, [mode, ms, int(mode[5:]) if mode.startswith("tris:") else 0])
        c1 = process_cpu()
        r["gpu_ms_per_frame"] = (
            1000 * (c1.get("gpu-process", 0) - c0.get("gpu-process", 0)) / r["frames"]
        )
        out[mode] = r
    page.close()
    return out


#: Variants: name -> (Chromium switches to add, or to drop when written "-switch"; environment to add;
#: page setup run after the face has loaded and the quality is fixed, or "?query" for the page's URL:
#: WebGL context attributes).
VARIANTS: dict[str, tuple[list[str], dict[str, str], str]] = {
    "baseline": (
        ["-" + ALLOC_RING],
        {},
        "facecast.renderer.setVertexCacheOrder(false); facecast.renderer.mouthScissor = false",
    ),
    "page": ([], {}, ""),
    "no-alloc-ring": (["-" + ALLOC_RING], {}, ""),
    "mesh-order": ([], {}, "facecast.renderer.setVertexCacheOrder(false)"),
    "no-mouth-window": ([], {}, "facecast.renderer.mouthScissor = false"),
    "pixel-lit": ([], {}, "facecast.setQuality({ shading: 'pixel' })"),
    "scale-0.85": ([], {}, "facecast.setQuality({ scale: 0.85 })"),
    "opaque-canvas": ([], {}, "?alpha=false"),
    "desynchronized": ([], {}, "?desynchronized=true"),
    "in-process-gpu": (["--in-process-gpu"], {}, ""),
    "gpu-compositing": (["-" + "--disable-gpu-compositing"], {}, ""),
    "no-vsync": (["--disable-gpu-vsync", "--disable-frame-rate-limit"], {}, ""),
    "lp-threads-0": ([], {"LP_NUM_THREADS": "0"}, ""),
    "lp-threads-1": ([], {"LP_NUM_THREADS": "1"}, ""),
    "lp-vector-128": ([], {"LP_NATIVE_VECTOR_WIDTH": "128"}, ""),
}


def sample(page, server_pid: int, seconds: float) -> dict:
    """The page's counters and the processes' CPU over `seconds` of streaming."""
    page.evaluate("facecast.viewer.stats.decodeMs = []")
    c0, s0, a = process_cpu(), process_cpu_seconds(server_pid), page.evaluate(COUNTERS_JS)
    time.sleep(seconds)
    c1, s1, b = process_cpu(), process_cpu_seconds(server_pid), page.evaluate(COUNTERS_JS)
    el = (b["t"] - a["t"]) / 1000
    dec = sorted(b["decode"])

    def q(p: float) -> float | None:
        return dec[min(len(dec) - 1, int(p * len(dec)))] if dec else None

    fresh = max(1, b["fresh"] - a["fresh"])
    cpu = {k: c1.get(k, 0) - c0.get(k, 0) for k in c1}
    return {
        "seconds": el,
        "received_fps": (b["received"] - a["received"]) / el,
        "drawn_fps": (b["fresh"] - a["fresh"]) / el,  # draws that showed a new vertex frame
        "draws_fps": (b["draws"] - a["draws"]) / el,  # all canvas draws
        "raf_fps": (b["rafs"] - a["rafs"]) / el,
        "superseded": b["superseded"]
        - a["superseded"],  # received but never drawn (a newer one came first)
        "dropped_by_server": b["dropped"] - a["dropped"],
        "decode_ms_p50": q(0.5),
        "decode_ms_p95": q(0.95),
        "decode_ms_max": dec[-1] if dec else None,
        "decode_samples": len(dec),
        "gpu_ms_per_frame": 1000 * cpu.get("gpu-process", 0) / fresh,
        "renderer_ms_per_frame": 1000 * cpu.get("renderer", 0) / fresh,
        "chromium_ms_per_frame": 1000 * sum(cpu.values()) / fresh,  # every Chromium process
        "cpu_ms_per_frame_by_process": {k: 1000 * v / fresh for k, v in cpu.items()},
        "server_cpu_percent": 100 * (s1 - s0) / el,
        "load_average": os.getloadavg()[0],
    }


def flags_for(gl: str, variant: str, extra: list[str]) -> list[str]:
    add, _, _ = VARIANTS[variant]
    drop = {a[1:] for a in add if a.startswith("-" + "--")}
    return [a for a in COMMON + GL_ARGS[gl] + extra if a not in drop] + [
        a for a in add if not a.startswith("-" + "--")
    ]


def median(xs: list[float]) -> float:
    return statistics.median(xs) if xs else float("nan")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=8.0, help="measured seconds per run")
    ap.add_argument("--repeats", type=int, default=3, help="rounds over the variants (interleaved)")
    ap.add_argument(
        "--variants", default="baseline,page", help="comma-separated: " + ", ".join(VARIANTS)
    )
    ap.add_argument("--face", type=Path, default=ICT)
    ap.add_argument("--fps", type=float, default=60.0)
    ap.add_argument("--gl", default="llvmpipe", help="comma-separated: " + ", ".join(GL_ARGS))
    ap.add_argument("--encodings", default="i16")
    ap.add_argument(
        "--scale",
        type=float,
        default=1.0,
        help="renderer.scale (drawing-buffer pixels per CSS pixel)",
    )
    ap.add_argument("--shading", choices=("pixel", "vertex"), default="vertex")
    ap.add_argument(
        "--lod",
        type=int,
        choices=(0, 1),
        default=0,
        help="level of detail (0: every triangle, 1: the coarse level)",
    )
    ap.add_argument(
        "--chromium-arg", action="append", default=[], help="extra Chromium switch (repeatable)"
    )
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument(
        "--screenshot", type=Path, default=None, help="directory for a screenshot per variant"
    )
    ap.add_argument(
        "--sweep",
        default="25000,50000",
        help="triangle counts for the dummy-scene ceiling, first repeat only (comma-separated; empty: none)",
    )
    args = ap.parse_args()
    variants = [v for v in args.variants.split(",") if v]
    for v in variants:
        if v not in VARIANTS:
            ap.error(f"unknown variant {v!r}; known: {', '.join(VARIANTS)}")
    from playwright.sync_api import sync_playwright

    key = "bench-key"
    server = LocalServer(None, env={"FACECAST_FACES": f"bench={args.face}"}, admin_key=key)
    url = server.url
    sweep = tuple(int(n) for n in args.sweep.split(",") if n)
    results: dict = {
        "face": str(args.face),
        "session_fps": args.fps,
        "cpus": os.cpu_count(),
        "scale": args.scale,
        "shading": args.shading,
        "lod": args.lod,
        "viewport": [args.width, args.height],
        "variants": {
            v: {"add_flags": VARIANTS[v][0], "env": VARIANTS[v][1], "page": VARIANTS[v][2]}
            for v in variants
        },
        "load_average_start": os.getloadavg(),
        "ceilings": [],
        "runs": [],
    }
    try:
        server.start(120)
        hdr = {"Authorization": f"Bearer {key}"}
        with sync_playwright() as p:
            for rep in range(args.repeats):
                for gl in args.gl.split(","):
                    browser = p.chromium.launch(
                        executable_path="/usr/bin/chromium",
                        args=COMMON + GL_ARGS[gl] + args.chromium_arg,
                    )
                    base = ceiling(
                        browser, args.width, args.height, 3000, sweep if rep == 0 else ()
                    )
                    browser.close()
                    results["ceilings"].append(
                        {"repeat": rep, "gl": gl, **base, "load_average": os.getloadavg()[0]}
                    )
                    for variant in variants:
                        _, venv, setup = VARIANTS[variant]
                        flags = flags_for(gl, variant, args.chromium_arg)
                        browser = p.chromium.launch(
                            executable_path="/usr/bin/chromium",
                            args=flags,
                            env={**os.environ, **venv},
                        )
                        page = browser.new_page(
                            viewport={"width": args.width, "height": args.height}
                        )
                        page.set_default_timeout(300_000)
                        for encoding in args.encodings.split(","):
                            s = httpx.post(
                                url + "/v1/sessions",
                                json={"face": "bench", "input": "fap", "fps": args.fps},
                                headers=hdr,
                                timeout=300,
                            ).json()
                            httpx.post(
                                f"{url}/v1/sessions/{s['id']}/demo", headers=hdr, timeout=60
                            ).raise_for_status()
                            query = setup if setup.startswith("?") else "?"
                            page.goto(
                                f"{url}/{query}#session={s['id']}&token={s['viewer_token']}&encoding={encoding}"
                            )
                            page.wait_for_function(
                                "window.facecast && window.facecast.viewer.stats.frames > 30"
                            )
                            page.evaluate(
                                "(q) => facecast.setQuality(q)",
                                {"scale": args.scale, "shading": args.shading, "lod": args.lod},
                            )
                            if setup and not setup.startswith("?"):
                                page.evaluate(f"() => {{ {setup}; }}")
                            time.sleep(3)  # let the page settle
                            run = {
                                "repeat": rep,
                                "variant": variant,
                                "gl": gl,
                                "flags": flags,
                                "env": venv,
                                "encoding": encoding,
                                **sample(page, server.proc.pid, args.seconds),
                            }
                            summary = page.evaluate(
                                "facecast.viewer.summary()"
                            )  # latency: frame sent -> in the page
                            run["latency_ms_p50"], run["latency_ms_p95"] = (
                                summary["latencyP50"],
                                summary["latencyP95"],
                            )
                            info = page.evaluate("""() => { const r = facecast.renderer, m = r.mesh;
                              const level = r.lod ? r.coarseLevel() : m, gl = r.gl;
                              const dbg = gl.getExtension('WEBGL_debug_renderer_info');
                              return { vertices: m.V, lod: r.lod, triangles: m.count / 3,
                                       triangles_drawn:
                                         level.groups.reduce((n, g) => n + g.count, 0) / 3,
                                       render_scale: r.scale, shading: r.shading,
                                       canvas: [r.canvas.width, r.canvas.height],
                                       vertex_cache_order: r.vertexCacheOrder, mouth_window: r.mouthScissor,
                                       gl_renderer: dbg ? gl.getParameter(dbg.UNMASKED_RENDERER_WEBGL) : null }; }""")
                            run.update(info)
                            run["drawn_vs_clear_ceiling"] = run["drawn_fps"] / base["clear"]["fps"]
                            if args.screenshot and rep == 0:
                                args.screenshot.mkdir(parents=True, exist_ok=True)
                                page.screenshot(
                                    path=str(
                                        args.screenshot
                                        / f"web_viewer_{gl}_{encoding}_{variant}.png"
                                    )
                                )
                            results["runs"].append(run)
                            print(
                                f"repeat {rep} {gl} {encoding} {variant}: "
                                f"drawn {run['drawn_fps']:.1f} fps, GPU process "
                                f"{run['gpu_ms_per_frame']:.1f} ms/frame, load {run['load_average']:.2f}",
                                file=sys.stderr,
                                flush=True,
                            )
                            httpx.delete(f"{url}/v1/sessions/{s['id']}", headers=hdr, timeout=60)
                        browser.close()
    finally:
        server.stop()
    results["load_average_end"] = os.getloadavg()
    # Per variant: medians over the repeats, and the drawn-fps ratio to the baseline of the same repeat.
    summary = []
    for gl in args.gl.split(","):
        for encoding in args.encodings.split(","):
            for variant in variants:
                rs = [
                    r
                    for r in results["runs"]
                    if (r["gl"], r["encoding"], r["variant"]) == (gl, encoding, variant)
                ]
                if not rs:
                    continue
                ratios = []
                for r in rs:
                    b = [
                        x
                        for x in results["runs"]
                        if (x["gl"], x["encoding"], x["variant"], x["repeat"])
                        == (gl, encoding, "baseline", r["repeat"])
                    ]
                    if b and b[0]["drawn_fps"] > 0:
                        ratios.append(r["drawn_fps"] / b[0]["drawn_fps"])
                summary.append(
                    {
                        "gl": gl,
                        "encoding": encoding,
                        "variant": variant,
                        "runs": len(rs),
                        "drawn_fps_median": median([r["drawn_fps"] for r in rs]),
                        "drawn_fps_min": min(r["drawn_fps"] for r in rs),
                        "drawn_fps_max": max(r["drawn_fps"] for r in rs),
                        "received_fps_median": median([r["received_fps"] for r in rs]),
                        "vs_baseline_median": median(ratios) if ratios else None,
                        "gpu_ms_per_frame_median": median([r["gpu_ms_per_frame"] for r in rs]),
                        "renderer_ms_per_frame_median": median(
                            [r["renderer_ms_per_frame"] for r in rs]
                        ),
                        "chromium_ms_per_frame_median": median(
                            [r["chromium_ms_per_frame"] for r in rs]
                        ),
                        "decode_ms_p50_median": median(
                            [r["decode_ms_p50"] for r in rs if r["decode_ms_p50"] is not None]
                        ),
                        "decode_ms_p95_max": max(
                            (r["decode_ms_p95"] for r in rs if r["decode_ms_p95"] is not None),
                            default=None,
                        ),
                        "load_average_range": [
                            min(r["load_average"] for r in rs),
                            max(r["load_average"] for r in rs),
                        ],
                        "triangles_drawn": rs[0]["triangles_drawn"],
                        "triangles": rs[0]["triangles"],
                        "canvas": rs[0]["canvas"],
                        "shading": rs[0]["shading"],
                        "render_scale": rs[0]["render_scale"],
                    }
                )
    results["summary"] = summary
    out = ROOT / "bench" / "out"
    out.mkdir(parents=True, exist_ok=True)
    (out / "web_viewer.json").write_text(json.dumps(results, indent=2))
    la0, la1 = results["load_average_start"][0], results["load_average_end"][0]
    print(
        f"ICT head, viewport {args.width}x{args.height}, session {args.fps:g} fps, {os.cpu_count()} CPUs, "
        f"{args.repeats} repeats x {args.seconds:g} s, load average {la0:.1f} -> {la1:.1f}"
    )
    print(
        "| GL | stream | variant | canvas px (scale, lighting) | triangles drawn | received fps | drawn fps median "
        "(min-max) | vs baseline | GPU-process ms/frame | renderer ms/frame | all Chromium ms/frame "
        "| decode p50 / p95 ms | load avg |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in summary:
        vs = f"{r['vs_baseline_median']:.2f}" if r["vs_baseline_median"] else "–"
        print(
            f"| {r['gl']} | {r['encoding']} | {r['variant']} | {r['canvas'][0]}x{r['canvas'][1]} "
            f"({r['render_scale']:.2f}, {r['shading']}) "
            f"| {r['triangles_drawn']:.0f} of {r['triangles']:.0f} "
            f"| {r['received_fps_median']:.1f} | {r['drawn_fps_median']:.1f} "
            f"({r['drawn_fps_min']:.1f}-{r['drawn_fps_max']:.1f}) "
            f"| {vs} | {r['gpu_ms_per_frame_median']:.1f} | {r['renderer_ms_per_frame_median']:.1f} "
            f"| {r['chromium_ms_per_frame_median']:.1f} "
            f"| {r['decode_ms_p50_median']:.2f} / {r['decode_ms_p95_max'] or 0:.2f} "
            f"| {r['load_average_range'][0]:.1f}-{r['load_average_range'][1]:.1f} |"
        )
    print()
    print(
        f"Ceiling: a page that only clears a {args.width}x{args.height} WebGL2 canvas "
        "(plus N small visible triangles, one draw call, first repeat) every animation frame"
    )
    print(
        "| GL | repeat | idle rAF fps | clear fps (GPU ms/frame) | "
        + " | ".join(f"+{n // 1000}k triangles fps (GPU ms)" for n in sweep)
        + " | load avg |"
    )
    print("|---|---|---|---|" + "---|" * len(sweep) + "---|")
    for c in results["ceilings"]:
        print(
            f"| {c['gl']} | {c['repeat']} | {c['idle']['fps']:.0f} | {c['clear']['fps']:.0f} "
            f"({c['clear']['gpu_ms_per_frame']:.1f}) | "
            + " | ".join(
                f"{c[f'tris:{n}']['fps']:.0f} ({c[f'tris:{n}']['gpu_ms_per_frame']:.1f})"
                if f"tris:{n}" in c
                else "–"
                for n in sweep
            )
            + f" | {c['load_average']:.1f} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
