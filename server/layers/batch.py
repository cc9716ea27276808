"""Many frames mixed at once: the live path's mix of a deform batch, one frame per session.

``combine`` (``mix``) works on one frame's ``Contribution`` objects; here every layer of every
frame becomes rows of arrays (``Columns``): the common layers (idle, expression overlays, gaze)
are sampled for all frames together (``sample_many``), the others one at a time, and the rules
of ``mix`` then run once on ``(B, 69)`` arrays, whatever the batch holds. The results equal
``combine``'s to rounding (a few ulp). Costs (``bench/layers.py``): a few microseconds a frame
and a fixed ~0.1 ms a batch. Most of it is NumPy's cost per call on arrays this small, so the
rules use its cheap calls (``take``, ``count_nonzero``, ufuncs without keywords), skip what
cannot change the result, and sample the rows of alike sessions together (``Mixer.snapshot``).

``mix_batch`` hands its batches to ``kernel`` (the same rules in one compiled call: a few µs a
batch, whatever its size); this path mixes them until the kernel is compiled, and without numba.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..state import FaceState
from . import kernel
from .expansions import gaze_q, overlay_at, overlay_mask
from .gaze import GazeLayer
from .idle import CLOSED_LIDS, LID_MASK, IdleLayer
from .mix import (
    _AU,
    _DEFAULT_GEOMETRY,
    _LIDS_CHEEKS_AT,
    _LIPS,
    _LIPS_REGION,
    _SPEECH,
    _SPEECH_F,
    CLOSED_GAP,
    EYE_PITCH_MAX,
    EYE_YAW_MAX,
    OPEN_GAP,
    WIDTH,
    _eyes_to,
    _offsets,
    _unrotate1,
    combine,
    meet_lids,
    mixed_states,
    primaries,
)
from .model import Contribution, Geometry, Layer, N, Role
from .overlay import ExpressionLayer

#: One frame to mix: ``(primary, items, t)`` as ``combine``'s arguments.
Frame = tuple[FaceState | None, Sequence[tuple[Role, Contribution]], float | None]


@dataclass
class Columns:
    """Contributions of one role to the rows of a batch, as arrays (each part optional, each
    with the batch rows it belongs to; a row may appear several times).

    Attributes:
        off: ``(rows (K,), X (K, 69) offsets (amount applied; (1, 69): the same on every row,
            with weights), W (K, 1) or (K, 69) weights, or None: 1)``.
        over: ``(rows, O (K, 69) or (1, 69): the same on every row, absolute values, OW (K, 69)
            weights)``.
        head: ``(rows, V (K, 3) poses in AU, w (K,))``.
        gaze: ``(rows, Q (K, 3): a point minus the head pivot or a direction, is_point (K,),
            w (K,))``.
    """

    role: Role
    off: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None = None
    over: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    head: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    gaze: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None


def _rows(x: list[int]) -> np.ndarray:
    """``x`` as an index array; ``0, 1, ..., K - 1`` as the one read-only array of them
    (``_every`` knows it by identity)."""
    if x == list(range(len(x))):
        return _range(len(x))
    return np.array(x, dtype=np.intp)


_RANGES: dict[int, np.ndarray] = {}


def _range(K: int) -> np.ndarray:
    """The read-only ``arange(K)`` of ``_rows``."""
    r = _RANGES.get(K)
    if r is None:
        r = np.arange(K, dtype=np.intp)
        r.flags.writeable = False
        if len(_RANGES) < 4096:
            _RANGES[K] = r
    return r


def columns_of(entries: Sequence[tuple[int, Role, Contribution]], geo: Geometry) -> list[Columns]:
    """``Columns`` (one per role) of contributions ``(row, role, contribution)``."""
    by_role: dict[Role, list[tuple[int, Contribution]]] = {}
    for r, role, c in entries:
        by_role.setdefault(role, []).append((r, c))
    out = []
    for role, items in by_role.items():
        col = Columns(role)
        orow, xs, ws = [], [], []
        vrow, os_, ows = [], [], []
        hrow, hs, hws = [], [], []
        grow, gq, gp, gws = [], [], [], []
        for r, c in items:
            x = _offsets(c, geo)
            if x is not None:
                orow.append(r)
                xs.append(x)
                ws.append(c.weight)
            if c.override is not None:
                vrow.append(r)
                os_.append(c.override)
                ows.append(c.override_weight)
            if c.head is not None and c.head_weight > 0:
                hrow.append(r)
                hs.append(c.head)
                hws.append(c.head_weight)
            if c.gaze is not None and c.gaze_weight > 0:
                g = c.gaze
                grow.append(r)
                gp.append(g.point is not None)
                gq.append(g.point - geo.head_pivot if g.point is not None else g.direction)
                gws.append(c.gaze_weight)
        if orow:
            col.off = _rows(orow), np.array(xs, dtype=np.float64), _weights(ws)
        if vrow:
            ow = np.empty((len(ows), N))
            ow[...] = np.array([np.broadcast_to(w, (N,)) for w in ows])
            col.over = _rows(vrow), np.array(os_, dtype=np.float64), ow
        if hrow:
            col.head = _rows(hrow), np.array(hs, dtype=np.float64), np.array(hws, dtype=float)
        if grow:
            col.gaze = _rows(grow), np.array(gq, dtype=np.float64), np.array(gp), np.array(gws)
        out.append(col)
    return out


def _weights(ws: list[Any]) -> np.ndarray:
    """``(K, 1)`` of scalar weights, ``(K, 69)`` when one is per FAP."""
    if all(type(w) is float or type(w) is int for w in ws):
        return np.array(ws, dtype=np.float64)[:, None]
    return np.array([np.broadcast_to(np.asarray(w, dtype=np.float64), (N,)) for w in ws])


# -- the common layers, sampled for many frames at once ---------------------------------------------


def _idle_columns(rows: list[int], layers: list[IdleLayer], ts: np.ndarray) -> Columns:
    X, closure = IdleLayer.sample_many(layers, ts)
    r = _rows(rows)
    col = Columns(Role.IDLE, off=(r, X, None))
    blink = closure > 0.0
    if np.count_nonzero(blink):
        col.over = (r[blink], CLOSED_LIDS[None], closure[blink, None] * LID_MASK)
    return col


def _expression_columns(
    rows: list[int], layers: list[ExpressionLayer], ts: np.ndarray, geo: Geometry, role: Role
) -> Columns | None:
    keep: list[int] = []
    xs: list[np.ndarray] = []
    ws: list[Any] = []
    scalar = True
    for r, layer, t in zip(rows, layers, ts.tolist()):
        got = overlay_at(layer, t, geo)
        if got is None:
            continue
        e, x = got
        keep.append(r)
        xs.append(x)
        if layer.regions is None:
            ws.append(e)
        else:
            ws.append(overlay_mask(layer, geo) * e)
            scalar = False
    if not keep:
        return None
    W = np.array(ws, dtype=np.float64)[:, None] if scalar else _weights(ws)
    x0 = xs[0]
    X = x0[None] if all(x is x0 for x in xs) else np.array(xs)  # (1, 69): the same on every row
    return Columns(role, off=(_rows(keep), X, W))


def _gaze_columns(
    rows: list[int], layers: list[GazeLayer], ts: np.ndarray, geo: Geometry, role: Role
) -> Columns | None:
    keep, qs, ps, ws = [], [], [], []
    for r, layer, t in zip(rows, layers, ts.tolist()):
        w = layer.amount * layer.envelope(t)
        if w <= 0.0:
            continue
        g = layer.target
        keep.append(r)
        ps.append(g.point is not None)
        qs.append(gaze_q(g, geo))
        ws.append(w)
    if not keep:
        return None
    return Columns(role, gaze=(_rows(keep), np.array(qs), np.array(ps), np.array(ws)))


#: Layers sampled by kind, many rows at once: ``(type, role) -> (rows, layers, times)``.
Kinds = dict[tuple[type, Role], tuple[list[int], list[Any], list[float]]]
_TOGETHER = (IdleLayer, ExpressionLayer, GazeLayer)


def sample_columns(entries: Sequence[tuple[int, Layer, float]], geo: Geometry) -> list[Columns]:
    """The contributions of layers ``(row, layer, t)`` at their times, as ``Columns``: idle,
    expression and gaze layers sampled together by kind, the others one at a time."""
    kinds: Kinds = {}
    other: list[tuple[int, Role, Contribution]] = []
    for r, layer, t in entries:
        kind = type(layer)
        if kind in _TOGETHER:
            key = (kind, layer.role)
            group = kinds.get(key)
            if group is None:
                group = kinds[key] = ([], [], [])
            group[0].append(r)
            group[1].append(layer)
            group[2].append(t)
        else:
            other.append((r, layer.role, layer.sample(t)))
    return _columns(kinds, other, geo)


def _columns(
    kinds: Kinds, other: list[tuple[int, Role, Contribution]], geo: Geometry
) -> list[Columns]:
    """``Columns`` of the layers sampled by kind and of the others' contributions."""
    out = columns_of(other, geo) if other else []
    for (kind, role), (rows, layers, ts) in kinds.items():
        T = np.array(ts, dtype=np.float64)
        col: Columns | None
        if kind is IdleLayer and role is Role.IDLE:
            col = _idle_columns(rows, layers, T)
        elif kind is ExpressionLayer:
            col = _expression_columns(rows, layers, T, geo, role)
        elif kind is GazeLayer:
            col = _gaze_columns(rows, layers, T, geo, role)
        else:  # an idle layer given another role: as it samples itself
            col = None
            out += columns_of([(r, role, x.sample(t)) for r, x, t in zip(rows, layers, ts)], geo)
        if col is not None:
            out.append(col)
    return out


