"""The live mix of a batch in one compiled call: ``batch.combine_columns``'s rules as one loop over
rows and FAPs.

The NumPy path (``batch``) pays a fixed ~1 µs per NumPy call on arrays of a few frames, ~100 calls
a batch: at the live batches' 2-8 frames (4.7 a batch at 25 sessions) it cost 25-35 µs a frame,
measurable in ``bench serve`` (issue 18). Here the layers are sampled in Python floats (``pack``:
a few numbers per layer and frame) and every rule runs in ``_mix_rows``, compiled by numba, in
about 2 µs a batch; what is left is Python's per frame (sampling, ``FaceState``): ``bench/layers.py
--against`` (serve's 3 layers, thread CPU, load 9) 35 -> 18 µs a frame at 1 frame a batch, 35 ->
10 at 4, 25 -> 9 at 8, 13 -> 8 at 25.

Other layers (a producer's, a head gesture or pose, a track) are sampled as they sample themselves
and their contributions read as ``batch.columns_of`` reads them (offsets, head poses, overrides).
Every batch takes the NumPy path until the kernel is compiled (``ready``; ``warm`` compiles it in
a thread, cached on disk by numba), and without numba. The results equal ``combine_columns``'s to
rounding (tests: within 1e-9 FAPU).
"""

from __future__ import annotations

import importlib.util
import logging
import math
import threading
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..state import FaceState
from .expansions import gaze_q, overlay_at, overlay_mask
from .gaze import GazeLayer
from .idle import _PHASES, _RATES, _SWAY, IdleLayer
from .mix import (
    _AU,
    _LIPS,
    _LIPS_REGION,
    _SPEECH,
    CLOSED_GAP,
    EYE_PITCH_MAX,
    EYE_YAW_MAX,
    LID_PER_CHEEK,
    LIDS_MEET,
    OPEN_GAP,
    WIDTH,
    _offsets,
    mixed_states,
    primaries,
)
from .model import Geometry, N, Role
from .overlay import ExpressionLayer

log = logging.getLogger(__name__)

#: numba compiles the kernel (imported in the compiling thread: ~1 s, not in a deform thread);
#: without it the NumPy path mixes every batch.
HAVE_NUMBA = importlib.util.find_spec("numba") is not None

#: Entry kinds (``ints[k, 0]``): an idle layer, offsets (an overlay's, or any contribution's), a
#: gaze, a head pose, an override.
IDLE, OVERLAY, GAZE, HEAD, OVERRIDE = 0, 1, 2, 3, 4
OTHER = -1  # (``pack``: a layer read through its contribution)
#: No rows (``H``, ``E``, ``X``, ``M`` without any). The kernel's arrays are all writeable (a
#: read-only array is another type to numba: another compilation), though it writes only ``F``.
_EMPTY = np.zeros((0, 69))

# constants the compiled kernel reads (numba freezes global arrays)
_K_SPEECH = _SPEECH.astype(np.int8)
_K_LIPS = _LIPS.astype(np.int64)
_K_WIDTH = WIDTH.astype(np.int64)
_K_IS_WIDTH = np.zeros(69, dtype=np.int8)
_K_IS_WIDTH[WIDTH] = 1
_K_LIPS_REGION = _LIPS_REGION.astype(np.int64)
_K_RATES = _RATES.copy()
_K_PHASES = _PHASES.copy()
_K_SWAY = _SWAY.copy()
_SPAN = OPEN_GAP - CLOSED_GAP
_TWO_PI = 2 * math.pi


