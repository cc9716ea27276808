"""Mixing a primary face state with layers into one ``FaceState`` per frame, and a session's ``Mixer``.

The rules (Kshirsagar et al. and Kähler's combining slide, ``research/seed-000-B.md`` §2.2), in the
order they apply to one frame:

1. **Primary**: the producer's state, high-level FAPs expanded with the face's tables.
2. **Head pose**: contributions with a ``head`` pose replace the primary's head (FAPs 48-50, or
   its ``head`` transform) by their weight (several: averaged by weight).
3. **Offsets add**: each role's ``faps`` (plus its expanded viseme/expression) are added; inside
   one role, FAPs two layers weigh on are averaged by weight, ``Σ w·x / max(1, Σ w)`` (one layer at
   weight w adds ``w·x``; two at full weight give their mean; a layer weighs only on the FAPs it
   moves). Expression overlays also compete with the primary, at weight 1, on the FAPs it moves
   (a joy overlay over an anger stream gives their mean brows, not a sum no face can make), except
   a speaking primary's speech in the mouth and tongue: speech and expression add there
   (Kshirsagar et al.'s expressive speech, a vector sum), under rule 4; the primary's own
   expression (FAP 2) still competes there.
4. **Closures and openings**: where the primary holds the lips together (a /p b m/, silence: a
   lip pair's gap near or below contact) the offsets' lip-opening part is taken out, shared by both
   lips (their common shift and the corners stay), and so is their jaw opening.
   Where the speech opens the mouth, the offsets open it only as far as they would alone: the
   mouth opens by the larger of the two, not their sum. In a speaking mouth a FAP that the
   speech and the offsets move the same way goes as far as the larger of the two
   (``limit_mouth``; opposite ways they add): a smile's parted lips, dropped jaw and stretched
   corners over an "aa" summed to a mouth wider than either makes, and creased the chin (issue
   18); the mixed mouth stays within the ranges its parts use. The lips' width (the corners'
   stretch, ``WIDTH``) is the speech's articulation (spread, rounded, or neutral: a position
   too) as much as the overlay's, so where the offsets move it the two compete and are averaged
   (rule 3's mean at weight 1 each), whichever way each goes: summed, a smile's stretch over
   closed, rounded or open lips pulled the lips through the teeth on the ICT head (issue 18:
   42-50 socket vertices poking through against 32-36 for the parts alone; averaged, 24-26).
   A primary that does not speak but moves its lips (a pout, pressed lips) shapes its mouth
   too: there its lips' width competes with the overlays' even where it is 0 (rule 3's mean,
   ``_role_part``'s ``width``); added in full, a smile's stretch over ICT's pressed lips in
   ``beg`` poked 42 socket vertices through against 36 for the parts alone.
5. **Overrides** (``override``): absolute FAP values replace the result by their weight (blinks).
   **The lids meet**: where the layers changed an eye's upper lid or cheek, the upper lid closes
   (FAP 19/20 > 0) no further than ``LIDS_MEET - LID_PER_CHEEK · cheek`` (FAPs 41/42 raised,
   ENS): a raised cheek (a smile's squint) lifts the lower lid, so a closed upper lid meets it
   higher (``meet_lids``). A blink over a smile's cheeks, or a smile over a stream's closed lids,
   closing the full way folded the skin at the eyes' outer corners (issue 18, the built-in head:
   4 flipped triangles in each part, 6 in the mix with a primary's lowered brows).
6. **Gaze**: eye yaw/pitch (FAPs 23-26) turned to the target from the eye centres under the final
   head pose, replacing the eyes' rotation by the weight.

The result keeps the primary's viseme, expression and controls: its ``faps`` are the mixed
low-level values minus the primary's high-level expansion, so the rig's ``expand`` gives the mix.
With no layers the primary is returned as it is.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from ..errors import Conflict, InputError, NotFound
from ..mocap.stabilise import euler_from_matrix
from ..mpeg4.rig import about
from ..state import FaceState
from .model import REGIONS, Contribution, GazeTarget, Geometry, Layer, Role

#: Lip pairs (upper lip FAP, + down; lower lip FAP, + up): inner mid, left, right; outer the same.
#: A pair's gap (FAPU MNS, 0 = the neutral closed mouth) is ``-(upper + lower)``.
LIP_PAIRS: np.ndarray = np.array([[4, 5], [8, 10], [9, 11], [51, 52], [55, 57], [56, 58]])
#: Primary lip gap (MNS) at and below which the lips count as closed, and above which as open;
#: in between the overlay may open them in proportion.
CLOSED_GAP, OPEN_GAP = 80.0, 300.0
_AU = 1e-5
#: The FAPs speech moves (mouth and tongue): where a speaking primary and an overlay add.
_SPEECH = np.zeros(69, dtype=bool)
_SPEECH[list(REGIONS["mouth"] + REGIONS["tongue"])] = True
_MOUTH = np.flatnonzero(_SPEECH).tolist()
#: Farthest the eyes turn from their rest direction (radians): 50° sideways, 45° up or down.
EYE_YAW_MAX, EYE_PITCH_MAX = math.radians(50.0), math.radians(45.0)
_DEFAULT_GEOMETRY = Geometry()


def _expand(
    viseme: tuple[int, int, int] | None,
    expression: tuple[int, int, int, int] | None,
    geo: Geometry,
) -> np.ndarray | None:
    """``(69,)`` low-level FAPs of FAP 1/2 with the geometry's tables (None when both are None);
    remembered per geometry (read-only arrays)."""
    if viseme is None and expression is None:
        return None

    def make() -> np.ndarray:
        from ..mpeg4.highlevel import expand

        return expand(FaceState(viseme=viseme, expression=expression), geo.visemes, geo.expressions)

    return geo.remember((viseme, expression), make)


def _offsets(c: Contribution, geo: Geometry) -> np.ndarray | None:
    """``(69,)`` FAP offsets of one contribution: its FAPs plus its FAP 1/2 expanded, times its
    amount (None when it moves no FAP)."""
    x = c.faps
    h = _expand(c.viseme, c.expression, geo)
    if h is not None:
        x = h if x is None else x + h
    if x is not None and c.amount != 1.0:
        x = c.amount * x
    return x


def _offsets_nz(c: Contribution, geo: Geometry) -> tuple[np.ndarray, np.ndarray | None] | None:
    """``_offsets`` of ``c`` and, for a contribution of high-level FAPs alone (an expression
    overlay's), where they are non-zero (``(69,)`` float 0/1; else None: ``x != 0`` when
    needed): those are remembered per geometry (read-only)."""
    if c.faps is not None:
        x = _offsets(c, geo)
        return None if x is None else (x, None)

    def make() -> tuple[np.ndarray, np.ndarray] | None:
        x = _offsets(c, geo)
        if x is None:
            return None
        x = np.array(x, dtype=np.float64)
        return x, (x != 0).astype(np.float64)

    return geo.remember((c.viseme, c.expression, c.amount), make)


def _rot(pitch: float, yaw: float, roll: float) -> list[list[float]]:
    """``Ry(yaw) · Rx(pitch) · Rz(roll)`` (radians), the rig's head rotation, as nested lists."""
    cp, sp, cy, sy = math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
    cr, sr = math.cos(roll), math.sin(roll)
    return [
        [cy * cr + sy * sp * sr, -cy * sr + sy * sp * cr, sy * cp],
        [cp * sr, cp * cr, -sp],
        [-sy * cr + cy * sp * sr, sy * sr + cy * sp * cr, cy * cp],
    ]


