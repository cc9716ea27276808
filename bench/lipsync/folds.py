"""Speaker-disjoint evaluation of the frame network: ``python bench/lipsync/folds.py``.

Folds by speaker (``FOLDS``): for each, a network is trained on the other speakers' real
recordings plus the synthetic development sentences (``frames.py``), and the held-out speakers'
recordings are scored as the bench scores (ten classes, 100 frames/s, against PocketSphinx
alignments): facecast batch (``pipeline.lipsync`` with the fold's network), facecast live
(``AudioLiveDriver``, default look-ahead, 20 ms chunks, FAP 1) and facecast with the transcript
(``align.align_text``), next to the energy and MFCC baselines. Never a number on a speaker the
network was trained on; the fold's class-prior exponent (``frames.tune_prior``) is chosen on its
training speakers alone (each held out in turn by a network trained without it and the fold).
Writes bench/out/lipsync_folds.json and .md.
"""

from __future__ import annotations

import argparse
import copy
import json
import logging
import os
import pickle
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

import frames
from baselines import MfccTemplates, energy_visemes
from classes import CLASSES, VISEME_CLASS
from run import fit_len, scores

from facecast.server.audio.classify import FrameNet
from facecast.server.audio.io import read_audio
from facecast.server.audio.live import AudioLiveDriver
from facecast.server.audio.pipeline import lipsync
from facecast.server.errors import InputError

log = logging.getLogger("bench.lipsync.folds")
#: Held-out speaker groups (every speaker is held out exactly once).
FOLDS = (
    ("michael",),
    ("librivox",),
    ("lj", "slt"),
    ("cards", "digits", "uberi", "libri61"),
    ("bobby", "mary"),
)
SYSTEMS = ("facecast", "facecast-live", "facecast-text", "facecast-live-text", "energy", "mfcc")
#: Another recording's transcript for each one (offsets into the list of transcripts): the
#: mismatched texts the transcript check must refuse.
OTHER_OFFSETS = (1, 3, 5, 8, 12, 17, 19, 23, 27, 31, 36)
#: Each fold's mismatch limit: the largest own-transcript value of its training speakers (each
#: scored by a network that never heard it) plus this.
LIMIT_MARGIN = 0.05


def text_excess(proba: np.ndarray, text: str, speech: float) -> float:
    """``align.mismatch_excess`` of ``text`` on class probabilities ``proba (T, 10)``; inf when
    the phone rate over ``speech`` seconds of sound or the length refuses it first."""
    from facecast.server.audio.align import PHONE_RATE, mismatch_excess, text_fit, text_phones
    from facecast.server.errors import InputError

    n_phones = sum(len(w) for w in text_phones(text))
    if not PHONE_RATE[0] <= n_phones / max(speech, 0.1) <= PHONE_RATE[1]:
        return float("inf")
    try:
        _, mismatch, n_phones = text_fit(proba, text)
    except InputError:  # more phones than frames
        return float("inf")
    return mismatch_excess(mismatch, n_phones)


def items_path() -> Path:
    return frames.OUT / "lipsync_data" / "items.pkl"


def cached_items(refresh: bool = False):
    path = items_path()
    if path.exists() and not refresh:
        # our own cache, written below into bench/out (gitignored); never a downloaded file
        return pickle.loads(path.read_bytes())  # noqa: S301
    items = frames.load_items()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(items))
    return items


def run_live(
    x: np.ndarray, sr: float, net, chunk: float = 0.02, params=None, text: str | None = None
) -> np.ndarray:
    drv = AudioLiveDriver(None, sr, fps=100.0, fap1=True, net=net, params=params, text=text)
    states, n = [], max(1, int(chunk * sr))
    for i in range(0, len(x), n):
        states += drv.push(x[i : i + n].astype(np.float32), i / sr)
    states += drv.flush()
    return np.array([s.viseme[0] for s in states])


