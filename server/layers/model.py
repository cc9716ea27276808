"""The layer types: what one layer gives to one frame, its role, its timing, the face it needs.

A session's face is mixed from a **primary** (speech, a FAP stream, mocap: a ``FaceState``) and
any number of **layers**. Each layer is sampled at the frame's media time and gives a
``Contribution``; ``layers.mix`` combines them by the seed's rules (Kshirsagar et al.; Kähler's
"combining is non-trivial" slide, ``research/seed-000-B.md`` §2.2): offsets add, layers of one
role that compete for a FAP are averaged by weight, the mouth keeps the speech's closures, gaze
and head pose override. Units: FAP values in FAPU (angles in AU = 1e-5 rad), times in seconds,
points in the face's mesh units and axes (MPEG-4: +x the face's left, +y up, +z out of the face).
"""

from __future__ import annotations

import enum
import itertools
import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol, TypeVar, runtime_checkable

import numpy as np

from ..mpeg4.highlevel import EXPRESSIONS, VISEMES

_T = TypeVar("_T")
_MISSING = object()

#: Length of a FAP vector: index k = FAP k (0 unused, 1/2 high-level).
N = 69
#: AU (MPEG-4 angle unit, 1e-5 rad) per degree.
AU_PER_DEG = math.pi / 180 / 1e-5


class Role(str, enum.Enum):
    """What a layer is for. Layers of one role compete (averaged by weight where they overlap);
    layers of different roles add. The primary is not a layer: it is ``mix``'s first argument."""

    PRIMARY = "primary"  #: speech, a FAP stream, mocap (a producer's driver)
    EXPRESSION = "expression"  #: expression overlays (amount, envelope)
    IDLE = "idle"  #: blinks, saccades, sway, breathing
    GAZE = "gaze"  #: eyes at a target (overrides eye rotation)
    HEAD = "head"  #: head gestures (nod, shake, tilt) and poses (override the primary's)


#: Face regions: name -> low-level FAP numbers (MPEG-4 FAP groups, the mouth split in jaw and lips).
REGIONS: dict[str, tuple[int, ...]] = {
    "jaw": (3, 14, 15, 18),
    "lips": (4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 16, 17, *range(51, 61)),
    "eyelids": (19, 20, 21, 22),
    "eyes": tuple(range(23, 31)),
    "eyebrows": tuple(range(31, 39)),
    "cheeks": (39, 40, 41, 42),
    "tongue": (43, 44, 45, 46, 47),
    "head": (48, 49, 50),
    "nose": (61, 62, 63, 64),
    "ears": (65, 66, 67, 68),
}
REGIONS["mouth"] = REGIONS["jaw"] + REGIONS["lips"]


def region_mask(regions: Mapping[str, float] | Iterable[str], amount: float = 1.0) -> np.ndarray:
    """``(69,) float64`` per-FAP weights: ``amount`` (times the region's value for a mapping) on
    the FAPs of the named ``REGIONS``, 0 elsewhere. KeyError names an unknown region."""
    w = np.zeros(N)
    items = regions.items() if isinstance(regions, Mapping) else ((r, 1.0) for r in regions)
    for name, value in items:
        if name not in REGIONS:
            raise KeyError(f"unknown face region {name!r}; known: {', '.join(sorted(REGIONS))}")
        w[list(REGIONS[name])] = amount * float(value)
    return w


@dataclass(frozen=True, eq=False)  # (holds arrays: compared by identity)
class GazeTarget:
    """Where the eyes look: a ``point (3,)`` in the face's coordinates (mesh units; the neutral
    face's frame, so a turned head is compensated), or a ``direction (3,)`` (a target at
    infinity, e.g. the camera straight ahead: ``GazeTarget.camera()``). Exactly one is set."""

    point: np.ndarray | None = None
    direction: np.ndarray | None = None

    def __post_init__(self) -> None:
        if (self.point is None) == (self.direction is None):
            raise ValueError("a gaze target is a point or a direction, exactly one of them")
        for name in ("point", "direction"):
            v = getattr(self, name)
            if v is not None:
                v = np.asarray(v, dtype=np.float64).reshape(-1)
                if v.shape != (3,) or not np.all(np.isfinite(v)):
                    raise ValueError(f"gaze {name} must be 3 finite numbers")
                if name == "direction" and not np.linalg.norm(v) > 0:
                    raise ValueError("gaze direction must not be zero")
                object.__setattr__(self, name, v)

    @classmethod
    def camera(cls) -> GazeTarget:
        """Straight ahead (+z), as a camera far in front of the face."""
        return cls(direction=np.array([0.0, 0.0, 1.0]))


