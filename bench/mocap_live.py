"""Live mocap: time from marker frame in to vertex frame out, and the Kalman filter's lag.

    python bench/mocap_live.py [--face default] [--markers 60] [--fps 120] [--seconds 10] [--backend auto]
                               [--prior off|auto|PATH]

A synthetic take (``facecast.server.mocap.synthetic``: 60 markers on the face, 0.5 mm noise, gaps,
head motion) is pushed frame by frame through ``MarkerLiveDriver`` and a ``pipeline.Animator``
(deformation + rigid parts). Reported: per-frame time of the driver alone and of driver + deform
(mean, p50, p95, p99), the sustained rate (frames / wall time, back to back), and, as the baseline
from the same run, the deformation alone. The Kalman filter's lag is the delay that best aligns the
driver's stabilised output with the ground truth. Also this thread's CPU time per frame (``host_cpu``;
the OpenCL device's threads not counted), which a loaded machine moves far less than the wall
time: run two versions alternately (``PYTHONPATH`` an exported tree) and compare it. Target
(issue 6): >= 120 frames/s sustained with 60 markers on the 25k-vertex face. Writes
``bench/out/mocap_live.json`` and prints a table.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from facecast.protocol.units import UNIT_MM

OUT = Path(__file__).resolve().parent / "out" / "mocap_live.json"  # suffixed by the prior


def pct(ms: list[float]) -> dict:
    a = np.asarray(ms)
    return {
        "mean_ms": float(a.mean()),
        "p50_ms": float(np.percentile(a, 50)),
        "p95_ms": float(np.percentile(a, 95)),
        "p99_ms": float(np.percentile(a, 99)),
        "max_ms": float(a.max()),
    }


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--face", default="default")
    p.add_argument("--markers", type=int, default=60)
    p.add_argument("--fps", type=float, default=120.0)
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--engine", default="fp")
    p.add_argument("--backend", default="auto")
    p.add_argument(
        "--prior", default="off", help="the face prior (mocap.prior): off, auto or a basis path"
    )
    p.add_argument(
        "--take",
        default=None,
        help="a generated ICT take of this variant (mocap.variants: issue16, technician, ...) "
        "instead of the synthetic one: the face prior then fits real expressions (its cost)",
    )
    a = p.parse_args(argv)

    from facecast.server.faces import load_face
    from facecast.server.mocap.clean import best_delay, kalman_lag
    from facecast.server.mocap.live import MarkerLiveDriver
    from facecast.server.mocap.synthetic import synthetic_take
    from facecast.server.pipeline import Animator

    syn = None
    if a.take:
        import tempfile

        from facecast.server.mocap.generate import load_ict
        from facecast.server.mocap.io import read_take
        from facecast.server.mocap.variants import make_take

        face = load_ict()
        with tempfile.TemporaryDirectory() as tmp:  # the take is read whole, then removed
            tr = make_take(a.take, tmp, seconds=a.seconds, fps=a.fps, face=face, formats=("trc",))
            layout = json.loads(tr.paths["layout"].read_text())
            take = read_take(tr.paths["trc"], default_units=layout["units"])
        names, frames = take.names, (take.xyz * UNIT_MM[take.units or "mm"]).astype(np.float32)
        layout["units"] = "mm"
    else:
        face = load_face(a.face)
        syn = synthetic_take(
            face, n_markers=a.markers, seconds=a.seconds, fps=a.fps, seed=7, noise_mm=0.5, gaps=True
        )
        names, layout, frames = syn.take.names, syn.layout, syn.take.xyz.astype(np.float32)
    drv = MarkerLiveDriver(face, names, layout, fps=a.fps, prior=a.prior)
    t0 = time.perf_counter()
    anim = Animator(face, engine=a.engine, backend=a.backend, control_vertices=drv.control_vertices)
    setup_s = time.perf_counter() - t0
    backend = getattr(anim.deformer, "name", type(anim.deformer).__name__)

    # warm up (kernels, caches) on a copy of the driver
    warm = MarkerLiveDriver(face, names, layout, fps=a.fps, prior=a.prior)
    for i in range(40):
        for s in warm.push(frames[i], i / a.fps):
            anim.frame(s)

    drv_ms, total_ms, cpu_ms, states = [], [], [], []
    wall0 = time.perf_counter()
    for i, f in enumerate(frames):
        c1 = time.thread_time()
        t1 = time.perf_counter()
        out = drv.push(f, i / a.fps)
        t2 = time.perf_counter()
        for s in out:
            verts = anim.frame(s)
        t3 = time.perf_counter()
        c3 = time.thread_time()
        if out:
            drv_ms.append(1e3 * (t2 - t1))
            total_ms.append(1e3 * (t3 - t1))
            cpu_ms.append(1e3 * (c3 - c1))
            states.append(out[-1])
    wall = time.perf_counter() - wall0
    assert np.isfinite(verts).all()
    # baseline: deformation alone, same states
    base_ms = []
    for s in states[:: max(1, len(states) // 300)]:
        t1 = time.perf_counter()
        anim.frame(s)
        base_ms.append(1e3 * (time.perf_counter() - t1))

    # Kalman lag and error (synthetic take): the driver's controls against the truth (mm)
    lag, err, raw_err = 0, None, None
    if syn is not None:
        n0 = len(frames) - len(states)
        d = np.stack([s.controls[: a.markers] for s in states]) * face.mm_per_unit
        truth = (syn.local - syn.local[0])[n0:]
        lag = best_delay(d, truth)
        err = np.linalg.norm(d - truth, axis=2)
        # capture noise baseline: raw markers stabilised with the true pose
        raw_local = np.einsum("tmj,tji->tmi", syn.take.xyz - syn.head_t[:, None], syn.head_r)
        raw_err = np.linalg.norm((raw_local - syn.local)[n0:], axis=2)

    sine_lag = kalman_lag(a.fps, drv.kf.Q[1, 1] / drv.kf.dt, drv.kf.r)
    rec = {
        "face": a.face,
        "take": a.take or "synthetic",
        "prior": a.prior,
        "vertices": face.n_vertices,
        "markers": len(names),
        "controls": len(drv.control_vertices),
        "fps": a.fps,
        "frames": len(states),
        "backend": backend,
        "engine": a.engine,
        "setup_s": setup_s,
        "driver": pct(drv_ms),
        "driver_plus_deform": pct(total_ms),
        "deform_only": pct(base_ms),
        # this thread's CPU time per frame (the device's threads not counted): on a loaded machine
        # it moves far less than the wall time, so it compares code versions run side by side
        "host_cpu": pct(cpu_ms),
        "loadavg": os.getloadavg(),
        "sustained_fps": len(frames) / wall,
        "kalman_lag_frames": lag,
        "kalman_lag_ms": 1e3 * lag / a.fps,
        "kalman_sine_lag_ms": {f"{f:g} Hz": v for f, v in sine_lag.items()},
        "control_error_mm": _mean_p95(err),
        "raw_error_mm": _mean_p95(raw_err),
    }
    out = OUT if a.prior == "off" else OUT.with_name("mocap_live-prior.json")
    if a.take:
        out = out.with_name(out.stem + f"-{a.take}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rec, indent=1) + "\n")

    subject = f"generated ICT take {a.take!r}" if a.take else f"face {a.face}"
    print(
        f"Mocap live — {subject} ({face.n_vertices} vertices), prior {a.prior}, {len(names)} markers "
        f"({rec['controls']} controls with anchors), {a.fps:g} Hz, {len(states)} frames, {a.engine} on {backend}\n"
    )
    print("| per frame | mean (ms) | p50 | p95 | p99 | max |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, key in (
        ("driver (filter, stabilise, retarget)", "driver"),
        ("driver + deform (marker frame in -> vertices out)", "driver_plus_deform"),
        ("deform alone (baseline)", "deform_only"),
        ("host CPU of marker in -> vertices out (this thread)", "host_cpu"),
    ):
        r = rec[key]
        print(
            f"| {name} | {r['mean_ms']:.3f} | {r['p50_ms']:.3f} | {r['p95_ms']:.3f} | {r['p99_ms']:.3f} | "
            f"{r['max_ms']:.2f} |"
        )
    print(
        f"\nsustained: {rec['sustained_fps']:.0f} frames/s back to back (target >= {a.fps:g}): "
        f"{'met' if rec['sustained_fps'] >= a.fps else 'NOT met'}; driver share of a frame: "
        f"{rec['driver']['mean_ms'] / rec['driver_plus_deform']['mean_ms']:.0%}; load "
        + " ".join(f"{x:.2f}" for x in rec["loadavg"])
    )
    print(
        "Kalman lag on sinusoids (steady state): "
        + ", ".join(f"{k}: {v:.1f} ms" for k, v in rec["kalman_sine_lag_ms"].items())
    )
    if err is None:  # a named variant take: its accuracy is bench/mocap_fidelity.py's
        return 0
    print(
        f"best-aligning delay on the take: {lag} frames = {rec['kalman_lag_ms']:.1f} ms; control error mean "
        f"{rec['control_error_mm']['mean']:.3f} mm, p95 {rec['control_error_mm']['p95']:.3f} mm "
        f"(raw markers with the true head pose: mean {rec['raw_error_mm']['mean']:.3f}, p95 "
        f"{rec['raw_error_mm']['p95']:.3f})"
    )
    return 0


def _mean_p95(err: np.ndarray | None) -> dict[str, float] | None:
    """Mean and 95th percentile of an error array (mm), or None when it was not measured."""
    if err is None:
        return None
    return {"mean": float(np.nanmean(err)), "p95": float(np.nanpercentile(err, 95))}


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
