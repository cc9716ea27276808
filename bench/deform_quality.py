"""Deformation quality: how smooth and artifact-free is the deformed skin?

Measured in head-local space (``rest + B·D``, the rigid head/jaw/eye transforms left out) over the
*outer skin* (the ``skin`` part without the mouth and eye sockets): strain, dihedral-angle change
(creases), vertex-normal turn, flipped triangles, and mouth-socket vertices poking through the skin;
definitions in ``server/deform/quality.py``.

Per frame p99 and max are taken, then the worst frame (max over frames) is reported.

    python bench/deform_quality.py [--engines fp,rbf] [--faces default,ict] [--param k=v ...]

Sources: the built-in demo performance (``server/drivers/demo.py``, 10 fps, one loop) on
``default``, and every ``../shared/data/xface/faps/*.fap`` on ``default`` and on the ICT head.
Writes ``bench/out/deform_quality.json`` and a markdown table.

``--layered``: layered streams instead (issue 18). The primaries are real speech
(``../shared/data/speech``) and the sources above; the layers are a joy overlay, the idle layer,
gaze at a point and a nod (``layered_sources``). Each primary gives three rows: ``NAME`` (alone),
``NAME+layers`` (mixed) and ``layers@NAME`` (the layers over a neutral primary for as long);
the mixed stream should have no more flipped triangles or creases than the other two. Like is
compared with like: a frame's p99 over the whole skin grows when more of the face moves at once
(speech in the mouth, a smile in the cheeks, a blink) even where nothing creases more, so the
mixed row also gives ``parts_dihedral_p99``, the worst frame's p99 of the *worse of the two parts
at each hinge* (the same frame of ``NAME`` and ``layers@NAME``), ``excess_dihedral_p99``, the worst
frame's p99 of how much the mix's fold exceeds that, and ``parts_pokes``, the socket vertices
poking through in either part (the mix should have no more).
"""

from __future__ import annotations

import argparse
import ast
import json
import sys
import time
from pathlib import Path

import numpy as np

from facecast.server.deform.normals import face_normals
from facecast.server.deform.quality import (
    POKE_TOL_MM,
    QualityMesh,
    _dihedral,
    measure,
    socket_signed_mm,
    summarise,
)


def head_local(animator, states) -> np.ndarray:
    """``(T, V, 3)`` rest + B·D for each state (no rigid transforms)."""
    rest = animator.face.vertices
    return np.stack([rest + animator.operator.apply(animator.solve(s)[0]) for s in states])


def run_source(animator, states, qm: QualityMesh, step: int = 1) -> dict:
    frames = [measure(p, qm) for p in head_local(animator, states[::step])]
    s = summarise(frames)
    s["worst_dihedral_frame"] = int(np.argmax([f["dihedral_p99"] for f in frames]) * step)
    return s


def against_parts(animator, mixed, parts: tuple, qm: QualityMesh, step: int = 1) -> dict:
    """The mixed stream against the worse of its two ``parts`` (streams as long) hinge by hinge
    and socket vertex by socket vertex, frame by frame: worst-frame p99 of the parts' per-hinge
    maximum fold (degrees), of the mix's excess over it, and most socket vertices poking through
    in either part."""

    def folds(points: np.ndarray) -> np.ndarray:
        fn = face_normals(points.astype(np.float64), qm.tri)
        return np.degrees(np.abs(_dihedral(fn, qm.hinge) - qm.rest_dihedral))

    worst, excess, pokes = 0.0, 0.0, 0
    frames = zip(*(head_local(animator, s[::step]) for s in (mixed, *parts)), strict=True)
    for m, a, b in frames:
        parts_fold = np.maximum(folds(a), folds(b))
        worst = max(worst, float(np.percentile(parts_fold, 99)))
        excess = max(excess, float(np.percentile(folds(m) - parts_fold, 99)))
        out = (socket_signed_mm(a.astype(np.float64), qm) > POKE_TOL_MM) | (
            socket_signed_mm(b.astype(np.float64), qm) > POKE_TOL_MM
        )
        pokes = max(pokes, int(out.sum()))
    return {"parts_dihedral_p99": worst, "excess_dihedral_p99": excess, "parts_pokes": pokes}


def layered_sources(sources: dict, geometry, speech: tuple[str, ...] = ()) -> dict:
    """Each source as itself, mixed with the layers, and the layers alone over as many frames.
    Sources named in ``speech`` or with visemes speak (they keep their closures, expressions add
    to their mouth); the others are expression streams the overlay competes with."""
    from facecast.server.layers import (
        Envelope,
        ExpressionLayer,
        GazeLayer,
        GazeTarget,
        HeadGesture,
        IdleLayer,
        mix_states,
    )
    from facecast.server.state import FaceState

    layers = [
        ExpressionLayer(1, envelope=Envelope(start=0.2, attack_peak=0.8)),
        IdleLayer(seed=2),
        GazeLayer(GazeTarget(point=np.array([150.0, 80.0, 500.0]))),
        HeadGesture("nod", envelope=Envelope(start=0.5, end=1.7), repetitions=2),
    ]
    out = {}
    for name, states in sources.items():
        out[name] = states
        speaks = name in speech or any(s.viseme is not None for s in states)
        out[f"{name}+layers"] = mix_states(states, layers, geometry=geometry, closures=speaks)
        neutral = [FaceState(t=s.t) for s in states]
        out[f"layers@{name}"] = mix_states(neutral, layers, geometry=geometry, closures=False)
    return out


