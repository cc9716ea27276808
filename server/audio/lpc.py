"""Linear-predictive analysis of speech frames (Kshirsagar & Magnenat-Thalmann, ICME 2000).

Pure functions over NumPy arrays; the sample rate, frame length and hop are explicit. Time is the
last axis. Polynomial convention: ``A(z) = 1 + a_1 z^-1 + ... + a_p z^-p`` (as ``scipy.signal.lfilter``
takes it), so an AR process is ``x = lfilter([1], a, e)``; reflection coefficients ``k_i`` are the
last coefficient of the order-i predictor in the Levinson–Durbin recursion (``k_1 = -R1/R0``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Analysis rate of the source, Hz.
ANALYSIS_RATE = 10000
#: Frame length (20 ms in the source) and hop (10 ms: facecast's choice, 100 frames/s), seconds.
FRAME_LENGTH = 0.020
HOP_LENGTH = 0.010
#: LPC order (12 reflection coefficients in the source).
ORDER = 12
#: Pre-emphasis coefficient (not stated in the source; the usual 0.97).
PREEMPHASIS = 0.97
#: Frames analysed per block in ``analyze``.
BLOCK = 4096


def preemphasis(x: np.ndarray, *, coef: float = PREEMPHASIS, zi: float = 0.0) -> np.ndarray:
    """``y[n] = x[n] - coef·x[n-1]`` along the last axis; ``zi`` is the sample before ``x[0]``."""
    x = np.asarray(x, dtype=np.float64)
    y = x.copy()
    y[..., 1:] -= coef * x[..., :-1]
    y[..., 0] -= coef * zi
    return y


def frame(x: np.ndarray, *, frame_length: int, hop_length: int) -> np.ndarray:
    """Strided view ``(n_frames, frame_length)`` of ``x (n,)``; frame i starts at ``i·hop_length``.

    ``n_frames = 1 + (n - frame_length) // hop_length`` (0 when ``n < frame_length``).
    """
    x = np.ascontiguousarray(x)
    n = 0 if len(x) < frame_length else 1 + (len(x) - frame_length) // hop_length
    if n == 0:
        return np.zeros((0, frame_length), dtype=x.dtype)
    return np.lib.stride_tricks.as_strided(
        x, shape=(n, frame_length), strides=(x.strides[0] * hop_length, x.strides[0]), writeable=False)


def autocorrelate(frames: np.ndarray, *, max_lag: int) -> np.ndarray:
    """Biased autocorrelation ``R[..., l] = sum_n y[n]·y[n+l]`` for lags ``0..max_lag``.

    Args:
        frames: ``(..., n)`` windowed frames.
    Returns:
        ``(..., max_lag + 1) float64``.
    """
    y = np.asarray(frames, dtype=np.float64)
    n = y.shape[-1]
    return np.stack([np.einsum("...i,...i->...", y[..., : n - lag], y[..., lag:])
                     for lag in range(max_lag + 1)], axis=-1)


def levinson(r: np.ndarray, *, order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Levinson–Durbin recursion on autocorrelations, vectorised over leading axes.

    Args:
        r: ``(..., >= order+1)`` autocorrelation lags ``R0..Rp``.
        order: predictor order p > 0.
    Returns:
        ``(a, k, err)``: ``a (..., p+1)`` predictor polynomial with ``a[..., 0] = 1``;
        ``k (..., p)`` reflection coefficients in (-1, 1); ``err (...,)`` final prediction-error
        power. Frames with ``R0 == 0`` (digital silence) give ``a = [1, 0, ...]``, ``k = 0``.
    """
    r = np.asarray(r, dtype=np.float64)
    lead = r.shape[:-1]
    a = np.zeros(lead + (order + 1,))
    a[..., 0] = 1.0
    k = np.zeros(lead + (order,))
    err = r[..., 0].copy()
    live = err > 0
    safe_err = np.where(live, err, 1.0)
    for i in range(1, order + 1):
        acc = r[..., i] + np.einsum("...j,...j->...", a[..., 1:i], r[..., i - 1:0:-1])
        ki = np.where(live, -acc / safe_err, 0.0)
        ki = np.clip(ki, -0.999999, 0.999999)  # guards round-off on ill-conditioned frames
        prev = a[..., 1:i].copy()
        a[..., 1:i] = prev + ki[..., None] * prev[..., ::-1]
        a[..., i] = ki
        k[..., i - 1] = ki
        err = err * (1.0 - ki * ki)
        safe_err = np.where(live & (err > 0), err, 1.0)
        live = live & (err > 0)
    return a, k, err


