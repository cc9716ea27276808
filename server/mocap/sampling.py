"""Farthest-point sampling: spreading markers (or pins) evenly over a set of points."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def farthest_points(
    points: np.ndarray,
    k: int,
    *,
    start: int | None = None,
    seed_points: np.ndarray | None = None,
    weights: np.ndarray | None = None,
    until: float | None = None,
) -> np.ndarray:
    """Indices of up to ``k`` of ``points (N, 3)``, each the farthest from those chosen before.

    The first is ``start`` if given; else the point farthest from ``seed_points`` (kept away from
    too), or from the points' mean. ``weights (N,)`` scale the distances (denser where high);
    sampling stops early once no point is farther than ``until``.
    """
    if k <= 0 or not len(points):
        return np.zeros(0, dtype=np.int64)
    w = np.ones(len(points)) if weights is None else np.asarray(weights, dtype=np.float64)
    chosen: list[int] = []
    if start is not None:
        chosen.append(int(start))
        dist = np.linalg.norm(points - points[start], axis=1) * w
    elif seed_points is not None and len(seed_points):
        dist = cKDTree(seed_points).query(points)[0] * w
    else:
        dist = np.linalg.norm(points - points.mean(axis=0), axis=1) * w  # the outermost first
    while len(chosen) < min(k, len(points)):
        i = int(np.argmax(dist))
        if until is not None and dist[i] <= until:
            break
        chosen.append(i)
        dist = np.minimum(dist, np.linalg.norm(points - points[i], axis=1) * w)
    return np.asarray(chosen, dtype=np.int64)
