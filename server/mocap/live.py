"""Live mocap driver: marker frames in, face states out, causally (``LiveDriver`` protocol).

Per frame: constant-velocity Kalman filter with spike gating (``clean.KalmanCV``), head pose from the
stable markers (Kabsch / three-marker), removal, RBF retarget onto the face (``rig.MarkerRig``).
The actor's neutral is the average of the first ``neutral_frames`` frames in which every control
marker and at least three stable markers are visible; until then ``push`` returns no state.
"""
from __future__ import annotations

import logging

import numpy as np

from ...protocol.markers_file import UNITS_MM
from ..errors import InputError
from ..faces.face import Face
from ..state import FaceState
from .clean import KalmanCV
from .io import detect_units
from .layout import Layout, load_layout
from .rig import MarkerRig, match_names
from .stabilise import solve_pose

log = logging.getLogger(__name__)

__all__ = ["MarkerLiveDriver"]


class MarkerLiveDriver:
    """Turns live marker frames into ``FaceState`` s for ``face``.

    Args:
        face: target face.
        names: marker names of the producer's frames, in frame order (from the hello message).
        layout: marker layout (path, JSON text, dict or ``Layout``).
        units: units of the frames (default: the layout's, else guessed from the first frame).
        fps: nominal frame rate (the filter follows the actual time stamps).
        neutral_frames: frames averaged into the actor's neutral.
        q, r: Kalman acceleration density (mm²/s³) and measurement variance (mm²).

    Attributes:
        control_vertices: ``(K,) int32`` face vertices driven, or None until the neutral is taken when
            the layout asks for automatic placement.
        lag_frames: frames since the last measured sample, per marker (diagnostics).
    """

    def __init__(self, face: Face, names: list[str], layout, *, units: str | None = None, fps: float = 120.0,
                 neutral_frames: int = 12, q: float = 1.0e3, r: float = 0.25, kernel: str = "imq", mu: float = 2.0):
        self.face = face
        self.layout: Layout = load_layout(layout)
        self.names = [str(n) for n in names]
        if len(set(self.names)) != len(self.names):
            raise InputError("marker names in the hello message repeat", where="hello.markers")
        self.index = match_names(self.names, self.layout, "hello.markers")
        self.units = units or self.layout.units
        self.fps = float(fps)
        self.neutral_frames = max(1, int(neutral_frames))
        self.kernel, self.mu = kernel, mu
        self.kf = KalmanCV(len(self.layout.names), 1.0 / self.fps, q=q, r=r)
        self._q = q
        self.stable = np.array([self.layout.names.index(n) for n in self.layout.stable], dtype=np.int64)
        self.rig: MarkerRig | None = None
        self._neutral_sum = np.zeros((len(self.layout.names), 3))
        self._neutral_n = 0
        self._ref_stable: np.ndarray | None = None
        self._pose = (np.eye(3), np.zeros(3))
        self._last_t: float | None = None
        self.frames = 0
        self.bad_frames = 0
        auto = any("vertex" not in s and "fp" not in s and s.get("control", True) is not False
                   for s in self.layout.markers.values())
        self.control_vertices: np.ndarray | None = None
        if not auto:
            from .layout import place_markers

            self.control_vertices = place_markers(self.layout, face).vertices

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
            raise InputError(f"marker frame has shape {xyz.shape}; the hello named {len(self.names)} markers, so "
                             f"frames must be ({len(self.names)}, 3) — the marker count cannot change mid-stream",
                             where=f"frame {self.frames}")
        xyz = np.where(np.isfinite(xyz), xyz, np.nan)[self.index]
        if self.units is None:
            guess = detect_units(xyz[None])
            if guess is None:
                return []  # nothing visible yet to tell the units by
            self.units = guess
            log.info("live markers: units not declared; the marker cloud's size says %s", guess)
        z = xyz * UNITS_MM[self.units]
        if self._last_t is not None:
            dt = float(t) - self._last_t
            if dt > 0 and abs(dt - self.kf.dt) > 0.02 * self.kf.dt and dt < 1.0:
                self._set_dt(dt)
        self._last_t = float(t)
        self.frames += 1
        seen = np.isfinite(z).all(axis=1)
        filt = self.kf.step(z)
        if self.rig is None:
            self._gather_neutral(z, seen)
            if self.rig is None:
                return []
        pose = self._solve_pose(filt, seen)
        r, tr = pose
        local = (filt - tr) @ r
        # markers never seen since the start hold their neutral position
        local = np.where(np.isfinite(local), local, self.rig.neutral)
        return [self.rig.solve(local, r, tr, float(t))]

    def _set_dt(self, dt: float) -> None:
        from .clean import _cv_model

        self.kf.dt = dt
        self.kf.A, self.kf.Q = _cv_model(dt, self._q)

    def _gather_neutral(self, z: np.ndarray, seen: np.ndarray) -> None:
        ctrl = np.array([i for i, n in enumerate(self.layout.names)
                         if self.layout.markers[n].get("control") is not False])
        if not seen[ctrl].all() or seen[self.stable].sum() < 3:
            return
        self._neutral_sum += np.where(seen[:, None], z, 0.0)
        self._neutral_n += 1
        if self._neutral_n < self.neutral_frames:
            return
        neutral = self._neutral_sum / self._neutral_n
        self.rig = MarkerRig(self.face, self.layout, neutral, kernel=self.kernel, mu=self.mu)
        self._ref_stable = neutral[self.stable]
        self.control_vertices = self.rig.control_vertices
        log.info("live markers: neutral taken from %d frames; %d controls", self._neutral_n, len(self.rig.control))

    def _solve_pose(self, filt: np.ndarray, seen: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cur = filt[self.stable]
        measured = seen[self.stable]
        if measured.sum() >= 3:
            cur = np.where(measured[:, None], cur, np.nan)
        pose = solve_pose(self._ref_stable, cur)
        if pose is not None:
            self._pose = pose
        return self._pose
