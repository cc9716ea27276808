"""Decision rules over the frame network's outputs, chosen and scored by speaker:
``python bench/lipsync/smoothing.py``.

For each of ``folds.FOLDS`` (outer), the networks ``folds.py`` trains (the same recipe and cache
under bench/out/lipsync_data/nets: trained here when absent) give class probabilities of every
training speaker from a network that never heard it (inner folds) and of the held-out speakers.
Each rule's free parameters are tuned on the inner folds only. Two scores per rule:

- **inner**: each inner fold scored with the parameters tuned on the other inner folds of the same
  outer fold (pooled over the inner folds, mean over the outer ones): the model-selection number,
  which never sees an outer speaker;
- **held out**: parameters tuned on all inner folds, scored on the outer speakers (pooled). Only
  for rules that are kept (``--held-out``): never used to choose.

Rules: the shipped one (class prior ``a·log(prior)`` in the output biases, median filter of 3,
argmax), the prior's exponent chosen for macro-F1 instead of accuracy + macro-F1, the median's
length, ten per-class biases (coordinate ascent), and a Viterbi decoder over the ten classes
(transition log-probabilities learnt from the training alignments times a weight w, a switch
penalty s, the prior exponent a). Writes bench/out/lipsync_smoothing.json and .md.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # one core
    os.environ.setdefault(_v, "1")

import argparse
import itertools
import json
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

import frames
from folds import FOLDS, cached_items, items_path, net_path
from run import scores

from facecast.server.audio.classify import FrameNet
from facecast.server.audio.visemes import median_filter_proba

Decide = Callable[[np.ndarray], np.ndarray]
#: (probabilities (T, 10), truth (T,), inner fold index or -1 for held out)
Pair = tuple[np.ndarray, np.ndarray, int]


def nested_outputs() -> dict[int, dict]:
    """Per outer fold k: ``pairs`` (inner and held-out ``Pair``s), the training ``prior`` and
    ``trans`` (class-to-class counts of consecutive frames in the training alignments)."""
    real, dev = cached_items()
    stamp = int(items_path().stat().st_mtime)
    nets: dict[tuple[int, ...], FrameNet] = {}

    def net(groups: tuple[int, ...]) -> FrameNet:
        if groups not in nets:
            p = net_path(groups, stamp)
            if p.exists():
                nets[groups] = FrameNet.load(p)
            else:
                held = {s for g in groups for s in FOLDS[g]}
                nets[groups] = frames.train([it for it in real if it.utt.speaker not in held] + dev)
                p.parent.mkdir(parents=True, exist_ok=True)
                nets[groups].save(p)
        return nets[groups]

    out = {}
    for k, fold in enumerate(FOLDS):
        pairs: list[Pair] = [
            (net((k,)).proba(it.feats[0]), it.utt.truth, -1)
            for it in real
            if it.utt.speaker in fold
        ]
        for j in range(len(FOLDS)):
            if j != k:
                inet = net(tuple(sorted((k, j))))
                pairs += [
                    (inet.proba(it.feats[0]), it.utt.truth, j)
                    for it in real
                    if it.utt.speaker in FOLDS[j]
                ]
        train_items = [it for it in real if it.utt.speaker not in fold] + dev
        trans = np.zeros((10, 10))
        for it in train_items:
            t = it.utt.truth
            ok = (t[:-1] >= 0) & (t[1:] >= 0)
            np.add.at(trans, (t[:-1][ok], t[1:][ok]), 1)
        out[k] = {"pairs": pairs, "prior": frames.class_prior(train_items), "trans": trans}
    return out


def pooled(pairs: list[Pair], decide: Decide) -> tuple[float, float, np.ndarray, np.ndarray]:
    """Accuracy, macro-F1 and the pooled truth and decisions of ``pairs``."""
    ts, ps = [], []
    for p, t, _ in pairs:
        n = min(len(p), len(t))
        ts.append(t[:n])
        ps.append(decide(p[:n]))
    t, p = np.concatenate(ts), np.concatenate(ps)
    s = scores(t, p)
    return s["accuracy"], s["macro_f1"], t, p


def median_rule(prior: np.ndarray, a: float, size: int = 3, bias=None) -> Decide:
    lb = a * np.log(prior) + (0.0 if bias is None else np.asarray(bias))

    def decide(p: np.ndarray) -> np.ndarray:
        z = np.exp(np.log(np.maximum(p, 1e-12)) + lb)
        return np.argmax(median_filter_proba(z / z.sum(1, keepdims=True), size), 1)

    return decide


def viterbi(e: np.ndarray, log_a: np.ndarray) -> np.ndarray:
    """Most likely class path of emission scores ``e (T, C)`` under ``log_a (C, C)``."""
    T, C = e.shape
    back = np.zeros((T, C), dtype=np.int64)
    d = e[0].copy()
    for t in range(1, T):
        m = d[:, None] + log_a
        back[t] = np.argmax(m, 0)
        d = m[back[t], np.arange(C)] + e[t]
    path = np.zeros(T, dtype=np.int64)
    path[-1] = np.argmax(d)
    for t in range(T - 1, 0, -1):
        path[t - 1] = back[t, path[t]]
    return path


def viterbi_rule(prior: np.ndarray, trans: np.ndarray, a: float, w: float, s: float) -> Decide:
    A = trans + 1.0
    log_a = w * np.log(A / A.sum(1, keepdims=True)) - s * (1 - np.eye(10))
    lb = a * np.log(prior)
    return lambda p: viterbi(np.log(np.maximum(p, 1e-12)) + lb, log_a)


def acc_f1(acc: float, f1: float) -> float:
    return acc + f1


def f1_floor(acc: float, f1: float) -> float:
    """Macro-F1, with accuracy below 0.56 (the 0.55 target and a margin) penalised."""
    return f1 - 5 * max(0.0, 0.56 - acc)


A = frames.PRIOR_EXPONENTS
Tuner = Callable[[list[Pair], dict], tuple[Decide, object]]


def grid(rule: Callable[..., Decide], points: list[tuple], objective) -> Tuner:
    def tune(pairs: list[Pair], v: dict) -> tuple[Decide, object]:
        best = max(points, key=lambda g: objective(*pooled(pairs, rule(v, *g))[:2]))
        return rule(v, *best), best

    return tune


def biases(objective, steps=(-1.0, -0.5, -0.25, 0.25, 0.5, 1.0), passes: int = 2) -> Tuner:
    """The prior's exponent, then ten per-class biases by coordinate ascent (median of 3)."""

    def tune(pairs: list[Pair], v: dict) -> tuple[Decide, object]:
        a = max(A, key=lambda a: objective(*pooled(pairs, median_rule(v["prior"], a))[:2]))
        b = np.zeros(10)
        cur = objective(*pooled(pairs, median_rule(v["prior"], a, 3, b))[:2])
        for _ in range(passes):
            for c, d in itertools.product(range(10), steps):
                bb = b.copy()
                bb[c] += d
                val = objective(*pooled(pairs, median_rule(v["prior"], a, 3, bb))[:2])
                if val > cur + 1e-4:
                    cur, b = val, bb
        return median_rule(v["prior"], a, 3, b), (a, b.round(2).tolist())

    return tune


