"""Cleaning marker trajectories: spike rejection, DCT gap filling, constant-velocity Kalman filtering.

After Sánchez Lorenzo (2006) §4.2: gaps are rebuilt from the M lowest DCT coefficients of a window of
N samples on each side, extended into the gap and cross-faded linearly; noise is removed by a
per-coordinate constant-velocity Kalman filter (state = position, velocity), causal so that it runs
live. Batch input may also use the Rauch-Tung-Striebel smoother (the same model, run backwards too:
no lag). Positions are millimetres, time in frames at ``fps``; NaN = occluded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.fft import dct, idct
from scipy.ndimage import median_filter

__all__ = [
    "CleanParams",
    "KalmanCV",
    "clean",
    "despike",
    "estimate_noise",
    "estimate_q",
    "estimate_q_cv",
    "estimate_r",
    "fill_gap_dct",
    "fill_gaps",
    "find_gaps",
    "kalman_filter",
    "kalman_lag",
    "lowpass_dct",
    "lowrank_denoise",
    "motion_rank",
    "optimal_rank",
    "rts_smooth",
]


# ------------------------------------------------------------------------------------------- gaps


def find_gaps(valid: np.ndarray) -> list[tuple[int, int]]:
    """Runs of False in ``(T,) bool``: list of ``(t0, t1)``, missing samples ``t0 .. t1-1``."""
    v = np.asarray(valid, dtype=bool)
    d = np.diff(np.r_[0, (~v).astype(np.int8), 0])
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    return list(zip(starts.tolist(), ends.tolist()))


def lowpass_dct(window: np.ndarray, keep: float) -> np.ndarray:
    """``(n, D)`` samples reduced to their ``keep * n`` lowest DCT-II coefficients (thesis Eq 4.1),
    after removing the linear trend (so that the even extension implied by the DCT does not bend
    the ends), then transformed back. Returns ``(n, D)``."""
    n = len(window)
    if n < 3:
        return np.array(window, dtype=np.float64)
    i = np.arange(n, dtype=np.float64)
    a = np.c_[np.ones(n), i - (n - 1) / 2]
    coef, *_ = np.linalg.lstsq(a, window, rcond=None)
    c = dct(window - a @ coef, type=2, norm="ortho", axis=0)
    c[max(1, round(keep * n)) :] = 0.0
    return a @ coef + idct(c, type=2, norm="ortho", axis=0)


def _thesis_extension(window: np.ndarray, keep: float, positions: np.ndarray) -> np.ndarray:
    """The truncated DCT-II series of ``(n, D)`` samples (Eq 4.1, M = keep * n) evaluated at
    ``positions`` beyond the window (Eq 4.2 continues the series, which mirrors it)."""
    n = len(window)
    c = dct(window, type=2, norm="ortho", axis=0)
    m = max(1, round(keep * n))
    k = np.arange(m, dtype=np.float64)
    scale = np.where(k == 0, np.sqrt(1.0 / n), np.sqrt(2.0 / n))
    basis = scale[None, :] * np.cos(np.pi * k[None, :] * (2 * positions[:, None] + 1) / (2 * n))
    return basis @ c[:m]


def fill_gap_dct(
    x: np.ndarray,
    t0: int,
    t1: int,
    *,
    window: int = 50,
    keep: float = 0.2,
    bridge: int = 10,
    method: str = "bridge",
) -> np.ndarray:
    """Values for the missing samples ``x[t0:t1]`` of ``(T, D)`` samples (NaN elsewhere allowed).

    Left window: the valid run ending at ``t0`` (at most ``window`` samples); right window: the
    valid run starting at ``t1``. Each is low-passed to its ``keep * window`` lowest DCT
    coefficients (Eq 4.1; N=50, M=0.2N in the thesis). The gap is then bridged by the least-squares
    cubic through the ``bridge`` low-passed samples nearest the gap on each side. (The thesis
    extends each window into the gap and cross-fades them (Eq 4.2); its extension is ill-defined —
    a truncated cosine series has zero slope at the window ends — and measured worse here, so the
    two windows are joined by one smooth curve instead; ``method="thesis"`` gives the thesis's
    extension and cross-fade for comparison.) A gap with data on one side only holds the low-passed
    end value. Returns ``(t1 - t0, D)``.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 1:
        return fill_gap_dct(
            x[:, None], t0, t1, window=window, keep=keep, bridge=bridge, method=method
        )[:, 0]
    ok = np.isfinite(x).all(axis=1)
    length = t1 - t0
    lo = t0
    while lo > 0 and ok[lo - 1] and t0 - lo < window:
        lo -= 1
    hi = t1
    while hi < len(x) and ok[hi] and hi - t1 < window:
        hi += 1
    if t0 == lo and hi == t1:
        return np.full((length, x.shape[1]), np.nan)
    if t0 == lo:
        return np.repeat(lowpass_dct(x[t1:hi], keep)[:1], length, axis=0)
    if hi == t1:
        return np.repeat(lowpass_dct(x[lo:t0], keep)[-1:], length, axis=0)
    if method == "thesis":
        j = np.arange(length, dtype=np.float64)
        w = ((j + 1) / (length + 1))[:, None]
        left = _thesis_extension(x[lo:t0], keep, (t0 - lo) + j)
        right = _thesis_extension(x[t1:hi], keep, j - length)
        return (1 - w) * left + w * right
    if method != "bridge":
        raise ValueError(f"method must be 'bridge' or 'thesis', not {method!r}")
    left = lowpass_dct(x[lo:t0], keep)[-bridge:]
    right = lowpass_dct(x[t1:hi], keep)[:bridge]
    pos = np.r_[np.arange(t0 - len(left), t0), np.arange(t1, t1 + len(right))].astype(np.float64)
    centre, scale = (t0 + t1 - 1) / 2, (length + 2 * bridge) / 2
    u = (pos - centre) / scale
    deg = min(3, len(pos) - 1)
    vander = np.vander(u, deg + 1)
    coef, *_ = np.linalg.lstsq(vander, np.r_[left, right], rcond=None)
    return np.vander((np.arange(t0, t1) - centre) / scale, deg + 1) @ coef


