"""Linear-predictive analysis of speech frames (Kshirsagar & Magnenat-Thalmann, ICME 2000).

Pure functions over NumPy arrays; the sample rate, frame length and hop are explicit. Time is the
last axis. Polynomial convention: ``A(z) = 1 + a_1 z^-1 + ... + a_p z^-p`` (as ``scipy.signal.lfilter``
takes it), so an AR process is ``x = lfilter([1], a, e)``; reflection coefficients ``k_i`` are the
last coefficient of the order-i predictor in the Levinson–Durbin recursion (``k_1 = -R1/R0``).
"""

from __future__ import annotations

import functools
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

    ``n_frames = 1 + (n - frame_length) // hop_length`` (0 when ``n < frame_length``); up to
    ``SMALL`` frames come as a copy.
    """
    x = np.ascontiguousarray(x)
    n = 0 if len(x) < frame_length else 1 + (len(x) - frame_length) // hop_length
    if n == 0:
        return np.zeros((0, frame_length), dtype=x.dtype)
    if n <= SMALL:  # a copy by index: as_strided's own cost dominates on the live path's chunks
        frames: np.ndarray = x[_frame_index(n, frame_length, hop_length)]
        return frames
    return np.lib.stride_tricks.as_strided(
        x,
        shape=(n, frame_length),
        strides=(x.strides[0] * hop_length, x.strides[0]),
        writeable=False,
    )


@functools.lru_cache(maxsize=64)
def _frame_index(n: int, frame_length: int, hop_length: int) -> np.ndarray:
    """``(n, frame_length)`` sample indices of ``n`` frames (``frame``'s copy by index)."""
    idx = np.arange(n)[:, None] * hop_length + np.arange(frame_length)
    idx.flags.writeable = False
    return idx


def autocorrelate(frames: np.ndarray, *, max_lag: int) -> np.ndarray:
    """Biased autocorrelation ``R[..., l] = sum_n y[n]·y[n+l]`` for lags ``0..max_lag``.

    Args:
        frames: ``(..., n)`` windowed frames.
    Returns:
        ``(..., max_lag + 1) float64``.
    """
    y = np.asarray(frames, dtype=np.float64)
    n = y.shape[-1]
    return np.stack(
        [
            np.einsum("...i,...i->...", y[..., : n - lag], y[..., lag:])
            for lag in range(max_lag + 1)
        ],
        axis=-1,
    )


#: Up to this many frames, ``levinson`` and ``cepstrum`` run a scalar loop per frame: NumPy's
#: per-call overhead dominates on the live path's one or two frames per chunk (10x faster there).
SMALL = 8
#: ``levinson`` treats frames with ``R0`` at or below this as digital silence (mean power near
#: -220 dB, far below any recording's noise floor): on the decaying tails of filters, whose
#: samples reach the denormal range, the prediction error would underflow to 0 and the
#: recursion give NaN.
SILENT_R0 = 1e-20


def levinson(r: np.ndarray, *, order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Levinson–Durbin recursion on autocorrelations, vectorised over leading axes.

    Args:
        r: ``(..., >= order+1)`` autocorrelation lags ``R0..Rp``.
        order: predictor order p > 0.
    Returns:
        ``(a, k, err)``: ``a (..., p+1)`` predictor polynomial with ``a[..., 0] = 1``;
        ``k (..., p)`` reflection coefficients in (-1, 1); ``err (...,)`` final prediction-error
        power. Frames with ``R0 <= SILENT_R0`` (digital silence) give ``a = [1, 0, ...]``,
        ``k = 0``.
    """
    r = np.asarray(r, dtype=np.float64)
    lead = r.shape[:-1]
    r2 = r.reshape(-1, r.shape[-1])
    a, k, err = (_levinson_small if len(r2) <= SMALL else _levinson_rows)(r2, order)
    return a.reshape(lead + (order + 1,)), k.reshape(lead + (order,)), err.reshape(lead)


def _levinson_rows(r: np.ndarray, order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``levinson`` of ``r (T, >= order+1)``, vectorised over the rows."""
    T = len(r)
    a = np.zeros((T, order + 1))
    a[:, 0] = 1.0
    k = np.zeros((T, order))
    err = r[:, 0].copy()
    silent = ~(err > SILENT_R0)
    err[silent] = np.inf  # digital silence: every k is 0
    for i in range(1, order + 1):
        acc = r[:, i] + np.einsum("ij,ij->i", a[:, 1:i], r[:, i - 1 : 0 : -1])
        # the clip guards round-off on ill-conditioned frames, and keeps err > 0
        ki = np.minimum(np.maximum(-acc / err, -0.999999), 0.999999)
        a[:, 1:i] += ki[:, None] * a[:, i - 1 : 0 : -1].copy()
        a[:, i] = ki
        k[:, i - 1] = ki
        err *= 1.0 - ki * ki
    err[silent] = 0.0
    return a, k, err


def _levinson_small(r: np.ndarray, order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``levinson`` of a few rows ``r (T, >= order+1)``, one scalar loop per row."""
    T = len(r)
    A, K, E = np.zeros((T, order + 1)), np.zeros((T, order)), np.zeros(T)
    A[:, 0] = 1.0
    for t, row in enumerate(r.tolist()):
        err = row[0]
        if not err > SILENT_R0:
            continue
        a, ks = [1.0] + [0.0] * order, [0.0] * order
        for i in range(1, order + 1):
            acc = row[i]
            for j in range(1, i):
                acc += a[j] * row[i - j]
            ki = -acc / err
            if ki < -0.999999:  # (not min/max: their call cost, in this innermost loop)
                ki = -0.999999
            elif ki > 0.999999:
                ki = 0.999999
            # a[j] += ki·a[i-j] for all j at once: pairs (j, i-j) updated together, no copy
            for j in range(1, (i + 1) // 2):
                aj, aij = a[j], a[i - j]
                a[j], a[i - j] = aj + ki * aij, aij + ki * aj
            if not i & 1:
                a[i // 2] += ki * a[i // 2]
            a[i] = ks[i - 1] = ki
            err *= 1.0 - ki * ki
        A[t], K[t], E[t] = a, ks, err
    return A, K, E


def zero_crossing_rate(frames: np.ndarray, *, sr: float) -> np.ndarray:
    """Zero crossings per 10 ms of each frame ``(..., n)`` (frame mean removed first).

    Returns ``(...,) float64``; the source's reference means are 49 (unvoiced) and 14 (voiced).
    """
    y = np.asarray(frames, dtype=np.float64)
    y = y - y.sum(axis=-1, keepdims=True) / y.shape[-1]
    s = np.signbit(y)
    crossings = (s[..., 1:] != s[..., :-1]).sum(axis=-1)  # count_nonzero(axis=) costs more
    return crossings * (0.010 * sr) / y.shape[-1]


@dataclass
class Features:
    """Per-frame LPC features. Frame i is centred on ``t0 + i·hop`` seconds.

    Attributes:
        k: ``(T, 12)`` reflection coefficients.
        energy_db: ``(T,)`` 10·log10 of the mean power R0/N of the windowed, pre-emphasised frame.
        zcr: ``(T,)`` zero crossings per 10 ms.
        shape: ``(T, N_BANDS)`` spectral shape: log power in mel bands of the windowed,
            pre-emphasised frame, minus the frame's mean over the bands (level-independent).
        cep: ``(T, 12)`` LPC cepstrum (``cepstrum``).
        hop: seconds between frames; t0: time of frame 0, seconds.
    """

    k: np.ndarray
    energy_db: np.ndarray
    zcr: np.ndarray
    shape: np.ndarray | None = None
    cep: np.ndarray | None = None
    hop: float = HOP_LENGTH
    t0: float = 0.0

    def __len__(self) -> int:
        return len(self.energy_db)

    @property
    def times(self) -> np.ndarray:
        """``(T,)`` frame centre times, seconds."""
        return self.t0 + self.hop * np.arange(len(self))


#: Mel bands of the spectral-shape feature (100 Hz to 4.8 kHz at the analysis rate).
N_BANDS = 16


@functools.lru_cache(maxsize=8)
def _mel_bands(n_fft: int, sr: float, n_bands: int = N_BANDS) -> np.ndarray:
    """``(n_fft//2 + 1, n_bands)`` triangular mel filters, 100 Hz .. 0.48·sr."""
    mel = lambda f: 2595.0 * np.log10(1.0 + f / 700.0)  # noqa: E731
    edges = 700.0 * (10 ** (np.linspace(mel(100.0), mel(0.48 * sr), n_bands + 2) / 2595.0) - 1)
    f = np.linspace(0, sr / 2, n_fft // 2 + 1)[:, None]
    lo, c, hi = edges[None, :-2], edges[None, 1:-1], edges[None, 2:]
    return np.maximum(0.0, np.minimum((f - lo) / (c - lo), (hi - f) / (hi - c)))


def _shape_of_power(p: np.ndarray, n_fft: int, sr: float) -> np.ndarray:
    """``(T, N_BANDS)`` log mel-band power of power spectra ``p (T, n_fft//2 + 1)``, each row
    minus its mean (the spectrum's shape, independent of the level)."""
    b = np.log(p @ _mel_bands(n_fft, float(sr)) + 1e-10)
    return b - b.sum(axis=-1, keepdims=True) / b.shape[-1]  # = mean, without its per-call cost


@functools.lru_cache(maxsize=4)
def _cep_weights(n: int) -> tuple[tuple[float, ...], ...]:
    """``w[m][i] = i/m`` for 0 <= i < m <= n (the scalar ``cepstrum``'s weights, made once)."""
    return tuple(tuple(i / m for i in range(m)) if m else () for m in range(n + 1))


def cepstrum(a: np.ndarray, n: int = ORDER) -> np.ndarray:
    """``(T, n)`` LPC cepstrum c_1..c_n (n <= p) of predictors ``a (T, p+1)`` (``a[:, 0] = 1``):
    the cepstrum of ``1 / A(z)``, by ``c_m = -a_m - sum_{j<m} (j/m) c_j a_{m-j}``."""
    T = a.shape[0]
    if T <= SMALL:  # scalar loops: the live path's few frames
        out = np.zeros((T, n))
        ws = _cep_weights(n)
        for t, row in enumerate(a.tolist()):
            cs = [0.0] * (n + 1)
            for m in range(1, n + 1):
                acc, wm = row[m], ws[m]
                for i in range(1, m):
                    acc += wm[i] * cs[i] * row[m - i]
                cs[m] = -acc
            out[t] = cs[1:]
        return out
    c = np.zeros((T, n + 1))
    j = np.arange(n + 1, dtype=np.float64)
    for m in range(1, n + 1):
        c[:, m] = -a[:, m] - (c[:, 1:m] * a[:, m - 1 : 0 : -1]) @ (j[1:m] / m)
    return c[:, 1:]


@functools.lru_cache(maxsize=8)
def _autocorr_basis(n_fft: int, order: int) -> np.ndarray:
    """``(n_fft//2 + 1, order + 1)``: a power spectrum ``p`` of ``n_fft`` points times this is
    ``irfft(p, n_fft)[:order + 1]`` (the autocorrelation's first lags), one small matrix product
    instead of a whole inverse FFT per frame (read-only, made once)."""
    m = np.arange(n_fft // 2 + 1)[:, None]
    w = np.where((m == 0) | (2 * m == n_fft), 1.0, 2.0) / n_fft
    basis = w * np.cos(2 * np.pi * m * np.arange(order + 1)[None, :] / n_fft)
    basis.flags.writeable = False
    return basis


@functools.lru_cache(maxsize=8)
def _hamming(n: int) -> np.ndarray:
    """``np.hamming(n)``, made once per length."""
    w = np.hamming(n)
    w.flags.writeable = False
    return w


def analyze_frames(
    raw_frames: np.ndarray,
    emph_frames: np.ndarray,
    *,
    sr: float = ANALYSIS_RATE,
    order: int = ORDER,
) -> tuple[np.ndarray, ...]:
    """LPC features of already-cut frames. The autocorrelation comes from the frame's power
    spectrum (one FFT, zero-padded past ``N + order`` so no lag wraps; its first lags by
    ``_autocorr_basis``), which also gives the spectral shape.

    Args:
        raw_frames: ``(T, N)`` frames of the signal (for the zero-crossing rate).
        emph_frames: ``(T, N)`` the same frames of the pre-emphasised signal.
    Returns:
        ``(k (T, order), energy_db (T,), zcr (T,), shape (T, N_BANDS), cep (T, order))``.
    """
    n = emph_frames.shape[-1]
    y = emph_frames * _hamming(n)
    n_fft = 1 << (n - 1).bit_length()
    n_r = n_fft if n_fft >= n + order else 2 * n_fft
    spec = np.fft.rfft(y, n=n_r)
    p = spec.real**2 + spec.imag**2
    r = p @ _autocorr_basis(n_r, order)
    a, k, _ = levinson(r, order=order)
    energy_db = 10.0 * np.log10(np.maximum(r[..., 0], 0.0) / n + 1e-12)
    shape = _shape_of_power(p if n_r == n_fft else p[..., ::2], n_fft, sr)
    return k, energy_db, zero_crossing_rate(raw_frames, sr=sr), shape, cepstrum(a, order)


def analyze(
    x: np.ndarray,
    *,
    sr: float = ANALYSIS_RATE,
    frame_length: float = FRAME_LENGTH,
    hop_length: float = HOP_LENGTH,
    order: int = ORDER,
    preemph: float = PREEMPHASIS,
) -> Features:
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
    k, e, z, sh, c = (np.concatenate([p[j] for p in parts]) for j in range(5))
    return Features(k=k, energy_db=e, zcr=z, shape=sh, cep=c, hop=n_hop / sr, t0=0.0)


def _window(x: np.ndarray, start: int, stop: int) -> np.ndarray:
    """``x[start:stop]`` as float64, with zeros where the range leaves ``x``."""
    out = np.zeros(max(0, stop - start))
    a, b = max(start, 0), min(stop, len(x))
    if b > a:
        out[a - start : b - start] = x[a:b]
    return out
