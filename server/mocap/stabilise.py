"""Head stabilisation: the rigid head motion from the stable markers, removed from all markers.

The thesis (Sánchez Lorenzo 2006 §4.2.3) fits the rigid transform that best maps the stable markers
of the neutral frame onto the current frame (least squares) by Gauss-Newton on an exponential map;
the same optimum has a closed form (Kabsch / Horn: SVD of the cross-covariance, with a reflection
guard), used here. With exactly three stable markers, Kshirsagar's construction (two difference
unit vectors and their cross product as a third, R = M' M^-1, re-orthonormalised) is available.
Convention: ``frame ~= R @ neutral + t``; stabilised = ``R.T @ (frame - t)``.

Batch takes refine the poses with every marker (``refine_poses``): the face moves in few ways, so
each frame's stabilised markers are split, by least squares, into a small rigid motion (what the
stable markers got wrong) and a combination of the take's own principal motions.
"""

from __future__ import annotations

import numpy as np

from .prior import ramp

__all__ = [
    "ShapePose",
    "check_stable",
    "compose_correction",
    "euler_from_matrix",
    "head_track",
    "hold_pose",
    "kabsch",
    "matrix_from_euler",
    "pose_in_frame",
    "pose_uncertainty",
    "refine_poses",
    "remove_head",
    "rigid_fields",
    "rigidity_weights",
    "robust_pose",
    "smooth_poses",
    "solve_pose",
    "start_neutral",
    "three_marker",
    "to_matrix",
]