def _mix_rows(
    F: np.ndarray,
    H: np.ndarray,
    E: np.ndarray,
    flags: np.ndarray,
    ints: np.ndarray,
    floats: np.ndarray,
    X: np.ndarray,
    M: np.ndarray,
    roles: np.ndarray,
    geo: np.ndarray,
) -> None:
    """The rules of ``batch.combine_columns`` on ``F (B, 69)`` in place (the primaries' FAPs in,
    the mix out; the primaries' high-level expansion ``H`` is added and taken off again).

    Args:
        H, E: ``(B, 69)`` the primaries' high-level expansion and that of their expression alone
            (``(0, 69)``: none).
        flags: ``(B, 2)`` int8: the row keeps closures (a speaking primary); it has ``H``.
        ints, floats: ``(K, 5)`` / ``(K, 7)``, one entry per layer and row (a contribution may
            give several): ``ints`` kind (``IDLE``, ``OVERLAY``, ``GAZE``, ``HEAD``,
            ``OVERRIDE``), row, role (index into ``roles``), then offsets' (an override's values)
            row in ``X`` and weights' (an overlay's regions, an override's weights) row in ``M``
            (-1: none), a gaze's is-a-point; ``floats`` an idle layer's ``t`` and
            ``IdleLayer.row``, offsets' weight (an overlay's envelope), a gaze's weight and target
            (its point minus the head pivot, or its direction), a head pose's weight and pose (AU).
        X, M: ``(U, 69)`` offsets (amount applied) or override values, ``(V, 69)`` weights.
        roles: ``(R,)`` int8, 1 for ``Role.EXPRESSION`` (which competes with the primary).
        geo: ``(19,)`` the head pivot, then per eye ``Geometry.eye_consts``.
    """
    B = F.shape[0]
    K = ints.shape[0]
    R = roles.shape[0]
    has_h = H.shape[0] > 0
    has_e = E.shape[0] > 0
    before = np.empty((B, 4))
    for b in range(B):
        F[b, 0] = 0.0
        F[b, 1] = 0.0
        F[b, 2] = 0.0
        if has_h:
            for j in range(69):
                F[b, j] += H[b, j]
        before[b, 0] = F[b, 19]
        before[b, 1] = F[b, 20]
        before[b, 2] = F[b, 41]
        before[b, 3] = F[b, 42]

    # 2. head poses, averaged by weight, replace the head (FAPs 48-50) by min(1, Σ w)
    for b in range(B):
        wsum = 0.0
        h0 = h1 = h2 = 0.0
        for k in range(K):
            if ints[k, 0] == HEAD and ints[k, 1] == b:
                w = floats[k, 0]
                h0 += floats[k, 1] * w
                h1 += floats[k, 2] * w
                h2 += floats[k, 3] * w
                wsum += w
        if wsum > 0.0:
            W = min(1.0, wsum)
            F[b, 48] += W * (h0 / wsum - F[b, 48])
            F[b, 49] += W * (h1 / wsum - F[b, 49])
            F[b, 50] += W * (h2 / wsum - F[b, 50])

    # 3. offsets: Σ w·x / max(1, Σ w·[x ≠ 0]) per role; expression overlays compete with the primary
    if R > 0:
        A = np.zeros((B, 69))
        num = np.empty((B, 69))
        den = np.empty((B, 69))
        x = np.zeros(69)
        for r in range(R):
            num[:] = 0.0
            den[:] = 0.0
            for k in range(K):
                if ints[k, 2] != r or ints[k, 0] > OVERLAY:
                    continue
                b = ints[k, 1]
                if ints[k, 0] == IDLE:  # IdleLayer.sample_many's row
                    tt = _TWO_PI * floats[k, 0]
                    s0 = math.sin(tt * _K_RATES[0] + _K_PHASES[0])
                    s1 = math.sin(tt * _K_RATES[1] + _K_PHASES[1])
                    s2 = math.sin(tt * _K_RATES[2] + _K_PHASES[2])
                    s3 = math.sin(tt * _K_RATES[3] + _K_PHASES[3])
                    s4 = math.sin(tt * _K_RATES[4] + _K_PHASES[4])
                    x[:] = 0.0
                    x[23] = x[24] = floats[k, 1]
                    x[25] = x[26] = floats[k, 2]
                    sw = floats[k, 4]
                    x[48] = sw * (s0 * _K_SWAY[0, 0] + s1 * _K_SWAY[1, 0])
                    x[49] = sw * (s2 * _K_SWAY[2, 1])
                    x[50] = sw * (s3 * _K_SWAY[3, 2])
                    x[48] += floats[k, 5] * s4
                    x[61] = x[62] = floats[k, 6] * max(s4, 0.0)
                    for j in (23, 24, 25, 26, 48, 49, 50, 61, 62):
                        num[b, j] += x[j]
                        if x[j] != 0.0:
                            den[b, j] += 1.0
                else:  # an overlay: weight (× its regions' mask) and offsets
                    w = floats[k, 0]
                    xi = ints[k, 3]
                    mi = ints[k, 4]
                    for j in range(69):
                        v = X[xi, j]
                        wj = M[mi, j] * w if mi >= 0 else w
                        num[b, j] += wj * v
                        if v != 0.0:
                            den[b, j] += wj
            for b in range(B):
                if roles[r] == 1:
                    closing = flags[b, 0] == 1
                    shaped = False  # a still primary's lips' width competes (rule 4)
                    if not closing:
                        for j in _K_LIPS_REGION:
                            if F[b, j] != 0.0:
                                shaped = True
                    for j in range(69):
                        p = F[b, j]
                        if closing and _K_SPEECH[j] == 1:
                            p = E[b, j] if has_e else 0.0
                        d = 1.0 if p != 0.0 else 0.0
                        if shaped and _K_IS_WIDTH[j] == 1:
                            d = 1.0
                        d = max(d + den[b, j], 1.0)
                        A[b, j] += (p + num[b, j]) / d - p
                else:
                    for j in range(69):
                        A[b, j] += num[b, j] / max(den[b, j], 1.0)
        # 4. a speaking mouth: limit_mouth, the lips' width, keep_closures
        for b in range(B):
            if flags[b, 0] != 1:
                continue
            a0 = A[b, _K_WIDTH[0]]
            a1 = A[b, _K_WIDTH[1]]
            a2 = A[b, _K_WIDTH[2]]
            a3 = A[b, _K_WIDTH[3]]
            for j in range(69):
                if _K_SPEECH[j] == 1:
                    a = A[b, j]
                    f = min(max(F[b, j], min(a, 0.0)), max(a, 0.0))
                    A[b, j] = a - f
            for i, a in enumerate((a0, a1, a2, a3)):
                if a != 0.0:
                    w = _K_WIDTH[i]
                    A[b, w] = (a - F[b, w]) / 2
            jaw = A[b, 3]
            for i in range(6):
                top = _K_LIPS[2 * i]
                bottom = _K_LIPS[2 * i + 1]
                shut = A[b, top] + A[b, bottom]
                g = (F[b, top] + F[b, bottom] + CLOSED_GAP) / -_SPAN
                g = min(max(g, 0.0), 1.0)
                c = 1.0 - g * g * (3.0 - 2.0 * g)
                if i == 0 and jaw > 0.0:
                    A[b, 3] = jaw * (1.0 - c)
                cut = min(shut, 0.0) * c * -0.5
                A[b, top] += cut
                A[b, bottom] += cut
        for b in range(B):
            for j in range(69):
                F[b, j] += A[b, j]
            F[b, 0] = 0.0
            F[b, 1] = 0.0
            F[b, 2] = 0.0

    # 5. overrides (a blink's closed lids, a producer's gaze), averaged by weight per FAP,
    #    replace the mix by min(1, Σ w); then the lids meet
    onum = np.zeros(69)
    oden = np.zeros(69)
    for b in range(B):
        some = False
        for k in range(K):
            if ints[k, 1] != b:
                continue
            if ints[k, 0] == IDLE and floats[k, 3] > 0.0:
                if not some:
                    onum[:] = 0.0
                    oden[:] = 0.0
                    some = True
                c = floats[k, 3]
                for j in range(19, 23):
                    onum[j] += c * (1024.0 if j < 21 else 150.0)
                    oden[j] += c
            elif ints[k, 0] == OVERRIDE:
                if not some:
                    onum[:] = 0.0
                    oden[:] = 0.0
                    some = True
                xi = ints[k, 3]
                mi = ints[k, 4]
                for j in range(69):
                    ow = M[mi, j]
                    onum[j] += ow * X[xi, j]
                    oden[j] += ow
        if some:
            for j in range(69):
                if oden[j] > 0.0:
                    fv = F[b, j]
                    F[b, j] = fv + min(1.0, oden[j]) * (onum[j] / oden[j] - fv)
        for s in range(2):
            lid = F[b, 19 + s]
            cheek = F[b, 41 + s]
            cap = max(LIDS_MEET - LID_PER_CHEEK * max(cheek, 0.0), 0.0)
            if lid > cap and (lid != before[b, s] or cheek != before[b, 2 + s]):
                F[b, 19 + s] = cap

    # 6. gaze, from the final head pose (FAPs 48-50)
    for b in range(B):
        W = 0.0
        e0 = e1 = e2 = e3 = 0.0
        for k in range(K):
            if ints[k, 0] != GAZE or ints[k, 1] != b:
                continue
            w = floats[k, 0]
            point = ints[k, 3] == 1
            pitch, yaw, roll = F[b, 48] * _AU, F[b, 49] * _AU, F[b, 50] * _AU
            cp, sp, cy, sy = math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
            cr, sr = math.cos(roll), math.sin(roll)
            qx, qy, qz = floats[k, 1], floats[k, 2], floats[k, 3]
            ux, uz = cy * qx - sy * qz, sy * qx + cy * qz  # Ryᵀ
            uy, uz = cp * qy + sp * uz, cp * uz - sp * qy  # Rxᵀ
            qx, qy, qz = cr * ux + sr * uy, cr * uy - sr * ux, uz  # Rzᵀ
            if point:  # Rᵀ(p - pv) + pv, seen from each eye
                qx, qy, qz = qx + geo[0], qy + geo[1], qz + geo[2]
            for side in range(2):
                o = 3 + 8 * side
                dx, dy, dz = qx, qy, qz
                if point:
                    dx, dy, dz = qx - geo[o], qy - geo[o + 1], qz - geo[o + 2]
                n = math.sqrt(dx * dx + dy * dy + dz * dz)
                if not n > 1e-12:
                    continue
                ax, ay, az, rr, phi = geo[o + 3], geo[o + 4], geo[o + 5], geo[o + 6], geo[o + 7]
                ep = math.acos(max(-1.0, min(1.0, dy / n / rr))) - phi
                ez = ay * math.sin(ep) + az * math.cos(ep)
                ey = math.atan2(dx, dz) - math.atan2(ax, ez)
                ey = (ey + math.pi) % _TWO_PI - math.pi
                ey = max(-EYE_YAW_MAX, min(EYE_YAW_MAX, ey)) / _AU
                ep = max(-EYE_PITCH_MAX, min(EYE_PITCH_MAX, ep)) / _AU
                if side == 0:
                    e0 += w * ey
                    e2 += w * ep
                else:
                    e1 += w * ey
                    e3 += w * ep
            W += w
        if W > 0.0:
            for i, e in enumerate((e0, e1, e2, e3)):
                if W >= 1.0:
                    F[b, 23 + i] = e / W
                else:
                    F[b, 23 + i] += W * (e / W - F[b, 23 + i])

        if has_h and flags[b, 1] == 1:
            for j in range(69):
                F[b, j] -= H[b, j]
            F[b, 0] = 0.0
            F[b, 1] = 0.0
            F[b, 2] = 0.0


