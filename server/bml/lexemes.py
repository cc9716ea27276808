"""Face lexemes and FACS action units as low-level FAP shapes (FAPU, at BML amount 1).

facecast's own table, written with the same generic face in mind as ``mpeg4.highlevel``'s
expressions (of whose sizes these are): odd FAPs are the face's left, even its right. The six
MPEG-4 expressions are not here: they are FAP 2 (``EXPRESSION_IDS``), so a face's own expression
table applies.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

import numpy as np

from ...protocol.bml import EXPRESSION_LEXEMES, FACE_LEXEMES, FACS_UNITS
from ..mpeg4.highlevel import EXPRESSION_NAMES, N, mouth

__all__ = ["EXPRESSION_IDS", "FACS", "LEXEMES", "face_shape"]

#: Expression lexeme -> MPEG-4 expression id (FAP 2); SMILE is joy.
EXPRESSION_IDS: Mapping[str, int] = MappingProxyType(
    {**{name: EXPRESSION_NAMES.index(name.lower()) for name in EXPRESSION_LEXEMES}, "SMILE": 1}
)


def _f(**faps: float) -> np.ndarray:
    """``(69,)`` FAPs from ``f12=150``-style keywords (a tuple of numbers: ``f31_32=...`` sets both)."""
    v = np.zeros(N)
    for name, value in faps.items():
        for k in name[1:].split("_"):
            v[int(k)] = value
    return v


_CORNERS_L, _CORNERS_R = "f12_59", "f13_60"
#: Lexeme -> FAP shape at amount 1 (expressions: ``EXPRESSION_IDS``).
LEXEMES: Mapping[str, np.ndarray] = MappingProxyType(
    {
        "OBLIQUE_BROWS": _f(f31_32=200, f33_34=60, f35_36=-60, f37_38=60),
        "RAISE_BROWS": _f(f31_32=200, f33_34=220, f35_36=180),
        "RAISE_LEFT_BROW": _f(f31=200, f33=220, f35=180),
        "RAISE_RIGHT_BROW": _f(f32=200, f34=220, f36=180),
        "LOWER_BROWS": _f(f31_32=-180, f33_34=-120, f35_36=-40, f37_38=120),
        "LOWER_LEFT_BROW": _f(f31=-180, f33=-120, f35=-40, f37=120),
        "LOWER_RIGHT_BROW": _f(f32=-180, f34=-120, f36=-40, f38=120),
        "LOWER_MOUTH_CORNERS": _f(f12_13_59_60=-150),
        "LOWER_LEFT_MOUTH_CORNER": _f(**{_CORNERS_L: -150}),
        "LOWER_RIGHT_MOUTH_CORNER": _f(**{_CORNERS_R: -150}),
        "RAISE_MOUTH_CORNERS": _f(f12_13_59_60=180, f6_7_53_54=60),
        "RAISE_LEFT_MOUTH_CORNER": _f(f12_59=180, f6_53=60),
        "RAISE_RIGHT_MOUTH_CORNER": _f(f13_60=180, f7_54=60),
        "OPEN_MOUTH": mouth(jaw=350, top=80, bottom=350),
        "OPEN_LIPS": mouth(top=80, bottom=100),
        "WIDEN_EYES": _f(f19_20=-300),
        "CLOSE_EYES": _f(f19_20=1024, f21_22=100),
        "FROWN": _f(f31_32=-150, f33_34=-100, f37_38=150, f12_13_59_60=-100),
    }
)

#: FACS action unit -> FAP shape at amount 1, ``(left, right)`` halves summed for both sides.
FACS: Mapping[int, tuple[np.ndarray, np.ndarray]] = MappingProxyType(
    {
        1: (_f(f31=200), _f(f32=200)),  # inner brow raiser
        2: (_f(f35=200), _f(f36=200)),  # outer brow raiser
        4: (_f(f31=-150, f33=-100, f37=120), _f(f32=-150, f34=-100, f38=120)),  # brow lowerer
        5: (_f(f19=-300), _f(f20=-300)),  # upper lid raiser
        6: (_f(f41=200, f21=150), _f(f42=200, f22=150)),  # cheek raiser
        7: (_f(f21=200), _f(f22=200)),  # lid tightener
        9: (_f(f61=100), _f(f62=100)),  # nose wrinkler
        10: (_f(f8=-150, f55=-150) + _f(f4_51=-75), _f(f9=-150, f56=-150) + _f(f4_51=-75)),
        12: (_f(f12_59=180, f6_53=80), _f(f13_60=180, f7_54=80)),  # lip corner puller
        15: (_f(f12_59=-150), _f(f13_60=-150)),  # lip corner depressor
        17: (_f(f5_52=-40, f18=-60), _f(f5_52=-40, f18=-60)),  # chin raiser (halves)
        20: (_f(f6_53=150), _f(f7_54=150)),  # lip stretcher
        25: (mouth(top=50, bottom=60) / 2, mouth(top=50, bottom=60) / 2),  # lips part
        26: (mouth(jaw=300, bottom=200) / 2, mouth(jaw=300, bottom=200) / 2),  # jaw drop
        43: (_f(f19=1024, f21=100), _f(f20=1024, f22=100)),  # eyes closed
        45: (_f(f19=1024, f21=100), _f(f20=1024, f22=100)),  # blink (held: eyes closed)
    }
)

assert set(LEXEMES) | set(EXPRESSION_IDS) == set(FACE_LEXEMES), "protocol.bml's lexeme list"
assert set(FACS) == set(FACS_UNITS), "protocol.bml's FACS unit list"


def face_shape(
    lexeme: str | None, au: int | None, side: str = "BOTH"
) -> tuple[int, np.ndarray | None]:
    """``(expression id or 0, FAP shape (69,) or None)`` of a face lexeme or FACS unit on ``side``."""
    if au is not None:
        left, right = FACS[au]
        return 0, (left if side == "LEFT" else right if side == "RIGHT" else left + right)
    if lexeme is None:
        raise KeyError("a face needs a lexeme or a FACS unit")
    if lexeme in EXPRESSION_IDS:
        return EXPRESSION_IDS[lexeme], None
    return 0, LEXEMES[lexeme].copy()
