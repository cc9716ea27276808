"""The built-in demo performance: expressions and speech-like visemes over the idle layer, as face states.

The script (``SCRIPT``) gives the expressions and visemes; the idle motion (blinks, saccades and
fixations, head sway, breathing) is the idle layer (``server/layers/idle.py``) mixed over it.
Everything is a deterministic function of the seed, so a demo can be replayed and tested.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from ..layers import IdleLayer, mix
from ..state import FaceState

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


def demo_states(
    fps: float = 30.0, *, loops: int | None = None, seed: int = 7
) -> Iterator[FaceState]:
    """Face states of the demo at ``fps``; endless when ``loops`` is None, else that many passes."""
    idle = IdleLayer(seed=seed)
    period = sum(s for s, _, _ in SCRIPT)
    starts = np.cumsum([0.0] + [s for s, _, _ in SCRIPT])
    n = 0
    while loops is None or n < loops * round(period * fps):
        t = n / fps
        local = t % period
        k = int(np.searchsorted(starts, local, side="right") - 1)
        seg_len, expr, visemes = SCRIPT[k]
        u = (local - starts[k]) / seg_len
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
        script = FaceState(t=t, viseme=viseme, expression=expression)
        yield mix(script, [idle], t, closures=False)
        n += 1
