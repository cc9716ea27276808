"""Head layers: nod, shake and tilt gestures (offsets over the head's motion) and held poses."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .model import (
    AU_PER_DEG,
    EMPTY,
    Contribution,
    Envelope,
    N,
    Role,
    check_envelope,
    check_number,
)

#: Gesture -> (FAP moved, amplitude in degrees at amount 1). Nod: pitch down (+), shake: yaw,
#: tilt: roll.
GESTURES: dict[str, tuple[int, float]] = {"nod": (48, 8.0), "shake": (49, 12.0), "tilt": (50, 10.0)}
#: Default duration of one nod or shake cycle (s) when the envelope has no end.
CYCLE = 0.6


@dataclass(frozen=True)
class HeadGesture:
    """A head gesture: ``nod`` (down and back, ``repetitions`` times), ``shake`` (left-right
    cycles) or ``tilt`` (roll held over the envelope), scaled by ``amount`` (1 = 8° nod, 12°
    shake, 10° tilt; negative mirrors). Its FAP offsets add to the head's other motion.

    Nods and shakes run from ``envelope.start`` to ``envelope.end`` (default: ``repetitions`` ×
    0.6 s); a tilt follows the envelope (attack, hold, relax).
    """

    kind: str = "nod"
    amount: float = 1.0
    envelope: Envelope = field(default_factory=Envelope)
    repetitions: int = 1
    role: Role = Role.HEAD

    def __post_init__(self) -> None:
        if not isinstance(self.kind, str) or self.kind not in GESTURES:
            raise ValueError(f"head gesture {self.kind!r}: expected one of {', '.join(GESTURES)}")
        object.__setattr__(self, "amount", check_number("amount", self.amount, -5.0, 5.0))
        check_envelope(self.envelope)
        if isinstance(self.repetitions, bool) or not isinstance(self.repetitions, int):
            raise ValueError("repetitions must be a whole number")
        if not 1 <= self.repetitions <= 100:
            raise ValueError("repetitions must be 1..100")

    @property
    def end(self) -> float | None:
        if self.kind == "tilt" or self.envelope.end is not None:
            return self.envelope.end
        return self.envelope.start + CYCLE * self.repetitions

    def sample(self, t: float) -> Contribution:
        fap, degrees = GESTURES[self.kind]
        start = self.envelope.start
        if self.kind == "tilt":
            shape = self.envelope(t)
        else:
            end = self.end
            assert end is not None
            if not start <= t < end or end <= start:
                return EMPTY
            u = (t - start) / (end - start) * self.repetitions
            shape = (
                float(np.sin(np.pi * u) ** 2)
                if self.kind == "nod"
                else float(np.sin(2 * np.pi * u)) * float(np.sin(np.pi * u / self.repetitions))
            )
        if shape == 0.0:
            return EMPTY
        faps = np.zeros(N)
        faps[fap] = self.amount * degrees * AU_PER_DEG * shape
        return Contribution(faps=faps)


@dataclass(frozen=True)
class HeadPose:
    """A held head pose (degrees: ``pitch`` down +, ``yaw`` to the face's left +, ``roll``) that
    replaces the primary's head by ``amount`` × the envelope; gestures and sway still add."""

    pitch: float = 0.0
    yaw: float = 0.0
    roll: float = 0.0
    amount: float = 1.0
    envelope: Envelope = field(default_factory=Envelope)
    role: Role = Role.HEAD

    def __post_init__(self) -> None:
        for name in ("pitch", "yaw", "roll"):
            v = check_number(f"head {name} (degrees)", getattr(self, name), -90.0, 90.0)
            object.__setattr__(self, name, v)
        object.__setattr__(self, "amount", check_number("head amount", self.amount, 0.0, 1.0))
        check_envelope(self.envelope)

    @property
    def end(self) -> float | None:
        return self.envelope.end

    def sample(self, t: float) -> Contribution:
        w = self.amount * self.envelope(t)
        if w <= 0.0:
            return EMPTY
        return Contribution(
            head=np.array([self.pitch, self.yaw, self.roll]) * AU_PER_DEG, head_weight=w
        )
