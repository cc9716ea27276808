"""The built-in procedural head ``default``: a parametric adult head in millimetres, in the spirit of
Parke's parametric face.

``build_default_head(n_vertices, **conformation)`` samples the same parametric surfaces at a density
derived from ``n_vertices`` (about 2k to 500k+ vertices), so the shape and the 84 MPEG-4 feature
points (placed at fixed surface parameters) agree across resolutions. Parts: ``skin`` (head, face,
ears, neck stub, the mouth cavity behind the lips and the sacs behind the eyelids: a closed surface
apart from the separate ears), ``eye_l``/``eye_r`` (eyeballs, pupil centre = front pole),
``teeth_upper``/``teeth_lower``, ``gums_upper``/``gums_lower``, ``tongue``; plus annotation subsets of
``skin`` (``SKIN_SUBSETS``): ``lip_upper``, ``lip_lower`` (vermilion and inner lip, never joined by an
edge), ``mouth_socket`` (the cavity), ``eye_socket_l``/``eye_socket_r`` (the sacs). See
``skin`` for how the surfaces are made; ``head_colors`` colours it for previews."""

from __future__ import annotations

import hashlib
import logging
import os
from dataclasses import asdict, fields
from functools import lru_cache
from pathlib import Path

import numpy as np

from ... import paths
from ...errors import InputError
from ..face import Face
from .layout import (
    RAY_ORIGIN,
    Conformation,
    Layout,
    direction_from_plane,
    direction_to,
    gnomonic,
)
from .parts import ear, eyeball, gums, teeth, tongue
from .skin import (
    SkinGrid,
    SkinModel,
    axes_for,
    eye_sac,
    eye_sac_rings,
    mouth_pocket,
    pocket_triangles,
    skin_grid,
)

log = logging.getLogger(__name__)

__all__ = ["MAX_VERTICES", "MIN_VERTICES", "Conformation", "build_default_head", "head_colors"]

MIN_VERTICES = 1_000
MAX_VERTICES = 5_000_000
#: Annotation parts that are subsets of ``skin`` (not rigid, not disjoint from ``skin``).
SKIN_SUBSETS = ("lip_upper", "lip_lower", "mouth_socket", "eye_socket_l", "eye_socket_r")

_MIRROR = np.array([-1.0, 1.0, 1.0])


def build_default_head(n_vertices: int = 25_000, **conformation: float) -> Face:
    """The built-in head with about ``n_vertices`` vertices (within ~15 %), in mm, MPEG-4 axes.

    ``conformation``: any field of ``Conformation`` (mm), e.g. ``face_width=140, nose_length=50``.
    Deterministic and memoised: the same arguments give equal arrays (each call returns a fresh
    ``Face`` over copies, so callers may modify it).
    """
    n = int(n_vertices)
    if not MIN_VERTICES <= n <= MAX_VERTICES:
        raise InputError(
            f"the built-in head needs between {MIN_VERTICES} and {MAX_VERTICES} vertices, not {n}",
            where="n_vertices",
        )
    names = set(Conformation.names())
    unknown = sorted(set(conformation) - names)
    if unknown:
        raise InputError(
            f"unknown head conformation parameter(s) {', '.join(unknown)}; "
            f"known: {', '.join(sorted(names))}",
            where="conformation",
        )
    conf = Conformation(**{k: float(v) for k, v in conformation.items()})
    face = _build(n, conf)
    return Face(
        name=face.name,
        vertices=face.vertices.copy(),
        triangles=face.triangles.copy(),
        units="mm",
        parts={**{k: v.copy() for k, v in face.parts.items()}, **iris_parts(face)},
        feature_points=dict(face.feature_points),
        pivots={k: v.copy() for k, v in face.pivots.items()},
    )