def _sample_alike(
    alike: dict[tuple[tuple[type, Role], ...], tuple[list[int], list[tuple[Layer, ...]]]],
    ts: list[float],
    geo: Geometry,
) -> list[Columns]:
    """``sample_columns`` of rows whose layers are alike (the same ``(type, role)`` in the same
    order: ``Mixer.snapshot``): ``signature -> (rows, their layers)``, ``ts`` by row. A kind's
    layers are gathered by position, not layer by layer; the columns are ``sample_columns``'s,
    their rows in another order."""
    kinds: Kinds = {}
    other: list[tuple[int, Role, Contribution]] = []
    for sig, (rows, layer_lists) in alike.items():
        times = [ts[r] for r in rows]
        for k, key in enumerate(sig):
            layers = [x[k] for x in layer_lists]
            if key[0] in _TOGETHER:
                group = kinds.get(key)
                if group is None:
                    kinds[key] = (list(rows), layers, list(times))
                else:
                    group[0].extend(rows)
                    group[1].extend(layers)
                    group[2].extend(times)
            else:
                other += [(r, x.role, x.sample(t)) for r, x, t in zip(rows, layers, times)]
    return _columns(kinds, other, geo)


# -- the rules on arrays ------------------------------------------------------------------------------


#: Fewest frames ``mix_batch`` mixes together: fewer cost less one by one (``combine``: a
#: batch has ~100 NumPy calls of fixed cost; 4 frames cost 1.1x, 5 about the same, 6 0.9x
#: ``combine``'s, bench/serve.py's layers at load 6-7).
BATCH_MIN = 5
#: Below this many gaze rows, gaze is worked out row by row (``_gaze_rows``; 7 rows about even).
SMALL_GAZE = 8
_SPAN = OPEN_GAP - CLOSED_GAP
_TWO_PI = 2 * math.pi


