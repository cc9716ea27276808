"""Many frames mixed at once: the live path's mix of a deform batch, one frame per session.

``combine`` (``mix``) works on one frame's ``Contribution`` objects; here every layer of every
frame becomes rows of arrays (``Columns``): the common layers (idle, expression overlays, gaze)
are sampled for all frames together (``sample_many``), the others one at a time, and the rules
of ``mix`` then run once on ``(B, 69)`` arrays, whatever the batch holds. The results equal
``combine``'s to rounding (a few ulp). Costs (``bench/layers.py``): a few microseconds a frame
and a fixed ~0.1 ms a batch.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..state import FaceState
from .gaze import GazeLayer
from .idle import CLOSED_LIDS, LID_MASK, IdleLayer
from .mix import (
    _AU,
    _DEFAULT_GEOMETRY,
    _LIDS_CHEEKS,
    _LIPS_REGION,
    _SPEECH,
    WIDTH,
    _expand,
    _eye_angles_batch,
    _eyes_to,
    _keep_closures_batch,
    _limit_mouth_batch,
    _offsets,
    _unrotate,
    _unrotate1,
    combine,
    keep_closures,
    meet_lids,
)
from .model import Contribution, GazeTarget, Geometry, Layer, N, Role, region_mask
from .overlay import ExpressionLayer

#: One frame to mix: ``(primary, items, t)`` as ``combine``'s arguments.
Frame = tuple[FaceState | None, Sequence[tuple[Role, Contribution]], float | None]


@dataclass
class Columns:
    """Contributions of one role to the rows of a batch, as arrays (each part optional, each
    with the batch rows it belongs to; a row may appear several times).

    Attributes:
        off: ``(rows (K,), X (K, 69) offsets (amount applied), W (K, 1) or (K, 69) weights, or
            None: 1)``.
        over: ``(rows, O (K, 69) absolute values, OW (K, 69) weights)``.
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
    return np.array(x, dtype=np.intp)


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
    if blink.any():
        k = int(blink.sum())
        col.over = (
            r[blink],
            np.broadcast_to(CLOSED_LIDS, (k, N)),
            closure[blink, None] * LID_MASK,
        )
    return col


def _overlay_offsets(layer: ExpressionLayer, geo: Geometry) -> np.ndarray | None:
    """``(69,)`` what ``layer`` adds at full weight (``_offsets`` of its contribution), remembered
    with the geometry's expansions (read-only)."""

    def make() -> np.ndarray | None:
        c = Contribution(
            faps=layer.faps,
            amount=layer.amount,
            expression=(layer.expression, 63, 0, 0) if layer.expression else None,
        )
        x = _offsets(c, geo)
        return None if x is None else np.array(x, dtype=np.float64)

    return geo.remember((layer, "offsets"), make)


def _overlay_mask(layer: ExpressionLayer, geo: Geometry) -> np.ndarray:
    """``(69,)`` the region mask of ``layer`` (``region_mask(regions)``), remembered."""
    return geo.remember((layer, "mask"), lambda: region_mask(layer.regions or ()))


def _expression_columns(
    rows: list[int], layers: list[ExpressionLayer], ts: np.ndarray, geo: Geometry, role: Role
) -> Columns | None:
    keep: list[int] = []
    xs: list[np.ndarray] = []
    ws: list[Any] = []
    scalar = True
    for r, layer, t in zip(rows, layers, ts.tolist()):
        e = layer.envelope(t)
        if e <= 0.0:
            continue
        x = _overlay_offsets(layer, geo)
        if x is None:
            continue
        keep.append(r)
        xs.append(x)
        if layer.regions is None:
            ws.append(e)
        else:
            ws.append(_overlay_mask(layer, geo) * e)
            scalar = False
    if not keep:
        return None
    W = np.array(ws, dtype=np.float64)[:, None] if scalar else _weights(ws)
    return Columns(role, off=(_rows(keep), np.array(xs), W))


def _gaze_q(target: GazeTarget, geo: Geometry) -> np.ndarray:
    """``(3,)`` a target's point minus the head pivot, or its direction; remembered with the
    geometry's expansions (read-only)."""

    def make() -> np.ndarray:
        q = target.direction if target.point is None else target.point - geo.head_pivot
        return np.array(q, dtype=np.float64)

    return geo.remember((target, "q"), make)


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
        qs.append(_gaze_q(g, geo))
        ws.append(w)
    if not keep:
        return None
    return Columns(role, gaze=(_rows(keep), np.array(qs), np.array(ps), np.array(ws)))


