"""``annotate_mesh``: a complete ``.face.json`` annotation for any head mesh, by fitting the template.

Steps (Kähler, Haber, Seidel 2002): weld the mesh and split it into connected pieces; find the head
and its axes and align the template to it (``orient``); warp the template onto it (``warp``); then
carry the template's parts, feature points and pivots over by closest point, with sanity checks.
What the mesh cannot carry (no back of the head, no mouth opening, no eyeballs) is left out and said.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from ...deform.mesh_graph import components, edge_graph
from ...deform.normals import vertex_normals
from ...errors import InputError
from ..face import FEATURE_POINT_IDS, UNIT_MM
from .detect import mouth_corners, profile_landmarks, sphere_centre
from .orient import Similarity, frame, place, umeyama
from .template import (
    INNER,
    OUTER,
    PIECE_PARTS,
    TEMPLATES,
    Template,
    ict_available,
)
from .warp import Target, fit, warp_points

#: A feature point farther than this (template mm) from every mesh vertex is left out (1.6x this on
#: the face, where a surface cannot be missing, only sunk into an eye or mouth opening).
FP_REACH_MM = 9.0
#: Asymmetry (mm) of a mirrored pair of feature points above which ``_mirror`` looks at it, and the
#: difference (mm) in how far the two landed from where they were looked for above which it redoes one.
MIRROR_MM, MIRROR_OFF_MM = 3.0, 1.5
#: Largest angle (degrees) between the alignment and the mesh's own axes that is taken as the
#: alignment's error, not the head's tilt (cranial points then take their direction in the axes).
UPRIGHT_DEG = 10.0
#: The jaw's corners (gonion), placed with the skull and the chin (``_skull_fit``, ``_face_fit``), not the
#: warp.
JAW_ANGLE = ("2.13", "2.14")
#: The chin's points below and beside the gnathion (the chin's bottom, its sides), placed with the
#: skull and moved as the mesh's chin is (``_skull_fit``), not slid along the smooth chin by the warp.
CHIN = ("2.1", "2.11", "2.12")
#: The eyeball (``_anchors``) whose centre sets each brow point's height (``_feature_points``).
BROW_EYE = {f"4.{i}": "eye_l" if i % 2 else "eye_r" for i in range(1, 7)}
#: How far (mm) up or down from its eye's height a brow point must lie to be moved there: ICT's
#: and MakeHuman's lie within 3.2, a short skull's slid 7-9.
BROW_SLIP_MM = 4.0
#: ``_face_fit``: landmarks it needs, and the largest scale (either way) it may have.
FACE_MIN_ANCHORS, FACE_MAX_SCALE = 6, 1.15
#: How far (mm) from the warped point a cranial feature point is looked for along its ray.
RADIAL_MM = 25.0
#: Neutral FAPU distances (mm, on a head scaled to the template) a human face has.
FAPU_RANGE_MM: dict[str, tuple[float, float]] = {
    "IRISD": (4.0, 25.0),
    "ES": (40.0, 90.0),
    "ENS": (15.0, 65.0),
    "MNS": (6.0, 45.0),
    "MW": (25.0, 85.0),
}
#: FAPU -> (fp_a, fp_b, axis), as ``mpeg4.fapu``.
_FAPU = {
    "IRISD": ("3.1", "3.3", 1),
    "ES": ("3.5", "3.6", 0),
    "ENS": ("3.5", "9.15", 1),
    "MNS": ("9.15", "2.2", 1),
    "MW": ("8.3", "8.4", 0),
}


#: Vertices of the matched piece above which triangle centroids are not added as surface samples.
DENSE = 30_000
#: Feature points animation cannot do without: the chin (the jaw's angle) and the FAPU's.
ESSENTIAL = frozenset({"2.1", "3.1", "3.3", "3.5", "3.6", "9.15", "2.2", "8.3", "8.4"})
#: A mesh vertex whose normal meets a skin point's template normal at a lower cosine is behind the
#: surface (an eye or mouth socket behind the lid or lip): only taken when nothing else is near.
#: Not higher: a coarse mesh's vertex where the lips meet faces forward, the template's lip
#: contact point down.
FACING_MIN = 0.0
FACING_NEAR = 1.5
#: ... or within this fraction of the mesh's median edge (a coarse mesh's fold lies farther away).
FACING_NEAR_EDGE = 0.35
#: Median distance (mm) from a mouth piece to the warped template's pieces under which the
#: template's part names label it.
PIECE_NAMES_MM = 2.5
#: Largest rotation (degrees) and shift (mm) of a piece's rigid fit that is trusted.
PIECE_MAX_DEG, PIECE_MAX_MM = 10.0, 5.0
#: Largest median gap (mm, over the mesh's vertex spacing) from a fitted piece to the mesh's.
PIECE_GAP_MM = 1.5
#: Ear pieces (``_fit_ears``): largest median gap (mm) from the warped template ear to the mesh's,
#: largest rotation (degrees) and shift (mm) of the fit from the warp.
EAR_GAP_MM, EAR_MAX_DEG, EAR_MAX_MM = 8.0, 30.0, 15.0
#: Ear feature points off the ear piece (where it joins the head) within this distance (template
#: mm) of a fitted ear move with it.
EAR_NEAR_MM = 25.0
_FAPU_CHECK = True  # tests and debugging may look at a failed fit
_FAPU_POINTS = {p for a, b, _ in _FAPU.values() for p in (a, b)}


def weld(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(rep, welded_triangles)``: ``rep (V,)`` maps every vertex to the lowest id at its position
    (vertices split at UV seams become one), ``welded_triangles`` uses those ids."""
    v = np.asarray(vertices, dtype=np.float64)
    tol = max(float(np.ptp(v, axis=0).max()), 1e-12) * 1e-7
    _, first, inverse = np.unique(
        np.round(v / tol).astype(np.int64), axis=0, return_index=True, return_inverse=True
    )
    rep = first[inverse.ravel()]
    return rep, rep[np.asarray(triangles, dtype=np.int64)]