def fill_gaps(
    xyz: np.ndarray, *, window: int = 50, keep: float = 0.2, max_gap: int | None = None
) -> np.ndarray:
    """Fill every occlusion of ``(T, M, 3)`` markers with ``fill_gap_dct``.

    Gaps longer than ``max_gap`` frames (None: no limit) are bridged by linear interpolation
    between their ends instead (the DCT extension is meant for short gaps). Markers never seen stay
    NaN. Returns a new array.
    """
    out = np.array(xyz, dtype=np.float64, copy=True)
    for m in range(out.shape[1]):
        track = out[:, m]
        ok = np.isfinite(track).all(axis=1)
        if ok.all() or not ok.any():
            continue
        src = track.copy()
        src[~ok] = np.nan
        for t0, t1 in find_gaps(ok):
            if max_gap is not None and t1 - t0 > max_gap and t0 > 0 and t1 < len(track):
                w = (np.arange(1, t1 - t0 + 1) / (t1 - t0 + 1))[:, None]
                track[t0:t1] = (1 - w) * src[t0 - 1] + w * src[t1]
            else:
                track[t0:t1] = fill_gap_dct(src, t0, t1, window=window, keep=keep)
    return out


# ----------------------------------------------------------------------------------------- spikes


def despike(
    xyz: np.ndarray, *, size: int = 7, threshold_mm: float = 4.0, k: float = 8.0
) -> tuple[np.ndarray, int]:
    """Mark samples far from their running median as occluded.

    For each marker, the running median over ``size`` visible samples is compared with each sample;
    a sample whose 3-D distance exceeds ``max(threshold_mm, k * robust sigma)`` becomes NaN (to be
    gap-filled). Returns ``(new (T, M, 3) array, number of samples rejected)``.
    """
    out = np.array(xyz, dtype=np.float64, copy=True)
    rejected = 0
    for m in range(out.shape[1]):
        ok = np.flatnonzero(np.isfinite(out[:, m]).all(axis=1))
        if len(ok) < size:
            continue
        pts = out[ok, m]
        med = median_filter(pts, size=(size, 1), mode="nearest")
        dist = np.linalg.norm(pts - med, axis=1)
        sigma = 1.4826 * np.median(np.abs(dist - np.median(dist)))
        bad = dist > max(threshold_mm, k * sigma)
        rejected += int(bad.sum())
        out[ok[bad], m] = np.nan
    return out, rejected


