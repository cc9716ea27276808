"""Batch lip-sync of a whole signal: resample → LPC features → calibration → frame network over
context-stacked features (ten visual classes) → median filter → visemes → coarticulation."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from .classify import CLASS_VISEMES, FrameNet, default_frame_net, frame_features
from .io import RATE_TOLERANCE, decode_audio, resample, validate_pcm
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
#: Per class: the least intensity (a closure 1, fricatives 0.5) and a factor (silence 0).
_W_FLOOR = np.zeros(len(CLASS_VISEMES))
_W_FLOOR[[_LABIODENTAL, _SIBILANT]], _W_FLOOR[_CLOSED] = 0.5, 1.0
_W_SCALE = np.ones(len(CLASS_VISEMES))
_W_SCALE[_SIL] = 0.0


@dataclass
class LipSync:
    """Result of ``lipsync``: per analysis frame (100/s) ``features``, ``proba (T, 10)`` (median
    filtered class probabilities, ``classify.CLASSES``), ``visemes (T,)``, ``weights (T,)``, the
    ``calibration`` used, and ``track``: the coarticulated output sampled at the requested frame
    rate."""

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
        i = np.clip(
            np.round(np.asarray(t) / self.features.hop).astype(np.int64), 0, len(self.visemes) - 1
        )
        return self.visemes[i], self.weights[i]


def features_of(x: np.ndarray, sr: float) -> Features:
    """LPC features of ``x (n,)`` at ``sr`` Hz, resampled to the analysis rate.

    A signal already within ``RATE_TOLERANCE`` of the analysis rate (``decode_audio`` gives one
    for odd file rates) is analysed at its own rate, so the frame times stay exact.
    """
    if abs(float(sr) / ANALYSIS_RATE - 1.0) > RATE_TOLERANCE:
        x, sr = resample(x, sr, ANALYSIS_RATE), ANALYSIS_RATE
    return analyze(x, sr=sr)


def frame_proba(f: Features, cal: Calibration, net: FrameNet | None = None) -> np.ndarray:
    """``(T, 10)`` frame-network class probabilities (``classify.CLASSES``) of features ``f``
    under the energy calibration ``cal`` (default network: the shipped one)."""
    net = net or default_frame_net()
    return net.proba(
        frame_features(f.k, f.energy_db, f.zcr, cal.silence_db, cal.max_db, f.shape, f.cep)
    )


def lipsync_file(
    path: str | Path,
    *,
    fps: float = 100.0,
    lookahead: float | None = None,
    calibration: Calibration | None = None,
    silence_db: float | None = None,
    max_db: float | None = None,
    text: str | None = None,
    voice: str = "en-us",
    params: Params | None = None,
    net: FrameNet | None = None,
    table: np.ndarray | None = None,
    max_seconds: float | None = None,
) -> LipSync:
    """Lip-sync an audio file, decoded in blocks straight to the analysis rate.

    The peak memory follows the audio's duration, whatever the file's rate, channels or format:
    its ``ANALYSIS_RATE`` float32 samples (144 MB for an hour), the per-frame features and network
    inputs, and the output track (``facecast lipsync`` of an hour: 735 MB peak RSS at 100 fps).

    Args:
        calibration: energy levels (e.g. ``calibration_file``); default: from the file.
        silence_db, max_db: explicit energy levels, dB full scale, overriding those of
            ``calibration`` (or of the file).
        text: the transcript: its phones are aligned to the audio (``align.align_features``).
        max_seconds: longest audio accepted (default ``io.max_audio_seconds()``).
        Others: as ``lipsync``.
    Raises:
        InputError: unreadable, invalid or too long audio (``io.decode_audio``), a ``max_db``
            not above the silence threshold, or a transcript that does not match the audio.
    """
    if text is not None:
        from .align import align_features, check_text  # align builds on this module

        check_text(text)  # before the decoding
    audio = decode_audio(path, ANALYSIS_RATE, max_seconds=max_seconds)
    f = features_of(audio.x, audio.rate)
    seconds = audio.seconds
    del audio  # the signal is not needed past the features
    cal = calibration
    if silence_db is not None or max_db is not None:
        auto = cal or calibrate(f.energy_db)
        cal = Calibration(
            auto.silence_db if silence_db is None else float(silence_db),
            auto.max_db if max_db is None else float(max_db),
        )
        if cal.max_db <= cal.silence_db:
            raise InputError(
                f"the loudest level (--max-db) {cal.max_db} dB must be above the silence "
                f"threshold {cal.silence_db} dB",
                where="max_db",
            )
    if text is not None:
        return align_features(
            f,
            seconds,
            text,
            net=net,
            calibration=cal,
            fps=fps,
            lookahead=lookahead,
            params=params,
            table=table,
            voice=voice,
        )
    cal = cal or calibrate(f.energy_db)
    return track_of(
        f,
        frame_proba(f, cal, net),
        seconds,
        fps=fps,
        lookahead=lookahead,
        calibration=cal,
        params=params,
        table=table,
    )


def calibration_file(path: str | Path, *, max_seconds: float | None = None) -> Calibration:
    """``calibration_from`` of an audio file, decoded in blocks straight to the analysis rate."""
    audio = decode_audio(path, ANALYSIS_RATE, max_seconds=max_seconds)
    return calibrate_reference(features_of(audio.x, audio.rate).energy_db, where=str(path))


def calibration_from(x: np.ndarray, sr: float, *, where: str = "calibration") -> Calibration:
    """Calibration from a recording of room noise and a loud sustained /a/
    (``visemes.calibrate_reference``); pass it to ``lipsync`` or ``AudioLiveDriver``."""
    x = validate_pcm(x, sr, where=where)
    return calibrate_reference(features_of(x, sr).energy_db, where=where)


def lipsync(
    x: np.ndarray,
    sr: float,
    *,
    fps: float = 100.0,
    lookahead: float | None = None,
    calibration: Calibration | None = None,
    params: Params | None = None,
    net: FrameNet | None = None,
    where: str = "audio",
    table: np.ndarray | None = None,
) -> LipSync:
    """Lip-sync ``x`` (samples, mono or ``(n, channels)``) at ``sr`` Hz.

    Args:
        fps: output frame rate of ``track`` (frames at ``i / fps`` seconds).
        lookahead: coarticulation look-ahead in seconds; None = free (batch).
        calibration: energy levels (``visemes.Calibration``, e.g. from ``calibration_from``);
            None = calibrated from this signal (``visemes.calibrate``).
        net: the frame network (default: the shipped one).
        table: viseme → FAP targets ``(15, 69)`` (default ``visemes.viseme_table()``).
    """
    x = validate_pcm(x, sr, where=where)
    f = features_of(x, sr)
    cal = calibration or calibrate(f.energy_db)
    return track_of(
        f,
        frame_proba(f, cal, net),
        len(x) / float(sr),
        fps=fps,
        lookahead=lookahead,
        calibration=cal,
        params=params,
        table=table,
    )


def first_sound(energy_db: np.ndarray, cal: Calibration) -> int:
    """Index of the first frame at or above the silence threshold (``len`` if none)."""
    loud = np.asarray(energy_db) >= cal.silence_db
    return int(np.argmax(loud)) if loud.any() else len(loud)


def classes_to_visemes(
    cls: np.ndarray, energy_db: np.ndarray, cal: Calibration, first: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``(viseme (T,), weight (T,))`` from frame classes ``cls (T,)``: the class's viseme, with an
    intensity linear in dB between the calibrated silence and maximum (silence 0, a closure 1,
    fricatives at least 0.5). Frames before ``first`` (default: ``first_sound``, frame 0 being
    the start of the stream) are silence: the mouth rests until the first sound."""
    cls = np.asarray(cls)
    first = first_sound(energy_db, cal) if first is None else first
    if first > 0:  # (the live path's windows mostly start after the first sound)
        cls = np.where(np.arange(len(cls)) < first, _SIL, cls)
    vis = CLASS_VISEMES[cls] if len(cls) else np.zeros(0, dtype=np.int64)
    # intensity in [0, 1] raised to the class's floor, times its factor (table lookups: fewer
    # NumPy calls than a where per rule, same values)
    w = np.maximum(cal.intensity(energy_db), _W_FLOOR[cls]) * _W_SCALE[cls]
    return vis.astype(np.int64), w


def track_of(
    f: Features,
    proba: np.ndarray,
    duration: float,
    *,
    fps: float = 100.0,
    lookahead: float | None = None,
    calibration: Calibration | None = None,
    params: Params | None = None,
    table: np.ndarray | None = None,
) -> LipSync:
    """The rest of ``lipsync`` from features and frame network outputs ``proba (T, 10)``."""
    params = params or Params()
    proba = median_filter_proba(proba, params.median)
    cal = calibration or calibrate(f.energy_db)
    cls = np.argmax(proba, axis=1) if len(proba) else np.zeros(0, dtype=np.int64)
    vis, w = classes_to_visemes(cls, f.energy_db, cal)
    n_out = int(np.floor(duration * fps + 1e-9)) + 1 if len(f) else 0
    track = coarticulate(
        f.times, vis, w, np.arange(n_out) / fps, params, hop=f.hop, lookahead=lookahead, table=table
    )
    return LipSync(f, proba, vis, w, cal, track, duration)
