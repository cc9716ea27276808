"""The idle layer: what a face does when nobody directs it. Blinks, saccades between fixations,
a slow head sway and breathing, as a pure, seeded function of time.

- **Blinks**: about ``blink_rate`` a minute (default 17; people at rest blink 10-25 times a
  minute), Poisson-like: intervals are a refractory minimum plus an exponential wait. Each blink
  closes in 100-150 ms, stays closed 20-60 ms and opens about twice as slowly (200-320 ms). The
  lids are *set* closed by the closure (an override), so a blink closes over any expression.
- **Saccades and fixations**: fixations of 0.3-3 s (log-normal, median 0.9 s) on points a few
  degrees around straight ahead; a saccade's duration follows the main sequence,
  ``21 ms + 2.2 ms/°`` of amplitude.
- **Sway**: incommensurate sines of a few degrees on head pitch, yaw and roll.
- **Breathing**: about 14 breaths a minute: a fraction of a degree of head pitch and a slight
  flare of the nostrils.

Events are drawn once for ``horizon`` seconds and repeat after it.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from .model import AU_PER_DEG, Contribution, N, Role, check_number, smoothstep

#: Closed lids: upper lids down one IRISD0 (tangent to the iris -> closed), lower lids up a little.
CLOSED_LIDS = np.zeros(N)
CLOSED_LIDS[[19, 20]] = 1024.0
CLOSED_LIDS[[21, 22]] = 150.0
LID_MASK = np.zeros(N)
LID_MASK[19:23] = 1.0
#: Sway (head pitch, yaw, roll: degrees of sines of 7.3, 3.1, 9.7 and 11.3 s periods) and
#: breathing (4.3 s): the sines' rates (1/s), phases and the sway's mix of them.
_RATES = 1.0 / np.array([7.3, 3.1, 9.7, 11.3, 4.3])
_PHASES = np.array([0.0, 0.0, 1.0, 2.0, 0.0])
_SWAY = np.array([[2.0, 0.0, 0.0], [0.8, 0.0, 0.0], [0.0, 3.0, 0.0], [0.0, 0.0, 1.5]])
_SINES = tuple(zip(_RATES.tolist(), _PHASES.tolist()))
_SWAY.flags.writeable = False
_SWAY_ROWS = _SWAY.tolist()
#: The FAPs ``sample`` sets: the eyes' yaw l, r, pitch l, r; the head; the nostrils l, r.
_MOVED = np.array([23, 24, 25, 26, 48, 49, 50, 61, 62])


def blink_times(
    rng: np.random.Generator, horizon: float, rate: float, refractory: float
) -> np.ndarray:
    """``(B, 4)`` blinks in ``[0, horizon)``: start, closing, closed, opening durations (s)."""
    wait = max(60.0 / rate - refractory, 1e-3)
    n = int(horizon / max(refractory, 0.05)) + 16  # more than can fit
    close = rng.uniform(0.10, 0.15, n)
    closed = rng.uniform(0.02, 0.06, n)
    opening = close * rng.uniform(1.8, 2.4, n)
    waits = rng.exponential(wait, n)
    step = np.maximum(refractory, close + closed + opening) + waits
    starts = np.concatenate([[waits[-1]], waits[-1] + np.cumsum(step[:-1])])
    keep = starts < horizon
    return np.stack([starts, close, closed, opening], axis=1)[keep]


def blink_closure(t: float, blinks: Sequence[Sequence[float]], starts: Sequence[float]) -> float:
    """Lid closure 0..1 at ``t`` for ``blinks`` (rows of ``blink_times``) starting at ``starts``."""
    i = bisect.bisect_right(starts, t) - 1
    if i < 0:
        return 0.0
    s, close, closed, opening = blinks[i]
    d = t - s
    if d < close:
        return smoothstep(d / close)
    d -= close
    if d < closed:
        return 1.0
    d -= closed
    if d < opening:
        return 1.0 - smoothstep(d / opening)
    return 0.0


def fixations(
    rng: np.random.Generator, horizon: float, yaw_deg: float, pitch_deg: float
) -> np.ndarray:
    """``(S, 4)`` fixations in ``[0, horizon)``: start (s), yaw, pitch (degrees), and the saccade
    duration (s) that leads to it (main sequence: 21 ms + 2.2 ms per degree)."""
    n = int(horizon / 0.3) + 2
    durations = np.clip(rng.lognormal(np.log(0.9), 0.6, n), 0.3, 3.0)
    spread = np.array([yaw_deg, pitch_deg])
    points = np.clip(rng.normal(0.0, 1.0, (n, 2)) * spread, -2.5 * spread, 2.5 * spread)
    points[0] = 0.0
    starts = np.concatenate([[0.0], np.cumsum(durations[:-1])])
    amplitude = np.hypot(*np.diff(points, axis=0, prepend=points[:1]).T)
    rows = np.column_stack([starts, points, 0.021 + 0.0022 * amplitude])
    rows[0, 3] = 0.0
    return rows[starts < horizon]


@dataclass(frozen=True)
class IdleLayer:
    """Idle motion, deterministic by ``seed`` (see the module docstring).

    Attributes:
        seed: the random seed of the events.
        amount: scale of the saccades, sway and breathing (0..1; blinks are whole).
        blink_rate: blinks a minute (mean); refractory: least time (s) from one blink to the next.
        blinks, saccades, sway, breathing: which parts run.
        gaze_spread: standard deviation (degrees yaw, pitch) of the fixation points.
        horizon: seconds of events drawn; they repeat after it.
    """

    seed: int = 0
    amount: float = 1.0
    blink_rate: float = 17.0
    refractory: float = 1.0
    blinks: bool = True
    saccades: bool = True
    sway: bool = True
    breathing: bool = True
    gaze_spread: tuple[float, float] = (4.0, 2.0)
    horizon: float = 1800.0
    role: Role = Role.IDLE
    _blinks: list[list[float]] = field(init=False, repr=False, compare=False)
    _blink_starts: list[float] = field(init=False, repr=False, compare=False)
    _fix: list[list[float]] = field(init=False, repr=False, compare=False)
    _fix_starts: list[float] = field(init=False, repr=False, compare=False)
    _scale: float = field(init=False, repr=False, compare=False)
    _factors: tuple[float, float, float] = field(init=False, repr=False, compare=False)
    #: ``[lo, hi)`` (s, within the horizon) where the lids were last found open between two
    #: blinks (replaced whole: a thread reads the old span or the new one, both right)
    _open: tuple[float, float] = field(init=False, repr=False, compare=False)
    #: ``[lo, hi)`` (s) and the fixation's yaw and pitch where the eyes were last found holding
    #: it, past its saccade (as ``_open``)
    _hold: tuple[float, float, float, float] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if isinstance(self.seed, bool) or not isinstance(self.seed, int):
            raise ValueError("seed must be a whole number")
        rate = check_number("blink_rate (a minute)", self.blink_rate, 1.0, 60.0)
        check_number("refractory", self.refractory, 0.0, 60.0 / rate - 1e-3)
        check_number("idle amount", self.amount, 0.0, 1.0)
        check_number("horizon", self.horizon, 10.0, 86400.0)
        for name in ("blinks", "saccades", "sway", "breathing"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be true or false")
        spread = tuple(self.gaze_spread)
        if len(spread) != 2:
            raise ValueError("gaze_spread is (yaw, pitch) degrees")
        for v in spread:
            check_number("gaze_spread (degrees)", v, 0.0, 15.0)
        object.__setattr__(self, "gaze_spread", (float(spread[0]), float(spread[1])))
        rng = np.random.default_rng([int(self.seed) & 0xFFFFFFFF, 18])
        b = blink_times(rng, self.horizon, self.blink_rate, self.refractory)
        f = fixations(rng, self.horizon, *self.gaze_spread)
        object.__setattr__(self, "_blinks", b.tolist())
        object.__setattr__(self, "_blink_starts", b[:, 0].tolist())
        object.__setattr__(self, "_fix", f.tolist())
        object.__setattr__(self, "_fix_starts", f[:, 0].tolist())
        object.__setattr__(self, "_open", (0.0, 0.0))
        object.__setattr__(self, "_hold", (0.0, 0.0, 0.0, 0.0))
        a = self.amount * AU_PER_DEG
        object.__setattr__(self, "_scale", a)
        sway, breath = float(self.sway), float(self.breathing)
        object.__setattr__(
            self, "_factors", (a * sway, a * 0.3 * breath, self.amount * 20.0 * breath)
        )

    @property
    def end(self) -> float | None:
        return None

    def closure(self, t: float) -> float:
        """Lid closure 0..1 at ``t`` (s)."""
        local = t % self.horizon
        lo, hi = self._open
        if lo <= local < hi:  # (between the same two blinks as last time: open)
            return 0.0
        c = blink_closure(local, self._blinks, self._blink_starts)
        if c == 0.0:  # remember the open span ``local`` is in: the frames after it are there too
            starts = self._blink_starts
            i = bisect.bisect_right(starts, local)
            if i > 0:
                s, close, closed, opening = self._blinks[i - 1]
                lo = s + close + closed + opening
            else:
                lo = 0.0
            hi = starts[i] if i < len(starts) else self.horizon
            if lo <= local < hi:
                object.__setattr__(self, "_open", (lo, hi))
        return c

    def gaze(self, t: float) -> tuple[float, float]:
        """Eye ``(yaw, pitch)`` in degrees at ``t`` (s), before ``amount``."""
        local = t % self.horizon
        lo, hi, yaw, pitch = self._hold
        if lo <= local < hi:  # (in the fixation found last time, past its saccade)
            return yaw, pitch
        f = self._fix
        starts = self._fix_starts
        j = bisect.bisect_right(starts, local) - 1
        cur = f[j]
        if j > 0 and local - cur[0] < cur[3]:
            u = smoothstep((local - cur[0]) / cur[3])
            prev = f[j - 1]
            return prev[1] + (cur[1] - prev[1]) * u, prev[2] + (cur[2] - prev[2]) * u
        lo = cur[0] + cur[3] if j > 0 else cur[0]
        hi = starts[j + 1] if j + 1 < len(starts) else self.horizon
        if lo <= local < hi:
            object.__setattr__(self, "_hold", (lo, hi, cur[1], cur[2]))
        return cur[1], cur[2]

    def row(self, t: float) -> list[float]:
        """``sample_many``'s row at ``t`` (s): the eyes' yaw and pitch (AU, ``amount`` applied; 0
        without saccades), the lids' closure (0 without blinks), and what scales the sines: the
        sway's (AU), the breath's head pitch (AU) and the nostrils' flare (0 for a part off)."""
        a = self._scale
        yaw = pitch = c = 0.0
        if self.saccades:
            yaw, pitch = self.gaze(t)
            yaw, pitch = a * yaw, a * pitch
        if self.blinks:
            c = self.closure(t)
        return [yaw, pitch, c, *self._factors]

    def sample(self, t: float) -> Contribution:
        """One frame in Python floats (cheaper than ``sample_many`` for one)."""
        a = self._scale
        yaw = pitch = h48 = h49 = h50 = nose = 0.0
        if self.saccades:
            yaw, pitch = self.gaze(t)
            yaw, pitch = a * yaw, a * pitch
        s = [math.sin(2 * math.pi * t * r + p) for r, p in _SINES]
        if self.sway:  # (S @ _SWAY)
            w = _SWAY_ROWS
            h48 = a * (w[0][0] * s[0] + w[1][0] * s[1])
            h49 = a * w[2][1] * s[2]
            h50 = a * w[3][2] * s[3]
        if self.breathing:
            b = s[4]
            h48 += a * 0.3 * b
            nose = self.amount * 20.0 * max(b, 0.0)
        faps = np.zeros(N)
        faps.put(_MOVED, (yaw, yaw, pitch, pitch, h48, h49, h50, nose, nose))
        c = self.closure(t) if self.blinks else 0.0
        if c > 0.0:
            return Contribution(faps=faps, override=CLOSED_LIDS, override_weight=c * LID_MASK)
        return Contribution(faps=faps)

    @staticmethod
    def sample_many(layers: Sequence[IdleLayer], ts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``layers[k]`` at ``ts[k]`` (s), all at once: the FAP offsets ``(K, 69)`` (saccades,
        sway, breathing) and the lid closure ``(K,)`` 0..1 (a blink: ``CLOSED_LIDS`` by it).
        The events (fixations, blinks) are looked up row by row, the sines computed together."""
        K = len(layers)
        flat: list[float] = []
        for x, t in zip(layers, ts.tolist()):
            flat += x.row(t)
        V = np.array(flat).reshape(K, 6)
        S = np.sin(np.multiply.outer(2 * math.pi * ts, _RATES) + _PHASES)  # (K, 5)
        faps = np.zeros((K, N))
        faps[:, 23:25] = V[:, 0:1]
        faps[:, 25:27] = V[:, 1:2]
        faps[:, 48:51] = V[:, 3:4] * (S[:, :4] @ _SWAY)
        b = S[:, 4:5]
        faps[:, 48:49] += V[:, 4:5] * b
        faps[:, 61:63] = V[:, 5:6] * np.maximum(b, 0.0)
        return faps, V[:, 2]
