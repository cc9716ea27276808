"""FAPs -> control displacements ``D (K, 3)`` and rigid transforms ``(G, 3, 4)`` for one face.

The decoder side of MPEG-4 for a face with feature points (``docs/mpeg4-reference.md``; the
feature-point method of Kshirsagar et al., ``research/seed-000-A.md`` §5):

- **Controls** (``fap_controls``): every feature point the face has on a deformable vertex.
  FPs without a FAP are anchors (displacement 0). FPs on rigid parts (pupil centres 3.5/3.6 on
  the eyeballs, teeth points 9.8-9.11) are not controls: those parts move by their rigid
  transforms. FPs that share a vertex share one control.
- **Per-axis rule**: by default every control is constrained on x, y and z; a FAP-driven FP keeps
  its neutral coordinate on the axes no FAP of it moves (as in a FAT, an FP moves only along its
  FAP directions). With ``per_axis=True`` a FAP-driven FP is constrained only on the axes its
  FAPs move (2.2: y by FAP 4, z by FAP 17) and left free on the others for the operator to
  interpolate, as Kshirsagar et al. describe; jaw riders, tongue points and anchors stay
  constrained on all axes. All-axes is the default because it looked clearly better: on the
  built-in head, joy.fap frame 56 with the ``fp`` engine shows cracks across both cheeks with
  per-axis constraints and a smooth surface with all axes constrained.
- **Translations**: FP displacement = value x FAPU x + direction, summed over the FAPs of the FP,
  in head-local space (the deformer then applies the head transform). Low-level lip FAPs are taken
  as absolute displacements from the neutral face (not relative to the jaw): the Xface files drop
  the lower lip (FAP 5) together with the jaw (FAP 3) by similar amounts.
- **Jaw** (FAPs 3, 14, 15): a rigid transform of the ``jaw`` group (lower teeth, lower gums,
  tongue): rotation about the x axis through ``face.pivot("jaw")`` by the angle that drops FP 2.1
  by ``open_jaw x MNS``, then translation by ``thrust_jaw x MNS`` (+z) and ``shift_jaw x MW`` (-x).
  The skin chin points follow it (plus FAP 18 on 2.10). The angle is capped at ``MAX_JAW``; any
  drop the capped rotation cannot reach is added as a downward translation, so 2.1 always drops
  by exactly the FAP amount.
- **Tongue** (43-47): displacements of 6.1-6.4 in jaw-local space (the tongue rides the jaw);
  ``tongue_roll`` lifts 6.3/6.4 by ``tan(angle) x`` their distance from 6.2 across the tongue.
- **Eyeballs** (23-28): yaw about +y, pitch about +x through the eyeball centre
  (``face.pivot("eye_l"/"eye_r")``), then ``thrust x ES`` along +z. Pupil dilation (29/30) has no
  geometry on a rigid eyeball and is ignored.
- **Head** (48-50): ``R = Ry(yaw) · Rx(pitch) · Rz(roll)`` about ``face.pivot("head")`` (FP 7.1);
  ``FaceState.head`` replaces it when given. Every group transform is composed with it.

Negative values of unidirectional FAPs (real files have them) are applied as they are.
"""

from __future__ import annotations

import logging

import numpy as np

from ..faces.face import RIGID_GROUPS
from .fapu import measure_fapu
from .highlevel import EXPRESSIONS, VISEMES, expand
from .tables import FAPS, FEATURE_POINTS, FP_FAPS, JAW_SKIN_FPS, TONGUE_FPS

log = logging.getLogger(__name__)

G = len(RIGID_GROUPS)
#: Largest jaw rotation (rad); a drop beyond it (a pivot almost straight above the chin) is translated.
MAX_JAW = 0.5
_HEAD, _JAW, _EYE_L, _EYE_R = (RIGID_GROUPS.index(n) for n in ("head", "jaw", "eye_l", "eye_r"))


def fap_controls(face, *, per_axis: bool = False) -> tuple[list[str], np.ndarray, np.ndarray]:
    """The face's FAP control set: ``(fp_ids, vertex_ids (K,) int32, constrained (K, 3) bool)``.

    ``fp_ids[i]`` names the feature point(s) of control i (``"2.2"``, or ``"2.2+8.1"`` when
    several FPs sit on one vertex). See the module docstring for the per-axis rule.
    """
    deformable = face.deformable
    order: list[int] = []
    names: dict[int, list[str]] = {}
    axes: dict[int, np.ndarray] = {}
    for fp in FEATURE_POINTS:
        if fp not in face.feature_points:
            continue
        v = face.feature_points[fp]
        if not deformable[v]:
            continue
        c = _constrained_axes(fp) if per_axis else np.ones(3, dtype=bool)
        if v not in names:
            order.append(v)
            names[v], axes[v] = [], np.zeros(3, dtype=bool)
        names[v].append(fp)
        axes[v] |= c
    return (
        ["+".join(names[v]) for v in order],
        np.array(order, dtype=np.int32),
        np.array([axes[v] for v in order], dtype=bool).reshape(-1, 3),
    )


