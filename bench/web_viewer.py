"""The web viewer's speed in headless Chromium: draw rate and int16 decode time on the ICT head.

Starts a real ``facecast serve`` with the ICT FaceKit head, plays the server-side demo into a 60 fps
session, opens the page watching it (int16 and float32), and samples the page's own counters.
Baseline in the same run: the rate at which this Chromium runs requestAnimationFrame on an idle
page (the most a page can draw here). Writes bench/out/web_viewer.json and prints a table.

    python bench/web_viewer.py [--seconds 10] [--face PATH]
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
ARGS = ["--no-sandbox", "--disable-gpu", "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
        "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run"]

RAF_JS = """(ms) => new Promise((done) => {
  let n = 0; const t0 = performance.now();
  const tick = () => { n++; if (performance.now() - t0 < ms) requestAnimationFrame(tick); else done(1000 * n / (performance.now() - t0)); };
  requestAnimationFrame(tick);
})"""

SAMPLE_JS = """(ms) => new Promise((done) => {
  const v = facecast.viewer, s = v.stats, f0 = s.frames, d0 = facecast.state.drawTimes.length;
  const draws = []; const t0 = performance.now();
  const orig = facecast.renderer.draw.bind(facecast.renderer);
  facecast.renderer.draw = () => { draws.push(performance.now()); orig(); };
  s.decodeMs = [];
  setTimeout(() => {
    facecast.renderer.draw = orig;
    const el = (performance.now() - t0) / 1000, dec = [...s.decodeMs].sort((a, b) => a - b);
    const q = (p) => dec.length ? dec[Math.min(dec.length - 1, Math.floor(p * dec.length))] : null;
    done({ seconds: el, frames_received: s.frames - f0, received_fps: (s.frames - f0) / el,
           draw_fps: draws.length / el, decode_ms_p50: q(0.5), decode_ms_p95: q(0.95), decode_ms_max: dec.at(-1) ?? null,
           decode_samples: dec.length, dropped: s.dropped, bytes_per_frame: s.bytes });
  }, ms);
})"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--face", type=Path, default=ICT)
    ap.add_argument("--fps", type=float, default=60.0)
    ap.add_argument("--scale", type=float, default=None,
                    help="fix renderer.scale (drawing-buffer pixels per CSS pixel); default: the page adapts it")
    ap.add_argument("--chromium-arg", action="append", default=[], help="extra Chromium switch (repeatable)")
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    port, key = free_port(), "bench-key"
    url = f"http://127.0.0.1:{port}"
    env = {**os.environ, "FACECAST_ADMIN_KEY": key, "FACECAST_FACES": f"bench={args.face}"}
    data = tempfile.mkdtemp(prefix="facecast-web-bench-")
    server = subprocess.Popen([sys.executable, "-m", "facecast.server.cli", "serve", "--port", str(port),
                               "--data-dir", data], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    results: dict = {"face": str(args.face), "session_fps": args.fps, "cpus": os.cpu_count(), "scale": args.scale, "chromium_args": ARGS + args.chromium_arg,
                     "viewport": [args.width, args.height],
                     "load_average": os.getloadavg()}
    try:
        for _ in range(300):
            try:
                if httpx.get(url + "/healthz", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                time.sleep(0.2)
        hdr = {"Authorization": f"Bearer {key}"}
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path="/usr/bin/chromium", args=ARGS + args.chromium_arg)
            page = browser.new_page(viewport={"width": args.width, "height": args.height})
            page.goto(url + "/")
            results["raf_fps_idle"] = page.evaluate(RAF_JS, 3000)
            for encoding in ("i16", "f32"):
                s = httpx.post(url + "/v1/sessions", json={"face": "bench", "input": "fap", "fps": args.fps},
                               headers=hdr, timeout=300).json()
                httpx.post(f"{url}/v1/sessions/{s['id']}/demo", headers=hdr, timeout=60).raise_for_status()
                page.goto(f"{url}/?{encoding}#session={s['id']}&token={s['viewer_token']}&encoding={encoding}")
                page.set_default_timeout(300_000)
                page.wait_for_function("window.facecast && window.facecast.viewer.stats.frames > 30")
                if args.scale is not None:  # pin it: stop the page's adaptation
                    page.evaluate(f"Object.defineProperty(facecast.renderer, 'scale', {{get: () => {args.scale}, set: () => {{}}}})")
                time.sleep(2)
                sample = page.evaluate(SAMPLE_JS, int(args.seconds * 1000))
                sample["vertices"] = page.evaluate("facecast.renderer.mesh.V")
                sample["draw_vs_raf"] = sample["draw_fps"] / results["raf_fps_idle"]
                sample["render_scale"] = page.evaluate("facecast.renderer.scale")
                results[encoding] = sample
                httpx.delete(f"{url}/v1/sessions/{s['id']}", headers=hdr, timeout=60)
            browser.close()
    finally:
        server.terminate()
        server.wait(20)
    out = ROOT / "bench" / "out"
    out.mkdir(parents=True, exist_ok=True)
    (out / "web_viewer.json").write_text(json.dumps(results, indent=2))
    print(f"| stream | vertices | received fps | draw fps | draw / idle rAF ({results['raf_fps_idle']:.0f} fps) "
          "| decode p50 ms | decode p95 ms | bytes/frame | render scale |")
    print("|---|---|---|---|---|---|---|---|---|")
    for enc in ("i16", "f32"):
        r = results[enc]
        print(f"| {enc} | {r['vertices']} | {r['received_fps']:.1f} | {r['draw_fps']:.1f} | {r['draw_vs_raf']:.2f} "
              f"| {r['decode_ms_p50']} | {r['decode_ms_p95']:.2f} | {r['bytes_per_frame']} | {r['render_scale']:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
