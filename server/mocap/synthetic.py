"""Synthetic marker takes on any face (no expression data needed): for tests and the live benchmark.

Markers sit on skin vertices of the face; the skin moves by a smooth random field (a few Gaussian
"muscle" bumps with smooth random amplitudes), the head moves rigidly, and capture noise, gaps and
spikes are optional. Ground truth comes back with the take.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import PchipInterpolator

from ...protocol.markers_file import MarkerTake
from ..faces.face import Face
from .sampling import farthest_points
from .stabilise import matrix_from_euler

__all__ = ["SyntheticTake", "ellipsoid_face", "synthetic_take"]


@dataclass
class SyntheticTake:
    """A take with its layout (dict) and ground truth: ``local`` ``(T, M, 3)`` mm marker positions
    with the head motion removed (face axes, mm); ``head_r (T, 3, 3)``/``head_t (T, 3)`` capture pose
    (mm); ``vertices (M,)`` marker vertices."""

    take: MarkerTake
    layout: dict
    local: np.ndarray
    clean: np.ndarray
    head_r: np.ndarray
    head_t: np.ndarray
    vertices: np.ndarray


def ellipsoid_face(
    subdivisions: int = 3, radii_mm: tuple[float, float, float] = (75.0, 105.0, 90.0)
) -> Face:
    """A head-sized ellipsoid ``Face`` (mm, all skin, no feature points): a mesh for tests."""
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=subdivisions)
    return Face(
        "ellipsoid",
        np.asarray(ico.vertices) * np.asarray(radii_mm),
        np.asarray(ico.faces),
        units="mm",
    )


def _smooth(
    rng, n: int, fps: float, amp: float, hold: int, period: tuple[float, float] = (0.3, 0.9)
) -> np.ndarray:
    keys = [0.0, hold / fps]
    while keys[-1] < n / fps + 1:
        keys.append(keys[-1] + rng.uniform(*period))
    vals = np.r_[0.0, 0.0, rng.uniform(-amp, amp, len(keys) - 2)]
    return PchipInterpolator(keys, vals)(np.arange(n) / fps)


def synthetic_take(
    face: Face,
    *,
    n_markers: int = 30,
    n_stable: int = 4,
    seconds: float = 2.0,
    fps: float = 120.0,
    seed: int = 0,
    noise_mm: float = 0.0,
    gaps: bool = False,
    head_motion: bool = True,
    amplitude_mm: float = 4.0,
    units: str = "mm",
    fp_markers: tuple[str, ...] = (),
) -> SyntheticTake:
    """A take of ``n_markers`` markers (``n_stable`` of them on the top of the head) on ``face``;
    ``fp_markers`` adds markers on those feature points (named ``FP2_1`` ..., tied by ``fp``)."""
    rng = np.random.default_rng(seed)
    mm = face.mm_per_unit
    v = face.vertices.astype(np.float64) * mm
    skin = face.part("skin")
    if not len(skin):
        skin = np.flatnonzero(face.deformable)
    lo, hi = v[skin].min(axis=0), v[skin].max(axis=0)
    size = hi - lo
    top = skin[v[skin, 1] > hi[1] - 0.15 * size[1]]
    # spread the stable markers: farthest points among the top
    stable = top[farthest_points(v[top], n_stable, start=int(np.argmax(v[top, 2])))]
    front = skin[(v[skin, 2] > lo[2] + 0.6 * size[2]) & (v[skin, 1] < hi[1] - 0.3 * size[1])]
    front = np.setdiff1d(front, stable)
    n_face = n_markers - n_stable
    face_m = front[farthest_points(v[front], n_face, start=int(np.argmax(v[front, 2])))]
    fp_v = [face.feature_points[f] for f in fp_markers]
    face_m = np.r_[fp_v, np.setdiff1d(face_m, fp_v)[: n_face - len(fp_v)]].astype(np.int64)
    n_face = len(face_m)
    verts = np.r_[stable, face_m].astype(np.int64)
    names = (
        [f"HEAD{i + 1}" for i in range(n_stable)]
        + ["FP" + f.replace(".", "_") for f in fp_markers]
        + [f"M{i + 1:02d}" for i in range(n_face - len(fp_markers))]
    )
    n = max(2, round(seconds * fps))
    hold = min(n - 1, int(0.25 * fps))
    # deformation field: bumps centred on some face markers
    centres = v[face_m[rng.choice(n_face, size=min(6, n_face), replace=False)]]
    radius = 0.25 * size[0]
    amps = np.stack(
        [
            np.stack([_smooth(rng, n, fps, amplitude_mm, hold) for _ in range(3)], -1)
            for _ in centres
        ]
    )  # (B, T, 3)
    w = np.exp(
        -((v[verts][:, None, :] - centres[None]) ** 2).sum(axis=2) / (2 * radius**2)
    )  # (M, B)
    w[:n_stable] = 0.0
    local = v[verts][None] + np.einsum("mb,btc->tmc", w, amps)
    if "2.1" in fp_markers:  # the chin drops now and then (jaw opening)
        chin = names.index("FP2_1")
        local[:, chin, 1] -= np.abs(_smooth(rng, n, fps, 2.0 * amplitude_mm, hold))
    if head_motion:
        ang = np.stack(
            [_smooth(rng, n, fps, a, hold, (0.6, 1.5)) for a in np.radians([6.0, 10.0, 4.0])], -1
        )
        trans = np.stack([_smooth(rng, n, fps, 10.0, hold, (0.8, 2.0)) for _ in range(3)], -1)
    else:
        ang, trans = np.zeros((n, 3)), np.zeros((n, 3))
    r = matrix_from_euler(ang)
    pivot = face.pivot("head") * mm
    clean = np.einsum("tij,tmj->tmi", r, local - pivot) + pivot + trans[:, None, :]
    head_t = pivot - np.einsum("tij,j->ti", r, pivot) + trans
    xyz = clean + rng.normal(0.0, noise_mm, clean.shape) if noise_mm else clean.copy()
    if gaps:
        for j in range(n_stable, len(verts)):
            if rng.random() < 0.3:
                length = int(rng.integers(3, max(4, n // 8)))
                start = int(rng.integers(hold + 1, max(hold + 2, n - length)))
                xyz[start : start + length, j] = np.nan
    from ...protocol.units import UNIT_MM

    take = MarkerTake(names, xyz / UNIT_MM[units], float(fps), units)
    markers: dict[str, dict] = {nm: {"vertex": int(vid)} for nm, vid in zip(names, verts)}
    for f in fp_markers:
        markers["FP" + f.replace(".", "_")] = {"fp": f}
    layout = {"units": units, "stable": names[:n_stable], "markers": markers}
    return SyntheticTake(take, layout, local, clean, r, head_t, verts)
