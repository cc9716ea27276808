"""The 12-10-5 back-propagation network over reflection coefficients; inference in NumPy.

Weights ship as ``vowel_net.npz`` beside this module (made by ``python -m
facecast.server.audio.train``). Layers: standardise → tanh(12→10) → softmax(10→5) over /a e i o u/.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.signal

from ..errors import FacecastError

WEIGHTS = Path(__file__).with_name("vowel_net.npz")
VOWELS = ("a", "e", "i", "o", "u")


#: Arrays every network file holds (the dataclasses' first fields, in order).
_PARAMS = ("w1", "b1", "w2", "b2", "mean", "std")


def _softmax(z: np.ndarray) -> np.ndarray:
    """Row-wise softmax of ``z (T, C)``."""
    z = np.exp(z - z.max(axis=-1, keepdims=True))
    return z / z.sum(axis=-1, keepdims=True)


def _save(
    path: str | Path, net, classes: tuple[str, ...], meta: dict[str, str], **extra: np.ndarray
) -> None:
    """Write ``net``'s ``_PARAMS``, ``extra`` arrays, the class names and ``meta_*`` strings."""
    np.savez(
        path,
        **{n: getattr(net, n) for n in _PARAMS},
        **extra,
        classes=np.array(classes),
        **{f"meta_{k}": np.array(v) for k, v in meta.items()},
    )


def _load(path: str | Path, what: str, make: str, *extra: str) -> list[np.ndarray]:
    """``_PARAMS`` as float64, then the ``extra`` arrays as stored, from ``path``; FacecastError
    naming ``what`` network and the command that ``make``s the file when it is missing."""
    path = Path(path)
    if not path.is_file():
        raise FacecastError(f"{what} network weights missing: {path}; run '{make}'")
    with np.load(path) as z:
        return [z[n].astype(np.float64) for n in _PARAMS] + [
            z[n] if n in z.files else None for n in extra
        ]


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
        return _softmax(self.logits(k))

    def predict(self, k: np.ndarray) -> np.ndarray:
        """``(T,) int`` index into ``VOWELS``."""
        return np.argmax(self.logits(k), axis=-1)

    def save(self, path: str | Path, **meta: str) -> None:
        _save(path, self, VOWELS, meta)

    @classmethod
    def load(cls, path: str | Path = WEIGHTS) -> VowelNet:
        return cls(*_load(path, "vowel", "python -m facecast.server.audio.train"))


@functools.lru_cache(maxsize=1)
def default_net() -> VowelNet:
    """The shipped network (loaded once)."""
    return VowelNet.load(WEIGHTS)


# -- the frame network: ten visual classes from context-stacked LPC features ---------------------

#: Visual classes of the frame network (phones grouped by what the mouth shows; the same ten
#: classes as ``bench/lipsync``): silence; P B M; F V; S Z SH ZH CH JH; AA AE AH AW AY; EH EY ER;
#: IH IY Y; AO OW OY; UH UW W; the rest (tongue and throat consonants: T D N L K G R HH NG TH DH).
CLASSES = (
    "sil",
    "closed",
    "labiodental",
    "sibilant",
    "open",
    "mid",
    "spread",
    "round",
    "narrow-round",
    "other",
)
#: MPEG-4 viseme id shown for each class (0 sil, 1 PP, 2 FF, 7 SS, 10 aa, 11 E, 12 ih, 13 oh,
#: 14 ou, 4 DD).
CLASS_VISEMES = np.array([0, 1, 2, 7, 10, 11, 12, 13, 14, 4])
FRAME_WEIGHTS = Path(__file__).with_name("frame_net.npz")
#: Feature columns per frame (see ``frame_features``).
N_FRAME_FEATURES = 44


