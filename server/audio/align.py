"""Lip-sync with a known transcript: the text's phones, forced onto the audio.

espeak-ng turns the text into IPA phones (``espeak-ng -q --ipa --sep=_``); each phone becomes the
visual class the frame network knows (``classify.CLASSES``), every phone lasting at least
``MIN_FRAMES`` frames, with optional silence between words; a Viterbi search over the network's
class posteriors (divided by the class priors, hybrid style) finds the timing. Text that does not
fit the audio is refused: when its phones would be spoken implausibly fast or slow over the
audio's sound (``PHONE_RATE``), or when the forced path scores far below the network's own best
reading under the same duration rules (``MAX_MISMATCH`` nats per speech frame, with an allowance
for short texts), the text is not what was said. Live streams follow a transcript known ahead
frame by frame (``TextFollower``).
"""

from __future__ import annotations

import functools
import logging
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

log = logging.getLogger(__name__)
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
#: Refuse the text when the forced path scores more than this far below the free reading, nats
#: per speech frame, less ``MISMATCH_SLACK / sqrt(phones)`` (a short text's free reading has few
#: frames to average over: the 38 real transcripts' own gap is 1.3-1.8 on 6-15 phones, 0.5-1.0 on
#: long ones). Chosen on speakers held out (bench/lipsync/folds.py: each recording scored by a
#: network that never heard its speaker): the largest own-transcript value + 0.05, so no
#: correct transcript of those 38 is refused; in the bench each fold's limit comes from its
#: training speakers alone. Re-chosen whenever the network is re-shipped: session 18's network
#: (per-speaker running normalisation) 1.16 + 0.05 (pocketsphinx-cards/004; another recording's
#: transcript refused 206 of 418 times, 168 at the previous 1.36); session 16's 1.31 + 0.05.
MAX_MISMATCH = 1.21
#: Length allowance of the mismatch (nats per frame times sqrt(phones)), see ``MAX_MISMATCH``.
MISMATCH_SLACK = 2.0
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


def mismatch_excess(mismatch: float, n_phones: int) -> float:
    """The mismatch (nats per speech frame) judged against ``MAX_MISMATCH``: less the length
    allowance ``MISMATCH_SLACK / sqrt(n_phones)``."""
    return float(mismatch) - MISMATCH_SLACK / np.sqrt(max(int(n_phones), 1))


def checked_fit(
    proba: np.ndarray,
    text: str,
    speech: float,
    voice: str = "en-us",
    max_mismatch: float | None = None,
) -> np.ndarray:
    """``text_fit``'s class per frame, or InputError when the text does not match the audio:
    ``speech`` seconds of sound (frames above the silence threshold) hold fewer than
    ``PHONE_RATE[0]`` or more than ``PHONE_RATE[1]`` of its phones per second, or the forced
    reading is worse than the free one by more than ``max_mismatch`` (default ``MAX_MISMATCH``)
    after the length allowance (``mismatch_excess``)."""
    limit = MAX_MISMATCH if max_mismatch is None else float(max_mismatch)
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
    excess = mismatch_excess(mismatch, n_phones)
    if excess > limit:
        raise InputError(
            f"the transcript does not match the audio (its {n_phones} phones fit "
            f"{mismatch:.2f} nats per frame worse than what the audio sounds like, "
            f"{excess:.2f} after the allowance for their number; limit {limit:g}): check "
            "that the text is what is said, or leave it out",
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
    max_mismatch: float | None = None,
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
        max_mismatch=max_mismatch,
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
    max_mismatch: float | None = None,
) -> LipSync:
    """``align_text`` from the audio's features ``f`` and its ``duration`` (s), e.g. those of
    ``pipeline.lipsync_file``'s bounded decoding."""
    check_text(text)
    cal = calibration or calibrate(f.energy_db)
    proba = frame_proba(f, cal, net)
    speech = float(np.sum(np.asarray(f.energy_db) >= cal.silence_db)) * f.hop
    path = checked_fit(proba, text, speech, voice, max_mismatch)
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


