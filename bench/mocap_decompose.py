"""Where the mocap skin error comes from: oracle swaps on held-out expression folds.

    python bench/mocap_decompose.py [--variants issue16 ...] [--folds 3] [--run-folds N] [--engine fp]

For each take variant and fold (as ``bench/mocap_fidelity.py``: the truth blends only held-out ICT
expressions), the take is run through the batch driver (``mocap.driver.process``, the pipeline
``facecast render`` uses) and rendered with the engine; then parts of its output are swapped for the
truth, one at a time, each step keeping the swaps before it:

- ``full``: what ``render`` writes (the driver's control displacements and head poses);
- ``+pose``: the true head pose in place of the driver's;
- ``+neutral``: and each marker's constant error over the take removed (an oracle neutral: what a
  wrong neutral frame, or a wrong rest offset of a marker, adds to every frame alike);
- ``+markers``: the true displacements at the markers (noise, filtering, gaps, stabilisation gone):
  the engine's interpolation between the markers is all that is left (the floor of this layout);
- ``fit``: the least-squares best control displacements for this engine and these controls (what
  no marker data can beat: the layout's coverage with this engine).

Each as a ratio of the mean skin error to not deforming (the neutral face on the true head motion).
Writes ``bench/out/mocap_decompose.json`` and prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parent / "out" / "mocap_decompose.json"
STEPS = ("full", "+pose", "+neutral", "+markers", "fit")


def best_controls(op, target: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``(T, K, 3)`` least-squares control displacements whose ``op`` image best matches ``target
    (T, V, 3)`` displacements over the vertices ``rows`` (per axis)."""
    k = op.n_controls
    cols = []
    for a in range(3):
        basis = np.zeros((k, 3), dtype=np.float32)
        mats = []
        for j in range(k):
            basis[:] = 0.0
            basis[j, a] = 1.0
            mats.append(op.apply(basis)[rows, a])
        cols.append(np.stack(mats, axis=1))  # (R, K)
    out = np.zeros((len(target), k, 3))
    for a in range(3):
        out[:, :, a] = np.linalg.lstsq(cols[a], target[:, rows, a].T, rcond=None)[0].T
    return out


