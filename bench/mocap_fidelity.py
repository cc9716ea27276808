"""Mocap fidelity: the ICT head driven by a take whose markers sit on the ICT head itself.

    python bench/mocap_fidelity.py [--markers 60] [--seconds 10] [--fps 120] [--every 4]
                                   [--engines fp rbf shell] [--placement technician motion]

A take generated from the ICT expressions (``facecast.server.mocap.generate``: noise, gaps, spikes,
head motion) goes through the batch driver (identity retarget: the actor is the ICT head) and each
deformation engine; the skin vertices (head motion removed) are compared with the ground-truth
blend of the expressions. Baselines from the same run: not deforming (the neutral) and the same
engine driven by the exact marker displacements (no capture error: the engine's own limit). Each
marker placement (``generate.choose_markers``: a technician's layout sheet, or feature points plus
motion-weighted spreading) gets its own take (same seed) and rows.
Target (issue 6): with ~60 markers, mean skin error <= 1/4 of the not-deforming error.
Writes ``bench/out/mocap_fidelity.json`` and prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parent / "out" / "mocap_fidelity.json"


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--markers", type=int, default=60)
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--fps", type=float, default=120.0)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--stable", type=int, default=5, help="stable head markers among the markers")
    p.add_argument("--every", type=int, default=4, help="evaluate every N-th frame (default 4)")
    p.add_argument("--engines", nargs="+", default=["fp", "rbf", "shell"])
    p.add_argument("--placement", nargs="+", default=["technician", "motion"],
                   help="marker placements (generate.choose_markers)")
    p.add_argument("--backend", default="numpy")
    a = p.parse_args(argv)

    from facecast.server.mocap.driver import process
    from facecast.server.mocap.generate import (
        generated_take,
        load_expressions,
        load_ict,
        truth_vertices,
    )
    from facecast.server.pipeline import Animator
    from facecast.server.state import FaceState

    face = load_ict()
    _, deltas = load_expressions(face)
    skin = face.part("skin")
    moving = skin[np.linalg.norm(deltas[:, skin], axis=2).max(axis=0) * face.mm_per_unit > 0.5]
    mm = face.mm_per_unit
    records: dict = {
        "markers": a.markers,
        "seconds": a.seconds,
        "fps": a.fps,
        "skin_vertices": len(skin),
        "moving_skin_vertices": len(moving),
        "placements": {},
        "rows": [],
    }
    rows = records["rows"]
    for placement in a.placement:
        truth, take, layout = generated_take(n_markers=a.markers, seconds=a.seconds, fps=a.fps, seed=a.seed,
                                             n_stable=a.stable, placement=placement)
        t0 = time.perf_counter()
        proc = process(take, face, layout)
        driver_s = time.perf_counter() - t0
        cv = proc.rig.control_vertices
        frames = np.arange(0, len(proc.states), a.every)
        gt = truth_vertices(face, deltas, truth.weights[frames])  # (F, V, 3) face units
        exact = gt[:, cv] - face.vertices[cv]  # exact marker displacements
        nm = len(proc.rig.placement.vertices)
        got = np.stack([proc.states[f].controls[:nm] for f in frames])
        marker_err = np.linalg.norm(got - exact[:, :nm], axis=2) * mm  # the capture error the engines see
        records["placements"][placement] = {"controls": len(cv), "markers": nm,
                                            "frames_evaluated": len(frames), "driver_seconds": driver_s,
                                            "marker_error_mean_mm": float(marker_err.mean()),
                                            "marker_error_p95_mm": float(np.percentile(marker_err, 95)),
                                            "lowrank_directions": proc.info.get("lowrank")}

        def errors(verts: np.ndarray, gt=gt) -> dict:
            out = {}
            for name, ids in (("skin", skin), ("moving_skin", moving)):
                e = np.linalg.norm(verts[:, ids] - gt[:, ids], axis=2) * mm
                out[name] = {"mean_mm": float(e.mean()), "p95_mm": float(np.percentile(e, 95))}
            return out

        rows.append({"placement": placement, "method": "not deforming (neutral)", "engine": "-",
                     **errors(np.broadcast_to(face.vertices, gt.shape))})
        for engine in a.engines:
            t0 = time.perf_counter()
            anim = Animator(face, engine=engine, backend=a.backend, control_vertices=cv)
            build_s = time.perf_counter() - t0

            def render(ds: list[np.ndarray], animator=anim, gt=gt) -> np.ndarray:
                out = np.empty_like(gt)
                for i, d in enumerate(ds):
                    out[i] = animator.frame(FaceState(controls=d))  # head removed: compare in head space
                return out

            mocap = render([proc.states[f].controls for f in frames])
            oracle = render([exact[i].astype(np.float32) for i in range(len(frames))])
            rows.append({"placement": placement, "method": "mocap take (driver)", "engine": engine,
                         **errors(mocap), "operator_s": build_s})
            rows.append({"placement": placement, "method": "exact marker displacements", "engine": engine,
                         **errors(oracle)})
    base = {r["placement"]: r["skin"]["mean_mm"] for r in rows if r["engine"] == "-"}
    for r in rows:
        r["neutral_over_mean"] = base[r["placement"]] / r["skin"]["mean_mm"]
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(records, indent=1) + "\n")

    print(
        f"Mocap fidelity — ICT head, {a.markers} markers ({a.stable} stable), {a.seconds:g} s at {a.fps:g} fps, "
        f"every {a.every}th frame, {len(skin)} skin vertices ({len(moving)} that move); controls (markers + "
        f"anchors): {', '.join(k + ' ' + str(v['controls']) for k, v in records['placements'].items())}\n"
    )
    print(
        "| placement | input | engine | skin mean (mm) | skin p95 (mm) | moving skin mean | moving skin p95 "
        "| neutral / mean |"
    )
    print("|---|---|---|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['placement']} | {r['method']} | {r['engine']} | {r['skin']['mean_mm']:.3f} | {r['skin']['p95_mm']:.3f} | "
            f"{r['moving_skin']['mean_mm']:.3f} | {r['moving_skin']['p95_mm']:.3f} | {r['neutral_over_mean']:.2f}x |"
        )
    print()
    for k, v in records["placements"].items():
        print(f"- {k}: the driver's marker displacements err by {v['marker_error_mean_mm']:.3f} mm mean "
              f"({v['marker_error_p95_mm']:.3f} p95) against the truth; driver {v['driver_seconds']:.1f} s")
    for r in rows:
        if r["method"].startswith("mocap"):
            ok = r["skin"]["mean_mm"] <= base[r["placement"]] / 4
            print(
                f"- {r['placement']}, {r['engine']}: mean skin error {r['skin']['mean_mm']:.3f} mm vs "
                f"{base[r['placement']]:.3f} mm not deforming "
                f"({r['neutral_over_mean']:.2f}x; target >= 4x): {'met' if ok else 'NOT met'}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
