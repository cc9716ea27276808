"""Finding the head in a mesh: its up and forward axes, where it ends (a body is cropped at the neck),
and the similarity transform (scale, rotation, translation) taking it onto the template.

Every axis-aligned orientation (24: up along ±x ±y ±z, forward along one of the four others) is tried;
each is cropped to the head, aligned by trimmed ICP with scale, and scored by how well the mesh lies on
the template and how much of the template's face the mesh covers. The best one wins.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..loaders import AXES as _AXIS
from ..loaders import axes_frame as frame
from .template import Template

AXIS_NAMES = tuple(_AXIS)
#: Depth below the crown, in head widths, where the head crop ends (the chin is at about 1.35).
HEAD_ASPECT = 1.6


def orientations() -> list[tuple[str, str]]:
    """The 24 (up, forward) pairs of axis names."""
    return [(u, f) for u in AXIS_NAMES for f in AXIS_NAMES if u[1] != f[1]]


@dataclass
class Similarity:
    """``y = scale * rotation @ x + translation``: mesh units -> template mm."""

    scale: float
    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)

    def apply(self, x: np.ndarray) -> np.ndarray:
        return self.scale * x @ self.rotation.T + self.translation

    def inverse(self, y: np.ndarray) -> np.ndarray:
        return ((y - self.translation) / self.scale) @ self.rotation


@dataclass
class Placement:
    """The chosen orientation, head crop and alignment."""

    up: str
    forward: str
    similarity: Similarity
    crop: np.ndarray  # (V,) bool: mesh vertices belonging to the head region
    score: float  # mm, lower is better
    cropped: bool  # True when the mesh extends well below the head (a bust or a body)


def head_crop(p: np.ndarray) -> tuple[float, float, bool]:
    """``(top, width, cropped)`` of the head in points ``p (N, 3)`` already in MPEG-4 axes.

    The head's width is the fixed point of "the widest x-extent within 0.7 widths of the top" (the
    ears' level; shoulders lie lower); the head ends ``HEAD_ASPECT`` widths below the top, and
    ``cropped`` says whether the mesh goes on below that (a bust, a body).
    """
    y = p[:, 1]
    top, height = float(y.max()), float(np.ptp(y))
    order = np.argsort(top - y)
    depth = (top - y)[order]
    xs = p[order, 0]
    lo, hi = np.minimum.accumulate(xs), np.maximum.accumulate(xs)
    width = hi - lo  # x-extent of everything within depth[i] of the top
    w = float(width[min(len(width) - 1, np.searchsorted(depth, 0.05 * height))]) or height
    for _ in range(12):
        k = min(len(width) - 1, int(np.searchsorted(depth, 0.7 * w, side="right")) - 1)
        nw = float(width[max(k, 0)])
        if abs(nw - w) <= 1e-3 * nw:
            break
        w = nw
    return top, w, HEAD_ASPECT * w < 0.9 * height


def umeyama(
    src: np.ndarray, dst: np.ndarray, w: np.ndarray | None = None, scale: float | None = None
) -> Similarity:
    """Least-squares similarity taking ``src (N, 3)`` onto ``dst (N, 3)`` (optional weights), or
    with its ``scale`` given, the least-squares rotation and translation at that scale."""
    w = np.ones(len(src)) if w is None else w
    w = w / w.sum()
    ms, md = w @ src, w @ dst
    a, b = src - ms, dst - md
    cov = (b * w[:, None]).T @ a
    u, s, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    sign = np.array([1.0, 1.0, d])
    rot = u @ np.diag(sign) @ vt
    var = float(w @ (a**2).sum(axis=1))
    if scale is None:
        scale = float((s * sign).sum() / var) if var > 0 else 1.0
    return Similarity(scale, rot, md - scale * rot @ ms)


def _subsample(n: int, k: int, rng: np.random.Generator) -> np.ndarray:
    return np.arange(n) if n <= k else np.sort(rng.choice(n, k, replace=False))


def icp(
    points: np.ndarray,
    normals: np.ndarray,
    tpl: Template,
    start: Similarity,
    *,
    iterations: int,
    tree: cKDTree,
    samples: np.ndarray,
    face_pts: np.ndarray,
) -> tuple[Similarity, float]:
    """Trimmed ICP with scale of mesh ``points`` (and unit ``normals``) onto the template's outer skin.

    The mesh may be partial (a mask) or larger than the template (shoulders): pairs farther than a
    shrinking threshold are dropped, and each template face sample also pulls its nearest mesh point
    so that a mask cannot slide off the face. Returns the similarity and its score (mm, lower is
    better): median mesh-to-template distance + mean template-face-to-mesh distance + a penalty for
    normals that disagree (which tells a face from an upside-down or backward one).
    """
    sim = start
    tpl_n = tpl.normals[samples]
    pts = tpl.vertices[samples]
    for it in range(iterations):
        y = sim.apply(points)
        d, j = tree.query(y)
        thr = max(np.quantile(d, 0.7), 3.0) * (2.5 if it < iterations // 2 else 1.5)
        keep = d < thr
        d2, i2 = cKDTree(y).query(face_pts)
        k2 = d2 < max(np.quantile(d2, 0.8), 3.0) * 1.5
        src, dst = np.r_[points[keep], points[i2[k2]]], np.r_[pts[j[keep]], face_pts[k2]]
        if len(src) < 10:
            break
        sim = umeyama(src, dst)
    y = sim.apply(points)
    d, j = tree.query(y)
    n = normals @ sim.rotation.T
    agree = np.abs(np.einsum("ij,ij->i", n, tpl_n[j]))
    near = d < np.quantile(d, 0.7)
    score = (
        float(np.median(d))
        + float(np.minimum(cKDTree(y).query(face_pts)[0], 40.0).mean())
        + 20.0 * float(1.0 - agree[near].mean())
    )
    return sim, score


def place(
    vertices: np.ndarray,
    normals: np.ndarray,
    template: Template,
    *,
    axes: tuple[str, str] | None = None,
    landmarks: dict[str, np.ndarray] | None = None,
    seed: int = 0,
) -> Placement:
    """Find the head in ``vertices (V, 3)`` (mesh units, unit ``normals``) and align it to ``template``.

    Args:
        axes: ``(up, forward)`` if known (skips the orientation search).
        landmarks: MPEG-4 feature point id -> ``(3,)`` position in mesh units (``--landmarks``);
            with three or more, they give the alignment directly (and the axes if not given).
    """
    rng = np.random.default_rng(seed)
    v = np.asarray(vertices, dtype=np.float64)
    tpl_all = template.vertices[template.outer]
    samples = template.outer[_subsample(len(template.outer), 5000, rng)]
    tree = cKDTree(template.vertices[samples])
    face_all = template.vertices[template.face_region]
    face_fine = face_all[_subsample(len(face_all), 800, rng)]
    face_coarse = face_all[_subsample(len(face_all), 250, rng)]
    t_top, t_width, _ = head_crop(tpl_all)
    fit = {"tree": tree, "samples": samples}

    def run(sim: Similarity, crop: np.ndarray, k: int, iterations: int, face_pts: np.ndarray):
        ids = np.nonzero(crop)[0]
        ids = ids[_subsample(len(ids), k, np.random.default_rng(seed))]
        return icp(
            v[ids], normals[ids], template, sim, iterations=iterations, face_pts=face_pts, **fit
        )

    if landmarks and len(landmarks) >= 3:
        keys = [k for k in landmarks if k in template.feature_points]
        sim = umeyama(
            np.array([landmarks[k] for k in keys]),
            np.array([template.fp_position(k) for k in keys]),
        )
        up, forward = axes or _nearest_axes(sim.rotation)
        y = sim.apply(v)
        crop = (
            (y[:, 1] > t_top - HEAD_ASPECT * t_width)
            & (np.abs(y[:, 0]) < 150)
            & (np.abs(y[:, 2]) < 200)
        )
        sim, score = run(sim, crop, 4000, 8, face_fine)
        return Placement(up, forward, sim, crop, score, bool((~crop).any()))

    candidates: list[Placement] = []
    for up, forward in [axes] if axes else orientations():
        rot = frame(up, forward)
        p = v @ rot.T
        top, width, cropped = head_crop(p)
        crop = p[:, 1] >= top - (HEAD_ASPECT * width if cropped else np.inf)
        if crop.sum() < 10:
            continue
        c = p[crop]
        # Start: scale from the head widths, crown (or, for a mask, forehead) and front aligned.
        scale = t_width / width if width > 0 else 1.0
        for drop in [0.0] if cropped else [0.0, 0.3]:
            t = np.array(
                [
                    -scale * (c[:, 0].max() + c[:, 0].min()) / 2,
                    t_top - drop * t_width - scale * top,
                    tpl_all[:, 2].max() - scale * c[:, 2].max(),
                ]
            )
            sim = Similarity(scale, rot, t)
            sim, score = run(sim, crop, 500, 8, face_coarse)
            candidates.append(Placement(up, forward, sim, crop, score, cropped))
    if not candidates:
        from ...errors import InputError

        raise InputError("the mesh has too few vertices to find a head in it")
    candidates.sort(key=lambda c: c.score)
    best = None
    for cand in candidates[:4]:
        cand.similarity, cand.score = run(cand.similarity, cand.crop, 2500, 12, face_fine)
        if best is None or cand.score < best.score:
            best = cand
    best.similarity, best.score = run(best.similarity, best.crop, 6000, 6, face_fine)
    return best


def _nearest_axes(rotation: np.ndarray) -> tuple[str, str]:
    """The axis-aligned (up, forward) closest to a rotation taking mesh axes to MPEG-4 axes."""
    up_vec, fwd_vec = rotation[1], rotation[2]
    names = list(_AXIS)
    up = names[int(np.argmax([np.dot(up_vec, _AXIS[n]) for n in names]))]
    rest = [n for n in names if n[1] != up[1]]
    forward = rest[int(np.argmax([np.dot(fwd_vec, _AXIS[n]) for n in rest]))]
    return up, forward