def combine_columns(
    prims: Sequence[FaceState | None],
    ts: Sequence[float],
    columns: Sequence[Columns],
    geo: Geometry,
    closures: bool,
) -> list[FaceState]:
    """``combine`` of ``B`` frames: primaries (None: the neutral face; none with a ``head``
    transform), their times, and every layer's contribution as ``columns``."""
    B = len(prims)
    F, H, E, closing_rows, high = primaries(prims, geo, closures)
    F[:, :3] = 0.0
    some_close, all_close = bool(closing_rows.any()), bool(closing_rows.all())
    if H is not None:
        F += H
    before = F.take(_LIDS_CHEEKS_AT, 1)

    # 2. head poses
    heads = [c.head for c in columns if c.head is not None]
    if heads:
        num3, wsum = np.zeros((B, 3)), np.zeros(B)
        for rows, V, w in heads:
            np.add.at(num3, rows, V * w[:, None])
            np.add.at(wsum, rows, w)
        on = wsum > 0
        target = num3[on] / wsum[on, None]
        F[on, 48:51] += np.minimum(1.0, wsum[on])[:, None] * (target - F[on, 48:51])

    # 3. offsets: Σ w·x / max(1, Σ w·[x ≠ 0]) per role; expression overlays compete with the
    #    primary too (in a speaking mouth with its expression only); 4. closures
    roles: dict[Role, list[tuple[np.ndarray, np.ndarray, np.ndarray | None]]] = {}
    for c in columns:
        if c.off is not None:
            roles.setdefault(c.role, []).append(c.off)
    if roles:
        A: Any = None
        for role, offs in roles.items():
            if role is Role.EXPRESSION:
                num, den = _sums(offs, B)
                P = F
                if some_close:
                    mask = _SPEECH if all_close else closing_rows[:, None] & _SPEECH
                    P = np.where(mask, 0.0 if E is None else E, F)
                d = P != 0
                if not all_close:  # a still primary's lips' width competes (rule 4)
                    shaped = (F[:, _LIPS_REGION] != 0).any(axis=1) & ~closing_rows
                    d[:, WIDTH] |= shaped[:, None]
                d = d + den
                np.maximum(d, 1.0, out=d)
                part = P + num
                part /= d
                part -= P
            elif len(offs) == 1 and offs[0][2] is None and _every(offs[0][0], B):
                # one unweighted layer on every row: X / max(1, [X ≠ 0]) is X
                part = offs[0][1] if A is not None or len(roles) > 1 else offs[0][1].copy()
            else:
                num, den = _sums(offs, B)
                part = num / np.maximum(den, 1.0)
            A = part if A is None else A + part
        if some_close:
            _mouth(F, A, None if all_close else closing_rows)  # (A is a new array: in place)
        F += A
        F[:, :3] = 0.0

    # 5. overrides
    overs = [c.over for c in columns if c.over is not None]
    if overs:
        F = _override(F, overs)
    if np.count_nonzero(F[:, 19:21] > 0.0):  # closing lids: rule 5's meeting
        meet_lids(F, before)

    # 6. gaze, from the final head pose (FAPs 48-50)
    gazes = [c.gaze for c in columns if c.gaze is not None]
    if gazes:
        if sum(len(g[0]) for g in gazes) < SMALL_GAZE:
            _gaze_rows(F, gazes, geo)
        else:
            _gaze(F, gazes, geo)

    if H is not None:
        F -= H
        F[high, :3] = 0.0
    return mixed_states(F, ts, prims)


