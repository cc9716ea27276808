"""High-level FAPs: the 15 visemes (FAP 1) and 7 expressions (FAP 2) as low-level FAP vectors.

The standard names the visemes and expressions but leaves their shapes to the face model (its FAT).
These default shapes are facecast's own, written as low-level FAP values (in FAPU, at full
strength) for a generic face; a face can replace them (``Face.visemes`` / ``Face.expressions``
attributes, ``(15, 69)`` / ``(7, 69)`` arrays, or the ``FapRig`` arguments).

Blending (``docs/mpeg4-reference.md`` §4.3):

- FAP 1: ``select1 · blend/63 + select2 · (1 − blend/63)``;
- FAP 2: ``select1 · intensity1/63 + select2 · intensity2/63`` (added, not complementary).

High-level and low-level FAPs of the same frame are added.
"""

from __future__ import annotations

import numpy as np

N = 69  # FAP vector length: index k = FAP k


def _vec(**faps: float) -> np.ndarray:
    v = np.zeros(N)
    for name, value in faps.items():
        v[int(name[1:])] = value
    return v


def mouth(
    jaw: float = 0,
    top: float = 0,
    bottom: float = 0,
    width: float = 0,
    push: float = 0,
    corners: float = 0,
) -> np.ndarray:
    """A mouth shape: ``jaw`` open (MNS), upper lip ``top`` up / lower lip ``bottom`` down (MNS,
    positive = lips part), ``width`` corner stretch outward (MW), ``push`` lips forward (MNS),
    ``corners`` lip corners up (MNS); inner and outer contours move together, the lip midpoints
    (2.6-2.9, 8.5-8.8) by 0.8 of the middle."""
    v = np.zeros(N)
    v[3] = jaw
    v[[4, 51]] = -top
    v[[8, 9, 55, 56]] = -0.8 * top
    v[[5, 52]] = -bottom
    v[[10, 11, 57, 58]] = -0.8 * bottom
    v[[6, 7, 53, 54]] = width
    v[[16, 17]] = push
    v[[12, 13, 59, 60]] = corners
    return v


#: Viseme names in id order (= Meta/OVR viseme order).
VISEME_NAMES: tuple[str, ...] = (
    "sil",
    "PP",
    "FF",
    "TH",
    "DD",
    "kk",
    "CH",
    "SS",
    "nn",
    "RR",
    "aa",
    "E",
    "ih",
    "oh",
    "ou",
)
#: Expression names in id order.
EXPRESSION_NAMES: tuple[str, ...] = (
    "neutral",
    "joy",
    "sadness",
    "anger",
    "fear",
    "disgust",
    "surprise",
)

#: ``(15, 69) float64``: viseme id -> low-level FAPs (FAPU) at full strength.
VISEMES: np.ndarray = np.stack(
    [
        np.zeros(N),  # sil
        mouth(top=-40, bottom=-60, push=30),  # PP: lips pressed
        mouth(jaw=80, top=40, bottom=-30, push=-120) + _vec(f16=-150),  # FF: lower lip under teeth
        mouth(jaw=150, top=40, bottom=150) + _vec(f44=100, f45=300),  # TH: tongue tip out
        mouth(jaw=150, top=40, bottom=150) + _vec(f44=250),  # DD: tip up to the ridge
        mouth(jaw=200, top=50, bottom=200) + _vec(f46=200),  # kk: tongue back up
        mouth(jaw=120, top=80, bottom=120, width=-80, push=150),  # CH: lips rounded forward
        mouth(jaw=60, top=40, bottom=60, width=40),  # SS: teeth close, spread
        mouth(jaw=150, top=40, bottom=150) + _vec(f44=250),  # nn
        mouth(jaw=120, top=40, bottom=120, width=-60, push=100),  # RR
        mouth(jaw=450, top=80, bottom=450, corners=-40),  # aa: wide open
        mouth(jaw=250, top=80, bottom=250, width=80),  # E
        mouth(jaw=150, top=60, bottom=150, width=100, corners=30),  # ih: spread
        mouth(jaw=350, top=100, bottom=350, width=-120, push=120),  # oh: round open
        mouth(jaw=200, top=60, bottom=200, width=-200, push=200),  # ou: round, protruded
    ]
)


