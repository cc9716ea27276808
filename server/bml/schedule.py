"""Resolving a BML block's sync references to times: a ``Performance`` (pure, no I/O).

Behaviours are resolved in topological order of their references (a behaviour after every one it
refers to); a reference to an unknown behaviour or sync point, to the behaviour itself, or a cycle
is refused with the line and element. Each behaviour's constrained points are then completed from
its kind's default timing (``DEFAULTS``, seconds from its start):

- **faces, gazes, tilts** (an envelope): the points before the first constraint and after the last
  keep their default distances to it; between two constraints they keep their default distance to
  the nearer one, scaled down when the span is shorter than the default one;
- **nods, shakes** (evenly spaced strokes: every point is ``start + f·duration``): one constraint
  places the default duration, two set start and duration; more must agree;
- **speech** (rigid: its recording's duration, its marks where the transcript's words are): one
  constraint places it.

Unconstrained behaviours start with the block (0 s); a completed point that falls before 0 is
moved to 0 (a constraint before 0 is refused). Speeches may not overlap (one voice). Times are
seconds from the block's start.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

from ...protocol.bml import Behaviour, BmlBlock, BmlError, Head, Speech, SyncRef

__all__ = ["CYCLE", "DEFAULTS", "Performance", "SpeechTiming", "Timed", "schedule"]

#: Seconds of one nod or shake stroke (the head layer's cycle).
CYCLE = 0.6
#: Default offsets (s) of each sync point from the start, per kind (heads: ``head_defaults``).
DEFAULTS: Mapping[str, Mapping[str, float]] = MappingProxyType(
    {
        "face": {"start": 0.0, "attackPeak": 0.3, "relax": 1.7, "end": 2.0},
        "gaze": {"start": 0.0, "ready": 0.3, "relax": 1.7, "end": 2.0},
        "tilt": {
            "start": 0.0,
            "ready": 0.3,
            "strokeStart": 0.3,
            "stroke": 0.3,
            "strokeEnd": 1.2,
            "relax": 1.2,
            "end": 1.5,
        },
    }
)
#: Two times closer than this (s) agree.
TOLERANCE = 1e-3


@dataclass(frozen=True)
class SpeechTiming:
    """A speech's timing from its recording: ``duration`` (s) and each text mark's time from the
    speech's start (s)."""

    duration: float
    marks: Mapping[str, float]


@dataclass(frozen=True)
class Timed:
    """A behaviour and the time (s from the block's start) of each of its sync points."""

    behaviour: Behaviour
    times: Mapping[str, float]

    @property
    def start(self) -> float:
        return self.times["start"]

    @property
    def end(self) -> float:
        return self.times["end"]


@dataclass(frozen=True)
class Performance:
    """A scheduled block: ``timed`` behaviours in document order, ``duration`` (s: the last end)."""

    block: BmlBlock
    timed: tuple[Timed, ...]
    duration: float

    def __getitem__(self, behaviour_id: str) -> Timed:
        for t in self.timed:
            if t.behaviour.id == behaviour_id:
                return t
        raise KeyError(behaviour_id)


def head_defaults(head: Head) -> dict[str, float]:
    """A nod's or shake's points as fractions ``f`` of its duration (start + f·duration); a
    tilt's default offsets (s). ``stroke`` is the first stroke's peak, ``strokeEnd`` the last's."""
    if head.lexeme == "TILT":
        return dict(DEFAULTS["tilt"])
    n = head.repetition
    return {
        "start": 0.0,
        "ready": 0.0,
        "strokeStart": 0.0,
        "stroke": 0.5 / n,
        "strokeEnd": (n - 0.5) / n,
        "relax": 1.0,
        "end": 1.0,
    }


def _linear_head(b: Behaviour) -> bool:
    return isinstance(b, Head) and b.lexeme != "TILT"


def _err(b: Behaviour, reason: str, where: str) -> BmlError:
    return BmlError(reason, line=b.line, element=f'{b.element} id="{b.id}"', where=where)


