"""The built-in demo performance: expressions, speech-like visemes and idle motion, as face states.

Idle motion follows what people do at rest: a blink every 2-6 s (about 150 ms closing, 100 ms
closed, 200 ms opening), slow head sway of a few degrees, and gaze shifts (saccades) every 1-3 s.
Everything is a deterministic function of the seed, so a demo can be replayed and tested.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from ..state import FaceState, zero_faps

#: AU per degree (MPEG-4 angle unit = 1e-5 rad).
AU_PER_DEG = np.pi / 180 / 1e-5

#: The script: (seconds, expression id 0-6, visemes spoken during it). Expressions: 1 joy,
#: 2 sadness, 3 anger, 4 fear, 5 disgust, 6 surprise.
SCRIPT: tuple[tuple[float, int, tuple[int, ...]], ...] = (
    (3.0, 1, ()),
    (3.0, 0, (10, 1, 13, 7, 12, 4, 10, 14, 8, 11)),
    (3.0, 6, ()),
    (2.5, 2, ()),
    (3.0, 0, (5, 11, 7, 1, 10, 9, 13, 2, 12, 6)),
    (2.5, 3, ()),
    (2.5, 4, ()),
    (2.5, 5, ()),
)


def _smoothstep(x: np.ndarray | float) -> np.ndarray | float:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _events(rng: np.random.Generator, duration: float, lo: float, hi: float) -> np.ndarray:
    """Event start times (s) with gaps drawn uniformly from [lo, hi)."""
    times, t = [], rng.uniform(lo, hi) / 2
    while t < duration:
        times.append(t)
        t += rng.uniform(lo, hi)
    return np.array(times)


def blink_closure(t: float, starts: np.ndarray) -> float:
    """Eyelid closure 0..1 at time t for blinks starting at ``starts`` (s)."""
    dt = t - starts
    dt = dt[(dt >= 0) & (dt < 0.45)]
    if not len(dt):
        return 0.0
    d = float(dt[-1])
    if d < 0.15:
        return float(_smoothstep(d / 0.15))
    if d < 0.25:
        return 1.0
    return float(1 - _smoothstep((d - 0.25) / 0.2))


def demo_states(
    fps: float = 30.0, *, loops: int | None = None, seed: int = 7
) -> Iterator[FaceState]:
    """Face states of the demo at ``fps``; endless when ``loops`` is None, else that many passes."""
    rng = np.random.default_rng(seed)
    period = sum(s for s, _, _ in SCRIPT)
    blinks = _events(rng, period, 2.0, 6.0)
    saccades = _events(rng, period, 1.0, 3.0)
    gaze = rng.uniform(-1, 1, size=(len(saccades) + 1, 2)) * np.array(
        [8.0, 4.0]
    )  # degrees yaw, pitch
    starts = np.cumsum([0.0] + [s for s, _, _ in SCRIPT])
    n = 0
    while loops is None or n < loops * round(period * fps):
        t = n / fps
        local = t % period
        k = int(np.searchsorted(starts, local, side="right") - 1)
        seg_len, expr, visemes = SCRIPT[k]
        u = (local - starts[k]) / seg_len
        faps = zero_faps()
        # Expressions rise and fall within their segment.
        intensity = (
            int(round(63 * _smoothstep(u / 0.25) * _smoothstep((1 - u) / 0.25))) if expr else 0
        )
        expression = (expr, intensity, 0, 0) if expr else None
        viseme = None
        if visemes:
            pos = u * len(visemes)
            i = min(int(pos), len(visemes) - 1)
            frac = pos - i
            nxt = visemes[i + 1] if i + 1 < len(visemes) else 0
            # Blend towards the next viseme over the last 40 % of each: simple coarticulation.
            blend = 63 if frac < 0.6 else int(round(63 * (1 - _smoothstep((frac - 0.6) / 0.4))))
            viseme = (visemes[i], nxt, blend)
        closure = blink_closure(local, blinks)
        faps[19] = faps[20] = 1024 * closure  # upper lids down by one IRISD0 when closed
        faps[21] = faps[22] = 150 * closure
        # Head sway: incommensurate sines, a few degrees.
        faps[48] = AU_PER_DEG * (
            2.0 * np.sin(2 * np.pi * t / 7.3) + 0.8 * np.sin(2 * np.pi * t / 3.1)
        )
        faps[49] = AU_PER_DEG * (3.0 * np.sin(2 * np.pi * t / 9.7 + 1.0))
        faps[50] = AU_PER_DEG * (1.5 * np.sin(2 * np.pi * t / 11.3 + 2.0))
        # Gaze: hold, then jump to the next target within 60 ms.
        j = int(np.searchsorted(saccades, local, side="right"))
        prev, cur = gaze[max(j - 1, 0)], gaze[j]
        since = local - (saccades[j - 1] if j > 0 else 0.0)
        g = prev + (cur - prev) * _smoothstep(since / 0.06) if j > 0 else cur
        faps[23] = faps[24] = AU_PER_DEG * g[0]
        faps[25] = faps[26] = AU_PER_DEG * g[1]
        yield FaceState(t=t, faps=faps, viseme=viseme, expression=expression)
        n += 1