_compiled: Any = None
_lock = threading.Lock()
_disabled = False  # (``disable``: never compiled)
_thread: threading.Thread | None = None


def ready() -> bool:
    """Whether the compiled kernel is there (``warm`` compiles it)."""
    return _compiled is not None


def warm(block: bool = False) -> bool:
    """Compile the kernel (numba; cached on disk) in a thread, once (``block``: wait for it);
    whether it is ready now. Without numba it never is."""
    global _thread
    if _compiled is not None or not HAVE_NUMBA:
        return _compiled is not None
    with _lock:
        if not _disabled and _thread is None:
            _thread = threading.Thread(target=_compile, name="layers-kernel", daemon=True)
            _thread.start()
        thread = _thread
    if block and thread is not None:
        thread.join()
    return _compiled is not None


def disable() -> None:
    """Mix with NumPy from now on (tests: both paths)."""
    global _compiled, _disabled
    with _lock:
        _compiled, _disabled = None, True


def _compile() -> None:
    global _compiled
    try:
        import numba

        fn = numba.njit(cache=True, error_model="numpy")(_mix_rows)  # (holding the GIL: a
        # few µs; released, the deform thread waited for it back behind the event loop)
        F = np.zeros((1, 69))
        ints = np.array([[IDLE, 0, 0, -1, -1], [OVERLAY, 0, 1, 0, 0], [GAZE, 0, 0, 1, -1]])
        floats = np.zeros((3, 7))
        flags = np.ones((1, 2), dtype=np.int8)
        roles = np.array([0, 1], dtype=np.int8)
        fn(F, F.copy(), F.copy(), flags, ints, floats, F.copy(), F.copy(), roles, np.ones(19))
        fn.disable_compile()  # one signature: any other is a bug, refused (TypeError), not compiled
        _compiled = fn
    except Exception:  # (the NumPy path mixes then)
        log.exception("compiling the layers' mix kernel failed; mixing with NumPy")


