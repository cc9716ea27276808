"""Cleaning: DCT gap filling, spike rejection, constant-velocity Kalman filter and RTS smoother."""

from __future__ import annotations

import numpy as np

from facecast.server.mocap.clean import (
    CleanParams,
    KalmanCV,
    clean,
    despike,
    estimate_q,
    estimate_r,
    fill_gap_dct,
    fill_gaps,
    find_gaps,
    kalman_filter,
    lowrank_denoise,
    motion_rank,
    rts_smooth,
)

FPS = 120.0


def _signal(n=720):
    t = np.arange(n) / FPS
    return 10 * np.sin(2 * np.pi * 0.9 * t) + 5 * np.sin(2 * np.pi * 0.35 * t + 1.0)


def test_find_gaps():
    valid = np.array([0, 1, 1, 0, 0, 1, 0], dtype=bool)
    assert find_gaps(valid) == [(0, 1), (3, 5), (6, 7)]
    assert find_gaps(np.ones(4, bool)) == []


def test_dct_fill_restores_a_smooth_gap():
    sig = _signal()
    x = sig.copy()
    x[300:336] = np.nan  # 0.3 s
    fill = fill_gap_dct(x, 300, 336, window=50, keep=0.2)
    err = np.abs(fill - sig[300:336]).max()
    linear = np.linspace(sig[299], sig[336], 38)[1:-1]
    assert err < 0.1 * np.ptp(sig)
    assert err < np.abs(linear - sig[300:336]).max()  # better than joining the ends
    thesis = fill_gap_dct(x, 300, 336, window=50, keep=0.2, method="thesis")  # Eq 4.2's extension
    assert np.isfinite(thesis).all() and err < np.abs(thesis - sig[300:336]).max()


def test_fill_gaps_handles_edges_and_never_seen_markers():
    sig = _signal(200)
    xyz = np.stack([sig, -sig, 2 * sig], -1)[:, None, :].repeat(2, axis=1)
    xyz[:5, 0] = np.nan
    xyz[190:, 0] = np.nan
    xyz[80:90, 0] = np.nan
    xyz[:, 1] = np.nan
    out = fill_gaps(xyz)
    assert np.isfinite(out[:, 0]).all()
    assert np.isnan(out[:, 1]).all()
    np.testing.assert_allclose(out[80:90, 0], np.stack([sig, -sig, 2 * sig], -1)[80:90], atol=0.5)


def test_despike_removes_spikes_only(rng):
    sig = _signal(400)
    xyz = np.stack([sig, sig, sig], -1)[:, None, :] + rng.normal(0, 0.3, (400, 1, 3))
    xyz[100, 0] += [15.0, 0, 0]
    xyz[250, 0] += [0, -12.0, 5.0]
    out, n = despike(xyz)
    assert n == 2
    assert np.isnan(out[[100, 250], 0]).all()


def test_kalman_reduces_noise_and_its_lag_is_bounded(rng):
    sig = _signal()
    noisy = sig + rng.normal(0, 0.5, sig.shape)
    xyz = np.stack([noisy] * 3, -1)[:, None, :]
    out = kalman_filter(xyz, FPS, q=1e3, r=0.25)[:, 0, 0]
    rms_raw = np.sqrt(np.mean((noisy - sig)[60:] ** 2))
    rms_kf = np.sqrt(np.mean((out - sig)[60:] ** 2))
    assert rms_kf < 0.75 * rms_raw
    # lag: the shift that best aligns the filtered signal with the truth
    shifts = np.arange(0, 13)
    errs = [np.mean((out[60 + s :] - sig[60 : len(sig) - s]) ** 2) for s in shifts]
    assert shifts[int(np.argmin(errs))] <= 3  # <= 25 ms at 120 Hz
    # a step is followed within a bounded number of frames
    step = np.r_[np.zeros(60), np.full(60, 10.0)]
    out = kalman_filter(np.stack([step] * 3, -1)[:, None, :], FPS, q=1e3, r=0.25, gate=1e9)[:, 0, 0]
    assert np.abs(out[60 + 24 :] - 10.0).max() < 1.0


def test_kalman_phase_lag_is_small_at_facial_speeds():
    from facecast.server.mocap.clean import kalman_lag

    lag = kalman_lag(FPS, q=1e3, r=0.25, freqs=(1.0, 2.0))
    assert 0.0 < lag[1.0] < lag[2.0] < 25.0  # ms; it grows with speed and stays a few frames
    assert (
        kalman_lag(FPS, q=30.0, r=0.25, freqs=(2.0,))[2.0] > lag[2.0]
    )  # heavier filtering lags more


def test_kalman_coasts_through_occlusion_and_gates_spikes():
    kf = KalmanCV(1, 1 / FPS, q=1e3, r=0.25)
    for i in range(60):
        kf.step(np.array([[i * 0.5, 0.0, 0.0]]))
    p = kf.step(np.full((1, 3), np.nan))
    assert abs(p[0, 0] - 30.0) < 0.5  # predicted on at constant velocity
    spiked = kf.step(np.array([[30.5 + 20.0, 0.0, 0.0]]))
    assert abs(spiked[0, 0] - 30.5) < 1.0  # a 20 mm jump is not followed
    assert kf.n_rejected == 1
    for _ in range(kf.max_rejects):
        out = kf.step(np.array([[80.0, 0.0, 0.0]]))
    assert abs(out[0, 0] - 80.0) < 1.0  # a lasting jump is: the filter re-locks


