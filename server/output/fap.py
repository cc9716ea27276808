"""An ``Animation`` as an ASCII ``.fap`` stream (the FAPs of its states; explicit controls are dropped)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ...protocol.fap_file import FapFile, FapFrame, write_fap
from ..state import Animation
from .atomic import write_bytes_atomic

log = logging.getLogger(__name__)


def animation_to_fap(animation: Animation, *, name: str = "facecast") -> FapFile:
    """FAP file of ``animation``: integer values (rounded), one mask for all frames holding every
    low-level FAP that is non-zero in some frame; FAP 1/2 set in the frames that have them."""
    faps = np.array([s.faps for s in animation.states], dtype=np.float64).reshape(
        len(animation.states), -1
    )
    if any(s.controls is not None for s in animation.states):
        log.warning(
            "%s: explicit control displacements cannot be written as FAPs; only FAPs are kept",
            animation.source or "animation",
        )
    used = [k for k in range(3, 69) if len(faps) and np.any(np.rint(faps[:, k]) != 0)]
    fps = animation.fps if float(animation.fps) != int(animation.fps) else int(animation.fps)
    frames = []
    for i, s in enumerate(animation.states):
        vis = (*map(int, s.viseme[:3]), 0) if s.viseme is not None else None
        expr = (*map(int, s.expression[:4]), 0, 0) if s.expression is not None else None
        frames.append(
            FapFrame.build(
                i, {k: int(np.rint(faps[i, k])) for k in used}, viseme=vis, expression=expr
            )
        )
    return FapFile(name=name, fps=fps, frames=tuple(frames))


def write_fap_file(path: str | Path, animation: Animation, *, name: str | None = None) -> None:
    """Write ``animation`` as ``.fap`` to ``path`` atomically."""
    f = animation_to_fap(animation, name=name or Path(path).stem.strip() or "facecast")
    write_bytes_atomic(path, write_fap(f).encode("utf-8"))