def evaluate(outs: dict[int, dict], tune: Tuner, held_out: bool) -> dict:
    inner, per_fold, ts, ps = [], [], [], []
    for k, v in outs.items():
        folds_j = sorted({j for *_, j in v["pairs"] if j >= 0})
        it, ip = [], []
        for j in folds_j:
            decide, _ = tune([q for q in v["pairs"] if q[2] not in (j, -1)], v)
            _, _, t, p = pooled([q for q in v["pairs"] if q[2] == j], decide)
            it.append(t)
            ip.append(p)
        s = scores(np.concatenate(it), np.concatenate(ip))
        inner.append((s["accuracy"], s["macro_f1"]))
        row = {"fold": k, "inner": inner[-1]}
        if held_out:
            decide, params = tune([q for q in v["pairs"] if q[2] >= 0], v)
            acc, f1, t, p = pooled([q for q in v["pairs"] if q[2] == -1], decide)
            row |= {"params": params, "held_out": (acc, f1)}
            ts.append(t)
            ps.append(p)
        per_fold.append(row)
    res: dict = {"inner": np.mean(inner, 0).tolist(), "per_fold": per_fold}
    if held_out:
        s = scores(np.concatenate(ts), np.concatenate(ps))
        res["held_out"] = (s["accuracy"], s["macro_f1"])
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--held-out", action="store_true", help="also score the outer speakers")
    ap.add_argument("--no-viterbi", action="store_true", help="skip the (slow) Viterbi rule")
    args = ap.parse_args(argv)
    outs = nested_outputs()
    med = lambda v, a, size=3: median_rule(v["prior"], a, size)  # noqa: E731
    rules: dict[str, Tuner] = {
        "shipped: prior a (acc+F1), median 3": grid(med, [(a,) for a in A], acc_f1),
        "prior a for F1 (acc >= 0.56)": grid(med, [(a,) for a in A], f1_floor),
        "prior a and median 1/3/5/7": grid(med, list(itertools.product(A, (1, 3, 5, 7))), acc_f1),
        "prior a + 10 class biases (acc+F1)": biases(acc_f1),
        "prior a + 10 class biases (F1)": biases(f1_floor),
    }
    if not args.no_viterbi:
        vit = lambda v, a, w, s: viterbi_rule(v["prior"], v["trans"], a, w, s)  # noqa: E731
        points = list(itertools.product((0.3, 0.45, 0.6, 0.75), (0.0, 0.5, 1.0), (0, 1, 2, 3)))
        rules["Viterbi a, w, s (acc+F1)"] = grid(vit, points, acc_f1)
    res = {}
    lines = [
        "| rule | inner acc / F1 | " + ("held out acc / F1 |" if args.held_out else ""),
        "|---|---|" + ("---|" if args.held_out else ""),
    ]
    for name, tune in rules.items():
        res[name] = r = evaluate(outs, tune, args.held_out)
        cell = f"{r['inner'][0]:.3f} / {r['inner'][1]:.3f}"
        held = f" {r['held_out'][0]:.3f} / {r['held_out'][1]:.3f} |" if args.held_out else ""
        lines.append(f"| {name} | {cell} |{held}")
        print(lines[-1], flush=True)
    text = "\n".join(lines) + f"\n\nLoad average {os.getloadavg()[0]:.1f}.\n"
    frames.OUT.mkdir(parents=True, exist_ok=True)
    (frames.OUT / "lipsync_smoothing.json").write_text(json.dumps(res, indent=1, default=str))
    (frames.OUT / "lipsync_smoothing.md").write_text(text)
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
