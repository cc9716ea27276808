"""Training recipes compared on nested inner speaker folds only:
``python bench/lipsync/recipes.py --recipe base --recipe dropout=0.2 --seeds 0,1,2``.

For each recipe (``frames.train`` keyword overrides, ``name=value``; ``base`` = the shipped
recipe) and seed, one network (one member) per pair of ``folds.FOLDS`` (k, j) is trained without
both folds' speakers; it scores fold j's speakers for outer fold k and fold k's for outer fold j.
Each outer fold's inner score is ``smoothing.evaluate``'s (the shipped decision rule, its prior
exponent tuned on the other inner folds), mean over the outer folds. No outer speaker is ever
scored here: this is the model-selection number. Reports each recipe's mean over seeds and the
seed spread; writes bench/out/lipsync_recipes.json and .md (appending to the JSON's runs).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # one core
    os.environ.setdefault(_v, "1")

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

import frames
from folds import FOLDS, cached_items
from smoothing import A, acc_f1, evaluate, grid, median_rule


def parse_recipe(text: str) -> dict[str, float]:
    """``"base"`` or ``"name=value,name=value"`` -> keyword overrides of ``frames.train``."""
    if text == "base":
        return {}
    out = {}
    for part in text.split(","):
        name, value = part.split("=")
        out[name] = float(value) if "." in value else int(value)
    return out


def inner_outputs(real, dev, kw: dict, seed: int) -> dict[int, dict]:
    """``smoothing.nested_outputs``' structure, inner pairs only, for one recipe and seed."""
    pairs: dict[int, list] = {k: [] for k in range(len(FOLDS))}
    for k in range(len(FOLDS)):
        for j in range(k + 1, len(FOLDS)):
            held = set(FOLDS[k]) | set(FOLDS[j])
            net = frames.train(
                [it for it in real if it.utt.speaker not in held] + dev, seed=seed, members=1, **kw
            )
            for outer, inner in ((k, j), (j, k)):
                pairs[outer] += [
                    (net.proba(it.feats[0]), it.utt.truth, inner)
                    for it in real
                    if it.utt.speaker in FOLDS[inner]
                ]
    return {
        k: {
            "pairs": pairs[k],
            "prior": frames.class_prior(
                [it for it in real if it.utt.speaker not in FOLDS[k]] + dev
            ),
        }
        for k in pairs
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recipe", action="append", default=None, help="base or name=value,...")
    ap.add_argument("--seeds", default="0,1,2")
    args = ap.parse_args(argv)
    real, dev = cached_items()
    seeds = [int(s) for s in args.seeds.split(",")]
    rule = grid(lambda v, a: median_rule(v["prior"], a), [(a,) for a in A], acc_f1)
    runs = []
    lines = ["| recipe | seed | inner acc / F1 |", "|---|---|---|"]
    for text in args.recipe or ["base"]:
        kw = parse_recipe(text)
        res = []
        for seed in seeds:
            t0 = time.process_time()
            r = evaluate(inner_outputs(real, dev, kw, seed), rule, held_out=False)
            res.append(r["inner"])
            lines.append(f"| {text} | {seed} | {r['inner'][0]:.3f} / {r['inner'][1]:.3f} |")
            print(lines[-1], f"({time.process_time() - t0:.0f} s)", flush=True)
            runs.append({"recipe": text, "seed": seed, "inner": r["inner"], "folds": r["per_fold"]})
        m, lo, hi = np.mean(res, 0), np.min(res, 0), np.max(res, 0)
        lines.append(
            f"| **{text}** | mean of {len(seeds)} | **{m[0]:.3f} / {m[1]:.3f}** "
            f"(acc {lo[0]:.3f}-{hi[0]:.3f}, F1 {lo[1]:.3f}-{hi[1]:.3f}) |"
        )
        print(lines[-1], flush=True)
    text = "\n".join(lines) + f"\n\nLoad average {os.getloadavg()[0]:.1f}.\n"
    frames.OUT.mkdir(parents=True, exist_ok=True)
    path = frames.OUT / "lipsync_recipes.json"  # read now: other runs may have appended
    path.write_text(
        json.dumps((json.loads(path.read_text()) if path.exists() else []) + runs, indent=1)
    )
    with (frames.OUT / "lipsync_recipes.md").open("a") as f:
        f.write(text)
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