def iris_parts(face: Face) -> dict[str, np.ndarray]:
    """``iris_l`` / ``iris_r``: eyeball vertices within the iris disc around the pupil (3.5 / 3.6).

    The iris radius is 0.475 of the eyeball radius (an 11-12 mm iris on a 12 mm eyeball).
    """
    out = {}
    for eye, fp in (("eye_l", "3.5"), ("eye_r", "3.6")):
        ids = face.part(eye)
        if not len(ids) or fp not in face.feature_points:
            continue
        centre = face.pivot(eye)
        v = face.vertices[ids].astype(np.float64) - centre
        r = np.linalg.norm(v, axis=1)
        front = face.fp_position(fp) - centre
        cosang = v @ (front / np.linalg.norm(front)) / np.maximum(r, 1e-9)
        lateral = r * np.sqrt(np.clip(1 - cosang**2, 0, 1))
        out["iris" + eye[3:]] = ids[(cosang > 0) & (lateral < 0.475 * np.linalg.norm(front))]
    return out


def _name(n: int, conf: Conformation) -> str:
    changed = {
        f.name: getattr(conf, f.name) for f in fields(conf) if getattr(conf, f.name) != f.default
    }
    extra = "".join(f",{k}={v:g}" for k, v in sorted(changed.items()))
    return f"default:{n}{extra}"


@lru_cache(maxsize=6)
def _build(n: int, conf: Conformation) -> Face:
    name = _name(n, conf)
    use_disk = n >= DISK_CACHE_MIN_VERTICES
    path = None
    if use_disk:
        try:
            path = paths.cache_dir("faces") / f"default-{_cache_key(n, conf)}.npz"
            if path.exists():
                return _load_npz(path, name)
        except Exception as exc:  # noqa: BLE001 - a damaged or unreadable cache is rebuilt, never fatal
            log.warning("ignoring cached head %s: %s", path, exc)
    lay = Layout(conf)
    model = SkinModel(lay)
    spacing = _calibrate(model, lay, n)
    face = _assemble(model, lay, spacing, name)
    if use_disk and path is not None:
        try:
            _save_npz(path, face)
        except OSError as exc:
            log.warning("could not cache the head in %s: %s", path, exc)
    return face


#: Heads at least this large are cached on disk (building 500k vertices takes a few seconds).
DISK_CACHE_MIN_VERTICES = 150_000


def _cache_key(n: int, conf: Conformation) -> str:
    h = hashlib.blake2b(digest_size=10)
    here = Path(__file__).parent
    for f in sorted(here.glob("*.py")) + [here.parent / "face.py"]:
        h.update(f.read_bytes())
    h.update(repr((n, sorted(asdict(conf).items()))).encode())
    return h.hexdigest()


def _save_npz(path: Path, face: Face) -> None:
    arrays = {
        "vertices": face.vertices,
        "triangles": face.triangles,
        "fp_names": np.array(list(face.feature_points)),
        "fp_ids": np.array(list(face.feature_points.values())),
        "pivot_names": np.array(list(face.pivots)),
        "pivots": np.array([face.pivots[k] for k in face.pivots]),
    }
    for k, v in face.parts.items():
        arrays[f"part_{k}"] = v
    tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, path)


def _load_npz(path: Path, name: str) -> Face:
    with np.load(path) as z:
        parts = {k[5:]: z[k] for k in z.files if k.startswith("part_")}
        fps = dict(zip(z["fp_names"].tolist(), z["fp_ids"].tolist()))
        pivots = dict(zip(z["pivot_names"].tolist(), z["pivots"]))
        return Face(
            name=name,
            vertices=z["vertices"],
            triangles=z["triangles"],
            units="mm",
            parts=parts,
            feature_points=fps,
            pivots=pivots,
        )


# ---- resolution --------------------------------------------------------------------------------------
def _skin_count(model: SkinModel, spacing: float) -> int:
    thetas, phis = axes_for(model, spacing)
    nr, nc = len(phis), len(thetas)
    mouth = int(np.sum(np.abs(thetas) < model.theta_mc - 1e-9))
    eyes = 2 * int(
        np.sum((np.abs(thetas) > model.theta_in + 1e-9) & (np.abs(thetas) < model.theta_out - 1e-9))
    )
    rings = max(3, int(round(76.0 / (1.6 * spacing)))) - 1
    sacs = eye_sac_rings(spacing, model.lay.conf.eye_radius + 0.35) * (eyes + 4) + 2
    return (nr - 2) * nc + 2 + mouth + eyes + rings * 2 * (mouth + 1) + 1 + sacs


