"""Operator build time and output of the deformation engines against a baseline commit.

Builds each engine's operator (``fp``, ``rbf``, ``shell``) as the server does
(``build.build_operator``, its DEFAULTS) on the built-in head, with its MPEG-4 FAP controls
(per-axis constraints: the sparse path of ``rbf`` and ``shell``) and with every axis constrained
(their dense path), ``inner`` copy and membrane, once with the current engines and once with the
engines (and ``BASELINE_MODULES``) as they were at ``--baseline`` (from git history), alternately,
``--rounds`` times. Checks that both give the same operator (bit for bit) and reports the time ratio
new/old (of the medians and of the best runs); the machine's load goes into each record. Writes
``bench/out/deform_build.json`` and a short table.

    python bench/deform_build.py [--baseline REV] [--vertices 25000] [--rounds 3]

Exit 1 when an operator differs from the baseline's.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import types
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "bench" / "out" / "deform_build.json"
PACKAGE = "facecast.server.deform"
ENGINE_MODULES = {"fp": "feature_point", "rbf": "rbf", "shell": "shell"}


#: The modules loaded from the baseline, in import order (the rest of the package is current).
BASELINE_MODULES = ("operator", "smoothing", "controls", "feature_point", "rbf", "shell")


def baseline_engines(rev: str) -> dict[str, types.ModuleType]:
    """The engines' modules at ``rev`` (with their ``BASELINE_MODULES``), in the same package."""
    from facecast.server.bench.history import module_at

    old = {f"from .{m} import": f"from ._baseline_{m} import" for m in BASELINE_MODULES}
    loaded = {
        m: module_at(ROOT, rev, f"server/deform/{m}.py", f"{PACKAGE}._baseline_{m}", old)
        for m in BASELINE_MODULES
    }
    return {e: loaded[m] for e, m in ENGINE_MODULES.items()}


def same_operator(a, b) -> bool:
    """Bit-identical: same form, arrays and meta."""
    if a.is_sparse != b.is_sparse or a.meta != b.meta:
        return False
    names = ("indptr", "indices", "weights") if a.is_sparse else ("dense",)
    return all(np.array_equal(getattr(a, n), getattr(b, n)) for n in names)


def build_with(build, fn, face, controls, engine: str, constrained, inner: str):
    """``build.build_operator`` (the server's call of an engine) with ``fn`` as ``engine``."""
    current = build.ENGINES[engine]
    build.ENGINES[engine] = fn
    try:
        return build.build_operator(
            face, controls, engine=engine, constrained=constrained, inner=inner
        )
    finally:
        build.ENGINES[engine] = current


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline", default="ea3b128", help="git revision of the old engines")
    ap.add_argument("--vertices", type=int, default=25000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--engines", default="fp,rbf,shell")
    args = ap.parse_args(argv)

    from facecast.server.deform import build
    from facecast.server.faces import load_face
    from facecast.server.mpeg4 import fap_controls

    old = baseline_engines(args.baseline)
    face = load_face(f"default:{args.vertices}")
    _fp, controls, per_axis = fap_controls(face)
    records, ok = [], True
    for engine in args.engines.split(","):
        for label, constrained in (("per-axis", per_axis), ("all axes", None)):
            for inner in ("copy", "membrane"):
                fns = {
                    "new": build.ENGINES[engine],
                    "old": getattr(old[engine], build.ENGINES[engine].__name__),
                }
                times: dict[str, list[float]] = {"new": [], "old": []}
                ops = {}
                for _ in range(args.rounds):
                    for which, fn in fns.items():
                        t0 = time.perf_counter()
                        ops[which] = build_with(
                            build, fn, face, controls, engine, constrained, inner
                        )
                        times[which].append(time.perf_counter() - t0)
                same = same_operator(ops["new"], ops["old"])
                ok &= same
                new_s, old_s = float(np.median(times["new"])), float(np.median(times["old"]))
                best = min(times["new"]) / min(times["old"])
                records.append(
                    {
                        "engine": engine,
                        "constraints": label,
                        "inner": inner,
                        "vertices": face.n_vertices,
                        "identical": same,
                        "new_s": new_s,
                        "old_s": old_s,
                        "ratio": new_s / old_s,
                        "best_ratio": best,
                        "rounds": args.rounds,
                        "baseline": args.baseline,
                        "load_avg": os.getloadavg(),
                    }
                )
                print(
                    f"| {engine} | {label} | {inner} | {'yes' if same else 'NO'} | "
                    f"{new_s:.2f} | {old_s:.2f} | {new_s / old_s:.2f} | {best:.2f} | "
                    f"{os.getloadavg()[0]:.1f} |",
                    flush=True,
                )
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(records, indent=1))
    print(
        "(columns: engine | constraints | inner | identical | new s | old s (medians) | new/old "
        "(medians) | new/old (best runs) | load)"
    )
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
