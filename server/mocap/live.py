"""Live mocap driver: marker frames in, face states out, causally (``LiveDriver`` protocol).

Per frame: head pose from the measured stable markers (Kabsch / three-marker, one outlier dropped),
filtered by a constant-velocity Kalman filter on its rotation vector and the stable markers'
centroid; its removal from the raw markers; a constant-velocity Kalman filter with spike gating on
the stabilised markers (``clean.KalmanCV``: the face's motion alone is gentle, so it filters more
than it would with the head's on top); RBF retarget onto the face (``rig.MarkerRig``), and the
face prior (``prior``, the same as batch: the face's expression shapes fitted to each frame, warm
started from the last, carried to every vertex by the states' per-vertex channel). The actor's
neutral is taken from the first ``neutral_frames`` frames in which at least three stable markers
are visible, more until every control marker has been seen (``stabilise.start_neutral``:
stabilised and averaged, in the first frame's head pose, turned back square to the capture axes
when the head starts turned from them: ``neutral.square_rest``); until then ``push`` returns no
state.
A take that starts on an expression gets its neutral shape again where it later holds the face at
rest (``_watch_neutral``, scored as batch's ``--neutral-frame auto``). Each frame's head pose uses
every marker that has shown itself rigid (``stabilise.robust_pose``) and, with a face prior, every
marker again, the face's motion explained by the prior's shapes (``stabilise.ShapePose``).
"""

from __future__ import annotations

import logging
import math
from collections import deque

import numpy as np

from ...protocol.errors import FrameError, show_token
from ...protocol.units import UNIT_MM, unit_name
from ..errors import InputError
from ..faces.face import Face
from ..state import FaceState
from .clean import KalmanCV
from .io import FACE_SPAN_MM, detect_units
from .layout import Layout, load_layout
from .neutral import (
    AUTO_RATIO,
    HOLD_S,
    REST_MARGIN_DEG,
    rest_score,
    square_rest,
    tied_positions,
    turn_deg,
)
from .prior import DEFAULT as PRIOR_DEFAULT
from .prior import ramp
from .rig import MarkerRig, match_names
from .stabilise import ShapePose, rigidity_weights, robust_pose, solve_pose, start_neutral

log = logging.getLogger(__name__)

__all__ = ["MarkerFrameError", "MarkerLiveDriver"]

#: Each frame's head pose is refined with every marker, the face's motion explained by the face
#: prior's shapes (``stabilise.ShapePose``), when the face has a prior.
SHAPE_POSE = True
#: The automatic neutral scores every this many frames (a hold lasts ``neutral.HOLD_S``).
WATCH_EVERY = 4
#: Each frame's marker displacements move to what the face prior's fitted shapes give at the
#: markers while the fit's relative residual is below TOWARD_FIT[0], not at all above TOWARD_FIT[1],
#: linearly between (``_toward_fit``; None: off). The causal path has no look-ahead to clean the
#: markers' noise (0.5 mm: the live ratio was 0.60x with it, 0.20x without, issue16 mirror fold 0);
#: where the shapes explain a frame, its residual at the markers is mostly noise, which the engine
#: spreads over the skin around each marker. Chosen on issue16 and technician folds 0/1, live: mirror
#: 0.897 -> 0.855x (every take better; the prior's own trust range (0.5, 0.8): 0.836x, but strict
#: folds, whose shapes the prior does not span, 0.940 -> 0.955x); strict 0.940 -> 0.938x.
TOWARD_FIT: tuple[float, float] | None = (0.3, 0.6)
#: Seconds over which the head's rest slides to a later neutral hold's position (``_retake``, a take
#: that started turned): a slide, not a snap.
REST_SLIDE_S = 0.25


def _mean_seen(frames: np.ndarray) -> np.ndarray:
    """``(L, 3)``: the mean over ``frames (N, L, 3)`` of each marker where it was seen (finite);
    NaN for a marker never seen."""
    seen = np.isfinite(frames)
    with np.errstate(invalid="ignore"):
        return np.where(seen, frames, 0.0).sum(axis=0) / seen.sum(axis=0)


