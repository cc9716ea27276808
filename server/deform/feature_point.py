"""The feature-point deformation of Kshirsagar, Garchery & Magnenat-Thalmann, as a linear operator.

Every vertex P moves by a weighted average of the displacements of the feature points (FPs, the
controls) that reach it (paper §2, eqs. 1–5):

- **FP distribution.** Regions are grown from all FPs at once over the mesh surface; FPs whose
  regions share a boundary are *neighbours*, at surface distance ``d_ik``.
- **Effective radius** of FP_1 at P (eq. 2): FP_2 and FP_3 are the neighbours of FP_1 with the
  smallest angles ``θ`` (at FP_1, between FP_1→P and FP_1→FP_k), both ``< π/2``;
  ``d = (d_12 cosθ_2 + d_13 cosθ_3) / (cosθ_2 + cosθ_3)``, or ``d = d_12 / cosθ_2`` when only one
  neighbour qualifies.
- **Weight** (eqs. 3–4): ``W = sin(π/2 · (1 − d_1P / d))``, kept only when ``θ < π/2`` and
  ``d_1P < d`` (for P beyond every neighbour, see 2 below).
- **Per frame** (eq. 5): ``D_P = Σ W_i D_i / d_iP² / Σ W_i / d_iP²`` (``normalisation="paper"``),
  or the slides' ``Σ W_i D_i / Σ W_i`` (``"slides"``), or un-normalised ``Σ W_i D_i`` (``"none"``,
  the third option of the research digest §14.1), or facecast's ``Σ W_i D_i / max(Σ W_i, 1)``
  (``"clamped"``): the slides' average where FPs overlap (ΣW ≥ 1), the plain sine falloff where
  a lone FP's influence fades out, so the rim of the influenced region is continuous.

The answers chosen here to the questions the paper leaves open (research digest §14):

1. *Normalisation*: all are available. Of the paper's two, ``"slides"`` had the lower error in
   ``bench/fidelity.py`` (narrowly ahead of ``"paper"``); ``"clamped"`` beat both and is the
   default (see ``build.DEFAULTS``). With ``"paper"`` or ``"slides"`` a vertex reached by one FP
   only follows it fully: the falloff comes from neighbouring (possibly static) FPs, and the
   influenced region ends in a step; ``"clamped"`` lets a lone FP's weight fade out instead. At
   the FP itself ``d_iP = 0`` (eq. 5 is singular there); the FP's own vertex is set to follow its
   control exactly instead (below), and other distances are floored at 1e-6 of the mean edge
   length. Eq. 5's 1/d² makes an FP dominate its surroundings, so that exact vertex blends into
   them; the other normalisations do not, and neighbouring FPs still weigh in one edge away: a
   spike (a 0.3 mm edge of the ICT eyelid stretched 16-fold under a real FAP stream). Hence
   ``own_blend`` (κ = 0.5): within κ times an FP's nearest-neighbour distance, the other FPs'
   weights are scaled by the distance to that FP over that radius. With κ ≤ 0.5 the scaling is 1
   wherever the nearest FP changes (a Voronoi boundary), so it adds no discontinuity; it brought
   the worst strain down to 2.3 and the mean error from 0.2045 to 0.2010 mm.
2. *Angles* are measured in the tangent plane at FP_1 (chords projected along FP_1's vertex
   normal), so that the curvature of a nose or a chin does not skew them; where a projection is
   degenerate (< 1 % of the chord) the 3-D chord is used. (Plain 3-D chords measured about the
   same on the ICT expressions: 0.213 vs 0.217 mm with the FPs, 0.254 vs 0.247 with landmarks.)
   The one-neighbour radius ``d_12 / cosθ`` grows without bound as θ → π/2; it is capped at the
   FP's largest neighbour distance. When no neighbour has ``θ < π/2`` (P lies outside the control
   set, beyond a rim FP) the paper gives no rule; read literally, criterion (1) gives P no weight
   (``no_neighbour="skip"``), which cuts the influenced region off with a step along θ = π/2.
   The default ``"cap"`` uses the capped radius there, the limit of the one-neighbour radius as
   θ → π/2, so the weight is continuous in angle and fades to 0 with distance. It lowered the
   error on every control set and brought the 99th-percentile edge strain of jawOpen from 2.0
   to 1.0 (the artist's: 1.0). (The switch from two to one qualifying neighbour stays
   discontinuous, as in the paper: eq. 2 tends to ``d_12``, the one-neighbour rule to
   ``d_12 / cosθ_2``.)
3. *Surface distance* is Dijkstra over edge lengths everywhere (regions grow by distance, not by
   hop count), restricted to the deformable vertices and to edges within one rigid group, so the
   eyeballs and teeth are walls, not bridges, the tongue (on the jaw) never pulls the upper gums,
   and no weight crosses a slit except around it.
   Region neighbours are pruned: a pair whose distance exceeds ``neighbour_ratio`` times the larger
   of the two FPs' nearest-neighbour distances is dropped (with sparse controls, regions meet far
   away, e.g. behind the head, and such "neighbours" would blow the radii up).
4. *Per-axis constraints*: each axis is an independent deformation whose FPs are only the controls
   constrained on that axis (their distribution, neighbours and radii are computed from that set);
   an FP unconstrained on an axis is an ordinary vertex there, as the paper says. A control's own
   vertex follows its displacement exactly on its constrained axes. Several controls on one vertex
   share it (each gets 1/m of the weight).

Vertices of components no FP can reach (eyelashes, lacrimal films, unconnected gums) copy the
weights of the nearest reached vertex of their own rigid group, when the component comes within
``attach_distance`` of it; otherwise, and for non-deformable vertices, rows are zero.

facecast additions against creases and poke-through (measured with ``bench/deform_quality.py``,
chosen in ``build.DEFAULTS``):

- ``smooth``: the weights above are only piecewise smooth (the sine's kink at the radius, the
  FP_2/FP_3 switch, the clamp at ΣW = 1), and each kink is a crease line in the deformed skin.
  The weight field is diffused along the mesh edges (``smoothing.smooth_rows``) with the controls'
  rows held, so controls still reproduce D and zero D still gives zero motion; the number of
  steps scales with (FP spacing / edge length)², capped.
- ``inner="membrane"``: an unreachable component (an eyelash strip) copies rows only at the
  vertices that touch the skin (its root); the rest of it, and the ``inner_vertices`` (the mouth
  socket), take the harmonic extension of those rows, pulled towards the row of the skin vertex in
  front of them (``smoothing.harmonic_fill``): a lash moves as a whole with its lid instead of each
  tip copying a different lid vertex (spikes), and the socket behind the chin moves down with the
  chin instead of showing through the skin below a mouth corner.
"""

