"""Non-rigid fit of the template to the user's head (Kähler, Haber, Seidel 2002, "Head shop").

After the similarity alignment, the template is warped by a radial-basis-function field fitted to
displacements between the two surfaces, then refined: each round recomputes closest-point
correspondences both ways (template to mesh and mesh to template, dropping pairs that are far, lie on
the mesh's open rim or whose normals disagree), fits the field on more control points with less
smoothing, and warps again. User landmarks, when given, are extra controls with near-zero smoothing.
All positions are in the template's frame (mm, MPEG-4 axes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import RBFInterpolator
from scipy.spatial import cKDTree

from ...deform.normals import vertex_normals
from ...mocap.sampling import farthest_points
from .template import Template

#: Refinement rounds: (control points, correspondence distance limit in mm, smoothing).
SCHEDULE: tuple[tuple[int, float, float], ...] = (
    (40, 40.0, 30.0),
    (80, 30.0, 10.0),
    (160, 20.0, 3.0),
    (300, 14.0, 1.0),
    (500, 10.0, 0.3),
    (700, 8.0, 0.1),
    (900, 6.0, 0.05),
    (900, 5.0, 0.02),
)


#: Mesh samples pulling the template (mesh -> template correspondences) per round, at most.
BACK_SAMPLES = 30_000


@dataclass
class Target:
    """The user's head surface in the template frame.

    Attributes:
        points: ``(P, 3)`` mm: surface samples (vertices of the matched surface, then triangle centroids).
        normals: ``(P, 3)`` unit normals, oriented outwards like the template's.
        rim: ``(P,) bool``: samples on an open boundary (a mask's edge, a bust's cut).
    """

    points: np.ndarray
    normals: np.ndarray
    rim: np.ndarray


def fit(
    template: Template,
    target: Target,
    *,
    anchors: tuple[np.ndarray, np.ndarray] | None = None,
    crop: np.ndarray | None = None,
) -> tuple[np.ndarray, list]:
    """Warp all template vertices onto ``target``.

    Args:
        anchors: ``(src (K, 3), dst (K, 3))``: template-frame points of the template (landmarks found
            on it, the user's feature points, eyeball centres) and where they must land on the mesh.
        crop: ``(P,) bool``: target samples that belong to the head (others never pull the template).

    Returns:
        ``(N, 3)`` warped template vertices and the list of fitted RBF fields (apply in order to any
        template-frame point, e.g. a pivot, with ``warp_points``).
    """
    w = template.vertices.copy()
    outer = template.outer
    order = farthest_points(template.vertices[outer], max(s[0] for s in SCHEDULE), start=0)
    ttree = cKDTree(target.points)
    head = np.ones(len(target.points), bool) if crop is None else crop
    back = np.nonzero(head & ~target.rim)[0]
    if len(back) > BACK_SAMPLES:  # mesh -> template pairs: a dense mesh needs only a sample
        back = back[np.random.default_rng(0).choice(len(back), BACK_SAMPLES, replace=False)]
    back_pts, back_n = target.points[back], target.normals[back]
    fields = []
    src, dst = (
        (np.zeros((0, 3)), np.zeros((0, 3))) if anchors is None else (anchors[0].copy(), anchors[1])
    )
    for n_ctrl, limit, smooth in SCHEDULE:
        wo = w[outer]
        wn = vertex_normals(w, template.triangles)[outer]
        acc = np.zeros_like(wo)
        cnt = np.zeros(len(wo))
        # template -> mesh
        d, j = ttree.query(wo)
        ok = (
            (d < limit)
            & ~target.rim[j]
            & head[j]
            & (np.einsum("ij,ij->i", wn, target.normals[j]) > 0.3)
        )
        acc[ok] += target.points[j[ok]] - wo[ok]
        cnt[ok] += 1
        # mesh -> template
        d2, i2 = cKDTree(wo).query(back_pts)
        ok2 = (d2 < limit) & (np.einsum("ij,ij->i", back_n, wn[i2]) > 0.3)
        np.add.at(acc, i2[ok2], back_pts[ok2] - wo[i2[ok2]])
        np.add.at(cnt, i2[ok2], 1)
        has = cnt > 0
        if has.sum() < 10:
            break
        disp = np.zeros_like(wo)
        disp[has] = acc[has] / cnt[has, None]
        # Control displacements: the mean over the nearest matched template vertices.
        ctrl = order[:n_ctrl]
        matched = np.nonzero(has)[0]
        k = min(12, len(matched))
        _, nn = cKDTree(wo[matched]).query(wo[ctrl], k=k)
        nn = nn.reshape(len(ctrl), k)
        dist = np.linalg.norm(wo[matched][nn] - wo[ctrl][:, None], axis=2)
        near = dist < 2.5 * limit
        valid = near.any(axis=1)
        c_disp = (disp[matched][nn] * near[..., None]).sum(1)[valid] / near.sum(1)[valid][:, None]
        c_pos = wo[ctrl][valid]
        sm = np.full(len(c_pos), smooth)
        if len(src):
            # Anchors replace the surface controls around them (which would pull them elsewhere).
            far = cKDTree(src).query(c_pos)[0] > 0.5 * limit
            c_pos, c_disp, sm = (
                np.r_[c_pos[far], src],
                np.r_[c_disp[far], dst - src],
                np.r_[sm[far], np.full(len(src), 1e-3)],
            )
        rbf = RBFInterpolator(c_pos, c_disp, kernel="thin_plate_spline", smoothing=sm, degree=1)
        w = w + rbf(w)
        if len(src):
            src = src + rbf(src)
        fields.append(rbf)
    return w, fields


def warp_points(points: np.ndarray, fields: list) -> np.ndarray:
    """Carry template-frame ``points (K, 3)`` through the fitted fields (pivots, extra points)."""
    p = np.atleast_2d(np.asarray(points, dtype=np.float64))
    for f in fields:
        p = p + f(p)
    return p
