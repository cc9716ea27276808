"""The web page's per-frame vertex normals (``client/web/js/mesh.js`` ``VertexNormals.compute``) in Node,
against the same class at a baseline revision (from git history), in the same run.

    python bench/web_normals.py [--face default] [--baseline bd2ccb2] [--rounds 7] [--reps 40]

The frame: XFace ``joy.fap`` rendered on ``--face`` (``pipeline.Animator``, NumPy backend), its last
frame as float32 (what the page's compact and float32 frames hand to the renderer); the rest pose
when the shared data is absent. Rounds alternate the two implementations (``--reps`` calls each) so
that a busy machine slows them alike; the table gives the median ms per call and the ratio, and the
load average. Writes ``bench/out/web_normals.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from facecast.server.bench.history import source_at

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "out" / "web_normals.json"
MESH_JS = "client/web/js/mesh.js"

RUN_MJS = """
import { readFileSync } from 'node:fs';
import { VertexNormals as Now } from './now.mjs';
import { VertexNormals as Then } from './then.mjs';
const [dir, rounds, reps] = [process.argv[2], +process.argv[3], +process.argv[4]];
const raw = (name) => {
  const b = readFileSync(`${dir}/${name}`);
  return b.buffer.slice(b.byteOffset, b.byteOffset + b.length);
};
const tri = new Uint32Array(raw('triangles.u32')), frame = new Float32Array(raw('frame.f32')), V = frame.length / 3;
const rest = new Float32Array(raw('rest.f32'));  // a constructor that takes no rest pose ignores it
const impl = { now: new Now(tri, V, rest), then: new Then(tri, V, rest) };
const ms = { now: [], then: [] };
for (const k of ['now', 'then']) for (let i = 0; i < 5; i++) impl[k].compute(frame, null);  // warm up
for (let r = 0; r < rounds; r++) {
  for (const k of r % 2 ? ['then', 'now'] : ['now', 'then']) {
    const t0 = performance.now();
    for (let i = 0; i < reps; i++) impl[k].compute(frame, null);
    ms[k].push((performance.now() - t0) / reps);
  }
}
console.log(JSON.stringify(ms));
"""


def frame_of(face_spec: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """``(frame (V, 3) float32, rest (V, 3) float32, triangles (F, 3) uint32, what the frame is)``."""
    from facecast.server.drivers.fap import load as load_fap
    from facecast.server.faces import load_face
    from facecast.server.paths import shared_data
    from facecast.server.pipeline import Animator

    face = load_face(face_spec)
    tri = np.ascontiguousarray(face.triangles, dtype=np.uint32)
    rest = np.ascontiguousarray(face.vertices, dtype=np.float32)
    data = shared_data()
    joy = data / "xface" / "faps" / "joy.fap" if data is not None else None
    if joy is None or not joy.is_file():
        return rest, rest, tri, "rest pose"
    frames = Animator(face, backend="numpy").render(load_fap(joy, face))
    return np.ascontiguousarray(frames[-1], dtype=np.float32), rest, tri, "last frame of joy.fap"


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--face", default="default")
    ap.add_argument("--baseline", default="bd2ccb2", help="git revision of the old mesh.js")
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--reps", type=int, default=40, help="calls per implementation and round")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    node = shutil.which("node")
    if node is None:
        print("web_normals: Node.js is not installed (.ci/setup installs it)", file=sys.stderr)
        return 2
    frame, rest, tri, what = frame_of(args.face)
    old = source_at(ROOT, args.baseline, MESH_JS)
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="web-normals-") as tmp:
        d = Path(tmp)
        shutil.copy(ROOT / MESH_JS, d / "now.mjs")
        (d / "then.mjs").write_text(old)
        (d / "run.mjs").write_text(RUN_MJS)
        frame.tofile(d / "frame.f32")
        rest.tofile(d / "rest.f32")
        tri.tofile(d / "triangles.u32")
        r = subprocess.run(
            [node, str(d / "run.mjs"), str(d), str(args.rounds), str(args.reps)],
            check=True,
            capture_output=True,
            text=True,
        )
    ms = json.loads(r.stdout)
    med = {k: float(np.median(v)) for k, v in ms.items()}
    ratios = [n / t for n, t in zip(ms["now"], ms["then"])]
    result = {
        "face": args.face,
        "vertices": int(frame.shape[0]),
        "triangles": int(tri.shape[0]),
        "frame": what,
        "baseline": args.baseline,
        "ms_per_call": ms,
        "median_ms": med,
        "ratio_now_over_baseline_median": float(np.median(ratios)),
        "ratio_range": [min(ratios), max(ratios)],
        "load_average": [round((a + b) / 2, 2) for a, b in zip(load0, os.getloadavg())],
        "cpus": os.cpu_count(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print("| implementation | ms per frame (median) |\n|---|---:|")
    print(f"| mesh.js now | {med['now']:.2f} |\n| mesh.js at {args.baseline} | {med['then']:.2f} |")
    print(
        f"\nnow / baseline {result['ratio_now_over_baseline_median']:.2f} "
        f"(rounds {min(ratios):.2f}-{max(ratios):.2f}); {result['vertices']} vertices, "
        f"{result['triangles']} triangles, {what}; load average {result['load_average'][0]:.1f} "
        f"on {os.cpu_count()} CPUs; wrote {args.out}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