def kabsch(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid ``(R (3,3), t (3,))`` with ``dst ~= src @ R.T + t`` for ``(N, 3)`` points
    (N >= 3, not collinear). A reflection (det < 0) is never returned."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    cs, cd = w @ src, w @ dst
    h = (src - cs).T @ ((dst - cd) * w[:, None])
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cd - r @ cs


def _orthonormalise(m: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


def three_marker(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kshirsagar's rigid pose from three markers ``(3, 3)`` (rows = markers): with unit difference
    vectors ``m1 = p2 - p1``, ``m2 = p3 - p2`` and ``m3 = m1 x m2`` (normalised) in both frames,
    ``R = M' M^-1`` (re-orthonormalised by SVD, since data is noisy) and ``t = p'_1 - R p_1``."""

    def frame(p: np.ndarray) -> np.ndarray:
        m1 = p[1] - p[0]
        m2 = p[2] - p[1]
        m1 = m1 / np.linalg.norm(m1)
        m2 = m2 / np.linalg.norm(m2)
        m3 = np.cross(m1, m2)
        m3 = m3 / np.linalg.norm(m3)
        return np.c_[m1, m2, m3]

    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    r = _orthonormalise(frame(dst) @ np.linalg.inv(frame(src)))
    # the translation that best fits all three, not just p1 (identical for exact data)
    return r, dst.mean(axis=0) - r @ src.mean(axis=0)


def solve_pose(
    neutral: np.ndarray, frame: np.ndarray, method: str = "auto"
) -> tuple[np.ndarray, np.ndarray] | None:
    """Pose of one frame from ``(S, 3)`` stable markers (NaN = occluded) against their neutral
    positions; None with fewer than 3 visible (or degenerate). ``method``: ``kabsch``, ``three``
    (Kshirsagar, needs exactly 3 visible) or ``auto`` (three-marker when exactly 3 are visible)."""
    ok = np.isfinite(frame).all(axis=1) & np.isfinite(neutral).all(axis=1)
    n = int(ok.sum())
    if n < 3:
        return None
    src, dst = neutral[ok], frame[ok]
    spread = np.linalg.svd(src - src.mean(axis=0), compute_uv=False)
    if spread[1] < 1e-6 * max(spread[0], 1e-12):
        return None  # collinear: rotation about the line is undetermined
    if method == "three" or (method == "auto" and n == 3):
        return three_marker(src[:3], dst[:3])
    return kabsch(src, dst)


def head_track(
    xyz: np.ndarray,
    stable: np.ndarray,
    neutral: np.ndarray,
    method: str = "auto",
    refine: int = 2,
    observed: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-frame head pose of ``(T, M, 3)`` markers from the ``stable`` marker indices against the
    ``(M, 3)`` neutral. Returns ``(R (T, 3, 3), t (T, 3), solved (T,) bool)``; a frame with fewer than
    3 visible stable markers takes the pose of the nearest solved frame (identity if none).

    With ``refine`` > 0 the reference shape of the stable markers is re-estimated as the mean of
    their stabilised positions over the take and the poses solved again (generalised Procrustes),
    so that the noise of one neutral frame does not tilt every pose; the reference is re-anchored
    on the neutral frame's pose each time, so poses stay relative to the neutral.

    ``observed`` ``(T, M) bool`` marks samples that were measured (not gap-filled): a frame with at
    least 3 measured stable markers is solved from those only.
    """
    ref = np.asarray(neutral, dtype=np.float64)[stable]
    xs = np.asarray(xyz, dtype=np.float64)[:, stable]
    if observed is not None:
        obs = np.asarray(observed, dtype=bool)[:, stable]
        use = obs & (obs.sum(axis=1, keepdims=True) >= 3) | (obs.sum(axis=1, keepdims=True) < 3)
        xs = np.where(use[..., None], xs, np.nan)
    rs, ts, solved = _track(xs, ref, method)
    for _ in range(refine if solved.sum() > 1 else 0):
        loc = remove_head(xs[solved], rs[solved], ts[solved])
        mean = np.nanmean(loc, axis=0)
        ok = np.isfinite(mean).all(axis=1)
        if ok.sum() < 3:
            break
        # express the mean shape in the neutral frame's pose (least squares onto the old reference)
        fit = kabsch(mean[ok], ref[ok])
        new = mean @ fit[0].T + fit[1]
        ref = np.where(ok[:, None], new, ref)
        rs, ts, solved = _track(xs, ref, method)
    return rs, ts, solved


def _track(
    xs: np.ndarray, ref: np.ndarray, method: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t_n = len(xs)
    rs = np.tile(np.eye(3), (t_n, 1, 1))
    ts = np.zeros((t_n, 3))
    solved = np.zeros(t_n, dtype=bool)
    for f in range(t_n):
        pose = solve_pose(ref, xs[f], method)
        if pose is not None:
            rs[f], ts[f] = pose
            solved[f] = True
    if solved.any() and not solved.all():
        idx = np.flatnonzero(solved)
        nearest = idx[np.clip(np.searchsorted(idx, np.arange(t_n)), 0, len(idx) - 1)]
        prev = idx[np.clip(np.searchsorted(idx, np.arange(t_n)) - 1, 0, len(idx) - 1)]
        pick = np.where(
            np.abs(prev - np.arange(t_n)) <= np.abs(nearest - np.arange(t_n)), prev, nearest
        )
        rs[~solved], ts[~solved] = rs[pick[~solved]], ts[pick[~solved]]
    return rs, ts, solved


def remove_head(xyz: np.ndarray, r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Stabilised markers ``R^T (x - t)``: ``(T, M, 3)`` with ``r (T, 3, 3)``, ``t (T, 3)`` (or one
    frame ``(M, 3)`` with ``(3, 3)``, ``(3,)``)."""
    return np.einsum("...mj,...jk->...mk", np.asarray(xyz) - t[..., None, :], r)


def to_matrix(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(..., 3, 4)`` ``[R | t]``."""
    return np.concatenate([r, t[..., :, None]], axis=-1)


def pose_in_frame(
    r: np.ndarray, t: np.ndarray, q: np.ndarray, s: float, c: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """A rigid motion ``x' = R x + t`` of capture space expressed in another frame ``f = s Q x + c``
    (e.g. the face's): ``R_f = Q R Q^T``, ``t_f = c - R_f c + s Q t``. Works on stacks ``(..., 3, 3)``."""
    rf = q @ r @ q.T
    tf = c - np.einsum("...ij,j->...i", rf, c) + s * np.einsum("ij,...j->...i", q, t)
    return rf, tf


def euler_from_matrix(r: np.ndarray) -> np.ndarray:
    """``(..., 3)`` angles (pitch about +x, yaw about +y, roll about +z; radians) with
    ``R = Ry(yaw) @ Rx(pitch) @ Rz(roll)``. In MPEG-4 axes these are FAPs 48 (head_pitch: +down),
    49 (head_yaw: +towards the face's left) and 50 (head_roll: top towards the face's right)."""
    r = np.asarray(r, dtype=np.float64)
    pitch = np.arcsin(np.clip(-r[..., 1, 2], -1.0, 1.0))
    yaw = np.arctan2(r[..., 0, 2], r[..., 2, 2])
    roll = np.arctan2(r[..., 1, 0], r[..., 1, 1])
    return np.stack([pitch, yaw, roll], axis=-1)


def matrix_from_euler(angles: np.ndarray) -> np.ndarray:
    """Inverse of ``euler_from_matrix``: ``(..., 3)`` (pitch, yaw, roll) -> ``(..., 3, 3)``."""
    a = np.asarray(angles, dtype=np.float64)
    p, y, r = a[..., 0], a[..., 1], a[..., 2]
    one, zero = np.ones_like(p), np.zeros_like(p)
    rx = np.stack(
        [one, zero, zero, zero, np.cos(p), -np.sin(p), zero, np.sin(p), np.cos(p)], -1
    ).reshape(*p.shape, 3, 3)
    ry = np.stack(
        [np.cos(y), zero, np.sin(y), zero, one, zero, -np.sin(y), zero, np.cos(y)], -1
    ).reshape(*p.shape, 3, 3)
    rz = np.stack(
        [np.cos(r), -np.sin(r), zero, np.sin(r), np.cos(r), zero, zero, zero, one], -1
    ).reshape(*p.shape, 3, 3)
    return ry @ rx @ rz


def smooth_poses(
    r: np.ndarray,
    t: np.ndarray,
    centre: np.ndarray,
    fps: float,
    causal: bool = False,
    q: float = 1000.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Smooth a head pose track ``(T, 3, 3)``, ``(T, 3)``: the rotation as a rotation vector and the
    motion of ``centre`` (the stable markers' centroid, so that rotation and translation do not
    trade off). Batch: RTS with each acceleration density chosen by cross-validation; ``causal``:
    the constant-velocity Kalman filter with density ``q`` (as the live driver does)."""
    from scipy.spatial.transform import Rotation

    from .clean import estimate_q_cv, estimate_r, kalman_filter, rts_smooth

    c = np.asarray(centre, dtype=np.float64)
    # radians scaled by a head-sized lever arm (100 mm) so that both rows are in mm-like units
    rv = Rotation.from_matrix(r).as_rotvec() * 100.0
    tc = np.einsum("tij,j->ti", r, c) + t - c
    track = np.stack([rv, tc], axis=1)  # (T, 2, 3)
    noise = estimate_r(track)
    if causal:
        sm = kalman_filter(track, fps, q=q, r=noise, gate=1e9)
    else:
        sm = rts_smooth(track, fps, q=estimate_q_cv(track, fps, noise), r=noise)
    rs = Rotation.from_rotvec(sm[:, 0] / 100.0).as_matrix()
    return rs, c + sm[:, 1] - np.einsum("tij,j->ti", rs, c)


def rigid_fields(points: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """``(3P, 6)`` first-order displacements of ``(P, 3)`` points under a small rotation about
    ``centre`` (rotation vector, radians: columns 0-2) and a translation (columns 3-5)."""
    q = np.asarray(points, dtype=np.float64) - centre
    g = np.zeros((len(q), 3, 6))
    x, y, z = q[:, 0], q[:, 1], q[:, 2]
    g[:, 0, 1], g[:, 0, 2] = z, -y  # omega x q
    g[:, 1, 0], g[:, 1, 2] = -z, x
    g[:, 2, 0], g[:, 2, 1] = y, -x
    g[:, :, 3:] = np.eye(3)
    return g.reshape(-1, 6)


def refine_poses(
    xyz: np.ndarray,
    r: np.ndarray,
    t: np.ndarray,
    neutral: np.ndarray,
    stable: np.ndarray,
    motion: np.ndarray,
    fps: float,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Head poses refined with every marker (batch). Returns ``(R, t, k)``, k the principal motions used.

    Five stable markers with half a millimetre of noise leave the pose of each frame uncertain by about
    0.1°, which shows at the mouth, 10 cm away, as a rigid error of a few tenths of a millimetre.
    The face's own markers carry more information about the pose, once their expression motion is
    accounted for: that motion spans few directions (``clean.optimal_rank`` of them). So each frame's
    stabilised markers minus the ``neutral`` are fitted, by least squares, by a small rigid motion of
    the whole head (``rigid_fields``; the stable markers have no expression motion) plus a
    combination of the leading principal motions of the face markers in ``motion`` (smoothed
    displacements from the neutral, ``(T, M, 3)`` mm); the rigid corrections are smoothed (RTS) and
    composed into the poses.

    Args:
        xyz: ``(T, M, 3)`` gap-filled capture-space markers (mm).
        r, t: ``(T, 3, 3)``, ``(T, 3)`` the poses to refine (``frame = R x + t``).
        neutral: ``(M, 3)`` stabilised neutral; ``stable``: indices of the stable markers.

    On generated takes (0.5 mm noise, technician layout, 5 stable markers), measured when this was
    added: the stabilised displacements' mean error fell from 0.263 to 0.200 mm on seed 1 (0.273 to
    0.218 on seed 2, 0.223 to 0.215 on seed 3), both followed by a low-rank projection; the true
    poses would have given 0.165. ``driver.denoise_displacements`` has the current pipeline's.
    """
    from .clean import estimate_q_cv, estimate_r, optimal_rank, rts_smooth

    t_n, m = xyz.shape[:2]
    face = np.setdiff1d(np.arange(m), stable)
    raw = remove_head(np.asarray(xyz, dtype=np.float64), r, t) - neutral  # (T, M, 3)
    ok = np.isfinite(raw).all(axis=(1, 2)) & np.isfinite(motion).all(axis=(1, 2))
    if ok.sum() < 12 or len(face) < 2:
        return r, t, 0
    # the strict rank: a direction barely above the noise may be a head-pose error itself, and the
    # fit would then take the pose's correction for face motion
    white = raw[ok][:, face].reshape(int(ok.sum()), -1)
    k = optimal_rank(np.linalg.svd(white - white.mean(axis=0), compute_uv=False), white.shape)
    smooth = motion[ok][:, face].reshape(int(ok.sum()), -1)
    mean = smooth.mean(axis=0)
    basis = np.linalg.svd(smooth - mean, full_matrices=False)[2][:k].T  # (3F, k)
    full = np.zeros((m, 3, k))
    full[face] = basis.reshape(len(face), 3, k)
    offset = np.zeros((m, 3))
    offset[face] = mean.reshape(len(face), 3)
    centre = neutral[stable].mean(axis=0)
    a = np.concatenate([rigid_fields(neutral, centre), full.reshape(3 * m, k)], axis=1)
    delta = np.zeros((t_n, 6))
    delta[ok] = np.linalg.lstsq(a, (raw[ok] - offset).reshape(int(ok.sum()), -1).T, rcond=None)[0][
        :6
    ].T
    # smooth the corrections as a pose track (rotation scaled by a 100 mm lever arm, as smooth_poses)
    track = np.stack([delta[:, :3] * 100.0, delta[:, 3:]], axis=1)
    noise = estimate_r(track[ok])
    track = rts_smooth(
        np.where(ok[:, None, None], track, np.nan),
        fps,
        q=estimate_q_cv(track[ok], fps, noise),
        r=noise,
    )
    rr, tt = compose_correction(r, t, track[:, 0] / 100.0, track[:, 1], centre)
    return rr, tt, k


def compose_correction(
    r: np.ndarray, t: np.ndarray, rotvec: np.ndarray, shift: np.ndarray, centre: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Poses ``(..., 3, 3)``, ``(..., 3)`` with a small rigid motion of their stabilised markers
    (``rotvec`` radians about ``centre``, then ``shift``, ``(..., 3)``: as ``rigid_fields``)
    composed in: stabilised = ``S x + (c - S c + shift)``, so frame = ``R S x + R (c - S c + shift)
    + t``."""
    from scipy.spatial.transform import Rotation

    s = Rotation.from_rotvec(np.asarray(rotvec, dtype=np.float64)).as_matrix()
    off = centre - np.einsum("...ij,j->...i", s, centre) + shift
    return np.einsum("...ij,...jk->...ik", r, s), np.einsum("...ij,...j->...i", r, off) + t


class ShapePose:
    """One frame's head pose refined with every marker, the face's own motion explained by known
    shapes (a face prior's, at the markers): the causal counterpart of ``refine_poses``, whose
    motion basis is the take's principal motions, known only afterwards.

    Each frame's stabilised markers minus the ``neutral (M, 3)`` are fitted, by ridge least squares
    (the shapes' weights regularised by ``ridge`` x their mean squared column norm, the rigid part
    not), by a small rigid motion about ``centre`` (``rigid_fields``) plus a combination of
    ``motion (E, M, 3)`` (mm, capture frame; zero at the stable markers); the rigid part corrects
    the pose (``compose_correction``), scaled by how well the fit explains the frame: fully while
    the residual's rms per coordinate is within ``trust[0]`` x the markers' noise ``noise_mm``, not
    at all from ``trust[1]`` x (motion the shapes do not span would otherwise be taken for the
    head's). The normal equations are factored once; a frame with markers unseen removes
    their rows (a solve of E + 6 unknowns, cached while the same markers stay unseen)."""

    def __init__(
        self,
        neutral: np.ndarray,
        centre: np.ndarray,
        motion: np.ndarray,
        ridge: float = 0.03,
        noise_mm: float = 0.5,
        trust: tuple[float, float] = (1.0, 2.0),
    ):
        from scipy.linalg import cho_factor

        self.neutral = np.asarray(neutral, dtype=np.float64)
        self.centre = np.asarray(centre, dtype=np.float64)
        self.trust = (trust[0] * noise_mm, trust[1] * noise_mm)
        m = len(self.neutral)
        shapes = np.asarray(motion, dtype=np.float64).reshape(len(motion), 3 * m).T  # (3M, E)
        self._a = np.concatenate([rigid_fields(self.neutral, self.centre), shapes], axis=1)
        scale = float((shapes**2).sum(axis=0).mean()) if shapes.size else 0.0
        reg = np.r_[np.zeros(6), np.full(shapes.shape[1], ridge * scale)]
        self._gram = self._a.T @ self._a + np.diag(reg) + 1e-9 * np.eye(self._a.shape[1])
        self._full = cho_factor(self._gram)
        self._mask: np.ndarray | None = None
        self._part = self._full

    def _factor(self, seen: np.ndarray):
        """The Cholesky factor of the normal equations over the markers ``seen (M,) bool``."""
        from scipy.linalg import cho_factor

        if seen.all():
            return self._full
        if self._mask is None or not np.array_equal(seen, self._mask):
            gone = self._a[np.repeat(~seen, 3)]
            self._part = cho_factor(self._gram - gone.T @ gone)
            self._mask = seen.copy()
        return self._part

    def delta(self, res: np.ndarray) -> np.ndarray | None:
        """``(6,)`` the rigid part (``rigid_fields``) of stabilised markers minus the neutral
        ``res (M, 3)`` (NaN = unseen), scaled by the fit's trust (the class docstring); None with fewer than 6 markers
        seen."""
        from scipy.linalg import cho_solve

        seen = np.isfinite(res).all(axis=1)
        if seen.sum() < 6:
            return None
        b = np.where(seen[:, None], res, 0.0).reshape(-1)
        x = cho_solve(self._factor(seen), self._a.T @ b)
        # the residual over the seen rows (no copy of the fit's matrix per frame)
        rms = float(np.sqrt(np.mean((self._a @ x - b)[np.repeat(seen, 3)] ** 2)))
        return x[:6] * ramp(rms, self.trust)

    def __call__(
        self, frame: np.ndarray, r: np.ndarray, t: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(R, t)``: the pose ``r (3, 3)``, ``t (3,)`` of ``frame (M, 3)`` (mm, NaN = unseen)
        refined; as it was with fewer than 6 markers seen."""
        delta = self.delta(remove_head(np.asarray(frame, dtype=np.float64), r, t) - self.neutral)
        if delta is None:
            return r, t
        return compose_correction(r, t, delta[:3], delta[3:], self.centre)


def _distance_spread(xyz: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(len(a), len(b))`` standard deviation over the take of the distance between markers
    ``a[i]`` and ``b[j]`` (mm; frames where either is unseen are skipped; inf if never seen together)."""
    d = np.linalg.norm(xyz[:, a, None] - xyz[:, None, b], axis=3)  # (T, A, B)
    ok = np.isfinite(d)
    n = ok.sum(axis=0)
    mean = np.where(ok, d, 0.0).sum(axis=0) / np.maximum(n, 1)
    var = np.where(ok, (d - mean) ** 2, 0.0).sum(axis=0) / np.maximum(n - 1, 1)
    return np.where(n >= 3, np.sqrt(var), np.inf)


def check_stable(
    xyz: np.ndarray, stable: np.ndarray, names: list[str], ratio: float = 2.5, floor_mm: float = 0.5
) -> tuple[np.ndarray, list[str], list[str]]:
    """The declared stable markers that are rigid with each other: ``(kept indices, dropped names,
    added names)``.

    Markers on the skull keep their distances (up to the capture noise); a "stable" marker on skin
    that moves, a loose headband or a swapped label does not, and fitting the head to it bends every
    pose. Each stable marker's score is the median spread (standard deviation over the take, mm)
    of its distances to the other stable markers: most partners of a rigid marker are rigid. The
    worst is dropped while its score exceeds ``ratio`` x the median score and that median plus
    ``floor_mm``. With three stable markers left, the partners are all the markers (two cannot
    outvote one). If fewer than three are left (or declared), the face markers most rigid with the
    remaining ones are added (named in the result) so that the pose stays determined.

    Args:
        xyz: ``(T, M, 3)`` markers (mm, NaN = unseen), head motion included.
        stable: indices of the declared stable markers; ``names``: all M marker names.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    keep = [int(i) for i in stable]
    dropped: list[str] = []
    everyone = np.arange(xyz.shape[1])
    while len(keep) >= 3:
        k = np.asarray(keep)
        # with three, two partners cannot outvote one: every marker is a witness then
        spread = _distance_spread(xyz, k, k if len(k) > 3 else everyone)
        spread[spread == 0.0] = np.nan  # a marker with itself
        score = np.nanmedian(spread, axis=1)
        ref = float(np.median(score))
        worst = int(np.argmax(score))
        if not (score[worst] > ratio * ref and score[worst] > ref + floor_mm):
            break
        dropped.append(names[keep[worst]])
        del keep[worst]
    added: list[str] = []
    if len(keep) < 3 and len(keep) >= 1:
        others = np.setdiff1d(np.arange(xyz.shape[1]), keep)
        spread = _distance_spread(xyz, others, np.asarray(keep)).max(axis=1)
        for j in others[np.argsort(spread)][: 3 - len(keep)]:
            keep.append(int(j))
            added.append(names[int(j)])
    return np.asarray(keep, dtype=np.int64), dropped, added


def pose_uncertainty(
    ref: np.ndarray, frames: np.ndarray, r: np.ndarray, t: np.ndarray, at: np.ndarray
) -> tuple[float, float]:
    """``(degrees, mm)``: the standard error of a rigid pose fitted to the ``(S, 3)`` reference
    markers, from the residuals of ``(T, S, 3)`` frames against poses ``r``, ``t`` (their rms is the
    noise), as a rotation angle and as the rms displacement of the ``(P, 3)`` points ``at`` (the
    face) in the reference frame. Linearised least squares: ``cov = s^2 (J^T J)^-1``."""
    ref = np.asarray(ref, dtype=np.float64)
    res = np.asarray(frames) - (np.einsum("tij,sj->tsi", r, ref) + t[:, None])
    ok = np.isfinite(res).all(axis=2)
    dof = 3 * ok.sum() - 6 * int(ok.any(axis=1).sum())
    if dof <= 0:
        return float("nan"), float("nan")
    s2 = float(np.nansum(res**2)) / dof
    centre = ref.mean(axis=0)
    j = rigid_fields(ref, centre)
    cov = s2 * np.linalg.pinv(j.T @ j)
    deg = float(np.degrees(np.sqrt(np.trace(cov[:3, :3]))))
    jf = rigid_fields(np.asarray(at, dtype=np.float64), centre)
    mm = float(np.sqrt(np.einsum("ij,jk,ik->", jf, cov, jf) / len(at)))
    return deg, mm


def start_neutral(frames: np.ndarray, stable: np.ndarray) -> np.ndarray:
    """The actor's neutral ``(M, 3)`` in the pose of the FIRST of ``(N, M, 3)`` frames (mm, NaN =
    unseen), for a take that may move from its first frame (the live driver's start).

    Averaging the raw frames blurs the head's motion over them and leaves the reference at their
    mean pose, not the first frame's; the first frame alone is noisy. So each frame's pose is solved
    against the frames' mean shape (generalised Procrustes on the stable markers, then every marker
    weighted by how still it sat), every frame is stabilised and averaged, and the poses' trend
    (rotation vector and centroid, least squares) gives the first frame's pose, into which the
    average is carried. (Each marker's own trend, to remove the face's motion over the frames as
    well, was tried: over 12 frames its intercept's noise outweighed the motion it removed.)"""
    from scipy.spatial.transform import Rotation

    x = np.asarray(frames, dtype=np.float64)
    xs = x[:, stable]
    rs, ts, solved = _track(xs, xs[0], "kabsch")
    for _ in range(2):
        if solved.sum() < 2:
            return np.nanmean(x, axis=0)
        ref = np.nanmean(remove_head(xs[solved], rs[solved], ts[solved]), axis=0)
        ok = np.isfinite(ref).all(axis=1)
        ref = np.where(ok[:, None], ref, xs[0])
        rs, ts, solved = _track(xs, ref, "kabsch")
    loc = remove_head(x[solved], rs[solved], ts[solved])
    mean = np.nanmean(loc, axis=0)
    # the poses again from every marker, weighted by how still each sat on the head over the frames
    # (the face moves little in a fraction of a second; four stable markers alone left 0.4 deg)
    spread = np.nanmean(((loc - mean) ** 2).sum(axis=2), axis=0)
    noise = float(np.nanmedian(spread[stable])) if np.isfinite(spread[stable]).any() else 0.75
    w = rigidity_weights(spread, stable, max(noise, 1e-3))
    for f in np.flatnonzero(solved):
        pose = robust_pose(mean, x[f], w, scale_mm=1.5)
        if pose is not None:
            rs[f], ts[f] = pose
    loc = remove_head(x[solved], rs[solved], ts[solved])
    mean = np.nanmean(loc, axis=0)
    c = np.nanmean(ref, axis=0)
    k = np.flatnonzero(solved).astype(np.float64)
    track = np.c_[
        Rotation.from_matrix(rs[solved]).as_rotvec(),
        np.einsum("tij,j->ti", rs[solved], c) + ts[solved] - c,
    ]  # (n, 6)
    design = np.c_[np.ones_like(k), k] if len(k) < 12 else np.c_[np.ones_like(k), k, k**2]
    r0v, c0 = (design[:1] @ np.linalg.lstsq(design, track, rcond=None)[0])[0].reshape(2, 3)
    r0 = Rotation.from_rotvec(r0v).as_matrix()
    return mean @ r0.T + (c + c0 - r0 @ c)


def robust_pose(
    ref: np.ndarray, frame: np.ndarray, weights: np.ndarray, scale_mm: float = 1.0, iters: int = 3
) -> tuple[np.ndarray, np.ndarray] | None:
    """Rigid pose of one frame from ALL its markers: ``(R, t)`` with ``frame ~= R ref + t``, or None
    with fewer than 3 usable markers. ``ref``, ``frame``: ``(M, 3)`` (NaN = unseen); ``weights``
    ``(M,)`` how rigid each marker is (1 / its variance off the rigid motion: the stable markers
    high, the lips low). Iteratively reweighted (Cauchy, scale ``scale_mm``), so that a marker
    moving now, a spike or a swap pulls the pose little."""
    ok = np.isfinite(frame).all(axis=1) & np.isfinite(ref).all(axis=1) & (weights > 0)
    if ok.sum() < 3:
        return None
    src, dst, w = ref[ok], frame[ok], np.asarray(weights, dtype=np.float64)[ok]
    pose = kabsch(src, dst, w)
    for _ in range(iters):
        res = np.linalg.norm(dst - (src @ pose[0].T + pose[1]), axis=1)
        pose = kabsch(src, dst, w / (1.0 + (res / scale_mm) ** 2))
    return pose


def rigidity_weights(
    disp_sq: np.ndarray, stable: np.ndarray, noise_var: float, gate: float = np.inf
) -> np.ndarray:
    """``(M,)`` weights for ``robust_pose``: ``1 / (noise + non-rigid mean square)`` from each
    marker's mean squared displacement off the head ``disp_sq`` (mm², NaN = unknown: weight 0); the
    stable markers count as rigid; a marker whose mean square exceeds ``gate`` x the noise's gets 0."""
    d = np.where(np.isfinite(disp_sq), disp_sq, np.inf)
    d[np.asarray(stable)] = 0.0
    return np.where(d < gate * noise_var, 1.0 / (noise_var + d), 0.0)


#: ``hold_pose``: hold frames whose head sits within these of the hold's median pose (degrees; mm at
#: the stable markers' centre) are averaged, and the average replaces the neutral frame's own pose
#: only when it lies within these of it too (a head turning through the hold keeps its own): a few
#: times a smoothed pose's noise.
HOLD_POSE_DEG, HOLD_POSE_MM = 0.3, 0.5


def hold_pose(
    r: np.ndarray,
    t: np.ndarray,
    frames: list[int] | np.ndarray | range,
    nf: int,
    centre: np.ndarray,
    least: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """Frame ``nf``'s pose ``(R (3, 3), t (3,))``, averaged over the ``frames`` of its neutral hold
    (at least ``least`` of them, else its own) in which the head sits still (``HOLD_POSE_DEG`` /
    ``HOLD_POSE_MM``; ``centre`` ``(3,)``: the stable markers' centre, stabilised). Every output pose
    is relative to the neutral frame's, so that frame's error is carried into every frame; a hold
    shares it out over its frames. A head that moves or turns through the hold (10 % of its frames
    off the median, or a trend over it of a third of the tolerances) keeps frame ``nf``'s own pose
    (a take moving from frame 0 was biased by 0.13 deg otherwise). On generated takes with a
    half-second hold (held-out folds 1 and 2) the head pose error at the skin fell from 0.18/0.24
    to 0.145/0.145 mm (technician layout) and from 0.105/0.155 to 0.101/0.137 mm (neutral-last);
    takes without a hold keep frame ``nf``'s."""
    from scipy.spatial.transform import Rotation

    c = np.asarray(centre, dtype=np.float64)
    idx = np.unique(np.r_[nf, np.asarray(list(frames), dtype=np.int64)])
    if len(idx) < max(2, least) or not np.isfinite(c).all():
        return r[nf].copy(), t[nf].copy()
    rv = Rotation.from_matrix(np.einsum("tij,kj->tik", r[idx], r[nf])).as_rotvec()  # (n, 3) rad
    p = r[idx] @ c + t[idx]  # (n, 3) where the centre goes, mm
    still = (np.degrees(np.linalg.norm(rv - np.median(rv, axis=0), axis=1)) < HOLD_POSE_DEG) & (
        np.linalg.norm(p - np.median(p, axis=0), axis=1) < HOLD_POSE_MM
    )
    if still.sum() < max(2, least) or still.mean() < 0.9:
        return r[nf].copy(), t[nf].copy()  # no hold, or the head moves through it
    # a head turning slowly through the hold (within the tolerances) would bias the mean: the
    # trend over the hold must stay within a third of them
    span = np.c_[np.ones(int(still.sum())), idx[still] - idx[still].mean()]
    slope = np.linalg.lstsq(span, np.c_[np.degrees(rv[still]), p[still]], rcond=None)[0][
        1
    ] * np.ptp(idx[still])
    if (
        np.linalg.norm(slope[:3]) > HOLD_POSE_DEG / 3
        or np.linalg.norm(slope[3:]) > HOLD_POSE_MM / 3
    ):
        return r[nf].copy(), t[nf].copy()
    mean_rv, mean_p = rv[still].mean(axis=0), p[still].mean(axis=0)
    own = idx == nf
    turned = np.degrees(np.linalg.norm(mean_rv)) >= HOLD_POSE_DEG
    if turned or np.linalg.norm(mean_p - p[own][0]) >= HOLD_POSE_MM:
        return r[nf].copy(), t[nf].copy()
    r0 = Rotation.from_rotvec(mean_rv).as_matrix() @ r[nf]
    return r0, mean_p - r0 @ c