def rim_vertices(n: int, triangles: np.ndarray) -> np.ndarray:
    """``(n,) bool``: vertices on an open boundary (an edge used by one triangle only)."""
    t = np.asarray(triangles, dtype=np.int64)
    e = np.sort(np.r_[t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]], axis=1)
    key = e[:, 0] * n + e[:, 1]
    uniq, count = np.unique(key, return_counts=True)
    once = uniq[count == 1]
    out = np.zeros(n, dtype=bool)
    out[once // n] = True
    out[once % n] = True
    return out


def ranges(ids: np.ndarray) -> list:
    """Sorted ids as a compact list of ``[first, last]`` runs and single ids (the annotation's form)."""
    ids = np.unique(np.asarray(ids, dtype=np.int64))
    if not len(ids):
        return []
    breaks = np.nonzero(np.diff(ids) != 1)[0]
    starts, ends = np.r_[ids[0], ids[breaks + 1]], np.r_[ids[breaks], ids[-1]]
    return [int(a) if a == b else [int(a), int(b)] for a, b in zip(starts, ends)]


def annotate_mesh(
    vertices: np.ndarray,
    triangles: np.ndarray,
    *,
    landmarks: dict | None = None,
    axes: tuple[str, str] | None = None,
    units: str | None = None,
    template: Template | str | None = None,
) -> dict:
    """The annotation (``loaders`` format plus an ``automatic`` report) for a head mesh.

    Args:
        vertices: ``(V, 3)`` in the file's units and axes; ``triangles``: ``(F, 3)``.
        landmarks: MPEG-4 feature point id -> ``[x, y, z]`` in mesh units (nose tip 9.3, eye corners
            3.7/3.12, mouth corners 8.3/8.4, chin 2.1, ...), to guide the fit.
        axes: ``(up, forward)`` when known; ``units``: when the file says (else from the head size).
        template: ``"default"`` (the built-in head), ``"ict"`` (the ICT FaceKit neutral), a
            ``Template``, or None / ``"auto"``: the one the mesh's head is closer to after the rigid
            alignment (ICT only when ``../shared/data`` has it).

    Raises ``InputError`` when no head can be fitted (too few vertices, a fit too poor to trust).
    """
    t0 = time.perf_counter()
    v = np.asarray(vertices, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.int64)
    if len(v) < 50 or len(tri) < 50 or not np.all(np.isfinite(v)):
        raise InputError("the mesh is too small (or has non-finite vertices) to be a head")
    rep, wtri = weld(v, tri)
    wtri = wtri[
        (wtri[:, 0] != wtri[:, 1]) & (wtri[:, 1] != wtri[:, 2]) & (wtri[:, 0] != wtri[:, 2])
    ]
    used = np.zeros(len(v), bool)
    used[wtri.ravel()] = True
    label = components(edge_graph(v, wtri))
    label[~used] = -1
    sizes = np.bincount(label[used])
    main_label = int(np.argmax(sizes))
    main = np.nonzero(label == main_label)[0]
    vn = vertex_normals(v, wtri)

    lm = {
        k: v[p] if isinstance(p, (int, np.integer)) else np.asarray(p, dtype=np.float64)
        for k, p in (landmarks or {}).items()
    }
    tpl, pl, scores = _choose(template, v[main], vn[main], axes, lm or None)
    sim = pl.similarity
    y = sim.apply(v)  # every vertex in the template frame (mm)
    yn = vn @ sim.rotation.T

    # The matched surface: the main piece and the pieces lying on the template's skin (separate
    # ears, a scalp), their vertices and triangle centroids.
    crop_full = np.zeros(len(v), bool)
    crop_full[main[pl.crop]] = True
    surface = _surface_pieces(y, yn, label, sizes, main_label, tpl)
    on_surface = np.isin(label, surface)
    main = np.nonzero(on_surface)[0]
    mtri = wtri[on_surface[wtri[:, 0]]]
    rim = rim_vertices(len(v), mtri)
    cent = y[mtri].mean(axis=1)
    fn = np.cross(y[mtri[:, 1]] - y[mtri[:, 0]], y[mtri[:, 2]] - y[mtri[:, 0]])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-12)
    head_v = crop_full | (on_surface & (label != main_label))
    # Coarse meshes add their triangle centroids as samples; dense ones have enough vertices.
    use = np.ones(len(mtri), bool) if len(main) < DENSE else np.zeros(len(mtri), bool)
    pts, nrm = np.r_[y[main], cent[use]], np.r_[yn[main], fn[use]]
    head = np.r_[head_v[main], head_v[mtri[use]].all(axis=1)]
    # Orient the mesh's normals like the template's (some files wind their triangles inwards).
    d, j = cKDTree(tpl.vertices[tpl.outer]).query(pts[head])
    close = d < np.quantile(d, 0.5)
    if np.median(np.einsum("ij,ij->i", nrm[head][close], tpl.normals[tpl.outer][j[close]])) < 0:
        nrm, yn = -nrm, -yn
    anchors, found, eyes = _anchors(tpl, lm, sim, y, mtri, label, sizes, main_label)
    # Skin behind an eyeball's equator is its socket: never matched, never a feature point.
    socket_v = np.zeros(len(v), bool)
    for centre, radius in eyes:
        rel = y - centre
        socket_v |= (np.linalg.norm(rel, axis=1) < 1.3 * radius) & (rel[:, 2] < 0.3 * radius)
    socket_v &= label == main_label
    excluded = np.r_[rim[main] | socket_v[main], (rim | socket_v)[mtri[use]].any(axis=1)]
    target = Target(points=pts, normals=nrm, rim=excluded)
    warped, fields = fit(tpl, target, anchors=anchors, crop=head)

    box = (
        (y[:, 1] > tpl.vertices[:, 1].min() - 20)
        & (np.abs(y[:, 0]) < 140)
        & (np.abs(y[:, 2]) < 200)
    )
    parts = _parts(y, label, main_label, sizes, warped, tpl, box)
    # The mesh's own axes, in the template frame: a head is modelled upright in them, and the
    # alignment's few degrees off them come from the head's shape (a longer skull), not a tilt.
    up, forward = axes or (pl.up, pl.forward)
    upright = sim.rotation @ frame(up, forward).T
    off_axis = _angle_deg(upright)
    if off_axis > UPRIGHT_DEG:
        upright = np.eye(3)
    ears = _fit_ears(y, label, surface, wtri, warped, tpl)
    face = _face_fit(anchors, found)
    # Upright heads: the skull and the jaw's corners placed in the mesh's own axes (the face fit
    # turns a few degrees with the face's proportions, e.g. a longer nose).
    skull = (
        _skull_fit(anchors, found, upright, tpl, y[parts["skin"]])
        if face is not None and off_axis <= UPRIGHT_DEG
        else None
    )
    # each side's eyeball centre, template's and mesh's, for the height of the brows above it
    eye_at = {
        k: (anchors[0][found.index(k)], anchors[1][found.index(k)])
        for k in ("eye_l", "eye_r")
        if anchors is not None and k in found and skull is not None
    }
    fps, left_out, approximate = _feature_points(
        y, yn, wtri, parts, warped, tpl, socket_v, rep, tri, upright, ears, face, skull, eye_at
    )
    warnings = _checks(y, fps, left_out, tpl)

    # Pivots: template pivots through the warp, back to mesh coordinates.
    names = [
        k
        for k in ("jaw", "head", "eye_l", "eye_r")
        if k in tpl.pivots and not (k in parts and k.startswith("eye"))
    ]
    piv = sim.inverse(warp_points(np.array([tpl.pivots[k] for k in names]), fields))
    mm_per_unit = sim.scale
    unit = units or min(UNIT_MM, key=lambda u: abs(np.log(UNIT_MM[u] / mm_per_unit)))
    fit_err = float(np.median(cKDTree(warped[tpl.outer]).query(pts[head & ~target.rim])[0]))
    report = {
        "template": tpl.name,
        "template_scores_mm": scores,
        "seconds": round(time.perf_counter() - t0, 2),
        "mm_per_unit_measured": round(mm_per_unit, 4),
        "tilt_deg": round(off_axis, 1),
        "alignment_score_mm": round(pl.score, 2),
        "landmarks": found,
        "fit_median_mm": round(fit_err, 2),
        "cropped_to_head": bool(pl.cropped or (~head_v[used]).any()),
        "left_out": left_out,
        "approximate_mm": approximate,
        "warnings": warnings,
    }
    if abs(np.log(UNIT_MM[unit] / mm_per_unit)) > np.log(1.5):
        warnings.append(
            f"the head measures {mm_per_unit:.3g} mm per unit; the nearest unit {unit!r} is "
            f"{UNIT_MM[unit] / mm_per_unit:.2f}x that (only sizes in mm are affected)"
        )
    if off_axis > 25:
        warnings.append(f"the head is tilted {off_axis:.0f} degrees from the {up} / {forward} axes")
    if fit_err > 6.0:
        raise InputError(
            f"no head found: the template fits the mesh only to a median {fit_err:.1f} mm; "
            "give --landmarks or write the annotation by hand"
        )
    fapu = _fapu_mm(y, fps)
    odd = {k: v for k, v in fapu.items() if not FAPU_RANGE_MM[k][0] <= v <= FAPU_RANGE_MM[k][1]}
    bad = {
        k: v
        for k, v in fapu.items()
        if not FAPU_RANGE_MM[k][0] / 1.5 <= v <= FAPU_RANGE_MM[k][1] * 1.5
    }
    warnings.extend(
        f"FAPU {k} measures {v:.1f} mm on a head scaled to the template; humans have "
        f"{FAPU_RANGE_MM[k][0]:g}-{FAPU_RANGE_MM[k][1]:g} mm"
        for k, v in odd.items()
        if k not in bad
    )
    missing = [k for k in _FAPU if k not in fapu]
    if (bad or missing) and _FAPU_CHECK:
        raise InputError(
            "the fitted feature points give implausible face proportions ("
            + ", ".join([f"{k} {v:.1f} mm" for k, v in bad.items()] + [f"no {k}" for k in missing])
            + "); give --landmarks or write the annotation by hand"
        )
    return {
        "units": unit,
        "axes": {"up": up, "forward": forward},
        "feature_points": dict(
            sorted(fps.items(), key=lambda kv: tuple(int(x) for x in kv[0].split(".")))
        ),
        "parts": {k: ranges(ids) for k, ids in parts.items()},
        "pivots": {k: [round(float(x), 6) for x in p] for k, p in zip(names, piv)},
        "automatic": report,
    }


