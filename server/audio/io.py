"""Audio in: decode a file, validate samples, downmix, resample (batch and streaming).

Everything that reaches the analysis is ``(n,) float64`` mono in [-1, 1] at a known rate.
"""
from __future__ import annotations

import logging
from fractions import Fraction
from pathlib import Path

import numpy as np
import scipy.signal

from ..errors import InputError

log = logging.getLogger(__name__)

#: Suffixes the decoder accepts (libsndfile formats).
AUDIO_SUFFIXES = (".wav", ".flac", ".ogg")
#: Lowest / highest input sample rate accepted, Hz.
MIN_RATE, MAX_RATE = 4000, 384000
#: Fraction of samples at |x| >= CLIP_LEVEL above which a file is reported as clipped.
CLIP_LEVEL, CLIP_WARN_FRACTION = 0.999, 0.01


def read_audio(path: str | Path) -> tuple[np.ndarray, int]:
    """Decode ``path`` (WAV/FLAC/OGG, any sample format and rate) to mono float64.

    Returns:
        ``(x, sr)``: ``x (n,) float64`` in [-1, 1] (channels averaged), ``sr`` in Hz.

    Raises:
        InputError: missing, unsupported, corrupt or empty file, or non-finite samples.
    """
    import soundfile as sf

    path = Path(path)
    where = str(path)
    if not path.is_file():
        raise InputError("no such audio file", where=where)
    if path.suffix.lower() not in AUDIO_SUFFIXES:
        raise InputError(f"unsupported audio type {path.suffix or '(none)'!r}; use "
                         f"{', '.join(AUDIO_SUFFIXES)}", where=where)
    try:
        data, sr = sf.read(str(path), dtype="float64", always_2d=True)
    except (RuntimeError, sf.LibsndfileError, ValueError) as e:  # libsndfile reports corrupt data so
        raise InputError(f"cannot decode audio ({e}); is it a valid WAV/FLAC/OGG file?",
                         where=where) from None
    if data.shape[1] > 1:
        log.info("%s: %d channels, averaged to mono", path.name, data.shape[1])
    x = data.mean(axis=1)
    return validate_pcm(x, sr, where=where), int(sr)


def validate_pcm(x: np.ndarray, sr: float, *, where: str = "audio",
                 allow_empty: bool = False, warn_clipping: bool = True) -> np.ndarray:
    """Check samples and rate; return ``(n,) float64`` mono.

    Accepts ``(n,)`` or ``(n, channels)`` arrays (channels averaged). Integer arrays are scaled
    from their full range (uint8 is offset binary). Raises InputError naming ``where`` for an
    unsupported rate, an empty signal or NaN/inf samples; warns on clipping (``warn_clipping``).
    """
    if not (MIN_RATE <= float(sr) <= MAX_RATE):
        raise InputError(f"sample rate {sr} Hz is outside {MIN_RATE}-{MAX_RATE} Hz", where=where)
    x = np.asarray(x)
    if x.ndim == 2:
        x = x.mean(axis=1) if x.dtype.kind == "f" else x.astype(np.float64).mean(axis=1)
    elif x.ndim != 1:
        raise InputError(f"expected samples of shape (n,) or (n, channels), got {x.shape}",
                         where=where)
    if x.dtype == np.uint8:
        x = (x.astype(np.float64) - 128.0) / 128.0
    elif x.dtype.kind in "iu":
        x = x.astype(np.float64) / float(np.iinfo(x.dtype).max + 1)
    elif x.dtype.kind == "f":
        x = x.astype(np.float64)
    else:
        raise InputError(f"unsupported sample type {x.dtype}", where=where)
    if x.size == 0 and not allow_empty:
        raise InputError("no audio samples", where=where)
    bad = ~np.isfinite(x)
    if bad.any():
        raise InputError(f"{int(bad.sum())} NaN/inf samples (first at sample {int(np.argmax(bad))})",
                         where=where)
    clipped = np.mean(np.abs(x) >= CLIP_LEVEL) if x.size else 0.0
    if clipped > CLIP_WARN_FRACTION and warn_clipping:
        log.warning("%s: %.1f%% of samples are clipped; intensity will saturate", where,
                    100 * clipped)
    return np.clip(x, -1.0, 1.0)


