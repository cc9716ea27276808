"""Lip-sync with a known transcript: the text's phones, forced onto the audio.

espeak-ng turns the text into IPA phones (``espeak-ng -q --ipa --sep=_``); each phone becomes the
visual class the frame network knows (``classify.CLASSES``), every phone lasting at least
``MIN_FRAMES`` frames, with optional silence between words; a Viterbi search over the network's
class posteriors (divided by the class priors, hybrid style) finds the timing. Text that does not
fit the audio is refused: when its phones would be spoken implausibly fast or slow over the
audio's sound (``PHONE_RATE``), or when the forced path scores far below the network's own best
reading under the same duration rules (``MAX_MISMATCH`` nats per speech frame), the text is not
what was said.
"""

from __future__ import annotations

import functools
import re
import shutil
import subprocess

import numpy as np

from ..errors import InputError
from .classify import CLASSES, FrameNet
from .io import validate_pcm
from .lpc import Features
from .pipeline import LipSync, features_of, frame_proba, track_of
from .visemes import Calibration, Params, calibrate

C = {name: i for i, name in enumerate(CLASSES)}
#: IPA symbol (stress and length marks removed) → class; multi-letter symbols first.
IPA_CLASSES = {
    "tʃ": "sibilant",
    "dʒ": "sibilant",
    "aɪ": "open",
    "aʊ": "open",
    "eɪ": "mid",
    "oʊ": "round",
    "ɔɪ": "round",
    "əʊ": "round",
    "p": "closed",
    "b": "closed",
    "m": "closed",
    "f": "labiodental",
    "v": "labiodental",
    "s": "sibilant",
    "z": "sibilant",
    "ʃ": "sibilant",
    "ʒ": "sibilant",
    "a": "open",
    "ɑ": "open",
    "æ": "open",
    "ʌ": "open",
    "ə": "open",
    "ɐ": "open",
    "ɒ": "round",
    "e": "mid",
    "ɛ": "mid",
    "ɚ": "mid",
    "ɜ": "mid",
    "ɝ": "mid",
    "i": "spread",
    "ɪ": "spread",
    "ᵻ": "spread",
    "j": "spread",
    "o": "round",
    "ɔ": "round",
    "u": "narrow-round",
    "ʊ": "narrow-round",
    "w": "narrow-round",
}
#: Frames (10 ms) each phone lasts at least.
MIN_FRAMES = 3
#: Refuse the text when the forced path scores this much below the free reading, nats per frame.
#: Measured with speaker-held-out networks (bench/lipsync/folds.py, 38 real recordings): own
#: transcripts median 0.87 (11 of 38 above 1.0: short or mumbled recordings), another recording's
#: transcript min 0.86 (36 of 38 above 1.0). Set to refuse rather than animate the wrong text.
MAX_MISMATCH = 1.0
#: Phones per second of sound (frames above the silence threshold) a transcript may imply:
#: English speech runs at about 10-15; the 38 real recordings' own transcripts give 5.2-25.7
#: (bench/lipsync/folds.py), another recording's transcript 1.2-50 (17 of 35 outside).
PHONE_RATE = (4.0, 30.0)
#: Most text accepted, characters.
MAX_TEXT = 10000