def _choose(template: Template | str | None, v: np.ndarray, vn: np.ndarray, axes, lm):
    """``(template, placement, {name: alignment score mm})``: the given template, or (auto) the
    one whose rigid alignment to the head scores best."""
    if isinstance(template, Template):
        return template, place(v, vn, template, axes=axes, landmarks=lm), {}
    name = template or "auto"
    if name not in (*TEMPLATES, "auto"):
        raise InputError(
            f"unknown template {name!r}; use {', '.join(TEMPLATES)} or auto", where="template"
        )
    names = [name] if name != "auto" else ["default", *(["ict"] if ict_available() else [])]
    best = None
    scores = {}
    for n in names:
        tpl = TEMPLATES[n]()
        pl = place(
            v, vn, tpl, axes=axes or (best[1].up, best[1].forward) if best else axes, landmarks=lm
        )
        scores[n] = round(pl.score, 2)
        if best is None or pl.score < best[1].score:
            best = (tpl, pl)
    assert best is not None
    return best[0], best[1], scores


def _surface_pieces(y, yn, label, sizes, main_label, tpl: Template) -> list[int]:
    """The main piece and the other pieces that lie on the template's skin after the alignment
    (large enough, within 6 mm, facing the same way, not round like an eyeball)."""
    out = [main_label]
    tree = cKDTree(tpl.vertices[tpl.outer])
    for c in np.nonzero(sizes >= max(20, 0.01 * sizes[main_label]))[0]:
        if c == main_label:
            continue
        ids = np.nonzero(label == c)[0]
        d, j = tree.query(y[ids])
        if np.median(d) > 6.0:
            continue
        facing = np.abs(np.einsum("ij,ij->i", yn[ids], tpl.normals[tpl.outer][j]))
        centre = sphere_centre(y[ids])
        r = np.linalg.norm(y[ids] - centre, axis=1)
        if np.median(facing) > 0.5 and not r.std() < 0.15 * r.mean():
            out.append(int(c))
    return out


def _anchors(tpl: Template, lm: dict, sim, y, mtri, label, sizes, main_label):
    """Template points and where they belong on the mesh: the user's landmarks, else the midline
    profile landmarks and mouth corners (``detect``) and the centres of eyeball pieces; also the
    eyeballs found, as ``[(centre, radius)]``."""
    src, dst, found, eyes = [], [], [], []
    if lm:
        for k, p in lm.items():
            if k in tpl.feature_points:
                src.append(tpl.fp_position(k))
                dst.append(sim.apply(np.asarray(p, dtype=np.float64)[None])[0])
                found.append(k)
    else:
        mine = profile_landmarks(y, mtri, tpl.profile_heights)
        for name, p in mine.items():
            if name in tpl.profile:
                src.append(tpl.profile[name])
                dst.append(p)
                found.append(name)
        if "slit" in mine:
            half = abs(tpl.fp_position("8.3")[0])
            for k, p in mouth_corners(y, mtri, mine["slit"], half).items():
                if k in tpl.mouth_corners:
                    src.append(_corner_source(tpl, k, float(p[0])))
                    dst.append(p)
                    found.append(k)
        for eye in ("eye_l", "eye_r"):
            c = tpl.pivots[eye]
            best = None
            for comp in np.nonzero(sizes)[0]:
                if comp == main_label or sizes[comp] < 20:
                    continue
                ids = np.nonzero(label == comp)[0]
                centre = sphere_centre(y[ids])
                radius = np.linalg.norm(y[ids] - centre, axis=1)
                round_ = radius.std() < 0.15 * radius.mean() and 6.0 < radius.mean() < 20.0
                d = np.linalg.norm(centre - c)
                if round_ and d < 18.0 and (best is None or d < best[0]):
                    best = (d, centre, float(radius.mean()))
            if best is not None:
                src.append(c)
                dst.append(best[1])
                found.append(eye)
                eyes.append((best[1], best[2]))
                # The outer eye corner sits where it sits beside the template's eyeball, scaled by
                # the eyeballs' sizes, on the mesh's surface nearest that spot.
                corner = "3.7" if eye == "eye_l" else "3.12"
                t_radius = float(
                    np.linalg.norm(tpl.fp_position("3.5" if eye == "eye_l" else "3.6") - c)
                )
                guess = best[1] + (tpl.fp_position(corner) - c) * best[2] / max(t_radius, 1e-6)
                d_s, i_s = cKDTree(y[np.unique(mtri)]).query(guess)
                if d_s < 6.0:
                    src.append(tpl.fp_position(corner))
                    dst.append(y[np.unique(mtri)][i_s])
                    found.append(corner)
    if not src:
        return None, found, eyes
    return (np.array(src), np.array(dst)), found, eyes


def _corner_source(tpl: Template, key: str, mesh_x: float) -> np.ndarray:
    """The template point ``(3,)`` (mm) anchored at the mesh's detected mouth corner ``key``.

    The detector may stop short of a template's own corner ``key`` (a shallow slit: the built-in
    head's ends 7 mm inside its 8.3). Where the mesh's slit ends as early (``mesh_x``, template
    frame, at the template's detected end or inside), the two detections are matched; where it
    reaches as far out as the template's corner, the mesh's slit end is its corner; in between, the
    point between the two. So a mesh of another family (a sharp slit that runs to the corner) gets
    its corner where its slit ends, and a mesh like the template gets the template's offset."""
    found, own = tpl.mouth_corners[key], tpl.fp_position(key)
    span = abs(own[0]) - abs(found[0])
    if span <= 1.0:
        return found
    t = float(np.clip((abs(mesh_x) - abs(found[0])) / span, 0.0, 1.0))
    return found + t * (own - found)


