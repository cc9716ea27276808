"""Closed parts of the procedural head: eyeballs, teeth, tongue, gums and ears (left ones; right = mirror).

Each builder returns ``(vertices (n, 3), triangles (m, 3), anchors)`` where ``anchors`` names vertex
indices at fixed parameters (feature points), so they are the same points at every resolution.
"""

from __future__ import annotations

import numpy as np

from .layout import Layout
from .mesh import closed_surface, graded_axis, orient_outward, smoothstep

Part = tuple[np.ndarray, np.ndarray, dict[str, int]]


def _ring_index(t_rings: np.ndarray, t: float) -> int:
    return int(np.argmin(np.abs(t_rings - t)))


def eyeball(lay: Layout, spacing: float) -> Part:
    """Left eyeball: sphere about its centre, front pole = pupil centre, rings at the pupil and iris edges.

    The cornea bulges 0.7 mm over the iris. Anchor ``pupil`` is the front pole.
    """
    c = lay.conf
    r = c.eye_radius
    a_p = np.arcsin(lay.iris_radius / 3 / r)
    a_i = np.arcsin(lay.iris_radius / r)
    n = max(4, int(round(np.pi * r / (0.7 * spacing))))
    t = graded_axis([0.0, a_p / np.pi, a_i / np.pi, 1.0], n, lambda x: 1.0 + 1.5 * (x < 0.3))[1:-1]
    n_seg = max(8, 4 * int(round(2 * np.pi * r / (4 * 0.7 * spacing))))
    e = lay.eye_centre_l

    def pts(tt, ww):
        al = np.pi * tt
        bulge = 0.7 * np.clip(1 - (al / a_i) ** 2, 0, 1)
        rr = r + bulge
        return e + np.stack(
            [rr * np.sin(al) * np.cos(ww), rr * np.sin(al) * np.sin(ww), rr * np.cos(al)], -1
        )

    v, f = closed_surface(pts, t, n_seg)
    return v, orient_outward(v - e, f), {"pupil": 0}


def _arch(z_front: float, half_width: float, depth: float):
    """Dental arch (left half): U-shaped, ``z = z_front - depth * (x / half_width)**3.5``; returns
    ``(x, z, arc length)`` samples."""
    x = np.linspace(0, half_width * 1.3, 2001)
    z = z_front - depth * (x / half_width) ** 3.5
    s = np.concatenate([[0], np.cumsum(np.hypot(np.diff(x), np.diff(z)))])
    return x, z, s


_UPPER = [  # width, height, labio-lingual depth (mm), central incisor first
    (8.5, 10.5, 7.0),
    (6.6, 9.0, 6.2),
    (7.6, 10.0, 8.0),
    (7.0, 8.2, 9.0),
    (6.6, 7.8, 9.0),
    (10.0, 7.2, 11.0),
    (9.0, 6.8, 10.5),
]
_LOWER = [
    (5.4, 9.0, 6.0),
    (5.9, 9.0, 6.2),
    (6.9, 10.0, 7.5),
    (7.0, 8.4, 7.8),
    (7.1, 8.0, 8.2),
    (11.0, 7.5, 10.5),
    (10.5, 7.2, 10.0),
]