# -- what the kernel needs of a batch --------------------------------------------------------------


class Packed:
    """A batch's layers sampled for ``_mix_rows``: its ``ints``, ``floats``, ``X``, ``M`` and
    ``roles`` arrays."""

    __slots__ = ("M", "X", "floats", "ints", "roles")

    def __init__(
        self, ints: np.ndarray, floats: np.ndarray, X: np.ndarray, M: np.ndarray, roles: np.ndarray
    ) -> None:
        self.ints, self.floats, self.X, self.M, self.roles = ints, floats, X, M, roles


def pack(
    alike: dict[tuple[tuple[type, Role], ...], tuple[list[int], list[tuple[Any, ...]]]],
    ts: Sequence[float],
    geo: Geometry,
) -> Packed | None:
    """The layers of rows ``signature -> (rows, their layers)`` (``batch._sample_alike``'s) at
    their times ``ts`` (by row) as ``Packed``; None when a contribution gazes but not from a
    ``GazeLayer`` (the NumPy path mixes that batch)."""
    ints: list[int] = []
    floats: list[float] = []
    roles: dict[Role, int] = {}
    xs: dict[int, int] = {}
    X: list[np.ndarray] = []
    ms: dict[tuple[str, ...], int] = {}
    M: list[np.ndarray] = []
    pad = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    for sig, (rows, layer_lists) in alike.items():
        kinds = []  # per position: its kind's code and its role's index
        for kind, role in sig:
            if kind is IdleLayer and role is Role.IDLE:
                code = IDLE
            elif kind is ExpressionLayer:
                code = OVERLAY
            elif kind is GazeLayer:
                code = GAZE
            else:
                code = OTHER
            kinds.append((code, -1 if code == GAZE else roles.setdefault(role, len(roles))))
        for r, layers in zip(rows, layer_lists):
            t = ts[r]
            for (code, ri), layer in zip(kinds, layers):
                if code == IDLE:
                    ints += (IDLE, r, ri, -1, -1)
                    floats.append(t)
                    floats += layer.row(t)
                elif code == OVERLAY:
                    got = overlay_at(layer, t, geo)
                    if got is None:
                        continue
                    e, offsets = got
                    xi = xs.get(id(offsets))
                    if xi is None:
                        xi = xs[id(offsets)] = len(X)
                        X.append(offsets)
                    mi = -1
                    if layer.regions is not None:
                        mi = ms.get(layer.regions, -1)
                        if mi < 0:
                            mi = ms[layer.regions] = len(M)
                            M.append(overlay_mask(layer, geo))
                    ints += (OVERLAY, r, ri, xi, mi)
                    floats.append(e)
                    floats += pad
                elif code == GAZE:
                    w = layer.amount * layer.envelope(t)
                    if w <= 0.0:
                        continue
                    point, q = _gaze_entry(layer.target, geo)
                    ints += (GAZE, r, -1, point, -1)
                    floats.append(w)
                    floats += q
                else:  # any other layer: its contribution (``batch.columns_of``'s reading)
                    c = layer.sample(t)
                    if c.gaze is not None and c.gaze_weight > 0:
                        return None  # (only a GazeLayer gazes)
                    if c.head is not None and c.head_weight > 0:
                        ints += (HEAD, r, -1, -1, -1)
                        floats.append(float(c.head_weight))
                        floats += np.asarray(c.head, dtype=np.float64).tolist()
                        floats += (0.0, 0.0, 0.0)
                    x = _offsets(c, geo)
                    if x is not None:
                        w = c.weight
                        mi = -1
                        if not (type(w) is float or type(w) is int):
                            mi = len(M)
                            M.append(np.broadcast_to(np.asarray(w, dtype=np.float64), (N,)))
                            w = 1.0
                        ints += (OVERLAY, r, ri, len(X), mi)
                        X.append(x)
                        floats.append(float(w))
                        floats += pad
                    if c.override is not None:
                        ow = np.asarray(c.override_weight, dtype=np.float64)
                        ints += (OVERRIDE, r, -1, len(X), len(M))
                        X.append(c.override)
                        M.append(np.broadcast_to(ow, (N,)))
                        floats.append(0.0)
                        floats += pad
    K = len(ints) // 5
    return Packed(
        np.array(ints, dtype=np.int64).reshape(K, 5),
        np.array(floats, dtype=np.float64).reshape(K, 7),
        np.array(X, dtype=np.float64) if X else _EMPTY,
        np.array(M, dtype=np.float64) if M else _EMPTY,
        np.array([int(r is Role.EXPRESSION) for r in roles], dtype=np.int8),
    )


