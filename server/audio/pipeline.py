"""Batch lip-sync of a whole signal: resample → LPC features → network → labels → coarticulation."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from .classify import VowelNet, default_net
from .io import RATE_TOLERANCE, decode_audio, resample, validate_pcm
from .lpc import ANALYSIS_RATE, Features, analyze
from .visemes import (
    Calibration,
    Params,
    Track,
    calibrate,
    coarticulate,
    label_frames,
    median_filter_proba,
)


@dataclass
class LipSync:
    """Result of ``lipsync``: per analysis frame (100/s) ``features``, ``proba (T, 5)`` (median
    filtered), ``visemes (T,)``, ``weights (T,)``, the ``calibration`` used, and ``track``: the
    coarticulated output sampled at the requested frame rate."""

    features: Features
    proba: np.ndarray
    visemes: np.ndarray
    weights: np.ndarray
    calibration: Calibration
    track: Track
    duration: float

    def labels_at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(viseme (N,), weight (N,))``: the classified viseme and intensity of the analysis frame
        nearest each time ``t (N,)`` s — what is being said, before coarticulation (the viseme
        track that ``facecast lipsync`` prints; the animation's FAPs are coarticulated)."""
        if len(self.visemes) == 0:
            z = np.zeros(len(t))
            return z.astype(np.int64), z
        i = np.clip(np.round(np.asarray(t) / self.features.hop).astype(np.int64), 0,
                    len(self.visemes) - 1)
        return self.visemes[i], self.weights[i]


def features_of(x: np.ndarray, sr: float) -> Features:
    """LPC features of ``x (n,)`` at ``sr`` Hz, resampled to the analysis rate.

    A signal already within ``RATE_TOLERANCE`` of the analysis rate (``decode_audio`` gives one
    for odd file rates) is analysed at its own rate, so the frame times stay exact.
    """
    if abs(float(sr) / ANALYSIS_RATE - 1.0) > RATE_TOLERANCE:
        x, sr = resample(x, sr, ANALYSIS_RATE), ANALYSIS_RATE
    return analyze(x, sr=sr)


def lipsync_file(path: str | Path, *, fps: float = 100.0, lookahead: float | None = None,
                 silence_db: float | None = None, max_db: float | None = None,
                 params: Params | None = None, net: VowelNet | None = None,
                 table: np.ndarray | None = None, max_seconds: float | None = None) -> LipSync:
    """Lip-sync an audio file, decoded in blocks straight to the analysis rate.

    The peak memory is about the file's duration × ``ANALYSIS_RATE`` float32 samples (144 MB
    for an hour) plus the per-frame features, whatever the file's rate, channels or format.

    Args:
        silence_db, max_db: explicit energy calibration, dB full scale (default: from the file).
        max_seconds: longest audio accepted (default ``io.max_audio_seconds()``).
        Others: as ``lipsync``.
    Raises:
        InputError: unreadable, invalid or too long audio (``io.decode_audio``), or a ``max_db``
            not above the silence threshold.
    """
    audio = decode_audio(path, ANALYSIS_RATE, max_seconds=max_seconds)
    f = features_of(audio.x, audio.rate)
    seconds = audio.seconds
    del audio  # the signal is not needed past the features
    cal = None
    if silence_db is not None or max_db is not None:
        auto = calibrate(f.energy_db)
        cal = Calibration(auto.silence_db if silence_db is None else float(silence_db),
                          auto.max_db if max_db is None else float(max_db))
        if cal.max_db <= cal.silence_db:
            raise InputError(f"the loudest level (--max-db) {cal.max_db} dB must be above the silence "
                             f"threshold {cal.silence_db} dB", where="max_db")
    net = net or default_net()
    return track_of(f, net.proba(f.k), seconds, fps=fps, lookahead=lookahead, calibration=cal,
                    params=params, table=table)


def lipsync(x: np.ndarray, sr: float, *, fps: float = 100.0, lookahead: float | None = None,
            calibration: Calibration | None = None, params: Params | None = None,
            net: VowelNet | None = None, where: str = "audio",
            table: np.ndarray | None = None) -> LipSync:
    """Lip-sync ``x`` (samples, mono or ``(n, channels)``) at ``sr`` Hz.

    Args:
        fps: output frame rate of ``track`` (frames at ``i / fps`` seconds).
        lookahead: coarticulation/pause look-ahead in seconds; None = free (batch).
        calibration: energy levels; None = calibrated from this signal (``visemes.calibrate``).
        table: viseme → FAP targets ``(15, 69)`` (default ``visemes.viseme_table()``).
    """
    x = validate_pcm(x, sr, where=where)
    net = net or default_net()
    f = features_of(x, sr)
    return track_of(f, net.proba(f.k), len(x) / float(sr), fps=fps, lookahead=lookahead,
                    calibration=calibration, params=params, table=table)


def track_of(f: Features, proba: np.ndarray, duration: float, *, fps: float = 100.0,
             lookahead: float | None = None, calibration: Calibration | None = None,
             params: Params | None = None, table: np.ndarray | None = None) -> LipSync:
    """The rest of ``lipsync`` from features and raw network outputs ``proba (T, 5)``."""
    params = params or Params()
    proba = median_filter_proba(proba, params.median)
    cal = calibration or calibrate(f.energy_db)
    # with a limited look-ahead (live equivalence) the pause rule is causal
    vis, w = label_frames(f.energy_db, f.zcr, proba, cal, params, hop=f.hop,
                          lookahead=None if lookahead is None else 0.0)
    n_out = int(np.floor(duration * fps + 1e-9)) + 1 if len(f) else 0
    track = coarticulate(f.times, vis, w, np.arange(n_out) / fps, params, hop=f.hop,
                         lookahead=lookahead, table=table)
    return LipSync(f, proba, vis, w, cal, track, duration)
