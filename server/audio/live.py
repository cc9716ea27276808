"""Live lip-sync: PCM chunks in, face states stamped with the audio's media time out.

``AudioLiveDriver`` runs the batch pipeline incrementally (streaming resampler, frame-by-frame LPC
analysis, the same labelling and coarticulation functions over a sliding window), so with the same
calibration its output equals ``pipeline.lipsync(..., lookahead=driver.coart_lookahead)``.

Algorithmic latency (audio that must arrive after media time t before the state at t is final):
resampler delay (~1 ms) + half an analysis frame (10 ms) + the frame network's look-ahead context
(``FrameNet.future`` frames) + half the median filter + the coarticulation look-ahead;
``lookahead`` is the budget for the sum (default 60 ms).
"""

from __future__ import annotations

import logging
import math

import numpy as np

from ..errors import InputError
from ..state import FaceState
from .classify import FrameNet, default_frame_net, frame_features, stack_rows
from .io import CLIP_LEVEL, MAX_RATE, MIN_RATE, StreamResampler, validate_pcm
from .lpc import (
    ANALYSIS_RATE,
    FRAME_LENGTH,
    HOP_LENGTH,
    ORDER,
    PREEMPHASIS,
    analyze_frames,
    frame,
    preemphasis,
)
from .pipeline import classes_to_visemes
from .visemes import (
    MIN_SILENCE_DB,
    NOISE_MARGIN_DB,
    SILENCE_RANGE_DB,
    Calibration,
    Params,
    coarticulate,
    median_filter_proba,
    viseme_table,
)

log = logging.getLogger(__name__)

#: A gap in the media time larger than this restarts the analysis instead of filling with silence.
MAX_GAP = 2.0


def _fap1(tr, i: int) -> tuple[int, int, int]:
    return int(tr.select1[i]), int(tr.select2[i]), int(round(63 * float(tr.blend[i])))