# ----------------------------------------------------------------------------------------- Kalman


def _cv_model(dt: float, q: float) -> tuple[np.ndarray, np.ndarray]:
    """Transition ``A`` and process covariance ``Q`` of the constant-velocity model with white
    acceleration of spectral density ``q`` (mm²/s³)."""
    a = np.array([[1.0, dt], [0.0, 1.0]])
    qm = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    return a, qm


#: The thesis's values (L1349), converted from m² to mm² (for 120 Hz): Q ~ 1e-11 m² [...], R ~ 2.2e-7 m².
THESIS_Q_MM2 = 1e-11 * 1e6 * np.array([[0.6, 1.2], [1.2, 2.5]])
THESIS_R_MM2 = 2.2e-7 * 1e6


class KalmanCV:
    """Causal constant-velocity Kalman filter for ``M`` markers (x, y, z filtered independently).

    ``step(z)`` takes one frame ``(M, 3)`` in mm (NaN = occluded) and returns the filtered positions.
    A marker is initialised at its first observation. An observation whose innovation exceeds
    ``gate`` standard deviations (and ``gate_mm``) is treated as a spike and ignored, unless that
    happens ``max_rejects`` frames in a row (then the filter re-locks onto the measurements).
    While occluded, a marker coasts on its prediction with its velocity damped by ``coast_damping``
    per frame. Markers never seen yet return NaN.

    Args:
        m: number of markers. dt: frame period (s). q: acceleration spectral density (mm²/s³).
        r: measurement variance (mm²). Q: explicit 2x2 process covariance (overrides q).
    """

    def __init__(
        self,
        m: int,
        dt: float,
        *,
        q: float = 1.0e3,
        r: float = 0.25,
        Q: np.ndarray | None = None,
        gate: float = 6.0,
        gate_mm: float = 4.0,
        max_rejects: int = 4,
        coast_damping: float = 0.9,
    ):
        self.m, self.dt = m, float(dt)
        self.A, self.Q = _cv_model(self.dt, q)
        if Q is not None:
            self.Q = np.asarray(Q, dtype=np.float64)
        self.r = float(r)
        self.gate, self.gate_mm, self.max_rejects, self.coast_damping = (
            gate,
            gate_mm,
            max_rejects,
            coast_damping,
        )
        self.x = np.zeros((m, 3, 2))  # position, velocity per coordinate
        self.P = np.zeros((m, 2, 2))
        self.alive = np.zeros(m, dtype=bool)
        self.rejects = np.zeros(m, dtype=np.int32)
        self.n_rejected = 0

    @classmethod
    def thesis(cls, m: int, dt: float = 1 / 120, **kw) -> KalmanCV:
        """The filter with the thesis's Q and R (tuned there for 120 Hz Vicon data)."""
        return cls(m, dt, Q=THESIS_Q_MM2, r=THESIS_R_MM2, **kw)

    def _init(self, idx: np.ndarray, z: np.ndarray) -> None:
        self.x[idx, :, 0] = z
        self.x[idx, :, 1] = 0.0
        self.P[idx] = np.diag([self.r, 1e6 * self.r])  # unknown velocity
        self.alive[idx] = True
        self.rejects[idx] = 0

    def predict(self) -> None:
        """Advance every marker one frame."""
        self.x = self.x @ self.A.T
        self.P = self.A @ self.P @ self.A.T + self.Q

    def step(self, z: np.ndarray) -> np.ndarray:
        """Filter one frame ``(M, 3)`` mm -> ``(M, 3)`` mm (see class docstring)."""
        z = np.asarray(z, dtype=np.float64)
        seen = np.isfinite(z).all(axis=1)
        new = seen & ~self.alive
        if new.any():
            self._init(np.flatnonzero(new), z[new])
        live = self.alive & ~new
        self.x[live] = self.x[live] @ self.A.T
        self.P[live] = self.A @ self.P[live] @ self.A.T + self.Q
        upd = live & seen
        if upd.any():
            idx = np.flatnonzero(upd)
            s = self.P[idx, 0, 0] + self.r  # (n,)
            nu = z[idx] - self.x[idx, :, 0]  # (n, 3)
            d2 = (nu**2).sum(axis=1) / s
            spike = (d2 > self.gate**2 * 3) & (np.sqrt((nu**2).sum(axis=1)) > self.gate_mm)
            relock = spike & (self.rejects[idx] + 1 >= self.max_rejects)
            if relock.any():
                self._init(idx[relock], z[idx[relock]])
            self.rejects[idx[spike & ~relock]] += 1
            self.n_rejected += int((spike & ~relock).sum())
            ok = ~spike
            if ok.any():
                i2 = idx[ok]
                self.rejects[i2] = 0
                k = self.P[i2, :, 0] / s[ok][:, None]  # (n, 2) gain
                self.x[i2] += k[:, None, :] * nu[ok][:, :, None]
                self.P[i2] = self.P[i2] - k[:, :, None] * self.P[i2, 0, :][:, None, :]
        coast = live & ~seen
        if coast.any():
            self.x[coast, :, 1] *= self.coast_damping
        out = self.x[:, :, 0].copy()
        out[~self.alive] = np.nan
        return out


