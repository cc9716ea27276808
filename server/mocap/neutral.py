"""Where a take's neutral is (``--neutral-frame auto``): the frame whose markers look most like the
target face at rest.

A layout that ties markers to the face (``{"vertex": id}`` or ``{"fp": "2.1"}``) says where each sits
on the face's neutral mesh, so the frame whose stabilised markers best fit those positions after a
similarity (rotation, scale, shift: another actor's head) is the actor's neutral: an open jaw, a smile
or raised brows move markers away from the face at rest, and on another actor's face the same marks
still sit in a neutral arrangement (lips together, brows down). Frames are smoothed over 0.1 s first
(the noise would otherwise choose), and the fit is judged by its median residual (a marker placed
badly on the actor does not decide).
"""

from __future__ import annotations

import logging

import numpy as np

from ..faces.face import Face
from .layout import Layout
from .rig import similarity
from .stabilise import head_track, remove_head

log = logging.getLogger(__name__)

__all__ = [
    "AUTO_RATIO",
    "HOLD_S",
    "REST_MARGIN_DEG",
    "SQUARE_MAX_DEG",
    "auto_neutral_frame",
    "axis_deviation",
    "axis_turn",
    "find_neutral",
    "held_frames",
    "rest_frame",
    "rest_score",
    "square_rest",
    "tied_positions",
    "turn_deg",
]

#: The default frame stays the neutral unless it fits the face at rest this many times worse than
#: the best frame. Small expressions (brows, lids: a few tenths of a millimetre) are within the noise
#: of the fit, and the first frame's fit is noisier (its 0.1 s smoothing is one-sided): on generated
#: takes (0.5 mm noise) moving from a neutral frame 0, frame 0 fitted 1.3-1.8x worse than the best
#: frame, which was an expression (weights summing to 1.3-1.4) in 2 of 9; a take starting on an
#: expression fitted 2-30x worse than its neutral hold.
AUTO_RATIO = 2.0
#: ... and only for a neutral *held*: a run of at least this long (s) of frames fitting within
#: ``AUTO_RATIO`` of the best. A face passing through neutral between two expressions also fits
#: well, and the head is anywhere then (the output's head is at rest in the neutral frame). On
#: generated takes with fast expressions (fast-large, held-out folds, 2 and 3 s) the best frame
#: was taken 3 times in 8 (a 13.8 degree head turn carried into every output frame: 41.9x not
#: deforming); with this rule 2 (a real 0.4 s neutral late in the take, with the head turned, which
#: no rule tells from a take that starts on an expression). The neutral-last takes' 0.5 s holds are
#: found as before (7 of 8).
HOLD_S = 0.4
#: ``rest_frame``: the default frame's head pose is the head's rest instead of the automatic
#: neutral frame's when its face sits this much (degrees) closer to the capture axes.
REST_MARGIN_DEG = 1.0
#: ``square_rest``: a start turned further than this (degrees) from the capture axes is not taken
#: for a turned head (the axes are then not square to the actor, or the layout does not fit).
SQUARE_MAX_DEG = 30.0


def tied_positions(layout: Layout, face: Face) -> np.ndarray:
    """``(L, 3)`` the face positions (face units) of the layout's markers tied to a vertex or a
    feature point; NaN for the others (placed automatically, or unknown to this face)."""
    out = np.full((len(layout.names), 3), np.nan)
    for i, name in enumerate(layout.names):
        spec = layout.markers[name]
        v = spec.get("vertex", face.feature_points.get(spec["fp"]) if "fp" in spec else None)
        if v is not None and 0 <= int(v) < face.n_vertices:
            out[i] = face.vertices[int(v)]
    return out