def _parts(y, label, main_label, sizes, warped, tpl: Template, head_v) -> dict[str, np.ndarray]:
    """Parts of the mesh: ``skin``, the pieces (eyes, teeth, gums, tongue), ``mouth_socket``, ``other``
    (pieces that are not part of the head: clothing, a body's markers)."""
    tree = cKDTree(warped)
    d, j = tree.query(y)
    tlabel = tpl.label[j]
    parts: dict[str, list] = {"skin": [np.nonzero(label == main_label)[0]]}
    socket = np.zeros(len(tpl.vertices), bool)
    socket[tpl.mouth_socket] = True
    mouth_centre = (
        warped[tpl.mouth_socket].mean(axis=0)
        if len(tpl.mouth_socket)
        else warped[tpl.feature_points["2.2"]]
    )

    def inside_mouth(ids: np.ndarray) -> bool:
        """A separate piece behind the lips (ICT's upper teeth look like the socket's inside)."""
        return bool(np.linalg.norm(y[ids].mean(axis=0) - mouth_centre) < 35.0)

    interior: list[np.ndarray] = []
    for c in np.nonzero(sizes)[0]:
        if c == main_label:
            continue
        ids = np.nonzero(label == c)[0]
        lab, dist = tlabel[ids], d[ids]
        if np.median(dist) > 12.0 or not head_v[ids].any():
            parts.setdefault("other", []).append(ids)
            continue
        counts = np.bincount(lab, minlength=2 + len(PIECE_PARTS))
        top = int(np.argmax(counts))
        if top >= 2 and PIECE_PARTS[top - 2].startswith("eye"):
            parts.setdefault(PIECE_PARTS[top - 2], []).append(ids)
        elif (
            top >= 2
            or (top == INNER and socket[j[ids]].mean() < 0.5)
            or (top == INNER and inside_mouth(ids))
        ):
            interior.append(ids)
        elif top == INNER:
            parts.setdefault("mouth_socket", []).append(ids)
        elif top == OUTER and np.median(dist) < 6.0:
            parts["skin"].append(ids)  # a separate ear, a scalp
        else:
            parts.setdefault("other", []).append(ids)
    if interior:
        for k, v in _mouth_parts(y, interior, warped, tpl).items():
            parts.setdefault(k, []).extend(v)
    # The main piece's own mouth cavity (a mesh whose lips fold inwards into a socket).
    main = parts["skin"][0]
    inside = main[socket[j[main]] & (d[main] < 6.0)]
    if len(inside) >= 10:
        parts.setdefault("mouth_socket", []).append(inside)
    out = {k: np.unique(np.concatenate(v)) for k, v in parts.items()}
    if "mouth_socket" in out:
        out["skin"] = (
            np.setdiff1d(out["skin"], out["mouth_socket"]) if "mouth_socket" in out else out["skin"]
        )
    return out


def _mouth_parts(
    y: np.ndarray, interior: list[np.ndarray], warped: np.ndarray, tpl: Template
) -> dict[str, list[np.ndarray]]:
    """Part name -> vertex ids of the mouth's pieces (``interior``: each piece's ids; ``y`` and
    ``warped`` in the template frame, mm).

    What animation needs is which pieces ride the jaw: a piece above the mouth slit stays with the
    head (upper teeth, upper gums), one below rides the jaw (lower teeth, lower gums, tongue); a
    piece across it (gums and tongue in one) is cut at the slit. The template's nearest part names
    teeth apart from gums and tongue. Where the template's pieces lie on the mesh's (a head of the
    template's family: over all the mouth's pieces, not one tooth that happens to lie near one of
    the template's), their names say which jaw a piece is on (upper incisors reach below the slit)
    and whether it is one of the template's pieces; elsewhere only the slit and the teeth are
    trusted."""
    slit_y = float(warped[tpl.feature_points["2.2"], 1])
    mouth = np.nonzero(tpl.label >= 2 + PIECE_PARTS.index("teeth_upper"))[0]
    tree = cKDTree(warped[mouth])
    d_all, k_all = tree.query(y[np.concatenate(interior)])
    family = bool(np.median(d_all) < PIECE_NAMES_MM)
    out: dict[str, list[np.ndarray]] = {}
    at = 0
    for ids in interior:
        d_mouth, k = d_all[at : at + len(ids)], k_all[at : at + len(ids)]
        at += len(ids)
        name = np.array([PIECE_PARTS[s - 2] for s in tpl.label[mouth[k]]])
        teeth = np.char.startswith(name, "teeth")
        above = y[ids, 1] > slit_y
        close = family and np.median(d_mouth) < PIECE_NAMES_MM
        upper = np.char.endswith(name, "_upper").mean()
        if close and (upper > 0.7 or upper < 0.3):
            above[:] = upper > 0.5
        elif close and teeth.mean() > 0.5:
            # a tooth is never cut at the slit (upper incisors reach below it): the whole piece
            # goes with the jaw the template's names mostly say, on a tie the one it reaches into
            # farther
            reach_up = float(y[ids, 1].max()) - slit_y > slit_y - float(y[ids, 1].min())
            above[:] = upper > 0.5 or (upper == 0.5 and reach_up)
        elif above.mean() > 0.8 or above.mean() < 0.2:
            above[:] = above.mean() > 0.5
        if teeth.mean() > 0.8 or teeth.mean() < 0.2 or above.all() or not above.any():
            teeth[:] = teeth.mean() > 0.5
        label_of = np.where(
            above,
            np.where(teeth, "teeth_upper", "gums_upper"),
            np.where(teeth, "teeth_lower", np.where(name == "tongue", "tongue", "gums_lower")),
        )
        names, counts = np.unique(name, return_counts=True)
        if close and counts.max() >= 0.6 * len(name):  # one of the template's pieces
            label_of[:] = names[np.argmax(counts)]
        for s in np.unique(label_of):
            out.setdefault(str(s), []).append(ids[label_of == s])
    return out