def teeth(lay: Layout, spacing: float, upper: bool) -> Part:
    """Left half-arch of upper or lower teeth: rounded blocks along a parabolic arch.

    Anchors: ``edge`` (biting-edge centre of the central incisor) and ``root`` (the opposite end).
    """
    spec = _UPPER if upper else _LOWER
    zf = lay.z_incisors - (0.0 if upper else 1.2)
    hw = 24.5 if upper else 23.0
    x, z, s = _arch(zf, hw, 38.0 if upper else 36.0)
    y0 = lay.y_occlusal
    verts, tris, anchors = [], [], {}
    pos, nv = 0.4, 0
    for k, (w, h, dpt) in enumerate(spec):
        sc = s_c = pos + w / 2
        pos += w + 0.35
        xc, zc = np.interp(s_c, s, x), np.interp(sc, s, z)
        i = np.searchsorted(s, s_c)
        tx, tz = (
            x[min(i + 1, len(x) - 1)] - x[max(i - 1, 0)],
            z[min(i + 1, len(z) - 1)] - z[max(i - 1, 0)],
        )
        tn = np.hypot(tx, tz)
        tang = np.array([tx / tn, 0, tz / tn])
        lab = np.array([-tang[2], 0, tang[0]])
        yc = y0 + h / 2 if upper else y0 - h / 2
        centre = np.array([xc, yc, zc]) - lab * dpt / 2
        n_r = int(np.clip(round(h / (0.9 * spacing)), 2, 12))
        n_s = int(np.clip(2 * round((w + dpt) / (0.9 * spacing)), 6, 32))
        incisor = k < 3

        def pts(tt, ww, w=w, h=h, dpt=dpt, centre=centre, tang=tang, lab=lab, incisor=incisor):
            eta = np.pi * tt - np.pi / 2  # -pi/2 at t=0 (edge for upper, root end for lower)
            if not upper:
                eta = -eta
            ex = 0.45
            ce, se = np.cos(eta), np.sin(eta)
            cw, sw = np.cos(ww), np.sin(ww)
            px = np.sign(ce) * np.abs(ce) ** ex * np.sign(cw) * np.abs(cw) ** ex
            py = np.sign(se) * np.abs(se) ** ex
            pz = np.sign(ce) * np.abs(ce) ** ex * np.sign(sw) * np.abs(sw) ** ex
            frac = (py + 1) / 2 if upper else (1 - py) / 2  # 0 at the biting edge
            thin = (0.35 + 0.65 * smoothstep(0.0, 0.7, frac)) if incisor else (0.85 + 0.15 * frac)
            return (
                centre
                + (px * w / 2)[..., None] * tang
                + (py * h / 2)[..., None] * np.array([0.0, 1.0, 0.0])
                + (pz * dpt / 2 * thin)[..., None] * lab
            )

        t = (np.arange(n_r) + 0.5) / n_r
        t = np.clip(t, 0.02, 0.98)
        v, f = closed_surface(pts, t, n_s)
        f = orient_outward(v - v.mean(axis=0), f)
        if k == 0:
            anchors["edge"] = nv + 0  # t = 0 pole: the biting edge
            anchors["root"] = nv + len(v) - 1  # t = 1 pole
        verts.append(v)
        tris.append(f + nv)
        nv += len(v)
    return np.concatenate(verts), np.concatenate(tris), anchors


def gums(lay: Layout, spacing: float, upper: bool) -> Part:
    """Left half of a gum ridge: a flattened tube along the arch over the tooth roots (closed at both ends)."""
    zf = lay.z_incisors - (0.0 if upper else 1.2)
    hw = 24.5 if upper else 23.0
    x, z, s = _arch(zf, hw, 38.0 if upper else 36.0)
    length = sum(t[0] + 0.35 for t in (_UPPER if upper else _LOWER)) + 0.4
    y = lay.y_occlusal + (9.8 if upper else -9.0)
    n_r = max(4, int(round(length / (1.2 * spacing))))
    n_s = max(6, 2 * int(round(24 / (2 * 1.2 * spacing))))

    def pts(tt, ww):
        sc = -1.5 + tt * (length + 1.5)
        xc, zc = np.interp(sc, s, x, left=-1.5), np.interp(sc, s, z, left=zf)
        dx = np.interp(sc + 0.5, s, x) - np.interp(sc - 0.5, s, x)
        dz = np.interp(sc + 0.5, s, z) - np.interp(sc - 0.5, s, z)
        nrm = np.hypot(dx, dz)
        ok = nrm > 1e-9
        lx = np.where(ok, -dz / np.where(ok, nrm, 1), 0.0)
        lz = np.where(ok, dx / np.where(ok, nrm, 1), 1.0)
        cap = np.sin(np.pi * np.clip(tt, 0, 1)) ** 0.3
        rw, rh = 4.8 * cap, 3.6 * cap
        off = -3.6
        px = xc + (off + rw * np.cos(ww)) * lx
        pz = zc + (off + rw * np.cos(ww)) * lz
        py = y + rh * np.sin(ww)
        return np.stack([px, np.broadcast_to(py, px.shape), pz], -1)

    t = (np.arange(1, n_r + 1)) / (n_r + 1)
    v, f = closed_surface(pts, t, n_s)
    return v, orient_outward(v - v.mean(axis=0), f), {}