def _override(F: np.ndarray, overs: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> np.ndarray:
    """Step 5: the override columns ``(rows, values, OW)`` averaged by weight per row and FAP,
    replacing ``F`` by ``min(1, Σ OW)``; F itself or a new array."""
    if len(overs) == 1 and _ascending(overs[0][0]):  # (one override a row, as a blink's)
        rows, values, OW = overs[0]
        Fr = F[rows]
        on = OW > 0
        target = np.divide(OW * values, OW, out=np.zeros(Fr.shape), where=on)
        F[rows] = np.where(on, Fr + np.minimum(1.0, OW) * (target - Fr), Fr)
        return F
    B = F.shape[0]
    onum, oden = np.zeros((B, N)), np.zeros((B, N))
    for rows, values, OW in overs:
        np.add.at(onum, rows, OW * values)
        np.add.at(oden, rows, OW)
    on = oden > 0
    target = np.divide(onum, oden, out=np.zeros((B, N)), where=on)
    return np.where(on, F + np.minimum(1.0, oden) * (target - F), F)


def _every(rows: np.ndarray, B: int) -> bool:
    """Whether ``rows`` are ``0, 1, ..., B - 1``."""
    if len(rows) != B or B == 0:
        return False
    return rows is _RANGES.get(B) or (rows[0] == 0 and rows[-1] == B - 1 and _ascending(rows))


def _ascending(rows: np.ndarray) -> bool:
    """Whether ``rows`` ascend strictly (no row twice)."""
    if len(rows) < 2 or rows is _RANGES.get(len(rows)):
        return True
    return bool(np.count_nonzero(rows[1:] > rows[:-1]) == len(rows) - 1)


def _sums(
    offs: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]], B: int
) -> tuple[np.ndarray, np.ndarray]:
    """``(Σ w·x, Σ w·[x ≠ 0])`` per row ``(B, 69)`` of one role's columns ``(rows, X, W)``: read
    only (one column's own arrays, or ``X`` itself)."""
    num: Any = None
    den: Any = None
    own = False  # num and den are arrays of this function's (written in place)
    for rows, X, W in offs:
        if W is None:
            WX, WN = X, (X != 0).astype(np.float64)
        else:
            WX, WN = W * X, W * (X != 0)
        if num is None and _every(rows, B):
            num, den = WX, WN
            continue
        if num is None:
            num, den, own = np.zeros((B, N)), np.zeros((B, N)), True
        elif not own:
            num, den, own = num.copy(), den.copy(), True
        if _ascending(rows):
            num[rows] += WX
            den[rows] += WN
        else:
            np.add.at(num, rows, WX)
            np.add.at(den, rows, WN)
    return num, den


