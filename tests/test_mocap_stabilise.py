"""Head stabilisation (Kabsch, Kshirsagar's three markers, tracking) and the RBF retarget."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.server.mocap.retarget import RBFMap
from facecast.server.mocap.stabilise import (
    ShapePose,
    euler_from_matrix,
    head_track,
    kabsch,
    matrix_from_euler,
    pose_in_frame,
    refine_poses,
    remove_head,
    rigid_fields,
    smooth_poses,
    solve_pose,
    three_marker,
)


def _rotation(rng) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_kabsch_recovers_a_known_rigid_motion(rng):
    src = rng.normal(size=(6, 3)) * 50
    r, t = _rotation(rng), rng.normal(size=3) * 100
    r2, t2 = kabsch(src, src @ r.T + t)
    np.testing.assert_allclose(r2, r, atol=1e-10)
    np.testing.assert_allclose(t2, t, atol=1e-8)


def test_kabsch_never_returns_a_reflection(rng):
    src = rng.normal(size=(5, 3)) * 50
    mirrored = src * [-1.0, 1.0, 1.0]
    r, _ = kabsch(src, mirrored)
    assert np.linalg.det(r) == pytest.approx(1.0)


def test_three_marker_construction_matches_kabsch(rng):
    src = np.array([[0.0, 0.0, 0.0], [60.0, 5.0, 0.0], [30.0, 40.0, 20.0]])
    r, t = _rotation(rng), rng.normal(size=3) * 10
    dst = src @ r.T + t
    r3, t3 = three_marker(src, dst)
    np.testing.assert_allclose(r3, r, atol=1e-10)
    np.testing.assert_allclose(t3, t, atol=1e-8)
    # with noise it still returns a rotation, close to the truth
    noisy = dst + rng.normal(0, 0.2, dst.shape)
    r3, _ = three_marker(src, noisy)
    assert np.allclose(r3 @ r3.T, np.eye(3), atol=1e-12)
    assert np.degrees(np.arccos((np.trace(r3.T @ r) - 1) / 2)) < 1.5


def test_solve_pose_needs_three_visible_non_collinear_markers(rng):
    src = rng.normal(size=(4, 3)) * 40
    frame = src.copy()
    frame[:2] = np.nan
    assert solve_pose(src, frame) is None
    line = np.outer(np.arange(4.0), [1.0, 2.0, 3.0])
    assert solve_pose(line, line) is None
    frame = src + 5.0
    frame[0] = np.nan  # three visible: Kshirsagar's construction
    r, t = solve_pose(src, frame)
    np.testing.assert_allclose(r, np.eye(3), atol=1e-10)
    np.testing.assert_allclose(t, 5.0, atol=1e-9)


def test_head_track_removes_head_motion_and_bridges_lost_frames(rng):
    n, m = 50, 8
    neutral = rng.normal(size=(m, 3)) * 60
    angles = np.stack([np.linspace(0, 0.2, n), np.linspace(0, -0.3, n), np.zeros(n)], -1)
    rs = matrix_from_euler(angles)
    ts = np.linspace(0, 20, n)[:, None] * [1.0, 0.5, -1.0]
    local = neutral[None].repeat(n, 0)
    local[:, 4:] += np.sin(np.arange(n))[:, None, None] * 3.0  # non-rigid markers
    xyz = np.einsum("tij,tmj->tmi", rs, local) + ts[:, None]
    xyz[20, :3] = np.nan  # too few stable markers in this frame
    r, t, solved = head_track(xyz, np.arange(4), neutral)
    assert not solved[20] and solved.sum() == n - 1
    keep = solved
    np.testing.assert_allclose(r[keep], rs[keep], atol=1e-9)
    out = remove_head(xyz[keep], r[keep], t[keep])
    np.testing.assert_allclose(out, local[keep], atol=1e-8)
    np.testing.assert_allclose(r[20], r[19])  # held from the nearest solved frame


def test_euler_round_trip_and_mpeg4_signs():
    a = np.array([[0.1, -0.2, 0.3], [0.0, 0.5, 0.0]])
    np.testing.assert_allclose(euler_from_matrix(matrix_from_euler(a)), a, atol=1e-12)
    # positive pitch turns the gaze (+z) down, positive yaw towards +x (the face's left)
    gaze = np.array([0.0, 0.0, 1.0])
    assert (matrix_from_euler([0.3, 0, 0]) @ gaze)[1] < 0
    assert (matrix_from_euler([0, 0.3, 0]) @ gaze)[0] > 0
    assert (matrix_from_euler([0, 0, 0.3]) @ np.array([0, 1.0, 0]))[0] < 0  # roll: top towards -x


def test_pose_in_another_frame(rng):
    r, t = _rotation(rng), rng.normal(size=3)
    q, s, c = _rotation(rng), 0.1, rng.normal(size=3)
    x = rng.normal(size=(5, 3))
    rf, tf = pose_in_frame(r, t, q, s, c)

    def to_f(p):
        return s * p @ q.T + c

    np.testing.assert_allclose(to_f(x @ r.T + t), to_f(x) @ rf.T + tf, atol=1e-12)


def test_identity_retarget_reproduces_the_input_exactly(rng):
    src = rng.normal(size=(30, 3)) * 50
    moved = src + rng.normal(size=src.shape) * 3
    for kernel in ("imq", "r"):
        m = RBFMap(src, src.copy(), kernel=kernel)
        assert np.array_equal(m(moved), moved)
        np.testing.assert_array_equal(m.displacements(moved), moved - src)


def test_retarget_carries_a_change_of_frame_and_units_exactly(rng):
    src = rng.normal(size=(30, 3)) * 50  # mm
    r = _rotation(rng)
    dst = 0.1 * src @ r.T + [1.0, 2.0, 3.0]  # cm, another orientation
    moved = src + rng.normal(size=src.shape) * 3
    for kernel in ("imq", "r"):
        m = RBFMap(src, dst, kernel=kernel)
        np.testing.assert_allclose(m(src), dst, atol=1e-9)
        np.testing.assert_allclose(m(moved), 0.1 * moved @ r.T + [1.0, 2.0, 3.0], atol=1e-7)


def test_retarget_interpolates_a_different_face(rng):
    src = rng.normal(size=(40, 3)) * 50
    dst = src * [1.2, 0.9, 1.0] + 0.002 * src**2  # a non-linearly different face
    m = RBFMap(src, dst, kernel="imq", mu=2.0)
    np.testing.assert_allclose(m(src), dst, atol=1e-6)
    d = m.displacements(src + [0.0, 1.0, 0.0])
    assert np.isfinite(d).all() and np.abs(d[:, 1]).mean() == pytest.approx(0.9, abs=0.25)


def test_rigid_fields_are_the_first_order_rigid_motion(rng):
    pts = rng.normal(size=(6, 3)) * 50
    centre = np.array([1.0, 2.0, 3.0])
    delta = np.array([1e-4, -2e-4, 3e-4, 0.5, -0.2, 0.1])  # rotation vector (rad), translation (mm)
    from scipy.spatial.transform import Rotation

    exact = (pts - centre) @ Rotation.from_rotvec(delta[:3]).as_matrix().T + centre + delta[3:]
    np.testing.assert_allclose(
        (rigid_fields(pts, centre) @ delta).reshape(-1, 3), exact - pts, atol=1e-5
    )


def test_refine_poses_uses_the_face_markers_to_steady_the_head(rng):
    """Five noisy stable markers high on the head, 40 face markers below moving in 4 ways: the
    poses refined with every marker are closer to the truth at the face than the stable-only ones."""
    fps, n = 120.0, 720
    t = np.arange(n) / fps
    band = np.c_[
        np.cos(np.linspace(0, 2 * np.pi, 5, endpoint=False)) * 80,
        np.full(5, 60.0),
        np.sin(np.linspace(0, 2 * np.pi, 5, endpoint=False)) * 80,
    ]
    face = np.c_[rng.uniform(-50, 50, 40), rng.uniform(-90, 0, 40), rng.uniform(60, 90, 40)]
    neutral = np.r_[band, face]
    stable = np.arange(5)
    w = np.stack(
        [np.sin(2 * np.pi * f * t + p) for f, p in ((0.5, 0), (0.8, 1), (1.1, 2), (0.3, 3))], 1
    )
    motion = np.zeros((n, 45, 3))
    motion[:, 5:] = (w @ rng.normal(size=(4, 120)) * 2.0).reshape(n, 40, 3)
    angles = np.stack(
        [
            0.1 * np.sin(2 * np.pi * 0.4 * t),
            0.15 * np.sin(2 * np.pi * 0.3 * t + 1),
            0.05 * t / t[-1],
        ],
        -1,
    )
    rs = matrix_from_euler(angles)
    ts = np.stack([10 * np.sin(2 * np.pi * 0.25 * t), 5 * np.cos(2 * np.pi * 0.35 * t), 0 * t], -1)
    xyz = (
        np.einsum("tij,tmj->tmi", rs, neutral + motion)
        + ts[:, None]
        + rng.normal(0, 0.5, (n, 45, 3))
    )
    r, tt, _ = head_track(xyz, stable, neutral)
    r, tt = smooth_poses(r, tt, neutral[stable].mean(axis=0), fps)
    local = remove_head(xyz, r, tt)

    def pose_error(r_, t_):  # mm at the face markers' neutral positions
        est = np.einsum("tij,mj->tmi", r_, face) + t_[:, None]
        return np.linalg.norm(
            est - (np.einsum("tij,mj->tmi", rs, face) + ts[:, None]), axis=2
        ).mean()

    r2, t2, rank = refine_poses(xyz, r, tt, neutral, stable, local - neutral, fps)
    assert 4 <= rank <= 8  # every motion found (head-pose errors may count too), not the noise
    assert pose_error(r2, t2) < 0.7 * pose_error(r, tt)


def test_shape_pose_explains_the_face_s_motion_and_corrects_the_pose(rng):
    """One frame: four stable markers and 40 face markers moved by known shapes; a pose that is
    0.5 deg and 1 mm off is brought within a tenth of a degree by the face markers, where
    a pose from all markers without the shapes (Kabsch) is pulled off by the expression."""
    from scipy.spatial.transform import Rotation

    band = np.c_[rng.uniform(-80, 80, 4), np.full(4, 60.0), rng.uniform(-80, 80, 4)]
    face = np.c_[rng.uniform(-50, 50, 40), rng.uniform(-90, 0, 40), rng.uniform(60, 90, 40)]
    neutral = np.r_[band, face]
    shapes = np.zeros((6, 44, 3))
    shapes[:, 4:] = rng.normal(0, 3.0, (6, 40, 3))
    w = np.array([0.8, 0.0, 0.5, 0.3, 0.0, 0.6])
    r_true = Rotation.from_rotvec([0.1, 0.2, -0.05]).as_matrix()
    t_true = np.array([5.0, -3.0, 2.0])
    frame = (neutral + np.einsum("e,emc->mc", w, shapes)) @ r_true.T + t_true
    frame += rng.normal(0, 0.2, frame.shape)
    frame[10] = np.nan  # an occluded face marker
    off = Rotation.from_rotvec(np.radians(0.5) * np.array([0.6, 0.8, 0.0])).as_matrix()
    r0, t0 = r_true @ off, t_true + np.array([1.0, 0.0, 0.0])
    refine = ShapePose(neutral, band.mean(axis=0), shapes)
    r1, t1 = refine(frame, r0, t0)

    def err(r, t):  # degrees, mm at the face markers
        deg = np.degrees(Rotation.from_matrix(r.T @ r_true).magnitude())
        return deg, np.linalg.norm(face @ (r - r_true).T + t - t_true, axis=1).mean()

    seen = np.isfinite(frame).all(axis=1)
    plain = kabsch(neutral[seen], frame[seen])
    assert err(r1, t1)[0] < 0.1 and err(r1, t1)[1] < 0.2
    assert err(*plain)[0] > 3 * err(r1, t1)[0]
    assert err(r0, t0)[0] > 5 * err(r1, t1)[0]


def test_hold_pose_shares_the_neutral_frames_pose_error_over_its_hold(rng):
    """The head still through a 60-frame neutral hold, each frame's pose 0.1 deg and 0.1 mm (per
    axis) off at random: the hold's pose is far closer than frame 0's own; a head turning through the hold is
    followed only within the tolerance; too short a hold keeps the frame's own pose."""
    from scipy.spatial.transform import Rotation

    from facecast.server.mocap.stabilise import HOLD_POSE_DEG, hold_pose

    n = 60
    centre = np.array([0.0, 80.0, 20.0])
    noise = Rotation.from_rotvec(np.radians(rng.normal(0.0, 0.1, (n, 3)))).as_matrix()
    r, t = noise, rng.normal(0.0, 0.1, (n, 3)) + centre - np.einsum("tij,j->ti", noise, centre)

    def err(rr: np.ndarray, tt: np.ndarray) -> tuple[float, float]:
        return float(np.degrees(Rotation.from_matrix(rr).magnitude())), float(
            np.linalg.norm(rr @ centre + tt - centre)
        )

    own = err(r[0], t[0])
    got = err(*hold_pose(r, t, range(n), 0, centre, least=15))
    assert got[0] < 0.05 and got[1] < 0.06 and got[0] < own[0] and got[1] < own[1]
    assert err(*hold_pose(r, t, range(10), 0, centre, least=15)) == own  # not a hold
    # the head turning 2 deg over the hold: only the frames within the tolerance count
    turn = Rotation.from_rotvec(
        np.c_[np.zeros(n), np.radians(np.linspace(0, 2, n)), np.zeros(n)]
    ).as_matrix()
    got = err(*hold_pose(turn, np.zeros((n, 3)), range(n), 0, centre, least=2))
    assert got[0] < HOLD_POSE_DEG / 2 + 0.01
    # a slow turn within the tolerance (0.25 deg over the hold, as a take moving from frame 0): the
    # mean would sit 0.12 deg off frame 0's pose; its own is kept
    slow = Rotation.from_rotvec(
        np.c_[np.zeros(n), np.radians(np.linspace(0, 0.25, n)), np.zeros(n)]
    ).as_matrix()
    assert err(*hold_pose(slow, np.zeros((n, 3)), range(n), 0, centre, least=2))[0] < 0.01


def test_only_a_held_neutral_moves_the_neutral_frame():
    """``neutral.held_frames``: a face passing through neutral for an instant is no hold."""
    from facecast.server.mocap.neutral import held_frames

    low = np.array([1, 1, 0, 1, 1, 1, 0, 1, 1, 1, 1], dtype=bool)
    assert held_frames(low, 3).tolist() == [0, 0, 0, 1, 1, 1, 0, 1, 1, 1, 1]
    assert not held_frames(low, 5).any()
    assert held_frames(np.ones(4, bool), 4).all()
