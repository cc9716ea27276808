"""A BML speech's recording: its lip-sync track and the times of the ``<sync>`` marks in its text.

With a transcript (the speech's ``<text>``), the lip-sync aligns the text's phones to the audio
(``audio.align``, issue 17; text that does not match the audio is refused) and each mark falls at the
onset of the word after it (at the end of the last word for a mark at the end), from the same
forced alignment. Without espeak-ng (which the alignment needs to find the phones) the mouth is
lip-synced from the audio alone and the marks are spread by characters over the span of sound
(first to last frame above the silence level): the documented fallback.
"""

from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...protocol.bml import Speech
from ..audio.pipeline import LipSync, frame_proba, lipsync_file
from ..audio.visemes import Params
from .schedule import SpeechTiming

log = logging.getLogger(__name__)

__all__ = ["SpokenSpeech", "char_marks", "lipsync_speech", "word_bounds"]


@dataclass(frozen=True)
class SpokenSpeech:
    """A speech's lip-sync (``lipsync.track`` at the performance's frame rate, from the recording's
    start), its ``timing`` and how the marks were timed (``aligned`` or ``characters``)."""

    lipsync: LipSync
    timing: SpeechTiming
    marks_from: str


def word_bounds(ls: LipSync, words: tuple[tuple[int, ...], ...]) -> np.ndarray:
    """``(W + 1,)`` seconds: each word's onset and the last word's end, from the forced alignment
    of the phone classes ``words`` (``align.text_phones``) over ``ls``'s features.

    The same Viterbi as ``align.text_fit`` (same states, scores and class priors); its states
    carry, instead of their class, the id of their run of equal classes, so the path tells which
    word each frame belongs to.
    """
    from ..audio.align import MIN_FRAMES, _states, forced_path  # the aligner's own states

    cls, opt = _states(words)
    word_of_state = np.full(len(cls), -1)
    s = 1  # [silence] word 0's phones [silence] word 1's phones ...
    for w, word in enumerate(words):
        n = len(word) * MIN_FRAMES
        word_of_state[s : s + n] = w
        s += n + 1
    run = np.concatenate([[0], np.cumsum(cls[1:] != cls[:-1])])
    first = np.unique(run, return_index=True)[1]
    run_class, run_word = cls[first], word_of_state[first]
    proba = frame_proba(ls.features, ls.calibration)
    prior = np.maximum(proba.mean(axis=0), 1e-4)
    logp = np.log(np.maximum(proba, 1e-8)) - np.log(prior)
    path, _ = forced_path(logp[:, run_class], run, opt)
    frame_word = run_word[path]
    times = np.asarray(ls.features.times, dtype=np.float64)
    hop = float(ls.features.hop)
    bounds = np.empty(len(words) + 1)
    for w in range(len(words)):
        hit = np.flatnonzero(frame_word == w)
        bounds[w] = times[hit[0]] if len(hit) else (bounds[w - 1] if w else 0.0)
    last = np.flatnonzero(frame_word == len(words) - 1)
    bounds[-1] = times[last[-1]] + hop if len(last) else bounds[-2]
    return bounds


def char_marks(speech: Speech, ls: LipSync) -> dict[str, float]:
    """Marks spread by characters over the span of sound (the fallback without alignment)."""
    e = np.asarray(ls.features.energy_db)
    loud = np.flatnonzero(e >= ls.calibration.silence_db)
    times = np.asarray(ls.features.times, dtype=np.float64)
    if len(loud):
        a, b = float(times[loud[0]]), float(times[loud[-1]] + ls.features.hop)
    else:
        a, b = 0.0, ls.duration
    n = max(1, len(speech.text or ""))
    return {m.id: a + (b - a) * m.chars / n for m in speech.marks}


def lipsync_speech(
    speech: Speech,
    audio: Path,
    fps: float,
    table: np.ndarray | None = None,
    *,
    max_seconds: float | None = None,
) -> SpokenSpeech:
    """Lip-sync ``speech``'s recording ``audio`` at ``fps`` and time its marks (a recording over
    ``max_seconds``, default ``FACECAST_MAX_AUDIO_SECONDS``, is refused from its header).

    Raises:
        InputError: unreadable or too long audio, or a transcript that does not match it.
    """
    text = speech.text
    aligned = text is not None and shutil.which("espeak-ng") is not None
    if text is not None and not aligned:
        log.warning(
            "speech %s: espeak-ng is missing: its marks are spread by characters", speech.id
        )
    ls = lipsync_file(
        audio,
        fps=fps,
        params=Params(),
        table=table,
        text=text if aligned else None,
        max_seconds=max_seconds,
    )
    marks: dict[str, float] = {}
    if speech.marks and aligned and text is not None:
        from ..audio.align import text_phones

        segments, last = [], 0
        for m in speech.marks:
            segments.append(text[last : m.chars])
            last = m.chars
        segments.append(text[last:])
        per = [text_phones(seg) if seg.strip() else () for seg in segments]
        words = tuple(w for seg in per for w in seg)
        bounds = word_bounds(ls, words)
        before = 0
        for m, seg in zip(speech.marks, per, strict=False):
            before += len(seg)
            marks[m.id] = float(bounds[before])
    elif speech.marks:
        marks = char_marks(speech, ls)
    timing = SpeechTiming(duration=float(ls.duration), marks=marks)
    return SpokenSpeech(ls, timing, "aligned" if aligned else "characters")
