"""A scheduled BML performance as face layers, and rendered into an ``Animation``.

The speeches' lip-sync is the primary (each recording from its speech's start; the mouth rests
elsewhere); every other behaviour is a layer of ``server.layers`` with its sync points as its
envelope: a face lexeme an ``ExpressionLayer`` (an MPEG-4 expression through FAP 2, or a FAP shape
of ``lexemes``), a gaze a ``GazeLayer`` (plus a ``HeadPose`` turned ``HEAD_SHARE`` of the way to
the target when its influence is HEAD or NECK), a head lexeme a ``HeadGesture``. ``layers.mix``
combines them per frame by the seed's rules (the speech keeps its lip closures).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ...protocol.bml import Face, Gaze, Head, Speech
from ..layers import (
    Envelope,
    ExpressionLayer,
    GazeLayer,
    GazeTarget,
    Geometry,
    HeadGesture,
    HeadPose,
    IdleLayer,
    Layer,
    mix_states,
)
from ..state import Animation, FaceState
from .lexemes import face_shape
from .schedule import Performance, Timed

__all__ = ["HEAD_SHARE", "SpeechTrack", "gaze_target", "performance_layers", "render_performance"]

#: Part of a gaze's turn the head takes when the gaze's influence is HEAD or NECK.
HEAD_SHARE = 0.7
#: offsetDirection -> (x, y) in the face's axes (+x the face's left, +y up): the character's own.
_DIRECTIONS: Mapping[str, tuple[float, float]] = {
    "RIGHT": (-1.0, 0.0),
    "LEFT": (1.0, 0.0),
    "UP": (0.0, 1.0),
    "DOWN": (0.0, -1.0),
    "UPRIGHT": (-math.sqrt(0.5), math.sqrt(0.5)),
    "UPLEFT": (math.sqrt(0.5), math.sqrt(0.5)),
    "DOWNRIGHT": (-math.sqrt(0.5), -math.sqrt(0.5)),
    "DOWNLEFT": (math.sqrt(0.5), -math.sqrt(0.5)),
}


@dataclass(frozen=True)
class SpeechTrack:
    """A speech's mouth: ``states`` (lip-sync face states at ``fps``, from the recording's start)
    played from ``start`` (s of the performance)."""

    start: float
    fps: float
    states: Sequence[FaceState]

    def at(self, t: float) -> FaceState | None:
        """The state at performance time ``t`` (nearest frame), None outside the recording."""
        i = int(math.floor((t - self.start) * self.fps + 0.5))
        return self.states[i] if 0 <= i < len(self.states) else None


def _envelope(t: Timed, peak: str) -> Envelope:
    x = t.times
    return Envelope(start=x["start"], attack_peak=x[peak], relax=x["relax"], end=x["end"])


def gaze_target(g: Gaze) -> GazeTarget:
    """The gaze's target: the point, or the camera (straight ahead, the face's +z) turned by the
    offset angle towards the offset direction."""
    if g.point is not None:
        return GazeTarget(point=np.array(g.point, dtype=np.float64))
    a = math.radians(g.offset_angle)
    dx, dy = _DIRECTIONS[g.offset_direction]
    return GazeTarget(direction=np.array([math.sin(a) * dx, math.sin(a) * dy, math.cos(a)]))


def _head_towards(target: GazeTarget, geometry: Geometry) -> tuple[float, float]:
    """``(pitch, yaw)`` degrees that turn the head's forward (+z) to ``target``."""
    if target.direction is not None:
        d = target.direction
    else:
        assert target.point is not None
        d = target.point - geometry.head_pivot
    x, y, z = (float(v) for v in d)
    yaw = math.degrees(math.atan2(x, z))
    pitch = -math.degrees(math.atan2(y, math.hypot(x, z)))
    return max(-90.0, min(90.0, pitch)), max(-90.0, min(90.0, yaw))


def performance_layers(perf: Performance, geometry: Geometry | None = None) -> list[Layer]:
    """The layers of every behaviour but speech, in document order."""
    geometry = geometry or Geometry()
    out: list[Layer] = []
    for t in perf.timed:
        b = t.behaviour
        if isinstance(b, Face):
            expression, faps = face_shape(b.lexeme, b.au, b.side)
            out.append(
                ExpressionLayer(
                    expression=expression,
                    faps=faps,
                    amount=b.amount,
                    envelope=_envelope(t, "attackPeak"),
                )
            )
        elif isinstance(b, Gaze):
            target = gaze_target(b)
            env = _envelope(t, "ready")
            out.append(GazeLayer(target=target, envelope=env))
            if b.influence in ("HEAD", "NECK"):
                pitch, yaw = _head_towards(target, geometry)
                out.append(HeadPose(pitch=pitch * HEAD_SHARE, yaw=yaw * HEAD_SHARE, envelope=env))
        elif isinstance(b, Head):
            if b.lexeme == "TILT":
                env = Envelope(
                    start=t.start, attack_peak=t.times["ready"], relax=t.times["relax"], end=t.end
                )
            else:
                env = Envelope(start=t.start, end=t.end)
            out.append(
                HeadGesture(
                    kind=b.lexeme.lower(), amount=b.amount, envelope=env, repetitions=b.repetition
                )
            )
    return out


def render_performance(
    perf: Performance,
    speech: Mapping[str, Sequence[FaceState]],
    fps: float,
    *,
    geometry: Geometry | None = None,
    idle: bool = False,
    layers: Sequence[Layer] = (),
    source: str = "",
) -> Animation:
    """One mixed ``FaceState`` per frame of ``perf`` (its duration, at least one frame).

    Args:
        speech: each speech's lip-sync states at ``fps`` (by id), from its recording's start.
        geometry: the face's (``Geometry.of_face``), for gaze and head turns; default: generic.
        idle: add the idle layer (blinks, saccades, sway, breathing; deterministic).
        layers: more layers (``render --idle``, ``--layer``, ``--gaze``), mixed with the
            performance's own in one mix: its gaze then looks past the idle sway, its head
            gestures add to it.
    """
    geometry = geometry or Geometry()
    tracks = [
        SpeechTrack(t.start, fps, speech[t.behaviour.id])
        for t in perf.timed
        if isinstance(t.behaviour, Speech)
    ]
    own = performance_layers(perf, geometry) + list(layers)
    if idle:
        own.append(IdleLayer())
    n = int(math.floor(perf.duration * fps + 1e-9)) + 1
    bases = []
    for i in range(n):
        t = i / fps
        primary = next((s for s in (tr.at(t) for tr in tracks) if s is not None), None)
        bases.append(
            FaceState(t=t)
            if primary is None
            else FaceState(t=t, faps=primary.faps, viseme=primary.viseme)
        )
    states = mix_states(bases, own, geometry=geometry)
    return Animation(fps=float(fps), states=states, source=source)
