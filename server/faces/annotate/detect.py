"""Facial landmarks found geometrically on a head already aligned to the template (template frame:
mm, y up, z forward, the face's midline near x = 0).

The midline profile (the front-most surface point every millimetre of height within a thin slab
around x = 0) rises and falls in a fixed order going down from the nose tip: subnasale (dip), upper
lip (bump), mouth slit (dip), lower lip (bump), the fold under the lip (dip), chin (bump); the
nasion is the deepest point above the tip. Below the lower lip, the gnathion is where the chin's
front turns under towards the neck (``gnathion``): it says how long the chin is. The same detector
runs on the template and on the mesh, so the pairs it finds pull the template's features onto the
mesh's during the warp.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import find_peaks

#: Names of the profile landmarks, in order from the top.
PROFILE = (
    "nasion",
    "tip",
    "subnasale",
    "lip_upper",
    "slit",
    "lip_lower",
    "fold",
    "chin",
    "gnathion",
)
#: A first dip farther (mm) below the nose's base (``nose_base``) than this may be on the lips (an
#: upper lip that rises straight from the nose, with no dip between them): the profile is then also
#: read with the base as the subnasale.
SUBNASALE_MM = 3.0
#: ``gnathion``: the profile's slope (mm of depth lost per mm of height, going down: 45 degrees) where
#: the chin turns under, and how far (mm) below the lower lip it is looked for.
GNATHION_SLOPE, GNATHION_SPAN_MM = 1.0, 50.0


def midline_section(
    vertices: np.ndarray, triangles: np.ndarray, step: float = 0.5, x: float = 0.0
) -> np.ndarray:
    """``(M, 3)`` points of the surface's section by the plane x = ``x``, every ``step`` mm along it."""
    v = np.asarray(vertices, dtype=np.float64) - np.array([x, 0.0, 0.0])
    t = np.asarray(triangles, dtype=np.int64)
    side = v[t, 0] >= 0  # (F, 3)
    cross = side.any(axis=1) & ~side.all(axis=1)
    t = t[cross]
    ends = []
    for a, b in ((0, 1), (1, 2), (2, 0)):
        pa, pb = v[t[:, a]], v[t[:, b]]
        hit = (pa[:, 0] >= 0) != (pb[:, 0] >= 0)
        f = np.where(hit, pa[:, 0] / np.where(hit, pa[:, 0] - pb[:, 0], 1.0), np.nan)
        ends.append(pa + f[:, None] * (pb - pa))
    e = np.stack(ends, axis=1)  # (F, 3, 3), one NaN row per triangle
    ok = ~np.isnan(e[:, :, 0])
    e = e[ok.sum(axis=1) == 2]
    ok = ~np.isnan(e[:, :, 0])
    p0 = np.array([row[m][0] for row, m in zip(e, ok)]) if len(e) else np.zeros((0, 3))
    p1 = np.array([row[m][1] for row, m in zip(e, ok)]) if len(e) else np.zeros((0, 3))
    if not len(p0):
        return np.zeros((0, 3))
    n = np.maximum(1, np.ceil(np.linalg.norm(p1 - p0, axis=1) / step).astype(int))
    f = np.concatenate([np.linspace(0, 1, k + 1) for k in n])
    rep = np.repeat(np.arange(len(p0)), n + 1)
    return p0[rep] + f[:, None] * (p1[rep] - p0[rep]) + np.array([x, 0.0, 0.0])