def _order(block: BmlBlock, where: str) -> list[Behaviour]:
    """The behaviours, each after those it refers to; BmlError for unknown ids, self references
    and cycles."""
    for b in block.behaviours:
        for point, ref in b.sync.items():
            if ref.ref is None:
                continue
            if ref.ref == b.id:
                raise _err(
                    b,
                    f"{point}={ref} refers to the behaviour itself; give its time from another "
                    "behaviour or in seconds",
                    where,
                )
            if ref.ref not in block.by_id:
                ids = ", ".join(x.id for x in block.behaviours if x.id != b.id) or "none"
                raise _err(
                    b,
                    f"{point}={ref} refers to {ref.ref!r}, which no behaviour has; ids: {ids}",
                    where,
                )
    done: list[Behaviour] = []
    state: dict[str, int] = {}  # 1: in progress, 2: done

    def visit(b: Behaviour, path: list[str]) -> None:
        # iterative depth is bounded by MAX_BEHAVIOURS (512): recursion is fine
        if state.get(b.id) == 2:
            return
        if state.get(b.id) == 1:
            cycle = path[path.index(b.id) :] + [b.id]
            raise _err(b, f"sync references form a cycle: {' -> '.join(cycle)}", where)
        state[b.id] = 1
        for ref in b.sync.values():
            if ref.ref is not None:
                visit(block.by_id[ref.ref], [*path, b.id])
        state[b.id] = 2
        done.append(b)

    for b in block.behaviours:
        visit(b, [])
    return done


def _resolve(
    ref: SyncRef, times: Mapping[str, Mapping[str, float]], block: BmlBlock
) -> float | str:
    """The time of ``ref`` (its behaviour already resolved), or why it has none."""
    if ref.ref is None:
        return ref.offset
    target = times[ref.ref]
    if ref.point not in target:
        other = block.by_id[ref.ref]
        return (
            f"{ref.ref} ({other.element}) has no sync point {ref.point!r}; it has "
            f"{', '.join(other.points())}"
        )
    return target[ref.point] + ref.offset


def _envelope(
    points: tuple[str, ...], d: Mapping[str, float], known: dict[str, float]
) -> dict[str, float]:
    """Complete ``known`` times: outside the constraints at default distances, between two at the
    default distance to the nearer one (scaled when the span is short)."""
    idx = [i for i, p in enumerate(points) if p in known]
    out = dict(known)
    for i, p in enumerate(points):
        if p in known:
            continue
        before = [j for j in idx if j < i]
        after = [j for j in idx if j > i]
        if not after:
            a = points[before[-1]]
            out[p] = known[a] + d[p] - d[a]
        elif not before:
            b = points[after[0]]
            out[p] = known[b] - (d[b] - d[p])
        else:
            a, b = points[before[-1]], points[after[0]]
            span, default = known[b] - known[a], d[b] - d[a]
            if default <= 0:
                out[p] = known[a]
            elif span < default:
                out[p] = known[a] + (d[p] - d[a]) * span / default
            elif d[p] - d[a] <= d[b] - d[p]:
                out[p] = known[a] + d[p] - d[a]
            else:
                out[p] = known[b] - (d[b] - d[p])
    return out


def _linear(
    b: Behaviour,
    f: Mapping[str, float],
    known: dict[str, float],
    duration: float,
    where: str,
    what: str,
    *,
    stretch: bool = True,
) -> dict[str, float]:
    """Points at ``start + f[p]·duration``: one constraint places the default ``duration``, two with
    different ``f`` set start and duration (unless not ``stretch``); the rest must agree."""
    items = sorted(known.items(), key=lambda kv: f[kv[0]])
    p0, t0 = items[0]
    start = t0 - f[p0] * duration
    second = next(((p, t) for p, t in items[1:] if f[p] - f[p0] > 1e-9), None) if stretch else None
    if second is not None:
        p1, t1 = second
        duration = (t1 - t0) / (f[p1] - f[p0])
        if duration <= 0:
            raise _err(b, f"{p1} ({t1:.3f} s) must come after {p0} ({t0:.3f} s)", where)
        start = t0 - f[p0] * duration
    out = {p: start + fp * duration for p, fp in f.items()}
    for p, t in known.items():
        if abs(out[p] - t) > TOLERANCE:
            raise _err(
                b,
                f"sync points {', '.join(known)} cannot all hold: {what}; constrain "
                + ("one of them" if what.startswith("its timing") else "at most two"),
                where,
            )
    return out


