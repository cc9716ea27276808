"""Projection of retargeted marker displacements to MPEG-4 FAPs (Kshirsagar et al. §4).

A marker that sits on a feature point gives every translation FAP of that point: its displacement
(face units, face axes, head removed) along the FAP's + direction, divided by the FAP's unit measured
on the face (FAPU). The jaw marker gives FAP 3 (open_jaw) even when it is not tied to FP 2.1, so
that the rigid jaw, teeth and tongue follow the chin. The head pose gives FAPs 48-50 in AU.
"""

from __future__ import annotations

import numpy as np

from ..faces.face import Face
from ..state import zero_faps
from .stabilise import euler_from_matrix

__all__ = ["FapProjection"]

#: FAP kinds that are translations of a feature point.
_TRANSLATIONS = ("move", "jaw")


class FapProjection:
    """Linear map from ``(K, 3)`` control displacements (+ head rotation) to the ``(69,)`` FAP vector.

    Args:
        face: the target face (its feature points and FAPU).
        placement: the control markers' vertices (``layout.Placement``); a marker counts as being on
            a feature point when its vertex is that point's vertex.
        fapu: ``measure_fapu(face)``.
        jaw: index of the jaw marker among the controls (FAP 3 from it), or None.
    """

    def __init__(self, face: Face, placement, fapu: dict[str, float], jaw: int | None = None):
        from ..mpeg4.tables import FAPS

        vert_to_fp: dict[int, str] = {}
        for fp, v in face.feature_points.items():
            vert_to_fp.setdefault(int(v), fp)
        rows, cols, numbers = [], [], []
        self.covered: dict[int, str] = {}  # FAP number -> marker name
        for k, v in enumerate(np.asarray(placement.vertices).tolist()):
            fp = vert_to_fp.get(v)
            if fp is None:
                continue
            for f in FAPS:
                if f.kind in _TRANSLATIONS and fp in f.fps and f.number not in self.covered:
                    rows.append(f.vector / fapu[f.unit])
                    cols.append(k)
                    numbers.append(f.number)
                    self.covered[f.number] = placement.names[k]
        if jaw is not None and 3 not in self.covered:
            f3 = FAPS[2]
            rows.append(f3.vector / fapu[f3.unit])
            cols.append(jaw)
            numbers.append(3)
            self.covered[3] = placement.names[jaw]
        self.rows = np.array(rows, dtype=np.float64).reshape(-1, 3)
        self.cols = np.array(cols, dtype=np.int64)
        self.numbers = np.array(numbers, dtype=np.int64)
        self.au = fapu["AU"]

    def faps(self, d: np.ndarray, head_r: np.ndarray | None = None) -> np.ndarray:
        """``(69,) float64`` FAPs from ``(K, 3)`` displacements in face units and an optional
        ``(3, 3)`` head rotation in face axes."""
        out = zero_faps()
        if len(self.cols):
            out[self.numbers] = (np.asarray(d, dtype=np.float64)[self.cols] * self.rows).sum(axis=1)
            out[3] = max(
                out[3], 0.0
            )  # open_jaw is one-sided: a jaw does not close past its neutral
        if head_r is not None:
            out[48:51] = euler_from_matrix(head_r) / self.au
        return out
