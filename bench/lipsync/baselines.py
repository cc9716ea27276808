"""Baselines measured in the same run as facecast.

1. ``energy``: "jaw flapping" — mouth open (viseme aa) whenever the frame energy is above the
   silence threshold, closed (sil) otherwise; intensity from energy.
2. ``mfcc``: template matching in the manner of uLipSync — per-vowel mean MFCC templates from the
   same generated training material as facecast's network, nearest template per frame (Euclidean
   on standardised coefficients), energy gate for silence. MFCC written here with NumPy/SciPy.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import scipy.fft

from facecast.server.audio.generate import NUCLEUS_DB, NUCLEUS_MAX_ZCR, speak, utterances
from facecast.server.audio.io import read_audio, resample
from facecast.server.audio.lpc import frame, preemphasis
from facecast.server.audio.pipeline import features_of
from facecast.server.audio.visemes import AA, SIL, VOWEL_VISEMES, calibrate, median_filter_proba

MFCC_RATE = 16000


def mel_filterbank(
    *, sr: float, n_fft: int, n_mels: int = 26, fmin: float = 0.0, fmax: float | None = None
) -> np.ndarray:
    """``(n_mels, n_fft//2 + 1)`` triangular filters equally spaced on the mel scale (HTK mel)."""
    fmax = fmax or sr / 2

    def mel(f):
        return 2595.0 * np.log10(1.0 + f / 700.0)

    def hz(m):
        return 700.0 * (10 ** (m / 2595.0) - 1.0)

    edges = hz(np.linspace(mel(fmin), mel(fmax), n_mels + 2))
    freqs = np.linspace(0, sr / 2, n_fft // 2 + 1)
    lo, c, hi = edges[:-2, None], edges[1:-1, None], edges[2:, None]
    return np.maximum(0.0, np.minimum((freqs - lo) / (c - lo), (hi - freqs) / (hi - c)))


def mfcc(
    x: np.ndarray,
    *,
    sr: float = MFCC_RATE,
    frame_length: float = 0.025,
    hop_length: float = 0.010,
    n_mels: int = 26,
    n_mfcc: int = 12,
) -> np.ndarray:
    """``(T, n_mfcc)`` MFCCs c1..c_n (c0 dropped: loudness) of centred frames at ``i·hop``."""
    n_frame, n_hop = int(round(frame_length * sr)), int(round(hop_length * sr))
    n_fft = 1 << (n_frame - 1).bit_length()
    n_out = -(-len(x) // n_hop)
    padded = np.concatenate([np.zeros(n_frame // 2), x, np.zeros(n_frame)])
    f = frame(preemphasis(padded), frame_length=n_frame, hop_length=n_hop)[:n_out]
    spec = np.abs(np.fft.rfft(f * np.hamming(n_frame), n=n_fft)) ** 2
    mel = np.log(spec @ mel_filterbank(sr=sr, n_fft=n_fft, n_mels=n_mels).T + 1e-10)
    return scipy.fft.dct(mel, type=2, norm="ortho", axis=1)[:, 1 : n_mfcc + 1]


class MfccTemplates:
    """Per-vowel mean MFCC from the generated training utterances (vowel-nucleus frames)."""

    def __init__(self, n_per_vowel: int = 40, seed: int = 0) -> None:
        feats, labels = [], []
        with tempfile.TemporaryDirectory() as tmp:
            wav = Path(tmp) / "u.wav"
            for voice, text, pitch, rate, _variant, vi in utterances(n_per_vowel, seed):
                speak(text, voice=voice, pitch=pitch, rate=rate, out=wav)
                x, sr = read_audio(wav)
                f = features_of(x, sr)
                m = mfcc(resample(x, sr, MFCC_RATE))
                n = min(len(f), len(m))
                keep = (f.energy_db[:n] >= f.energy_db.max() - NUCLEUS_DB) & (
                    f.zcr[:n] < NUCLEUS_MAX_ZCR
                )
                feats.append(m[:n][keep])
                labels.append(np.full(int(keep.sum()), vi))
        allf, ally = np.concatenate(feats), np.concatenate(labels)
        self.mean, self.std = allf.mean(0), allf.std(0) + 1e-9
        z = (allf - self.mean) / self.std
        self.templates = np.stack([z[ally == v].mean(0) for v in range(5)])
        self.n_frames = len(ally)

    def visemes(self, x: np.ndarray, sr: float) -> tuple[np.ndarray, np.ndarray]:
        """``(visemes (T,), weights (T,))`` per 10 ms frame."""
        f = features_of(x, sr)
        cal = calibrate(f.energy_db)
        m = mfcc(resample(x, sr, MFCC_RATE))
        m = np.vstack([m, np.repeat(m[-1:], max(0, len(f) - len(m)), 0)])[: len(f)]
        d = (((m - self.mean) / self.std)[:, None, :] - self.templates[None]) ** 2
        score = np.exp(-(d.sum(-1) - d.sum(-1).min(1, keepdims=True)) / 12.0)
        score = median_filter_proba(score / score.sum(1, keepdims=True), 5)
        vis = VOWEL_VISEMES[np.argmax(score, axis=1)]
        quiet = f.energy_db < cal.silence_db
        return np.where(quiet, SIL, vis), cal.intensity(f.energy_db)


def energy_visemes(x: np.ndarray, sr: float) -> tuple[np.ndarray, np.ndarray]:
    """Jaw flapping: ``(visemes (T,), weights (T,))`` per 10 ms frame."""
    f = features_of(x, sr)
    cal = calibrate(f.energy_db)
    return np.where(f.energy_db < cal.silence_db, SIL, AA), cal.intensity(f.energy_db)