class TextFollower:
    """``forced_path`` one frame at a time, for live streams whose transcript is known ahead.

    Each pushed frame advances the Viterbi scores over the text's states; the class of frame
    t is decided ``lag`` frames later (fixed-lag: the best state at t + lag, traced back), so the
    text constrains the classes within the stream's look-ahead. Emissions are log probabilities
    over the mean of the probabilities so far, started with ``prior`` (the network's mean output,
    ``FrameNet.mean_proba``) counted as ``PRIOR_FRAMES`` frames (the batch path divides by the
    whole utterance's mean). Past the text's last phone the frames take the network's own class (speech that goes
    on beyond the text still moves the mouth). The text is dropped (``active`` False, the
    network's own classes from then on) when, after ``CHECK_FRAMES`` frames of speech, the best
    forced reading scores ``MAX_MISMATCH`` nats per speech frame below the free reading
    (``free_score``), as the batch check refuses such a text.
    """

    #: Speech frames (10 ms) on the text's path before the mismatch is judged.
    CHECK_FRAMES = 200

    #: Frames the prior ``prior`` counts for in the running mean (speakers held out,
    #: bench/lipsync/folds.py: chosen among 1, 100, 300, 1000 and 1e6 on each fold's training
    #: speakers, 100 in four folds of five; without it 0.583 / 0.495 on the transcribed
    #: recordings, with it 0.653 / 0.548).
    PRIOR_FRAMES = 100
    #: States more than this many nats below the best are dropped (their paths cannot recover
    #: within a stream's few frames of look-ahead; the bench's results are the same without).
    BEAM = 100.0

    def __init__(
        self,
        text: str,
        *,
        lag: int = 1,
        voice: str = "en-us",
        prior: np.ndarray | None = None,
    ) -> None:
        check_text(text)
        words = text_phones(text, voice)
        if not words:
            raise InputError("the transcript has no speakable words", where="text")
        self.cls, opt = _states(words)
        S = len(self.cls)
        #: phones up to and including each state's
        self.phones_before = np.cumsum(~opt) // MIN_FRAMES
        nxt = np.append(self.cls[1:], -1)
        same_next = (self.cls == nxt) & ~opt & np.append(~opt[1:], False)
        self.loop = ~same_next
        self.skip_ok = np.zeros(S, dtype=bool)
        self.skip_ok[2:] = opt[1:-1]
        self.lag = max(0, int(lag))
        self.active = True
        self.score: np.ndarray | None = None
        #: back pointers of the undecided frames: (first state, predecessor of each state)
        self.back: list[tuple[int, np.ndarray]] = []
        self.lo, self.hi = 0, 0  # the live band of states
        self.pending: list[int] = []  # the network's own class of the undecided frames
        self.psum = np.zeros(len(CLASSES))
        self.n = 0
        if prior is not None:  # the network's mean output, worth PRIOR_FRAMES frames
            self.psum = np.asarray(prior, dtype=np.float64) * self.PRIOR_FRAMES
            self.n = self.PRIOR_FRAMES
        self.free = np.full((len(CLASSES), MIN_FRAMES), -1e18)
        self.speech = 0  # frames whose best state is a phone

    def _step(self, p: np.ndarray) -> np.ndarray:
        """Advance by one frame of class probabilities ``p (10,)``; the state scores now.

        Only the states within ``BEAM`` nats of the best are kept alive (a long text's far
        states cost nothing): the scores are computed over the live band ``[lo, hi)`` and the
        two states a frame can advance into."""
        self.psum += p
        self.n += 1
        logp = np.log(np.maximum(p, 1e-8)) - np.log(np.maximum(self.psum / self.n, 1e-4))
        neg = -1e18
        S = len(self.cls)
        if self.score is None:
            self.score = np.full(S, neg)
            a, b = 0, min(2, S)
            self.score[a:b] = logp[self.cls[a:b]]
            self.free[:, 0] = logp
            back = np.arange(a, b)
        else:
            a, b = self.lo, min(S, self.hi + 2)
            s = self.score[a:b]  # states below a are dead: no predecessor from there
            stay = np.where(self.loop[a:b], s, neg)
            step = np.concatenate(([neg], s[:-1]))
            jump = np.where(self.skip_ok[a:b], np.concatenate(([neg, neg], s[:-2]))[: b - a], neg)
            best = np.maximum(np.maximum(stay, step), jump)
            idx = np.arange(a, b)
            back = np.where(best == stay, idx, np.where(best == step, idx - 1, idx - 2))
            self.score[a:b] = best + logp[self.cls[a:b]]
            f = np.empty_like(self.free)
            f[:, 0] = self.free[:, -1].max()
            f[:, 1:] = self.free[:, :-1]
            f[:, -1] = np.maximum(f[:, -1], self.free[:, -1])
            self.free = f + logp[:, None]
        band = self.score[a:b]
        alive = np.flatnonzero(band >= band.max() - self.BEAM)
        band[: alive[0]] = neg
        band[alive[-1] + 1 :] = neg
        self.lo, self.hi = a + int(alive[0]), a + int(alive[-1]) + 1
        self.back.append((a, back))
        self.pending.append(int(np.argmax(p)))
        return self.score

    def _decide(self, n: int) -> list[int]:
        """Classes of the ``n`` oldest undecided frames, traced back from the best state now."""
        assert self.score is not None
        s = int(np.argmax(self.score))
        states = [s]
        for a, back in reversed(self.back[1:]):
            s = int(back[s - a])
            states.append(s)
        states.reverse()  # states of the undecided frames, oldest first
        last = len(self.cls) - 1
        out = [
            own if (st == last or not self.active) else int(self.cls[st])
            for st, own in zip(states[:n], self.pending[:n])
        ]
        del self.back[:n], self.pending[:n]
        return out

    def push(self, proba: np.ndarray) -> np.ndarray:
        """Feed class probabilities ``(T, 10)`` of the next frames; return the classes of the
        frames now decided (all but the last ``lag``), oldest first."""
        out: list[int] = []
        for p in np.asarray(proba, dtype=np.float64):
            score = self._step(p)
            best = int(np.argmax(score))
            if self.cls[best] != C["sil"]:
                self.speech += 1
            if self.active and self.speech >= self.CHECK_FRAMES:
                mismatch = mismatch_excess(
                    (self.free.max() - score[best]) / self.speech,
                    max(1, int(self.phones_before[best])),
                )
                if mismatch > MAX_MISMATCH:
                    self.active = False
                    log.warning(
                        "the live transcript does not match the audio (%.2f nats per frame "
                        "worse than what it sounds like after the allowance for its length; limit %s): "
                        "following the audio alone",
                        mismatch,
                        MAX_MISMATCH,
                    )
            if len(self.pending) > self.lag:
                out += self._decide(len(self.pending) - self.lag)
        return np.array(out, dtype=np.int64)

    def flush(self) -> np.ndarray:
        """The classes of every undecided frame (end of stream); the text position is kept."""
        if not self.pending:
            return np.zeros(0, dtype=np.int64)
        return np.array(self._decide(len(self.pending)), dtype=np.int64)