def _gaze_entry(target: Any, geo: Geometry) -> tuple[int, tuple[float, ...]]:
    """A gaze target's ``ints[k, 3]`` (a point: 1) and ``floats[k, 1:]`` (``expansions.gaze_q``, then
    padding), remembered with the geometry's expansions."""
    hit = geo.expansions.get((target, "kernel"))
    if hit is None:
        q = gaze_q(target, geo).tolist()
        hit = geo.remember(
            (target, "kernel"), lambda: (int(target.point is not None), (*q, 0.0, 0.0, 0.0))
        )
    return hit


def _geo_consts(geo: Geometry) -> np.ndarray:
    """``(19,)`` the head pivot and both eyes' ``eye_consts`` (``_mix_rows``'s ``geo``)."""
    return geo.remember(  # (in a list: ``remember`` would make the array read-only)
        "kernel constants",
        lambda: [np.array([*geo.pivot, *geo.eye_consts[0], *geo.eye_consts[1]], dtype=np.float64)],
    )[0]


def combine_packed(
    prims: Sequence[FaceState | None],
    ts: Sequence[float],
    packed: Packed,
    geo: Geometry,
    closures: bool,
) -> list[FaceState] | None:
    """``batch.combine_columns`` of ``B`` frames (primaries: None the neutral face, none with a
    ``head`` transform) with their layers ``packed``, by the compiled kernel (``ready()``); None
    if it refuses them (then ``disable``d)."""
    F, H, E, closing, high = primaries(prims, geo, closures)
    flags = np.stack([closing, high], axis=1).astype(np.int8)
    args = (packed.ints, packed.floats, packed.X, packed.M, packed.roles, _geo_consts(geo))
    try:
        _compiled(F, _EMPTY if H is None else H, _EMPTY if E is None else E, flags, *args)
    except TypeError:  # arrays of a type it was not compiled for (a bug): NumPy from now on
        log.exception("the layers' mix kernel refused its arguments; mixing with NumPy")
        disable()
        return None
    return mixed_states(F, ts, prims)
