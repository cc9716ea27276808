"""The skin of the procedural head: a star-shaped surface r(θ, φ) about ``RAY_ORIGIN``, sampled on a graded
(θ, φ) grid with two slits (mouth, eyes) and a mouth pocket behind the lips.

* Shape: a smooth union of ray-exit distances of ellipsoids (skull, face, jaw, muzzle) and a neck
  cylinder, plus radial features laid out on the face plane (nose, lips, brows, sockets, cheeks,
  chin), and eyelid spheres around the eyeballs.
* Mouth: the grid row through the lip contact is cut between the lip corners; the upper lip uses one
  copy of the row, the lower lip another at the same place (lips in contact, no shared edge). A
  pocket (the mouth cavity) hangs from the cut and closes at the throat.
* Eyes: the row through the pupils is cut between the eye corners and the two sides are pushed
  apart along φ so the cut opens into the palpebral fissure; the lids lie on spheres 1 mm outside
  the eyeballs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .layout import (
    RAY_ORIGIN,
    Layout,
    direction_to,
    gnomonic,
    unit_dirs,
)
from .mesh import (
    graded_axis,
    grid_triangles,
    mirror_cells,
    ray_exit,
    ray_exit_cylinder,
    smooth_max,
    smoothstep,
)


def _lip_profile(u: np.ndarray) -> np.ndarray:
    """Cross-section of a lip from the contact line (u = 0) to the vermilion border (u = 1): rolls
    out quickly, peaks, and meets the skin with zero slope just past the border."""
    return (1 - np.exp(-u / 0.16)) * (1 - smoothstep(0.7, 1.25, u)) * (1 - 0.2 * u)


def _g(px, py, x0, y0, sx, sy):
    return np.exp(-(((px - x0) / sx) ** 2) - ((py - y0) / sy) ** 2)


class SkinModel:
    """The parametric skin surface of one conformation (no sampling yet)."""

    def __init__(self, lay: Layout) -> None:
        self.lay = lay
        # Lip-contact line: level, at the stomion height, curving back along the dental arch.
        xs = np.linspace(-2.0, 2.0, 401) * lay.x_mouth
        pts = np.stack(
            [
                xs,
                np.full_like(xs, lay.y_stomion),
                lay.z_lip_line(np.clip(xs, -1.3 * lay.x_mouth, 1.3 * lay.x_mouth)),
            ],
            -1,
        )
        th, ph = direction_to(pts)
        self.phi_m = float(ph[200])
        self.slit_theta = th
        self.slit_dphi = ph - self.phi_m
        px, py, _ = gnomonic(unit_dirs(th, ph))
        self._slit_px, self._slit_py = px, py
        self.theta_mc = float(
            direction_to(
                np.array([lay.x_mouth, lay.y_stomion, float(lay.z_lip_line(lay.x_mouth))])
            )[0]
        )
        xo = lay.x_mouth + 1.2
        self.theta_oc = float(
            direction_to(np.array([xo, lay.y_stomion, float(lay.z_lip_line(1.05 * lay.x_mouth))]))[
                0
            ]
        )
        self.px_corner = float(np.interp(self.theta_mc, th, px))
        # Eyes (left; the right one is the mirror image).
        e, r = lay.eye_centre_l, lay.lid_radius
        front = e + np.array([0, 0, r])
        self.theta_e, self.phi_e = (float(v) for v in direction_to(front))
        off_in, off_out = lay.canthus_offsets
        cin = e + np.array([off_in, 0, np.sqrt(max(r * r - off_in**2, 0.0)) + 0.3])
        cout = (
            e + np.array([off_out, 0, np.sqrt(max(r * r - off_out**2, 0.0)) + 0.3])
            if abs(off_out) < r
            else e + np.array([off_out, 0, 0.3])
        )
        self.theta_in = float(direction_to(cin)[0])
        self.theta_out = float(direction_to(cout)[0])
        ir = lay.iris_radius
        up = e + np.array([0, ir, np.sqrt(r * r - ir * ir)])
        lo = e + np.array([0, -ir, np.sqrt(r * r - ir * ir)])
        self.d_up = float(direction_to(up)[1]) - self.phi_e
        self.d_lo = self.phi_e - float(direction_to(lo)[1])
        # Secant steps so the lid margins land exactly at the iris top and bottom (lids tangent to the iris).
        th = np.array([self.theta_e])
        for sign, target in ((1, e[1] + ir), (-1, e[1] - ir)):
            d0 = self.d_up if sign > 0 else self.d_lo
            y0 = self.points(th, np.array([self.phi_e + sign * d0]))[0, 1]
            d1 = d0 * 1.02
            for _ in range(4):
                y1 = self.points(th, np.array([self.phi_e + sign * d1]))[0, 1]
                if abs(y1 - target) < 1e-6 or y1 == y0:
                    break
                d0, d1, y0 = d1, d1 + (target - y1) * (d1 - d0) / (y1 - y0), y1
            if sign > 0:
                self.d_up = float(d1)
            else:
                self.d_lo = float(d1)
        self.eye_L = 2.6 * max(self.d_up, self.d_lo)

    # ---- parameter maps -------------------------------------------------------------------------
    def mouth_warp(self, theta: np.ndarray) -> np.ndarray:
        """Elevation offset that makes the slit row follow the level lip-contact line."""
        ta = np.abs(theta)
        edge = self.slit_theta[-1]
        m = np.interp(ta, self.slit_theta[200:], self.slit_dphi[200:])
        return np.where(ta <= edge, m, self.slit_dphi[-1] * np.exp(-(((ta - edge) / 0.3) ** 2)))

    def warp_phi(self, theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
        return phi + self.mouth_warp(theta) * np.exp(-(((phi - self.phi_m) / 0.25) ** 2))

    def unwarp_phi(self, theta: np.ndarray, phi_eff: np.ndarray) -> np.ndarray:
        phi = np.array(phi_eff, dtype=np.float64)
        for _ in range(30):
            phi = phi_eff - (self.warp_phi(theta, phi) - phi)
        return phi

    def eye_opening(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Half-openings (upper, lower) in elevation at azimuth ``theta`` (both eyes, 0 outside them)."""
        ta = np.abs(theta)
        u = np.where(
            ta >= self.theta_e,
            (ta - self.theta_e) / (self.theta_out - self.theta_e),
            (self.theta_e - ta) / (self.theta_e - self.theta_in),
        )
        inside = u < 1
        base = np.where(inside, np.clip(1 - u * u, 0, 1) ** 0.62, 0.0)
        # the upper lid peaks a little towards the nose
        skew = np.where(ta < self.theta_e, 1.0, 1.0 - 0.12 * u)
        return self.d_up * base * skew, self.d_lo * base

    def eye_remap(self, theta: np.ndarray, phi: np.ndarray, side: np.ndarray) -> np.ndarray:
        """Push grid rows away from the eye slit; ``side`` is +1/-1 on the slit row copies, 0 elsewhere."""
        s = phi - self.phi_e
        sign = np.where(side != 0, side, np.sign(s))
        hu, hl = self.eye_opening(theta)
        h = np.where(sign > 0, hu, hl)
        w = np.clip(1 - np.abs(s) / self.eye_L, 0, 1) ** 2
        return phi + sign * h * w

    # ---- the surface -------------------------------------------------------------------------------
    def radius(self, d: np.ndarray) -> np.ndarray:
        """Distance from ``RAY_ORIGIN`` to the skin along unit rays ``d (N, 3)``."""
        lay, c = self.lay, self.lay.conf
        o = RAY_ORIGIN
        cran = ray_exit(
            o, d, (0, c.head_height - 90, -3.0), (c.head_width / 2, 90, c.head_length / 2)
        )
        face = ray_exit(o, d, (0, -26, 10), (c.face_width / 2, 66, 83))
        jaw = ray_exit(o, d, (0, lay.y_menton + 46, 16), (c.jaw_width / 2, 46, 72))
        muzzle = ray_exit(o, d, (0, lay.y_stomion + 4, 48), (lay.x_mouth + 19, 34, 45))
        neck = ray_exit_cylinder(
            o,
            d,
            0.0,
            -14.0,
            0.92 * c.neck_radius,
            c.neck_radius,
            lay.y_menton - c.neck_length,
            30.0,
        )
        r = smooth_max([cran, face, jaw, muzzle, neck], 8.0)
        r = r + self.features(d)
        e = lay.eye_centre_l
        lid_l = ray_exit(o, d, e, (lay.lid_radius,) * 3)
        lid_r = ray_exit(o, d, e * np.array([-1, 1, 1]), (lay.lid_radius,) * 3)
        r = smooth_max([r, lid_l, lid_r], 1.0)
        # upper-lid crease (supratarsal fold), following the lid margin ~8 mm above it
        px, py, fm = gnomonic(d)
        u = (np.abs(px) - e[0]) / 14.5
        arc = e[1] + 3.0 + 7.5 * np.sqrt(np.clip(1 - u * u, 0, 1))
        return r - 0.5 * fm * smoothstep(1.0, 0.55, np.abs(u)) * np.exp(-(((py - arc) / 1.4) ** 2))

    def features(self, d: np.ndarray) -> np.ndarray:
        """Radial relief of the face (mm), laid out on the face plane."""
        lay, c = self.lay, self.lay.conf
        px, py, fm = gnomonic(d)
        ax = np.abs(px)
        ex = lay.eye_centre_l[0]
        yn, ysn = lay.y_nasion, lay.y_subnasale
        out = np.zeros(len(d))
        # eye sockets, brow ridge, glabella, nasion
        out += -8.0 * _g(ax, py, ex, 1.0, 17, 13)
        out += 3.5 * _g(ax, py, ex - 3, c.brow_height - 3, 22, 7) + 3.0 * _g(
            px, py, 0, yn + 8, 12, 8
        )
        out += -2.5 * _g(px, py, 0, yn, 7, 5)
        # temples in, cheekbones out, cheeks
        out += -2.5 * _g(ax, py, c.face_width / 2 - 8, 18, 12, 18)
        out += 4.0 * _g(ax, py, c.face_width / 2 - 22, -16, 20, 12)
        out += 6.5 * _g(ax, py, 42, -42, 19, 19)
        out += 3.5 * _g(ax, py, lay.x_mouth + 9, lay.y_stomion + 2, 11, 13)
        # nose: dorsum ridge with a rounded tip, alae, nostrils
        span = yn - (ysn + 2.0)
        q = (yn - py) / span  # 0 at the nasion, 1 at the subnasale (in face-plane coordinates)
        qt = 0.66  # where the tip is
        prot = c.nose_protrusion + 3.0
        h_up = prot * (0.12 + 0.88 * np.clip(q / qt, 0, 1) ** 1.25)
        h_dn = prot * np.sqrt(np.clip(1 - ((q - qt) / (1 - qt)) ** 2, 0, 1))
        ridge_h = np.where(q < qt, h_up, h_dn) * (q > -0.1)
        ridge_h *= smoothstep(-0.15, 0.05, q)
        w = 4.8 + 3.6 * np.clip(q, 0, 1) + 2.6 * np.exp(-(((q - qt) / 0.12) ** 2))
        ridge = ridge_h * np.exp(-(np.abs(px / w) ** 2.2))
        alae_y = ysn + 0.3 * span * (1 - qt) + 4.0
        alae = 10.0 * _g(ax, py, c.nose_width / 2 - 6.5, alae_y, 6.5, 7.0)
        nose = smooth_max([ridge, alae, np.zeros_like(px)], 1.5)
        out += nose - 1.2 * _g(ax, py, c.nose_width / 2 - 1, alae_y + 2, 2.0, 8.0)
        # philtrum and nasolabial folds
        out += -0.8 * _g(px, py, 0, (ysn + lay.y_stomion) / 2 + 2, 2.5, 6) + 0.6 * _g(
            ax, py, 4.5, (ysn + lay.y_stomion) / 2 + 2, 1.5, 6
        )
        fold_x = (
            c.nose_width / 2
            + 3
            + (py - ysn) / (lay.y_stomion - ysn) * (lay.x_mouth - c.nose_width / 2)
        )
        out += (
            -0.8
            * np.exp(-(((ax - fold_x) / 4.0) ** 2))
            * _g(0, py, 0, (ysn + lay.y_stomion) / 2, 1, 14)
        )
        # lips
        out += self.lips(px, py)
        # chin and labiomental fold
        out += 8.0 * _g(px, py, 0, lay.y_menton + 14, 17, 13) - 2.0 * _g(
            px, py, 0, lay.y_stomion - 21, 16, 4
        )
        return out * fm

    def slit_py(self, px: np.ndarray) -> np.ndarray:
        return np.interp(px, self._slit_px, self._slit_py)

    def lip_heights(self, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Vermilion heights (upper, lower) in face-plane mm at lateral fraction ``a`` (1 = corner)."""
        c = self.lay.conf
        a2 = np.clip(a * a, 0, 1)
        bow = (
            1.0
            - 0.10 * np.exp(-((a / 0.1) ** 2))
            + 0.05 * np.exp(-(((np.abs(a) - 0.28) / 0.1) ** 2))
        )
        return c.lip_thickness * (1 - 0.75 * a2**1.3) * bow, 1.2 * c.lip_thickness * (
            1 - 0.8 * a2**1.2
        )

    def lips(self, px: np.ndarray, py: np.ndarray) -> np.ndarray:
        c = self.lay.conf
        a = px / self.px_corner
        s = py - self.slit_py(px)
        env = smoothstep(1.08, 0.55, np.abs(a)) * (1 - 0.25 * a * a)
        vu, vl = self.lip_heights(a)
        u = np.clip(s / np.maximum(vu, 1e-3), 0, 1.3)
        lo = np.clip(-s / np.maximum(vl, 1e-3), 0, 1.3)
        upper = 0.5 * c.lip_thickness * _lip_profile(u) * (s > 0)
        lower = 0.65 * c.lip_thickness * _lip_profile(lo) * (s <= 0)
        crease = 1.6 * np.exp(-((s / 1.2) ** 2))
        corner = -2.0 * _g(np.abs(a), s, 1.05, 0, 0.12, 3.0)
        return env * (upper + lower - crease) + corner

    def nostrils(self, d: np.ndarray) -> np.ndarray:
        """Depth (mm) of the nostrils on the underside of the nose (0 elsewhere), for rays ``d``."""
        lay = self.lay
        px, py, fm = gnomonic(d)
        yn, ysn = lay.y_nasion, lay.y_subnasale
        span = yn - (ysn + 2.0)
        cy = yn - 0.9 * span
        u = ((np.abs(px) - 6.0) / 3.2) ** 2 + ((py - cy) / 4.0) ** 2
        return 5.5 * fm * np.clip(1 - u, 0, 1) ** 1.5

    def points(self, theta: np.ndarray, phi_remapped: np.ndarray) -> np.ndarray:
        """Skin points ``(N, 3)`` at grid parameters (after the eye remap).

        Points lie on the star-shaped surface, except in the nostrils, which are pushed up into the
        nose (the underside of the nose is nearly parallel to the rays, so radial relief cannot dent it).
        """
        d = unit_dirs(theta, self.warp_phi(theta, phi_remapped))
        p = RAY_ORIGIN + self.radius(d)[:, None] * d
        p[:, 1] += self.nostrils(d)
        return p


@dataclass
class SkinGrid:
    """A sampled skin: vertex parameters and triangles, with the slit bookkeeping."""

    theta: np.ndarray  # (N,) per vertex
    phi: np.ndarray  # (N,) per vertex, before the eye remap
    side: np.ndarray  # (N,) int8: +1 upper copy / -1 lower copy on slit rows, 0 elsewhere
    row: np.ndarray  # (N,) grid row (-1 for pocket vertices)
    col: np.ndarray  # (N,) grid column
    ids: np.ndarray  # (R, C) vertex ids (upper copies on slit rows)
    ids_low: np.ndarray  # (R, C) vertex ids (lower copies on slit rows)
    triangles: np.ndarray
    thetas: np.ndarray  # (C,) column azimuths
    phis: np.ndarray  # (R,) row elevations
    row_mouth: int
    row_eye: int
    mouth_cols: tuple[int, int]  # corner columns (right, left)


def axes_for(model: SkinModel, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Column azimuths (wrapping, no duplicate at ±π) and row elevations (poles included)."""

    def dth(t):
        return 0.38 + 1.25 * np.exp(-((t / 0.7) ** 2)) + 0.25 * np.exp(-(((t - 1.45) / 0.35) ** 2))

    def dph(p):
        return (0.45 + 1.0 * np.exp(-(((p + 0.3) / 0.6) ** 2))) * (0.35 + 0.65 * np.cos(p))

    half = graded_axis(
        [
            0.0,
            model.theta_mc / 2,
            model.theta_in,
            model.theta_mc,
            model.theta_oc,
            model.theta_e,
            model.theta_out,
            np.pi,
        ],
        int(round(np.pi * 0.62 * 95 / spacing)),
        dth,
    )
    thetas = np.concatenate([-half[::-1][:-1], half[:-1]])
    phis = graded_axis(
        [-np.pi / 2, model.phi_m, model.phi_e, np.pi / 2],
        int(round(np.pi * 0.62 * 100 / spacing)),
        dph,
    )
    return thetas, phis


def skin_grid(model: SkinModel, spacing: float) -> SkinGrid:
    """Sample the skin grid (without the mouth pocket) at about ``spacing`` mm on the face."""
    thetas, phis = axes_for(model, spacing)
    nr, nc = len(phis), len(thetas)
    ids = np.empty((nr, nc), dtype=np.int64)
    ids[0] = 0
    ids[1:-1] = 1 + np.arange((nr - 2) * nc).reshape(nr - 2, nc)
    n = 1 + (nr - 2) * nc
    ids[-1] = n
    n += 1
    th = np.empty(n)
    ph = np.empty(n)
    rows = np.empty(n, dtype=np.int64)
    cols = np.empty(n, dtype=np.int64)
    th[ids[1:-1]] = np.broadcast_to(thetas, (nr - 2, nc))
    ph[ids[1:-1]] = np.broadcast_to(phis[1:-1, None], (nr - 2, nc))
    rows[ids[1:-1]] = np.broadcast_to(np.arange(1, nr - 1)[:, None], (nr - 2, nc))
    cols[ids[1:-1]] = np.broadcast_to(np.arange(nc), (nr - 2, nc))
    th[0], ph[0], rows[0], cols[0] = 0.0, -np.pi / 2, 0, 0
    th[-1], ph[-1], rows[-1], cols[-1] = 0.0, np.pi / 2, nr - 1, 0
    side = np.zeros(n, dtype=np.int8)

    jm = int(np.argmin(np.abs(phis - model.phi_m)))
    je = int(np.argmin(np.abs(phis - model.phi_e)))
    i_a = int(np.argmin(np.abs(thetas + model.theta_mc)))
    i_b = int(np.argmin(np.abs(thetas - model.theta_mc)))
    ids_low = ids.copy()
    extra_th, extra_ph, extra_r, extra_c = [], [], [], []

    def cut(row, c0, c1):
        nonlocal n
        cs = np.arange(c0 + 1, c1)
        new = n + np.arange(len(cs))
        ids_low[row, cs] = new
        side[ids[row, cs]] = 1
        extra_th.append(thetas[cs])
        extra_ph.append(np.full(len(cs), phis[row]))
        extra_r.append(np.full(len(cs), row))
        extra_c.append(cs)
        n += len(cs)

    cut(jm, i_a, i_b)
    for sgn in (-1, 1):
        ci = int(np.argmin(np.abs(thetas - sgn * model.theta_in)))
        co = int(np.argmin(np.abs(thetas - sgn * model.theta_out)))
        cut(je, min(ci, co), max(ci, co))
    n_new = sum(len(e) for e in extra_th)
    th = np.concatenate([th] + extra_th)
    ph = np.concatenate([ph] + extra_ph)
    rows = np.concatenate([rows] + extra_r)
    cols = np.concatenate([cols] + extra_c)
    side = np.concatenate([side, -np.ones(n_new, dtype=np.int8)])
    tris = grid_triangles(ids, ids_low, wrap=True, mirror_cols=thetas < -1e-12)
    return SkinGrid(th, ph, side, rows, cols, ids, ids_low, tris, thetas, phis, jm, je, (i_a, i_b))


def mouth_pocket(
    model: SkinModel, grid: SkinGrid, slit_points: np.ndarray, spacing: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The mouth cavity hanging from the lip slit.

    ``slit_points (C, 3)``: positions of the slit row's vertices (by column). Returns
    ``(vertices (P, 3), triangles with ids >= N_skin counted from the skin's vertex count, side (P,), depth (P,))``;
    triangles refer to skin ids for the first ring (the slit itself).
    """
    lay = model.lay
    i_a, i_b = grid.mouth_cols
    jm = grid.row_mouth
    cs = np.arange(i_a + 1, i_b)
    loop = np.concatenate(
        [[grid.ids[jm, i_a]], grid.ids_low[jm, cs], [grid.ids[jm, i_b]], grid.ids[jm, cs[::-1]]]
    )
    lcols = np.concatenate([[i_a], cs, [i_b], cs[::-1]])
    lside = np.concatenate([[0], -np.ones(len(cs)), [0], np.ones(len(cs))])
    base = slit_points[lcols]
    a = np.clip(grid.thetas[lcols] / model.theta_mc, -1, 1)
    dmax = 76.0
    n_rings = max(3, int(round(dmax / (1.6 * spacing))))
    depths = graded_axis([0.0, 6.0, dmax], n_rings, lambda x: 1.0 + 2.0 * np.exp(-x / 6.0))[1:-1]
    z_mid = lay.z_stomion
    dd = depths[:, None]
    close = smoothstep(0.5, 13.0, dd) * np.sqrt(np.clip(1 - (dd / dmax) ** 2, 0, 1))
    h_up, h_lo = 20.0 * close, 25.0 * close
    widen = (1 + 0.45 * smoothstep(2.0, 24.0, dd)) * np.sqrt(np.clip(1 - (dd / dmax) ** 3, 0, 1))
    yc = 3.0 * smoothstep(3.0, 22.0, dd)
    flatten = smoothstep(0.0, 25.0, dd)
    x = base[None, :, 0] * widen
    arc = np.sqrt(np.clip(1 - a[None, :] ** 2, 0, 1))
    y = (
        base[None, :, 1]
        + yc
        + np.where(lside[None, :] > 0, h_up, -h_lo) * np.abs(lside[None, :]) * arc
    )
    z = base[None, :, 2] * (1 - flatten) + z_mid * flatten - dd
    ring_pts = np.stack([x, y, z], -1).reshape(-1, 3)
    pole = np.array([[0.0, lay.y_stomion + 3.0, z_mid - dmax]])
    verts = np.concatenate([ring_pts, pole])
    k, m = len(depths), len(loop)
    return (
        verts,
        loop,
        (k, m),
        np.concatenate([np.tile(lside, k), [0]]),
        np.concatenate([np.repeat(depths, m), [dmax]]),
    )


def pocket_triangles(
    loop: np.ndarray, k: int, m: int, first_id: int, loop_x: np.ndarray | None = None
) -> np.ndarray:
    """Triangles of the pocket: ring 0 = ``loop`` (skin ids), rings 1..k new ids from ``first_id``, then the pole.

    ``loop_x (m,)``: x of the loop vertices; the cells on the -x side take the other diagonal
    (``mirror_cells``), so the mouth pocket is mirror-symmetric and the right eye's sac is the
    mirror image of the left's (whose loop runs the other way round).
    """
    ids = np.empty((k + 2, m), dtype=np.int64)
    ids[0] = loop
    ids[1:-1] = first_id + np.arange(k * m).reshape(k, m)
    ids[-1] = first_id + k * m
    cells = None if loop_x is None else mirror_cells(loop_x)
    return grid_triangles(ids, ids, wrap=True, mirror_cols=cells)


def eye_sac_rings(spacing: float, radius: float) -> int:
    """Number of rings of an eye sac at this spacing."""
    return max(2, int(round(np.pi * radius / (1.8 * spacing))))


def eye_sac(
    grid: SkinGrid,
    skin_v: np.ndarray,
    centre: np.ndarray,
    eye_radius: float,
    cols: tuple[int, int],
    spacing: float,
) -> tuple[np.ndarray, np.ndarray, int, int]:
    """The conjunctival sac of one eye: from the lid margins back around the eyeball (just outside
    it, 0.35 mm outside) to a pole behind it, so the skin is closed and the eye corners show no gap.

    ``cols``: the eye's corner columns on the slit row. Returns ``(vertices (k*m+1, 3), loop ids
    (m,), k, m)``; triangulate with ``pocket_triangles``.
    """
    je = grid.row_eye
    c0, c1 = min(cols), max(cols)
    cs = np.arange(c0 + 1, c1)
    loop = np.concatenate(
        [[grid.ids[je, c0]], grid.ids_low[je, cs], [grid.ids[je, c1]], grid.ids[je, cs[::-1]]]
    )
    p = skin_v[loop] - centre
    dist = np.linalg.norm(p, axis=1)
    u = p / dist[:, None]
    alpha0 = np.arccos(np.clip(u[:, 2], -1, 1))
    beta = np.arctan2(u[:, 1], u[:, 0])
    r_sac = eye_radius + 0.35
    k = eye_sac_rings(spacing, r_sac)
    t = (np.arange(1, k + 1) / (k + 1))[:, None]
    # turn in towards the eyeball at once (so the sac never grazes the lid), then run back around it
    alpha = alpha0[None, :] + (np.pi - alpha0[None, :]) * t**1.25
    rad = r_sac + (dist[None, :] - r_sac) * np.clip(1 - t / 0.08, 0, 1) ** 2
    ring = np.stack(
        [
            rad * np.sin(alpha) * np.cos(beta),
            rad * np.sin(alpha) * np.sin(beta),
            rad * np.cos(alpha),
        ],
        -1,
    )
    verts = np.concatenate([ring.reshape(-1, 3), [[0.0, 0.0, -r_sac]]]) + centre
    return verts, loop, k, len(loop)