def _feature_points(
    y,
    yn,
    wtri,
    parts,
    warped,
    tpl: Template,
    socket_v,
    rep,
    tri,
    upright: np.ndarray,
    ears=(),
    face: tuple[Similarity, Similarity, np.ndarray] | None = None,
    skull: tuple[Similarity, float, np.ndarray | None] | None = None,
    eye_at: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
) -> tuple[dict[str, int], dict[str, str], dict]:
    """MPEG-4 id -> mesh vertex id, the ids left out with the reason, and the essential ones placed
    on the nearest surface though it is farther than the reach (id -> mm).

    Each feature point goes to the nearest mesh vertex of its part; among coincident vertices (lips
    that touch but are not joined) the one whose neighbourhood lies on the template point's side.
    Two feature points never share a vertex: the farther one takes its next-nearest free vertex.
    A point of the template's outer skin avoids mesh vertices facing another way (an eye or mouth
    socket just behind the lid or lip). ``rep``: the welded id of every vertex (``weld``); ``tri``:
    the mesh's own triangles, which tell coincident vertices apart.
    """
    t_normals = vertex_normals(warped, tpl.triangles)
    ring = _ring(y, wtri)
    own_ring = _ring(y, tri)
    coincident: dict[int, list[int]] = {}
    for j in np.nonzero(rep != np.arange(len(rep)))[0]:
        coincident.setdefault(int(rep[j]), [int(rep[j])]).append(int(j))
    t_ring = np.zeros((len(warped), 3))
    t_cnt = np.zeros(len(warped))
    tc = warped[tpl.triangles].mean(axis=1)
    for k in range(3):
        np.add.at(t_ring, tpl.triangles[:, k], tc)
        np.add.at(t_cnt, tpl.triangles[:, k], 1)
    t_ring = t_ring / np.maximum(t_cnt, 1)[:, None] - warped

    edges = np.linalg.norm(y[wtri] - y[np.roll(wtri, 1, axis=1)], axis=2)
    near_fold = max(FACING_NEAR, FACING_NEAR_EDGE * float(np.median(edges)))
    skin_ids = np.r_[parts["skin"], parts.get("mouth_socket", np.zeros(0, np.int64))]
    trees = {"skin": (cKDTree(y[skin_ids]), skin_ids)}
    taken: set[int] = set()
    approximate: dict[str, float] = {}
    fps: dict[str, int] = {}
    left_out: dict[str, str] = {}
    wanted = []
    aim: dict[str, np.ndarray] = {}  # where each point was looked for (template frame, mm)
    piece_fit: dict = {}
    for fp in FEATURE_POINT_IDS:
        if fp not in tpl.feature_points:
            continue
        part = tpl.part_of(fp)
        key = part if part in parts else "skin"
        if part != key and part not in ("eye_l", "eye_r"):
            left_out[fp] = f"the mesh has no {part.replace('_', ' ')}"
            continue
        if key not in trees:
            # A tooth's point is looked for on its jaw's teeth and gums: a mesh whose teeth and gums
            # are one piece is split by the template's nearest part names, which across families
            # may call its incisors gums.
            jaw = key.split("_")[-1]
            near = [k for k in (f"teeth_{jaw}", f"gums_{jaw}") if k in parts]
            ids = (
                np.unique(np.concatenate([parts[k] for k in near]))
                if key.startswith("teeth")
                else parts[key]
            )
            trees[key] = (cKDTree(y[ids]), ids)
        p = warped[tpl.feature_points[fp]]
        if key == "skin" and fp in tpl.cranial:
            c0 = tpl.skull_centre
            if skull is not None:
                # the ray keeps its height and depth and widens as the mesh's skull does
                rel = (tpl.fp_position(fp) - c0) * [skull[1], 1.0, 1.0]
                centre, t = skull[0].apply(np.array([c0, c0 + rel]))
            elif face is not None:
                centre, t = face[0].apply(np.array([c0, tpl.fp_position(fp)]))
            else:
                centre, t = c0, c0 + upright @ (tpl.fp_position(fp) - c0)
            p = _radial(p, t, centre, y, *trees["skin"])
        if fp in JAW_ANGLE and skull is not None and skull[2] is not None:
            # the template's corner placed with the skull (unscaled: the face's scale comes from
            # its height, not its depth), as far up or down as the mesh's chin is; then sideways
            # from the midline onto the mesh's jaw
            p = skull[0].apply(tpl.fp_position(fp)[None])[0] + [0.0, skull[2][1], 0.0]
            p = _radial(p, p, p * [0.0, 1.0, 1.0], y, *trees["skin"])
        elif fp in CHIN and skull is not None and skull[2] is not None:
            # the template's point placed with the skull, moved as far as the mesh's gnathion lies
            # from the placed template's (a longer chin reaches lower); the nearest surface to it
            p = skull[0].apply(tpl.fp_position(fp)[None])[0] + skull[2]
        elif fp in JAW_ANGLE and face is not None:
            # The smooth jaw lets the warp slide its corner along it: the template's corner as the
            # face's landmarks place it (with their scale), at the height the chin says, is nearer.
            p = face[1].apply(tpl.fp_position(fp)[None])[0] + face[2]
            # ... and as wide as the mesh's jaw is there: sideways from the midline onto the mesh
            # (the nearest surface to a point inside a wider jaw lies lower, under the corner)
            p = _radial(p, p, p * [0.0, 1.0, 1.0], y, *trees["skin"])
        ear = _ear_of(fp, tpl, ears)
        if key == "skin" and ear is not None:
            ids_t, e_sim, e_ids, joint = ear
            if tpl.feature_points[fp] in ids_t:  # on the ear itself: on the mesh's ear
                p = e_sim.apply(tpl.fp_position(fp)[None])[0]
                trees[fp] = (cKDTree(y[e_ids]), e_ids)
                key = fp
            else:
                p = joint.apply(tpl.fp_position(fp)[None])[0]
        if eye_at and BROW_EYE.get(fp) in eye_at:
            # A short skull's alignment slides the brows up the forehead (7-9 mm): where the warp's
            # point lies farther than BROW_SLIP_MM from the template's height above its eyeball's
            # centre (in the mesh's axes, from the mesh's eyeball centre), it is moved to that
            # height, keeping its place across and in depth. Nearer, the warp's point is kept
            # (moving those few mm flips more triangles at full-strength expressions).
            src_e, dst_e = eye_at[BROW_EYE[fp]]
            up = upright[:, 1]
            rise = float(up @ (dst_e + upright @ (tpl.fp_position(fp) - src_e) - p))
            if abs(rise) > BROW_SLIP_MM:
                p = p + up * rise
        if key != "skin" and key == part:
            if key not in piece_fit:
                piece_fit[key] = _fit_piece_from(warped, tpl, key, y[parts[key]])
            # from the start that fits the piece better; where that leaves the point beyond reach
            # of the mesh's piece (a piece of another family, partly named otherwise), the other
            cands = [
                sim.apply(start[tpl.feature_points[fp]][None])[0] for start, sim in piece_fit[key]
            ]
            gaps = [float(trees[key][0].query(c)[0]) for c in cands]
            p = cands[0] if gaps[0] <= FP_REACH_MM or gaps[1] >= gaps[0] else cands[1]
        d, i = trees[key][0].query(p, k=min(16, len(trees[key][1])))
        wanted.append((float(np.atleast_1d(d)[0]), fp, key, np.atleast_1d(d), np.atleast_1d(i)))
        aim[fp] = p
    for d0, fp, key, d, i in sorted(wanted):
        reach = FP_REACH_MM * (
            2.0 if key != tpl.part_of(fp) else 1.0 if fp.split(".")[0] in ("7", "10", "11") else 1.6
        )
        ids = trees[key][1][i]
        if d0 > reach and fp in ESSENTIAL and d0 < 2.5 * reach:
            reach = d0 + 1.0  # the jaw and the FAPU need it: the nearest surface will do
            approximate[fp] = round(d0, 1)
        elif d0 > reach:
            left_out[fp] = (
                f"no surface within {reach:.0f} mm of where it belongs (the mesh ends there)"
            )
            continue
        tr = t_ring[tpl.feature_points[fp]]
        cost = d + 2.0 * np.linalg.norm(ring[ids] - tr, axis=1) * (d < d0 + 0.5)
        cost[d >= d0 + 0.5] += 1e3
        cost[socket_v[ids] & (d > near_fold)] += 2e3  # an eye socket, unless right at the point
        vid = tpl.feature_points[fp]
        if tpl.label[vid] == OUTER:
            facing = yn[ids] @ t_normals[vid]
            # behind the surface: only if nothing else is near (a vertex within FACING_NEAR of the
            # point is where the surface folds, e.g. a coarse mesh's lips meeting: taken)
            cost[(facing < FACING_MIN) & (d > near_fold)] += 2e3
        free = [
            j
            for j in np.argsort(cost)
            if d[j] <= reach
            and any(m not in taken for m in coincident.get(int(ids[j]), [int(ids[j])]))
        ]
        if not free:
            left_out[fp] = "no free vertex near it (the mesh is too coarse there)"
            continue
        group = [
            m for m in coincident.get(int(ids[free[0]]), [int(ids[free[0]])]) if m not in taken
        ]
        fps[fp] = group[int(np.argmin(np.linalg.norm(own_ring[group] - tr, axis=1)))]
        taken.add(fps[fp])
    _mirror(y, fps, aim, tpl, trees["skin"], taken, coincident)
    # Pupils: the front pole of each eyeball piece (a neutral head looks straight ahead, +z).
    for eye, fp in (("eye_l", "3.5"), ("eye_r", "3.6")):
        ids = parts.get(eye)
        if ids is not None and len(ids) >= 10:
            vid = int(ids[np.argmax(y[ids, 2])])
            if vid not in taken:
                taken.discard(fps.get(fp, -1))
                fps[fp] = vid
                taken.add(vid)
    return fps, left_out, approximate