@dataclass(frozen=True, eq=False)  # (holds arrays: compared by identity)
class Contribution:
    """What one layer gives to one frame. Every channel is optional; an empty one gives nothing.

    Attributes:
        faps: ``(69,) float64`` low-level FAP offsets (FAPU), added to the primary's.
        amount: scale of ``faps`` and the high-level FAPs (BML's amount; may exceed 1).
        weight: ``float`` or ``(69,)`` per-FAP weight 0..1 of ``faps`` and the high-level FAPs
            (amount × envelope × region mask). Where two layers of one role both weigh on a FAP
            their offsets are averaged by weight (``Σ w·x / max(1, Σ w)``).
        viseme, expression: high-level FAPs 1/2 as in ``FaceState``, expanded to low-level offsets
            with the face's tables and weighted as ``faps``.
        override: ``(69,) float64`` absolute FAP values that replace, after the offsets are added,
            what the FAPs would be (a blink's closed lids), by ``override_weight`` (``float`` or
            ``(69,)``; 0 leaves the FAP alone, 1 replaces it).
        head: ``(3,) float64`` head pose ``(pitch, yaw, roll)`` in AU (FAPs 48, 49, 50) that
            replaces the primary's head (its FAPs or its ``head`` transform) by ``head_weight``;
            head offsets of other layers (sway, nods) still add on top.
        gaze: eyes turned to this target by ``gaze_weight`` (computed last, from the final head pose).
    """

    faps: np.ndarray | None = None
    amount: float = 1.0
    weight: float | np.ndarray = 1.0
    viseme: tuple[int, int, int] | None = None
    expression: tuple[int, int, int, int] | None = None
    override: np.ndarray | None = None
    override_weight: float | np.ndarray = 1.0
    head: np.ndarray | None = None
    head_weight: float = 1.0
    gaze: GazeTarget | None = None
    gaze_weight: float = 1.0


#: A contribution that gives nothing (a layer before its start or after its end).
EMPTY = Contribution()


def check_number(name: str, value: object, lo: float, hi: float) -> float:
    """``value`` as a float if it is a real number (not a bool) within ``[lo, hi]``; ValueError
    naming ``name`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise ValueError(f"{name} must be a number")
    v = float(value)
    if not lo <= v <= hi:  # (NaN fails too)
        raise ValueError(f"{name} must be within [{lo:g}, {hi:g}]")
    return v


def check_envelope(value: object) -> None:
    """ValueError unless ``value`` is an ``Envelope``."""
    if not isinstance(value, Envelope):
        raise ValueError("envelope must be an Envelope (start, attack_peak, relax, end)")


def check_regions(value: object) -> tuple[str, ...] | None:
    """``value`` (None or names of ``REGIONS``) as a tuple; ValueError otherwise."""
    if value is None:
        return None
    if isinstance(value, str) or not isinstance(value, Iterable):
        raise ValueError("regions must be a list of region names")
    names = tuple(value)
    if not all(isinstance(r, str) for r in names):
        raise ValueError("regions must be a list of region names")
    unknown = [r for r in names if r not in REGIONS]
    if unknown:
        raise ValueError(f"unknown face region {unknown[0]!r}; known: {', '.join(sorted(REGIONS))}")
    return names


def smoothstep(x: float) -> float:
    """``3x² − 2x³`` of ``x`` clipped to [0, 1]: a 0 → 1 ease with zero slope at both ends."""
    x = 0.0 if x <= 0.0 else min(1.0, x)
    return x * x * (3.0 - 2.0 * x)


@dataclass(frozen=True)
class Envelope:
    """BML timing of a behaviour (seconds of media time): 0 before ``start``, rising to 1 at
    ``attack_peak``, 1 until ``relax``, falling to 0 at ``end``; ``end=None`` holds for ever.

    A missing ``attack_peak`` is an instant rise at ``start``, a missing ``relax`` an instant fall
    at ``end``; rises and falls ease in and out (``smoothstep``). ``Envelope()`` is always 1.
    """

    start: float = 0.0
    attack_peak: float | None = None
    relax: float | None = None
    end: float | None = None

    def __post_init__(self) -> None:
        for name in ("start", "attack_peak", "relax", "end"):
            v = getattr(self, name)
            if v is not None or name == "start":
                object.__setattr__(self, name, check_number(f"envelope {name}", v, -1e9, 1e9))
        times = [self.start, self.attack_peak, self.relax, self.end]
        given = [v for v in times if v is not None]
        if any(b < a for a, b in itertools.pairwise(given)):
            raise ValueError("envelope times must satisfy start ≤ attack_peak ≤ relax ≤ end")

    def __call__(self, t: float) -> float:
        """The envelope's value 0..1 at media time ``t``."""
        if t < self.start or (self.end is not None and t >= self.end):
            return 0.0
        peak = self.attack_peak
        if peak is not None and t < peak:
            return smoothstep((t - self.start) / (peak - self.start))
        relax = self.relax
        if relax is None or self.end is None or t < relax:
            return 1.0
        return 1.0 - smoothstep((t - relax) / (self.end - relax))


@runtime_checkable
class Layer(Protocol):
    """A source of contributions: ``sample(t)`` is a pure function of the media time ``t`` (s).

    ``role`` decides how it mixes (``Role``); ``end`` is the media time after which it gives
    nothing (None: never ends), so a ``Mixer`` may drop it.
    """

    @property
    def role(self) -> Role: ...

    @property
    def end(self) -> float | None: ...

    def sample(self, t: float) -> Contribution: ...