def _mouth(F: np.ndarray, A: np.ndarray, rows: np.ndarray | None) -> None:
    """Rule 4 on ``F``, ``A (B, 69)``, in place on ``A``, for the rows (bool ``(B,)``; None: all)
    of speaking primaries: ``limit_mouth``, then ``keep_closures``. (NumPy's calls on arrays this
    small cost more than their arithmetic: ``take`` and ``count_nonzero`` are its cheap ones.)"""
    # limit_mouth: what of A goes the way F does beyond F; the lips' width: their mean
    a = A.take(WIDTH, 1)
    f = F * (_SPEECH_F if rows is None else rows[:, None] * _SPEECH_F)
    f = np.minimum(np.maximum(f, np.minimum(A, 0.0)), np.maximum(A, 0.0))
    A -= f
    moved = a != 0
    if rows is not None:
        moved &= rows[:, None]
    k = np.count_nonzero(moved)
    if k == moved.size:
        A[:, WIDTH] = (a - F.take(WIDTH, 1)) / 2
    elif k:
        A[:, WIDTH] = np.where(moved, (a - F.take(WIDTH, 1)) / 2, A.take(WIDTH, 1))
    # keep_closures: what A opens (lips, jaw) taken out by how closed F holds the lips
    LA = A.take(_LIPS, 1)
    shut = LA[:, 0::2] + LA[:, 1::2]  # (B, 6): minus what A opens each lip pair
    jaw = A[:, 3]
    opens = jaw > 0
    if not np.count_nonzero(opens) and not np.count_nonzero(shut < 0):
        return  # A opens neither the lips nor the jaw
    LF = F.take(_LIPS, 1)
    x = (LF[:, 0::2] + LF[:, 1::2] + CLOSED_GAP) / -_SPAN  # (-(top + bottom) - CLOSED) / span
    x = np.minimum(np.maximum(x, 0.0), 1.0)
    c = 1.0 - x * x * (3.0 - 2.0 * x)  # (B, 6): 1 closed .. 0 open
    if rows is not None:
        c[~rows] = 0.0
    if not np.count_nonzero(c):
        return  # every mouth open: nothing to keep
    A[:, 3] = np.where(opens, jaw * (1.0 - c[:, 0]), jaw)
    cut = np.minimum(shut, 0.0) * c * -0.5  # what of each pair's opening both lips give back
    LA[:, 0::2] += cut
    LA[:, 1::2] += cut
    A[:, _LIPS] = LA


def _gaze_rows(
    F: np.ndarray,
    gazes: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    geo: Geometry,
) -> None:
    """``_gaze`` row by row in Python floats (as ``combine``): cheaper for a few rows."""
    per_row: dict[int, list[tuple[list[float], bool, float]]] = {}
    for rows, Q, point, w in gazes:
        for r, q, is_point, x in zip(rows.tolist(), Q.tolist(), point.tolist(), w.tolist()):
            per_row.setdefault(r, []).append((q, is_point, x))
    pv = geo.pivot
    for r, gs in per_row.items():
        angles = F[r, 48:51].tolist()
        W = 0.0
        eyes = [0.0, 0.0, 0.0, 0.0]
        for q, is_point, x in gs:  # q: the point minus the pivot, or a direction
            d = _unrotate1(angles, q)
            if is_point:  # Rᵀ(p - pv) + pv, seen from each eye
                d = (d[0] + pv[0], d[1] + pv[1], d[2] + pv[2])
            e = _eyes_to(d, is_point, geo)
            eyes = [a + x * b for a, b in zip(eyes, e)]
            W += x
        eyes = [e / W for e in eyes]
        if W >= 1.0:
            F[r, 23:27] = eyes
        else:
            F[r, 23:27] += W * (np.array(eyes) - F[r, 23:27])