def tongue(lay: Layout, spacing: float) -> Part:
    """The tongue (whole, symmetric): front pole = tip (FP 6.1) just behind the lower incisors.

    Anchors: ``tip``, ``body`` (top centre), ``left``, ``right`` (side edges).
    """
    length, wmax = 47.0, 15.0
    z_tip = lay.z_incisors - 1.2 - 6.8
    y_top = lay.y_occlusal - 1.0
    t_body, t_edge = 0.45, 0.3
    n = max(4, int(round(length / (0.9 * spacing))))
    t = graded_axis([0.0, t_edge, t_body, 1.0], n, lambda x: np.ones_like(x))[1:-1]
    n_seg = max(8, 4 * int(round(2 * np.pi * 12 / (4 * 0.9 * spacing))))

    def pts(tt, ww):
        g = np.sin(np.pi * np.clip(tt, 0, 1) ** 0.65) ** 0.55
        top = y_top - 5.0 * tt
        ht, hb = 5.0 * g, 11.0 * g
        ymid = top - ht
        sw = np.sin(ww)
        y = ymid + np.where(sw > 0, ht, hb) * sw
        x = wmax * g * np.cos(ww)
        z = z_tip - length * tt
        return np.stack([x, y, np.broadcast_to(z, x.shape)], -1)

    v, f = closed_surface(pts, t, n_seg, mirror=True)
    f = orient_outward(v - v.mean(axis=0), f)
    r_body, r_edge = _ring_index(t, t_body), _ring_index(t, t_edge)
    anchors = {
        "tip": 0,
        "body": 1 + r_body * n_seg + n_seg // 4,
        "left": 1 + r_edge * n_seg + 0,
        "right": 1 + r_edge * n_seg + n_seg // 2,
    }
    return v, f, anchors


def ear(lay: Layout, spacing: float, attach: np.ndarray) -> Part:
    """Left ear: a flattened shell tilted back, flared from the head, with a concha bowl and a narrow lobe.

    ``attach``: skin point at the ear's centre. Anchors: ``top``, ``back``, ``lobe``.
    """
    size = lay.conf.ear_size
    ah, aw, at = size / 2, size * 0.29, 4.5
    beta, psi = np.radians(14), np.radians(24)
    up = np.array([0.0, np.cos(beta), -np.sin(beta)])
    fwd0 = np.array([0.0, np.sin(beta), np.cos(beta)])
    out0 = np.array([1.0, 0.0, 0.0])
    fwd = np.cos(psi) * fwd0 - np.sin(psi) * out0
    out = np.sin(psi) * fwd0 + np.cos(psi) * out0
    centre = attach + out0 * 6.0 - fwd0 * 2.0
    n = max(4, int(round(np.pi * 10 / (0.9 * spacing))))
    t = graded_axis([0.0, 0.5, 1.0], n, lambda x: np.ones_like(x))[1:-1]
    n_seg = max(8, 4 * int(round(2 * np.pi * 23 / (4 * 0.9 * spacing))))

    def pts(tt, ww):
        st, ct = np.sin(np.pi * tt), np.cos(np.pi * tt)
        u, v = st * np.sin(ww), st * np.cos(ww)  # u: up, v: forward (unit disc)
        width = aw * (0.82 + 0.22 * u) * (1 - 0.12 * smoothstep(-0.3, -1.0, u))
        bowl = np.exp(-(((u + 0.18) / 0.36) ** 2) - ((v - 0.22) / 0.42) ** 2)  # concha
        scapha = np.exp(-(((st - 0.8) / 0.07) ** 2)) * smoothstep(
            -0.2, 0.3, u - 0.4 * v
        )  # groove inside the rim
        lobe = smoothstep(-0.55, -0.85, u)  # the lobe is flat and soft
        rim = 1.0 + 0.9 * smoothstep(0.8, 0.97, st) * (1 - lobe)
        thick = at * ct * np.where(ct > 0, np.maximum(rim - 2.0 * bowl - 0.6 * scapha, -0.7), 1.0)
        return (
            centre
            + (u * ah)[..., None] * up
            + (v * width)[..., None] * fwd
            + thick[..., None] * out
        )

    v, f = closed_surface(pts, t, n_seg)
    f = orient_outward(v - v.mean(axis=0), f)
    r_eq = _ring_index(t, 0.5)
    base = 1 + r_eq * n_seg
    return (
        v,
        f,
        {"top": base + n_seg // 4, "back": base + n_seg // 2, "lobe": base + 3 * n_seg // 4},
    )