def _face_fit(
    anchors: tuple[np.ndarray, np.ndarray] | None, found: list[str]
) -> tuple[Similarity, Similarity, np.ndarray] | None:
    """``(rigid, similarity, jaw shift)`` (template frame) taking the template's landmarks onto the
    mesh's (``anchors``: ``(src, dst)``, named by ``found``), when there are ``FACE_MIN_ANCHORS``
    besides the chin and they stay within ``UPRIGHT_DEG`` and ``FACE_MAX_SCALE`` of the alignment;
    else None.

    The alignment fits the whole head, so a longer or broader skull turns and shrinks the face by
    a few degrees and per cent in it. The cranial points are placed by rays from the skull's
    centre as the face implies it (where the template's would be behind the mesh's face, turned
    and shifted with it but not scaled: a smaller face is not a smaller skull); the jaw's corners
    where the face (scaled) puts them, moved up or down (``(3,)``, mm) as far as the mesh's chin
    (the gnathion) lies above or below where the face puts the template's. The chin is left out of
    the fit itself: its length varies apart from the eyes, nose and mouth. (Used for heads tilted
    beyond ``UPRIGHT_DEG`` in their own axes; upright ones use ``_skull_fit``.)"""
    if anchors is None:
        return None
    chin = np.array([k == "gnathion" for k in found], bool)
    src, dst = anchors[0][~chin], anchors[1][~chin]
    if len(src) < FACE_MIN_ANCHORS:
        return None
    fit = umeyama(src, dst)
    rigid = umeyama(src, dst, scale=1.0)
    turn = max(_angle_deg(fit.rotation), _angle_deg(rigid.rotation))
    if turn > UPRIGHT_DEG or abs(np.log(fit.scale)) > np.log(FACE_MAX_SCALE):
        return None
    shift = np.zeros(3)
    if chin.any():
        g = int(np.argmax(chin))
        shift[1] = anchors[1][g][1] - fit.apply(anchors[0][g][None])[0][1]
    return rigid, fit, shift


def _skull_fit(
    anchors: tuple[np.ndarray, np.ndarray],
    found: list[str],
    upright: np.ndarray,
    tpl: Template,
    skin: np.ndarray,
) -> tuple[Similarity, float, np.ndarray | None]:
    """``(placement, width ratio, chin shift)`` of the template's skull on the mesh (template
    frame, mm; ``skin``: the mesh's skin points ``(N, 3)`` in it).

    The placement is rigid: turned as the mesh's own axes say (``upright``: heads are modelled
    upright in them, while a fit of the face's landmarks turns a few degrees with the face's
    proportions), shifted as the upper face's landmarks (those above the template's nose tip:
    eyes, nasion; the lower face's heights vary with its length) say on average. The width ratio
    is the mesh's skull breadth over the template's (``_skull_breadth``, clipped to 0.8-1.25); the
    chin shift ``(3,)`` (mm, None without a detected chin) the mesh's gnathion less the placed
    template's."""
    src, dst = anchors
    upper = src[:, 1] > tpl.profile["tip"][1] if "tip" in tpl.profile else np.ones(len(src), bool)
    if not upper.any():
        upper[:] = True
    place_ = Similarity(1.0, upright, np.mean(dst[upper] - src[upper] @ upright.T, axis=0))
    chin = None
    if "gnathion" in found:
        g = found.index("gnathion")
        chin = dst[g] - place_.apply(src[g][None])[0]
    c0 = tpl.skull_centre
    ratio = _skull_breadth(place_.inverse(skin), c0) / _skull_breadth(tpl.vertices[tpl.outer], c0)
    return place_, float(np.clip(ratio, 0.8, 1.25)) if np.isfinite(ratio) else 1.0, chin


def _skull_breadth(p: np.ndarray, centre: np.ndarray) -> float:
    """Half the x-extent (mm) of skin points ``p (N, 3)`` in the band from the height of the skull's
    ``centre`` to 40 mm above it (above the ears), within 30 mm of its depth; NaN when the band
    is nearly empty (a face mask)."""
    rel = p - centre
    band = (rel[:, 1] > 0) & (rel[:, 1] < 40.0) & (np.abs(rel[:, 2]) < 30.0)
    return float(np.ptp(rel[band, 0]) / 2) if band.sum() > 10 else float("nan")


def _ear_of(fp: str, tpl: Template, ears) -> tuple | None:
    """The fitted ear (``_fit_ears``) that carries ear feature point ``fp`` (MPEG-4 group 10): the
    one it lies on, or the nearest within ``EAR_NEAR_MM``; None when there is none."""
    if not fp.startswith("10.") or not ears:
        return None
    p = tpl.fp_position(fp)
    d = [float(np.min(np.linalg.norm(tpl.vertices[e[0]] - p, axis=1))) for e in ears]
    k = int(np.argmin(d))
    return ears[k] if d[k] < EAR_NEAR_MM else None


def _mirror_pairs(tpl: Template) -> list[tuple[str, str]]:
    """``(left, right)`` skin feature points of the template that are mirror images (within 1.5 mm)."""
    skin = {k: tpl.fp_position(k) for k in tpl.feature_points if tpl.part_of(k) == "skin"}
    right = [k for k, p in skin.items() if p[0] < -1.0]
    out = []
    for a, p in skin.items():
        if p[0] > 1.0 and right:
            b = min(right, key=lambda k: float(np.linalg.norm(skin[k] - p * [-1, 1, 1])))
            if np.linalg.norm(skin[b] - p * [-1, 1, 1]) < 1.5:
                out.append((a, b))
    return out


