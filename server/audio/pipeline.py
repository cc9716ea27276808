"""Batch lip-sync of a whole signal: resample → LPC features → network → labels → coarticulation."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .classify import VowelNet, default_net
from .io import resample, validate_pcm
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
    """LPC features of ``x (n,)`` at ``sr`` Hz, resampled to the analysis rate."""
    return analyze(resample(x, sr, ANALYSIS_RATE), sr=ANALYSIS_RATE)


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
