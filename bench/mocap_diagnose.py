"""Where the batch mocap error comes from: head pose against non-rigid, and within the non-rigid part
the face prior's span against marker interpolation and marker estimation.

    python bench/mocap_diagnose.py [--variants issue16 ...] [--protocol mirror] [--folds 2]
                                   [--run-folds 2] [--seconds 2] [--toward-fit LO HI] [--tag=-x]

For each variant and fold (held-out expressions, as ``bench/mocap_fidelity.py``, prior ``fold``) the
take is processed by the batch driver (``mocap.driver.process``, as ``render`` does) and rendered
several ways, each scored as mean skin error (mm) against the posed truth, as a ratio to not
deforming:

- ``batch``: the states as they are (what ``render`` writes), with its head pose error (degrees:
  ``mocap_fidelity.rigid_errors`` over the skin no expression moves);
- ``oracle_head``: the same states with the true head pose: ``batch - oracle_head`` is the pose part;
- ``exact_markers``: the true marker displacements (no noise, no stabilisation error) through the
  prior and the engine, true head: the floor of the non-rigid path with perfect markers
  (moved toward the prior's fit as the batch's, ``rig.BATCH_TOWARD_FIT``; ``--toward-fit LO HI``
  sets that gate for a run);
- ``exact_noprior``: the same without the prior (the engine alone interpolating the markers);
- ``span``: the truth's skin displacements projected (least squares over the skin) onto the prior's
  shapes: what no fit from markers can beat with this prior (the held-out shape's residual).

So ``oracle_head - exact_markers`` is the error of the estimated markers (noise, stabilisation,
neutral), ``exact_markers - span`` what fitting from a few markers and interpolating the residual
loses, ``span`` the prior's shape-space residual. Writes ``bench/out/mocap_diagnose-<protocol>.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parent / "out"


def main(argv: list[str]) -> int:
    from mocap_fidelity import rigid_errors

    from facecast.server.mocap.clean import CleanParams
    from facecast.server.mocap.driver import process
    from facecast.server.mocap.generate import load_expressions, load_ict
    from facecast.server.mocap.io import read_take
    from facecast.server.mocap.layout import load_layout
    from facecast.server.mocap.prior import ExpressionBasis
    from facecast.server.mocap.variants import PROTOCOLS, VARIANTS, fold_protocol, make_take
    from facecast.server.pipeline import Animator
    from facecast.server.state import Animation

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    p.add_argument("--protocol", default="mirror", choices=PROTOCOLS)
    p.add_argument("--folds", type=int, default=2)
    p.add_argument("--run-folds", type=int, default=2)
    p.add_argument("--seconds", type=float, default=2.0)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--every", type=int, default=2)
    p.add_argument(
        "--toward-fit", type=float, nargs=2, default=None, help="rig.BATCH_TOWARD_FIT (lo hi)"
    )
    p.add_argument("--fit-pose", type=int, default=None, help="driver.FIT_POSE_PASSES (0: off)")
    p.add_argument("--tag", default="", help="a suffix for the output file")
    a = p.parse_args(argv)
    from facecast.server.mocap import rig as rig_mod

    if a.toward_fit is not None:
        rig_mod.BATCH_TOWARD_FIT = tuple(a.toward_fit)
    from facecast.server.mocap import driver as driver_mod

    if a.fit_pose is not None:
        driver_mod.FIT_POSE_PASSES = a.fit_pose

    face = load_ict()
    enames, deltas = load_expressions(face)
    mm = face.mm_per_unit
    skin = face.part("skin")
    # the skull's skin (no expression moves it): where the head pose error is measured
    still = skin[np.linalg.norm(deltas[:, skin], axis=2).max(axis=0) * mm < 0.01]
    splits = fold_protocol(enames, a.protocol, a.folds)
    rows = []
    for vname in a.variants:
        for k, (held, known) in enumerate(splits[: a.run_folds]):
            with tempfile.TemporaryDirectory() as tmp:
                tr = make_take(
                    vname, tmp, seed=a.seed + k, seconds=a.seconds, expressions=held, face=face
                )
                fmt = ("trc", "c3d", "csv")[k % 3]
                frames = np.arange(0, len(tr.weights), a.every)
                gt = tr.posed(face, deltas, frames)
                gl = tr.local(face, deltas, frames)
                hr, ht = tr.head(face, frames)
                rest = np.einsum("tij,vj->tvi", hr, face.vertices) + ht[:, None]

                def err(v: np.ndarray, gt=gt) -> float:
                    return float((np.linalg.norm(v[:, skin] - gt[:, skin], axis=2) * mm).mean())

                base = err(rest)
                basis = ExpressionBasis([enames[i] for i in known], deltas[known])
                lay = load_layout(str(tr.paths["layout"]))
                take = read_take(tr.paths[fmt], default_units=lay.units)
                proc = process(take, face, lay, clean_params=CleanParams(filter="rts"), prior=basis)
                rig = proc.rig
                anim = Animator(
                    face, engine="fp", backend="numpy", control_vertices=rig.control_vertices
                )
                states = [proc.states[f] for f in frames]
                heads = np.concatenate([hr, ht[:, :, None]], axis=2)

                def render(sts) -> np.ndarray:
                    return anim.render(Animation(fps=tr.fps, states=sts))

                got = render(states)
                pose = rigid_errors(got, gt, still, skin, mm)
                oracle = render([replace(s, head=h) for s, h in zip(states, heads)])
                # the true marker displacements (face units) through the same prior and engine
                mv = rig.placement.vertices
                dx = (gl[:, mv] - face.vertices[mv][None]).astype(np.float32) * rig.gains[None]
                exact = render(rig.states(dx, heads, tr.fps))
                noprior = render(
                    [
                        replace(rig.state(dx[i], heads[i], i / tr.fps), shapes=None)
                        for i in range(len(dx))
                    ]
                )
                # the prior's span: least squares of the true skin displacements on its shapes
                if rig.prior is not None:
                    b = rig.prior.shapes[:, skin].reshape(len(rig.prior.shapes), -1).T
                    y = (gl[:, skin] - face.vertices[skin][None]).reshape(len(gl), -1).T
                    coef = np.linalg.lstsq(b.astype(np.float64), y.astype(np.float64), rcond=None)
                    res = (b @ coef[0] - y).T.reshape(len(gl), -1, 3)
                    span = float((np.linalg.norm(res, axis=2) * mm).mean())
                else:
                    span = float("nan")
                row = {
                    "variant": vname,
                    "fold": k,
                    "neutral_frame": int(proc.neutral_frame),
                    "not_deforming_mm": base,
                    "batch": err(got) / base,
                    "pose_deg": pose["pose_deg_mean"],
                    "oracle_head": err(oracle) / base,
                    "exact_markers": err(exact) / base,
                    "exact_noprior": err(noprior) / base,
                    "span": span / base,
                }
                rows.append(row)
                print(
                    " ".join(
                        f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}"
                        for k, v in row.items()
                    ),
                    file=sys.stderr,
                    flush=True,
                )
    OUT.mkdir(exist_ok=True)
    (OUT / f"mocap_diagnose-{a.protocol}{a.tag}.json").write_text(
        json.dumps(
            {
                "loadavg": os.getloadavg(),
                "toward_fit": rig_mod.BATCH_TOWARD_FIT,
                "fit_pose_passes": driver_mod.FIT_POSE_PASSES,
                "rows": rows,
            },
            indent=1,
        )
        + "\n"
    )
    print(
        f"Batch error split ({a.protocol} folds, {a.seconds:g} s, prior fold; ratios to not deforming)\n"
    )
    print(
        "| variant | fold | batch | head pose (deg) | oracle head (non-rigid) | pose part | exact markers "
        "| engine alone | prior span residual |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['variant']} | {r['fold']} | {r['batch']:.2f} | {r['pose_deg']:.3f} | "
            f"{r['oracle_head']:.2f} | "
            f"{r['batch'] - r['oracle_head']:.2f} | {r['exact_markers']:.2f} | "
            f"{r['exact_noprior']:.2f} | {r['span']:.2f} |"
        )
    if rows:
        print(
            f"\nMean over {len(rows)} takes: batch {np.mean([r['batch'] for r in rows]):.3f}x, head "
            f"pose {np.mean([r['pose_deg'] for r in rows]):.3f} deg (load "
            f"{os.getloadavg()[0]:.1f})"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