@functools.lru_cache(maxsize=256)
def text_phones(text: str, voice: str = "en-us") -> tuple[tuple[int, ...], ...]:
    """Class ids of the phones of each word of ``text`` (espeak-ng's pronunciation)."""
    exe = shutil.which("espeak-ng")
    if exe is None:
        raise InputError(
            "a transcript needs espeak-ng (Debian package espeak-ng) to find its "
            "phones; install it or leave out the text",
            where="text",
        )
    res = subprocess.run(
        [exe, "-q", "--ipa", "--sep=_", "-v", voice, "--stdin"],
        input=text,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    if res.returncode != 0:
        raise InputError(
            f"espeak-ng could not read the text: {res.stderr.strip()[:200]}", where="text"
        )
    words = []
    for word in res.stdout.split():
        classes = []
        for ph in word.split("_"):
            ph = re.sub("[ˈˌːˑ\u200d-]", "", ph)
            if not ph:
                continue
            rhotic = len(ph) > 1 and ph.endswith("ɹ")
            ph = ph[:-1] if rhotic else ph
            cls = IPA_CLASSES.get(ph[:2]) or IPA_CLASSES.get(ph[:1]) or "other"
            classes.append(C[cls])
            if rhotic:
                classes.append(C["other"])
        if classes:
            words.append(tuple(classes))
    return tuple(words)


def _states(words: tuple[tuple[int, ...], ...]) -> tuple[np.ndarray, np.ndarray]:
    """Left-to-right states: ``(class (S,), optional (S,) bool)``; silence around every word is
    optional, each phone is ``MIN_FRAMES`` chained states of its class."""
    cls, opt = [C["sil"]], [True]
    for word in words:
        for c in word:
            cls += [c] * MIN_FRAMES
            opt += [False] * MIN_FRAMES
        cls.append(C["sil"])
        opt.append(True)
    return np.array(cls), np.array(opt)


def forced_path(logp: np.ndarray, cls: np.ndarray, opt: np.ndarray) -> tuple[np.ndarray, float]:
    """Viterbi through the left-to-right states: ``(class per frame (T,), total score)``.

    A state is entered from the one before it, or from two before when the skipped one is
    optional; the last ``MIN_FRAMES`` states of each phone and the silences may repeat. Starts in
    state 0 or 1, ends in the last or the one before."""
    T, S = len(logp), len(cls)
    emit = logp[:, cls]  # (T, S)
    loop = np.ones(S, dtype=bool)
    nxt = np.append(cls[1:], -1)
    same_next = (cls == nxt) & ~opt & np.append(~opt[1:], False)
    loop[same_next] = False  # inner chained states of a phone
    skip_ok = np.zeros(S, dtype=bool)
    skip_ok[2:] = opt[1:-1]
    neg = -1e18
    score = np.full(S, neg)
    score[0] = emit[0, 0]
    if S > 1:
        score[1] = emit[0, 1]
    back = np.zeros((T, S), dtype=np.int32)
    idx = np.arange(S)
    for t in range(1, T):
        stay = np.where(loop, score, neg)
        step = np.concatenate([[neg], score[:-1]])
        jump = np.where(skip_ok, np.concatenate([[neg, neg], score[:-2]]), neg)
        best = np.maximum(np.maximum(stay, step), jump)
        back[t] = np.where(best == stay, idx, np.where(best == step, idx - 1, idx - 2))
        score = best + emit[t]
    ends = [S - 1] + ([S - 2] if S > 1 else [])
    s = max(ends, key=lambda j: score[j])
    total = float(score[s])
    path = np.empty(T, dtype=np.int64)
    for t in range(T - 1, -1, -1):
        path[t] = s
        s = back[t, s]
    return cls[path], total


def free_score(logp: np.ndarray, min_frames: int = MIN_FRAMES) -> float:
    """Best Viterbi score of any class sequence over ``logp (T, C)`` in which every class lasts
    at least ``min_frames`` frames (the free reading a transcript is measured against)."""
    T, n = logp.shape
    neg = -1e18
    score = np.full((n, min_frames), neg)
    score[:, 0] = logp[0]
    for t in range(1, T):
        new = np.empty_like(score)
        new[:, 0] = score[:, -1].max()
        new[:, 1:] = score[:, :-1]
        new[:, -1] = np.maximum(new[:, -1], score[:, -1])
        score = new + logp[t][:, None]
    return float(score[:, -1].max())


def text_fit(proba: np.ndarray, text: str, voice: str = "en-us") -> tuple[np.ndarray, float, int]:
    """Force the phones of ``text`` onto frame class probabilities ``proba (T, 10)``.

    Returns ``(class per frame (T,), mismatch, phones)``: mismatch = how much worse the forced
    path scores than the free reading (``free_score``: any class sequence with the same minimum
    durations), nats per speech frame (0 = the text explains the audio as well as the network's
    own best guess). Raises InputError for text without speakable
    words or with more phones than the frames can hold."""
    words = text_phones(text, voice)
    if not words:
        raise InputError("the transcript has no speakable words", where="text")
    cls, opt = _states(words)
    n_phones = int((~opt).sum()) // MIN_FRAMES
    if (~opt).sum() > len(proba):
        raise InputError(
            f"the transcript has {n_phones} phones, more than "
            f"{len(proba) / 100:.2f} s of audio can hold: it does not match the audio",
            where="text",
        )
    prior = np.maximum(proba.mean(axis=0), 1e-4)
    logp = np.log(np.maximum(proba, 1e-8)) - np.log(prior)
    path, forced = forced_path(logp, cls, opt)
    free = free_score(logp)
    speech = max(1, int(np.sum(path != C["sil"])))
    return path, (free - forced) / speech, n_phones


def checked_fit(proba: np.ndarray, text: str, speech: float, voice: str = "en-us") -> np.ndarray:
    """``text_fit``'s class per frame, or InputError when the text does not match the audio:
    ``speech`` seconds of sound (frames above the silence threshold) hold fewer than
    ``PHONE_RATE[0]`` or more than ``PHONE_RATE[1]`` of its phones per second, or the forced
    reading is more than ``MAX_MISMATCH`` worse than the free one."""
    path, mismatch, n_phones = text_fit(proba, text, voice)
    rate = n_phones / max(speech, 0.1)
    lo, hi = PHONE_RATE
    if not lo <= rate <= hi:
        raise InputError(
            f"the transcript does not match the audio: its {n_phones} phones would "
            f"be spoken at {rate:.1f} per second over the {speech:.2f} s of sound "
            f"(speech has {lo:g}-{hi:g}): check that the text is what is said, or "
            "leave it out",
            where="text",
        )
    if mismatch > MAX_MISMATCH:
        raise InputError(
            f"the transcript does not match the audio (its {n_phones} phones fit "
            f"{mismatch:.2f} nats per frame worse than what the audio sounds like; "
            f"limit {MAX_MISMATCH}): check that the text is what is said, or leave "
            "it out",
            where="text",
        )
    return path


def check_text(text: str) -> None:
    """Refuse (InputError) an empty transcript or one longer than ``MAX_TEXT`` characters."""
    if not isinstance(text, str) or not text.strip():
        raise InputError("the transcript is empty", where="text")
    if len(text) > MAX_TEXT:
        raise InputError(f"the transcript is longer than {MAX_TEXT} characters", where="text")


def align_text(
    x: np.ndarray,
    sr: float,
    text: str,
    *,
    net: FrameNet | None = None,
    calibration: Calibration | None = None,
    fps: float = 100.0,
    lookahead: float | None = None,
    params: Params | None = None,
    table: np.ndarray | None = None,
    where: str = "audio",
    voice: str = "en-us",
) -> LipSync:
    """Lip-sync ``x`` at ``sr`` Hz knowing its transcript ``text`` (English by default).

    Raises:
        InputError: empty text, text without speakable words, or text that does not match the
            audio (more phones than the audio can hold, or a forced reading much worse than the
            free one).
    """
    check_text(text)
    x = validate_pcm(x, sr, where=where)
    return align_features(
        features_of(x, sr),
        len(x) / float(sr),
        text,
        net=net,
        calibration=calibration,
        fps=fps,
        lookahead=lookahead,
        params=params,
        table=table,
        voice=voice,
    )


def align_features(
    f: Features,
    duration: float,
    text: str,
    *,
    net: FrameNet | None = None,
    calibration: Calibration | None = None,
    fps: float = 100.0,
    lookahead: float | None = None,
    params: Params | None = None,
    table: np.ndarray | None = None,
    voice: str = "en-us",
) -> LipSync:
    """``align_text`` from the audio's features ``f`` and its ``duration`` (s), e.g. those of
    ``pipeline.lipsync_file``'s bounded decoding."""
    check_text(text)
    cal = calibration or calibrate(f.energy_db)
    proba = frame_proba(f, cal, net)
    speech = float(np.sum(np.asarray(f.energy_db) >= cal.silence_db)) * f.hop
    path = checked_fit(proba, text, speech, voice)
    onehot = np.eye(len(CLASSES))[path]
    return track_of(
        f,
        onehot,
        duration,
        fps=fps,
        lookahead=lookahead,
        calibration=cal,
        params=params,
        table=table,
    )