def net_path(
    groups: tuple[int, ...],
    stamp: int,
    *,
    epochs: int = frames.EPOCHS,
    hidden: int = frames.HIDDEN,
    balance: float = frames.BALANCE,
    dropout: float = frames.DROPOUT,
    step: int = frames.STEP,
    members: int = frames.MEMBERS,
    offsets=frames.OFFSETS,
    dev: bool = True,
    live_cal: bool = frames.LIVE_CALIBRATION,
    norm: bool = frames.NORM,
) -> Path:
    """Cache file (under bench/out, gitignored) of the network trained without the speakers of
    ``FOLDS[g]`` for g in ``groups`` by this recipe, on the cached features of mtime ``stamp``."""
    return (
        frames.OUT
        / "lipsync_data"
        / "nets"
        / (
            f"{'-'.join(map(str, groups))}_e{epochs}_h{hidden}_b{balance}_s{step}_m{members}"
            f"{f'_d{dropout}' if dropout else ''}"
            f"_o{'.'.join(map(str, offsets))}{'' if dev else '_nodev'}{'_lc' if live_cal else ''}"
            f"{'_n' if norm else ''}"
            f"_c{stamp}.npz"
        )
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--refresh", action="store_true", help="recompute the cached features")
    ap.add_argument("--quick", action="store_true", help="frame-level batch scores only")
    ap.add_argument("--epochs", type=int, default=frames.EPOCHS)
    ap.add_argument("--hidden", type=int, default=frames.HIDDEN)
    ap.add_argument("--offsets", default=",".join(map(str, frames.OFFSETS)))
    ap.add_argument("--balance", type=float, default=frames.BALANCE)
    ap.add_argument("--dropout", type=float, default=frames.DROPOUT)
    ap.add_argument("--step", type=int, default=frames.STEP)
    ap.add_argument(
        "--members", type=int, default=frames.MEMBERS, help="networks merged into one (seeds)"
    )
    ap.add_argument("--median", type=int, default=3)
    ap.add_argument("--no-dev", action="store_true", help="train without synthetic speech")
    ap.add_argument(
        "--no-live-cal",
        action="store_true",
        help="train every copy under its file calibration (frames.LIVE_CALIBRATION off)",
    )
    ap.add_argument("--no-norm", action="store_true", help="no per-speaker running normalisation")
    ap.add_argument("--cmvn", action="store_true", help="quick: per-utterance mean removal")
    ap.add_argument(
        "--no-prior",
        action="store_true",
        help="no class prior in the output biases (else its exponent is chosen on "
        "the training speakers' own folds)",
    )
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    offsets = np.array([int(v) for v in args.offsets.split(",")])
    real, dev = cached_items(args.refresh)
    if args.cmvn:
        for it in real + dev:
            for F in it.feats:
                speech = F[:, 26] > 0
                F[:, :25] -= F[speech if speech.sum() > 10 else slice(None), :25].mean(0)
    speakers = sorted({it.utt.speaker for it in real})
    assert sorted(s for f in FOLDS for s in f) == speakers, speakers
    mfcc = None if args.quick else MfccTemplates()
    truths: dict[str, list] = {s: [] for s in speakers}
    preds: dict[str, dict[str, list]] = {m: {s: [] for s in speakers} for m in SYSTEMS}
    audio_s, cpu = 0.0, dict.fromkeys(SYSTEMS, 0.0)
    check: dict[str, dict] = {}  # recording -> own and other transcripts' mismatch, limit
    texts = [it.utt.text for it in real if it.utt.text]
    import scipy.ndimage

    from facecast.server.audio.visemes import Params

    params = Params(median=args.median)

    nets: dict = {}
    # trained networks are kept under bench/out (gitignored) per training set and recipe, so a
    # rerun that changes only the scoring (transcript path, live driver) does not retrain
    cache_stamp = int(items_path().stat().st_mtime)

    # the training recipe: what names a cached network and what trains it
    recipe = {
        "epochs": args.epochs,
        "hidden": args.hidden,
        "balance": args.balance,
        "dropout": args.dropout,
        "step": args.step,
        "members": args.members,
        "live_cal": frames.LIVE_CALIBRATION and not args.no_live_cal,
        "norm": frames.NORM and not args.no_norm,
    }

    def net_without(groups: tuple[int, ...]):
        """The network trained without the speakers of ``FOLDS[g]`` for g in ``groups``."""
        cache = net_path(groups, cache_stamp, offsets=offsets, dev=not args.no_dev, **recipe)
        if groups not in nets and cache.exists() and not args.cmvn:
            nets[groups] = FrameNet.load(cache)
        if groups not in nets:
            t0 = time.perf_counter()
            held = {s for g in groups for s in FOLDS[g]}
            train_items = [it for it in real if it.utt.speaker not in held] + (
                [] if args.no_dev else dev
            )
            nets[groups] = frames.train(train_items, offsets, **recipe)
            log.info(
                "without %s: trained on %d utterances in %.0f s",
                sorted(held),
                len(train_items),
                time.perf_counter() - t0,
            )
            if not args.cmvn:
                cache.parent.mkdir(parents=True, exist_ok=True)
                nets[groups].save(cache)
        return nets[groups]

    exponents: dict = {}
    limits: dict = {}

    def speech_s(it) -> float:
        return float(np.sum(it.feats[0][:, 26] > 0)) / 100  # above the silence threshold

    for k, fold in enumerate(FOLDS):
        net = copy.deepcopy(net_without((k,)))
        if not args.no_prior:  # nested: chosen on the training speakers only, each held out once
            pairs = [
                (net_without(tuple(sorted((k, j)))).proba(it.feats[0]), it.utt.truth)
                for j in range(len(FOLDS))
                if j != k
                for it in real
                if it.utt.speaker in FOLDS[j]
            ]
            prior = frames.class_prior(
                [it for it in real if it.utt.speaker not in fold] + ([] if args.no_dev else dev)
            )
            exponents[fold[0]] = frames.tune_prior(pairs, prior, median=args.median)
            net = frames.with_prior(net, prior, exponents[fold[0]])
            log.info("fold %s: class prior exponent %s", fold, exponents[fold[0]])
        net.mean_proba = frames.mean_proba(  # the live transcript path's starting prior
            net, [it for it in real if it.utt.speaker not in fold] + ([] if args.no_dev else dev)
        )
        # the transcript check's limit, from the training speakers alone (nested as the prior)
        inner = []
        for j in range(len(FOLDS)):
            if j == k:
                continue
            held = {s for g in (k, j) for s in FOLDS[g]}
            inet = copy.deepcopy(net_without(tuple(sorted((k, j)))))
            if not args.no_prior:
                inet = frames.with_prior(
                    inet,
                    frames.class_prior(
                        [it for it in real if it.utt.speaker not in held]
                        + ([] if args.no_dev else dev)
                    ),
                    exponents[fold[0]],
                )
            inner += [
                text_excess(inet.proba(it.feats[0]), it.utt.text, speech_s(it))
                for it in real
                if it.utt.speaker in FOLDS[j] and it.utt.text
            ]
        limit = max(v for v in inner if np.isfinite(v)) + LIMIT_MARGIN
        limits[fold[0]] = limit
        log.info("fold %s: transcript mismatch limit %.3f", fold, limit)
        for it in real:
            u = it.utt
            if u.speaker not in fold:
                continue
            n = len(u.truth)
            truths[u.speaker].append(u.truth)
            if args.quick:
                for med in (1, 3, 5, 7):
                    p = scipy.ndimage.median_filter(
                        net.proba(it.feats[0]), size=(med, 1), mode="nearest"
                    )
                    key = "facecast" if med == args.median else f"median{med}"
                    preds.setdefault(key, {s: [] for s in speakers})
                    preds[key][u.speaker].append(fit_len(np.argmax(p, 1), n))
                continue
            x, sr = read_audio(u.audio)
            audio_s += len(x) / sr
            c = time.process_time()
            ls = lipsync(x, sr, fps=100.0, net=net, params=params)
            cpu["facecast"] += time.process_time() - c
            outs = {"facecast": ls.labels_at(ls.track.t)[0]}
            c = time.process_time()
            outs["facecast-live"] = run_live(x, sr, net, params=params)
            cpu["facecast-live"] += time.process_time() - c
            from facecast.server.audio.align import align_text

            if u.text:  # the transcript check: own text vs other recordings'
                proba = net.proba(it.feats[0])
                i = texts.index(u.text)
                check[u.name] = {
                    "own": text_excess(proba, u.text, speech_s(it)),
                    "other": [
                        text_excess(proba, texts[(i + o) % len(texts)], speech_s(it))
                        for o in OTHER_OFFSETS
                    ],
                    "limit": limit,
                }
                try:
                    c = time.process_time()
                    outs["facecast-text"] = align_text(
                        x, sr, u.text, net=net, max_mismatch=limit
                    ).labels_at(ls.track.t)[0]
                    cpu["facecast-text"] += time.process_time() - c
                except InputError as e:  # refused: scored with the no-text output
                    log.warning("%s: transcript refused: %s", u.name, e)
                    outs["facecast-text"] = outs["facecast"]
                c = time.process_time()
                outs["facecast-live-text"] = run_live(x, sr, net, params=params, text=u.text)
                cpu["facecast-live-text"] += time.process_time() - c
            else:
                outs["facecast-text"] = outs["facecast"]
                outs["facecast-live-text"] = outs["facecast-live"]
            outs["energy"] = energy_visemes(x, sr)[0]
            outs["mfcc"] = mfcc.visemes(x, sr)[0]
            for m, vis in outs.items():
                preds[m][u.speaker].append(VISEME_CLASS[fit_len(vis, n)])
    systems = tuple(preds) if args.quick else SYSTEMS
    systems = tuple(m for m in systems if any(preds[m][s] for s in speakers))
    res: dict = {
        "folds": [list(f) for f in FOLDS],
        "args": vars(args),
        "prior_exponents": exponents,
        "per_speaker": {},
        "overall": {},
        "load_average": os.getloadavg(),
    }
    for m in systems:
        res["per_speaker"][m] = {
            s: scores(np.concatenate(truths[s]), np.concatenate(preds[m][s])) for s in speakers
        }
        res["overall"][m] = scores(
            np.concatenate([np.concatenate(truths[s]) for s in speakers]),
            np.concatenate([np.concatenate(preds[m][s]) for s in speakers]),
        )
        if not args.quick:
            res["overall"][m]["x_realtime"] = audio_s / max(cpu[m], 1e-9) if cpu[m] else None
    lines = [
        (
            f"\n## Lip-sync, speakers held out ({len(FOLDS)} folds by speaker; "
            f"{sum(len(t) for s in speakers for t in truths[s])} frames)\n"
        ),
        "| speaker | fold | frames | " + " | ".join(f"{m} acc / F1" for m in systems) + " |",
        "|---|---|---|" + "---|" * len(systems),
    ]
    for s in speakers:
        fold = next(i for i, f in enumerate(FOLDS) if s in f)
        cells = [
            f"{res['per_speaker'][m][s]['accuracy']:.3f} / {res['per_speaker'][m][s]['macro_f1']:.3f}"
            for m in systems
        ]
        lines.append(
            f"| {s} | {fold + 1} | {res['per_speaker'][systems[0]][s]['frames']} | "
            + " | ".join(cells)
            + " |"
        )
    lines.append(
        "| **all** | | "
        + str(res["overall"][systems[0]]["frames"])
        + " | "
        + " | ".join(
            f"**{res['overall'][m]['accuracy']:.3f} / {res['overall'][m]['macro_f1']:.3f}**"
            for m in systems
        )
        + " |"
    )
    if not args.quick:
        lines.append(
            "\n× real time (1 core, process time): "
            + ", ".join(
                f"{m} {res['overall'][m]['x_realtime']:.0f}"
                for m in systems
                if res["overall"][m]["x_realtime"]
            )
        )
    if not args.quick:
        from facecast.server.audio.align import MAX_MISMATCH, MISMATCH_SLACK, PHONE_RATE

        own = [v["own"] > v["limit"] for v in check.values()]
        other = [o > v["limit"] for v in check.values() for o in v["other"]]
        shipped_own = [v["own"] > MAX_MISMATCH for v in check.values()]
        shipped_other = [o > MAX_MISMATCH for v in check.values() for o in v["other"]]
        res["transcript_check"] = {
            "limits": limits,
            "false_refusals": int(sum(own)),
            "own": len(own),
            "correct_refusals": int(sum(other)),
            "other": len(other),
            "refused_own": [n for n, v in check.items() if v["own"] > v["limit"]],
            "shipped_limit": MAX_MISMATCH,
            "shipped_false_refusals": int(sum(shipped_own)),
            "shipped_correct_refusals": int(sum(shipped_other)),
            "values": check,
        }
        lines.append(
            f"\nTranscript check (phones per second of sound {PHONE_RATE}; mismatch less "
            f"{MISMATCH_SLACK:g}/sqrt(phones) against each fold's limit, chosen on its training "
            f"speakers: {', '.join(f'{v:.2f}' for v in limits.values())}): correct transcripts "
            f"refused {sum(own)}/{len(own)} ({sum(own) / max(len(own), 1):.0%}), another "
            f"recording's transcript refused {sum(other)}/{len(other)} "
            f"({sum(other) / max(len(other), 1):.0%}); with the shipped limit {MAX_MISMATCH} "
            f"(chosen on all these held-out values): {sum(shipped_own)}/{len(own)} and "
            f"{sum(shipped_other)}/{len(other)}. Refused own transcripts are scored with the "
            "no-text output."
        )
        drv = AudioLiveDriver(None, 16000, fps=100.0)
        lines.append(
            f"\nLive look-ahead (algorithmic latency, with or without text): "
            f"{drv.latency * 1000:.0f} ms (budget {drv.lookahead * 1000:.0f} ms)."
        )
    lines.append(
        f"\nLoad average: {res['load_average'][0]:.1f} (2 cores shared). Args: {vars(args)}"
    )
    cm = np.array(res["overall"]["facecast"]["confusion"])
    lines.append(
        "\nConfusion, facecast batch, held-out speakers (rows truth, columns predicted):\n"
    )
    lines.append("| truth \\ pred | " + " | ".join(c[:6] for c in CLASSES) + " |")
    lines.append("|---" * (len(CLASSES) + 1) + "|")
    for i, c in enumerate(CLASSES):
        lines.append(f"| {c} | " + " | ".join(str(v) for v in cm[i]) + " |")
    text = "\n".join(lines) + "\n"
    frames.OUT.mkdir(parents=True, exist_ok=True)
    tag = f"_quick{os.getpid()}" if args.quick else ""
    (frames.OUT / f"lipsync_folds{tag}.json").write_text(json.dumps(res, indent=1))
    (frames.OUT / f"lipsync_folds{tag}.md").write_text(text)
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
