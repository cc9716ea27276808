"""Mocap fidelity, scored on what users get: ``facecast render``'s vertices against the posed truth.

    python bench/mocap_fidelity.py [--variants issue16 sparse30 ...] [--folds 3] [--seconds 3]
                                   [--engine fp] [--every 2] [--live]
                                   [--protocol random|strict|mirror] [--priors off fold]

For each take variant (``facecast.server.mocap.variants``: layouts, headbands, capture axes and
units, motion from frame 0, pivots, fast expressions) and each fold of held-out ICT expressions
(the truth blends only the fold's shapes), a take is written as C3D, TRC and CSV and rendered the
way a user does, ``render_file(take, out.npz, face=ICT, layout=...)`` (the format alternates over
folds). The written vertices, head motion included, are compared with the truth's:

- skin error: mean distance over the skin vertices (mm), and over the skin that moves;
- not deforming: the neutral face carried by the true head motion (the baseline);
- head pose error: per frame the rigid motion that best maps the output onto the truth over the skin
  that no expression moves (the skull): its angle (degrees) and its mean displacement of the skin (mm);
- non-rigid error: the skin error left after that per-frame rigid correction (an oracle).

Each take is rendered once per ``--priors`` entry: ``off`` (the engine alone) and ``fold`` (the face
prior, ``mocap.prior``, built from the fold's prior shapes only, saved as an ``.npz`` basis and passed
as ``render``'s ``prior``). ``--protocol`` (``variants.fold_protocol``) says which shapes a fold's
prior may know: ``strict`` none of the held-out families (nor their mirrors), ``mirror`` the held-out
shape's other side (as ICT ships one side of several pairs), ``random`` whatever the split leaves.

``--live`` also streams the take frame by frame through the live session's ``MarkerLiveDriver``
(causal), scored from its first state on.
Targets (issue 16): skin error <= 0.25x not deforming (batch), <= 0.4x (live); head pose <= 0.1 deg.
Writes ``bench/out/mocap_fidelity.json`` and prints a markdown table.
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

OUT = Path(__file__).resolve().parent / "out" / "mocap_fidelity.json"  # suffixed by protocol


def rigid_errors(
    got: np.ndarray, gt: np.ndarray, still: np.ndarray, skin: np.ndarray, mm: float
) -> dict:
    """Per-frame head pose error (the rigid fit of ``got`` onto ``gt`` over ``still`` vertices) and
    the skin error left after it. ``(F, V, 3)`` face units."""
    from scipy.spatial.transform import Rotation

    from facecast.server.mocap.stabilise import kabsch

    deg, shift, nonrigid = [], [], []
    for g, t in zip(got, gt):
        r, tr = kabsch(g[still], t[still])
        fixed = g[skin] @ r.T + tr
        deg.append(np.degrees(Rotation.from_matrix(r).magnitude()))
        shift.append(np.linalg.norm(fixed - g[skin], axis=1).mean() * mm)
        nonrigid.append(np.linalg.norm(fixed - t[skin], axis=1).mean() * mm)
    return {
        "pose_deg_mean": float(np.mean(deg)),
        "pose_deg_p95": float(np.percentile(deg, 95)),
        "pose_mm_mean": float(np.mean(shift)),
        "nonrigid_mm_mean": float(np.mean(nonrigid)),
    }


def live_vertices(
    tr, fmt: str, face, engine: str, backend: str, prior=None
) -> tuple[np.ndarray, int]:
    """The take streamed frame by frame through ``MarkerLiveDriver`` (the live session's driver) and
    rendered: ``(vertices (T - first, V, 3), first frame with a state)``."""
    from facecast.server.mocap.io import read_take
    from facecast.server.mocap.live import MarkerLiveDriver
    from facecast.server.pipeline import Animator

    layout = json.loads(tr.paths["layout"].read_text())
    take = read_take(tr.paths[fmt], default_units=layout["units"])
    drv = MarkerLiveDriver(face, take.names, layout, units=take.units, fps=take.fps, prior=prior)
    states, first = [], None
    for i, frame in enumerate(take.xyz):
        out = drv.push(frame, i / take.fps)
        if out and first is None:
            first = i
        states += out
    anim = Animator(face, engine=engine, backend=backend, control_vertices=drv.control_vertices)
    from facecast.server.state import Animation

    return anim.render(
        Animation(fps=take.fps, states=states, control_vertices=drv.control_vertices)
    ), first


def main(argv: list[str]) -> int:
    from facecast.server.mocap.prior import ExpressionBasis
    from facecast.server.mocap.variants import PROTOCOLS, VARIANTS, fold_protocol, make_take

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    p.add_argument("--folds", type=int, default=3, help="folds of held-out expressions (default 3)")
    p.add_argument("--run-folds", type=int, default=None, help="run only the first N folds")
    p.add_argument("--seconds", type=float, default=3.0)
    p.add_argument("--fps", type=float, default=120.0)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--every", type=int, default=2, help="score every N-th frame (default 2)")
    p.add_argument("--engine", default="fp")
    p.add_argument("--backend", default="numpy")
    p.add_argument("--live", action="store_true", help="also the causal (live) filter")
    p.add_argument(
        "--protocol",
        default="random",
        choices=PROTOCOLS,
        help="expression folds (variants.fold_protocol): random, strict (whole families held "
        "out), mirror (one side held out, the other in the prior)",
    )
    p.add_argument(
        "--priors",
        nargs="+",
        default=["off", "fold"],
        choices=["off", "fold"],
        help="face priors rendered in the same run: off, fold (the fold's prior shapes only)",
    )
    p.add_argument(
        "--neutral-frame",
        default=None,
        type=lambda v: v if v == "auto" else int(v),
        help="render's --neutral-frame: N or auto (default: render's default)",
    )
    a = p.parse_args(argv)

    from facecast.server.mocap.generate import load_expressions, load_ict
    from facecast.server.render import render_file

    face = load_ict()
    enames, deltas = load_expressions(face)
    mm = face.mm_per_unit
    skin = face.part("skin")
    motion = np.linalg.norm(deltas[:, skin], axis=2).max(axis=0) * mm
    moving, still = skin[motion > 0.5], skin[motion < 0.01]
    splits = fold_protocol(enames, a.protocol, a.folds)
    rows = []
    formats = ("trc", "c3d", "csv")
    for vname in a.variants:
        for k, (held, known) in enumerate(splits[: a.run_folds or len(splits)]):
            with tempfile.TemporaryDirectory() as tmp:
                tr = make_take(
                    vname,
                    tmp,
                    seed=a.seed + k,
                    seconds=a.seconds,
                    fps=a.fps,
                    expressions=held,
                    face=face,
                )
                fmt = formats[k % 3]
                frames = np.arange(0, len(tr.weights), a.every)
                gt = tr.posed(face, deltas, frames)
                r, t = tr.head(face, frames)
                rest = np.einsum("tij,vj->tvi", r, face.vertices) + t[:, None]

                def score(v: np.ndarray, gt=gt) -> dict:
                    e = np.linalg.norm(v[:, skin] - gt[:, skin], axis=2) * mm
                    em = np.linalg.norm(v[:, moving] - gt[:, moving], axis=2) * mm
                    return {
                        "skin_mm_mean": float(e.mean()),
                        "skin_mm_p95": float(np.percentile(e, 95)),
                        "moving_mm_mean": float(em.mean()),
                    }

                base = score(rest)
                # the fold's prior: only the shapes the protocol lets it know (never a held-out one)
                basis = ExpressionBasis([enames[i] for i in known], deltas[known]).save(
                    Path(tmp) / "prior.npz"
                )
                for prior in a.priors:
                    source = str(basis) if prior == "fold" else "off"
                    row = {
                        "variant": vname,
                        "fold": k,
                        "protocol": a.protocol,
                        "prior": prior,
                        "held_out": [enames[i] for i in held],
                        "format": fmt,
                        "frames": len(tr.weights),
                        "not_deforming": base,
                    }
                    t0 = time.perf_counter()
                    out = Path(tmp) / "out.npz"
                    render_file(
                        tr.paths[fmt],
                        out,
                        face=face,
                        engine=a.engine,
                        backend=a.backend,
                        layout=str(tr.paths["layout"]),
                        mocap={"neutral_frame": a.neutral_frame, "prior": source},
                    )
                    row["render_s"] = time.perf_counter() - t0
                    with np.load(out) as z:
                        got = z["vertices"][frames]
                    row["batch"] = {**score(got), **rigid_errors(got, gt, still, skin, mm)}
                    row["batch"]["ratio"] = row["batch"]["skin_mm_mean"] / base["skin_mm_mean"]
                    if a.live:
                        got, first = live_vertices(tr, fmt, face, a.engine, a.backend, source)
                        keep = frames >= first  # states start once the live neutral is taken
                        got = got[frames[keep] - first]
                        sc = score(got, gt[keep])
                        row["live"] = {
                            **sc,
                            **rigid_errors(got, gt[keep], still, skin, mm),
                            "ratio": sc["skin_mm_mean"]
                            / score(rest[keep], gt[keep])["skin_mm_mean"],
                            "first_frame": int(first),
                        }
                    rows.append(row)
                    print(
                        f"{vname} {a.protocol} fold {k} ({fmt}) prior {prior}: batch "
                        f"{row['batch']['ratio']:.2f}x, pose {row['batch']['pose_deg_mean']:.3f} deg"
                        + (f", live {row['live']['ratio']:.2f}x" if a.live else ""),
                        file=sys.stderr,
                        flush=True,
                    )
    load = os.getloadavg()
    rec = {
        "seconds": a.seconds,
        "fps": a.fps,
        "engine": a.engine,
        "folds": a.folds,
        "protocol": a.protocol,
        "every": a.every,
        "skin_vertices": len(skin),
        "moving_skin_vertices": len(moving),
        "still_skin_vertices": len(still),
        "loadavg": load,
        "rows": rows,
    }
    out_json = OUT.with_name(f"mocap_fidelity-{a.protocol}.json")
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(rec, indent=1) + "\n")

    print(
        f"Mocap fidelity through `render` (ICT head, engine {a.engine}, {a.seconds:g} s at {a.fps:g} fps, "
        f"every {a.every}th frame, held-out expression folds of {a.folds}; load {load[0]:.1f})\n"
    )
    paths = ["batch"] + (["live"] if a.live else [])
    print(
        "| variant | fold | fmt | prior | not deforming (mm) | path | skin mean (mm) | ratio | pose (deg) "
        "| pose (mm) | non-rigid (mm) |"
    )
    print("|---|---|---|---|---:|---|---:|---:|---:|---:|---:|")
    for r in rows:
        for pth in paths:
            s = r[pth]
            print(
                f"| {r['variant']} | {r['fold']} | {r['format']} | {r['prior']} | "
                f"{r['not_deforming']['skin_mm_mean']:.3f} | "
                f"{pth} | {s['skin_mm_mean']:.3f} | {s['ratio']:.2f}x | {s['pose_deg_mean']:.3f} | "
                f"{s['pose_mm_mean']:.3f} | {s['nonrigid_mm_mean']:.3f} |"
            )
    print()
    for prior in a.priors:
        sel = [r for r in rows if r["prior"] == prior]
        for pth, target in (("batch", 0.25), ("live", 0.4)):
            if pth not in paths:
                continue
            ratio = np.mean([r[pth]["ratio"] for r in sel])
            pose = np.mean([r[pth]["pose_deg_mean"] for r in sel])
            print(
                f"- prior {prior}, {pth} ({a.protocol} folds): mean ratio {ratio:.2f}x (target <= "
                f"{target}x): {'met' if ratio <= target else 'NOT met'}; mean head pose error "
                f"{pose:.3f} deg (target <= 0.1): {'met' if pose <= 0.1 else 'NOT met'}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
