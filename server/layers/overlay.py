"""Expression overlays: a high-level expression or a FAP shape, or a FAP stream, over the primary."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ..state import FaceState
from .model import (
    EMPTY,
    Contribution,
    Envelope,
    Role,
    check_envelope,
    check_number,
    check_regions,
    region_mask,
)


def _weight(regions: tuple[str, ...] | None, w: float) -> float | np.ndarray:
    return w if regions is None else region_mask(regions, w)


@dataclass(frozen=True, eq=False)  # (holds arrays: compared by identity)
class ExpressionLayer:
    """An expression held over the primary with BML timing.

    Attributes:
        expression: MPEG-4 expression id 1-6 (joy, sadness, anger, fear, disgust, surprise; the
            face's table), or 0 with ``faps`` for a shape of one's own.
        faps: ``(69,)`` low-level FAP offsets (FAPU) at full strength, added to the expression's.
        amount: scale of the shape (BML amount; 1 = the table's full expression).
        envelope: when it rises, holds and relaxes (``Envelope``).
        regions: the ``REGIONS`` it acts on (None: all its FAPs).
        role: ``Role.EXPRESSION`` (layers of one role compete).
    """

    expression: int = 0
    faps: np.ndarray | None = None
    amount: float = 1.0
    envelope: Envelope = field(default_factory=Envelope)
    regions: tuple[str, ...] | None = None
    role: Role = Role.EXPRESSION
    _held: Contribution = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if isinstance(self.expression, bool) or not isinstance(self.expression, int | np.integer):
            raise ValueError("expression must be an id 0..6")
        if not 0 <= int(self.expression) <= 6:
            raise ValueError(f"expression id {self.expression} is out of range 0..6")
        object.__setattr__(self, "expression", int(self.expression))
        object.__setattr__(self, "amount", check_number("amount", self.amount, -10.0, 10.0))
        check_envelope(self.envelope)
        if not isinstance(self.role, Role):
            raise ValueError("role must be a Role")
        if self.faps is not None:
            f = np.asarray(self.faps, dtype=np.float64).reshape(-1)
            if f.shape != (69,) or not np.all(np.isfinite(f)):
                raise ValueError("faps must be 69 finite numbers (index k = FAP k)")
            object.__setattr__(self, "faps", f)
        object.__setattr__(self, "regions", check_regions(self.regions))
        object.__setattr__(self, "_held", self._at(1.0))

    @property
    def end(self) -> float | None:
        return self.envelope.end

    def sample(self, t: float) -> Contribution:
        e = self.envelope(t)
        if e <= 0.0:
            return EMPTY
        return self._held if e == 1.0 else self._at(e)

    def _at(self, e: float) -> Contribution:
        """The contribution at envelope ``e`` (at 1, ``_held``: made once, its arrays read-only)."""
        c = Contribution(
            faps=self.faps,
            amount=self.amount,
            weight=_weight(self.regions, e),
            expression=(self.expression, 63, 0, 0) if self.expression else None,
        )
        if isinstance(c.weight, np.ndarray):
            c.weight.flags.writeable = False
        return c


@dataclass(frozen=True, eq=False)  # (holds arrays: compared by identity)
class TrackLayer:
    """A FAP stream (a decoded ``.fap`` file, a recorded performance) played as offsets over the
    primary from ``start``: frame ``i`` at ``start + i / fps`` (nearest frame); nothing outside
    it unless ``loop``.

    Attributes:
        states: the stream's face states (their FAPs, viseme and expression; head transforms and
            controls are not layered).
        fps: frames per second.
        start: media time of frame 0 (s).
        amount, regions, role: as ``ExpressionLayer``; ``envelope``: optional extra timing (None:
            the stream's own extent at full weight).
    """

    states: Sequence[FaceState]
    fps: float
    start: float = 0.0
    amount: float = 1.0
    loop: bool = False
    envelope: Envelope | None = None
    regions: tuple[str, ...] | None = None
    role: Role = Role.EXPRESSION

    def __post_init__(self) -> None:
        if not len(self.states):
            raise ValueError("a track layer needs at least one frame")
        object.__setattr__(self, "states", tuple(self.states))
        object.__setattr__(self, "fps", check_number("fps", self.fps, 1e-3, 1e4))
        object.__setattr__(self, "start", check_number("start", self.start, -1e9, 1e9))
        object.__setattr__(self, "amount", check_number("amount", self.amount, -10.0, 10.0))
        if not isinstance(self.loop, bool):
            raise ValueError("loop must be true or false")
        if self.envelope is not None:
            check_envelope(self.envelope)
        if not isinstance(self.role, Role):
            raise ValueError("role must be a Role")
        object.__setattr__(self, "regions", check_regions(self.regions))

    @property
    def end(self) -> float | None:
        if self.loop:
            return None if self.envelope is None else self.envelope.end
        own = self.start + len(self.states) / self.fps
        return (
            own
            if self.envelope is None or self.envelope.end is None
            else min(own, self.envelope.end)
        )

    def sample(self, t: float) -> Contribution:
        i = int(np.floor((t - self.start) * self.fps + 0.5))
        n = len(self.states)
        if self.loop:
            i %= n
        elif not 0 <= i < n:
            return EMPTY
        e = 1.0 if self.envelope is None else self.envelope(t)
        if e <= 0.0:
            return EMPTY
        s = self.states[i]
        return Contribution(
            faps=np.asarray(s.faps, dtype=np.float64),
            amount=self.amount,
            weight=_weight(self.regions, e),
            viseme=s.viseme,
            expression=s.expression,
        )