def _mv(R: list[list[float]], v: Sequence[float]) -> list[float]:
    return [R[i][0] * v[0] + R[i][1] * v[1] + R[i][2] * v[2] for i in range(3)]


def _mtv(R: list[list[float]], v: Sequence[float]) -> list[float]:
    return [R[0][i] * v[0] + R[1][i] * v[1] + R[2][i] * v[2] for i in range(3)]


def head_angles(head: np.ndarray, pivot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A head transform ``[R | t] (3, 4)`` as ``(pitch, yaw, roll)`` in AU (``R = Ry·Rx·Rz``) and
    the translation left over after rotating about ``pivot`` (mesh units)."""
    M = np.asarray(head, dtype=np.float64).reshape(3, 4)
    R = M[:, :3]
    return euler_from_matrix(R) / _AU, M[:, 3] - (pivot - R @ pivot)


def head_transform(
    angles: Sequence[float], pivot: np.ndarray, rest: np.ndarray | None = None
) -> np.ndarray:
    """``(3, 4)`` head transform of ``(pitch, yaw, roll)`` AU about ``pivot``, then ``rest``."""
    return about(np.array(_rot(*(float(a) * _AU for a in angles))), pivot, rest)


def eye_angles(direction: Sequence[float], axis: Sequence[float]) -> tuple[float, float]:
    """``(yaw, pitch)`` radians with ``Ry(yaw) · Rx(pitch) · axis`` along ``direction`` (head-local;
    ``axis`` the eyeball's unit neutral forward axis), limited to what eyes do (``EYE_YAW_MAX``,
    ``EYE_PITCH_MAX``: a target behind the head or inside the eye is looked at as far as they go)."""
    dx, dy, dz = direction
    n = math.sqrt(dx * dx + dy * dy + dz * dz)
    if not n > 1e-12:
        return 0.0, 0.0
    ax, ay, az = axis
    r = math.hypot(ay, az)
    pitch = math.acos(max(-1.0, min(1.0, dy / n / r))) - math.atan2(az, ay)
    uz = ay * math.sin(pitch) + az * math.cos(pitch)
    yaw = math.atan2(dx, dz) - math.atan2(ax, uz)
    yaw = (yaw + math.pi) % (2 * math.pi) - math.pi
    return max(-EYE_YAW_MAX, min(EYE_YAW_MAX, yaw)), max(-EYE_PITCH_MAX, min(EYE_PITCH_MAX, pitch))


def gaze_faps(
    target: GazeTarget, geo: Geometry, R: list[list[float]], t: Sequence[float]
) -> list[float]:
    """FAPs 23-26 (AU) turning both eyes to ``target`` under the head transform ``[R | t]``
    (nested lists): the eye centres move with the head, the target stays put. (An eye at ``c``
    sees a point ``p`` along ``Rᵀ(p - t) - c``, head-local, a direction ``u`` along ``Rᵀu``.)"""
    p = target.point
    if p is None:
        assert target.direction is not None
        return _eyes_to(_mtv(R, target.direction.tolist()), False, geo)
    px, py, pz = p.tolist()
    return _eyes_to(_mtv(R, (px - t[0], py - t[1], pz - t[2])), True, geo)


def _gaze_about_pivot(target: GazeTarget, geo: Geometry, angles: Sequence[float]) -> list[float]:
    """``gaze_faps`` under the head rotation ``angles`` (pitch, yaw, roll AU) about the head
    pivot ``pv``: ``Rᵀ(p - pv) + pv`` as three plane rotations (``R`` is not formed)."""
    p = target.point
    if p is None:
        assert target.direction is not None
        return _eyes_to(_unrotate1(angles, target.direction.tolist()), False, geo)
    pv = geo.pivot
    px, py, pz = p.tolist()
    x, y, z = _unrotate1(angles, (px - pv[0], py - pv[1], pz - pv[2]))
    return _eyes_to((x + pv[0], y + pv[1], z + pv[2]), True, geo)


def _unrotate1(angles: Sequence[float], q: Sequence[float]) -> tuple[float, float, float]:
    """``Rᵀ q`` for ``R = Ry(yaw)·Rx(pitch)·Rz(roll)`` of ``angles`` (pitch, yaw, roll AU)."""
    pitch, yaw, roll = angles[0] * _AU, angles[1] * _AU, angles[2] * _AU
    cp, sp, cy, sy = math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
    cr, sr = math.cos(roll), math.sin(roll)
    qx, qy, qz = q
    x, z = cy * qx - sy * qz, sy * qx + cy * qz  # Ryᵀ
    y, z = cp * qy + sp * z, cp * z - sp * qy  # Rxᵀ
    return cr * x + sr * y, cr * y - sr * x, z  # Rzᵀ


def _eyes_to(q: Sequence[float], point: bool, geo: Geometry) -> list[float]:
    """FAPs 23-26 (AU) of both eyes looking along ``q`` (head-local: a direction) or at ``q``
    (``point``: head-local, seen from each eye's centre): ``eye_angles`` of each eye, inlined
    with its axis' constants (``Geometry.eye_consts``)."""
    out = [0.0, 0.0, 0.0, 0.0]  # yaw l, r, pitch l, r
    qx, qy, qz = q
    left, right = geo.eye_consts
    for side, (cx, cy, cz, ax, ay, az, r, phi) in enumerate((left, right)):
        if side and not point and left[3:] == right[3:]:  # the same axis, the same direction
            out[1], out[3] = out[0], out[2]
            break
        dx, dy, dz = (qx - cx, qy - cy, qz - cz) if point else (qx, qy, qz)
        n = math.sqrt(dx * dx + dy * dy + dz * dz)
        if not n > 1e-12:
            continue
        pitch = math.acos(max(-1.0, min(1.0, dy / n / r))) - phi
        uz = ay * math.sin(pitch) + az * math.cos(pitch)
        yaw = math.atan2(dx, dz) - math.atan2(ax, uz)
        yaw = (yaw + math.pi) % (2 * math.pi) - math.pi
        out[side] = max(-EYE_YAW_MAX, min(EYE_YAW_MAX, yaw)) / _AU
        out[2 + side] = max(-EYE_PITCH_MAX, min(EYE_PITCH_MAX, pitch)) / _AU
    return out


_TOP, _BOTTOM = LIP_PAIRS[:, 0].copy(), LIP_PAIRS[:, 1].copy()
_PAIRS: tuple[tuple[int, int], ...] = tuple((int(a), int(b)) for a, b in LIP_PAIRS)
_LIPS = LIP_PAIRS.reshape(-1)


#: ``(69,)`` 1.0 on the mouth and tongue FAPs (``_SPEECH``), 0.0 elsewhere; its complement.
_SPEECH_F = _SPEECH.astype(np.float64)
_OTHER_F = 1.0 - _SPEECH_F
_ZEROS = np.zeros(69)
_ONES = np.ones(69)
for _a in (_SPEECH_F, _OTHER_F, _ZEROS, _ONES):
    _a.flags.writeable = False


#: The lips' width: the corners' stretch, inner and outer (FAPs 6, 7, 53, 54).
WIDTH: np.ndarray = np.array([6, 7, 53, 54])
_WIDTH = WIDTH.tolist()
#: The lips' FAPs (``REGIONS["lips"]``): a primary moving any of them shapes its mouth.
_LIPS_REGION: np.ndarray = np.array(REGIONS["lips"])


def primaries(
    prims: Sequence[FaceState | None], geo: Geometry, closures: bool
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray, np.ndarray]:
    """The primaries of ``B`` frames (None: the neutral face) as the batch mixes read them:
    ``(B, 69)`` their FAPs (a new array); ``(B, 69)`` the expansions of their visemes and
    expressions (None when none has one); ``(B, 69)`` of their expressions alone where they
    close the lips (None when none); ``(B,)`` bool which close the lips (``closures`` and a
    primary); ``(B,)`` bool which have a viseme or an expression."""
    B = len(prims)
    F = np.array([_NEUTRAL if p is None else p.faps for p in prims], dtype=np.float64)
    closing = np.array([closures and p is not None for p in prims], dtype=bool)
    high = np.array([p is not None and bool(p.viseme or p.expression) for p in prims], dtype=bool)
    H = E = None
    for r in np.flatnonzero(high).tolist():
        p = prims[r]
        assert p is not None
        H = np.zeros((B, 69)) if H is None else H
        H[r] = _expand(p.viseme, p.expression, geo)
        if closing[r] and p.expression is not None:
            E = np.zeros((B, 69)) if E is None else E
            E[r] = _expand(None, p.expression, geo)
    return F, H, E, closing, high


_NEUTRAL = np.zeros(69)
_NEUTRAL.flags.writeable = False


def mixed_states(
    F: np.ndarray, ts: Sequence[float], prims: Sequence[FaceState | None]
) -> list[FaceState]:
    """Each row of the mixed FAPs ``F (R, 69)`` as a ``FaceState`` at ``ts[r]``, keeping its
    primary's viseme, expression, controls, head and shapes (a row without a primary: FAPs only)."""
    return [
        FaceState(t=ts[r], faps=F[r])
        if p is None
        else FaceState(
            ts[r], F[r], p.viseme, p.expression, p.controls, p.head, p.shapes, p.shape_weights
        )
        for r, p in enumerate(prims)
    ]


def limit_mouth(F: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Offsets ``A (69,)`` over a speaking primary's FAPs ``F`` limited in the mouth and tongue
    (rule 4): where ``A`` moves a FAP the way ``F`` does, only what goes beyond ``F`` stays, so
    ``F + A`` is the larger of the two (opposite ways they add): ``A - clip(F, min(0, A),
    max(0, A))`` there; the lips' width (``WIDTH``) that ``A`` moves is the mean of the two,
    ``(F + A) / 2``. A new array."""
    f = F * _SPEECH_F
    np.maximum(f, np.minimum(A, _ZEROS), out=f)
    np.minimum(f, np.maximum(A, _ZEROS), out=f)
    out = A - f
    a = A.take(WIDTH).tolist()
    if a[0] or a[1] or a[2] or a[3]:
        w = F.take(WIDTH).tolist()
        out.put(WIDTH, [(x - y) / 2 if x else 0.0 for x, y in zip(a, w, strict=True)])
    return out


#: Closed upper lids (IRISD: one IRISD0 down, the idle layer's blink) and how much closure
#: (IRISD) a raised cheek (ENS) takes off them (rule 5, ``meet_lids``).
LIDS_MEET, LID_PER_CHEEK = 1024.0, 2.0
#: The upper lids' and cheeks' FAPs (left, right): close_t_*_eyelid, lift_*_cheek.
_LIDS_CHEEKS_AT = np.array([19, 20, 41, 42])


def meet_lids(F: np.ndarray, before: np.ndarray) -> None:
    """Rule 5's meeting lids, in place on the mixed FAPs ``F (..., 69)``: where an eye's upper lid
    or cheek differs from the primary's (``before (..., 4)``: FAPs 19, 20, 41, 42 of it), its
    upper lid closes at most ``max(0, LIDS_MEET - LID_PER_CHEEK · max(0, cheek))``."""
    lids, cheeks = F[..., 19:21], F[..., 41:43]
    cap = np.maximum(LIDS_MEET - LID_PER_CHEEK * np.maximum(cheeks, 0.0), 0.0)
    over = lids > cap
    if np.count_nonzero(over):  # (rare: a blink or closed lids over raised cheeks)
        over &= (lids != before[..., :2]) | (cheeks != before[..., 2:])
        F[..., 19:21] = np.where(over, cap, lids)


def _meet_lids1(F: np.ndarray, before: list[float]) -> None:
    """``meet_lids`` of one frame (``F (69,)``, ``before`` 4 floats), with Python floats."""
    after = F.take(_LIDS_CHEEKS_AT).tolist()
    if after == before:
        return
    for side in (0, 1):
        lid, cheek = after[side], after[2 + side]
        if lid != before[side] or cheek != before[2 + side]:
            cap = max(LIDS_MEET - LID_PER_CHEEK * max(cheek, 0.0), 0.0)
            if lid > cap:
                F[19 + side] = cap


def keep_closures(F: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Offsets ``A (69,)`` with the lip opening they would add to the primary's FAPs ``F`` taken out
    where ``F`` holds the lips closed (1 at or below ``CLOSED_GAP``, 0 from ``OPEN_GAP``); corners,
    spreading and the lips' common shift stay. Returns ``A`` itself when nothing changes, else a new array."""
    a = A.take(_LIPS).tolist()
    jaw = float(A[3])
    if jaw <= 0 and all(a[2 * i] + a[2 * i + 1] >= 0 for i in range(6)):
        return A  # the offsets open neither the lips nor the jaw
    f = F.take(_LIPS).tolist()
    span = OPEN_GAP - CLOSED_GAP
    out = None
    for i, (top, bottom) in enumerate(_PAIRS):
        x = (-(f[2 * i] + f[2 * i + 1]) - CLOSED_GAP) / span
        c = 1.0 if x <= 0.0 else 0.0 if x >= 1.0 else 1.0 - x * x * (3.0 - 2.0 * x)
        opening = -(a[2 * i] + a[2 * i + 1])
        if i == 0 and jaw > 0 and c > 0:
            out = A.copy() if out is None else out
            out[3] = jaw * (1.0 - c)
        if opening > 0 and c > 0:
            out = A.copy() if out is None else out
            cut = opening * c / 2
            out[top] += cut
            out[bottom] += cut
    return A if out is None else out


def combine(
    primary: FaceState | None,
    items: Sequence[tuple[Role, Contribution]],
    t: float | None = None,
    *,
    geometry: Geometry | None = None,
    closures: bool = True,
) -> FaceState:
    """Mix ``primary`` with the layers' contributions (``(role, contribution)`` pairs) by the
    module's rules into one ``FaceState`` at ``t`` (default: the primary's time).

    ``primary`` None is the neutral face (and no closures to keep); ``closures`` False lets
    overlays open the lips whatever the primary does (a primary that does not speak).
    ``geometry``: the face's (``Geometry.of_rig``); needed for gaze and for head poses over a
    primary ``head`` transform (the default has no eyes).
    """
    if primary is None:
        primary, closures = FaceState(t=0.0 if t is None else t), False
    t = primary.t if t is None else float(t)
    if not items:
        return primary if t == primary.t else dataclasses.replace(primary, t=t)
    geo = _DEFAULT_GEOMETRY if geometry is None else geometry
    F = np.array(primary.faps, dtype=np.float64)
    if F.shape != (69,):
        raise ValueError(f"FaceState.faps must have shape (69,), not {F.shape}")
    F[0] = F[1] = F[2] = 0.0
    high = (
        None
        if primary.viseme is None and primary.expression is None
        else _expand(primary.viseme, primary.expression, geo)
    )
    if high is not None:
        F += high

    # one pass over the contributions
    poses: list[tuple[np.ndarray, float]] = []
    gazes: list[tuple[GazeTarget, float]] = []
    overrides: list[tuple[np.ndarray, Any]] = []
    roles: dict[Role, list[tuple[np.ndarray, np.ndarray | None, Any]]] = {}
    for role, c in items:
        if c.head is not None and c.head_weight > 0:
            poses.append((c.head, c.head_weight))
        if c.gaze is not None and c.gaze_weight > 0:
            gazes.append((c.gaze, c.gaze_weight))
        if c.override is not None:
            overrides.append((c.override, c.override_weight))
        if c.faps is None and c.viseme is None and c.expression is None:
            continue
        xn = _offsets_nz(c, geo)
        if xn is None:
            continue
        group = roles.get(role)
        if group is None:
            roles[role] = [(*xn, c.weight)]
        else:
            group.append((*xn, c.weight))

    # 2. head pose over the primary's
    head_out = primary.head
    rest: np.ndarray | None = None
    if head_out is not None and (poses or any(_touches_head(c) for _, c in items)):
        F[48:51], rest = head_angles(head_out, geo.head_pivot)
    if poses:
        wsum = sum(w for _, w in poses)
        target = sum(np.asarray(p, dtype=np.float64) * w for p, w in poses) / wsum
        W = min(1.0, wsum)
        F[48:51] += W * (target - F[48:51])
        if rest is not None:
            rest = rest * (1.0 - W)

    # 3. offsets, averaged by weight inside a role (a layer weighs on the FAPs it moves);
    #    expression overlays also compete with the primary where it moves a FAP (weight 1),
    #    except a speaking primary's mouth and tongue, where speech and expression add
    if roles:
        A: Any = None
        for role, group in roles.items():
            P = None
            width = False  # a still primary's lips' width competes (rule 4)
            if role is Role.EXPRESSION:
                # what of the primary the overlays compete with: all of it, or, in a speaking
                # mouth, only its own expression (FAP 2), never the speech
                if not closures:
                    P = F
                    width = bool(F[_LIPS_REGION].any())
                elif primary.expression is None:
                    P = F * _OTHER_F
                else:
                    E = _expand(None, primary.expression, geo)
                    assert E is not None
                    P = np.where(_SPEECH, E, F)
            part = _role_part(group, P, width)
            A = part if A is None else A + part
        if closures:
            A = keep_closures(F, limit_mouth(F, A))
        F += A
        F[0] = F[1] = F[2] = 0.0

    # 5. overrides
    if overrides:
        num_o: Any = 0.0
        den_o: Any = 0.0
        for value, w in overrides:
            num_o = num_o + w * value
            den_o = den_o + w
        den = den_o
        if not (type(den) is np.ndarray and den.shape == (69,) and den.dtype == np.float64):
            den = np.broadcast_to(np.asarray(den_o, dtype=np.float64), (69,))
        on = den > 0
        target = np.divide(num_o, den, out=np.zeros(69), where=on)
        F = np.where(on, F + np.minimum(1.0, den) * (target - F), F)
    if F[19] > 0.0 or F[20] > 0.0:  # closing lids (rare): rule 5's meeting, against the primary's
        before = np.asarray(primary.faps, dtype=np.float64).take(_LIDS_CHEEKS_AT)
        _meet_lids1(F, (before if high is None else before + high.take(_LIDS_CHEEKS_AT)).tolist())

    # head transform of the mix
    if rest is not None:
        head_out = head_transform(F[48:51].tolist(), geo.head_pivot, rest)
        F[48:51] = 0.0

    # 6. gaze
    if gazes:
        if head_out is not None:
            H = np.asarray(head_out, dtype=np.float64).reshape(3, 4).tolist()
            R, tr = [row[:3] for row in H], [row[3] for row in H]

            def eyes_of(g: GazeTarget) -> list[float]:
                return gaze_faps(g, geo, R, tr)
        else:
            angles = F[48:51].tolist()

            def eyes_of(g: GazeTarget) -> list[float]:
                return _gaze_about_pivot(g, geo, angles)

        if len(gazes) == 1:
            g, W = gazes[0]
            eyes = eyes_of(g)
            W = min(1.0, W)
        else:
            wsum = 0.0
            eyes = [0.0, 0.0, 0.0, 0.0]
            for g, w in gazes:
                e = eyes_of(g)
                eyes = [a + w * b for a, b in zip(eyes, e, strict=True)]
                wsum += w
            eyes = [e / wsum for e in eyes]
            W = min(1.0, wsum)
        if W >= 1.0:
            F[23:27] = eyes
        else:
            F[23:27] += W * (np.array(eyes) - F[23:27])

    if high is not None:
        F -= high
        F[:3] = 0.0
    return FaceState(
        t=t,
        faps=F,
        viseme=primary.viseme,
        expression=primary.expression,
        controls=primary.controls,
        head=head_out,
        shapes=primary.shapes,
        shape_weights=primary.shape_weights,
    )


def _role_part(
    group: list[tuple[np.ndarray, np.ndarray | None, Any]],
    P: np.ndarray | None,
    width: bool = False,
) -> Any:
    """What one role's layers ``(x, nz, w)`` (offsets, where they are non-zero or None, weight)
    add: ``Σ w·x / max(1, Σ w·[x ≠ 0])``; with ``P``, the primary an expression overlay competes
    with (weight 1 where it is non-zero), ``(P + Σ w·x) / max(1, [P ≠ 0] + Σ w·[x ≠ 0]) - P``.
    ``width``: the primary's lips' width (``WIDTH``) competes even where it is 0 (rule 4: a
    still primary that moves its lips). May be ``x`` itself (read-only)."""
    x, nz, w = group[0]
    if len(group) == 1 and (type(w) is float or type(w) is int):
        if P is None:
            return x if w >= 1.0 else w * x
        if w <= 1.0 and not np.count_nonzero(P):
            return x if w == 1.0 else w * x  # Σ w ≤ 1, nothing to compete with: (P + w·x) / 1 - P
    if P is None and len(group) == 1:
        return _weighted(x, w)
    num: Any = 0.0
    den: Any = 0.0
    if len(group) == 1 and nz is not None and type(w) is float and w == 1.0:
        num, den = x, nz  # (0 + 1·x is x; read-only here)
    else:
        for x, nz, w in group:
            num = num + w * x
            den = den + w * (x != 0 if nz is None else nz)
    if P is None:
        return num / np.maximum(_ONES, den)
    d = (P != 0) + den
    if width:
        d[WIDTH] += P[WIDTH] == 0
    np.maximum(d, _ONES, out=d)
    part = P + num
    part /= d
    part -= P
    return part


def _weighted(x: np.ndarray, w: Any) -> np.ndarray:
    """``x`` of a layer alone in its role at weight ``w`` (float or ``(69,)``, capped at 1)."""
    if type(w) is float or type(w) is int:
        return x if w >= 1.0 else w * x
    return x * np.minimum(w, 1.0)


def _touches_head(c: Contribution) -> bool:
    """Whether ``c`` moves FAPs 48-50 (offsets or overrides)."""
    return any(v is not None and bool(np.any(v[48:51] != 0)) for v in (c.faps, c.override))


def mix(
    primary: FaceState | None,
    layers: Iterable[Layer],
    t: float | None = None,
    *,
    geometry: Geometry | None = None,
    closures: bool = True,
) -> FaceState:
    """Sample every layer at ``t`` (default: the primary's time) and ``combine`` them with
    ``primary``: the one pure entry point of a frame's mix."""
    if t is None:
        t = 0.0 if primary is None else primary.t
    items = [(layer.role, layer.sample(t)) for layer in layers]
    return combine(primary, items, t, geometry=geometry, closures=closures)


class Mixer:
    """A session's active layers by name, mixed with the primary of each frame.

    Thread-safe: ``set`` / ``remove`` / ``change`` may run on any thread while another mixes
    (``mix`` works on a snapshot taken under the lock). Layers whose ``end`` has passed are
    dropped as frames pass it.

    Args:
        geometry: the face's ``Geometry`` (gaze, head poses over transforms, high-level tables).
        closures: keep the primary's lip closures (False when the primary does not speak).
        max_layers: most layers held at once (``TooMany``... ``Conflict`` beyond it).
    """

    def __init__(
        self, geometry: Geometry | None = None, *, closures: bool = True, max_layers: int = 32
    ) -> None:
        self.geometry = geometry
        self.closures = closures
        self.max_layers = max_layers
        self._lock = threading.Lock()
        self._layers: dict[str, Layer] = {}
        self._next_end: float | None = None  # the earliest ``end`` of the layers (None: none ends)
        self._snapshot: tuple[tuple[Layer, ...], tuple[tuple[type, Role], ...]] = ((), ())

    def _changed(self) -> None:
        """Note the layers changed (call with the lock held): their earliest end, and the
        snapshot ``snapshot`` gives."""
        ends = [e for e in (lay.end for lay in self._layers.values()) if e is not None]
        self._next_end = min(ends) if ends else None
        layers = tuple(self._layers.values())
        self._snapshot = layers, tuple((type(lay), lay.role) for lay in layers)

    @staticmethod
    def _check_name(name: str) -> str:
        if not isinstance(name, str) or not 0 < len(name) <= 64 or not name.isprintable():
            raise InputError("a layer name is 1-64 printable characters")
        return name

    def set(self, name: str, layer: Layer) -> None:
        """Add ``layer`` as ``name``, replacing a layer of that name. ``Conflict`` when full."""
        if not isinstance(layer, Layer):
            raise TypeError(f"not a layer: {type(layer).__name__}")
        name = self._check_name(name)
        with self._lock:
            if name not in self._layers and len(self._layers) >= self.max_layers:
                raise Conflict(f"a session holds at most {self.max_layers} layers")
            self._layers[name] = layer
            self._changed()

    def add(self, name: str, layer: Layer) -> None:
        """Add ``layer`` as ``name``; ``Conflict`` if the name is taken."""
        with self._lock:
            if name in self._layers:
                raise Conflict(f"layer {name!r} exists already")
        self.set(name, layer)

    def remove(self, name: str) -> Layer | None:
        """Remove and return layer ``name`` (None if there was none)."""
        with self._lock:
            layer = self._layers.pop(name, None)
            self._changed()
            return layer

    def change(self, name: str, **fields: object) -> Layer:
        """Replace layer ``name`` by a copy with ``fields`` changed (layers are frozen dataclasses:
        ``change("smile", amount=0.5)``). ``NotFound`` without such a layer; ``InputError`` for a
        field the layer has not or a value it refuses."""
        with self._lock:
            layer = self._layers.get(name)
            if layer is None:
                raise NotFound(f"no layer {name!r}")
            try:
                new = dataclasses.replace(layer, **fields)  # type: ignore[type-var]
            except (TypeError, ValueError) as e:
                raise InputError(f"layer {name!r}: {e}") from None
            self._layers[name] = new
            self._changed()
            return new

    def get(self, name: str) -> Layer | None:
        with self._lock:
            return self._layers.get(name)

    def layers(self) -> dict[str, Layer]:
        """A snapshot: name -> layer, in the order they were added."""
        with self._lock:
            return dict(self._layers)

    def clear(self) -> None:
        with self._lock:
            self._layers.clear()
            self._changed()

    def __len__(self) -> int:
        return len(self._layers)

    def mix(self, primary: FaceState | None, t: float | None = None) -> FaceState:
        """The mixed state of this frame (``mix`` of the active layers); drops ended layers."""
        if t is None:
            t = 0.0 if primary is None else primary.t
        return combine(primary, self.items(t), t, geometry=self.geometry, closures=self.closures)

    def items(
        self, t: float, layers: Iterable[Layer] | None = None
    ) -> list[tuple[Role, Contribution]]:
        """The active layers (or ``layers``, from ``active``) sampled at ``t`` (``combine``'s
        items); drops ended layers."""
        return [
            (layer.role, layer.sample(t))
            for layer in (self.active(t) if layers is None else layers)
        ]

    def active(self, t: float) -> list[Layer]:
        """The layers at ``t``, in the order they were added; drops those whose end passed."""
        return list(self.snapshot(t)[0])

    def snapshot(self, t: float) -> tuple[tuple[Layer, ...], tuple[tuple[type, Role], ...]]:
        """``active(t)`` as a tuple, and each layer's ``(type, role)`` (the same objects until
        the layers change: ``batch.mix_batch`` samples the frames of alike mixers together)."""
        with self._lock:
            end = self._next_end
            if end is not None and end < t:
                for n, lay in list(self._layers.items()):
                    if lay.end is not None and lay.end < t:
                        del self._layers[n]
                self._changed()
            return self._snapshot


def mix_states(
    states: Sequence[FaceState],
    layers: Sequence[Layer],
    *,
    geometry: Geometry | None = None,
    closures: bool = True,
) -> list[FaceState]:
    """``mix`` of every state of a stream (each at its own time) with ``layers``: a batch render's
    layered animation, sampled and combined together (as ``batch.mix_batch``). Without layers the states
    themselves are returned (same objects)."""
    if not layers:
        return list(states)
    from .batch import combine_columns, sample_columns  # (batch imports this module)

    geo = _DEFAULT_GEOMETRY if geometry is None else geometry
    out = list(states)
    rows = []
    for i, s in enumerate(states):
        if s.head is None and np.shape(s.faps) == (69,):
            rows.append(i)
        else:  # a head transform (or FAPs ``combine`` refuses): one by one
            out[i] = mix(s, layers, s.t, geometry=geometry, closures=closures)
    for k in range(0, len(rows), _CHUNK):
        chunk = rows[k : k + _CHUNK]
        prims = [states[i] for i in chunk]
        ts = [float(s.t) for s in prims]
        entries = [(r, layer, ts[r]) for r in range(len(chunk)) for layer in layers]
        mixed = combine_columns(prims, ts, sample_columns(entries, geo), geo, closures)
        for i, state in zip(chunk, mixed, strict=True):
            out[i] = state
    return out


#: Most frames ``mix_states`` mixes in one go (bounds its arrays' memory: ~0.5 MB each).
_CHUNK = 1024