def _parts(model: SkinModel, lay: Layout, spacing: float) -> dict[str, tuple]:
    ear_dir = direction_to(np.array([lay.conf.head_width / 2, lay.ear_centre_height, -6.0]))
    attach = model.points(np.array([ear_dir[0]]), np.array([ear_dir[1]]))[0]
    return {
        "eye": eyeball(lay, spacing),
        "teeth_upper": teeth(lay, spacing, True),
        "teeth_lower": teeth(lay, spacing, False),
        "gums_upper": gums(lay, spacing, True),
        "gums_lower": gums(lay, spacing, False),
        "tongue": tongue(lay, spacing),
        "ear": ear(lay, spacing, attach),
    }


def _parts_count(parts: dict[str, tuple]) -> int:
    mirrored = ("eye", "teeth_upper", "teeth_lower", "gums_upper", "gums_lower", "ear")
    return sum(len(v) * (2 if k in mirrored else 1) for k, (v, _, _) in parts.items())


def _calibrate(model: SkinModel, lay: Layout, n: int) -> float:
    """Spacing (mm on the face) that gives about ``n`` vertices in all."""
    spacing = np.sqrt(190_000.0 / n)
    for _ in range(2):
        p0, s0 = _parts_count(_parts(model, lay, spacing)), spacing
        lo, hi = np.log(0.05), np.log(60.0)
        for _ in range(24):
            mid = (lo + hi) / 2
            sp = float(np.exp(mid))
            if _skin_count(model, sp) + p0 * (s0 / sp) ** 2 > n:
                lo = mid
            else:
                hi = mid
        spacing = float(np.exp((lo + hi) / 2))
    return spacing


# ---- feature points on the skin ------------------------------------------------------------------------
def _skin_targets(model: SkinModel, lay: Layout) -> dict[str, tuple[float, float]]:
    """Left-side and midline skin FPs as grid parameters (theta, phi before the eye remap)."""
    c = lay.conf
    ex = lay.eye_centre_l[0]
    yn, ysn, ymen = lay.y_nasion, lay.y_subnasale, lay.y_menton
    span = yn - (ysn + 2.0)
    out: dict[str, tuple[float, float]] = {}

    def plane(fp, px, py):
        th, ph = direction_from_plane(px, py)
        out[fp] = (float(th), float(model.unwarp_phi(th, ph)))

    def point(fp, p):
        th, ph = direction_to(np.asarray(p, dtype=np.float64))
        out[fp] = (float(th), float(model.unwarp_phi(th, ph)))

    point("2.1", (0, ymen - 3, 62))
    plane("2.10", 0, ymen + 14)
    plane("2.11", 19, ymen + 11)
    point("2.13", (c.jaw_width / 2, ymen + 27, 14))
    plane("4.1", ex - 15, c.brow_height - 5)
    plane("4.3", ex, c.brow_height)
    plane("4.5", ex + 16, c.brow_height - 6)
    plane("5.1", 38, -38)
    plane("5.3", c.face_width / 2 - 20, -16)
    point("7.1", (0, -52, -80))
    a = np.array([0.0, 0.5, 0.28])
    px = a * model.px_corner
    vu, vl = model.lip_heights(a)
    sp = model.slit_py(px)
    plane("8.1", 0, sp[0] + vu[0])
    plane("8.2", 0, sp[0] - vl[0])
    plane("8.5", px[1], sp[1] + vu[1])
    plane("8.7", px[1], sp[1] - vl[1])
    plane("8.10", px[2], sp[2] + vu[2])
    qt = 0.66
    plane("9.1", c.nose_width / 2 - 3.0, ysn + 0.3 * span * (1 - qt) + 4.0)
    plane("9.3", 0, yn - qt * span)
    plane("9.5", c.nose_width / 2 - 6.0, ysn + 2.5)
    plane("9.7", 5.5, yn - 3)
    plane("9.12", 0, yn - 0.36 * span)
    plane("9.13", 8.0, yn - 0.36 * span)
    plane("9.15", 0, ysn + 1.0)
    point("10.7", (c.head_width / 2 - 2, lay.ear_centre_height - 26, 4))
    point("10.9", (c.head_width / 2 - 2, lay.ear_centre_height + 24, 2))
    point("11.1", (0, 70, 85))
    point("11.3", (c.head_width / 2 - 18, 52, 50))
    # no hair: "top of the hair" (11.5) is the skull vertex just in front of the top (11.4)
    out["11.5"] = (0.0, float(np.pi / 2 - 0.05))
    point("11.6", (0, 20, -110))
    out["3.9"] = (model.theta_e, model.phi_e - 0.6 * model.eye_L)
    out["3.13"] = (model.theta_e, model.phi_e + 0.6 * model.eye_L)
    return out