def _brows(inner: float = 0, middle: float = 0, outer: float = 0, squeeze: float = 0) -> np.ndarray:
    v = np.zeros(N)
    v[[31, 32]], v[[33, 34]], v[[35, 36]], v[[37, 38]] = inner, middle, outer, squeeze
    return v


def _lids(upper: float = 0, lower: float = 0) -> np.ndarray:
    """Upper lids down by ``upper`` (IRISD; negative = wider), lower lids up by ``lower``."""
    v = np.zeros(N)
    v[[19, 20]], v[[21, 22]] = upper, lower
    return v


#: ``(7, 69) float64``: expression id -> low-level FAPs (FAPU) at intensity 63.
EXPRESSIONS: np.ndarray = np.stack(
    [
        np.zeros(N),  # neutral
        mouth(jaw=100, top=60, bottom=120, width=120, corners=200)
        + _brows(30, 30, 30)
        + _lids(0, 150)
        + _vec(f41=200, f42=200),  # joy
        mouth(bottom=-50, corners=-150)
        + _brows(200, 60, -60, 60)
        + _lids(250)
        + _vec(f18=100),  # sadness
        mouth(top=-60, bottom=-60, corners=-50)
        + _brows(-200, -120, -40, 150)
        + _lids(-150, 100)
        + _vec(f61=60, f62=60),  # anger
        mouth(jaw=150, top=20, bottom=200, width=100)
        + _brows(300, 220, 120, 100)
        + _lids(-250),  # fear
        mouth(top=200, bottom=-60, corners=-80, push=0)
        + _brows(-100, -80)
        + _lids(0, 150)
        + _vec(f61=80, f62=80, f63=100, f16=100),  # disgust
        mouth(jaw=500, top=80, bottom=500, width=-60)
        + _brows(350, 400, 300)
        + _lids(-300),  # surprise
    ]
)


def viseme_faps(
    select1: int, select2: int, blend: float, table: np.ndarray = VISEMES
) -> np.ndarray:
    """FAP 1: ``(69,)`` low-level FAPs of ``select1 · blend/63 + select2 · (1 − blend/63)``."""
    w = float(blend) / 63.0
    return table[int(select1)] * w + table[int(select2)] * (1.0 - w)


def expression_faps(
    select1: int,
    intensity1: float,
    select2: int,
    intensity2: float,
    table: np.ndarray = EXPRESSIONS,
) -> np.ndarray:
    """FAP 2: ``(69,)`` low-level FAPs of ``select1 · intensity1/63 + select2 · intensity2/63``."""
    return table[int(select1)] * (float(intensity1) / 63.0) + table[int(select2)] * (
        float(intensity2) / 63.0
    )


def expand(
    state, visemes: np.ndarray = VISEMES, expressions: np.ndarray = EXPRESSIONS
) -> np.ndarray:
    """``(69,) float64`` low-level FAPs of a ``FaceState``: its FAPs plus its viseme and expression."""
    faps = np.array(state.faps, dtype=np.float64).reshape(-1)
    if faps.shape != (N,):
        raise ValueError(f"FaceState.faps must have shape (69,), not {faps.shape}")
    faps[:3] = 0.0
    if state.viseme is not None:
        s1, s2, blend = state.viseme[:3]
        faps += viseme_faps(_check(s1, 14, "viseme"), _check(s2, 14, "viseme"), blend, visemes)
    if state.expression is not None:
        s1, i1, s2, i2 = state.expression[:4]
        faps += expression_faps(
            _check(s1, 6, "expression"), i1, _check(s2, 6, "expression"), i2, expressions
        )
    return faps


def _check(select: int, maximum: int, what: str) -> int:
    s = int(select)
    if not 0 <= s <= maximum:
        from ..errors import InputError

        raise InputError(f"{what} id {s} is out of range 0..{maximum}")
    return s


__all__ = [
    "EXPRESSIONS",
    "EXPRESSION_NAMES",
    "VISEMES",
    "VISEME_NAMES",
    "expand",
    "expression_faps",
    "mouth",
    "viseme_faps",
]