def best_delay(est: np.ndarray, truth: np.ndarray, max_lag: int = 24) -> int:
    """Frames by which ``est (T, ...)`` trails ``truth``: the shift that best aligns them (least mean
    squared difference over the finite samples, shifts 0 .. ``max_lag``)."""
    errs = [np.nanmean((est[s:] - truth[: len(truth) - s]) ** 2) for s in range(max_lag + 1)]
    return int(np.argmin(errs))


def kalman_lag(
    fps: float, q: float, r: float, freqs: tuple[float, ...] = (1.0, 2.0, 5.0)
) -> dict[float, float]:
    """Delay (ms) of ``KalmanCV`` on noise-free sinusoids of ``freqs`` Hz (its phase lag in
    steady state): how far behind the causal filter runs on motion of that speed."""
    out = {}
    for f in freqs:
        n = int(fps * max(4.0, 6.0 / f))
        t = np.arange(n) / fps
        x = 10.0 * np.sin(2 * np.pi * f * t)
        y = kalman_filter(np.stack([x] * 3, -1)[:, None, :], fps, q=q, r=r, gate=1e9)[:, 0, 0]
        keep = t > t[-1] / 2
        basis = np.c_[np.sin(2 * np.pi * f * t[keep]), np.cos(2 * np.pi * f * t[keep])]
        a, b = np.linalg.lstsq(basis, y[keep], rcond=None)[0]
        phase = np.arctan2(-b, a)  # y ~ A sin(2 pi f t - phase)
        out[f] = float(1000.0 * phase / (2 * np.pi * f))
    return out


def kalman_filter(xyz: np.ndarray, fps: float, **params) -> np.ndarray:
    """Run ``KalmanCV`` causally over ``(T, M, 3)`` mm; returns ``(T, M, 3)``."""
    kf = KalmanCV(xyz.shape[1], 1.0 / fps, **params)
    return np.stack([kf.step(f) for f in xyz])