def _ratio(sr_in: float, sr_out: float) -> tuple[int, int]:
    f = Fraction(int(round(sr_out)), int(round(sr_in)))
    return f.numerator, f.denominator


def resample_filter(sr_in: float, sr_out: float) -> tuple[int, int, np.ndarray]:
    """``(up, down, h)``: the anti-aliasing FIR that ``scipy.signal.resample_poly`` uses by default
    (Kaiser window, beta 5, half length 10·max(up, down)), scaled by ``up``."""
    up, down = _ratio(sr_in, sr_out)
    if up == down:
        return 1, 1, np.ones(1)
    m = max(up, down)
    h = scipy.signal.firwin(2 * 10 * m + 1, 1.0 / m, window=("kaiser", 5.0)) * up
    return up, down, h


def resample(x: np.ndarray, sr_in: float, sr_out: float) -> np.ndarray:
    """Resample ``x (n,)`` from ``sr_in`` to ``sr_out`` Hz with ``scipy.signal.resample_poly``.

    Returns ``(ceil(n·sr_out/sr_in),) float64``.
    """
    up, down = _ratio(sr_in, sr_out)
    if up == down:
        return np.asarray(x, dtype=np.float64)
    return scipy.signal.resample_poly(np.asarray(x, dtype=np.float64), up, down)


class StreamResampler:
    """Streaming version of ``resample``: feed chunks, get output samples as soon as they are final.

    Output sample j of the whole stream equals ``resample(whole_input)[j]`` (away from the end of
    the stream). Algorithmic delay: ``delay`` input seconds (half the FIR length).
    """

    def __init__(self, sr_in: float, sr_out: float) -> None:
        self.up, self.down, self.h = resample_filter(sr_in, sr_out)
        self.identity = self.up == self.down
        self.half = (len(self.h) - 1) // 2           # in the upsampled domain
        self.sr_in, self.sr_out = float(sr_in), float(sr_out)
        self.delay = 0.0 if self.identity else self.half / self.up / self.sr_in
        # Input history; index 0 of ``_buf`` is input sample ``_offset``. The stream is preceded by
        # zeros (as resample_poly pads).
        n_taps = len(self.h)
        self._m = np.arange(-(-n_taps // self.up))
        ks = np.arange(self.up)[:, None] + self.up * self._m[None, :]      # (up, M) tap ids
        self._taps = np.where(ks < n_taps, self.h[np.minimum(ks, n_taps - 1)], 0.0)
        pad = 0 if self.identity else len(self._m) + 2
        self._buf = np.zeros(pad)
        self._offset = -pad
        self._n_out = 0  # next output index

    def push(self, x: np.ndarray) -> np.ndarray:
        """Append input ``(n,)``; return the newly final output samples."""
        x = np.asarray(x, dtype=np.float64)
        if self.identity:
            self._n_out += len(x)
            return x.copy()
        self._buf = np.concatenate([self._buf, x])
        n_in_end = self._offset + len(self._buf)  # input samples known: [.., n_in_end)
        # output j sits at upsampled position p = j·down; it needs upsampled samples up to p + half,
        # i.e. input samples up to floor((p + half)/up).
        last_j = (n_in_end * self.up - 1 - self.half) // self.down  # largest j with all inputs known
        if last_j < self._n_out:
            return np.zeros(0)
        js = np.arange(self._n_out, last_j + 1)
        out = self._compute(js)
        self._n_out = last_j + 1
        # keep the history the next output needs
        first_needed = (self._n_out * self.down + self.half) // self.up - len(self._m) - 1
        drop = max(0, first_needed - self._offset)
        if drop:
            self._buf = self._buf[drop:]
            self._offset += drop
        return out

    def _compute(self, js: np.ndarray) -> np.ndarray:
        # y[j] = sum_k h[k] · u[p - k] with p = j·down + half and u the upsampled input (x[i] at
        # position i·up): only taps k = (p mod up) + m·up meet a nonzero sample, x[p//up - m].
        p = js * self.down + self.half
        idx = (p // self.up)[:, None] - self._m[None, :] - self._offset
        return np.einsum("nm,nm->n", self._taps[p % self.up], self._buf[idx])