def _gaze(
    F: np.ndarray,
    gazes: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    geo: Geometry,
) -> None:
    """Step 6 on ``F (B, 69)`` in place: each gaze's eye angles under its row's head pose,
    averaged by weight per row, replacing the eyes' rotation by ``min(1, Σ w)``.

    An eye at ``c`` under the head ``[R | pv - R·pv]`` sees a point ``p`` along
    ``Rᵀ(p - pv) + (pv - c)`` (head-local), a direction ``u`` along ``Rᵀu``."""
    B = F.shape[0]
    if len(gazes) == 1:
        rows, Q, point, w = gazes[0]
    else:
        rows = np.concatenate([g[0] for g in gazes])
        Q = np.concatenate([g[1] for g in gazes])
        point = np.concatenate([g[2] for g in gazes])
        w = np.concatenate([g[3] for g in gazes])
    every = len(gazes) == 1 and _every(rows, B)
    head = F[:, 48:51] if every else F[rows, 48:51]
    local = _unrotate(head * _AU, Q)[:, None, :]  # (K, 1, 3)
    points = np.count_nonzero(point)
    if points:
        off = geo.head_pivot - geo.eye_pivots  # (2, 3)
        local = local + (off if points == len(point) else point[:, None, None] * off)
    e = _eyes(local, geo)
    if len(gazes) == 1 and (every or _ascending(rows)):
        at: Any = slice(None) if every else rows
        mean, W = e, w
    else:
        num, wsum = np.zeros((B, 4)), np.zeros(B)
        np.add.at(num, rows, e * w[:, None])
        np.add.at(wsum, rows, w)
        at = np.flatnonzero(wsum > 0)
        mean, W = num[at] / wsum[at, None], wsum[at]
    if not np.count_nonzero(W < 1.0):
        F[at, 23:27] = mean
        return
    W = np.minimum(1.0, W)[:, None]
    cur = F[at, 23:27]
    F[at, 23:27] = np.where(W >= 1.0, mean, cur + W * (mean - cur))