#: left skin FP -> right counterpart (midline points have none)
_PAIRS = {
    "2.11": "2.12",
    "2.13": "2.14",
    "4.1": "4.2",
    "4.3": "4.4",
    "4.5": "4.6",
    "5.1": "5.2",
    "5.3": "5.4",
    "8.5": "8.6",
    "8.7": "8.8",
    "8.10": "8.9",
    "9.1": "9.2",
    "9.5": "9.4",
    "9.7": "9.6",
    "9.13": "9.14",
    "10.7": "10.8",
    "10.9": "10.10",
    "11.3": "11.2",
    "3.9": "3.10",
    "3.13": "3.14",
}


def _snap(
    grid: SkinGrid,
    targets: dict[str, tuple[float, float]],
    protected_rows: set[int],
    taken: set[int],
) -> dict[str, int]:
    """Move the nearest free grid node of each target onto it (staying well inside its link; else use it as is)."""
    nr, nc = len(grid.phis), len(grid.thetas)
    ext = np.concatenate([grid.thetas, [np.pi]])
    out = {}
    for fp, (t, p) in targets.items():
        t = (t + np.pi) % (2 * np.pi) - np.pi
        fi = float(np.interp(t, ext, np.arange(nc + 1)))
        fj = float(np.interp(p, grid.phis, np.arange(nr)))
        best, best_cost, fallback, fb_cost = None, 9.0, None, 1e9
        for j in range(int(np.floor(fj)) - 1, int(np.ceil(fj)) + 2):
            if j <= 0 or j >= nr - 1 or j in protected_rows:
                continue
            for i in range(int(np.floor(fi)) - 1, int(np.ceil(fi)) + 2):
                vid = int(grid.ids[j, i % nc])
                if vid in taken:
                    continue
                dx, dy = fi - i, fj - j
                # the node may move inside its link hexagon (diagonals are mirrored for theta < 0)
                th = grid.thetas[i % nc]
                skew = max(abs(dx - dy) if th >= 0 else 0.0, abs(dx + dy) if th <= 0 else 0.0)
                cost = max(abs(dx), abs(dy), skew)
                if cost <= 0.9 and cost < best_cost:
                    best, best_cost = vid, cost
                d2 = dx * dx + dy * dy
                if d2 < fb_cost:
                    fallback, fb_cost = vid, d2
        if best is not None:
            grid.theta[best], grid.phi[best] = t, p
            out[fp] = best
        else:
            out[fp] = fallback
        taken.add(out[fp])
    return out