def auto_neutral_frame(
    xyz: np.ndarray, stable: np.ndarray, fps: float, target: np.ndarray, default: int = 0
) -> tuple[int, str]:
    """``(frame, why)``: the frame of ``xyz`` ``(T, L, 3)`` (capture space, mm, NaN = occluded) whose
    face markers best fit ``target`` ``(L, 3)`` (``tied_positions``) after a similarity (see the
    module docstring), when ``default`` (the layout's neutral frame, else 0) fits more than
    ``AUTO_RATIO`` times worse; else ``default``, also when fewer than 4 face markers are tied."""
    x = np.asarray(xyz, dtype=np.float64)
    n, m = x.shape[:2]
    face = np.setdiff1d(np.arange(m), stable)
    tied = face[np.isfinite(target[face]).all(axis=1)]
    seen3 = np.isfinite(x[:, stable]).all(axis=2).sum(axis=1) >= 3
    if len(tied) < 4 or not seen3.any():
        return (
            default,
            f"{len(tied)} face markers tied to the face (4 needed) or no head pose: frame {default}",
        )
    ref = np.full((m, 3), np.nan)
    ref[stable] = x[int(np.argmax(seen3)), stable]
    r, t, _ = head_track(x, stable, ref, refine=0)
    local = remove_head(x, r, t)[:, tied]
    half = max(1, round(0.05 * fps))
    ok = np.isfinite(local)
    zero = np.zeros((1, *local.shape[1:]))
    csum = np.concatenate([zero, np.cumsum(np.where(ok, local, 0.0), axis=0)])
    ccnt = np.concatenate([zero, np.cumsum(ok, axis=0)])
    lo, hi = np.clip(np.arange(n) - half, 0, n), np.clip(np.arange(n) + half + 1, 0, n)
    with np.errstate(invalid="ignore", divide="ignore"):
        smooth = (csum[hi] - csum[lo]) / (ccnt[hi] - ccnt[lo])
    dst = target[tied]
    score = np.array([rest_score(smooth[f], dst) for f in range(n)])
    if not np.isfinite(score).any() or not 0 <= default < n:
        return default, f"no frame shows enough of the tied markers: frame {default}"
    best = int(np.argmin(score))
    if score[default] <= AUTO_RATIO * score[best]:
        return default, (
            f"frame {default} fits the face at rest within {AUTO_RATIO:g}x of the best frame "
            f"({score[default]:.2f} against {score[best]:.2f} mm, median): kept"
        )
    held = held_frames(score <= AUTO_RATIO * score[best], round(HOLD_S * fps))
    if not held.any():
        return default, (
            f"frame {best} fits the face at rest best ({score[best]:.2f} mm) but only in passing (no "
            f"{HOLD_S:g} s hold near it): frame {default} kept"
        )
    best = int(np.argmin(np.where(held, score, np.inf)))
    return best, (
        f"frame {best} fits the face at rest best ({score[best]:.2f} mm median off it; frame "
        f"{default} {score[default]:.2f} mm, the take's median {np.median(score[np.isfinite(score)]):.2f} mm)"
    )


def rest_score(markers: np.ndarray, target: np.ndarray) -> float:
    """How far ``markers (n, 3)`` (mm, NaN = unseen) lie from the face at rest ``target (n, 3)``
    (``tied_positions``, face units): the median residual (mm) after the best similarity; inf
    when fewer than three quarters of them (or 4) are seen. Shared by batch and live."""
    vis = np.isfinite(markers).all(axis=1) & np.isfinite(target).all(axis=1)
    if vis.sum() < max(4, (3 * len(markers)) // 4):
        return float("inf")  # too many markers unseen to judge this frame
    q, s, c = similarity(markers[vis], target[vis])
    res = np.linalg.norm(s * markers[vis] @ q.T + c - target[vis], axis=1)
    return float(np.median(res)) / max(s, 1e-12)  # in the take's units (mm), not the face's


def held_frames(low: np.ndarray, min_len: int) -> np.ndarray:
    """``(T,) bool``: the frames of ``low`` that lie in a run of at least ``min_len`` True frames."""
    out = np.zeros(len(low), dtype=bool)
    start = None
    for i, v in enumerate(np.r_[low, False]):
        if v and start is None:
            start = i
        elif not v and start is not None:
            if i - start >= max(1, min_len):
                out[start:i] = True
            start = None
    return out


def find_neutral(
    raw: np.ndarray, layout: Layout, face: Face, fps: float, where: str = "take"
) -> int:
    """The neutral frame of ``--neutral-frame auto`` (``auto_neutral_frame``, logged): ``raw`` ``(T, L,
    3)`` mm in layout order; the layout's own ``neutral_frame`` (a number) is the default."""
    default = layout.neutral_frame if isinstance(layout.neutral_frame, int) else 0
    stable = np.array([layout.names.index(n) for n in layout.stable], dtype=np.int64)
    frame, why = auto_neutral_frame(
        raw, stable, fps, tied_positions(layout, face), min(default, len(raw) - 1)
    )
    log.info("%s: neutral frame %d (auto: %s)", where, frame, why)
    return frame


def axis_turn(markers: np.ndarray, target: np.ndarray, min_seen: int = 4) -> np.ndarray | None:
    """``(3, 3)``: how the head of ``markers (n, 3)`` (mm, NaN = unseen) is turned in capture space
    from the nearest pose square to the capture axes (Y-up, Z-up, facing any axis: a signed
    permutation of the face's axes): ``markers ~ D (square pose)`` about their centre. From the
    rotation ``Q`` of the best similarity onto the face at rest ``target (n, 3)`` (``tied_positions``):
    ``Q = P D^T`` with ``P`` the nearest signed permutation. None with fewer than ``min_seen``
    markers seen (3 fix a rotation)."""
    from scipy.spatial.transform import Rotation

    vis = np.isfinite(markers).all(axis=1) & np.isfinite(target).all(axis=1)
    if vis.sum() < max(3, min_seen):
        return None
    q = similarity(markers[vis], target[vis])[0]
    best, turn = float("inf"), np.eye(3)
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        for signs in np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).T.reshape(-1, 3):
            p = np.zeros((3, 3))
            p[np.arange(3), perm] = signs
            if np.linalg.det(p) > 0:
                angle = float(Rotation.from_matrix(q @ p.T).magnitude())
                if angle < best:
                    best, turn = angle, q.T @ p
    return turn


