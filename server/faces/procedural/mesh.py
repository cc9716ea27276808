"""Mesh helpers for the procedural head: graded parameter axes, grid triangulation, closed parametric parts.

Everything here is vectorised NumPy; nothing loops per vertex.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def graded_axis(
    knots: list[float], n_intervals: int, density: Callable[[np.ndarray], np.ndarray]
) -> np.ndarray:
    """Sorted samples of ``[knots[0], knots[-1]]`` that contain every knot exactly.

    About ``n_intervals`` intervals in all, spaced inversely to ``density`` (each knot segment gets
    at least one interval).
    """
    k = np.unique(np.asarray(knots, dtype=np.float64))
    fine = np.linspace(k[0], k[-1], 2049)
    cdf = np.concatenate(
        [[0.0], np.cumsum((density(fine[1:]) + density(fine[:-1])) / 2 * np.diff(fine))]
    )
    ck = np.interp(k, fine, cdf)
    mass = np.diff(ck)
    counts = np.maximum(1, np.round(mass / cdf[-1] * n_intervals).astype(int))
    pieces = []
    for a, b, c in zip(ck[:-1], ck[1:], counts):
        pieces.append(np.interp(np.linspace(a, b, c + 1)[:-1], cdf, fine))
    out = np.concatenate(pieces + [k[-1:]])
    out[np.concatenate([[0], np.cumsum(counts)[:-1]])] = k[
        :-1
    ]  # exact knots despite interpolation rounding
    return out


def grid_triangles(
    ids_low: np.ndarray, ids_high: np.ndarray, wrap: bool, mirror_cols: np.ndarray | None = None
) -> np.ndarray:
    """Triangles of a ``(R, C)`` vertex-id grid, two per cell, counter-clockwise seen with rows up, columns right.

    ``ids_low[r]`` is used when row ``r`` is the lower row of a cell and ``ids_high[r]`` when it is the
    upper row (they differ only along slits). Cells whose corners repeat an id (poles) lose the
    degenerate triangle.
    """
    c = ids_low.shape[1]
    cols = np.arange(c if wrap else c - 1)
    nxt = (cols + 1) % c
    a = ids_low[:-1][:, cols]
    b = ids_low[:-1][:, nxt]
    cc = ids_high[1:][:, nxt]
    d = ids_high[1:][:, cols]
    t1, t2 = np.stack([a, b, cc], -1), np.stack([a, cc, d], -1)
    if (
        mirror_cols is not None
    ):  # cells of these columns take the other diagonal (mirror-symmetric meshes)
        m = np.broadcast_to(np.asarray(mirror_cols)[cols], a.shape)[..., None]
        t1 = np.where(m, np.stack([a, b, d], -1), t1)
        t2 = np.where(m, np.stack([b, cc, d], -1), t2)
    tris = np.concatenate([t1.reshape(-1, 3), t2.reshape(-1, 3)])
    keep = (tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 0] != tris[:, 2])
    return tris[keep]


def mirror_cells(x: np.ndarray) -> np.ndarray:
    """``(C,) bool``: the cells of a wrapped ring of columns (cell j joins columns j and j+1 mod C,
    ``x (C,)`` their x) on the +x side, for ``grid_triangles(mirror_cols=...)``.

    A ring symmetric under x -> -x runs through its mirror half in the opposite direction, so the
    same diagonal in every cell gives mirrored cells opposite diagonals; flipping one half makes the
    triangulation mirror-symmetric (and the surface distances and weights built on it). The +x half
    is flipped: of the two symmetric choices, the -x halves' diagonal is the one that did not fold
    (joy folded the left eye's sac at its outer corner, surprise the mouth pocket on the left).
    """
    x = np.asarray(x, dtype=np.float64)
    return (x + np.roll(x, -1)) > 0


def closed_grid(n_rings: int, n_seg: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Index layout of a closed surface with two poles: ``(ids (n_rings+2, n_seg), ring index, segment index)``.

    Row 0 is the first pole, rows 1..n_rings the rings, the last row the second pole.
    """
    n = n_rings * n_seg + 2
    ids = np.empty((n_rings + 2, n_seg), dtype=np.int64)
    ids[0] = 0
    ids[1:-1] = 1 + np.arange(n_rings * n_seg).reshape(n_rings, n_seg)
    ids[-1] = n - 1
    return ids, np.arange(n_rings + 2), np.arange(n_seg)


def closed_surface(
    points: Callable[[np.ndarray, np.ndarray], np.ndarray],
    t_rings: np.ndarray,
    n_seg: int,
    flip: bool = False,
    mirror: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Sample a closed two-pole parametric surface.

    ``points(t, w)`` maps ``t`` in [0, 1] (0, 1 = poles) and angle ``w`` in [0, 2π) to ``(..., 3)`` points.
    ``t_rings`` are the interior ring parameters (strictly between 0 and 1). ``mirror``: the surface
    is symmetric under x -> -x; triangulate it symmetrically too (``mirror_cells``). Returns
    ``(vertices (n, 3), triangles (m, 3))``; vertex 0 is the pole ``t = 0``, the last the pole ``t = 1``.
    """
    t_rings = np.asarray(t_rings, dtype=np.float64)
    w = np.arange(n_seg) * (2 * np.pi / n_seg)
    tt, ww = np.meshgrid(t_rings, w, indexing="ij")
    ring_pts = points(tt, ww).reshape(-1, 3)
    p0 = points(np.zeros(1), np.zeros(1)).reshape(1, 3)
    p1 = points(np.ones(1), np.zeros(1)).reshape(1, 3)
    verts = np.concatenate([p0, ring_pts, p1])
    ids, _, _ = closed_grid(len(t_rings), n_seg)
    mid = len(t_rings) // 2 * n_seg  # a middle ring: widest, no x near 0 but on the mirror plane
    cells = mirror_cells(ring_pts[mid : mid + n_seg, 0]) if mirror and len(t_rings) else None
    tris = grid_triangles(ids, ids, wrap=True, mirror_cols=cells)
    if flip:
        tris = tris[:, ::-1]
    return verts, tris


def orient_outward(verts: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Flip a closed part's triangles if its signed volume is negative (normals pointing inward)."""
    v = verts[tris]
    vol = np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum()
    return tris if vol >= 0 else tris[:, ::-1].copy()


def ray_exit(origin: np.ndarray, d: np.ndarray, centre, semi, soft: float = 2.0) -> np.ndarray:
    """Distance along unit rays ``d (N, 3)`` from ``origin`` to where they leave an ellipsoid.

    Rays that miss get the closest-approach distance minus the miss (a smooth continuation, so that
    smooth unions of ellipsoids that do not contain the origin have no cliff at their silhouettes);
    ``soft`` (mm) rounds the half-chord near the silhouette.
    """
    s = np.asarray(semi, dtype=np.float64)
    o = (np.asarray(origin, dtype=np.float64) - np.asarray(centre, dtype=np.float64)) / s
    dd = d / s
    a = (dd * dd).sum(-1)
    b = (dd * o).sum(-1)
    c = (o * o).sum() - 1
    q = (b * b - a * c) / (a * a)  # squared half-chord (mm^2), negative for misses
    return -b / a + q / np.sqrt(np.abs(q) + soft * soft)


def ray_exit_cylinder(
    origin: np.ndarray,
    d: np.ndarray,
    cx: float,
    cz: float,
    sx: float,
    sz: float,
    y_bottom: float,
    y_top: float,
) -> np.ndarray:
    """Exit distance from a vertical elliptic cylinder (axis through x=cx, z=cz) cut at ``y_bottom`` and
    ``y_top`` (the origin must be inside)."""
    ox, oz = (origin[0] - cx) / sx, (origin[2] - cz) / sz
    dx, dz = d[:, 0] / sx, d[:, 2] / sz
    a = dx * dx + dz * dz
    b = dx * ox + dz * oz
    c = ox * ox + oz * oz - 1
    disc = np.maximum(b * b - a * c, 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(a > 1e-12, (-b + np.sqrt(disc)) / np.where(a > 1e-12, a, 1), np.inf)
        tp = np.where(
            d[:, 1] < -1e-9, (y_bottom - origin[1]) / np.where(d[:, 1] < -1e-9, d[:, 1], -1), np.inf
        )
        tq = np.where(
            d[:, 1] > 1e-9, (y_top - origin[1]) / np.where(d[:, 1] > 1e-9, d[:, 1], 1), np.inf
        )
    return np.minimum(np.minimum(t, tp), tq)


def smooth_max(values: list[np.ndarray], k: float) -> np.ndarray:
    """Smooth maximum with blend width ``k`` (same units as the values), applied pairwise.

    Polynomial blend: exactly ``max`` where the values differ by more than ``k``, so a surface far
    below another has no influence at all.
    """
    out = values[0]
    for v in values[1:]:
        h = np.clip(k - np.abs(out - v), 0.0, None) / k
        out = np.maximum(out, v) + h * h * k * 0.25
    return out