def _unrotate(angles: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``Rᵀ q`` row by row: ``R = Ry(yaw)·Rx(pitch)·Rz(roll)`` (``_rot``) of ``angles (G, 3)``
    (pitch, yaw, roll radians), ``q (G, 3)``; three plane rotations, R itself is not formed."""
    cp, cy, cr = np.cos(angles).T
    sp, sy, sr = np.sin(angles).T
    qx, qy, qz = q.T
    x, z = cy * qx - sy * qz, sy * qx + cy * qz  # Ryᵀ
    y, z = cp * qy + sp * z, cp * z - sp * qy  # Rxᵀ
    out = np.empty_like(q)
    out[:, 0] = cr * x + sr * y  # Rzᵀ
    out[:, 1] = cr * y - sr * x
    out[:, 2] = z
    return out


def _eye_consts(geo: Geometry) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """The eyes' ``ax (2,)``, ``r = hypot(ay, az) (2,)``, ``φ = atan2(az, ay) (2,)`` and whether
    both look straight along their ``yz`` plane (``ax == 0``, ``r == 1``), remembered."""

    def make() -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
        ax, ay, az = geo.eye_axes.T
        r = np.hypot(ay, az)
        plane = bool((ax == 0).all() and (r == 1).all())
        return ax.copy(), r, np.arctan2(az, ay), plane

    return geo.remember("eye constants", make)


def _eyes(d: np.ndarray, geo: Geometry) -> np.ndarray:
    """FAPs 23-26 (AU; yaw l, r, pitch l, r) ``(G, 4)`` of both eyes looking along ``d (G, 2, 3)``
    or ``(G, 1, 3)`` (head-local): ``eye_angles`` of each eye. (With ``u = cos(pitch + φ)``, the
    rotated axis' z is ``ay·sin(pitch) + az·cos(pitch) = r·√(1 - u²)``; with ``ax = 0`` the yaw
    it takes off, ``atan2(0, r·√(1 - u²))``, is 0.)"""
    ax, r, phi, plane = _eye_consts(geo)
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    n = np.sqrt(dx * dx + dy * dy + dz * dz)
    ok = n > 1e-12
    every = np.count_nonzero(ok) == ok.size
    u = dy / (n if every else np.where(ok, n, 1.0))
    if not plane:
        u = u / r
    u = np.minimum(np.maximum(u, -1.0), 1.0)
    pitch = np.arccos(u) - phi
    yaw = np.arctan2(dx, dz)
    if not plane:
        yaw = yaw - np.arctan2(ax, r * np.sqrt(1.0 - u * u))
    yaw = (yaw + math.pi) % _TWO_PI - math.pi
    yaw = np.minimum(np.maximum(yaw, -EYE_YAW_MAX), EYE_YAW_MAX)
    pitch = np.minimum(np.maximum(pitch, -EYE_PITCH_MAX), EYE_PITCH_MAX)
    if not every:
        yaw = np.where(ok, yaw, 0.0)
        pitch = np.where(ok, pitch, 0.0)
    e = np.concatenate((yaw, yaw, pitch) if yaw.shape[1] == 1 else (yaw, pitch), 1)
    e /= _AU
    return e


# -- entry points ------------------------------------------------------------------------------------


def combine_batch(
    frames: Sequence[Frame], *, geometry: Geometry | None = None, closures: bool = True
) -> list[FaceState]:
    """``combine(primary, items, t, geometry=, closures=)`` of every frame, computed together
    (``combine_columns``). Frames without items, and those whose primary has a ``head``
    transform, go through ``combine`` one by one."""
    geo = _DEFAULT_GEOMETRY if geometry is None else geometry
    out: list[FaceState | None] = [None] * len(frames)
    todo: list[int] = []
    for i, (p, items, t) in enumerate(frames):
        if not items or (p is not None and p.head is not None) or not _shaped(p):
            out[i] = combine(p, items, t, geometry=geometry, closures=closures)
        else:
            todo.append(i)
    if todo:
        prims = [frames[i][0] for i in todo]
        ts = [_time(*frames[i][::2]) for i in todo]
        entries = [(r, role, c) for r, i in enumerate(todo) for role, c in frames[i][1]]
        mixed = combine_columns(prims, ts, columns_of(entries, geo), geo, closures)
        for i, state in zip(todo, mixed):
            out[i] = state
    return out  # type: ignore[return-value]


def mix_batch(frames: Sequence[tuple[Any, FaceState | None, float]]) -> list[FaceState]:
    """``mixer.mix(primary, t)`` of every ``(mixer, primary, t)`` (a ``Mixer``), the frames of
    mixers with the same geometry (``is``) and closures computed together: what a batch of live
    sessions' frames costs in one go (by the compiled ``kernel`` once it is ready). Drops the
    layers whose end has passed."""
    fast = kernel.warm()
    if len(frames) < BATCH_MIN and not fast:  # too few to gain from it: each alone
        return [mixer.mix(primary, t) for mixer, primary, t in frames]
    out: list[FaceState | None] = [None] * len(frames)
    # (geometry, closures) -> the geometry, frame indices, and by signature their rows and layers
    groups: dict[tuple[int, bool], tuple[Geometry, list[int], dict[Any, Any]]] = {}
    for i, (mixer, primary, t) in enumerate(frames):
        layers, sig = mixer.snapshot(t)
        if not layers or (primary is not None and primary.head is not None) or not _shaped(primary):
            out[i] = mixer.mix(primary, t)
            continue
        geo = _DEFAULT_GEOMETRY if mixer.geometry is None else mixer.geometry
        group = groups.get((id(geo), mixer.closures))
        if group is None:
            group = groups[(id(geo), mixer.closures)] = (geo, [], {})
        rows = group[1]
        same = group[2].get(sig)
        if same is None:
            group[2][sig] = ([len(rows)], [layers])
        else:
            same[0].append(len(rows))
            same[1].append(layers)
        rows.append(i)
    for (_, closures), (geo, rows, alike) in groups.items():
        ts = [float(frames[i][2]) for i in rows]
        packed = kernel.pack(alike, ts, geo) if fast else None
        if packed is None and len(rows) < BATCH_MIN:  # cheaper one by one
            for i in rows:
                mixer, primary, t = frames[i]
                out[i] = mixer.mix(primary, t)
            continue
        prims = [frames[i][1] for i in rows]
        got = None  # (None: the kernel is not ready, or refused the batch)
        if packed is not None:
            got = kernel.combine_packed(prims, ts, packed, geo, closures)
        mixed = got or combine_columns(prims, ts, _sample_alike(alike, ts, geo), geo, closures)
        for i, state in zip(rows, mixed):
            out[i] = state
    return out  # type: ignore[return-value]


def _time(primary: FaceState | None, t: float | None) -> float:
    if t is not None:
        return float(t)
    return 0.0 if primary is None else primary.t


def _shaped(primary: FaceState | None) -> bool:
    """A primary whose FAPs are a ``(69,)`` array (else ``combine`` converts them, or says what
    is wrong)."""
    return primary is None or getattr(primary.faps, "shape", None) == (N,)