def rotvec(r: np.ndarray) -> np.ndarray:
    """``(3,)`` radians: the rotation vector of rotation matrix ``r (3, 3)``, as scipy's
    ``Rotation.from_matrix(r).as_rotvec()`` (which costs ~80 us a live frame, this ~10), by its
    skew part; turns within 0.1 rad of a half turn, where that part vanishes, go to scipy."""
    cos = 0.5 * (r[0, 0] + r[1, 1] + r[2, 2] - 1.0)
    if cos < -0.995:
        from scipy.spatial.transform import Rotation

        return Rotation.from_matrix(r).as_rotvec()
    v = 0.5 * np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    sin = math.sqrt(float(v @ v))
    if sin < 1e-12:
        return v
    return v * (math.atan2(sin, min(cos, 1.0)) / sin)


class MarkerFrameError(FrameError):
    """A marker frame the driver cannot use (wrong shape, implausible units): an ``InputError`` and,
    as every ``FrameError``, a ``ValueError`` (HTTP 400 / close 4400; the frame is dropped)."""


class MarkerLiveDriver:
    """Turns live marker frames into ``FaceState`` s for ``face``.

    Args:
        face: target face.
        names: marker names of the producer's frames, in frame order (from the hello message).
        layout: marker layout (path, JSON text, dict or ``Layout``).
        units: units of the frames (default: the layout's, else guessed from the first frame).
        fps: nominal frame rate (the filter follows the actual time stamps).
        neutral_frames: frames averaged into the actor's neutral.
        q, r: Kalman acceleration density (mm²/s³) of the stabilised markers and measurement variance (mm²).
        q_pose: the same for the head pose (rotation in radians x 100 mm, translation in mm).

    Attributes:
        control_vertices: ``(K,) int32`` face vertices driven, or None until the neutral is taken when
            the layout asks for automatic placement.
        lag_frames: frames since the last measured sample, per marker (diagnostics).
        rest_turn_deg: how far the head started turned from the capture axes (degrees; 0 when the
            start was taken for the rest: ``neutral.square_rest``).
    """

    def __init__(
        self,
        face: Face,
        names: list[str],
        layout,
        *,
        units: str | None = None,
        fps: float = 120.0,
        neutral_frames: int = 12,
        q: float = 1000.0,
        r: float = 0.25,
        q_pose: float = 1000.0,
        kernel: str = "imq",
        mu: float = 2.0,
        prior=PRIOR_DEFAULT,
    ):
        self.face = face
        self.prior = prior  # the face prior's source (``rig.MarkerRig``), built once placed
        self.layout: Layout = load_layout(layout)
        self.names = [str(n) for n in names]
        if len(set(self.names)) != len(self.names):
            raise InputError("marker names in the hello message repeat", where="hello.markers")
        self.index = match_names(self.names, self.layout, "hello.markers")
        self.units = units or self.layout.units
        if units:  # the hello's units: a name or spelling of ``protocol.units``
            self.units = unit_name(units)
            if self.units is None:
                raise InputError(
                    f"unknown length unit {show_token(units)}; use one of {', '.join(UNIT_MM)}",
                    where="hello.units",
                )
        self.fps = float(fps)
        self.neutral_frames = max(1, int(neutral_frames))
        self.kernel, self.mu = kernel, mu
        self.kf = KalmanCV(len(self.layout.names), 1.0 / self.fps, q=q, r=r)
        self.kf_pose = KalmanCV(2, 1.0 / self.fps, q=q_pose, r=r / 2, gate=1e9)
        self._q, self._q_pose = q, q_pose
        self.stable = np.array(
            [self.layout.names.index(n) for n in self.layout.stable], dtype=np.int64
        )
        self.rig: MarkerRig | None = None
        self._gathered: list[np.ndarray] = []
        self._neutral_n = 0
        self._ref_stable: np.ndarray | None = None
        self._pose = (np.eye(3), np.zeros(3))
        self._last_t: float | None = None
        self.frames = 0
        self.bad_frames = 0
        auto = any(
            "vertex" not in s and "fp" not in s and s.get("control", True) is not False
            for s in self.layout.markers.values()
        )
        self.control_vertices: np.ndarray | None = None
        # the automatic neutral (``_watch_neutral``) needs 4 face markers tied to the face, and
        # controls that do not move with the neutral (no marker placed automatically)
        self.retakes = 0
        target = tied_positions(self.layout, face)
        tied = np.setdiff1d(np.flatnonzero(np.isfinite(target).all(axis=1)), self.stable)
        self._tied = tied if len(tied) >= 4 and not auto else None
        self._face_at_rest = target  # (L, 3) face units, NaN for markers not tied to the face
        self.rest_turn_deg = 0.0
        self._shift, self._shift_to, self._shift_left = np.zeros(3), np.zeros(3), 0
        self._target = target[tied]
        self._recent: deque[np.ndarray] = deque(maxlen=max(2, round(HOLD_S * self.fps)))
        self._window: deque[np.ndarray] = deque(maxlen=self.neutral_frames)
        self._run, self._neutral_score = 0, np.inf
        if not auto:
            from .layout import place_markers
            from .rig import anchor_vertices, rig_controls

            markers = place_markers(self.layout, face).vertices
            self.prior, self.control_vertices = rig_controls(
                face, markers, anchor_vertices(face, markers), prior
            )

    @property
    def ready(self) -> bool:
        """True once the neutral has been taken and states are produced."""
        return self.rig is not None

    def push(self, data: np.ndarray, t: float) -> list[FaceState]:
        """One marker frame ``(M, 3)`` (NaN = occluded) at media time ``t`` -> ``[FaceState]`` (or
        ``[]`` while the neutral is being taken). InputError for a frame of the wrong shape; the
        driver stays usable."""
        xyz = np.asarray(data, dtype=np.float64)
        if xyz.ndim != 2 or xyz.shape != (len(self.names), 3):
            self.bad_frames += 1
            raise MarkerFrameError(
                f"marker frame has shape {xyz.shape}; the hello named {len(self.names)} markers, so "
                f"frames must be ({len(self.names)}, 3) — the marker count cannot change mid-stream",
                where=f"frame {self.frames}",
            )
        xyz = np.where(np.isfinite(xyz), xyz, np.nan)[self.index]
        if self.units is None:
            guess = detect_units(xyz[None])
            if guess is None:
                return []  # nothing visible yet to tell the units by
            self.units = guess
            log.info("live markers: units not declared; the marker cloud's size says %s", guess)
        z = xyz * UNIT_MM[self.units]
        if self._last_t is not None:
            dt = float(t) - self._last_t
            if dt > 0 and abs(dt - self.kf.dt) > 0.02 * self.kf.dt and dt < 1.0:
                self._set_dt(dt)
        self._last_t = float(t)
        self.frames += 1
        seen = np.isfinite(z).all(axis=1)
        if self.rig is None:
            self._gather_neutral(z, seen)
            if self.rig is None:
                return []
        r, tr = self._solve_pose(z)
        raw_local = (z - tr) @ r
        d2 = ((raw_local - self.rig.neutral) ** 2).sum(axis=1)
        seen_d = np.isfinite(d2)
        self._disp_sq[seen_d] += self._alpha * (d2[seen_d] - self._disp_sq[seen_d])
        local = self.kf.step(raw_local)
        # markers never seen since the start hold their neutral position
        local = np.where(np.isfinite(local), local, self.rig.neutral)
        if self._shift_left:  # the rest sliding to a later hold's position (``_retake``)
            self._shift += (self._shift_to - self._shift) / self._shift_left
            self._shift_left -= 1
        state = self.rig.solve(local, r, tr - self._shift, float(t))
        self._toward_fit(state)
        self._watch_neutral(z, raw_local)
        return [state]

    def _toward_fit(self, state: FaceState) -> None:
        """Move ``state``'s marker displacements (its first controls) toward the face prior's fit
        at the markers, in place: ``d - g (d - B_m w)``, ``g`` from the fit's relative residual
        (``TOWARD_FIT``). At ``g = 1`` (and the channel's full trust) the output ``E d' + (B - E
        B_m) w`` is the fitted shapes' own skin, the engine's share of the residual (noise, mostly)
        dropped; a frame the shapes explain less well keeps more of its markers' own motion."""
        prior = self.rig.prior if self.rig is not None else None
        if TOWARD_FIT is None or prior is None or prior.last_fit is None:
            return
        g = ramp(prior.last_residual, TOWARD_FIT)
        if g > 0.0:
            d = state.controls[: len(prior.markers)]
            d -= (g * (d - prior.last_fit)).astype(d.dtype)

    def _watch_neutral(self, z: np.ndarray, raw_local: np.ndarray) -> None:
        """The automatic neutral, causally (as batch's ``neutral.auto_neutral_frame``): every
        ``WATCH_EVERY`` frames, the mean of the last ``neutral_frames`` stabilised frames is
        scored against the face at rest (``neutral.rest_score``), as the neutral (the mean of as
        many frames) was; a hold of ``neutral.HOLD_S`` seconds fitting ``AUTO_RATIO`` times better
        than the neutral (a take that started on an expression) gives the neutral shape from the
        next frame on (``_retake``)."""
        if self._tied is None:
            return
        self._recent.append(raw_local)
        self._window.append(raw_local[self._tied])
        if len(self._window) < self.neutral_frames or self.frames % WATCH_EVERY:
            return
        score = rest_score(_mean_seen(np.stack(self._window)), self._target)
        held = score * AUTO_RATIO <= self._neutral_score
        self._run = self._run + WATCH_EVERY if held else 0
        if self._run >= self._recent.maxlen:  # type: ignore[operator]
            self._retake(np.stack(self._recent), score, self._neutral_score)

    def _retake(self, frames: np.ndarray, score: float, old: float) -> None:
        """Take the actor's neutral shape again from ``frames (N, L, 3)`` mm (a hold at rest,
        stabilised): their mean. The head's rest keeps its rotation: a hold later in a take may
        come with the head turned (taking its pose as the rest too turned every later frame, 2.6x
        -> 14.9x of not deforming on a fast-expression take), and the pose filter goes on
        undisturbed. When the take started turned from the capture axes (``neutral.square_rest``:
        the start was no rest) and the hold's head sits square to them (within
        ``neutral.REST_MARGIN_DEG`` of the square rest, as batch's ``neutral.rest_frame`` judges a
        rest), the rest's position, which no layout tells, slides to the hold's over
        ``REST_SLIDE_S`` (the output head's translation, mm). A face passing through neutral
        mid-take with the head turned moves nothing (sliding there too made the head's position
        3.5-4.4 mm worse on 3 of 15 generated takes)."""
        mean = _mean_seen(frames)
        assert self.rig is not None
        self._build_rig(np.where(np.isfinite(mean), mean, self.rig.neutral))
        self.retakes += 1
        r, t = self._pose
        if self.rest_turn_deg and turn_deg(r) < REST_MARGIN_DEG:
            self._shift_to = r @ self._centre + t - self._centre
            self._shift_left = max(1, round(REST_SLIDE_S * self.fps))
        log.info(
            "live markers: neutral shape taken again at frame %d from a %.2f s hold fitting the "
            "face at rest %.2f mm (the neutral's %.2f mm)%s",
            self.frames - 1,
            len(frames) / self.fps,
            score,
            old,
            f"; the head's rest slides {np.linalg.norm(self._shift_to):.1f} mm to the hold"
            if self._shift_left
            else "",
        )

    def _set_dt(self, dt: float) -> None:
        from .clean import _cv_model

        self.kf.dt = self.kf_pose.dt = dt
        self.kf.A, self.kf.Q = _cv_model(dt, self._q)
        self.kf_pose.A, self.kf_pose.Q = _cv_model(dt, self._q_pose)

    def _gather_neutral(self, z: np.ndarray, seen: np.ndarray) -> None:
        ctrl = np.array(
            [
                i
                for i, n in enumerate(self.layout.names)
                if self.layout.markers[n].get("control") is not False
            ]
        )
        if seen[self.stable].sum() < 3:
            return
        self._gathered.append(z)
        self._neutral_n += 1
        # a marker occluded in some of the frames is averaged over the others (a take with gaps
        # from its start); wait until every control marker has been seen
        if self._neutral_n < self.neutral_frames:
            return
        gathered = np.stack(self._gathered)
        if not np.isfinite(gathered[:, ctrl]).all(axis=2).any(axis=0).all():
            return
        # in the first frame's head pose, the head's motion over the frames removed (the take may
        # move from its first frame; a plain average left a 0.6 deg bias on every later pose)
        with np.errstate(invalid="ignore"):
            neutral = start_neutral(gathered, self.stable)
        self._gathered = []
        span = float(np.nanmax(np.ptp(neutral[np.isfinite(neutral).all(axis=1)], axis=0)))
        lo, hi = FACE_SPAN_MM
        if not lo / 4 <= span <= hi * 4:
            self._neutral_n = 0
            self._gathered = []
            self.bad_frames += 1
            guess = detect_units(neutral[None] / UNIT_MM[self.units])
            raise MarkerFrameError(
                f"in {self.units} the markers span {span:.3g} mm, not a face"
                + (f"; they look like {guess}" if guess else "")
                + ": declare the right units in "
                "the hello or the layout",
                where=f"frame {self.frames - 1}",
            )
        # a take that starts with the head turned from the capture axes: the rest is square to them
        neutral, self.rest_turn_deg = square_rest(
            neutral, self._face_at_rest, self.stable, self.face.pivot("head")
        )
        if self.rest_turn_deg:
            log.info(
                "live markers: the head starts turned %.2f deg from the capture axes; its rest is "
                "square to them",
                self.rest_turn_deg,
            )
        self._build_rig(neutral)
        # each marker's mean square off the head (mm², an exponential average over ~0.5 s); until
        # measured, the face markers count as moving 5 mm
        self._disp_sq = np.full(len(neutral), 25.0)
        self._noise = 3.0 * self.kf.r  # mm², three axes
        self._alpha = 1.0 / (0.5 * self.fps)
        log.info(
            "live markers: neutral taken from %d frames; %d controls",
            self._neutral_n,
            len(self.rig.control),
        )

    def _build_rig(self, neutral: np.ndarray) -> None:
        """The rig, pose reference and rest score of the actor's ``neutral (L, 3)`` mm."""
        self.rig = MarkerRig(
            self.face, self.layout, neutral, kernel=self.kernel, mu=self.mu, prior=self.prior
        )
        self._ref_stable = neutral[self.stable]
        self._centre = np.nanmean(self._ref_stable, axis=0)
        self.control_vertices = self.rig.control_vertices
        motion = self.rig.marker_motion() if SHAPE_POSE else None
        self._shape_pose = (
            None
            if motion is None
            else ShapePose(
                np.where(np.isfinite(neutral), neutral, 0.0),
                self._centre,
                motion,
                noise_mm=float(np.sqrt(self.kf.r)),
            )
        )
        self._recent.clear()
        self._window.clear()
        self._run = 0
        if self._tied is not None:
            self._neutral_score = rest_score(neutral[self._tied], self._target)

    def _solve_pose(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Filtered head pose: ``stabilise.robust_pose`` over every marker, weighted by rigidity (the
        prediction when fewer than 3 stable markers are seen)."""
        from scipy.spatial.transform import Rotation

        cur = z[self.stable]
        pose = None
        if np.isfinite(cur).all(axis=1).sum() >= 3:
            # every marker, weighted by how rigidly it has moved with the head so far: with four
            # stable markers alone one frame's pose is uncertain by ~0.4 deg at 0.5 mm noise
            w = rigidity_weights(self._disp_sq, self.stable, self._noise, gate=2.0)
            pose = robust_pose(self.rig.neutral, z, w, scale_mm=1.5)
            if pose is not None and self._shape_pose is not None:
                pose = self._shape_pose(z, *pose)
        if pose is None:
            pose = solve_pose(self._ref_stable, cur)
        c = self._centre
        if pose is None:
            meas = np.full((2, 3), np.nan)
        else:
            r, t = pose
            meas = np.stack([rotvec(r) * 100.0, r @ c + t - c])
        est = self.kf_pose.step(meas)
        if not np.isfinite(est).all():
            return self._pose
        r = Rotation.from_rotvec(est[0] / 100.0).as_matrix()
        self._pose = (r, c + est[1] - r @ c)
        return self._pose