def frame_features(
    k: np.ndarray,
    energy_db: np.ndarray,
    zcr: np.ndarray,
    silence_db: np.ndarray | float,
    max_db: np.ndarray | float,
    shape: np.ndarray,
    cep: np.ndarray,
) -> np.ndarray:
    """``(T, 44)`` per-frame inputs of the frame network, all invariant to the input level:
    log-area ratios of ``k (T, 12)``, the LPC cepstrum c1..c12, the prediction gain (dB/10,
    voicing and spectral flatness), energy relative to the calibrated maximum and to the silence
    threshold (dB/10, clipped), log(1 + zero crossings per 10 ms), and the mel-band spectral
    shape ``(T, 16)`` (``Features.shape``, /4); ``cep (T, 12)`` is ``Features.cep``."""
    # np.minimum/np.maximum: np.clip's overhead weighs on the live path's few frames
    k = np.minimum(np.maximum(np.asarray(k, dtype=np.float64), -0.999), 0.999)
    lar = np.log((1 - k) / (1 + k))
    gain = 10 * np.log10((1 - k * k).prod(axis=1) + 1e-12) / 10  # the method: no wrapper
    rel_max, rel_sil = calibration_columns(energy_db, silence_db, max_db)
    # one concatenate of 2-D columns: np.column_stack's per-array conversions cost more
    return np.concatenate(
        [
            lar,
            np.asarray(cep, dtype=np.float64),
            gain[:, None],
            rel_max[:, None],
            rel_sil[:, None],
            np.log1p(np.asarray(zcr, dtype=np.float64))[:, None],
            np.asarray(shape, dtype=np.float64) / 4,
        ],
        axis=1,
    )


#: Columns of ``frame_features`` that depend on the energy calibration (``calibration_columns``).
CALIBRATION_COLUMNS = slice(25, 27)


def calibration_columns(
    energy_db: np.ndarray, silence_db: np.ndarray | float, max_db: np.ndarray | float
) -> tuple[np.ndarray, np.ndarray]:
    """``frame_features``' ``(rel_max (T,), rel_sil (T,))``: energy relative to the calibrated
    maximum and to the silence threshold, dB/10, clipped to [-6, 1] and [-3, 5]."""
    e = np.asarray(energy_db, dtype=np.float64)
    rel_max = np.minimum(np.maximum((e - max_db) / 10, -6.0), 1.0)
    rel_sil = np.minimum(np.maximum((e - silence_db) / 10, -3.0), 5.0)
    return rel_max, rel_sil


#: Columns of ``frame_features`` that a speaker's vocal tract and channel move (log-area ratios,
#: cepstrum, mel-band shape): ``SpeakerNorm`` takes their running mean out.
SPECTRAL_COLUMNS = np.r_[0:24, 28:44]
#: Column of ``frame_features`` above 0 on speech (energy over the silence threshold).
SPEECH_COLUMN = 26