def mouth_corners(
    vertices: np.ndarray, triangles: np.ndarray, slit: np.ndarray, half_width: float
) -> dict[str, np.ndarray]:
    """The mouth corners ``{"8.3": (3,), "8.4": (3,)}`` (left = +x, right), by following the mouth
    slit sideways from its midline point ``slit``: in each vertical section x = c (1 mm apart) the
    slit is the front profile's deepest dip near its last height; the corner is where the dip fades
    (under an eighth of its depth at the midline, or 0.25 mm). ``half_width``: the template's (mm); a
    corner closer than 0.6 or farther than 1.6 of it is not trusted (left out)."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    near = (np.abs(v[:, 1] - slit[1]) < 40) & (v[:, 2] > slit[2] - 40)
    t = t[near[t].all(axis=1)]
    out = {}

    def dip(c: float, y_prev: float) -> tuple[float, float, float] | None:
        sec = midline_section(v, t, step=0.3, x=c)
        ys, z = midline_profile(sec, y_range=(y_prev - 12.0, y_prev + 12.0))
        if not np.all(np.isfinite(z)):
            return None
        win = np.abs(ys - y_prev) <= 4.0
        i = int(np.nonzero(win)[0][np.argmin(z[win])])
        above, below = z[(ys > ys[i]) & (ys <= ys[i] + 6)], z[(ys < ys[i]) & (ys >= ys[i] - 6)]
        if not len(above) or not len(below):
            return None
        return float(ys[i]), float(z[i]), float(min(above.max(), below.max()) - z[i])

    first = dip(0.0, float(slit[1]))
    if first is None:
        return {}
    for key, sign in (("8.3", 1.0), ("8.4", -1.0)):
        y_prev, last = first[0], None
        threshold = max(0.25, first[2] / 8)
        for c in np.arange(2.0, 1.7 * half_width, 1.0):
            d = dip(sign * c, y_prev)
            if d is None or d[2] < threshold:
                break
            y_prev, last = d[0], (sign * c, d[0], d[1])
        if last is not None and 0.6 * half_width <= abs(last[0]) <= 1.6 * half_width:
            out[key] = np.array(last)
    return out


def midline_profile(
    points: np.ndarray, *, y_range: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """``(y, z)``: for every 1 mm of height in ``y_range``, the largest z of section ``points (N, 3)``
    (gaps interpolated; NaN when there is too little)."""
    y0, y1 = y_range
    sel = points[(points[:, 1] >= y0) & (points[:, 1] < y1)]
    ys = np.arange(y0, y1, 1.0)
    z = np.full(len(ys), -np.inf)
    if len(sel):
        idx = np.minimum(((sel[:, 1] - y0) // 1.0).astype(int), len(ys) - 1)
        np.maximum.at(z, idx, sel[:, 2])
    ok = np.isfinite(z)
    if ok.sum() < 10:
        return ys, np.full(len(ys), np.nan)
    z = np.interp(ys, ys[ok], z[ok])
    k = np.array([1, 2, 3, 2, 1], float) / 9  # a light smoothing: coarse meshes give a staircase
    return ys, np.convolve(np.pad(z, 2, mode="edge"), k, mode="valid")


def profile_landmarks(
    vertices: np.ndarray, triangles: np.ndarray, expect: dict[str, float] | None = None
) -> dict[str, np.ndarray]:
    """Named midline landmarks ``{name: (3,) point}`` of a surface (template frame).

    ``expect``: the template's landmark heights (mm): each landmark below the tip is then the
    candidate whose depth below the tip is nearest the template's (0.6-1.7 of it, within 18 mm of
    its height), in order; one the profile lacks is left out.
    """
    ys, z = midline_profile(midline_section(vertices, triangles), y_range=(-150.0, 80.0))
    if not np.all(np.isfinite(z)):
        return {}
    out: dict[str, np.ndarray] = {}
    # Near the template's tip height; on a template itself, anywhere from the mouth to the brows.
    lo, hi = (
        (expect["tip"] - 30, expect["tip"] + 30) if expect and "tip" in expect else (-70.0, 40.0)
    )
    band = (ys > lo) & (ys < hi)
    if not band.any():
        return {}
    i_tip = int(np.nonzero(band)[0][np.argmax(z[band])])
    out["tip"] = np.array([0.0, ys[i_tip], z[i_tip]])
    above = (ys > ys[i_tip] + 12) & (ys < ys[i_tip] + 60)
    if above.any():
        idx = np.nonzero(above)[0]
        k = int(np.argmin(z[idx]))
        if 0 < k < len(idx) - 1:  # a dip, not the window's edge (a receding forehead)
            out["nasion"] = np.array([0.0, ys[idx[k]], z[idx[k]]])
    # Going down from the tip: alternate dips and bumps.
    below = z[:i_tip][::-1]  # index 0 = just below the tip
    peaks, _ = find_peaks(below, prominence=0.4)
    dips, _ = find_peaks(-below, prominence=0.4)
    order = ("subnasale", "lip_upper", "slit", "lip_lower", "fold", "chin")
    base = nose_base(below)

    def chain(matched: bool, from_base: bool = False) -> dict[str, np.ndarray]:
        found, pos = {}, 0
        for name in order:
            dip = name in ("subnasale", "slit", "fold")
            cand = dips if dip else peaks
            cand = cand[cand > pos]
            if name == "subnasale" and from_base and base is not None:
                # the nose's base itself: the lip rises straight from the nose (no dip between)
                cand = np.array([base])
            if not matched and len(cand) and name != "subnasale":
                # dips and bumps alternate: a dip where a bump is looked for means the bump is
                # missing (an upper lip merged into the nose), not that the next bump is it
                other = peaks if dip else dips
                if ((other > pos) & (other < cand[0])).any():
                    continue
            if matched:
                # the dip or bump whose depth below the tip is nearest the template's; a feature
                # the profile lacks is skipped, not guessed
                if name not in expect:
                    continue
                depth = ys[i_tip] - ys[i_tip - 1 - cand]
                ratio = depth / max(expect["tip"] - expect[name], 1e-6)
                ok = _plausible(ratio, ys[i_tip - 1 - cand], expect[name])
                if not ok.any():
                    continue
                cand = cand[ok][np.argsort(np.abs(np.log(ratio[ok])))]
            elif not len(cand):
                break
            pos = int(cand[0])
            i = i_tip - 1 - pos
            found[name] = np.array([0.0, ys[i], z[i]])
        return found

    below = chain(False)
    if expect is not None and "tip" in expect:
        # The dips and bumps in order, trusted up to the first implausible one; where the first dip
        # lies well below the nose's base, also read from the base as the subnasale (the dip may
        # then be the mouth's slit) and the reading that explains more kept; or, when both keep
        # fewer, each matched to the template's by its depth below the tip.
        readings = [below]
        first = dips[0] if len(dips) else None
        if base is not None and (first is None or first - base > SUBNASALE_MM):
            readings.append(chain(False, from_base=True))
        kept: dict[str, np.ndarray] = {}
        for reading in readings:
            plausible = {}
            for name in order:
                if name not in reading:
                    continue  # missing from the profile (``chain``), not implausible
                if name not in expect:
                    break
                ratio = (ys[i_tip] - reading[name][1]) / max(expect["tip"] - expect[name], 1e-6)
                if not _plausible(np.array([ratio]), np.array([reading[name][1]]), expect[name])[0]:
                    break
                plausible[name] = reading[name]
            if len(plausible) > len(kept):
                kept = plausible
        matched = chain(True)
        below = kept if len(kept) >= len(matched) else matched
        if (
            "nasion" in out
            and "nasion" in expect
            and abs(out["nasion"][1] - expect["nasion"]) > 25.0
        ):
            del out["nasion"]
    out.update(below)
    start = [out[k][1] for k in ("lip_lower", "fold", "chin") if k in out]
    g = gnathion(ys, z, float(min(start))) if start else None
    if g is not None and expect is not None and "tip" in expect:
        if "gnathion" not in expect:
            g = None
        else:
            ratio = (ys[i_tip] - g[1]) / max(expect["tip"] - expect["gnathion"], 1e-6)
            if not _plausible(np.array([ratio]), np.array([g[1]]), expect["gnathion"])[0]:
                g = None
    if g is not None:
        out["gnathion"] = g
    return out


def nose_base(below: np.ndarray) -> int | None:
    """Index into ``below`` (the profile's depth every mm going down from the nose tip, index 0 just
    below it) where the nose's underside ends: the first point after its steepest descent (within
    25 mm of the tip) where the profile turns steeper than 45 degrees (less than 1 mm of depth lost
    per mm of height). None when there is no underside (under 2 mm per mm anywhere)."""
    drop = -np.diff(below[:26])  # depth lost from each mm to the next
    if not len(drop) or drop.max() < 2.0:
        return None
    k = int(np.argmax(drop))
    flat = np.nonzero(drop[k:] < 1.0)[0]
    return int(k + flat[0]) if len(flat) else None


def gnathion(ys: np.ndarray, z: np.ndarray, start_y: float) -> np.ndarray | None:
    """The chin's lower front corner ``(3,)`` on the midline profile ``(ys, z)`` (``midline_profile``),
    or None: within ``GNATHION_SPAN_MM`` below ``start_y`` (the lower lip, or the chin's bump), the
    profile point farthest forward and down at 45 degrees (largest z - y: where the chin's front
    turns under towards the neck), refined to where the profile's slope passes 1. None when that
    is at either end of the span (the lip's underside, or a neck: no chin turns there; a mask cut
    at the chin)."""
    span = (ys <= start_y) & (ys >= start_y - GNATHION_SPAN_MM)
    idx = np.nonzero(span)[0]
    if len(idx) < 5:
        return None
    k = int(idx[np.argmax(z[idx] - GNATHION_SLOPE * ys[idx])])
    if k <= idx[0] + 1 or k >= idx[-1] - 1:
        return None
    slope = np.gradient(z, ys)  # dz/dy: above 1 below the corner, under 1 above it
    y = float(ys[k])
    for a, b in ((k - 1, k), (k, k + 1)):
        sa, sb = slope[a] - GNATHION_SLOPE, slope[b] - GNATHION_SLOPE
        if sa * sb <= 0 and sa != sb:
            y = float(ys[a] + sa / (sa - sb) * (ys[b] - ys[a]))
            break
    return np.array([0.0, y, float(np.interp(y, ys, z))])


def _plausible(ratio: np.ndarray, y: np.ndarray, expect_y: float) -> np.ndarray:
    """Depth below the tip 0.6-1.7 of the template's, and within 18 mm of its height."""
    return (ratio >= 0.6) & (ratio <= 1.7) & (np.abs(y - expect_y) <= 18.0)


def sphere_centre(points: np.ndarray) -> np.ndarray:
    """Least-squares sphere centre of ``(N, 3)`` points."""
    a = np.c_[2 * points, np.ones(len(points))]
    b = (points**2).sum(axis=1)
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    return sol[:3]