def sample_columns(entries: Sequence[tuple[int, Layer, float]], geo: Geometry) -> list[Columns]:
    """The contributions of layers ``(row, layer, t)`` at their times, as ``Columns``: idle,
    expression and gaze layers sampled together by kind, the others one at a time."""
    kinds: dict[tuple[type, Role], tuple[list[int], list[Any], list[float]]] = {}
    other: list[tuple[int, Role, Contribution]] = []
    for r, layer, t in entries:
        kind = type(layer)
        if kind is IdleLayer or kind is ExpressionLayer or kind is GazeLayer:
            key = (kind, layer.role)
            group = kinds.get(key)
            if group is None:
                group = kinds[key] = ([], [], [])
            group[0].append(r)
            group[1].append(layer)
            group[2].append(t)
        else:
            other.append((r, layer.role, layer.sample(t)))
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


# -- the rules on arrays ------------------------------------------------------------------------------


#: Fewest frames ``mix_batch`` mixes together: fewer cost less one by one (``combine``: a
#: batch has ~30 NumPy calls of fixed cost; measured against it with bench/layers.py).
BATCH_MIN = 8
#: Below this many rows, lip closures and gaze are worked out row by row in Python floats (as
#: ``combine``): NumPy's ~40 calls on small arrays cost more than a few rows' arithmetic.
SMALL = 8
#: Below this many gaze rows, gaze is worked out row by row (``_gaze_rows``).
SMALL_GAZE = 10
_ZERO = np.zeros(N)
_ZERO.flags.writeable = False


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
    F = np.array([_ZERO if p is None else p.faps for p in prims], dtype=np.float64)
    F[:, :3] = 0.0
    closing = [closures and p is not None for p in prims]
    some_close, all_close = any(closing), all(closing)
    closing_rows = np.array(closing)
    H = E = None  # the primaries' high-level expansions; of their expression alone
    high = [r for r, p in enumerate(prims) if p is not None and (p.viseme or p.expression)]
    for r in high:
        p = prims[r]
        assert p is not None
        H = np.zeros((B, N)) if H is None else H
        H[r] = _expand(p.viseme, p.expression, geo)
        if closing[r] and p.expression is not None:
            E = np.zeros((B, N)) if E is None else E
            E[r] = _expand(None, p.expression, geo)
    if H is not None:
        F += H
    before = F[:, _LIDS_CHEEKS]

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
    sums: dict[Role, list[Any]] = {}  # role -> [Σ w·x, Σ w·[x ≠ 0]] (None until a layer adds)
    every = np.arange(B)
    for c in columns:
        if c.off is None:
            continue
        rows, X, W = c.off
        WX, WN = (X, X != 0) if W is None else (W * X, W * (X != 0))
        acc = sums.setdefault(c.role, [None, None, False])
        if acc[0] is None and len(rows) == B and (rows == every).all():
            # (fresh arrays, or X itself: never written to); alone and unweighted, its mean is X
            acc[0], acc[1], acc[2] = WX, WN, W is None
            continue
        acc[2] = False
        if acc[0] is None or acc[0] is X:
            acc[0] = np.zeros((B, N)) if acc[0] is None else acc[0].copy()
            acc[1] = np.zeros((B, N)) if acc[1] is None else acc[1].astype(np.float64)
        np.add.at(acc[0], rows, WX)
        np.add.at(acc[1], rows, WN)
    if sums:
        A: Any = None
        for role, (num, den, alone) in sums.items():
            if role is Role.EXPRESSION:
                P = F
                if some_close:
                    mask = _SPEECH if all_close else closing_rows[:, None] & _SPEECH
                    P = np.where(mask, 0.0 if E is None else E, F)
                present = P != 0
                if not all_close:  # a still primary's lips' width competes (rule 4)
                    shaped = (F[:, _LIPS_REGION] != 0).any(axis=1) & ~closing_rows
                    present[:, WIDTH] |= shaped[:, None]
                part = (P + num) / np.maximum(1.0, present + den) - P
            elif alone:  # one unweighted layer on every row: X / max(1, [X != 0]) is X
                part = num if A is not None or len(sums) > 1 else num.copy()
            else:
                part = num / np.maximum(1.0, den)
            A = part if A is None else A + part
        if some_close:
            rows = closing_rows
            _limit_mouth_batch(F, A, rows)  # (A is a new array: written in place)
            if B < SMALL:
                for r in range(B):
                    if closing[r]:
                        A[r] = keep_closures(F[r], A[r])
            else:
                _keep_closures_batch(F, A, rows)
        F += A
        F[:, :3] = 0.0

    # 5. overrides
    overs = [c.over for c in columns if c.over is not None]
    if overs:
        onum, oden = np.zeros((B, N)), np.zeros((B, N))
        for rows, values, OW in overs:
            np.add.at(onum, rows, OW * values)
            np.add.at(oden, rows, OW)
        on = oden > 0
        target = np.divide(onum, oden, out=np.zeros((B, N)), where=on)
        F = np.where(on, F + np.minimum(1.0, oden) * (target - F), F)
    if (F[:, 19:21] > 0.0).any():  # closing lids (rare): rule 5's meeting
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
    return [
        FaceState(t=ts[r], faps=F[r])
        if p is None
        else FaceState(
            ts[r], F[r], p.viseme, p.expression, p.controls, p.head, p.shapes, p.shape_weights
        )
        for r, p in enumerate(prims)
    ]


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
    rows = np.concatenate([g[0] for g in gazes])
    Q = np.concatenate([g[1] for g in gazes])
    point = np.concatenate([g[2] for g in gazes])
    w = np.concatenate([g[3] for g in gazes])
    local = _unrotate(F[rows, 48:51] * _AU, Q)[:, None, :]  # (K, 1, 3)
    off = geo.head_pivot - geo.eye_pivots  # (2, 3)
    if point.all():
        local = local + off
    elif point.any():
        local = local + point[:, None, None] * off
    yaw, pitch = _eye_angles_batch(local, geo.eye_axes)
    e = np.concatenate([yaw, pitch], axis=1) / _AU  # FAPs 23-26: yaw l, r, pitch l, r
    if len(rows) == len(set(rows.tolist())):
        at, mean, W = rows, e, w
    else:
        B = F.shape[0]
        num, wsum = np.zeros((B, 4)), np.zeros(B)
        np.add.at(num, rows, e * w[:, None])
        np.add.at(wsum, rows, w)
        at = np.flatnonzero(wsum > 0)
        mean, W = num[at] / wsum[at, None], wsum[at]
    W = np.minimum(1.0, W)[:, None]
    cur = F[at, 23:27]
    F[at, 23:27] = np.where(W >= 1.0, mean, cur + W * (mean - cur))


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
    sessions' frames costs in one go. Drops the layers whose end has passed."""
    if len(frames) < BATCH_MIN:  # too few to gain from it: each alone
        return [mixer.mix(primary, t) for mixer, primary, t in frames]
    out: list[FaceState | None] = [None] * len(frames)
    groups: dict[tuple[int, bool], tuple[Geometry, list[int], list[Any]]] = {}
    for i, (mixer, primary, t) in enumerate(frames):
        layers = mixer.active(t)
        if not layers or (primary is not None and primary.head is not None) or not _shaped(primary):
            out[i] = mixer.mix(primary, t)
            continue
        geo = _DEFAULT_GEOMETRY if mixer.geometry is None else mixer.geometry
        group = groups.setdefault((id(geo), mixer.closures), (geo, [], []))
        group[1].append(i)
        group[2].append(layers)
    for (_, closures), (geo, rows, layer_lists) in groups.items():
        if len(rows) < BATCH_MIN:  # cheaper one by one
            for i, layers in zip(rows, layer_lists):
                mixer, primary, t = frames[i]
                items = mixer.items(t, layers)
                out[i] = combine(primary, items, t, geometry=geo, closures=closures)
            continue
        prims = [frames[i][1] for i in rows]
        ts = [float(frames[i][2]) for i in rows]
        entries = [(r, layer, ts[r]) for r, layers in enumerate(layer_lists) for layer in layers]
        mixed = combine_columns(prims, ts, sample_columns(entries, geo), geo, closures)
        for i, state in zip(rows, mixed):
            out[i] = state
    return out  # type: ignore[return-value]


def _time(primary: FaceState | None, t: float | None) -> float:
    if t is not None:
        return float(t)
    return 0.0 if primary is None else primary.t


def _shaped(primary: FaceState | None) -> bool:
    """A primary whose FAPs are a ``(69,)`` vector (else ``combine`` says what is wrong)."""
    return primary is None or np.shape(primary.faps) == (N,)