def _forward(x: np.ndarray, fps: float, q: np.ndarray, r: float):
    """Forward Kalman pass over ``(T, M, 3)`` with per-marker ``q (M,)``; returns predicted and
    filtered states/covariances and the per-marker innovation log-likelihood ``(M,)``."""
    t_n, m = x.shape[:2]
    dt = 1.0 / fps
    a = np.array([[1.0, dt], [0.0, 1.0]])
    qm = q[:, None, None] * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])[None]
    xf = np.zeros((t_n, m, 3, 2))
    pf = np.zeros((t_n, m, 2, 2))
    xp = np.zeros_like(xf)
    pp = np.zeros_like(pf)
    loglik = np.zeros(m)
    first = np.nanmean(x[: min(t_n, 5)], axis=0)
    state = np.stack([np.nan_to_num(first), np.zeros((m, 3))], axis=-1)
    cov = np.broadcast_to(np.diag([r, 1e4 * r]), (m, 2, 2)).copy()
    for t in range(t_n):
        if t:
            state = state @ a.T
            cov = a @ cov @ a.T + qm
        xp[t], pp[t] = state, cov
        seen = np.isfinite(x[t]).all(axis=1)
        if seen.any():
            s = cov[seen, 0, 0] + r
            k = cov[seen, :, 0] / s[:, None]
            nu = x[t, seen] - state[seen, :, 0]
            if t > 2:
                loglik[seen] -= 0.5 * ((nu**2).sum(axis=1) / s + 3 * np.log(s))
            state[seen] += k[:, None, :] * nu[:, :, None]
            cov[seen] = cov[seen] - k[:, :, None] * cov[seen, 0, :][:, None, :]
        xf[t], pf[t] = state, cov
    return a, xp, pp, xf, pf, loglik


def rts_smooth(
    xyz: np.ndarray, fps: float, *, q: float | np.ndarray = 2.0e5, r: float = 0.25
) -> np.ndarray:
    """Rauch-Tung-Striebel smoothing of ``(T, M, 3)`` mm with the constant-velocity model (forward
    Kalman pass, then backward correction: zero lag, batch only). ``q`` is one acceleration density
    (mm²/s³) or one per marker ``(M,)``; NaN samples are treated as missing observations."""
    x = np.asarray(xyz, dtype=np.float64)
    qv = np.broadcast_to(np.asarray(q, dtype=np.float64), (x.shape[1],)).copy()
    a, xp, pp, xf, pf, _ = _forward(x, fps, qv, r)
    xs = xf.copy()
    for t in range(len(x) - 2, -1, -1):
        c = pf[t] @ a.T @ np.linalg.inv(pp[t + 1])  # (M, 2, 2)
        xs[t] = xf[t] + (xs[t + 1] - xp[t + 1]) @ np.swapaxes(c, 1, 2)
    return xs[..., 0]


