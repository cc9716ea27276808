"""The web viewer's speed in headless Chromium: draw rate and int16 decode time on the ICT head.

Starts a real ``facecast serve`` with the ICT FaceKit head, plays the server-side demo into a 60 fps
session and opens the page watching it (int16, then float32), once per software GL back-end:

- ``llvmpipe``: ANGLE on Mesa's EGL (llvmpipe), software compositing (needs libegl-mesa0 and
  libgl1-mesa-dri);
- ``swiftshader``: ANGLE on SwiftShader (Chromium's own software Vulkan), ``--disable-gpu``.

Baseline in the same run and browser (the most a page can draw here): the requestAnimationFrame rate
of an idle page, of a page that only clears a full-window WebGL2 canvas every frame, and of that clear
plus N small visible triangles (``--sweep``; the ICT head has 52,220).

Counts are honest: ``drawn fps`` is canvas draws per second that showed a new vertex frame (one draw
is one presented canvas update; the page never draws off-frame), ``raf fps`` the page's animation
frames, ``received fps`` the frames that arrived. CPU per drawn frame is measured from /proc for the
Chromium GPU process (where software GL rasterises) and the page's renderer process. Writes
bench/out/web_viewer.json and prints a markdown table.

    python bench/web_viewer.py [--seconds 8] [--gl llvmpipe,swiftshader] [--scale S] [--shading vertex]
                               [--lod 0|1] [--width 1280 --height 720] [--chromium-arg ARG] [--screenshot DIR]
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
ICT = ROOT.parent / "shared" / "data" / "ict-facekit" / "generic_neutral_mesh.obj"
COMMON = ["--no-sandbox", "--disable-background-networking", "--disable-component-update", "--disable-sync",
          "--no-first-run"]
GL_ARGS = {
    "llvmpipe": ["--use-gl=angle", "--use-angle=gl-egl", "--ignore-gpu-blocklist", "--disable-gpu-compositing"],
    "swiftshader": ["--disable-gpu", "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"],
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

TCK = os.sysconf("SC_CLK_TCK")


def process_cpu() -> dict[str, float]:
    """CPU seconds (user + system) of this process's Chromium descendants, summed by process type."""
    children: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                ppid = int(Path(f"/proc/{d}/stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(d))
    out: dict[str, float] = {}
    stack = [os.getpid()]
    while stack:
        pid = stack.pop()
        stack.extend(children.get(pid, []))
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_text().replace("\0", " ").split()
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if not cmd or "chrom" not in Path(cmd[0]).name:
            continue
        kind = next((a.split("=", 1)[1] for a in cmd if a.startswith("--type=")), "browser")
        out[kind] = out.get(kind, 0.0) + (int(fields[11]) + int(fields[12])) / TCK
    return out


def pid_cpu(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TCK


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


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
        r["gpu_ms_per_frame"] = 1000 * (c1.get("gpu-process", 0) - c0.get("gpu-process", 0)) / r["frames"]
        out[mode] = r
    page.close()
    return out


def sample(page, server_pid: int, seconds: float) -> dict:
    """The page's counters and the processes' CPU over `seconds` of streaming."""
    page.evaluate("facecast.viewer.stats.decodeMs = []")
    c0, s0, a = process_cpu(), pid_cpu(server_pid), page.evaluate(COUNTERS_JS)
    time.sleep(seconds)
    c1, s1, b = process_cpu(), pid_cpu(server_pid), page.evaluate(COUNTERS_JS)
    el = (b["t"] - a["t"]) / 1000
    dec = sorted(b["decode"])
    def q(p: float) -> float | None:
        return dec[min(len(dec) - 1, int(p * len(dec)))] if dec else None

    fresh = max(1, b["fresh"] - a["fresh"])
    cpu = {k: c1.get(k, 0) - c0.get(k, 0) for k in c1}
    return {
        "seconds": el,
        "received_fps": (b["received"] - a["received"]) / el,
        "drawn_fps": (b["fresh"] - a["fresh"]) / el,          # draws that showed a new vertex frame
        "draws_fps": (b["draws"] - a["draws"]) / el,          # all canvas draws
        "raf_fps": (b["rafs"] - a["rafs"]) / el,
        "superseded": b["superseded"] - a["superseded"],      # received but never drawn (a newer one came first)
        "dropped_by_server": b["dropped"] - a["dropped"],
        "decode_ms_p50": q(0.5), "decode_ms_p95": q(0.95), "decode_ms_max": dec[-1] if dec else None,
        "decode_samples": len(dec),
        "gpu_ms_per_frame": 1000 * cpu.get("gpu-process", 0) / fresh,
        "renderer_ms_per_frame": 1000 * cpu.get("renderer", 0) / fresh,
        "server_cpu_percent": 100 * (s1 - s0) / el,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--face", type=Path, default=ICT)
    ap.add_argument("--fps", type=float, default=60.0)
    ap.add_argument("--gl", default="llvmpipe,swiftshader", help="comma-separated: " + ", ".join(GL_ARGS))
    ap.add_argument("--encodings", default="i16,f32")
    ap.add_argument("--scale", type=float, default=None,
                    help="fix renderer.scale (drawing-buffer pixels per CSS pixel); default: the page adapts it")
    ap.add_argument("--shading", choices=("pixel", "vertex"), default=None,
                    help="fix the lighting (default: the page adapts: per pixel, per vertex when it falls behind)")
    ap.add_argument("--lod", type=int, choices=(0, 1), default=None,
                    help="fix the level of detail (0: every triangle, 1: the coarse level; default: the page adapts)")
    ap.add_argument("--chromium-arg", action="append", default=[], help="extra Chromium switch (repeatable)")
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--screenshot", type=Path, default=None, help="directory for a screenshot per run")
    ap.add_argument("--sweep", default="10000,25000,50000,100000",
                    help="triangle counts for the dummy-scene ceiling (comma-separated; empty: none)")
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    port, key = free_port(), "bench-key"
    url = f"http://127.0.0.1:{port}"
    env = {**os.environ, "FACECAST_ADMIN_KEY": key, "FACECAST_FACES": f"bench={args.face}"}
    data = tempfile.mkdtemp(prefix="facecast-web-bench-")
    server = subprocess.Popen([sys.executable, "-m", "facecast.server.cli", "serve", "--port", str(port),
                               "--data-dir", data], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    results: dict = {"face": str(args.face), "session_fps": args.fps, "cpus": os.cpu_count(), "scale": args.scale,
                     "shading": args.shading, "viewport": [args.width, args.height],
                     "load_average_start": os.getloadavg(), "runs": []}
    try:
        for _ in range(300):
            try:
                if httpx.get(url + "/healthz", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                time.sleep(0.2)
        hdr = {"Authorization": f"Bearer {key}"}
        with sync_playwright() as p:
            for gl in args.gl.split(","):
                flags = COMMON + GL_ARGS[gl] + args.chromium_arg
                browser = p.chromium.launch(executable_path="/usr/bin/chromium", args=flags)
                sweep = tuple(int(n) for n in args.sweep.split(",") if n)
                base = ceiling(browser, args.width, args.height, 3000, sweep)
                results.setdefault("ceilings", {})[gl] = base
                page = browser.new_page(viewport={"width": args.width, "height": args.height})
                for encoding in args.encodings.split(","):
                    s = httpx.post(url + "/v1/sessions", json={"face": "bench", "input": "fap", "fps": args.fps},
                                   headers=hdr, timeout=300).json()
                    httpx.post(f"{url}/v1/sessions/{s['id']}/demo", headers=hdr, timeout=60).raise_for_status()
                    page.goto(f"{url}/?{encoding}#session={s['id']}&token={s['viewer_token']}&encoding={encoding}")
                    page.set_default_timeout(300_000)
                    page.wait_for_function("window.facecast && window.facecast.viewer.stats.frames > 30")
                    if args.scale is not None or args.shading or args.lod is not None:
                        page.evaluate("(q) => facecast.setQuality(q)",
                                      {"scale": args.scale, "shading": args.shading, "lod": args.lod})
                    time.sleep(4)  # let the page's adaptation settle
                    run = {"gl": gl, "flags": flags, "encoding": encoding, "ceiling": base,
                           **sample(page, server.pid, args.seconds)}
                    summary = page.evaluate("facecast.viewer.summary()")  # latency: frame sent -> in the page
                    run["latency_ms_p50"], run["latency_ms_p95"] = summary["latencyP50"], summary["latencyP95"]
                    run["vertices"] = page.evaluate("facecast.renderer.mesh.V")
                    run["lod"] = page.evaluate("facecast.renderer.lod")
                    run["triangles"] = page.evaluate("facecast.renderer.mesh.count / 3")
                    run["triangles_drawn"] = page.evaluate(
                        "(facecast.renderer.lod ? facecast.renderer.coarseLevel() : facecast.renderer.mesh).count / 3")
                    run["render_scale"] = page.evaluate("facecast.renderer.scale")
                    run["shading"] = page.evaluate("facecast.renderer.shading")
                    run["canvas"] = page.evaluate("[facecast.renderer.canvas.width, facecast.renderer.canvas.height]")
                    run["drawn_vs_clear_ceiling"] = run["drawn_fps"] / base["clear"]["fps"]
                    if args.screenshot:
                        args.screenshot.mkdir(parents=True, exist_ok=True)
                        page.screenshot(path=str(args.screenshot / f"web_viewer_{gl}_{encoding}.png"))
                    results["runs"].append(run)
                    httpx.delete(f"{url}/v1/sessions/{s['id']}", headers=hdr, timeout=60)
                browser.close()
    finally:
        server.terminate()
        server.wait(20)
    results["load_average_end"] = os.getloadavg()
    out = ROOT / "bench" / "out"
    out.mkdir(parents=True, exist_ok=True)
    (out / "web_viewer.json").write_text(json.dumps(results, indent=2))
    print(f"ICT head, viewport {args.width}x{args.height}, session {args.fps:g} fps, {os.cpu_count()} CPUs, "
          f"load average {results['load_average_start'][0]:.1f} -> {results['load_average_end'][0]:.1f}")
    print("| GL | stream | canvas px (scale, lighting) | triangles drawn | received fps | drawn fps (new frames) | raf fps "
          "| idle / clear ceiling fps | drawn / clear | GPU-process CPU ms/frame (clear) | renderer ms/frame "
          "| server CPU % | latency p50 / p95 ms | decode p50 / p95 ms |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in results["runs"]:
        c = r["ceiling"]
        print(f"| {r['gl']} | {r['encoding']} | {r['canvas'][0]}x{r['canvas'][1]} ({r['render_scale']:.2f}, {r['shading']}) "
              f"| {r['triangles_drawn']:.0f} of {r['triangles']:.0f} "
              f"| {r['received_fps']:.1f} | {r['drawn_fps']:.1f} | {r['raf_fps']:.1f} "
              f"| {c['idle']['fps']:.0f} / {c['clear']['fps']:.0f} | {r['drawn_vs_clear_ceiling']:.2f} "
              f"| {r['gpu_ms_per_frame']:.1f} ({c['clear']['gpu_ms_per_frame']:.1f}) | {r['renderer_ms_per_frame']:.1f} "
              f"| {r['server_cpu_percent']:.0f} | {r['latency_ms_p50']:.0f} / {r['latency_ms_p95']:.0f} "
              f"| {r['decode_ms_p50']:.2f} / {r['decode_ms_p95']:.2f} |")
    print()
    print(f"Ceiling: a page that only clears a {args.width}x{args.height} WebGL2 canvas, plus N small visible "
          "triangles (one draw call), every animation frame")
    print("| GL | idle rAF fps | clear fps (GPU ms/frame) | " + " | ".join(
        f"+{n // 1000}k triangles fps (GPU ms)" for n in sweep) + " |")
    print("|---|---|---|" + "---|" * len(sweep))
    for gl, c in results.get("ceilings", {}).items():
        print(f"| {gl} | {c['idle']['fps']:.0f} | {c['clear']['fps']:.0f} ({c['clear']['gpu_ms_per_frame']:.1f}) | "
              + " | ".join(f"{c[f'tris:{n}']['fps']:.0f} ({c[f'tris:{n}']['gpu_ms_per_frame']:.1f})" for n in sweep)
              + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
