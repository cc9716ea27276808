"""Visual classes for scoring, and the tables that map phones and visemes onto them.

Ground truth: phone alignments → classes at 100 frames/s. facecast's output (MPEG-4 visemes)
→ classes with ``VISEME_CLASS``.
"""

from __future__ import annotations

import numpy as np

from facecast.server.audio.classify import CLASSES  # the network's classes, in its order

C = {name: i for i, name in enumerate(CLASSES)}

ARPABET = {
    "sil": "",
    "closed": "P B M",
    "labiodental": "F V",
    "sibilant": "S Z SH ZH CH JH",
    "open": "AA AE AH AW AY",
    "mid": "EH EY ER",
    "spread": "IH IY Y",
    "round": "AO OW OY",
    "narrow-round": "UH UW W",
    "other": "T D N L K G R HH NG TH DH",
}
ARPA_CLASS = {p: C[c] for c, ps in ARPABET.items() for p in ps.split()}
ARPA_CLASS.update({"PT": C["closed"]})  # bobby_phones: "PT" = the p-t cluster of "ripped"
SILENCE_LABELS = {"", "SIL", "SP", "sil", "sp", "<sil>", "+NSN+", "+SPN+", "NSN", "SPN"}

#: IPA (mary.TextGrid) → class; length marks are stripped first. œ (open-mid front rounded) is
#: scored as "mid", ə as "open" (ARPAbet AH0).
IPA = {
    "closed": "p b m",
    "labiodental": "f v",
    "sibilant": "s z ʃ ʒ tʃ dʒ ʧ ʤ",
    "open": "a ɑ æ ʌ ə ɐ aɪ aʊ",
    "mid": "e ɛ eɪ ɝ ɚ ɜ œ ø",
    "spread": "i ɪ j",
    "round": "ɔ o oʊ ɔɪ ɒ",
    "narrow-round": "u ʊ w",
    "other": "t d n l k g r ɹ ɾ h ŋ θ ð ɫ",
}
IPA_CLASS = {p: C[c] for c, ps in IPA.items() for p in ps.split()}

#: MPEG-4 viseme id → class (0 sil, 1 PP, 2 FF, 3 TH, 4 DD, 5 kk, 6 CH, 7 SS, 8 nn, 9 RR,
#: 10 aa, 11 E, 12 ih, 13 oh, 14 ou).
VISEME_CLASS = np.array(
    [
        C["sil"],
        C["closed"],
        C["labiodental"],
        C["other"],
        C["other"],
        C["other"],
        C["sibilant"],
        C["sibilant"],
        C["other"],
        C["other"],
        C["open"],
        C["mid"],
        C["spread"],
        C["round"],
        C["narrow-round"],
    ]
)

#: Lips apart? (for the open/closed accuracy): sil, closed and labiodental are "closed".
OPEN = np.array([c not in ("sil", "closed", "labiodental") for c in CLASSES])
#: Typical mouth opening per class (0 = closed, 1 = wide), for the onset-lag cross-correlation.
OPENING = np.array([0.0, 0.0, 0.1, 0.2, 1.0, 0.7, 0.4, 0.7, 0.4, 0.4])


def phone_class(label: str, alphabet: str) -> int | None:
    """Class of one phone label; None if the label is unknown (frame excluded from scoring)."""
    lab = label.strip()
    if lab in SILENCE_LABELS:
        return C["sil"]
    if alphabet == "arpabet":
        return ARPA_CLASS.get(lab.rstrip("012").upper())
    lab = lab.replace("ː", "").replace("ˈ", "").replace("ˌ", "")
    return IPA_CLASS.get(lab)


def frames_from_intervals(
    intervals: list[tuple[float, float, str]], alphabet: str, duration: float, fps: float = 100.0
) -> np.ndarray:
    """``(T,)`` class per frame at ``i / fps`` (-1 = unknown label); time outside intervals = sil."""
    n = int(np.floor(duration * fps + 1e-9)) + 1
    out = np.full(n, C["sil"], dtype=np.int64)
    t = np.arange(n) / fps
    for start, end, label in intervals:
        c = phone_class(label, alphabet)
        out[(t >= start) & (t < end)] = -1 if c is None else c
    return out