def zero_crossing_rate(frames: np.ndarray, *, sr: float) -> np.ndarray:
    """Zero crossings per 10 ms of each frame ``(..., n)`` (frame mean removed first).

    Returns ``(...,) float64``; the source's reference means are 49 (unvoiced) and 14 (voiced).
    """
    y = np.asarray(frames, dtype=np.float64)
    y = y - y.mean(axis=-1, keepdims=True)
    s = np.signbit(y)
    crossings = np.count_nonzero(s[..., 1:] != s[..., :-1], axis=-1)
    return crossings * (0.010 * sr) / y.shape[-1]


@dataclass
class Features:
    """Per-frame LPC features. Frame i is centred on ``t0 + i·hop`` seconds.

    Attributes:
        k: ``(T, 12)`` reflection coefficients.
        energy_db: ``(T,)`` 10·log10 of the mean power R0/N of the windowed, pre-emphasised frame.
        zcr: ``(T,)`` zero crossings per 10 ms.
        hop: seconds between frames; t0: time of frame 0, seconds.
    """

    k: np.ndarray
    energy_db: np.ndarray
    zcr: np.ndarray
    hop: float = HOP_LENGTH
    t0: float = 0.0

    def __len__(self) -> int:
        return len(self.energy_db)

    @property
    def times(self) -> np.ndarray:
        """``(T,)`` frame centre times, seconds."""
        return self.t0 + self.hop * np.arange(len(self))


def analyze_frames(raw_frames: np.ndarray, emph_frames: np.ndarray, *, sr: float = ANALYSIS_RATE,
                   order: int = ORDER) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """LPC features of already-cut frames.

    Args:
        raw_frames: ``(T, N)`` frames of the signal (for the zero-crossing rate).
        emph_frames: ``(T, N)`` the same frames of the pre-emphasised signal.
    Returns:
        ``(k (T, order), energy_db (T,), zcr (T,))``.
    """
    n = emph_frames.shape[-1]
    y = emph_frames * np.hamming(n)
    r = autocorrelate(y, max_lag=order)
    _, k, _ = levinson(r, order=order)
    energy_db = 10.0 * np.log10(r[..., 0] / n + 1e-12)
    return k, energy_db, zero_crossing_rate(raw_frames, sr=sr)


def analyze(x: np.ndarray, *, sr: float = ANALYSIS_RATE, frame_length: float = FRAME_LENGTH,
            hop_length: float = HOP_LENGTH, order: int = ORDER,
            preemph: float = PREEMPHASIS) -> Features:
    """Frame, pre-emphasise, window and LP-analyse ``x (n,)`` sampled at ``sr`` Hz.

    Frames are centred: frame i covers ``[i·hop - frame_length/2, i·hop + frame_length/2)`` with
    zeros before the start and after the end, so there are ``ceil(n / hop)`` frames. ``x`` may be
    float32: it is converted block by block (``BLOCK`` frames), so the memory beyond ``x`` and the
    features does not grow with its length.
    """
    x = np.asarray(x)
    if x.dtype.kind != "f":
        x = x.astype(np.float64)
    n_frame = int(round(frame_length * sr))
    n_hop = int(round(hop_length * sr))
    n_out = -(-len(x) // n_hop)
    half = n_frame // 2
    empty = np.zeros((0, n_frame))
    parts = [analyze_frames(empty, empty, sr=sr, order=order)]
    for i in range(0, n_out, BLOCK):
        m = min(BLOCK, n_out - i)
        # padded signal (half zeros, x, zeros) under this block's frames, and the sample before them
        lo = i * n_hop - half
        seg = _window(x, lo - 1, lo + (m - 1) * n_hop + n_frame)
        raw = seg[1:]
        emph = preemphasis(raw, coef=preemph, zi=seg[0])
        raw_f = frame(raw, frame_length=n_frame, hop_length=n_hop)[:m]
        emph_f = frame(emph, frame_length=n_frame, hop_length=n_hop)[:m]
        parts.append(analyze_frames(raw_f, emph_f, sr=sr, order=order))
    k, e, z = (np.concatenate([p[j] for p in parts]) for j in range(3))
    return Features(k=k, energy_db=e, zcr=z, hop=n_hop / sr, t0=0.0)


def _window(x: np.ndarray, start: int, stop: int) -> np.ndarray:
    """``x[start:stop]`` as float64, with zeros where the range leaves ``x``."""
    out = np.zeros(max(0, stop - start))
    a, b = max(start, 0), min(stop, len(x))
    if b > a:
        out[a - start:b - start] = x[a:b]
    return out
