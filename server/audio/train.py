"""Train the 12-10-5 vowel network on espeak-ng material and write ``vowel_net.npz``; and
``fit_frames``, the frame network's trainer (used by ``bench/lipsync/frames.py``).

    python -m facecast.server.audio.train [--per-vowel 200] [--seed 0] [--out PATH]

Reproducible: the utterance list, initial weights and shuffles all come from ``--seed``. The
network is trained by back-propagation (mini-batch gradient descent with momentum, cross-entropy
on a softmax output). The source trained for 5 shuffled cycles over its recordings; facecast's
generated set is cleaner but smaller per speaker, so it runs more epochs (``--epochs``).
Validation holds out two training voice variants and reports their frame accuracy.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time

import numpy as np

from .classify import VOWELS, WEIGHTS, FrameNet, VowelNet
from .generate import Dataset, generate

log = logging.getLogger(__name__)


def fit(
    k: np.ndarray,
    y: np.ndarray,
    *,
    hidden: int = 10,
    epochs: int = 60,
    lr: float = 0.05,
    momentum: float = 0.9,
    batch: int = 32,
    seed: int = 0,
) -> VowelNet:
    """Back-propagation training of a ``12-hidden-5`` net on ``k (N, 12)``, labels ``y (N,)``."""
    rng = np.random.default_rng(seed)
    mean, std = k.mean(axis=0), k.std(axis=0) + 1e-6
    x = (k - mean) / std
    n_in, n_out = x.shape[1], len(VOWELS)
    w1 = rng.normal(0, 1 / np.sqrt(n_in), (n_in, hidden))
    b1 = np.zeros(hidden)
    w2 = rng.normal(0, 1 / np.sqrt(hidden), (hidden, n_out))
    b2 = np.zeros(n_out)
    vel = [np.zeros_like(p) for p in (w1, b1, w2, b2)]
    onehot = np.eye(n_out)[y]
    # class-balanced sample weights
    cw = len(y) / (n_out * np.maximum(np.bincount(y, minlength=n_out), 1))
    for epoch in range(epochs):
        step = lr * (0.5 * (1 + np.cos(np.pi * epoch / epochs)) + 0.02)
        for idx in np.array_split(rng.permutation(len(x)), max(1, len(x) // batch)):
            xb, tb, wb = x[idx], onehot[idx], cw[y[idx]][:, None]
            h = np.tanh(xb @ w1 + b1)
            z = h @ w2 + b2
            p = np.exp(z - z.max(axis=1, keepdims=True))
            p /= p.sum(axis=1, keepdims=True)
            dz = (p - tb) * wb / len(idx)
            dh = (dz @ w2.T) * (1 - h * h)
            grads = (xb.T @ dh, dh.sum(0), h.T @ dz, dz.sum(0))
            for v, g, prm in zip(vel, grads, (w1, b1, w2, b2)):
                v *= momentum
                v -= step * g
                prm += v
    return VowelNet(w1, b1, w2, b2, mean, std)


def confusion(y: np.ndarray, pred: np.ndarray, n: int = len(VOWELS)) -> np.ndarray:
    """``(n, n)`` counts, rows = true class, columns = predicted."""
    m = np.zeros((n, n), dtype=np.int64)
    np.add.at(m, (y, pred), 1)
    return m


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m facecast.server.audio.train",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--per-vowel", type=int, default=200, help="utterances per vowel (default 200)")
    p.add_argument("--epochs", type=int, default=60)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=str(WEIGHTS), help=f"weights file (default {WEIGHTS})")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    t = time.perf_counter()
    data: Dataset = generate(args.per_vowel, args.seed, progress=sys.stderr.isatty())
    log.info(
        "generated %d frames from %d utterances in %.1f s; per class %s",
        len(data.y),
        5 * args.per_vowel,
        time.perf_counter() - t,
        np.bincount(data.y).tolist(),
    )
    groups = sorted(set(data.group))
    rng = np.random.default_rng(args.seed)
    val_groups = set(rng.choice(groups, size=2, replace=False))
    val = np.isin(data.group, list(val_groups))
    net = fit(data.k[~val], data.y[~val], epochs=args.epochs, seed=args.seed)
    acc = float(np.mean(net.predict(data.k[val]) == data.y[val]))
    log.info(
        "validation on held-out variants %s: frame accuracy %.3f\n%s",
        sorted(map(str, val_groups)),
        acc,
        confusion(data.y[val], net.predict(data.k[val])),
    )
    net = fit(data.k, data.y, epochs=args.epochs, seed=args.seed)  # final: all variants
    log.info("training accuracy %.3f", float(np.mean(net.predict(data.k) == data.y)))
    net.save(
        args.out,
        command="python -m facecast.server.audio.train " + " ".join(argv or sys.argv[1:]),
        validation_accuracy=f"{acc:.4f}",
        frames=str(len(data.y)),
    )
    log.info("wrote %s", args.out)
    return 0


def fit_frames(
    X: np.ndarray,
    y: np.ndarray,
    offsets: np.ndarray,
    *,
    hidden: int = 48,
    epochs: int = 30,
    lr: float = 3e-3,
    batch: int = 256,
    l2: float = 1e-4,
    balance: float = 0.5,
    dropout: float = 0.0,
    seed: int = 0,
    n_classes: int = 10,
):
    """Train a ``FrameNet`` (tanh hidden layer, softmax output, cross-entropy) with Adam on
    context-stacked inputs ``X (N, D)`` and class labels ``y (N,)`` (0..9).

    Class weights are ``(N / (C·count))**balance`` (0 = none, 1 = fully balanced), for macro-F1.
    ``dropout``: the fraction of hidden units zeroed per training example (inverted dropout: the
    kept ones scaled by ``1 / (1 - dropout)``, so inference is unchanged); 0 = none, and then no
    random numbers are drawn for it (the same weights as before it existed).
    Reproducible from ``seed``.
    """
    rng = np.random.default_rng(seed)
    mean, std = X.mean(axis=0), X.std(axis=0) + 1e-6
    x = ((X - mean) / std).astype(np.float32)
    n_in = x.shape[1]
    params = [
        rng.normal(0, 1 / np.sqrt(n_in), (n_in, hidden)).astype(np.float32),
        np.zeros(hidden, np.float32),
        rng.normal(0, 1 / np.sqrt(hidden), (hidden, n_classes)).astype(np.float32),
        np.zeros(n_classes, np.float32),
    ]
    m = [np.zeros_like(p) for p in params]
    v = [np.zeros_like(p) for p in params]
    counts = np.maximum(np.bincount(y, minlength=n_classes), 1)
    cw = ((len(y) / (n_classes * counts)) ** balance).astype(np.float32)
    onehot = np.eye(n_classes, dtype=np.float32)[y]
    step = 0
    for epoch in range(epochs):
        rate = lr * (0.5 * (1 + np.cos(np.pi * epoch / epochs)) + 0.02)
        for idx in np.array_split(rng.permutation(len(x)), max(1, len(x) // batch)):
            w1, b1, w2, b2 = params
            xb, tb, wb = x[idx], onehot[idx], cw[y[idx]][:, None]
            h = np.tanh(xb @ w1 + b1)
            hd = h
            if dropout > 0:
                mask = (rng.random(h.shape, dtype=np.float32) >= dropout) / np.float32(1 - dropout)
                hd = h * mask
            z = hd @ w2 + b2
            p = np.exp(z - z.max(axis=1, keepdims=True))
            p /= p.sum(axis=1, keepdims=True)
            dz = (p - tb) * wb / wb.sum()
            dh = (dz @ w2.T) * (1 - h * h)
            if dropout > 0:
                dh *= mask
            grads = (xb.T @ dh + l2 * w1, dh.sum(0), hd.T @ dz + l2 * w2, dz.sum(0))
            step += 1
            for i, g in enumerate(grads):
                m[i] = 0.9 * m[i] + 0.1 * g
                v[i] = 0.999 * v[i] + 0.001 * g * g
                mh = m[i] / (1 - 0.9**step)
                vh = v[i] / (1 - 0.999**step)
                params[i] -= rate * mh / (np.sqrt(vh) + 1e-8)
    return FrameNet(
        *(p.astype(np.float64) for p in params), mean, std, np.asarray(offsets, dtype=np.int64)
    )


def merge_frame_nets(nets: list[FrameNet]) -> FrameNet:
    """One ``FrameNet`` whose output is the normalised geometric mean of ``nets``' outputs.

    Members trained on the same inputs (same standardisation and offsets) with different seeds
    side by side: the hidden layers are concatenated (``H·len(nets)`` units) and the output
    logits averaged, ``softmax(mean_i z_i)`` = the product of the members' probabilities,
    renormalised. One matrix product per layer, so a frame costs one wider network, not
    ``len(nets)`` calls."""
    first = nets[0]
    for n in nets[1:]:
        if not (
            np.array_equal(n.offsets, first.offsets)
            and np.allclose(n.mean, first.mean)
            and np.allclose(n.std, first.std)
            and (n.norm_mean is None) == (first.norm_mean is None)
            and (n.norm_mean is None or np.allclose(n.norm_mean, first.norm_mean))
        ):
            raise ValueError(
                "ensemble members must share their inputs (offsets, standardisation, "
                "speaker normalisation)"
            )
    k = len(nets)
    return FrameNet(
        np.concatenate([n.w1 for n in nets], axis=1),
        np.concatenate([n.b1 for n in nets]),
        np.concatenate([n.w2 for n in nets], axis=0) / k,
        np.mean([n.b2 for n in nets], axis=0),
        first.mean,
        first.std,
        first.offsets,
        norm_mean=first.norm_mean,
    )


if __name__ == "__main__":
    sys.exit(main())
