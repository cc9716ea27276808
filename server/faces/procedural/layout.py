"""Conformation parameters of the procedural head and the landmarks derived from them (mm, MPEG-4 axes).

Origin: x = 0 on the mid-sagittal plane, y = 0 at pupil height, z = 0 at the ear canals; +x is the
face's own left, +y up, +z out of the face.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

#: Origin of the rays that parametrise the skin (the skin is star-shaped about this point).
RAY_ORIGIN = np.array([0.0, -5.0, 10.0])
#: Depth of the plane on which face features are laid out ("gnomonic" coordinates px, py).
FEATURE_PLANE_Z = 90.0


@dataclass(frozen=True)
class Conformation:
    """Shape parameters of the built-in head, in millimetres (defaults: an average adult)."""

    face_width: float = 136.0  #: bizygomatic breadth (cheekbone to cheekbone)
    face_height: float = 122.0  #: nasion to menton (chin bottom)
    head_width: float = 152.0  #: skull breadth
    head_length: float = 196.0  #: glabella to back of the skull
    head_height: float = 118.0  #: top of the skull above the pupils
    jaw_width: float = 104.0  #: bigonial breadth (jaw angle to jaw angle)
    chin_length: float = 47.0  #: lip contact (stomion) to menton
    nose_length: float = 52.0  #: nasion to subnasale
    nose_width: float = 34.0  #: alar breadth
    nose_protrusion: float = 20.0  #: tip in front of the subnasale
    mouth_width: float = 50.0  #: lip corner to lip corner
    lip_thickness: float = 8.0  #: upper vermilion height at the middle (the lower lip is 1.2x)
    eye_spacing: float = 63.0  #: pupil to pupil
    eye_radius: float = 12.2  #: eyeball radius
    iris_diameter: float = 11.6
    brow_height: float = 22.0  #: top of the eyebrow above the pupil
    ear_size: float = 62.0  #: ear length (top to lobe)
    neck_radius: float = 52.0
    neck_length: float = 60.0  #: below the chin

    @classmethod
    def names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))


@dataclass(frozen=True)
class Layout:
    """Landmarks derived from a conformation."""

    conf: Conformation

    # vertical landmarks
    @property
    def y_nasion(self) -> float:
        return 10.0

    @property
    def y_subnasale(self) -> float:
        return self.y_nasion - self.conf.nose_length

    @property
    def y_menton(self) -> float:
        return self.y_nasion - self.conf.face_height

    @property
    def y_stomion(self) -> float:
        return self.y_menton + self.conf.chin_length

    @property
    def z_stomion(self) -> float:
        return 95.0

    @property
    def x_mouth(self) -> float:
        return self.conf.mouth_width / 2

    def z_lip_line(self, x: np.ndarray) -> np.ndarray:
        """Depth of the lip-contact line at lateral position ``x`` (it follows the dental arch)."""
        a = np.asarray(x, dtype=np.float64) / self.x_mouth
        return self.z_stomion - 10.0 * a**2

    @property
    def eye_centre_l(self) -> np.ndarray:
        return np.array([self.conf.eye_spacing / 2, 0.0, 69.0])

    @property
    def lid_radius(self) -> float:
        return self.conf.eye_radius + 1.4

    @property
    def iris_radius(self) -> float:
        return self.conf.iris_diameter / 2

    @property
    def canthus_offsets(self) -> tuple[float, float]:
        """Lateral offsets of the inner and outer eye corners from the pupil (mm)."""
        r = self.lid_radius
        return -0.9 * r, 0.96 * r

    @property
    def y_occlusal(self) -> float:
        """Height where the upper and lower teeth meet."""
        return self.y_stomion - 1.5

    @property
    def z_incisors(self) -> float:
        """Depth of the labial face of the upper central incisors."""
        return self.z_stomion - 10.0

    @property
    def jaw_pivot(self) -> np.ndarray:
        return np.array([0.0, -22.0, 8.0])

    @property
    def head_pivot(self) -> np.ndarray:
        return np.array([0.0, -50.0, -10.0])

    @property
    def ear_centre_height(self) -> float:
        return -10.0


def gnomonic(d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Face-plane coordinates ``(px, py)`` where unit rays ``d (N, 3)`` from ``RAY_ORIGIN`` cross
    z = ``FEATURE_PLANE_Z``, and a 0–1 weight that fades features out on rays not facing forward."""
    dz = np.maximum(d[:, 2], 0.05)
    k = (FEATURE_PLANE_Z - RAY_ORIGIN[2]) / dz
    px = RAY_ORIGIN[0] + k * d[:, 0]
    py = RAY_ORIGIN[1] + k * d[:, 1]
    t = np.clip((d[:, 2] - 0.25) / 0.3, 0, 1)
    return px, py, t * t * (3 - 2 * t)


def direction_to(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray angles ``(theta, phi)`` (azimuth towards +x from +z, elevation) of points ``(..., 3)``."""
    v = np.asarray(p, dtype=np.float64) - RAY_ORIGIN
    theta = np.arctan2(v[..., 0], v[..., 2])
    phi = np.arcsin(np.clip(v[..., 1] / np.linalg.norm(v, axis=-1), -1, 1))
    return theta, phi


def direction_from_plane(px: np.ndarray, py: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray angles through face-plane point ``(px, py)``."""
    px, py = np.broadcast_arrays(np.asarray(px, dtype=np.float64), np.asarray(py, dtype=np.float64))
    return direction_to(np.stack([px, py, np.full(px.shape, FEATURE_PLANE_Z)], -1))


def unit_dirs(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    cp = np.cos(phi)
    return np.stack([cp * np.sin(theta), np.sin(phi), cp * np.cos(theta)], -1)
