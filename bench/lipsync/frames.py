"""Training material and speaker-disjoint folds for facecast's frame network.

    python bench/lipsync/frames.py folds      # leave-one-speaker-out table → bench/out/lipsync_folds.*
    python bench/lipsync/frames.py ship       # train on every speaker → server/audio/frame_net.npz

Material: the real recordings (``corpus.recordings_utterances``: PocketSphinx alignments of
../shared/data/real-speech, cached under bench/out, plus bobby and mary) and espeak-ng development
sentences spoken by training voice variants (``corpus.generated_utterances(dev=True)``; the
scored synthetic sentences and held-out variants are never trained on). Each utterance is used
clean and through ``N_AUGMENT`` random channels (``channel``: level, band limit / sample rate,
tilt, room reverberation, noise).
"""
from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # one core
    os.environ.setdefault(_v, "1")

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.signal

sys.path.insert(0, str(Path(__file__).parent))

from corpus import Utterance, generated_utterances, recordings_utterances  # noqa: E402
from facecast.server.audio.classify import stack_context  # noqa: E402
from facecast.server.audio.generate import augment  # noqa: E402
from facecast.server.audio.io import read_audio, resample  # noqa: E402
from facecast.server.audio.pipeline import features_of  # noqa: E402
from facecast.server.audio.visemes import calibrate  # noqa: E402
from facecast.server.audio.classify import frame_features  # noqa: E402
from facecast.server.audio.train import fit_frames  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "bench" / "out"
#: Context offsets (10 ms frames) of the shipped network: 80 ms back, 30 ms ahead.
OFFSETS = np.array([-8, -6, -4, -3, -2, -1, 0, 1, 2, 3])
N_AUGMENT = 2
HIDDEN = 64
EPOCHS = 12
#: Class weighting (1 = balanced: macro-F1 counts every class alike).
BALANCE = 1.0
#: Every STEP-th frame of each copy is trained on (neighbouring 10 ms frames are nearly equal).
STEP = 3


def channel(x: np.ndarray, sr: int, rng: np.random.Generator) -> np.ndarray:
    """A random recording channel: ``generate.augment`` (tilt, band limit, level, noise), then
    maybe a room (exponentially decaying noise impulse response, RT60 0.15-0.5 s, 30-60 % wet)
    and maybe a telephone-like 8 kHz round trip."""
    y = augment(x, sr, rng)
    if rng.random() < 0.4:
        rt60 = rng.uniform(0.15, 0.5)
        n = int(rt60 * sr)
        ir = rng.normal(0, 1, n) * np.exp(-6.9 * np.arange(n) / n)
        ir[0] = 0
        wet = scipy.signal.fftconvolve(y, ir)[:len(y)]
        wet *= np.sqrt(np.mean(y ** 2) / (np.mean(wet ** 2) + 1e-20))
        y = y + rng.uniform(0.3, 0.6) * wet
    if rng.random() < 0.2 and sr > 8000:
        y = resample(resample(y, sr, 8000), 8000, sr)[:len(y)]
    return np.clip(y / (np.abs(y).max() + 1e-12) * rng.uniform(0.05, 0.9), -1, 1)


def utterance_frames(x: np.ndarray, sr: int) -> np.ndarray:
    """``(T, 44)`` frame features of one utterance with its own file calibration."""
    f = features_of(x, sr)
    cal = calibrate(f.energy_db)
    return frame_features(f.k, f.energy_db, f.zcr, cal.silence_db, cal.max_db, f.shape, f.cep)


@dataclass
class Item:
    utt: Utterance
    feats: list[np.ndarray]   # clean, then augmented copies: (T, 44) each


def load_items(seed: int = 0) -> tuple[list[Item], list[Item]]:
    """``(real, synthetic_dev)`` utterances with their clean and augmented frame features."""
    from facecast.server.paths import shared_data

    data = shared_data()
    if data is None:
        raise SystemExit("../shared/data is absent")
    rng = np.random.default_rng(seed)
    real = recordings_utterances(data, OUT / "lipsync_data" / "real")
    dev = generated_utterances(OUT / "lipsync_data", 18, dev=True)
    out = []
    for group in (real, dev):
        items = []
        for u in group:
            x, sr = read_audio(u.audio)
            items.append(Item(u, [utterance_frames(x, sr)] +
                              [utterance_frames(channel(x, sr, rng), sr) for _ in range(N_AUGMENT)]))
        out.append(items)
    return out[0], out[1]


def training_set(items: list[Item], offsets: np.ndarray,
                 step: int = STEP) -> tuple[np.ndarray, np.ndarray]:
    """Stacked inputs and labels of every ``step``-th frame with a known class (copy c starts at
    frame c, so the copies together cover every frame), all copies."""
    xs, ys = [], []
    for it in items:
        for c, F in enumerate(it.feats):
            n = min(len(F), len(it.utt.truth))
            X, y = stack_context(F, offsets)[:n], it.utt.truth[:n]
            keep = (np.arange(n) % step) == (c % step)
            X, y = X[keep], y[keep]
            ok = y >= 0
            xs.append(X[ok])
            ys.append(y[ok])
    return np.concatenate(xs).astype(np.float32), np.concatenate(ys)


def train(items: list[Item], offsets: np.ndarray = OFFSETS, seed: int = 0, step: int = STEP,
          **kw):
    X, y = training_set(items, offsets, step)
    kw = {"hidden": HIDDEN, "epochs": EPOCHS, "balance": BALANCE} | kw
    return fit_frames(X, y, offsets, seed=seed, **kw)


def ship(argv: list[str]) -> int:
    from facecast.server.audio.classify import FRAME_WEIGHTS

    from folds import cached_items

    real, dev = cached_items(refresh="--refresh" in argv)
    net = train(real + dev)
    speakers = sorted({it.utt.speaker for it in real})
    net.save(FRAME_WEIGHTS, command="python bench/lipsync/frames.py ship",
             speakers=" ".join(speakers), utterances=str(len(real) + len(dev)))
    print(f"wrote {FRAME_WEIGHTS} ({len(real)} real utterances of {len(speakers)} speakers + "
          f"{len(dev)} synthetic)")
    return 0


if __name__ == "__main__":
    cmd = sys.argv[1] if len(sys.argv) > 1 else "folds"
    if cmd == "ship":
        sys.exit(ship(sys.argv[2:]))
    from folds import main

    sys.exit(main(sys.argv[2:]))