def estimate_r(xyz: np.ndarray, cluster: int = 6) -> float:
    """Measurement variance (mm²) after the thesis (L1347): the deviation of samples within groups
    of ``cluster`` frames (6 frames at 120 Hz ~ the 20 fps of perceptible motion). Each group is
    detrended by its own straight line first, so that steady motion does not count as noise (the
    residual variance is scaled by n/(n-2) for the two fitted parameters)."""
    x = np.asarray(xyz, dtype=np.float64)
    t_n = (len(x) // cluster) * cluster
    if t_n < 2 * cluster or cluster < 3:
        return 0.25
    c = x[:t_n].reshape(t_n // cluster, cluster, -1)  # (G, n, D)
    i = np.arange(cluster, dtype=np.float64) - (cluster - 1) / 2
    mean = c.mean(axis=1, keepdims=True)
    slope = (c * i[None, :, None]).sum(axis=1, keepdims=True) / (i**2).sum()
    resid = c - mean - slope * i[None, :, None]
    var = float(np.nanmean(resid**2)) * cluster / (cluster - 2)
    return max(var, 1e-6) if np.isfinite(var) else 0.25


#: Acceleration densities tried by ``estimate_q`` (mm²/s³).
Q_GRID = np.array([1.0, 3.0, 10.0, 30.0, 100.0, 300.0, 1e3, 3e3, 1e4, 3e4])


def estimate_q(
    xyz: np.ndarray,
    fps: float,
    r: float,
    grid: np.ndarray = Q_GRID,
    per_marker: bool = True,
    max_frames: int = 1200,
) -> np.ndarray:
    """Acceleration density per marker ``(M,)`` (mm²/s³) by maximum likelihood of the forward
    filter's innovations over ``grid`` (one shared value when ``per_marker`` is False). All grid
    values run in one pass (the markers are tiled, one copy per value)."""
    x = np.asarray(xyz, dtype=np.float64)[:max_frames]
    m, g = x.shape[1], len(grid)
    ll = _forward(np.tile(x, (1, g, 1)), fps, np.repeat(np.asarray(grid, dtype=np.float64), m), r)[
        -1
    ]
    ll = ll.reshape(g, m)
    if per_marker:
        return grid[np.argmax(ll, axis=0)]
    return np.full(m, grid[int(np.argmax(ll.sum(axis=1)))])


def estimate_q_cv(
    xyz: np.ndarray,
    fps: float,
    r: float,
    grid: np.ndarray = Q_GRID,
    folds: int = 4,
    per_marker: bool = True,
) -> np.ndarray:
    """Acceleration density per marker ``(M,)`` by cross-validation of the RTS smoother: every
    ``folds``-th sample is hidden in turn and predicted from the rest; the ``q`` with the least
    squared prediction error wins. Slower than ``estimate_q`` (``len(grid) * folds`` smoother runs)
    but it chooses for smoothing, not for one-step prediction, which on head poses picks smoother,
    more accurate tracks."""
    x = np.asarray(xyz, dtype=np.float64)
    m, g = x.shape[1], len(grid)
    qs = np.repeat(np.asarray(grid, dtype=np.float64), m)
    err = np.zeros(g * m)
    for off in range(folds):
        hidden = np.tile(x, (1, g, 1))
        hidden[off::folds] = np.nan
        sm = rts_smooth(hidden, fps, q=qs, r=r)
        truth = np.tile(x[off::folds], (1, g, 1))
        err += np.nanmean(((sm[off::folds] - truth) ** 2).sum(axis=2), axis=0)
    err = err.reshape(g, m)
    if per_marker:
        return grid[np.argmin(err, axis=0)]
    return np.full(x.shape[1], grid[int(np.argmin(err.sum(axis=1)))])


def estimate_noise(xyz: np.ndarray, fps: float, cluster: int = 6) -> tuple[float, float]:
    """``(r, q)``: measurement variance (``estimate_r``) and one acceleration density (``estimate_q``)."""
    r = estimate_r(xyz, cluster)
    return r, float(estimate_q(xyz, fps, r, per_marker=False)[0])


# -------------------------------------------------------------------------------------- low rank


def optimal_rank(singular_values: np.ndarray, shape: tuple[int, int]) -> int:
    """How many singular values of a ``shape`` data matrix (centred) are worth keeping to estimate
    its signal under white noise of unknown level: Gavish & Donoho's (2014) hard threshold
    ``ω(β) · median(σ)``, ``β`` = short side / long side, ``ω(β) ≈ 0.56β³ − 0.95β² + 1.82β + 1.43``.
    Stricter than ``motion_rank``'s noise edge: directions barely above the noise are left out."""
    s = np.sort(np.asarray(singular_values, dtype=np.float64))[::-1]
    if not len(s) or s[0] <= 0:
        return 0
    beta = min(shape) / max(shape)
    omega = 0.56 * beta**3 - 0.95 * beta**2 + 1.82 * beta + 1.43
    return int((s > omega * np.median(s)).sum())


def motion_rank(disp: np.ndarray, noise_var: float | None = None) -> int:
    """How many directions the motion in ``(T, M, 3)`` displacements spans (mm; unsmoothed, so that
    the noise is white): the principal components of their variation that stand above the noise,
    i.e. whose singular value exceeds the largest a ``T x 3M`` matrix of white noise has
    (Marchenko-Pastur: ``σ (√T + √3M)``). ``noise_var`` is ``σ²`` (mm²; None: ``estimate_r``).
    Frames with a NaN are skipped."""
    d = np.asarray(disp, dtype=np.float64)
    flat = d.reshape(len(d), -1)
    ok = np.isfinite(flat).all(axis=1)
    if ok.sum() < 2:
        return flat.shape[1]
    var = estimate_r(d[ok]) if noise_var is None else float(noise_var)
    s = np.linalg.svd(flat[ok] - flat[ok].mean(axis=0), compute_uv=False)
    return int((s > np.sqrt(var) * (np.sqrt(ok.sum()) + np.sqrt(flat.shape[1]))).sum())


def lowrank_denoise(disp: np.ndarray, rank: int) -> np.ndarray:
    """``(T, M, 3)`` marker displacements from the neutral (mm) projected onto the ``rank`` leading
    principal directions of their variation.

    A face moves in few independent ways (a few dozen muscles or expressions) while capture noise
    spreads over all ``3M`` coordinates, so dropping the directions that do not stand above the
    noise (``motion_rank``) removes most of the noise a smoother leaves (batch only: the directions
    come from the whole take). The projection passes through zero, not through the take's mean:
    with no expression there is no displacement, so the true motion, its mean included, lies in a
    subspace through zero; the part of the mean outside it is an error of the neutral (which offsets
    every frame) and goes. Frames with a NaN are left as they are.
    """
    d = np.asarray(disp, dtype=np.float64)
    flat = d.reshape(len(d), -1)
    ok = np.isfinite(flat).all(axis=1)
    if ok.sum() < 2:
        return d.copy()
    centred = flat[ok] - flat[ok].mean(axis=0)
    basis = np.linalg.svd(centred, full_matrices=False)[2][: max(0, int(rank))].T  # (3M, k)
    out = flat.copy()
    out[ok] = flat[ok] @ basis @ basis.T
    return out.reshape(d.shape)


# ------------------------------------------------------------------------------------------ batch


@dataclass
class CleanParams:
    """Batch cleaning settings: DCT window N and kept fraction M/N; longest gap rebuilt by the DCT
    (longer ones are interpolated linearly); filter ``rts`` (smoother, batch), ``kalman`` (causal) or
    ``none``; q/r None = estimated from the take (q per marker by maximum likelihood, r as in the thesis);
    ``lowrank``: the stabilised displacements of a batch take smoothed by ``rts`` are projected onto
    their leading principal components (``lowrank_denoise``): ``auto`` (as many as stand above the
    noise), ``off``, or a number of components."""

    window: int = 50
    keep: float = 0.2
    max_gap: int | None = 240
    despike: bool = True
    spike_mm: float = 4.0
    filter: str = "rts"
    lowrank: str | int = "auto"
    q: float | None = None
    r: float | None = None
    per_marker_q: bool = True


def clean(
    xyz: np.ndarray, fps: float, params: CleanParams | None = None
) -> tuple[np.ndarray, dict]:
    """Despike, gap-fill and filter ``(T, M, 3)`` mm. Returns ``(cleaned (T, M, 3), info)`` where
    info holds the counts and the noise parameters used."""
    p = params or CleanParams()
    x = np.asarray(xyz, dtype=np.float64)
    info: dict = {"occluded": int((~np.isfinite(x).all(axis=2)).sum())}
    if p.despike:
        before = np.isfinite(x).all(axis=2)
        x, info["spikes"] = despike(x, threshold_mm=p.spike_mm)
        info["rejected"] = before & ~np.isfinite(x).all(axis=2)
    x = fill_gaps(x, window=p.window, keep=p.keep, max_gap=p.max_gap)
    r = p.r if p.r is not None else estimate_r(x)
    q = (
        np.full(x.shape[1], p.q)
        if p.q is not None
        else estimate_q(x, fps, r, per_marker=p.per_marker_q)
    )
    info.update(q=q, r=r, filter=p.filter)
    if p.filter == "rts":
        seen = np.isfinite(x).all(axis=2)
        sm = rts_smooth(x, fps, q=q, r=r)
        x = np.where(seen[..., None], sm, x)
    elif p.filter == "kalman":
        x = kalman_filter(x, fps, q=float(np.median(q)), r=r)
    elif p.filter != "none":
        raise ValueError(f"filter must be rts, kalman or none, not {p.filter!r}")
    return x, info