class RunningCalibration:
    """Continuous energy calibration for live streams (the source calibrated once per user).

    ``visemes.calibrate`` over the frames so far: noise floor = 5th percentile, maximum = 99th
    percentile of every frame energy received (a histogram of ``step_db`` bins over
    ``range_db``, O(1) memory), thresholds as ``calibrate``; so as the stream goes on the live
    levels become the batch levels of the same audio. Before the first loud frame the maximum is
    the noise floor's neighbourhood and everything is silence. Speakers held out
    (bench/lipsync/folds.py): live 0.517 / 0.360 with the former peak follower (+6 dB headroom,
    2 dB/s decay), 0.523 / 0.370 with the percentiles (batch 0.550 / 0.378).

    Each percentile is tracked incrementally: its bin and the count of energies up to and
    including that bin move by a few bins per frame (no cumulative sum over the histogram).
    """

    #: Quantiles tracked (noise floor, maximum).
    QUANTILES = (0.05, 0.99)

    def __init__(
        self, range_db: tuple[float, float] = (-140.0, 20.0), step_db: float = 0.25
    ) -> None:
        self.lo, self.step = float(range_db[0]), float(step_db)
        #: energies counted per bin (Python ints: updated frame by frame)
        self.hist = [0] * (int(round((range_db[1] - range_db[0]) / step_db)) + 1)
        self.n = 0
        self._bin = [0, 0]  # each quantile's bin: the first whose cumulative count reaches it
        self._cum = [0, 0]  # cumulative count up to and including that bin

    def levels(self) -> tuple[float, float]:
        """``(noise, top)`` dB: the 5th and 99th percentiles of the energies so far."""
        noise, top = self._bin
        return self.lo + self.step * (noise + 0.5), self.lo + self.step * (top + 0.5)

    def _add(self, b: int) -> None:
        """Count one energy in bin ``b``; move each quantile's bin to the first whose cumulative
        count reaches ``q·n`` (``np.searchsorted(np.cumsum(hist), q·n)``)."""
        counts = self.hist
        counts[b] += 1
        self.n += 1
        for j, q in enumerate(self.QUANTILES):
            target = q * self.n
            i, c = self._bin[j], self._cum[j]
            if b <= i:
                c += 1
            while i > 0 and c - counts[i] >= target:  # the bin below already reaches it
                c -= counts[i]
                i -= 1
            while c < target:
                i += 1
                c += counts[i]
            self._bin[j], self._cum[j] = i, c

    def update(self, energy_db: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Feed frame energies ``(T,)`` dB; return per-frame ``(silence_db, max_db)`` arrays
        (each frame's levels include it and every frame before)."""
        sil = np.empty(len(energy_db))
        mx = np.empty(len(energy_db))
        last = len(self.hist) - 1
        for i, e in enumerate(np.asarray(energy_db, dtype=np.float64).tolist()):
            b = int((e - self.lo) / self.step) if math.isfinite(e) else 0
            self._add(min(max(b, 0), last))
            noise, top = self.levels()
            s = max(noise + NOISE_MARGIN_DB, top - SILENCE_RANGE_DB, MIN_SILENCE_DB)
            sil[i], mx[i] = s, max(top, s + 10.0)
        return sil, mx


class AudioLiveDriver:
    """``LiveDriver`` for PCM audio.

    Args:
        face: the target face (FAPs are in FAPU; kept for the protocol).
        rate: sample rate of the pushed chunks, Hz.
        lookahead: algorithmic latency budget, seconds (see module doc); the part left after the
            fixed delays is the coarticulation look-ahead ``coart_lookahead`` (whole 10 ms frames).
        fps: rate of the emitted face states (at ``t0 + k/fps``).
        calibration: fixed energy levels; None = estimated continuously from the stream.
        fap1: emit the viseme as FAP 1 (``FaceState.viseme``) instead of low-level FAPs.
        text: the transcript of what will be said, known ahead (English): the frames' classes
            follow its phones (``align.TextFollower``, decided as late as the median filter's
            half would be: the latency is unchanged) instead of the median-filtered network
            output. InputError for an empty or overlong text or one without speakable words.

    States carry the coarticulated mouth as low-level FAPs (jaw, inner and outer lips) and
    ``viseme=None``: a decoder adds FAP 1 to the low-level FAPs, so sending both would count the
    mouth twice. With ``fap1=True`` they carry FAP 1 only (top two visemes and their blend; no
    intensity), for viseme-only consumers.
    """

    control_vertices = None

    def __init__(
        self,
        face=None,
        rate: float = 16000,
        lookahead: float = 0.06,
        fps: float = 50.0,
        calibration: Calibration | None = None,
        params: Params | None = None,
        net: FrameNet | None = None,
        fap1: bool = False,
        text: str | None = None,
    ) -> None:
        if not (MIN_RATE <= float(rate) <= MAX_RATE):
            raise InputError(
                f"sample rate {rate} Hz is outside {MIN_RATE}-{MAX_RATE} Hz", where="rate"
            )
        if not (0 < fps <= 1000):
            raise InputError(f"fps must be in (0, 1000], got {fps}", where="fps")
        if lookahead < 0:
            raise InputError(f"lookahead must be >= 0 s, got {lookahead}", where="lookahead")
        self.face = face
        self.table = viseme_table(face)
        self.rate = float(rate)
        self.fps = float(fps)
        self.params = params or Params()
        self.net = net or default_frame_net()
        self.fixed_calibration = calibration
        self.fap1 = fap1
        self.hop = HOP_LENGTH
        self.n_frame = int(round(FRAME_LENGTH * ANALYSIS_RATE))
        self.n_hop = int(round(HOP_LENGTH * ANALYSIS_RATE))
        self.med_half = self.params.median // 2
        self.follower = None
        if text is not None:
            from .align import TextFollower  # align builds on the pipeline, as this module

            self.follower = TextFollower(text, lag=self.med_half, prior=self.net.mean_proba)
        self._future, self._past = self.net.future, self.net.past  # read per chunk
        fixed = (
            StreamResampler(self.rate, ANALYSIS_RATE).delay
            + FRAME_LENGTH / 2
            + (self.med_half + self.net.future) * self.hop
        )
        self.coart_frames = max(0, int(math.floor((lookahead - fixed) / self.hop + 1e-9)))
        self.coart_lookahead = self.coart_frames * self.hop
        #: Audio needed after t before the state at t is final, seconds.
        self.latency = fixed + self.coart_lookahead
        self.lookahead = lookahead
        self.dropped_chunks = 0
        self._warned_clipping = False
        self._reset(None)

    # -- stream state ---------------------------------------------------------------------
    def _reset(self, t0: float | None) -> None:
        self.t0 = t0  # media time of sample 0 of the current stream
        self._n_in = 0  # input samples consumed
        self._rs = StreamResampler(self.rate, ANALYSIS_RATE)
        self._cal = RunningCalibration()
        self._norm = self.net.speaker_norm()
        self._buf = np.zeros(self.n_frame // 2)  # centred frames: half a frame of zeros first
        self._buf_start = -(self.n_frame // 2)  # analysis-rate index of _buf[0]
        self._emph_prev = 0.0
        self._emph = np.zeros(self.n_frame // 2)
        self._n10 = 0  # analysis-rate samples received
        # features of frames [_f0, _f0 + len)
        self._f0 = 0
        self._e = np.zeros(0)
        self._F = np.zeros((0, len(self.net.mean) // len(self.net.offsets)))
        self._p = np.zeros((0, len(self.net.b2)))  # class probabilities of frames [_f0, _n_p)
        self._n_p = 0
        self._c = np.zeros(0, dtype=np.int64)  # text path: decided classes of [_f0, _n_c)
        self._n_c = 0
        self._first: int | None = None  # frame index of the first sound (None: not yet)
        self._sil = np.zeros(0)
        self._max = np.zeros(0)
        self._next_out = 0  # next output state index k (time t0 + k/fps)

    @property
    def _n_feat(self) -> int:
        return self._f0 + len(self._e)

    def push(self, data: np.ndarray, t: float) -> list[FaceState]:
        """Take one chunk of samples ``(n,)`` (or ``(n, channels)``, averaged) starting at media
        time ``t``; return the face states that became final, oldest first.

        A chunk that is late (starts before the end of what was already received) is trimmed or
        dropped; a gap up to ``MAX_GAP`` s is filled with silence, a longer one restarts the
        analysis at ``t``. Raises InputError for NaN/inf samples or a bad shape; the driver
        state is unchanged then and the next chunk is processed normally.
        """
        where = f"audio chunk at t={t:.3f}s" if np.isfinite(t) else "audio chunk"
        if not np.isfinite(t):
            raise InputError("media time is not finite", where="t")
        x = validate_pcm(data, self.rate, where=where, allow_empty=True, warn_clipping=False)
        clipped = np.count_nonzero(np.abs(x) >= CLIP_LEVEL) if not self._warned_clipping else 0
        if clipped > 0.01 * x.size:
            self._warned_clipping = True
            log.warning("%s: the stream is clipping; intensity will saturate", where)
        out: list[FaceState] = []
        if self.t0 is None:
            self._reset(float(t))
        expected = self.t0 + self._n_in / self.rate
        offset = int(round((t - expected) * self.rate))
        if offset < 0:  # late or out-of-order: drop what we already have
            if -offset >= len(x):
                self.dropped_chunks += 1
                log.warning(
                    "%s: dropped, it ends before the %.3f s already received", where, expected
                )
                return out
            log.warning(
                "%s: overlaps %.1f ms already received; trimmed", where, -offset / self.rate * 1e3
            )
            x = x[-offset:]
        elif offset > 0:
            if offset / self.rate > MAX_GAP:
                log.warning("%s: %.2f s gap; restarting the analysis", where, offset / self.rate)
                out = self.flush()
                self._reset(float(t))
            else:
                log.info("%s: %.1f ms gap filled with silence", where, offset / self.rate * 1e3)
                x = np.concatenate([np.zeros(offset), x])
        if len(x):
            self._n_in += len(x)
            self._consume(self._rs.push(x))
        return out + self._emit(final=False)

    def flush(self) -> list[FaceState]:
        """End of stream: pad with silence and return every remaining state."""
        if self.t0 is None:
            return []
        n_total10 = (
            -(-self._n_in * self._rs.up // self._rs.down) if not self._rs.identity else self._n_in
        )
        tail = self._rs.push(np.zeros(len(self._rs.h) // max(self._rs.up, 1) + 8))
        need = n_total10 - self._n10
        self._consume(tail[: max(need, 0)], end=n_total10)
        states = self._emit(final=True)
        self.t0 = None
        return states

    # -- analysis ---------------------------------------------------------------------------
    def _consume(self, y: np.ndarray, end: int | None = None) -> None:
        """Append analysis-rate samples and analyse every complete frame."""
        if len(y):
            emph = preemphasis(y, coef=PREEMPHASIS, zi=self._emph_prev)
            self._emph_prev = float(y[-1])
            self._buf = np.concatenate([self._buf, y])
            self._emph = np.concatenate([self._emph, emph])
            self._n10 += len(y)
        if end is not None:  # end of stream: frames up to ceil(n/hop), zero padded like batch
            n_frames_total = -(-end // self.n_hop)
            pad = self.n_frame
            self._buf = np.concatenate([self._buf, np.zeros(pad)])
            self._emph = np.concatenate([self._emph, np.zeros(pad)])
        else:
            n_frames_total = None
        # frame i covers analysis samples [i·hop - half, i·hop + half) = _buf[i·hop - _buf_start ...]
        start_i = self._n_feat
        first = start_i * self.n_hop - self.n_frame // 2 - self._buf_start
        raw = frame(self._buf[first:], frame_length=self.n_frame, hop_length=self.n_hop)
        emf = frame(self._emph[first:], frame_length=self.n_frame, hop_length=self.n_hop)
        if n_frames_total is not None:
            raw, emf = (
                raw[: max(0, n_frames_total - start_i)],
                emf[: max(0, n_frames_total - start_i)],
            )
        if len(raw):
            k, e, z, sh, cep = analyze_frames(raw, emf, sr=ANALYSIS_RATE, order=ORDER)
            if self.fixed_calibration is not None:
                sil = np.full(len(e), self.fixed_calibration.silence_db)
                mx = np.full(len(e), self.fixed_calibration.max_db)
            else:
                sil, mx = self._cal.update(e)
            self._e = np.concatenate([self._e, e])
            F = frame_features(k, e, z, sil, mx, sh, cep)
            self._F = np.concatenate([self._F, F if self._norm is None else self._norm(F)])
            if self._first is None and np.any(e >= sil):  # the stream's first sound
                self._first = start_i + int(np.argmax(e >= sil))
            self._sil = np.concatenate([self._sil, sil])
            self._max = np.concatenate([self._max, mx])
        # drop samples no future frame needs
        keep_from = self._n_feat * self.n_hop - self.n_frame // 2 - self._buf_start
        if keep_from > 0:
            self._buf = self._buf[keep_from:]
            self._emph = self._emph[keep_from:]
            self._buf_start += keep_from

    def _classify(self, final: bool) -> None:
        """Class probabilities of every frame whose look-ahead context has arrived (all at the
        end of the stream), as the batch pipeline computes them (edges repeated)."""
        n_feat = self._n_feat
        avail = n_feat if final else n_feat - self._future
        c = np.zeros(0, dtype=np.int64)
        if avail > self._n_p:
            lo = max(0, self._n_p - self._past)
            hi = min(n_feat, avail + self._future)
            F = self._F[lo - self._f0 : hi - self._f0]  # only the rows to classify are stacked
            p = self.net.proba_stacked(stack_rows(F, self.net.offsets, self._n_p - lo, avail - lo))
            self._p = np.concatenate([self._p, p])
            self._n_p = avail
            if self.follower is not None:
                c = self.follower.push(p)
        if self.follower is not None:
            if final:
                c = np.concatenate([c, self.follower.flush()])
            if len(c):
                self._c = np.concatenate([self._c, c])
                self._n_c += len(c)

    def _emit(self, final: bool) -> list[FaceState]:
        n_feat = self._n_feat
        if n_feat == 0:
            return []
        self._classify(final)
        # frames whose (median-filtered, or text-decided) label is final
        label_end = self._n_p if final else self._n_p - self.med_half
        if self.follower is not None:
            label_end = self._n_c
        # output k at time k/fps uses label frames up to floor(k/fps/hop) + coart_frames
        if final:  # as the batch pipeline: states at k/fps for k = 0 .. floor(duration·fps)
            k_end = int(math.floor(self._n_in / self.rate * self.fps + 1e-9)) + 1
        else:
            last_base = label_end - 1 - self.coart_frames
            if last_base < 0:
                return []
            k_end = int(math.floor((last_base + 1) * self.hop * self.fps - 1e-9)) + 1
            # base(k) = floor(k/fps/hop) must be <= last_base
            while k_end > 0 and math.floor((k_end - 1) / self.fps / self.hop + 1e-9) > last_base:
                k_end -= 1
        if k_end <= self._next_out:
            return []
        ks = np.arange(self._next_out, k_end)
        t_rel = ks / self.fps
        p = self.params
        past = int(round(p.coart_past / self.hop)) + self.med_half + self._past + 2
        first_base = int(math.floor(t_rel[0] / self.hop + 1e-9))
        s = max(self._f0, first_base - past)
        lo, hi = s - self._f0, self._n_p - self._f0
        if self.follower is not None:
            cls = self._c[lo : label_end - self._f0]
        else:
            proba = median_filter_proba(self._p[lo:hi], p.median)[: label_end - s]
            cls = np.argmax(proba, axis=1)
        n = len(cls)
        cal = Calibration(self._sil[lo : lo + n], self._max[lo : lo + n])
        first = n if self._first is None else self._first - s
        vis, w = classes_to_visemes(cls, self._e[lo : lo + n], cal, first=first)
        frame_t = (s + np.arange(len(vis))) * self.hop
        tr = coarticulate(
            frame_t,
            vis,
            w,
            t_rel,
            p,
            hop=self.hop,
            lookahead=self.coart_lookahead,
            table=self.table,
        )
        states = [
            FaceState(
                t=float(self.t0 + tr.t[i]),
                faps=tr.faps[i].copy(),
                viseme=_fap1(tr, i) if self.fap1 else None,
            )
            for i in range(len(ks))
        ]
        self._next_out = k_end
        # forget features no future output needs
        keep = max(0, int(math.floor(k_end / self.fps / self.hop)) - past - 1) - self._f0
        if keep > 0:
            self._f0 += keep
            for name in ("_e", "_F", "_p", "_c", "_sil", "_max"):
                setattr(self, name, getattr(self, name)[keep:])
        return states
