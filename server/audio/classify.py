"""The 12-10-5 back-propagation network over reflection coefficients; inference in NumPy.

Weights ship as ``vowel_net.npz`` beside this module (made by ``python -m
facecast.server.audio.train``). Layers: standardise → tanh(12→10) → softmax(10→5) over /a e i o u/.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FacecastError

WEIGHTS = Path(__file__).with_name("vowel_net.npz")
VOWELS = ("a", "e", "i", "o", "u")


@dataclass
class VowelNet:
    """Weights of the 12-10-5 network. ``w1 (12, 10)``, ``b1 (10,)``, ``w2 (10, 5)``, ``b2 (5,)``;
    inputs are standardised with ``mean (12,)``, ``std (12,)``."""

    w1: np.ndarray
    b1: np.ndarray
    w2: np.ndarray
    b2: np.ndarray
    mean: np.ndarray
    std: np.ndarray

    def hidden(self, k: np.ndarray) -> np.ndarray:
        return np.tanh(((k - self.mean) / self.std) @ self.w1 + self.b1)

    def logits(self, k: np.ndarray) -> np.ndarray:
        """``(T, 5)`` output activations for reflection coefficients ``k (T, 12)``."""
        return self.hidden(np.asarray(k, dtype=np.float64)) @ self.w2 + self.b2

    def proba(self, k: np.ndarray) -> np.ndarray:
        """``(T, 5)`` class probabilities (softmax), rows sum to 1."""
        z = self.logits(k)
        z = np.exp(z - z.max(axis=-1, keepdims=True))
        return z / z.sum(axis=-1, keepdims=True)

    def predict(self, k: np.ndarray) -> np.ndarray:
        """``(T,) int`` index into ``VOWELS``."""
        return np.argmax(self.logits(k), axis=-1)

    def save(self, path: str | Path, **meta: str) -> None:
        np.savez(path, w1=self.w1, b1=self.b1, w2=self.w2, b2=self.b2, mean=self.mean,
                 std=self.std, classes=np.array(VOWELS), **{f"meta_{k}": np.array(v)
                                                           for k, v in meta.items()})

    @classmethod
    def load(cls, path: str | Path = WEIGHTS) -> VowelNet:
        path = Path(path)
        if not path.is_file():
            raise FacecastError(f"vowel network weights missing: {path}; run "
                                "'python -m facecast.server.audio.train'")
        with np.load(path) as z:
            return cls(*(z[n].astype(np.float64) for n in ("w1", "b1", "w2", "b2", "mean", "std")))


@functools.lru_cache(maxsize=1)
def default_net() -> VowelNet:
    """The shipped network (loaded once)."""
    return VowelNet.load(WEIGHTS)
