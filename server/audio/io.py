"""Audio in: decode a file, validate samples, downmix, resample (batch and streaming).

Everything that reaches the analysis is ``(n,)`` mono in [-1, 1] at a known rate. Files are
decoded by ``decode_audio``: the header is checked against the limits (rate, channels, declared
length against ``max_audio_seconds()`` and, for WAV, the bytes present) before anything is
allocated, then the samples stream through in blocks, downmixed and resampled on the way, so an
upload costs about its duration at the output rate in memory, not its size (``read_audio`` keeps
the file's own rate: for tools and tests, not for uploads).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np
import scipy.signal

from ..errors import InputError
from ..settings import MAX_AUDIO_SECONDS, settings

log = logging.getLogger(__name__)

#: Suffixes the decoder accepts (libsndfile formats).
AUDIO_SUFFIXES = (".wav", ".flac", ".ogg")
#: Lowest / highest input sample rate accepted, Hz.
MIN_RATE, MAX_RATE = 4000, 384000
#: Fraction of samples at |x| >= CLIP_LEVEL above which a file is reported as clipped.
CLIP_LEVEL, CLIP_WARN_FRACTION = 0.999, 0.01
#: Longest audio file accepted by default, seconds (``FACECAST_MAX_AUDIO_SECONDS`` overrides).
MAX_SECONDS = MAX_AUDIO_SECONDS
#: Decoded values (frames × channels) per block: bounds the decoder's working memory (2 MiB).
BLOCK_SAMPLES = 1 << 18
#: Largest term of a resampling ratio (the filter has 20 taps per unit of the larger term).
MAX_RATIO_TERM = 1000
#: Output samples ``StreamResampler`` computes at once (bounds its working memory).
STREAM_SLICE = 8192
#: ``StreamResampler`` keeps up to 8 gather plans (outputs × taps per phase) of up to this many
#: elements each (live chunks: 20 ms at 48 kHz is 200 × 97): 16 MB at most.
PLAN_MAX = 1 << 17
#: Largest relative difference between ``Decoded.rate`` and the requested rate (5e-4 at worst).
RATE_TOLERANCE = 1e-3


@dataclass
class Decoded:
    """An audio file decoded to mono.

    Attributes:
        x: ``(n,)`` samples in [-1, 1] at ``rate`` (channels averaged).
        rate: sample rate of ``x``, Hz (the requested rate, or within ``RATE_TOLERANCE`` of it
            when the file's rate has no exact small ratio to it; see ``conversion_ratio``).
        seconds: duration of the file (its frames over its own rate), s.
        source_rate: the file's sample rate, Hz; channels: the file's channel count.
    """

    x: np.ndarray
    rate: float
    seconds: float
    source_rate: int
    channels: int


def max_audio_seconds() -> float:
    """The longest audio accepted, seconds: ``FACECAST_MAX_AUDIO_SECONDS`` (``settings.LocalSettings``)."""
    return settings().max_audio_seconds


def conversion_ratio(sr_in: float, sr_out: float) -> tuple[int, int]:
    """``(up, down)`` for a polyphase conversion from ``sr_in`` to about ``sr_out`` Hz.

    The exact reduced ratio when both terms are at most ``MAX_RATIO_TERM`` (every common rate:
    44100 → 10000 is 100/441); otherwise the closest ratio with terms that small (a rate such as
    383993 Hz would need a 7.7M-tap filter and minutes per second of audio). The output rate
    ``sr_in·up/down`` is then within ``RATE_TOLERANCE`` of ``sr_out``.
    """
    f = Fraction(int(round(sr_out)), int(round(sr_in)))
    if max(f.numerator, f.denominator) > MAX_RATIO_TERM:
        # the best approximation with the smaller term bounded keeps the larger one bounded too
        f = (
            f.limit_denominator(MAX_RATIO_TERM)
            if f < 1
            else 1 / (1 / f).limit_denominator(MAX_RATIO_TERM)
        )
    return f.numerator, f.denominator


class BlockResampler:
    """``scipy.signal.resample_poly`` over a stream of blocks, with bounded memory.

    Output sample j of the whole stream equals ``resample_poly(whole_input, up, down)[j]`` (to
    round-off): each call runs ``resample_poly`` on the new input plus the overlap the filter
    needs, starting at an input index that is a multiple of ``down`` so the phases line up.
    """

    def __init__(self, up: int, down: int) -> None:
        self.up, self.down = int(up), int(down)
        self.half = 10 * max(
            self.up, self.down
        )  # resample_poly's filter half length (upsampled domain)
        self._buf = np.zeros(0)
        self._start = 0  # input index of _buf[0] (a multiple of down)
        self._n_in = 0  # inputs received
        self._n_out = 0  # outputs returned

    def n_out(self, n_in: int) -> int:
        """Length of ``resample_poly`` of ``n_in`` inputs."""
        return -(-n_in * self.up // self.down)

    def push(self, x: np.ndarray) -> np.ndarray:
        """Append input ``(n,)``; return the outputs that are now final, ``(m,) float64``."""
        x = np.asarray(x, dtype=np.float64)
        if self.up == self.down:
            self._n_in += len(x)
            self._n_out += len(x)
            return x
        self._buf = np.concatenate([self._buf, x])
        self._n_in += len(x)
        # output j needs inputs up to floor((j·down + half) / up)
        last = (self._n_in * self.up - 1 - self.half) // self.down
        return self._emit(last + 1)

    def flush(self) -> np.ndarray:
        """The remaining outputs (the stream is over; zeros follow it, as in ``resample_poly``)."""
        if self.up == self.down:
            return np.zeros(0)
        return self._emit(self.n_out(self._n_in))

    def _emit(self, end: int) -> np.ndarray:
        if end <= self._n_out:
            return np.zeros(0)
        y = scipy.signal.resample_poly(self._buf, self.up, self.down)
        first = self._start * self.up // self.down  # output index of y[0]
        out = y[self._n_out - first : end - first]
        self._n_out = end
        # keep the inputs from the first one output n_out needs, rounded down to a multiple of down
        need = max(0, -(-(self._n_out * self.down - self.half) // self.up))
        start = need // self.down * self.down
        if start > self._start:
            self._buf = self._buf[start - self._start :]
            self._start = start
        return out


def _where_ok(path: str | Path) -> tuple[Path, str]:
    path = Path(path)
    where = str(path)
    if not path.is_file():
        raise InputError("no such audio file", where=where)
    if path.suffix.lower() not in AUDIO_SUFFIXES:
        raise InputError(
            f"unsupported audio type {path.suffix or '(none)'!r}; use {', '.join(AUDIO_SUFFIXES)}",
            where=where,
        )
    return path, where


def _libsndfile_says(e: Exception) -> str:
    """libsndfile's message without the file path soundfile prefixes it with."""
    return str(getattr(e, "error_string", None) or e).strip()


def _wav_shortfall(path: Path) -> tuple[int, int] | None:
    """``(declared, present)`` data bytes of a RIFF/WAVE file whose data chunk is cut short
    (libsndfile silently reads what is there); None when complete or not a plain WAV."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(12)
        if len(head) < 12 or head[:4] != b"RIFF" or head[8:12] != b"WAVE":
            return None
        pos = 12
        for _ in range(64):  # chunks before the data chunk (fmt, fact, LIST, ...)
            fh.seek(pos)
            chunk = fh.read(8)
            if len(chunk) < 8:
                return None
            n = int.from_bytes(chunk[4:], "little")
            if chunk[:4] == b"data":
                present = size - pos - 8
                if n in (0, 0xFFFFFFFF) or n <= present:  # 0 / -1: length not known by the writer
                    return None
                return n, present
            pos += 8 + n + (n & 1)
    return None


def _open(path: Path, where: str, max_seconds: float):
    """Open ``path`` with libsndfile and check what its header declares before decoding anything.

    Returns the open ``soundfile.SoundFile``. Raises InputError for an undecodable header, no
    channels, a rate outside ``MIN_RATE``-``MAX_RATE``, a declared length over ``max_seconds``
    (or more samples than ``max_seconds`` at ``MAX_RATE``) or a truncated WAV data chunk.
    """
    import soundfile as sf

    try:
        f = sf.SoundFile(str(path))
    except Exception as e:  # noqa: BLE001 - libsndfile and soundfile report bad headers many ways
        raise InputError(
            f"cannot decode audio ({_libsndfile_says(e)}); is it a valid WAV/FLAC/OGG file?",
            where=where,
        ) from None
    try:
        rate, channels, frames = int(f.samplerate), int(f.channels), int(f.frames)
        if channels < 1:
            raise InputError(
                "the file declares no audio channels; is it a valid WAV/FLAC/OGG file?", where=where
            )
        if not (MIN_RATE <= rate <= MAX_RATE):
            raise InputError(
                f"sample rate {rate} Hz is outside {MIN_RATE}-{MAX_RATE} Hz; "
                "resample the file to a common rate (16000, 44100, 48000 Hz)",
                where=where,
            )
        if frames >= 2**62:
            raise InputError(
                "the file's header does not say how many samples it holds; re-encode it "
                "(e.g. 'sox in.flac out.flac') so the length is written",
                where=where,
            )
        seconds = frames / rate
        if seconds > max_seconds:
            raise InputError(
                f"the audio lasts {seconds:.0f} s ({frames} samples at {rate} Hz, as its "
                f"header declares), over the limit of {max_seconds:.0f} s; send a shorter "
                "file (split it)",
                where=where,
            )
        if frames * channels > max_seconds * MAX_RATE:
            raise InputError(
                f"{channels} channels × {frames} samples is over the limit of "
                f"{max_seconds * MAX_RATE:.0f} samples; send fewer channels "
                "(a mono mix)",
                where=where,
            )
        cut = _wav_shortfall(path)
        if cut is not None:
            per_second = rate * channels * _bytes_per_sample(f.subtype)
            raise InputError(
                f"the file is truncated: its header declares {cut[0] / per_second:.2f} s "
                f"of audio, it holds {cut[1] / per_second:.2f} s; export or send the "
                "whole file again",
                where=where,
            )
    except BaseException:
        f.close()
        raise
    return f


def _bytes_per_sample(subtype: str) -> int:
    return {
        "PCM_S8": 1,
        "PCM_U8": 1,
        "PCM_16": 2,
        "PCM_24": 3,
        "PCM_32": 4,
        "FLOAT": 4,
        "DOUBLE": 8,
        "ULAW": 1,
        "ALAW": 1,
    }.get(subtype, 2)


def _blocks(f, where: str):
    """Yield the open file's samples as mono ``(m,) float64`` blocks (at most ``BLOCK_SAMPLES``
    decoded values each); InputError for non-finite samples or a stream that ends early."""
    frames, channels = int(f.frames), int(f.channels)
    step = max(1, BLOCK_SAMPLES // channels)
    done = 0
    while done < frames:
        try:
            block = f.read(min(step, frames - done), dtype="float64", always_2d=True)
        except Exception as e:  # noqa: BLE001 - a damaged or lying stream fails part-way
            raise InputError(
                f"cannot decode audio after {done} of {frames} samples "
                f"({_libsndfile_says(e)}); the file is damaged or truncated",
                where=where,
            ) from None
        if len(block) == 0:
            break
        mono = block[:, 0] if channels == 1 else block.mean(axis=1)
        bad = ~np.isfinite(mono)
        if bad.any():
            raise InputError(
                f"NaN/inf samples (first at sample {done + int(np.argmax(bad))})", where=where
            )
        done += len(mono)
        yield mono
    if done < frames:
        raise InputError(
            f"the file is truncated: its header declares {frames} samples, "
            f"{done} decode; export or send the whole file again",
            where=where,
        )


def decode_audio(
    path: str | Path,
    rate: float | None = None,
    *,
    dtype=np.float32,
    max_seconds: float | None = None,
) -> Decoded:
    """Decode ``path`` (WAV/FLAC/OGG, any sample format, rate and channel count) to mono.

    Streams: the file is decoded in blocks of ``BLOCK_SAMPLES`` values, each block is downmixed
    and resampled to ``rate`` (``BlockResampler``) and written into the output, so the peak memory
    is the output ``(n,)`` array of ``dtype`` plus a few blocks, whatever the file's rate,
    channels or format. The header is checked first (``_open``): nothing is allocated for a
    length the limits refuse.

    Args:
        rate: output rate, Hz (None: the file's own); see ``Decoded.rate``.
        dtype: output sample type (float32 halves the memory of float64).
        max_seconds: longest audio accepted (default ``max_audio_seconds()``).
    Raises:
        InputError: missing, unsupported, corrupt, truncated, too long or empty file, an
            unsupported rate, no channels, or non-finite samples.
    """
    path, where = _where_ok(path)
    max_seconds = max_audio_seconds() if max_seconds is None else float(max_seconds)
    with _open(path, where, max_seconds) as f:
        sr, channels, frames = int(f.samplerate), int(f.channels), int(f.frames)
        up, down = (1, 1) if rate is None else conversion_ratio(sr, rate)
        rs = BlockResampler(up, down)
        out = np.empty(rs.n_out(frames), dtype=dtype)
        n = clipped = 0

        def put(y: np.ndarray) -> None:
            nonlocal n
            out[n : n + len(y)] = y
            n += len(y)

        for mono in _blocks(f, where):
            clipped += int(np.count_nonzero(np.abs(mono) >= CLIP_LEVEL))
            put(rs.push(mono))
        put(rs.flush())
    if frames == 0:
        raise InputError("no audio samples", where=where)
    if channels > 1:
        log.info("%s: %d channels, averaged to mono", path.name, channels)
    if clipped > CLIP_WARN_FRACTION * frames:
        log.warning(
            "%s: %.1f%% of samples are clipped; intensity will saturate",
            where,
            100 * clipped / frames,
        )
    np.clip(out, -1.0, 1.0, out=out)
    return Decoded(out[:n], sr * up / down, frames / sr, sr, channels)


def read_audio(path: str | Path, *, max_seconds: float | None = None) -> tuple[np.ndarray, int]:
    """Decode ``path`` (WAV/FLAC/OGG, any sample format and rate) to mono float64 at its own rate.

    Returns:
        ``(x, sr)``: ``x (n,) float64`` in [-1, 1] (channels averaged), ``sr`` in Hz.

    Raises:
        InputError: as ``decode_audio``.
    """
    d = decode_audio(path, None, dtype=np.float64, max_seconds=max_seconds)
    return d.x, d.source_rate


def validate_pcm(
    x: np.ndarray,
    sr: float,
    *,
    where: str = "audio",
    allow_empty: bool = False,
    warn_clipping: bool = True,
) -> np.ndarray:
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
        raise InputError(
            f"expected samples of shape (n,) or (n, channels), got {x.shape}", where=where
        )
    if x.dtype == np.uint8:
        x = (x.astype(np.float64) - 128.0) / 128.0
    elif x.dtype.kind in "iu":
        x = x.astype(np.float64) / float(np.iinfo(x.dtype).max + 1)
    elif x.dtype.kind == "f":
        x = x.astype(np.float64)
    else:
        raise InputError(f"unsupported sample type {x.dtype}", where=where)
    if x.size == 0:
        if not allow_empty:
            raise InputError("no audio samples", where=where)
        return x
    # two reductions decide the common case (finite, below the clip level) without temporaries;
    # NaN or inf makes the min or the max non-finite
    lo, hi = float(x.min()), float(x.max())
    if not (math.isfinite(lo) and math.isfinite(hi)):
        bad = ~np.isfinite(x)
        raise InputError(
            f"{int(bad.sum())} NaN/inf samples (first at sample {int(np.argmax(bad))})", where=where
        )
    if max(-lo, hi) < CLIP_LEVEL:
        return x  # (a copy: made above; within the clip level, so within [-1, 1])
    clipped = np.mean(np.abs(x) >= CLIP_LEVEL) if warn_clipping else 0.0
    if clipped > CLIP_WARN_FRACTION:
        log.warning(
            "%s: %.1f%% of samples are clipped; intensity will saturate", where, 100 * clipped
        )
    return np.minimum(np.maximum(x, -1.0), 1.0)  # np.clip's per-call cost weighs on live chunks


def resample_filter(sr_in: float, sr_out: float) -> tuple[int, int, np.ndarray]:
    """``(up, down, h)``: the anti-aliasing FIR that ``scipy.signal.resample_poly`` uses by default
    (Kaiser window, beta 5, half length 10·max(up, down)), scaled by ``up``."""
    up, down = conversion_ratio(sr_in, sr_out)
    if up == down:
        return 1, 1, np.ones(1)
    m = max(up, down)
    h = scipy.signal.firwin(2 * 10 * m + 1, 1.0 / m, window=("kaiser", 5.0)) * up
    return up, down, h


def resample(x: np.ndarray, sr_in: float, sr_out: float) -> np.ndarray:
    """Resample ``x (n,)`` from ``sr_in`` to ``sr_out`` Hz with ``scipy.signal.resample_poly``.

    Returns ``(ceil(n·up/down),) float64`` with ``(up, down) = conversion_ratio(sr_in, sr_out)``
    (exactly ``sr_out/sr_in`` for every common rate; within ``RATE_TOLERANCE`` of it otherwise).
    """
    up, down = conversion_ratio(sr_in, sr_out)
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
        self.half = (len(self.h) - 1) // 2  # in the upsampled domain
        self.sr_in, self.sr_out = float(sr_in), float(sr_out)
        self.delay = 0.0 if self.identity else self.half / self.up / self.sr_in
        # Input history; index 0 of ``_buf`` is input sample ``_offset``. The stream is preceded by
        # zeros (as resample_poly pads).
        n_taps = len(self.h)
        self._m = np.arange(-(-n_taps // self.up))
        ks = np.arange(self.up)[:, None] + self.up * self._m[None, :]  # (up, M) tap ids
        self._taps = np.where(ks < n_taps, self.h[np.minimum(ks, n_taps - 1)], 0.0)
        pad = 0 if self.identity else len(self._m) + 2
        self._buf = np.zeros(pad)
        self._offset = -pad
        self._n_out = 0  # next output index
        self._plans: dict[tuple[int, int, int], tuple[np.ndarray, np.ndarray]] = {}

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
        last_j = (
            n_in_end * self.up - 1 - self.half
        ) // self.down  # largest j with all inputs known
        if last_j < self._n_out:
            return np.zeros(0)
        # in slices: _compute's gathers are (outputs × taps per phase); a 1 Mi-sample chunk at once
        # swung the memory by 600 MB
        if last_j + 1 - self._n_out <= STREAM_SLICE:  # one slice: a live chunk
            out = self._compute(np.arange(self._n_out, last_j + 1))
        else:
            out = np.concatenate(
                [
                    self._compute(np.arange(j, min(j + STREAM_SLICE, last_j + 1)))
                    for j in range(self._n_out, last_j + 1, STREAM_SLICE)
                ]
            )
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
        # js is a run j0..j0+n-1; its taps and gather indices depend only on key below, which a
        # stream of equal chunks repeats: those of a few small runs are kept
        p0 = int(js[0]) * self.down + self.half
        key = (p0 % self.up, len(js), p0 // self.up - self._offset)
        plan = self._plans.get(key)
        if plan is None:
            p = js * self.down + self.half
            idx = (p // self.up)[:, None] - self._m[None, :] - self._offset
            plan = (self._taps[p % self.up], idx)
            if idx.size <= PLAN_MAX:
                if len(self._plans) >= 8:
                    self._plans.clear()
                self._plans[key] = plan
        return np.einsum("nm,nm->n", plan[0], self._buf[plan[1]])
