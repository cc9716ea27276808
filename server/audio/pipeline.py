"""Batch lip-sync of a whole signal: resample → LPC features → calibration → frame network over
context-stacked features (ten visual classes) → median filter → visemes → coarticulation."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .classify import CLASS_VISEMES, FrameNet, default_frame_net, frame_features
from .io import resample, validate_pcm
from .lpc import ANALYSIS_RATE, Features, analyze
from .visemes import (
    Calibration,
    Params,
    Track,
    calibrate,
    calibrate_reference,
    coarticulate,
    median_filter_proba,
)

#: Class indices (``classify.CLASSES``) with a fixed intensity: silence rests, a closure closes.
_SIL, _CLOSED, _LABIODENTAL, _SIBILANT = 0, 1, 2, 3


@dataclass
class LipSync:
    """Result of ``lipsync``: per analysis frame (100/s) ``features``, ``proba (T, 10)`` (median
    filtered class probabilities, ``classify.CLASSES``), ``visemes (T,)``, ``weights (T,)``, the ``calibration`` used, and ``track``: the
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


def calibration_from(x: np.ndarray, sr: float, *, where: str = "calibration") -> Calibration:
    """Calibration from a recording of room noise and a loud sustained /a/
    (``visemes.calibrate_reference``); pass it to ``lipsync`` or ``AudioLiveDriver``."""
    x = validate_pcm(x, sr, where=where)
    return calibrate_reference(features_of(x, sr).energy_db, where=where)


def lipsync(x: np.ndarray, sr: float, *, fps: float = 100.0, lookahead: float | None = None,
            calibration: Calibration | None = None, params: Params | None = None,
            net: FrameNet | None = None, where: str = "audio",
            table: np.ndarray | None = None) -> LipSync:
    """Lip-sync ``x`` (samples, mono or ``(n, channels)``) at ``sr`` Hz.

    Args:
        fps: output frame rate of ``track`` (frames at ``i / fps`` seconds).
        lookahead: coarticulation look-ahead in seconds; None = free (batch).
        calibration: energy levels (``visemes.Calibration``, e.g. from ``calibrate_from``);
            None = calibrated from this signal (``visemes.calibrate``).
        net: the frame network (default: the shipped one).
        table: viseme → FAP targets ``(15, 69)`` (default ``visemes.viseme_table()``).
    """
    x = validate_pcm(x, sr, where=where)
    net = net or default_frame_net()
    f = features_of(x, sr)
    cal = calibration or calibrate(f.energy_db)
    F = frame_features(f.k, f.energy_db, f.zcr, cal.silence_db, cal.max_db, f.shape, f.cep)
    proba = net.proba(F)
    return track_of(f, proba, len(x) / float(sr), fps=fps, lookahead=lookahead,
                    calibration=cal, params=params, table=table)


def first_sound(energy_db: np.ndarray, cal: Calibration) -> int:
    """Index of the first frame at or above the silence threshold (``len`` if none)."""
    loud = np.asarray(energy_db) >= cal.silence_db
    return int(np.argmax(loud)) if loud.any() else len(loud)


def classes_to_visemes(cls: np.ndarray, energy_db: np.ndarray, cal: Calibration,
                       first: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(viseme (T,), weight (T,))`` from frame classes ``cls (T,)``: the class's viseme, with an
    intensity linear in dB between the calibrated silence and maximum (silence 0, a closure 1,
    fricatives at least 0.5). Frames before ``first`` (default: ``first_sound``, frame 0 being
    the start of the stream) are silence: the mouth rests until the first sound."""
    cls = np.asarray(cls)
    first = first_sound(energy_db, cal) if first is None else first
    cls = np.where(np.arange(len(cls)) < first, _SIL, cls)
    vis = CLASS_VISEMES[cls] if len(cls) else np.zeros(0, dtype=np.int64)
    w = cal.intensity(energy_db)
    w = np.where((cls == _LABIODENTAL) | (cls == _SIBILANT), np.maximum(w, 0.5), w)
    w = np.where(cls == _CLOSED, 1.0, np.where(cls == _SIL, 0.0, w))
    return vis.astype(np.int64), w


def track_of(f: Features, proba: np.ndarray, duration: float, *, fps: float = 100.0,
             lookahead: float | None = None, calibration: Calibration | None = None,
             params: Params | None = None, table: np.ndarray | None = None) -> LipSync:
    """The rest of ``lipsync`` from features and frame network outputs ``proba (T, 10)``."""
    params = params or Params()
    proba = median_filter_proba(proba, params.median)
    cal = calibration or calibrate(f.energy_db)
    cls = np.argmax(proba, axis=1) if len(proba) else np.zeros(0, dtype=np.int64)
    vis, w = classes_to_visemes(cls, f.energy_db, cal)
    n_out = int(np.floor(duration * fps + 1e-9)) + 1 if len(f) else 0
    track = coarticulate(f.times, vis, w, np.arange(n_out) / fps, params, hop=f.hop,
                         lookahead=lookahead, table=table)
    return LipSync(f, proba, vis, w, cal, track, duration)