@dataclass(frozen=True, eq=False)  # (holds arrays: compared by identity)
class Geometry:
    """What mixing needs of the face: eye centres and neutral eye axes (gaze), the head pivot
    (poses given as transforms), the high-level tables (FAP 1/2 expansion).

    Attributes:
        eye_pivots: ``(2, 3)`` left, right eyeball centres (mesh units, neutral face).
        eye_axes: ``(2, 3)`` unit neutral forward axes of the eyeballs (centre → pupil).
        head_pivot: ``(3,)`` the head's rotation centre.
        visemes, expressions: ``(15, 69)`` / ``(7, 69)`` high-level tables (the rig's).
    """

    eye_pivots: np.ndarray = field(default_factory=lambda: np.zeros((2, 3)))
    eye_axes: np.ndarray = field(default_factory=lambda: np.tile([0.0, 0.0, 1.0], (2, 1)))
    head_pivot: np.ndarray = field(default_factory=lambda: np.zeros(3))
    visemes: np.ndarray = field(default_factory=lambda: VISEMES)
    expressions: np.ndarray = field(default_factory=lambda: EXPRESSIONS)
    #: the eyes as Python floats (centre, axis) for the per-frame gaze arithmetic
    eyes: tuple[tuple[tuple[float, ...], tuple[float, ...]], ...] = field(
        init=False, repr=False, compare=False
    )
    #: the head pivot as Python floats
    pivot: tuple[float, ...] = field(init=False, repr=False, compare=False)
    #: per eye ``(cx, cy, cz, ax, ay, az, hypot(ay, az), atan2(az, ay))``: what ``eye_angles``
    #: works out of its centre and axis, once
    eye_consts: tuple[tuple[float, ...], ...] = field(init=False, repr=False, compare=False)
    #: what mixing remembers of this face: high-level FAP expansions ((viseme, expression) ->
    #: (69,)), overlays' offsets and masks (read-only arrays)
    expansions: dict[object, Any] = field(
        init=False, repr=False, compare=False, default_factory=dict
    )

    def __post_init__(self) -> None:
        for name, shape in (("eye_pivots", (2, 3)), ("eye_axes", (2, 3)), ("head_pivot", (3,))):
            v = np.asarray(getattr(self, name), dtype=np.float64)
            if v.shape != shape or not np.all(np.isfinite(v)):
                raise ValueError(f"{name} must be {shape} finite numbers")
            object.__setattr__(self, name, v)
        axes = self.eye_axes / np.linalg.norm(self.eye_axes, axis=1, keepdims=True)
        object.__setattr__(self, "eye_axes", axes)
        eyes = tuple(
            (tuple(map(float, self.eye_pivots[i])), tuple(map(float, axes[i]))) for i in range(2)
        )
        object.__setattr__(self, "eyes", eyes)
        object.__setattr__(self, "pivot", tuple(map(float, self.head_pivot)))
        consts = tuple(
            (*c, ax, ay, az, math.hypot(ay, az), math.atan2(az, ay)) for c, (ax, ay, az) in eyes
        )
        object.__setattr__(self, "eye_consts", consts)

    def remember(self, key: object, make: Callable[[], _T]) -> _T:
        """``make()`` kept in ``expansions`` under ``key`` (the arrays in it made read-only; the
        cache is emptied when it holds 4096 entries), so that it is worked out once per face."""
        hit = self.expansions.get(key, _MISSING)
        if hit is _MISSING:
            hit = make()
            for a in hit if isinstance(hit, tuple) else (hit,):
                if isinstance(a, np.ndarray):
                    a.flags.writeable = False
            if len(self.expansions) >= 4096:
                self.expansions.clear()
            self.expansions[key] = hit
        return hit

    @classmethod
    def of_rig(cls, rig: Any) -> Geometry:
        """The geometry of a ``FapRig`` (its face's pivots and pupils, its tables)."""
        face = rig.face
        pivots = np.array([face.pivot("eye_l"), face.pivot("eye_r")], dtype=np.float64)
        axes = np.tile([0.0, 0.0, 1.0], (2, 1))
        for i, (fp, part) in enumerate((("3.5", "eye_l"), ("3.6", "eye_r"))):
            v = face.feature_points.get(fp)
            if v is not None and v in set(face.part(part).tolist()):
                a = face.vertices[v].astype(np.float64) - pivots[i]
                if np.linalg.norm(a) > 0 and a[2] > 0:
                    axes[i] = a / np.linalg.norm(a)
        return cls(
            eye_pivots=pivots,
            eye_axes=axes,
            head_pivot=np.asarray(face.pivot("head"), dtype=np.float64),
            visemes=np.asarray(rig.visemes, dtype=np.float64),
            expressions=np.asarray(rig.expressions, dtype=np.float64),
        )

    @classmethod
    def of_face(cls, face: Any) -> Geometry:
        """The geometry of a ``Face`` with the default FAP rig."""
        from ..mpeg4.rig import FapRig

        return cls.of_rig(FapRig(face))