from __future__ import annotations

import logging

import numpy as np

from ..errors import InputError
from .controls import (
    assemble_per_axis,
    attached_rows,
    control_sites,
    copy_rows,
    engine_inputs,
    fill_inner,
    inner_is_membrane,
)
from .mesh_graph import bounded_distances, voronoi
from .normals import vertex_normals
from .operator import Operator
from .smoothing import smooth_rows

log = logging.getLogger(__name__)

NORMALISATIONS: tuple[str, ...] = ("paper", "slides", "clamped", "none")


def _tangent_units(chords: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Unit directions of ``(n, 3)`` chords projected onto the plane with unit ``normal``."""
    flat = chords - np.outer(chords @ normal, normal).astype(chords.dtype, copy=False)
    lf = np.einsum("ij,ij->i", flat, flat)
    degenerate = lf <= 1e-4 * np.einsum("ij,ij->i", chords, chords)  # projection < 1 % of the chord
    if degenerate.any():
        flat[degenerate] = chords[degenerate]
        lf[degenerate] = np.einsum("ij,ij->i", chords[degenerate], chords[degenerate])
    length = np.sqrt(lf)[:, None]
    return np.divide(flat, length, out=np.zeros_like(flat), where=length > 0)


def _site_weights(
    vertices, normal, site_vertex, ids, dist, nb_vertex, nb_dist, cap, rim=True, falloff="sine"
):
    """Eqs. 1–4 for one FP over the vertices it reaches (``rim``: see ``no_neighbour="cap"``).

    Returns ``(vertex ids, W, d_iP)`` of the vertices it influences (its own vertex with W = 1).
    """
    own = ids == site_vertex
    if len(nb_vertex) == 0:
        return np.array([site_vertex]), np.ones(1), np.zeros(1)
    origin = vertices[site_vertex]
    # float32 is ample for angles and halves the memory traffic on big meshes
    to_p = _tangent_units((vertices[ids] - origin).astype(np.float32), normal.astype(np.float32))
    to_k = _tangent_units(
        (vertices[nb_vertex] - origin).astype(np.float32), normal.astype(np.float32)
    )
    cos = (to_p @ to_k.T).astype(np.float64)  # (n, N)
    cos[cos <= 1e-6] = 0.0  # criterion (1): θ < π/2
    rows = np.arange(len(ids))
    first = cos.argmax(axis=1)  # FP_2: the smallest angle
    c2, d2 = cos[rows, first], nb_dist[first]
    cos[rows, first] = -1.0
    second = cos.argmax(axis=1)  # FP_3: the next smallest
    c3, d3 = np.maximum(cos[rows, second], 0.0), nb_dist[second]
    with np.errstate(divide="ignore", invalid="ignore"):
        two = (d2 * c2 + d3 * c3) / (c2 + c3)
        one = np.minimum(d2 / c2, cap)
    d = np.where(c3 > 0, two, np.where(c2 > 0, one, cap if rim else 0.0))
    keep = (d > 0) & (dist < d) & ~own
    w = np.sin(0.5 * np.pi * (1.0 - dist[keep] / d[keep]))
    if falloff == "smooth":  # sin²: zero slope at the radius too, no kink where the influence ends
        w = w * w
    keep_ids = ids[keep]
    pos = w > 0
    return (np.r_[site_vertex, keep_ids[pos]], np.r_[1.0, w[pos]], np.r_[0.0, dist[keep][pos]])


def feature_point_operator(
    vertices: np.ndarray,
    triangles: np.ndarray,
    control_vertices: np.ndarray,
    *,
    constrained: np.ndarray | None = None,
    deformable: np.ndarray | None = None,
    rigid_group: np.ndarray | None = None,
    normalisation: str = "clamped",
    no_neighbour: str = "cap",
    own_blend: float = 0.5,
    neighbour_ratio: float = 3.0,
    attach_distance: float | None = None,
    smooth: float = 0.0,
    smooth_hold: float = 0.0,
    inner: str = "copy",
    inner_vertices: np.ndarray | None = None,
    falloff: str = "sine",
) -> Operator:
    """Build the feature-point operator (sparse, per-axis weights).

    Args:
        vertices: ``(V, 3)`` neutral positions (any units).
        triangles: ``(F, 3)`` vertex ids.
        control_vertices: ``(K,)`` vertex id of each control (FP).
        constrained: ``(K, 3) bool``; on axis a only controls constrained on a are FPs (default:
            all axes).
        deformable: ``(V,) bool``; other vertices get zero rows and block surface paths.
        rigid_group: ``(V,)`` group ids: surface paths stay within a group, and unreachable
            components attach only to vertices of their own group (default: one group).
        normalisation: ``"paper"`` (eq. 5, W/d²), ``"slides"`` (W), ``"clamped"`` (W, dividing by
            ``max(ΣW, 1)``) or ``"none"`` (ΣW·D).
        no_neighbour: where no neighbour of FP_1 lies within 90° of P's direction: ``"cap"``
            uses the capped radius (the FP's largest neighbour distance), ``"skip"`` gives P no
            weight from FP_1 (criterion (1) read literally).
        own_blend: κ; within ``κ`` times an FP's nearest-neighbour distance, the weights of the
            other FPs are scaled by (distance to the FP) / (that radius), so they vanish at the FP
            and its own vertex, which follows its control exactly, is not a spike (0 disables;
            not applied with ``"paper"``, whose 1/d² already lets the FP dominate near itself).
        neighbour_ratio: prune FP neighbours further than this many times the larger of the two
            FPs' nearest-neighbour distances.
        attach_distance: how close (mesh units) an unreachable component must come to a reached
            vertex to copy its weights; default 3 median edge lengths.
        smooth: strength s of the smoothing of the weight field (``smoothing.smooth_rows``,
            controls held fixed): ``round(s · (h / e)²)`` Jacobi steps, h the median distance
            between neighbouring FPs and e the median edge length, so the smoothing spans the same
            fraction of the FP spacing at any mesh density (at most ``MAX_SMOOTH_ITERATIONS``);
            0 disables.
        smooth_hold: rows within this fraction of an FP's nearest-neighbour distance from it are
            held too (not smoothed), so a control does not become a cone rising out of a smoothed
            surrounding (the ICT eyelid FP's 0.3 mm edge stretched 8-fold in a blink without it).
        inner: ``"copy"``: every vertex of an unreachable component copies the row of its nearest
            reached vertex; ``"membrane"``: only the vertices within ``attach_distance`` of a
            reached vertex copy (an eyelash's root, a socket's rim), the rest of the component and
            the ``inner_vertices`` take the harmonic extension of their surroundings
            (``smoothing.harmonic_fill``): they move smoothly with the skin they hang from.
        inner_vertices: ``(n,)`` ids of inner surfaces attached to the skin (the mouth socket);
            used with ``inner="membrane"``.
        falloff: ``"sine"`` (eqs. 3–4) or ``"smooth"`` (its square: also flat where the influence
            ends, so the rim of a region is not a kink).

    Returns:
        ``Operator`` with ``weights (nnz, 3)``; ``meta`` holds the engine and parameters.
    """
    if no_neighbour not in ("cap", "skip"):
        raise InputError(
            f"no_neighbour must be 'cap' or 'skip', not {no_neighbour!r}", where="no_neighbour"
        )
    if normalisation not in NORMALISATIONS:
        raise InputError(
            f"normalisation must be one of {', '.join(NORMALISATIONS)}, not {normalisation!r}",
            where="normalisation",
        )
    vertices, triangles, controls, constrained, deformable = engine_inputs(
        vertices, triangles, control_vertices, constrained, deformable
    )
    n_vertices, n_controls = len(vertices), len(controls)
    meta = {
        "engine": "fp",
        "normalisation": normalisation,
        "no_neighbour": no_neighbour,
        "own_blend": float(own_blend),
        "neighbour_ratio": float(neighbour_ratio),
        "attach_distance": None if attach_distance is None else float(attach_distance),
        "smooth": float(smooth),
        "smooth_hold": float(smooth_hold),
        "inner": inner,
        "falloff": falloff,
    }
    if falloff not in ("sine", "smooth"):
        raise InputError(f"falloff must be 'sine' or 'smooth', not {falloff!r}", where="falloff")

    # Sites: the distinct deformable vertices carrying controls.
    graph, attach_distance, usable, sites, site_of = control_sites(
        vertices, triangles, controls, deformable, rigid_group, attach_distance
    )
    floor = 1e-6 * (float(graph.data.mean()) if graph.nnz else 1.0)
    normals = vertex_normals(vertices, triangles)

    site_ok = deformable[sites]
    # axis_sites[a]: (n_sites,) bool, the site carries a usable control constrained on axis a.
    axis_sites = np.zeros((3, len(sites)), dtype=bool)
    for a in range(3):
        np.logical_or.at(axis_sites[a], site_of, constrained[:, a] & usable)
    patterns = {tuple(m) for m in axis_sites}

    # Step 1: FP distribution per pattern -> pruned neighbour lists.
    neighbours: dict[tuple, list[tuple[np.ndarray, np.ndarray]]] = {}
    regions: dict[
        tuple, tuple[np.ndarray, np.ndarray]
    ] = {}  # pattern -> (owner site, distance) per vertex
    limits = np.zeros(len(sites))
    spacing: list[float] = []
    held: dict[tuple, np.ndarray] = {}
    for pat in patterns:
        members = np.flatnonzero(np.array(pat, dtype=bool) & site_ok)
        vor = voronoi(graph, sites[members])
        i, j = members[vor.pairs[:, 0]], members[vor.pairs[:, 1]]
        dij = vor.pair_distance
        nearest = np.full(len(sites), np.inf)
        np.minimum.at(nearest, i, dij)
        np.minimum.at(nearest, j, dij)
        keep = dij <= neighbour_ratio * np.maximum(nearest[i], nearest[j])
        i, j, dij = i[keep], j[keep], dij[keep]
        lists = []
        for s in range(len(sites)):
            sel_i, sel_j = i == s, j == s
            lists.append((np.r_[j[sel_i], i[sel_j]], np.r_[dij[sel_i], dij[sel_j]]))
            if len(lists[-1][1]):
                limits[s] = max(limits[s], lists[-1][1].max())
        neighbours[pat] = lists
        held[pat] = np.zeros(n_vertices, dtype=bool)
        if len(members):
            nn_pat = np.array([lst[1].min() if len(lst[1]) else 0.0 for lst in lists])
            own = members[np.maximum(vor.source, 0)]
            held[pat] = (vor.source >= 0) & (vor.distance < smooth_hold * nn_pat[own])
        spacing.extend(lst[1].min() for lst in lists if len(lst[1]))
        owner = (
            members[np.maximum(vor.source, 0)] if len(members) else np.zeros(n_vertices, np.int64)
        )
        regions[pat] = (np.where(vor.source >= 0, owner, -1), vor.distance)

    nn_spacing = float(np.median(spacing)) if spacing else 0.0

    # Step 2: bounded surface distances from every site, then weights per pattern.
    active = np.flatnonzero(axis_sites.any(axis=0) & site_ok)
    reach = bounded_distances(graph, sites[active], np.maximum(limits[active], floor) * (1 + 1e-9))
    reach_of = dict(zip(active.tolist(), reach))

    def exact(s: int, others: np.ndarray, approx: np.ndarray) -> np.ndarray:
        ids, dist = reach_of[s]
        pos = np.searchsorted(ids, sites[others])
        pos = np.minimum(pos, len(ids) - 1)
        found = ids[pos] == sites[others]
        return np.where(found, dist[pos], approx)

    axis_entries: dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for pat, lists in neighbours.items():
        members = np.flatnonzero(np.array(pat, dtype=bool) & site_ok)
        rows, cols, vals = [], [], []
        for s in members:
            nb, nb_d = lists[s]
            nb_d = exact(s, nb, nb_d)
            cap = nb_d.max() if len(nb_d) else 0.0
            ids, dist = reach_of[s]
            p, w, dp = _site_weights(
                vertices,
                normals[sites[s]],
                sites[s],
                ids,
                dist,
                sites[nb],
                nb_d,
                cap,
                rim=no_neighbour == "cap",
                falloff=falloff,
            )
            rows.append(p)
            cols.append(np.full(len(p), s))
            if normalisation == "paper":
                vals.append(w / np.maximum(dp, floor) ** 2)
            else:
                vals.append(w)
        if not rows:
            axis_entries[pat] = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
            continue
        r, c, v = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
        if own_blend > 0 and normalisation != "paper":
            # Near FP_i the other FPs fade out, so the FP's exact own vertex is not a spike.
            owner, to_owner = regions[pat]
            nn = np.array(
                [lists[k][1].min() if len(lists[k][1]) else np.inf for k in range(len(sites))]
            )
            o = owner[r]
            fade = np.clip(to_owner[r] / (own_blend * nn[np.maximum(o, 0)]), 0.0, 1.0)
            v = np.where((c == o) | (o < 0), v, v * fade)
        # A site's own vertex follows that site only.
        site_at = np.full(n_vertices, -1)
        site_at[sites[members]] = members
        keep = (site_at[r] < 0) | (site_at[r] == c)
        r, c, v = r[keep], c[keep], v[keep]
        if normalisation != "none":
            total = np.bincount(r, weights=v, minlength=n_vertices)
            v = v / (np.maximum(total[r], 1.0) if normalisation == "clamped" else total[r])
        axis_entries[pat] = (r, c, v)

    # Expand sites to controls, per axis.
    per_axis = []
    for a in range(3):
        r, s, v = axis_entries[tuple(axis_sites[a])]
        ctl = np.flatnonzero(constrained[:, a] & usable)
        ctl_site = site_of[ctl]
        count = np.bincount(ctl_site, minlength=len(sites))
        order = np.argsort(ctl_site, kind="stable")
        starts = np.r_[0, np.cumsum(count)]
        m = count[s]
        rr = np.repeat(r, m)
        vv = np.repeat(v / np.maximum(m, 1), m)
        offs = np.arange(len(rr)) - np.repeat(np.cumsum(m) - m, m)
        cc = ctl[order][np.repeat(starts[s], m) + offs]
        per_axis.append((rr, cc, vv))

    membrane = inner_is_membrane(inner)
    orphans, src, free, floating = attached_rows(
        vertices, graph, deformable, sites[active], rigid_group, attach_distance, membrane=membrane
    )
    per_axis = copy_rows(per_axis, orphans, src)
    op = assemble_per_axis(per_axis, n_vertices, n_controls, meta)
    fixed = np.zeros((n_vertices, 3), dtype=bool)
    for a in range(3):
        fixed[controls[constrained[:, a] & usable], a] = True
        if smooth_hold > 0:
            fixed[:, a] |= held[tuple(axis_sites[a])] & deformable
    iterations = smoothing_iterations(smooth, graph, nn_spacing)
    op.meta["smooth_iterations"] = iterations
    if iterations > 0:
        op = smooth_rows(op, graph, fixed, iterations)
    if not membrane:
        return op
    return fill_inner(
        op,
        graph,
        free,
        inner_vertices,
        fixed.any(axis=1),
        deformable,
        vertices,
        triangles,
        deformable & ~floating,
    )


#: Upper bound on the smoothing steps (a 500k-vertex head would otherwise need ~300).
MAX_SMOOTH_ITERATIONS = 60


def smoothing_iterations(strength: float, graph, spacing: float) -> int:
    """Jacobi steps for smoothing ``strength`` s: ``round(s · (spacing / median edge)²)``, capped."""
    if strength <= 0 or graph.nnz == 0 or spacing <= 0:
        return 0
    e = float(np.median(graph.data))
    return int(min(MAX_SMOOTH_ITERATIONS, round(strength * (spacing / e) ** 2)))