def main(argv: list[str]) -> int:
    from facecast.server.mocap.driver import process
    from facecast.server.mocap.generate import load_expressions, load_ict
    from facecast.server.mocap.io import read_take
    from facecast.server.mocap.variants import VARIANTS, folds, make_take, usable_expressions
    from facecast.server.pipeline import Animator
    from facecast.server.state import Animation, FaceState

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    p.add_argument("--folds", type=int, default=3)
    p.add_argument("--run-folds", type=int, default=None)
    p.add_argument("--seconds", type=float, default=3.0)
    p.add_argument("--fps", type=float, default=120.0)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--every", type=int, default=4, help="score every N-th frame (default 4)")
    p.add_argument("--engine", default="fp")
    a = p.parse_args(argv)

    face = load_ict()
    enames, deltas = load_expressions(face)
    mm = face.mm_per_unit
    skin = face.part("skin")
    splits = folds(len(enames), a.folds, seed=0, usable=usable_expressions(enames))
    rows = []
    for vname in a.variants:
        for k, held in enumerate(splits[: a.run_folds or len(splits)]):
            t0 = time.perf_counter()
            with tempfile.TemporaryDirectory() as tmp:
                tr = make_take(
                    vname,
                    tmp,
                    seed=a.seed + k,
                    seconds=a.seconds,
                    fps=a.fps,
                    expressions=held,
                    face=face,
                    formats=("trc",),
                )
                layout = json.loads(tr.paths["layout"].read_text())
                proc = process(
                    read_take(tr.paths["trc"], default_units=layout["units"]), face, layout
                )
            frames = np.arange(0, len(tr.weights), a.every)
            gt = tr.posed(face, deltas, frames)
            r, t = tr.head(face, frames)
            true_head = np.concatenate([r, t[:, :, None]], axis=2)
            rest = np.einsum("tij,vj->tvi", r, face.vertices) + t[:, None]
            rig = proc.rig
            cv = rig.control_vertices
            n_ctl = len(rig.placement.vertices)
            anim = Animator(face, engine=a.engine, backend="numpy", control_vertices=cv)

            def err(d: np.ndarray, heads: np.ndarray, gt=gt, anim=anim, cv=cv) -> float:
                states = [
                    FaceState(t=i / a.fps, controls=d[i].astype(np.float32), head=heads[i])
                    for i in range(len(d))
                ]
                got = anim.render(Animation(fps=a.fps, states=states, control_vertices=cv))
                return float((np.linalg.norm(got[:, skin] - gt[:, skin], axis=2) * mm).mean())

            base = float((np.linalg.norm(rest[:, skin] - gt[:, skin], axis=2) * mm).mean())
            d_out = np.stack([proc.states[f].controls for f in frames]).astype(np.float64)
            h_out = np.stack([proc.states[f].head for f in frames])
            truth_local = tr.local(face, deltas, frames) - face.vertices
            d_true = np.zeros_like(d_out)
            d_true[:, :n_ctl] = truth_local[:, rig.placement.vertices]
            off = d_out - d_true
            const = np.zeros_like(d_out)
            const[:, :n_ctl] = off[:, :n_ctl].mean(axis=0)
            fit = best_controls(anim.operator, truth_local, skin)
            mm_err = {
                "marker_err_mm": float((np.linalg.norm(off[:, :n_ctl], axis=2) * mm).mean()),
                "marker_const_mm": float((np.linalg.norm(const[0, :n_ctl], axis=1) * mm).mean()),
                "marker_disp_mm": float((np.linalg.norm(d_true[:, :n_ctl], axis=2) * mm).mean()),
            }
            mm_step = {
                "full": err(d_out, h_out),
                "+pose": err(d_out, true_head),
                "+neutral": err(d_out - const, true_head),
                "+markers": err(d_true, true_head),
                "fit": err(fit, true_head),
            }
            row = {
                "variant": vname,
                "fold": k,
                "held_out": [enames[i] for i in held],
                "engine": a.engine,
                "not_deforming_mm": base,
                "controls": n_ctl,
                "anchors": int(len(cv) - n_ctl),
                "mm": mm_step,
                "ratio": {s: v / base for s, v in mm_step.items()},
                **mm_err,
                "seconds": time.perf_counter() - t0,
            }
            rows.append(row)
            print(
                f"{vname} fold {k}: " + ", ".join(f"{s} {row['ratio'][s]:.2f}x" for s in STEPS),
                file=sys.stderr,
                flush=True,
            )
    load = os.getloadavg()
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(
        json.dumps({"engine": a.engine, "every": a.every, "loadavg": load, "rows": rows}, indent=1)
    )
    print(
        f"Mocap error decomposition (ICT head, engine {a.engine}, held-out folds of {a.folds}, ratio to not "
        f"deforming; load {load[0]:.1f})\n"
    )
    print(
        "| variant | fold | not deforming (mm) | "
        + " | ".join(STEPS)
        + " | marker err (mm) | of which constant | marker motion (mm) |"
    )
    print("|---|---|---:|" + "---:|" * (len(STEPS) + 3))
    for r in rows:
        print(
            f"| {r['variant']} | {r['fold']} | {r['not_deforming_mm']:.3f} | "
            + " | ".join(f"{r['ratio'][s]:.2f}x" for s in STEPS)
            + f" | {r['marker_err_mm']:.3f} | {r['marker_const_mm']:.3f} | {r['marker_disp_mm']:.3f} |"
        )
    print(
        "\n| mean | | | "
        + " | ".join(f"{np.mean([r['ratio'][s] for r in rows]):.2f}x" for s in STEPS)
        + " | | | |"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
