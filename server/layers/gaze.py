"""The gaze layer: both eyes at a target point or the camera, whatever the head does."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .model import EMPTY, Contribution, Envelope, GazeTarget, Role, check_envelope, check_number


@dataclass(frozen=True, eq=False)  # (holds arrays: compared by identity)
class GazeLayer:
    """Eyes turned to ``target`` by ``amount`` × the envelope (replacing the eyes' rotation).

    The mixer computes the eyeball yaw/pitch (FAPs 23-26) from the face's eye centres and neutral
    eye axes under the frame's final head pose (``mix.gaze_faps``), so a turned head is compensated.
    """

    target: GazeTarget = field(default_factory=GazeTarget.camera)
    amount: float = 1.0
    envelope: Envelope = field(default_factory=Envelope)
    role: Role = Role.GAZE
    _held: Contribution = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not isinstance(self.target, GazeTarget):
            raise ValueError("target must be a GazeTarget (a point or a direction)")
        object.__setattr__(self, "amount", check_number("gaze amount", self.amount, 0.0, 1.0))
        check_envelope(self.envelope)
        object.__setattr__(self, "_held", Contribution(gaze=self.target, gaze_weight=self.amount))

    @property
    def end(self) -> float | None:
        return self.envelope.end

    def sample(self, t: float) -> Contribution:
        e = self.envelope(t)
        w = self.amount * e
        if w <= 0.0:
            return EMPTY
        return self._held if e == 1.0 else Contribution(gaze=self.target, gaze_weight=w)


def parse_gaze(text: str) -> GazeTarget:
    """``camera`` or ``x,y,z`` (mesh units, the face's coordinates) as a ``GazeTarget``;
    ValueError saying what is expected otherwise."""
    s = text.strip().lower()
    if s == "camera":
        return GazeTarget.camera()
    parts = s.split(",")
    try:
        xyz = np.array([float(p) for p in parts])
    except ValueError:
        xyz = np.zeros(0)
    if xyz.shape != (3,) or not np.all(np.isfinite(xyz)):
        raise ValueError(f"gaze target {text!r}: expected 'camera' or x,y,z (three numbers)")
    return GazeTarget(point=xyz)