class SpeakerNorm:
    """Causal per-speaker normalisation of ``frame_features`` rows: the ``SPECTRAL_COLUMNS``
    minus their running mean over the speech frames so far (each speech frame's weight decays
    with time constant ``TAU`` seconds of speech), the mean starting at the training speech's
    ``mean (40,)`` counted as ``PRIOR`` frames. Calls carry the state on, so a stream fed in
    chunks gets the rows the whole file gets (batch and live read the same inputs)."""

    TAU = 2.0
    PRIOR = 50.0

    def __init__(self, mean: np.ndarray, hop: float = 0.01) -> None:
        self.decay = float(np.exp(-hop / self.TAU))
        #: 1 on the ``SPECTRAL_COLUMNS`` of a feature row, 0 elsewhere
        self.mask = np.zeros(N_FRAME_FEATURES)
        self.mask[SPECTRAL_COLUMNS] = 1.0
        self.acc = np.zeros(N_FRAME_FEATURES)
        self.acc[SPECTRAL_COLUMNS] = self.PRIOR * np.asarray(mean, dtype=np.float64)
        self.w = self.PRIOR
        self.mean = self.acc / self.w  # the running mean, 0 off the spectral columns

    def __call__(self, F: np.ndarray) -> np.ndarray:
        """``F (T, 44)`` normalised (a new array); the state moves past its rows."""
        F = np.asarray(F, dtype=np.float64)
        d = self.decay
        if len(F) <= 4:  # the live path's few frames: one small matrix product, no filter
            flags = (F[:, SPEECH_COLUMN] > 0).tolist()
            if not any(flags):
                return F - self.mean
            # row t's mean = (d^c_t·acc + sum over speech rows j <= t of d^(c_t - c_j)·F_j) / w_t,
            # c_t = speech rows up to t: coefficients in Python, then one product
            coef, w, acc_c, rows = [], self.w, 1.0, [0.0] * len(flags)
            for j, sp in enumerate(flags):
                if sp:
                    acc_c *= d
                    rows = [r * d for r in rows]
                    rows[j] = 1.0
                    w = d * w + 1.0
                coef.append([acc_c / w] + [r / w for r in rows])
            M = np.array(coef) @ np.concatenate([self.acc[None], F])  # (T, 44) running means
            self.w = w
            self.acc = M[-1] * w
            self.mean = M[-1] * self.mask
            return F - M * self.mask
        speech = F[:, SPEECH_COLUMN] > 0
        n = int(np.count_nonzero(speech))
        if n == 0:
            return F - self.mean
        acc, _ = scipy.signal.lfilter([1.0], [1.0, -d], F[speech], axis=0, zi=d * self.acc[None])
        dn = d ** np.arange(1, n + 1)
        w = dn * self.w + (1 - dn) / (1 - d)
        means = np.concatenate([self.mean[None], (acc / w[:, None]) * self.mask])
        self.acc, self.w, self.mean = acc[-1], float(w[-1]), means[-1]
        return F - means[np.cumsum(speech)]


#: Frames per block of ``FrameNet.proba`` (the stacked inputs of a block: about 14 MB).
BLOCK_FRAMES = 4096