def _mirror(
    y: np.ndarray,
    fps: dict[str, int],
    aim: dict[str, np.ndarray],
    tpl: Template,
    tree: tuple[cKDTree, np.ndarray],
    taken: set[int],
    coincident: dict[int, list[int]],
) -> None:
    """Redo (in place) a skin point that is not the mirror image of its pair's on a mesh that is
    symmetric there: the one that landed farther from where it was looked for (``aim``; pushed off
    by a neighbour that took its vertex, or snapped across a coarse mesh's edge) moves to the free
    vertex nearest its partner's mirror image, when that vertex lies within half the asymmetry of
    it (the mesh has the mirrored surface there) and was near enough to be looked at."""
    mid = [y[v, 0] for k, v in fps.items() if abs(tpl.fp_position(k)[0]) < 1.0]
    if not mid:
        return
    cx = float(np.median(mid))
    flip = np.array([-1.0, 1.0, 1.0])
    for a, b in _mirror_pairs(tpl):
        if a not in fps or b not in fps:
            continue
        pa, pb = y[fps[a]] - [cx, 0, 0], y[fps[b]] - [cx, 0, 0]
        asym = float(np.linalg.norm(pa * flip - pb))
        if asym < MIRROR_MM:
            continue
        off_a = float(np.linalg.norm(y[fps[a]] - aim[a]))
        off_b = float(np.linalg.norm(y[fps[b]] - aim[b]))
        if abs(off_a - off_b) < MIRROR_OFF_MM:
            continue  # both where the warp put them: the face itself is not symmetric there
        bad, good = (a, b) if off_a > off_b else (b, a)
        want = (y[fps[good]] - [cx, 0, 0]) * flip + [cx, 0, 0]
        d, i = tree[0].query(want, k=8)
        for dist, j in zip(np.atleast_1d(d), np.atleast_1d(i)):
            vid = int(tree[1][j])
            group = [m for m in coincident.get(vid, [vid]) if m not in taken]
            if dist > asym / 2 or np.linalg.norm(y[vid] - aim[bad]) > FP_REACH_MM:
                break
            if group:
                taken.discard(fps[bad])
                fps[bad] = group[0]
                taken.add(group[0])
                break


def _radial(
    p: np.ndarray, t: np.ndarray, centre: np.ndarray, y: np.ndarray, tree: cKDTree, ids: np.ndarray
) -> np.ndarray:
    """Where the ray from the template's skull ``centre`` through its feature point ``t`` meets
    the mesh (``y``: template frame, mm; ``tree`` over ``y[ids]``), near the warped point ``p``
    (all ``(3,)``): on the smooth skull the warp can slide the surface along itself, the similarity
    alignment of the whole head cannot. ``p`` itself when no mesh vertex lies near the ray."""
    near = ids[tree.query_ball_point(p, RADIAL_MM)]
    d = (t - centre) / max(float(np.linalg.norm(t - centre)), 1e-9)
    rel = y[near] - centre
    along = rel @ d
    tang = np.linalg.norm(rel - along[:, None] * d, axis=1)
    ok = (along > 0) & (tang < RADIAL_MM / 2)
    if not ok.any():
        return p
    best = np.argsort(np.where(ok, tang, np.inf))[: min(4, int(ok.sum()))]
    return centre + d * float(np.mean(along[best]))


def _angle_deg(rotation: np.ndarray) -> float:
    """Angle (degrees) of a ``(3, 3)`` rotation."""
    return float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1) / 2, -1.0, 1.0))))