def axis_deviation(markers: np.ndarray, target: np.ndarray) -> float:
    """How far (degrees) the head of ``markers (n, 3)`` (mm, NaN = unseen) is turned from the
    capture axes (``axis_turn``'s angle); inf with fewer than 4 markers seen."""
    return turn_deg(axis_turn(markers, target))


def turn_deg(turn: np.ndarray | None) -> float:
    """The angle (degrees) of the rotation ``turn (3, 3)``; inf for None."""
    from scipy.spatial.transform import Rotation

    return (
        float("inf") if turn is None else float(np.degrees(Rotation.from_matrix(turn).magnitude()))
    )


def rest_frame(raw: np.ndarray, target: np.ndarray, nf: int, default: int) -> int:
    """The frame whose head pose is the output head's rest when the automatic neutral ``nf`` is
    not the ``default`` frame: ``default`` when its head sits ``REST_MARGIN_DEG`` closer to the
    capture axes (``axis_deviation``; ``raw (T, L, 3)`` mm, ``target`` ``tied_positions``), else
    ``nf``.

    A face passes through neutral between fast expressions, and a take may hold its neutral late
    with the head turned: the neutral's shape is right there, but taking its pose as the head's rest
    turned every output frame (a fast-expression take: 13.8 degrees, 41.7x not deforming). A take
    that ends on its neutral hold with the head at rest (and starts turned) keeps the hold's pose.
    Captures set their axes square to the actor (Y or Z up, facing an axis), so of the two
    candidate rests the one squarer to them is taken; each is within a few hundredths of a degree of
    its true turn on generated takes (0.5 mm noise, one frame)."""
    if nf == default or not 0 <= default < len(raw):
        return nf
    own, other = axis_deviation(raw[nf], target), axis_deviation(raw[default], target)
    return default if other + REST_MARGIN_DEG < own else nf


def square_rest(
    neutral: np.ndarray, target: np.ndarray, stable: np.ndarray, pivot: np.ndarray | None = None
) -> tuple[np.ndarray, float]:
    """The live driver's head rest when it starts with the head turned: ``(neutral' (L, 3) mm,
    degrees)``, ``neutral (L, 3)`` (mm, NaN = unseen, the first frames' pose) carried back by the
    head's turn from the capture axes (``axis_turn``) about the face's head ``pivot`` (face units,
    carried into the capture frame by the best similarity; the stable markers' centre without
    one), and that turn's angle; ``(neutral, 0.0)`` unchanged when the head sits square.

    The turn is taken when the face markers tied to the face (``target``, ``tied_positions``) and
    the stable markers tied to it (when 3 are) both say the head is turned more than
    ``REST_MARGIN_DEG`` (and at most ``SQUARE_MAX_DEG``) from the axes, as batch's ``rest_frame``
    trusts a squarer frame by that margin; its rotation comes from the stable markers, which no
    expression moves (a take may start on one: the face markers were 0.9 deg off the true turn at
    an expression, the stable ones 0.07-0.1 deg; on square starts they gave 0.04-0.21 deg and the
    face markers 0.07-0.48 deg, generated takes, 0.5 mm noise). Every later pose is then solved
    against the square neutral, so the output's head is turned from the first state on, as the
    actor's is, instead of taking the turned start for the rest (6-9 deg on every frame of a take
    that holds its neutral at the end)."""
    every = axis_turn(neutral, target)
    only = np.full_like(target, np.nan)
    only[stable] = target[stable]
    band = axis_turn(neutral, only, min_seen=3)
    turn = band if band is not None else every
    deg = turn_deg(turn)
    checks = [turn_deg(every)] + ([deg] if band is not None else [])
    if turn is None or not all(REST_MARGIN_DEG < d <= SQUARE_MAX_DEG for d in checks):
        return neutral, 0.0
    vis = np.isfinite(neutral).all(axis=1) & np.isfinite(target).all(axis=1)
    if pivot is not None:
        q, scale, shift = similarity(neutral[vis], target[vis])
        c = (np.asarray(pivot, dtype=np.float64) - shift) @ q / scale
    else:
        seen = np.isfinite(neutral[stable]).all(axis=1)
        c = neutral[stable][seen].mean(axis=0) if seen.any() else np.nanmean(neutral, axis=0)
    return (neutral - c) @ turn + c, deg