def stack_context(F: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """``(T, D·len(offsets))``: row t holds rows ``t + o`` of ``F (T, D)`` for each offset o
    (edge rows repeated past either end)."""
    return stack_rows(F, offsets, 0, len(F))


def stack_rows(F: np.ndarray, offsets: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """Rows ``lo:hi`` of ``stack_context(F, offsets)``, ``(hi - lo, D·len(offsets))``."""
    offsets = np.asarray(offsets)
    idx = _stack_index(lo, hi, len(F), offsets.tobytes(), offsets.dtype.str)
    return F[idx].reshape(hi - lo, F.shape[1] * len(offsets))


@functools.lru_cache(maxsize=64)
def _stack_index(lo: int, hi: int, n: int, offsets: bytes, dtype: str) -> np.ndarray:
    """``(hi - lo, len(offsets))`` row indices of ``stack_rows`` (read-only; made once per
    shape: the live path asks for the same few every chunk)."""
    offs = np.frombuffer(offsets, dtype=dtype)
    idx = np.arange(lo, hi)[:, None] + offs[None, :]
    idx = np.minimum(np.maximum(idx, 0), max(n - 1, 0))
    idx.flags.writeable = False
    return idx


@dataclass
class FrameNet:
    """A small MLP over context-stacked frame features: standardise → tanh(D→H) → softmax(H→10)
    over ``CLASSES``. ``offsets``: frame offsets stacked (the largest is the look-ahead the
    network needs, in 10 ms frames)."""

    w1: np.ndarray
    b1: np.ndarray
    w2: np.ndarray
    b2: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    offsets: np.ndarray
    #: ``(10,)`` mean class probabilities over the speech it was trained on (the prior a
    #: transcript's alignment divides by before a stream has shown its own); None = unknown.
    mean_proba: np.ndarray | None = None
    #: ``(40,)`` the training speech's mean of the ``SPECTRAL_COLUMNS``: inputs pass through a
    #: ``SpeakerNorm`` started from it; None = none (inputs as they come).
    norm_mean: np.ndarray | None = None

    def speaker_norm(self) -> SpeakerNorm | None:
        """A fresh ``SpeakerNorm`` for one utterance or stream (None: the network has none)."""
        return None if self.norm_mean is None else SpeakerNorm(self.norm_mean)

    @property
    def future(self) -> int:
        """Frames after t the network needs for frame t."""
        return max(0, int(np.max(self.offsets)))

    @property
    def past(self) -> int:
        return max(0, -int(np.min(self.offsets)))

    def _folded(self) -> tuple[np.ndarray, np.ndarray]:
        """``(w1 / std, b1 - (mean / std) @ w1)`` as float32: the standardisation folded into
        the first layer (made once; remade if any of those arrays is replaced)."""
        key = (id(self.w1), id(self.b1), id(self.mean), id(self.std))
        cached = self.__dict__.get("_fold")
        if cached is None or cached[0] != key:
            w = (self.w1 / self.std[:, None]).astype(np.float32)
            b = (self.b1 - (self.mean / self.std) @ self.w1).astype(np.float32)
            self.__dict__["_fold"] = cached = (key, w, b)
        return cached[1], cached[2]

    def proba_stacked(self, X: np.ndarray) -> np.ndarray:
        """``(T, 10)`` class probabilities of context-stacked inputs ``X (T, D)`` (the hidden
        layer in float32: half the time of float64, probabilities within 1e-5)."""
        w1, b1 = self._folded()
        h = np.tanh(np.asarray(X, dtype=np.float32) @ w1 + b1)
        return _softmax(h.astype(np.float64) @ self.w2 + self.b2)

    def proba(self, F: np.ndarray) -> np.ndarray:
        """``(T, 10)`` class probabilities of per-frame features ``F (T, 44)`` (one utterance,
        through a fresh ``speaker_norm`` when the network has one).

        The context-stacked inputs are built ``BLOCK_FRAMES`` rows at a time (as
        ``stack_context``: edge rows repeated past either end of the utterance), so the memory
        beyond ``F`` and the output does not grow with the utterance's length.
        """
        T = len(F)
        norm = self.speaker_norm()
        if norm is None:
            # float32 before stacking (the hidden layer's type): one conversion of F, not of
            # the ten times larger stacked inputs; the same values
            F = np.asarray(F, dtype=np.float32)
        else:  # normalised a block at a time (the state carries on), into float32
            G = np.empty(np.shape(F), dtype=np.float32)
            for i in range(0, T, BLOCK_FRAMES):
                G[i : i + BLOCK_FRAMES] = norm(F[i : i + BLOCK_FRAMES])
            F = G
        blocks = (
            stack_rows(F, self.offsets, i, min(T, i + BLOCK_FRAMES))
            for i in range(0, max(T, 1), BLOCK_FRAMES)
        )  # one block's inputs at a time
        return np.concatenate([self.proba_stacked(X) for X in blocks])

    def save(self, path: str | Path, **meta: str) -> None:
        extra = {
            n: getattr(self, n) for n in ("mean_proba", "norm_mean") if getattr(self, n) is not None
        }
        _save(path, self, CLASSES, meta, offsets=self.offsets, **extra)

    @classmethod
    def load(cls, path: str | Path = FRAME_WEIGHTS) -> FrameNet:
        *params, offsets, mean_proba, norm_mean = _load(
            path,
            "frame",
            "python bench/lipsync/frames.py ship",
            "offsets",
            "mean_proba",
            "norm_mean",
        )
        return cls(
            *params,
            offsets=offsets.astype(np.int64),
            mean_proba=None if mean_proba is None else mean_proba.astype(np.float64),
            norm_mean=None if norm_mean is None else norm_mean.astype(np.float64),
        )


@functools.lru_cache(maxsize=1)
def default_frame_net() -> FrameNet:
    """The shipped frame network (loaded once)."""
    return FrameNet.load(FRAME_WEIGHTS)