def _ring(y: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``(V, 3)``: mean centroid of each vertex's triangles minus the vertex (0 for unused ones): which
    side of the vertex its surface lies on."""
    ring = np.zeros_like(y)
    cnt = np.zeros(len(y))
    cent = y[triangles].mean(axis=1)
    for k in range(3):
        np.add.at(ring, triangles[:, k], cent)
        np.add.at(cnt, triangles[:, k], 1)
    return ring / np.maximum(cnt, 1)[:, None] - y * (cnt > 0)[:, None]


def _fit_piece_from(
    warped: np.ndarray, tpl: Template, key: str, dst: np.ndarray
) -> list[tuple[np.ndarray, Similarity]]:
    """``[(start, fit)]``: the template piece ``key`` fitted rigidly onto the mesh's ``dst (M, 3)``
    from the warped template and from the template as aligned (``start``: the template's vertices
    it starts from, ``(N, 3)``), the one that ends nearer the mesh's piece (median both ways)
    first. The warp
    fits the skin; inside the mouth its field only extends the lips' displacement, which on a
    coarse mesh's chordal lips can push the teeth and tongue off by several mm."""
    tree = cKDTree(dst)
    sel = tpl.label == 2 + PIECE_PARTS.index(key)
    fits = []
    for start in (warped, tpl.vertices):
        sim = _fit_piece(start[sel], dst, tree)
        moved = sim.apply(start[sel])
        gap = float(np.median(tree.query(moved)[0]) + np.median(cKDTree(moved).query(dst)[0]))
        fits.append((gap, start, sim))
    fits.sort(key=lambda f: f[0])
    return [(start, sim) for _, start, sim in fits]


def _fit_piece(src: np.ndarray, dst: np.ndarray, tree: cKDTree, iterations: int = 12) -> Similarity:
    """Rigid fit (rotation, translation, scale within 0.8-1.25) of a template piece ``src (N, 3)``
    (warped teeth, tongue) onto the mesh's piece ``dst (M, 3)``: trimmed ICP both ways. The warp
    fits the skin; the pieces inside follow it only smoothly, so their points are placed by this."""
    if len(src) < 10 or len(dst) < 10:
        return Similarity(1.0, np.eye(3), np.zeros(3))
    sim = _icp_both_ways(src, dst, tree, iterations, (0.8, 1.25))
    # A piece of another shape (a whole dental arch against the template's) can slide along itself:
    # such a fit is not trusted.
    angle = np.degrees(np.arccos(np.clip((np.trace(sim.rotation) - 1) / 2, -1.0, 1.0)))
    moved = np.linalg.norm(sim.apply(src).mean(axis=0) - src.mean(axis=0))
    # Nor is one that leaves the piece off the mesh's (the labelled piece is another shape, or
    # only part of one): the median gap is set against the mesh's own vertex spacing.
    gap = float(np.median(tree.query(sim.apply(src))[0]))
    spacing = float(np.median(tree.query(dst, k=2)[0][:, 1]))
    if angle > PIECE_MAX_DEG or moved > PIECE_MAX_MM or gap > PIECE_GAP_MM + spacing:
        return _front_shift(src, dst, tree)
    return sim


def _icp_both_ways(
    src: np.ndarray,
    dst: np.ndarray,
    tree: cKDTree,
    iterations: int,
    scales: tuple[float, float],
    start: Similarity | None = None,
    rigid: bool = False,
) -> Similarity:
    """Similarity taking ``src (N, 3)`` onto ``dst (M, 3)`` (``tree`` over ``dst``): trimmed ICP with
    pairs both ways (each side's nearest 80 %), stopping before a scale outside ``scales``;
    ``rigid``: keeping the scale of ``start``."""
    sim = start or Similarity(1.0, np.eye(3), np.zeros(3))
    for _ in range(iterations):
        cur = sim.apply(src)
        d, j = tree.query(cur)
        keep = d <= np.quantile(d, 0.8)
        d2, i2 = cKDTree(cur).query(dst)
        keep2 = d2 <= np.quantile(d2, 0.8)
        new = umeyama(
            np.r_[src[keep], src[i2[keep2]]],
            np.r_[dst[j[keep]], dst[keep2]],
            scale=sim.scale if rigid else None,
        )
        if not scales[0] <= new.scale <= scales[1]:
            break
        sim = new
    return sim


def _moments(v: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(centroid (3,), variances (3,) ascending, axes (3, 3) as columns)`` of the surface
    ``tri`` over ``v``, weighted by triangle area (so not by how finely it is sampled)."""
    a, b, c = v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]
    w = np.linalg.norm(np.cross(b - a, c - a), axis=1) / 2
    w = w / max(float(w.sum()), 1e-12)
    cent = (a + b + c) / 3
    m = w @ cent
    d = cent - m
    cov = (d * w[:, None]).T @ d
    evals, evecs = np.linalg.eigh(cov)
    return m, evals, evecs


def _fit_ears(
    y: np.ndarray,
    label: np.ndarray,
    surface: list[int],
    wtri: np.ndarray,
    warped: np.ndarray,
    tpl: Template,
) -> list[tuple[np.ndarray, Similarity, np.ndarray, Similarity]]:
    """``[(template piece ids, fit, mesh piece ids, joint)]``: each of the template's separate skin pieces
    (the built-in head's ears) fitted onto the mesh's separate piece where it has one.

    The warp matches a thin, folded ear by closest points, so on a head of other proportions it
    slides along the rim (by 5-8 mm; ICP from there stays stuck too). Where both ears are whole
    pieces, their area-weighted centres and principal axes say where the ear is, how it is turned
    (the axis signs nearest the warp's) and its size (the long axis); a rigid ICP at that size
    refines it (``joint``: the same at the warp's scale, for the points where the ear joins the
    head). Trusted for the mesh piece the warped ear lies on (median gap under
    ``EAR_GAP_MM``, size within 0.6-1.6x), within ``EAR_MAX_DEG`` and ``EAR_MAX_MM`` of the warp."""
    out: list[tuple[np.ndarray, Similarity, np.ndarray, Similarity]] = []
    others = [c for c in surface if c != surface[0]]
    if not tpl.skin_pieces or not others:
        return out
    pieces = {c: np.nonzero(label == c)[0] for c in others}
    t_in = np.zeros(len(tpl.vertices), bool)
    for ids_t in tpl.skin_pieces:
        src = warped[ids_t]
        centre = src.mean(axis=0)
        best = None
        for c, ids in pieces.items():
            if np.linalg.norm(y[ids].mean(axis=0) - centre) > 40.0:
                continue
            gap = float(np.median(cKDTree(y[ids]).query(src)[0]))
            if best is None or gap < best[0]:
                best = (gap, c, ids)
        if best is None or best[0] > EAR_GAP_MM:
            continue
        _, c, ids = best
        mtri = wtri[(label[wtri] == c).all(axis=1)]
        t_in[:] = False
        t_in[ids_t] = True
        ttri = tpl.triangles[t_in[tpl.triangles].all(axis=1)]
        if len(mtri) < 20 or len(ttri) < 20:
            continue
        m_c, m_var, m_ax = _moments(y, mtri)
        t_c, t_var, t_ax = _moments(tpl.vertices, ttri)
        size = float(np.sqrt(m_var[-1] / max(t_var[-1], 1e-12)))
        if not 0.6 <= size <= 1.6:
            continue
        warp_fit = umeyama(tpl.vertices[ids_t], src)
        rot = None
        for signs in ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1)):
            r = m_ax @ np.diag(signs) @ t_ax.T
            if np.linalg.det(r) < 0:
                r = m_ax @ np.diag([-x for x in signs]) @ t_ax.T
            if rot is None or np.trace(r @ warp_fit.rotation.T) > np.trace(
                rot @ warp_fit.rotation.T
            ):
                rot = r
        assert rot is not None
        start = Similarity(size, rot, m_c - size * rot @ t_c)
        tree = cKDTree(y[ids])
        sim = _icp_both_ways(tpl.vertices[ids_t], y[ids], tree, 10, (0.6, 1.6), start, rigid=True)
        shift = float(np.linalg.norm(sim.apply(tpl.vertices[ids_t]).mean(axis=0) - centre))
        if _angle_deg(sim.rotation @ warp_fit.rotation.T) > EAR_MAX_DEG or shift > EAR_MAX_MM:
            continue
        # Where it joins the head scales with the head, not the ear: the fit's place and turn at
        # the warp's scale, about the ear's centre.
        joint = Similarity(
            warp_fit.scale,
            sim.rotation,
            sim.apply(t_c[None])[0] - warp_fit.scale * sim.rotation @ t_c,
        )
        out.append((ids_t, sim, ids, joint))
    return out


def _front_shift(src: np.ndarray, dst: np.ndarray, tree: cKDTree) -> Similarity:
    """The shift that puts a template piece's front at the midline (its most forward point within
    3 mm of x = 0, +z forward; template frame, mm) on the mesh piece's: where a rigid fit slides
    (pieces of different shapes), the front of the incisors or tongue is still where both agree.
    Taken only when the fronts lie within 10 mm in depth and it brings the piece closer to the
    mesh's both ways (median distance), else no shift."""
    none = Similarity(1.0, np.eye(3), np.zeros(3))
    mid_s, mid_d = np.abs(src[:, 0]) < 3.0, np.abs(dst[:, 0]) < 3.0
    if not mid_s.any() or not mid_d.any():
        return none
    shift = dst[mid_d][np.argmax(dst[mid_d, 2])] - src[mid_s][np.argmax(src[mid_s, 2])]
    if abs(shift[2]) > 2 * PIECE_MAX_MM:
        return none  # the mesh's piece has no front there (only back teeth were named so)

    def gap(t: np.ndarray) -> float:
        return float(np.median(tree.query(src + t)[0]) + np.median(cKDTree(src + t).query(dst)[0]))

    if gap(shift) >= gap(np.zeros(3)):
        return none
    return Similarity(1.0, np.eye(3), shift)


def _checks(y, fps: dict[str, int], left_out: dict, tpl: Template) -> list[str]:
    """Sanity checks: sides and mirrored pairs; points on the wrong side are dropped."""
    warnings = []
    centre = np.median(
        [y[v, 0] for k, v in fps.items() if abs(tpl.fp_position(k)[0]) < 1.0] or [0.0]
    )
    for fp in list(fps):
        tx = tpl.fp_position(fp)[0]
        if abs(tx) > 5.0 and np.sign(y[fps[fp], 0] - centre) != np.sign(tx):
            left_out[fp] = "landed on the wrong side of the face"
            del fps[fp]
    for a, b in (
        ("3.7", "3.12"),
        ("8.3", "8.4"),
        ("3.5", "3.6"),
        ("4.5", "4.6"),
        ("10.9", "10.10"),
    ):
        if a in fps and b in fps:
            pa, pb = y[fps[a]], y[fps[b]]
            asym = np.linalg.norm(
                (pa - centre * np.array([1, 0, 0])) * [1, 1, 1]
                - (pb - centre * np.array([1, 0, 0])) * [-1, 1, 1]
            )
            if asym > 12.0:
                warnings.append(f"{a} and {b} are {asym:.0f} mm from mirror images of each other")
    return warnings


def _fapu_mm(y, fps: dict[str, int]) -> dict[str, float]:
    out = {}
    for unit, (a, b, axis) in _FAPU.items():
        if a in fps and b in fps:
            out[unit] = float(y[fps[a], axis] - y[fps[b], axis])
    return out