def _constrained_axes(fp: str) -> np.ndarray:
    if fp in JAW_SKIN_FPS or fp in TONGUE_FPS:
        return np.ones(3, dtype=bool)
    faps = [FAPS[k - 1] for k in FP_FAPS.get(fp, ()) if FAPS[k - 1].kind == "move"]
    if not faps:
        return np.ones(3, dtype=bool)  # anchor
    return np.any([np.abs(f.vector) > 0 for f in faps], axis=0)


def _table(given, from_face, default: np.ndarray) -> np.ndarray:
    """The first of ``given``, ``from_face``, ``default`` that is set, as a float64 array of its shape."""
    for t in (given, from_face):
        if t is not None:
            t = np.asarray(t, dtype=np.float64)
            if t.shape != default.shape:
                raise ValueError(f"high-level table must have shape {default.shape}, not {t.shape}")
            return t
    return default


def rotation(axis: str, angle: float) -> np.ndarray:
    """``(3, 3)`` right-hand rotation by ``angle`` radians about ``x``, ``y`` or ``z``."""
    c, s = np.cos(angle), np.sin(angle)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def about(R: np.ndarray, pivot: np.ndarray, t: np.ndarray | None = None) -> np.ndarray:
    """``(3, 4)`` transform ``x -> R (x - pivot) + pivot + t``."""
    out = np.empty((3, 4))
    out[:, :3] = R
    out[:, 3] = pivot - R @ pivot + (0 if t is None else t)
    return out


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(3, 4)`` transform ``a ∘ b`` (apply b, then a)."""
    out = np.empty((3, 4))
    out[:, :3] = a[:, :3] @ b[:, :3]
    out[:, 3] = a[:, :3] @ b[:, 3] + a[:, 3]
    return out


def jaw_angle(chin: np.ndarray, pivot: np.ndarray, drop: float) -> float:
    """Angle (rad, right-hand about +x) that lowers ``chin`` by ``drop`` when rotating about ``pivot``.

    With ``r = chin - pivot = (., ry, rz)`` the chin height after rotation is
    ``ry cos a - rz sin a``; solves ``rz sin a + ry (1 - cos a) = drop`` (clamped at the reachable
    extreme).
    """
    ry, rz = float(chin[1] - pivot[1]), float(chin[2] - pivot[2])
    r = np.hypot(ry, rz)
    if r == 0:
        return 0.0
    # rz sin a - ry cos a = drop - ry  <=>  r sin(a + phi) = drop - ry, phi = atan2(-ry, rz)
    phi = np.arctan2(-ry, rz)
    return float(np.arcsin(np.clip((drop - ry) / r, -1.0, 1.0)) - phi)


class FapRig:
    """Turns ``FaceState`` s into control displacements and rigid transforms for one face.

    Args:
        face: the ``Face`` (needs the FAPU feature points, see ``measure_fapu``).
        control_vertices: ``(K,)`` vertex ids of an explicit control set (mocap markers); then
            ``D = state.controls`` (zeros when None) and FAPs drive only the jaw, eyes and head.
        per_axis: constrain FAP-driven FPs only on their FAP axes (see the module docstring).
        visemes, expressions: ``(15, 69)`` / ``(7, 69)`` high-level tables (default: the face's
            ``visemes`` / ``expressions`` attributes if it has them, else ``highlevel``'s).

    Attributes:
        fapu: ``measure_fapu(face)``.
        control_vertices: ``(K,) int32``; ``constrained``: ``(K, 3) bool``; ``fp_ids``: names.
    """

    def __init__(
        self,
        face,
        control_vertices: np.ndarray | None = None,
        *,
        per_axis: bool = False,
        visemes: np.ndarray | None = None,
        expressions: np.ndarray | None = None,
    ):
        self.face = face
        self.fapu = measure_fapu(face)
        self.visemes = _table(visemes, getattr(face, "visemes", None), VISEMES)
        self.expressions = _table(expressions, getattr(face, "expressions", None), EXPRESSIONS)
        self.explicit = control_vertices is not None
        if self.explicit:
            self.control_vertices = np.asarray(control_vertices, dtype=np.int32).reshape(-1)
            self.constrained = np.ones((len(self.control_vertices), 3), dtype=bool)
            self.fp_ids: list[str] = []
        else:
            self.fp_ids, self.control_vertices, self.constrained = fap_controls(
                face, per_axis=per_axis
            )
        self.n_controls = len(self.control_vertices)
        self._pivots = {g: face.pivot(g) for g in RIGID_GROUPS}
        self._pivot_rows = np.array([self._pivots[g] for g in RIGID_GROUPS], dtype=np.float64)
        self._chin = face.fp_position("2.1") if "2.1" in face.feature_points else None
        self._build_linear()

    # -- precomputation -----------------------------------------------------------------------
    def _build_linear(self) -> None:
        """``_M (K, 3, 69)``: D from the translation FAPs; jaw riders; tongue-roll lever arms."""
        K = self.n_controls
        self._M = np.zeros((K, 3, 69))
        self._jaw_riders = np.zeros(0, dtype=np.int64)
        self._roll = (np.zeros(0, dtype=np.int64), np.zeros(0))
        if self.explicit:
            return
        index = {fp: i for i, names in enumerate(self.fp_ids) for fp in names.split("+")}
        for f in FAPS:
            if f.kind != "move" or not f.unit:
                continue
            for fp in f.fps:
                if fp in index:
                    self._M[index[fp], :, f.number] += f.vector * self.fapu[f.unit]
        self._M *= self.constrained[:, :, None]
        self._jaw_riders = np.array([index[p] for p in JAW_SKIN_FPS if p in index], dtype=np.int64)
        self._rider_pos = self.face.vertices[self.control_vertices[self._jaw_riders]].astype(
            np.float64
        )
        if "6.2" in self.face.feature_points:
            mid = self.face.fp_position("6.2")
            ids, arms = [], []
            for p in ("6.3", "6.4"):
                if p in index:
                    ids.append(index[p])
                    arms.append(abs(self.face.fp_position(p)[0] - mid[0]))
            self._roll = (np.array(ids, dtype=np.int64), np.array(arms))

    # -- per frame ----------------------------------------------------------------------------
    def faps(self, state) -> np.ndarray:
        """``(69,) float64`` low-level FAPs of ``state`` with FAP 1/2 expanded."""
        return expand(state, self.visemes, self.expressions)

    def local_transforms(self, faps: np.ndarray) -> np.ndarray:
        """``(G, 3, 4) float64`` group transforms in head-local space (head slot = identity)."""
        u = self.fapu
        T = np.zeros((G, 3, 4))
        T[:, :, :3] = np.eye(3)
        # Jaw: rotate so that 2.1 drops by open_jaw, then thrust (+z) and shift (-x).
        pivot = self._pivots["jaw"]
        drop = faps[3] * u["MNS"]
        t = np.array([-faps[15] * u["MW"], 0.0, faps[14] * u["MNS"]])
        R = np.eye(3)
        if self._chin is not None and drop:
            R = rotation("x", float(np.clip(jaw_angle(self._chin, pivot, drop), -MAX_JAW, MAX_JAW)))
            t[1] -= drop - (
                self._chin[1] - (R @ (self._chin - pivot) + pivot)[1]
            )  # rest of the drop
        T[_JAW] = about(R, pivot, t)
        # Eyeballs: yaw (+y), pitch (+x) about the centre, then thrust along +z.
        for g, (yaw, pitch, thrust) in ((_EYE_L, (23, 25, 27)), (_EYE_R, (24, 26, 28))):
            R = rotation("y", faps[yaw] * u["AU"]) @ rotation("x", faps[pitch] * u["AU"])
            T[g] = about(
                R, self._pivots[RIGID_GROUPS[g]], np.array([0.0, 0.0, faps[thrust] * u["ES"]])
            )
        return T

    def head_transform(self, state, faps: np.ndarray) -> np.ndarray:
        """``(3, 4)`` head pose: ``state.head`` if given, else FAPs 48-50 about the head pivot."""
        if state.head is not None:
            return np.asarray(state.head, dtype=np.float64).reshape(3, 4)
        au = self.fapu["AU"]
        R = (
            rotation("y", faps[49] * au)
            @ rotation("x", faps[48] * au)
            @ rotation("z", faps[50] * au)
        )
        return about(R, self._pivots["head"])

    def solve(self, state) -> tuple[np.ndarray, np.ndarray]:
        """``state`` -> ``(D (K, 3) float32, transforms (G, 3, 4) float32)`` for the deformer.

        The first row of ``solve_batch([state])``: one state and a batch give the same bits.
        """
        D, T = self.solve_batch([state])
        return D[0], T[0]

    def solve_batch(self, states) -> tuple[np.ndarray, np.ndarray]:
        """``T`` states -> ``(D (T, K, 3) float32, transforms (T, G, 3, 4) float32)``.

        Vectorised over the states with elementwise float64 operations only (no BLAS): row ``i``
        is the same bits whatever else is in the batch, so live frames (deformed in batches of
        any size) equal a batch render. Raises as ``expand`` does for an invalid state.
        """
        n = len(states)
        F = self._faps_rows(states)
        local = self._transforms_batch(states, F)  # slot head: the head pose itself
        transforms = np.empty((n, G, 3, 4))
        transforms[:, _HEAD] = local[:, _HEAD]
        transforms[:, 1:] = _compose_batch(local[:, _HEAD, None], local[:, 1:])
        if self.explicit:
            D = np.zeros((n, self.n_controls, 3), dtype=np.float32)
            for i, s in enumerate(states):
                if s.controls is not None:
                    D[i] = np.asarray(s.controls, dtype=np.float32).reshape(self.n_controls, 3)
            return D, transforms.astype(np.float32)
        D = self._linear_batch(F)
        if len(self._jaw_riders):
            J = local[:, _JAW]  # (n, 3, 4)
            p = self._rider_pos  # (R, 3)
            moved = _apply_batch(J[:, None], p[None])  # (n, R, 3)
            D[:, self._jaw_riders] += moved - p
        ids, arms = self._roll
        if len(ids):
            roll = F[:, 47]
            lift = np.tan(roll * self.fapu["AU"])[:, None] * arms  # (n, len(ids))
            D[:, ids, 1] += np.where((roll != 0)[:, None], lift, 0.0)
        return D.astype(np.float32), transforms.astype(np.float32)

    # -- batched helpers (elementwise, so every row is independent of the batch) ---------------
    def _faps_rows(self, states) -> np.ndarray:
        """``(T, 69) float64``: ``faps(state)`` of each state."""
        F = np.empty((len(states), 69))
        for i, s in enumerate(states):
            if s.viseme is None and s.expression is None and np.shape(s.faps) == (69,):
                F[i] = s.faps  # what ``expand`` does when there is nothing to add
                F[i, :3] = 0.0
            else:
                F[i] = self.faps(s)
        return F

    def _linear_batch(self, F: np.ndarray) -> np.ndarray:
        """``(T, K, 3) float64``: ``_M @ faps`` of each row, as a sum over the non-zeros of ``_M``."""
        if not hasattr(self, "_sparse"):
            # row r of _M as its non-zeros (column, value), padded with column 0: FAP 0 is always
            # 0 in ``F`` (as in ``expand``), so padding adds exact zeros
            M = self._M.reshape(-1, 69)
            nz = [np.flatnonzero(row) for row in M]
            width = max((len(c) for c in nz), default=0)
            cols = np.zeros((width, len(nz)), dtype=np.int64)
            vals = np.zeros((width, len(nz)))
            for r, c in enumerate(nz):
                cols[: len(c), r], vals[: len(c), r] = c, M[r, c]
            self._sparse = (cols, vals)
        cols, vals = self._sparse
        D = np.zeros((F.shape[0], cols.shape[1]))
        for c, v in zip(cols, vals):  # the j-th non-zero of every row
            D += F[:, c] * v
        return D.reshape(F.shape[0], self.n_controls, 3)

    def _transforms_batch(self, states, F: np.ndarray) -> np.ndarray:
        """``(T, G, 3, 4) float64``: slot ``head`` is ``head_transform``, the other slots are
        ``local_transforms``, of each state and row of ``F``. All groups at once: one ``cos`` and
        one ``sin`` call for all the angles, one ``about`` for all the pivots."""
        u = self.fapu
        n = F.shape[0]
        drop = F[:, 3] * u["MNS"]
        moves = drop != 0
        rotates = moves if self._chin is not None else np.zeros(n, dtype=bool)
        # angles: jaw; yaw of eye_l, eye_r, head; pitch of eye_l, eye_r, head; head roll
        A = np.empty((n, 8))
        A[:, 1:] = F[:, [23, 24, 49, 25, 26, 48, 50]] * u["AU"]
        pivot = self._pivots["jaw"]
        if self._chin is not None:
            chin = np.asarray(self._chin, dtype=np.float64)
            jaw = np.clip(_jaw_angles(chin, pivot, drop), -MAX_JAW, MAX_JAW)
            A[:, 0] = np.where(rotates, jaw, 0.0)
        else:
            A[:, 0] = 0.0
        C, S = np.cos(A), np.sin(A)
        R = np.zeros((n, G, 3, 3))
        # Ry(yaw) · Rx(pitch) of the eyeballs and the head; the head then · Rz(roll)
        Y = _ry_rx(C[:, 1:4], S[:, 1:4], C[:, 4:7], S[:, 4:7])  # (n, 3, 3, 3)
        R[:, _EYE_L], R[:, _EYE_R] = Y[:, 0], Y[:, 1]
        Yh, cz, sz = Y[:, 2], C[:, 7:8], S[:, 7:8]
        R[:, _HEAD, :, 0] = Yh[:, :, 0] * cz + Yh[:, :, 1] * sz
        R[:, _HEAD, :, 1] = Yh[:, :, 0] * -sz + Yh[:, :, 1] * cz
        R[:, _HEAD, :, 2] = Yh[:, :, 2]
        # Jaw: rotate about x so that 2.1 drops by open_jaw, then thrust (+z) and shift (-x).
        c, s = C[:, 0], S[:, 0]
        R[:, _JAW, 0, 0] = 1.0
        R[:, _JAW, 1, 1], R[:, _JAW, 2, 2], R[:, _JAW, 2, 1] = c, c, s
        R[:, _JAW, 1, 2] = np.where(rotates, -s, 0.0)  # (an identity is exactly np.eye)
        t = np.zeros((n, G, 3))
        t[:, _JAW, 0] = -F[:, 15] * u["MW"]
        t[:, _JAW, 2] = F[:, 14] * u["MNS"]
        if self._chin is not None:
            w = chin - pivot
            y = (c * w[1] + -s * w[2]) + pivot[1]  # height of the rotated chin
            t[:, _JAW, 1] -= np.where(moves, drop - (chin[1] - y), 0.0)  # the rest of the drop
        # Eyeballs: thrust along +z after the rotation about their centres.
        t[:, _EYE_L, 2] = F[:, 27] * u["ES"]
        t[:, _EYE_R, 2] = F[:, 28] * u["ES"]
        out = _about_batch(R, self._pivot_rows, t)
        for i, st in enumerate(states):
            if st.head is not None:
                out[i, _HEAD] = np.asarray(st.head, dtype=np.float64).reshape(3, 4)
        return out


def _jaw_angles(chin: np.ndarray, pivot: np.ndarray, drop: np.ndarray) -> np.ndarray:
    """``jaw_angle`` of every drop in ``drop (T,)``."""
    ry, rz = float(chin[1] - pivot[1]), float(chin[2] - pivot[2])
    r = np.hypot(ry, rz)
    if r == 0:
        return np.zeros_like(drop)
    phi = np.arctan2(-ry, rz)
    return np.arcsin(np.clip((drop - ry) / r, -1.0, 1.0)) - phi


def _ry_rx(cy: np.ndarray, sy: np.ndarray, cx: np.ndarray, sx: np.ndarray) -> np.ndarray:
    """``(..., 3, 3)``: ``Ry(yaw) · Rx(pitch)`` from the cosines and sines ``(...)`` of the angles."""
    R = np.zeros(cy.shape + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 0, 2] = cy, sy * sx, sy * cx
    R[..., 1, 1], R[..., 1, 2] = cx, -sx
    R[..., 2, 0], R[..., 2, 1], R[..., 2, 2] = -sy, cy * sx, cy * cx
    return R


def _matvec(R: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``R (..., 3, 3) · x (..., 3)``, summed in the order 0, 1, 2."""
    return (R[..., 0] * x[..., None, 0] + R[..., 1] * x[..., None, 1]) + R[..., 2] * x[..., None, 2]


def _about_batch(R: np.ndarray, pivot: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(T, 3, 4)``: ``about`` for rotations ``R (T, 3, 3)`` and translations ``t (T, 3)``."""
    out = np.empty(R.shape[:-2] + (3, 4))
    out[..., :3] = R
    out[..., 3] = (pivot - _matvec(R, pivot)) + t
    return out


def _apply_batch(M: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Points ``p (..., 3)`` moved by transforms ``M (..., 3, 4)``."""
    return _matvec(M[..., :3], p) + M[..., 3]


def _compose_batch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(..., 3, 4)``: ``compose(a, b)`` (apply b, then a), broadcasting over leading axes."""
    A = a[..., :3]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., :3] = (A[..., :, 0:1] * b[..., 0:1, :3] + A[..., :, 1:2] * b[..., 1:2, :3]) + A[
        ..., :, 2:3
    ] * b[..., 2:3, :3]
    out[..., 3] = _matvec(A, b[..., 3]) + a[..., 3]
    return out