# ---- assembly --------------------------------------------------------------------------------------------
def _assemble(model: SkinModel, lay: Layout, spacing: float, name: str) -> Face:
    grid = skin_grid(model, spacing)
    jm, je = grid.row_mouth, grid.row_eye
    i_a, i_b = grid.mouth_cols
    col = {
        k: int(np.argmin(np.abs(grid.thetas - v)))
        for k, v in (
            ("0", 0.0),
            ("m2l", model.theta_mc / 2),
            ("m2r", -model.theta_mc / 2),
            ("ocl", model.theta_oc),
            ("ocr", -model.theta_oc),
            ("el", model.theta_e),
            ("er", -model.theta_e),
            ("inl", model.theta_in),
            ("inr", -model.theta_in),
            ("outl", model.theta_out),
            ("outr", -model.theta_out),
        )
    }
    fps: dict[str, int] = {
        "2.2": grid.ids[jm, col["0"]],
        "2.3": grid.ids_low[jm, col["0"]],
        "2.4": grid.ids[jm, i_b],
        "2.5": grid.ids[jm, i_a],
        "2.6": grid.ids[jm, col["m2l"]],
        "2.7": grid.ids[jm, col["m2r"]],
        "2.8": grid.ids_low[jm, col["m2l"]],
        "2.9": grid.ids_low[jm, col["m2r"]],
        "8.3": grid.ids[jm, col["ocl"]],
        "8.4": grid.ids[jm, col["ocr"]],
        "3.1": grid.ids[je, col["el"]],
        "3.2": grid.ids[je, col["er"]],
        "3.3": grid.ids_low[je, col["el"]],
        "3.4": grid.ids_low[je, col["er"]],
        "3.7": grid.ids[je, col["outl"]],
        "3.12": grid.ids[je, col["outr"]],
        "3.11": grid.ids[je, col["inl"]],
        "3.8": grid.ids[je, col["inr"]],
        "11.4": grid.ids[-1, 0],
    }
    fps = {k: int(v) for k, v in fps.items()}
    targets = _skin_targets(model, lay)
    ordered: dict[str, tuple[float, float]] = {}
    for fp, (t, p) in targets.items():
        ordered[fp] = (t, p)
        if fp in _PAIRS:
            ordered[_PAIRS[fp]] = (-t, p)
    fps.update(_snap(grid, ordered, {jm, je}, set(fps.values())))

    phi1 = model.eye_remap(grid.theta, grid.phi, grid.side)
    skin_v = model.points(grid.theta, phi1)
    slit = skin_v[grid.ids[jm]]
    pocket_v, loop, (k, m), pocket_side, pocket_depth = mouth_pocket(model, grid, slit, spacing)
    n_grid = len(skin_v)
    pocket_f = pocket_triangles(loop, k, m, n_grid, skin_v[loop, 0])
    near = np.isin(grid.triangles, loop).any(axis=1)
    if _has_duplicate_directed_edges(np.concatenate([grid.triangles[near], pocket_f[: 2 * m]])):
        pocket_f = pocket_f[:, ::-1]

    verts = [skin_v, pocket_v]
    tris = [grid.triangles, pocket_f]
    nv = n_grid + len(pocket_v)
    sockets = {}
    for sgn in (1.0, -1.0):
        centre = lay.eye_centre_l * np.array([sgn, 1.0, 1.0])
        cols = (col["inl" if sgn > 0 else "inr"], col["outl" if sgn > 0 else "outr"])
        sac_v, sac_loop, sk, sm = eye_sac(grid, skin_v, centre, lay.conf.eye_radius, cols, spacing)
        sac_f = pocket_triangles(sac_loop, sk, sm, nv, skin_v[sac_loop, 0])
        near = np.isin(grid.triangles, sac_loop).any(axis=1)
        if _has_duplicate_directed_edges(np.concatenate([grid.triangles[near], sac_f[: 2 * sm]])):
            sac_f = sac_f[:, ::-1]
        verts.append(sac_v)
        tris.append(sac_f)
        sockets["eye_socket_l" if sgn > 0 else "eye_socket_r"] = np.arange(nv, nv + len(sac_v))
        nv += len(sac_v)
    parts: dict[str, list[np.ndarray]] = {"skin": [np.arange(nv)]}

    def add(part: str, v: np.ndarray, f: np.ndarray) -> int:
        nonlocal nv
        start = nv
        verts.append(v)
        tris.append(f + start)
        parts.setdefault(part, []).append(np.arange(start, start + len(v)))
        nv += len(v)
        return start

    built = _parts(model, lay, spacing)
    ev, ef, ea = built["eye"]
    fps["3.5"] = add("eye_l", ev, ef) + ea["pupil"]
    fps["3.6"] = add("eye_r", ev * _MIRROR, ef[:, ::-1]) + ea["pupil"]
    for part in ("teeth_upper", "teeth_lower", "gums_upper", "gums_lower"):
        v, f, an = built[part]
        s = add(part, v, f)
        add(part, v * _MIRROR, f[:, ::-1])
        if part == "teeth_upper":
            fps["9.10"], fps["9.8"] = s + an["edge"], s + an["root"]
        elif part == "teeth_lower":
            fps["9.11"], fps["9.9"] = s + an["edge"], s + an["root"]
    tv, tf, ta = built["tongue"]
    s = add("tongue", tv, tf)
    fps.update(
        {"6.1": s + ta["tip"], "6.2": s + ta["body"], "6.3": s + ta["left"], "6.4": s + ta["right"]}
    )
    av, af, aa = built["ear"]
    s = add("skin", av, af)
    fps.update({"10.1": s + aa["top"], "10.3": s + aa["back"], "10.5": s + aa["lobe"]})
    s = add("skin", av * _MIRROR, af[:, ::-1])
    fps.update({"10.2": s + aa["top"], "10.4": s + aa["back"], "10.6": s + aa["lobe"]})

    vertices = np.concatenate(verts).astype(np.float32)
    triangles = np.concatenate(tris).astype(np.int32)
    part_ids = {k: np.concatenate(v) for k, v in parts.items()}
    part_ids.update(_lip_sets(model, grid, skin_v, n_grid, pocket_side, pocket_depth))
    part_ids["mouth_socket"] = np.arange(n_grid, n_grid + len(pocket_v))
    part_ids.update(sockets)
    e = lay.eye_centre_l
    pivots = {"head": lay.head_pivot, "jaw": lay.jaw_pivot, "eye_l": e, "eye_r": e * _MIRROR}
    log.debug(
        "built %s: %d vertices, %d triangles, spacing %.3f mm",
        name,
        len(vertices),
        len(triangles),
        spacing,
    )
    return Face(
        name=name,
        vertices=vertices,
        triangles=triangles,
        units="mm",
        parts=part_ids,
        feature_points=fps,
        pivots=pivots,
    )


