"""Lip-sync accuracy and speed benchmark: ``python bench/lipsync/run.py``.

Ground truth: phone alignments → visual classes at 100 frames/s (``classes.py``), from the real
recordings in ../shared/data/speech and from espeak-ng sentences (held-out voice variants)
force-aligned with PocketSphinx (``corpus.py``). Systems: facecast batch (the ``facecast lipsync``
viseme track), facecast-anim (the dominant viseme of the coarticulated animation, FAP 1), facecast
live (FAP 1 of ``AudioLiveDriver``: default look-ahead, continuous calibration, 20 ms chunks), and
two baselines measured in the same run (``baselines.py``). Writes bench/out/lipsync.json and prints a
markdown table and confusion matrices. Needs: espeak-ng, ``pip install -e .[bench]``.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # one core
    os.environ.setdefault(_v, "1")

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

from baselines import MfccTemplates, energy_visemes
from classes import CLASSES, OPEN, OPENING, VISEME_CLASS
from corpus import generated_utterances

from facecast.server.audio.io import read_audio
from facecast.server.audio.live import AudioLiveDriver
from facecast.server.audio.pipeline import lipsync
from facecast.server.mpeg4.highlevel import VISEMES
from facecast.server.paths import shared_data

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "bench" / "out"
log = logging.getLogger("bench.lipsync")
JAW_FULL = float(VISEMES[10, 3])  # open_jaw of "aa" at full strength


def fit_len(a: np.ndarray, n: int) -> np.ndarray:
    a = np.asarray(a)
    return a[:n] if len(a) >= n else np.concatenate([a, np.repeat(a[-1:], n - len(a), 0)])


def onset_lag_ms(truth: np.ndarray, pred_open: np.ndarray, max_lag: int = 25) -> float:
    """Lag (ms, + = prediction late) maximising the cross-correlation of the mouth-opening curves."""
    ok = truth >= 0
    a = np.where(ok, OPENING[np.clip(truth, 0, None)], 0.0)
    b = np.where(ok, pred_open, 0.0)
    a, b = a - a.mean(), b - b.mean()
    lags = np.arange(-max_lag, max_lag + 1)
    cc = [
        np.dot(a[max(0, -L) : len(a) - max(0, L)], b[max(0, L) : len(b) - max(0, -L)]) for L in lags
    ]
    return float(lags[int(np.argmax(cc))] * 10.0)


def scores(truth: np.ndarray, pred: np.ndarray) -> dict:
    ok = truth >= 0
    t, p = truth[ok], pred[ok]
    n = len(CLASSES)
    cm = np.zeros((n, n), dtype=np.int64)
    np.add.at(cm, (t, p), 1)
    f1 = []
    for c in range(n):
        if cm[c].sum() == 0:
            continue  # macro-F1 over the classes present in the truth
        prec = cm[c, c] / max(cm[:, c].sum(), 1)
        rec = cm[c, c] / cm[c].sum()
        f1.append(0.0 if prec + rec == 0 else 2 * prec * rec / (prec + rec))
    return {
        "frames": int(ok.sum()),
        "accuracy": float(np.mean(t == p)),
        "macro_f1": float(np.mean(f1)),
        "open_closed": float(np.mean(OPEN[t] == OPEN[p])),
        "confusion": cm.tolist(),
    }


def run_live(x: np.ndarray, sr: int, chunk: float = 0.02, fap1: bool = False) -> list:
    drv = AudioLiveDriver(None, sr, fps=100.0, fap1=fap1)
    states, n = [], max(1, int(chunk * sr))
    for i in range(0, len(x), n):
        states += drv.push(x[i : i + n].astype(np.float32), i / sr)
    return states + drv.flush()


def live_latency(x: np.ndarray, sr: int, chunk_samples: int = 16) -> dict:
    """Measured algorithmic latency: audio received after t when the state at t is returned."""
    drv = AudioLiveDriver(None, sr, fps=100.0)
    lat = []
    for i in range(0, len(x), chunk_samples):
        end = min(len(x), i + chunk_samples) / sr
        lat += [end - s.t for s in drv.push(x[i : i + chunk_samples].astype(np.float32), i / sr)]
    lat = np.array(lat) * 1e3
    return {
        "lookahead_s": drv.lookahead,
        "declared_ms": drv.latency * 1e3,
        "coart_lookahead_ms": drv.coart_lookahead * 1e3,
        "chunk_ms": chunk_samples / sr * 1e3,
        "median_ms": float(np.median(lat)),
        "max_ms": float(lat.max()),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sentences", type=int, default=24)
    ap.add_argument(
        "--no-folds",
        action="store_true",
        help="skip the speaker-disjoint real-speech folds (folds.py)",
    )
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    data = shared_data()
    if data is None:
        print("../shared/data is absent: no real speech to score", file=sys.stderr)
        return 1
    t0 = time.perf_counter()
    # real speech is scored by speaker-disjoint folds (folds.py): the shipped network has heard
    # every real speaker here, so it is never scored on them
    utts = generated_utterances(OUT / "lipsync_data", args.sentences)
    log.info("corpus ready (%d utterances) in %.1f s", len(utts), time.perf_counter() - t0)
    t0 = time.perf_counter()
    mfcc = MfccTemplates()
    log.info(
        "MFCC templates from %d training frames in %.1f s", mfcc.n_frames, time.perf_counter() - t0
    )

    systems = ("facecast", "facecast-anim", "facecast-live", "energy", "mfcc")
    kinds = ("generated",)
    preds: dict[str, dict[str, list]] = {s: {k: [] for k in kinds} for s in systems}
    truths: dict[str, list] = {k: [] for k in kinds}
    lags: dict[str, dict[str, list]] = {s: {k: [] for k in kinds} for s in systems}
    cpu = dict.fromkeys(systems, 0.0)
    audio_s = 0.0
    for u in utts:
        x, sr = read_audio(u.audio)
        audio_s += len(x) / sr
        n = len(u.truth)
        truths[u.kind].append(u.truth)
        outs = {}
        c = time.process_time()
        ls = lipsync(x, sr, fps=100.0)
        cpu["facecast"] += time.process_time() - c
        outs["facecast"] = (ls.labels_at(ls.track.t)[0], ls.track.faps[:, 3] / JAW_FULL)
        outs["facecast-anim"] = (ls.track.select1, ls.track.faps[:, 3] / JAW_FULL)
        c = time.process_time()
        jaw = np.array([s.faps[3] for s in run_live(x, sr)])
        cpu["facecast-live"] += time.process_time() - c
        v = np.array([s.viseme[0] for s in run_live(x, sr, fap1=True)])
        outs["facecast-live"] = (v, jaw / JAW_FULL)
        c = time.process_time()
        v, w = energy_visemes(x, sr)
        cpu["energy"] += time.process_time() - c
        outs["energy"] = (v, w)
        c = time.process_time()
        v, w = mfcc.visemes(x, sr)
        cpu["mfcc"] += time.process_time() - c
        outs["mfcc"] = (v, w * OPENING[VISEME_CLASS[v]])
        for s, (vis, opening) in outs.items():
            cls = VISEME_CLASS[fit_len(vis, n)]
            preds[s][u.kind].append(cls)
            lags[s][u.kind].append(onset_lag_ms(u.truth, fit_len(opening, n)))

    cpu["facecast-anim"] = cpu["facecast"]  # same run
    results = {
        "audio_seconds": audio_s,
        "utterances": {k: sum(u.kind == k for u in utts) for k in kinds},
        "classes": list(CLASSES),
        "systems": {},
    }
    for s in systems:
        r = {}
        for kind in kinds:
            r[kind] = scores(np.concatenate(truths[kind]), np.concatenate(preds[s][kind]))
            r[kind]["onset_lag_ms_median"] = float(np.median(lags[s][kind]))
        r["cpu_seconds"] = cpu[s]
        r["x_realtime"] = audio_s / max(cpu[s], 1e-9)
        results["systems"][s] = r
    x, sr = read_audio(data / "speech" / "bobby_16bit_16khz.wav")
    results["live_latency"] = live_latency(x, sr)
    fc = results["systems"]["facecast"]
    targets = {}
    for kind in kinds:
        for metric in ("accuracy", "macro_f1"):
            best = max(results["systems"][b][kind][metric] for b in ("energy", "mfcc"))
            targets[f"beats baselines: {kind} {metric}"] = fc[kind][metric] > best
    targets["synthetic no worse than before (0.537 / 0.487)"] = (
        fc["generated"]["accuracy"] >= 0.537 and fc["generated"]["macro_f1"] >= 0.487
    )
    targets[">= 500x real time (batch, 1 core)"] = fc["x_realtime"] >= 500
    targets[">= 50x real time (live, 20 ms chunks, 1 core)"] = (
        results["systems"]["facecast-live"]["x_realtime"] >= 50
    )
    targets["live latency <= 60 ms (default look-ahead)"] = results["live_latency"]["max_ms"] <= 60
    results["targets"] = targets
    results["load_average"] = os.getloadavg()
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "lipsync.json").write_text(json.dumps(results, indent=1))

    lines: list[str] = []
    out = lines.append  # the report goes to stdout and bench/out/lipsync.md
    out(
        f"\n## Lip-sync, synthetic speech: {results['utterances']['generated']} generated "
        "utterances (held-out espeak-ng variants), "
        f"{audio_s:.1f} s of audio, 10 visual classes at 100 frames/s\n"
    )
    out("| system | gen acc | gen macro-F1 | gen open/closed | gen lag ms | × real time (1 core) |")
    out("|---|---|---|---|---|---|")
    for s in systems:
        r = results["systems"][s]
        cells = []
        for kind in kinds:
            k = r[kind]
            cells += [
                f"{k['accuracy']:.3f}",
                f"{k['macro_f1']:.3f}",
                f"{k['open_closed']:.3f}",
                f"{k['onset_lag_ms_median']:+.0f}",
            ]
        out(f"| {s} | " + " | ".join(cells) + f" | {r['x_realtime']:.0f} |")
    lat = results["live_latency"]
    out(
        f"\nLive algorithmic latency (look-ahead budget {lat['lookahead_s'] * 1e3:.0f} ms, "
        f"{lat['chunk_ms']:.0f} ms chunks): median {lat['median_ms']:.1f} ms, max "
        f"{lat['max_ms']:.1f} ms (declared {lat['declared_ms']:.1f} ms)."
    )
    out(
        "\nTargets: "
        + "; ".join(f"{k}: {'met' if v else 'MISSED'}" for k, v in targets.items())
        + f". Load average during the run: {results['load_average'][0]:.1f} (2 cores shared)."
    )
    for kind in kinds:
        cm = np.array(results["systems"]["facecast"][kind]["confusion"])
        out(
            f"\nConfusion matrix, facecast batch, {kind} speech (rows = truth, columns = "
            "predicted, frames):\n"
        )
        short = [c[:6] for c in CLASSES]
        out("| truth \\ pred | " + " | ".join(short) + " |")
        out("|---" * (len(CLASSES) + 1) + "|")
        for i, c in enumerate(CLASSES):
            out(f"| {c} | " + " | ".join(str(v) for v in cm[i]) + " |")
    text = "\n".join(lines) + "\n"
    (OUT / "lipsync.md").write_text(text)
    sys.stdout.write(text)
    print(f"\nwrote {OUT / 'lipsync.json'} and {OUT / 'lipsync.md'}")
    if not args.no_folds:
        import folds

        return folds.main([])
    return 0


if __name__ == "__main__":
    sys.exit(main())