def main(argv: list[str] | None = None) -> int:
    from facecast.server.drivers import load_animation
    from facecast.server.drivers.demo import demo_states
    from facecast.server.faces import load_face
    from facecast.server.paths import shared_data
    from facecast.server.pipeline import Animator

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--engines", default="fp,rbf")
    ap.add_argument("--faces", default="default,ict")
    ap.add_argument(
        "--param", action="append", default=[], help="engine parameter k=v (python literal)"
    )
    ap.add_argument("--step", type=int, default=1, help="use every N-th frame")
    ap.add_argument("--tag", default="")
    ap.add_argument(
        "--layered", action="store_true", help="layered streams: each source alone, +layers, layers"
    )
    ap.add_argument(
        "--out", default=None, help="JSON (default bench/out/deform_quality[_layered].json)"
    )
    args = ap.parse_args(argv)
    params = {k: ast.literal_eval(v) for k, v in (p.split("=", 1) for p in args.param)}
    data = shared_data()
    faps = sorted((data / "xface" / "faps").glob("*.fap")) if data else []
    faces = {}
    for name in args.faces.split(","):
        if name == "ict":
            if data is None:
                print("../shared/data not found: skipping ict", file=sys.stderr)
                continue
            faces["ict"] = load_face(data / "ict-facekit" / "generic_neutral_mesh.obj")
        else:
            faces[name] = load_face(name)
    result = {
        "tag": args.tag,
        "params": params,
        "layered": args.layered,
        "machine_loaded": True,
        "rows": [],
    }
    for fname, face in faces.items():
        qm = QualityMesh.of(face)
        for engine in args.engines.split(","):
            t = time.perf_counter()
            anim = Animator(face, engine=engine, backend="numpy", **params)
            build = time.perf_counter() - t
            op = anim.operator
            nnz_row = op.nnz / op.n_vertices
            sources = {}
            if fname != "ict":
                sources["demo"] = list(demo_states(10, loops=1))
            for path in faps:
                sources[path.stem] = load_animation(path, face).states
            if args.layered:
                from facecast.server.layers import Geometry

                speech = ("mary", "bobby") if data else ()
                for name, wav in zip(speech, ("mary.wav", "bobby_16bit_16khz.wav"), strict=False):
                    sources[name] = load_animation(data / "speech" / wav, face).states
                sources = layered_sources(sources, Geometry.of_rig(anim.rig), speech)
            rest = measure(face.vertices, qm)
            for sname, states in sources.items():
                s = run_source(anim, states, qm, args.step)
                if args.layered and sname.endswith("+layers"):
                    base = sname[: -len("+layers")]
                    parts = (sources[base], sources[f"layers@{base}"])
                    s.update(against_parts(anim, states, parts, qm, args.step))
                row = {
                    "face": fname,
                    "engine": engine,
                    "source": sname,
                    "build_s": build,
                    "nnz_row": nnz_row,
                    "rest_pokes": rest["pokes"],
                    **s,
                }
                result["rows"].append(row)
                vs = (
                    f" | parts p99 {s['parts_dihedral_p99']:.2f}, excess p99 "
                    f"{s['excess_dihedral_p99']:.2f}, parts pokes {s['parts_pokes']}"
                    if "parts_pokes" in s
                    else ""
                )
                print(
                    f"{fname:8s} {engine:4s} {sname:10s} dih p99 {s['dihedral_p99']:6.2f} max "
                    f"{s['dihedral_max']:6.1f} strain p99 {s['strain_p99']:.3f} flips {s['flips']} "
                    f"pokes {s['pokes']} ({s['frames_with_pokes']} fr){vs}",
                    file=sys.stderr,
                )
    name = "deform_quality_layered.json" if args.layered else "deform_quality.json"
    out = Path(args.out or Path(__file__).parent / "out" / name)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    print(
        "\n| face | engine | source | dihedral° p99 (mean/worst) | dihedral° max | normal° p99 | "
        "strain p99 | strain max | flips | pokes (frames) | nnz/row | build s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in result["rows"]:
        print(
            f"| {r['face']} | {r['engine']} | {r['source']} | {r['dihedral_p99_mean']:.2f}/{r['dihedral_p99']:.2f} "
            f"| {r['dihedral_max']:.1f} | {r['normal_p99']:.1f} | {r['strain_p99']:.3f} | {r['strain_max']:.2f} | "
            f"{r['flips']} | {r['pokes']} ({r['frames_with_pokes']}) | {r['nnz_row']:.1f} | {r['build_s']:.2f} |"
        )
    mixed = [r for r in result["rows"] if "parts_pokes" in r]
    if mixed:
        print(
            "\n| face | engine | mixed | dihedral° p99 | worse of the parts per hinge, p99 | "
            "excess p99 | flips | pokes | parts' pokes |"
        )
        print("|---|---|---|---|---|---|---|---|---|")
        for r in mixed:
            print(
                f"| {r['face']} | {r['engine']} | {r['source']} | {r['dihedral_p99']:.2f} | "
                f"{r['parts_dihedral_p99']:.2f} | {r['excess_dihedral_p99']:.2f} | {r['flips']} | "
                f"{r['pokes']} | {r['parts_pokes']} |"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