def _has_duplicate_directed_edges(tris: np.ndarray) -> bool:
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]).astype(np.int64)
    key = e[:, 0] * (int(tris.max()) + 1) + e[:, 1]
    return len(np.unique(key)) != len(key)


def _lip_sets(
    model: SkinModel,
    grid: SkinGrid,
    skin_v: np.ndarray,
    n_grid: int,
    pocket_side: np.ndarray,
    pocket_depth: np.ndarray,
) -> dict[str, np.ndarray]:
    """Upper/lower lip vertex sets: vermilion rows on each side of the slit plus the inner lip."""
    jm = grid.row_mouth
    i_a, i_b = grid.mouth_cols
    d = skin_v - RAY_ORIGIN
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    px, py, _ = gnomonic(d)
    a = px / model.px_corner
    s = py - model.slit_py(px)
    vu, vl = model.lip_heights(a)
    inner = (grid.col > i_a) & (grid.col < i_b)
    upper_side = (grid.row > jm) | ((grid.row == jm) & (grid.side == 1))
    lower_side = ((grid.row < jm) & (grid.row > 0)) | ((grid.row == jm) & (grid.side == -1))
    up = np.nonzero(inner & upper_side & (s <= vu + 0.5))[0]
    lo = np.nonzero(inner & lower_side & (-s <= vl + 0.5))[0]
    pk_up = n_grid + np.nonzero((pocket_side > 0) & (pocket_depth <= 7.0))[0]
    pk_lo = n_grid + np.nonzero((pocket_side < 0) & (pocket_depth <= 7.0))[0]
    return {"lip_upper": np.concatenate([up, pk_up]), "lip_lower": np.concatenate([lo, pk_lo])}


# ---- colours for previews -----------------------------------------------------------------------------
def _conformation_from_name(name: str) -> Conformation | None:
    base, _, rest = name.partition(":")
    if base != "default":
        return None
    kw = {}
    for item in rest.split(",")[1:]:
        k, _, v = item.partition("=")
        if k not in Conformation.names():
            return None
        kw[k] = float(v)
    return Conformation(**kw)


def _brow_weight(face: Face) -> np.ndarray | None:
    """``(V,)`` 0–1 eyebrow weight (an arch through FPs 4.1/4.3/4.5 and their mirrors), or None."""
    if not all(k in face.feature_points for k in ("4.1", "4.3", "4.5", "4.2", "4.4", "4.6")):
        return None
    ids = face.part("skin")
    v = face.vertices[ids].astype(np.float64)
    out = np.zeros(face.n_vertices)
    for fps in (("4.1", "4.3", "4.5"), ("4.2", "4.4", "4.6")):
        p = np.array([face.fp_position(k) for k in fps])
        order = np.argsort(p[:, 0])
        p = p[order]
        x = v[:, 0]
        yb = np.polyval(np.polyfit(p[:, 0], p[:, 1], 2), x)
        zb = np.polyval(np.polyfit(p[:, 0], p[:, 2], 2), x)
        t = np.clip((x - p[0, 0]) / (p[-1, 0] - p[0, 0]), 0, 1)
        inner_first = order[0] == 0  # 4.1 (inner end) has the smallest x on the left side
        fat = 1.0 - 0.55 * (t if inner_first else 1 - t)
        half = 4.2 * fat
        band = np.clip((half - np.abs(v[:, 1] - yb + 1.0)) / 2.2 + 0.3, 0, 1)
        span = np.clip((np.minimum(x - p[0, 0], p[-1, 0] - x) + 3.0) / 4.0, 0, 1)
        near = np.abs(v[:, 2] - zb) < 12
        out[ids] = np.maximum(out[ids], 0.85 * band * span * near)
    return out