def _complete(
    b: Behaviour, known: dict[str, float], speech: Mapping[str, SpeechTiming], where: str
) -> dict[str, float]:
    if isinstance(b, Speech):
        timing = speech.get(b.id)
        if timing is None:  # the caller's bug, not the client's
            raise KeyError(f"no timing for speech {b.id!r}")
        f = {"start": 0.0, **{m.id: timing.marks[m.id] for m in b.marks}, "end": timing.duration}
        fixed = {p: v / max(timing.duration, 1e-9) for p, v in f.items()}
        if not known:
            known = {"start": 0.0}
        return _linear(
            b,
            fixed,
            known,
            max(timing.duration, 1e-9),
            where,
            f"its timing comes from its recording ({timing.duration:.2f} s)",
            stretch=False,
        )
    if isinstance(b, Head) and _linear_head(b):
        f = head_defaults(b)
        if not known:
            known = {"start": 0.0}
        return _linear(
            b, f, known, CYCLE * b.repetition, where, "a nod's or shake's strokes are evenly spaced"
        )
    d = head_defaults(b) if isinstance(b, Head) else DEFAULTS[b.kind]
    if not known:
        known = {"start": 0.0}
    return _envelope(b.points(), d, known)


def schedule(
    block: BmlBlock, speech: Mapping[str, SpeechTiming] | None = None, *, where: str = ""
) -> Performance:
    """Resolve ``block``'s sync references to times.

    Args:
        speech: each speech behaviour's ``SpeechTiming`` (by id), from its recording.
        where: the document's name for messages.
    Raises:
        BmlError: an unknown behaviour or sync point, a self reference, a cycle, sync points out of
            order or that cannot all hold, a time before the block's start; naming line and element.
    """
    speech = speech or {}
    times: dict[str, dict[str, float]] = {}
    for b in _order(block, where):
        known: dict[str, float] = {}
        for point, ref in b.sync.items():
            if point not in b.points():
                raise _err(b, f"has no sync point {point!r}; it has {', '.join(b.points())}", where)
            t = _resolve(ref, times, block)
            if isinstance(t, str):
                raise _err(b, f"{point}={ref}: {t}", where)
            if t < -TOLERANCE:
                raise _err(b, f"{point}={ref} falls at {t:.3f} s, before the block's start", where)
            known[point] = max(t, 0.0)
        points = b.points()
        given = [p for p in points if p in known]
        for p, q in itertools.pairwise(given):
            if known[q] < known[p] - TOLERANCE:
                raise _err(
                    b,
                    f"{q} ({known[q]:.3f} s) comes before {p} ({known[p]:.3f} s); sync points "
                    f"go in the order {', '.join(points)}",
                    where,
                )
        full = _complete(b, known, speech, where)
        if full["start"] < -TOLERANCE and (isinstance(b, Speech) or _linear_head(b)):
            raise _err(
                b,
                f"would start at {full['start']:.3f} s, before the block's start (its sync points "
                "are a fixed distance apart); constrain a later point or add an offset",
                where,
            )
        times[b.id] = {p: max(0.0, t) for p, t in full.items()}
    timed = tuple(Timed(b, MappingProxyType(times[b.id])) for b in block.behaviours)
    speeches = sorted((t for t in timed if isinstance(t.behaviour, Speech)), key=lambda t: t.start)
    for first, then in itertools.pairwise(speeches):
        if then.start < first.end - TOLERANCE:
            raise _err(
                then.behaviour,
                f"starts at {then.start:.3f} s, while {first.behaviour.id} speaks "
                f"({first.start:.3f}-{first.end:.3f} s); one voice speaks at a time: start it at "
                f"'{first.behaviour.id}:end'",
                where,
            )
    return Performance(block, timed, max((t.end for t in timed), default=0.0))