def test_rts_smoother_beats_the_causal_filter_and_fits_noise(rng):
    sig = _signal()
    noisy = sig + rng.normal(0, 0.5, sig.shape)
    xyz = np.stack([noisy] * 3, -1)[:, None, :]
    r = estimate_r(xyz)
    assert 0.15 < r < 0.5
    q = estimate_q(xyz, FPS, r)
    sm = rts_smooth(xyz, FPS, q=q, r=r)[:, 0, 0]
    kf = kalman_filter(xyz, FPS, q=float(q[0]), r=r)[:, 0, 0]
    assert np.mean((sm - sig)[60:] ** 2) < np.mean((kf - sig)[60:] ** 2)
    assert np.sqrt(np.mean((sm - sig) ** 2)) < 0.5 * 0.5


def test_clean_pipeline_counts(rng):
    sig = _signal(300)
    xyz = np.stack([sig, sig, sig], -1)[:, None, :].repeat(3, axis=1) + rng.normal(
        0, 0.4, (300, 3, 3)
    )
    xyz[50:70, 1] = np.nan
    xyz[200, 2] += 30.0
    out, info = clean(xyz, FPS, CleanParams(filter="rts"))
    assert np.isfinite(out).all()
    assert info["occluded"] == 20 and info["spikes"] == 1
    assert np.abs(out[200, 2] - sig[200]).max() < 2.0


def test_neutral_stops_averaging_when_a_few_markers_move(rng):
    """The neutral averages the still frames only: once the chin markers (a tenth of them) leave
    the tolerance, later frames are not averaged in, even though the median marker is still."""
    from facecast.server.mocap.driver import neutral_pose

    still = rng.normal(size=(20, 3)) * 10
    frames = np.repeat(still[None], 40, axis=0) + rng.normal(scale=0.05, size=(40, 20, 3))
    frames[10:, :3, 1] -= np.linspace(1.5, 10.0, 30)[
        :, None
    ]  # three markers (the jaw) move from frame 10
    neutral = neutral_pose(frames, 0, 40, tolerance_mm=1.0)
    np.testing.assert_allclose(neutral, still, atol=0.1)
    assert np.allclose(neutral_pose(frames, 0, 5), frames[:5].mean(axis=0))


def test_best_delay_finds_the_shift_and_ignores_gaps():
    from facecast.server.mocap.clean import best_delay

    t = np.linspace(0, 4 * np.pi, 400)
    truth = np.stack([np.sin(t), np.cos(2 * t), 0.5 * t], axis=1)[:, None, :]  # (T, 1, 3)
    late = np.empty_like(truth)
    late[7:], late[:7] = truth[:-7], truth[0]
    late[100:120] = np.nan  # an occlusion gap
    assert best_delay(late, truth) == 7 and best_delay(truth, truth) == 0


def _low_rank_take(rng, n=900, m=40, k=5, noise=0.5):
    """``(truth, noisy)`` ``(n, m, 3)`` mm: k smooth motions (a few mm) plus white noise."""
    t = np.arange(n) / FPS
    w = np.stack(
        [
            np.sin(2 * np.pi * f * t + p)
            for f, p in zip(rng.uniform(0.2, 1.5, k), rng.uniform(0, 6, k))
        ],
        1,
    )
    w += 0.5  # a mean expression over the take, as every real take has
    truth = (w @ rng.normal(size=(k, 3 * m)) * 1.5).reshape(n, m, 3)
    return truth, truth + rng.normal(0.0, noise, truth.shape)


def test_motion_rank_counts_the_motions_above_the_noise(rng):
    _truth, noisy = _low_rank_take(rng, k=5)
    assert motion_rank(noisy) == 5
    assert motion_rank(noisy, noise_var=0.25) == 5  # the noise level given instead of estimated
    assert motion_rank(rng.normal(0.0, 0.5, noisy.shape)) <= 1  # noise alone: nothing stands out


def test_lowrank_denoise_removes_the_noise_outside_the_motion(rng):
    truth, noisy = _low_rank_take(rng, k=5)
    before = np.linalg.norm(noisy - truth, axis=2).mean()
    after = np.linalg.norm(lowrank_denoise(noisy, motion_rank(noisy)) - truth, axis=2).mean()
    assert after < 0.3 * before  # 5 of 120 directions kept
    # an error of the neutral offsets every frame: the part outside the motion's subspace goes
    offset = rng.normal(0.0, 0.3, truth.shape[1:])
    out = lowrank_denoise(truth - offset, 5)
    assert np.linalg.norm(out - truth, axis=2).mean() < 0.35 * np.linalg.norm(offset, axis=1).mean()
    full = lowrank_denoise(noisy, 3 * noisy.shape[1])  # every direction kept: nothing changes
    np.testing.assert_allclose(full, noisy, atol=1e-9)
    gap = noisy.copy()
    gap[10, 3] = np.nan
    assert np.isnan(lowrank_denoise(gap, 6)[10, 3]).all()  # frames with a hole are left alone