def _nostril_weight(face: Face) -> np.ndarray | None:
    conf = _conformation_from_name(face.name)
    if conf is None:
        return None
    ids = face.part("skin")
    d = face.vertices[ids].astype(np.float64) - RAY_ORIGIN
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    out = np.zeros(face.n_vertices)
    out[ids] = np.clip(SkinModel(Layout(conf)).nostrils(d) / 3.0, 0, 1)
    return out


def _lip_weight(face: Face) -> np.ndarray | None:
    """``(V,)`` 0–1 vermilion weight of the built-in head's skin (smooth, for colouring), or None."""
    conf = _conformation_from_name(face.name)
    if conf is None:
        return None
    model = SkinModel(Layout(conf))
    ids = face.part("skin")
    d = face.vertices[ids].astype(np.float64) - RAY_ORIGIN
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    px, py, fm = gnomonic(d)
    a = px / model.px_corner
    s = py - model.slit_py(px)
    vu, vl = model.lip_heights(a)
    inside = np.where(s >= 0, vu - s, vl + s)
    w = (
        np.clip(inside / 3.0 + 0.45, 0, 1)
        * np.clip((1.0 - np.abs(a)) / 0.08 + 0.5, 0, 1)
        * (fm > 0.5)
    )
    out = np.zeros(face.n_vertices)
    out[ids] = w
    out[face.part("mouth_socket")] = 0
    out[face.part("lip_upper")] = np.maximum(out[face.part("lip_upper")], 0)
    return out


def head_colors(face: Face) -> np.ndarray:
    """``(V, 3)`` RGB 0–1 colours for previews of the built-in head (skin, lips, eyes, teeth, tongue)."""
    skin_rgb, lip_rgb = np.array([0.87, 0.70, 0.60]), np.array([0.76, 0.42, 0.42])
    col = np.tile(skin_rgb, (face.n_vertices, 1))
    lip, brow = _lip_weight(face), _brow_weight(face)
    if lip is not None:
        col += lip[:, None] * (lip_rgb - skin_rgb)
    if brow is not None:
        col += brow[:, None] * (np.array([0.36, 0.25, 0.19]) - col)
    nostril = _nostril_weight(face)
    if nostril is not None:
        col *= 1 - 0.45 * nostril[:, None]
    for p, rgb in (
        ("mouth_socket", (0.45, 0.16, 0.18)),
        ("eye_socket_l", (0.86, 0.55, 0.55)),
        ("eye_socket_r", (0.86, 0.55, 0.55)),
        ("teeth_upper", (0.95, 0.93, 0.85)),
        ("teeth_lower", (0.95, 0.93, 0.85)),
        ("gums_upper", (0.80, 0.40, 0.42)),
        ("gums_lower", (0.80, 0.40, 0.42)),
        ("tongue", (0.80, 0.38, 0.40)),
    ):
        col[face.part(p)] = rgb
    for eye, fp in (("eye_l", "3.5"), ("eye_r", "3.6")):
        col[face.part(eye)] = (0.95, 0.94, 0.92)
        iris = face.parts.get("iris" + eye[3:])
        if iris is None or not len(iris):
            continue
        col[iris] = (0.30, 0.45, 0.62)
        pupil = face.vertices[iris] - face.vertices[face.feature_points[fp]]
        radius = np.linalg.norm(face.vertices[iris] - face.pivot(eye), axis=1).mean() * 0.475
        col[iris[np.linalg.norm(pupil, axis=1) < radius / 3 * 1.05]] = (0.05, 0.05, 0.07)
    return col
