"""Radial-basis-function warp driven by control displacements, compiled to a dense operator.

``u(x) = Σ_j w_j φ_j(r(x, c_j)) + A x + b`` per axis, where the weights interpolate the control
displacements exactly and, with ``affine=True``, the affine part (``A, b``) satisfies the usual
side conditions ``Σ_j w_j = 0, Σ_j w_j c_j = 0``, so an affine motion of the controls is
reproduced exactly (Sánchez Lorenzo 2006, eqs. 3.14–3.16; when the controls are coplanar the
affine part is restricted to their plane). The system depends only on the neutral geometry, so
it is solved once per face: ``B = [Φ(x, c) P(x)] · M⁻¹[:, :K]`` and per frame ``u = B·D``.

Kernels:

- ``"imq"``: inverse multiquadric ``φ_j(r) = (r² + (s·δ_j)²)^(-1/2)``, δ_j the distance from
  centre j to its nearest other centre and s = ``shape`` (the shape parameter scales with the
  local control spacing, eq. 3.15);
- ``"r"``: ``φ(r) = r``, the biharmonic kernel in 3-D (Euclidean distance only: with surface
  distances its system is indefinite and the warp blew up on the ICT head).

``distance="euclidean"`` is the classic warp; it is blind to openings, so lower-lip controls pull
the upper lip across the mouth slit (on the ICT head 0.23 mm of upper-lip motion per mm of
lower-lip motion). ``distance="surface"`` uses surface (Dijkstra) distances over the deformable
vertices instead: motion then propagates along the skin and crosses a slit only around its
corners (0.016 mm/mm). Coincident centres (the two lips of a closed mouth, under Euclidean
distance) are merged and share their displacement.

Defaults (IMQ, surface distance, no affine part) are the measured best of ``bench/fidelity.py``:
with sparse controls the affine part extrapolates the controls' mean stretch over the whole
scalp and neck. Without it a rigid translation of all controls is not reproduced exactly (far
from the controls the warp fades to 0); rigid head motion is the rigid groups' job anyway.

As in the feature-point engine, only vertices connected (over deformable vertices of one rigid
group) to some control are warped; unreachable components copy the row of their nearest reached
vertex of the same rigid group within ``attach_distance``; everything else (eyeballs, teeth) has
zero rows. Per-axis constraints: on axis a only the controls constrained on a are centres; when
the axes differ the operator is stored sparse with full per-axis rows, otherwise dense ``(V, K)``.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.sparse.csgraph import dijkstra

from ..errors import InputError
from .controls import (
    assemble_per_axis,
    attached_rows,
    by_axis,
    control_sites,
    copy_rows,
    engine_inputs,
    expand_sites,
    fill_inner,
    inner_is_membrane,
    seeded_components,
)
from .operator import Operator

log = logging.getLogger(__name__)

KERNELS: tuple[str, ...] = ("imq", "r")
DISTANCES: tuple[str, ...] = ("euclidean", "surface")


def _kernel(r: np.ndarray, kernel: str, c: np.ndarray | None) -> np.ndarray:
    if kernel == "imq":
        return 1.0 / np.sqrt(r * r + c * c)
    return r


def _poly_basis(points: np.ndarray, centre: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """``[1, (x - centre) · axes]``: the affine basis restricted to the span of the centres."""
    return np.c_[np.ones(len(points)), (points - centre) @ axes]


def _surface_distances(
    graph, sources: np.ndarray, rows: np.ndarray, budget: int = 10_000_000
) -> tuple[np.ndarray, np.ndarray]:
    """Surface distances from every source (inf where unreachable), in chunks of sources.

    Returns ``(to_rows (len(rows), S) float32, between_sources (S, S) float64)``.
    """
    n_vertices = graph.shape[0]
    out = np.empty((len(rows), len(sources)), dtype=np.float32)
    between = np.empty((len(sources), len(sources)))
    chunk = max(1, budget // max(n_vertices, 1))
    for start in range(0, len(sources), chunk):
        d = np.atleast_2d(dijkstra(graph, directed=False, indices=sources[start : start + chunk]))
        out[:, start : start + chunk] = d[:, rows].T
        between[start : start + chunk] = d[:, sources]
    return out, between


def rbf_matrix(
    vertices: np.ndarray,
    centres: np.ndarray,
    *,
    kernel: str = "imq",
    shape: float = 1.0,
    affine: bool = True,
    centre_distances: np.ndarray | None = None,
    vertex_distances: np.ndarray | None = None,
    chunk: int = 65536,
) -> np.ndarray:
    """``(V, n) float32`` interpolation matrix: ``u = B @ D`` warps n centres' displacements.

    Args:
        vertices: ``(V, 3)`` points to warp.
        centres: ``(n, 3)`` centre positions (distinct).
        centre_distances: optional ``(n, n)`` centre-to-centre distances (default Euclidean).
        vertex_distances: optional ``(V, n)`` vertex-to-centre distances (default Euclidean),
            finite everywhere.
    """
    centres = np.asarray(centres, dtype=np.float64)
    n = len(centres)
    if n == 0:
        return np.zeros((len(vertices), 0), dtype=np.float32)
    rcc = (
        centre_distances
        if centre_distances is not None
        else np.linalg.norm(centres[:, None] - centres[None], axis=2)
    )
    # Coincident centres (e.g. the two lips of a closed mouth, under Euclidean distance) cannot
    # carry different values: they are merged and share their column equally.
    scale = float(np.ptp(centres)) if n > 1 else 1.0
    group = np.argmax(rcc <= 1e-9 * max(scale, 1e-300), axis=1)
    if np.any(group != np.arange(n)):
        reps, group = np.unique(group, return_inverse=True)
        count = np.bincount(group)
        vd = None if vertex_distances is None else vertex_distances[:, reps]
        merged = rbf_matrix(
            vertices,
            centres[reps],
            kernel=kernel,
            shape=shape,
            affine=affine,
            centre_distances=rcc[np.ix_(reps, reps)],
            vertex_distances=vd,
            chunk=chunk,
        )
        return (merged[:, group] / count[group]).astype(np.float32)
    c = None
    if kernel == "imq":
        if n > 1:
            off = rcc + np.diag(np.full(n, np.inf))
            delta = off.min(axis=1)
        else:
            delta = np.ones(1)
        delta = np.where(
            np.isfinite(delta) & (delta > 0),
            delta,
            np.nanmax(np.r_[delta[np.isfinite(delta)], 1.0]),
        )
        c = shape * delta
    phi = _kernel(rcc, kernel, c)
    mean = centres.mean(axis=0)
    axes = np.zeros((3, 0))
    if affine and n > 1:
        _, sv, vt = np.linalg.svd(centres - mean, full_matrices=False)
        rank = int((sv > 1e-9 * max(sv[0], 1e-300)).sum())
        axes = vt[:rank].T
    if affine:
        p = _poly_basis(centres, mean, axes)
        m = p.shape[1]
        system = np.block([[phi, p], [p.T, np.zeros((m, m))]])
    else:
        system = phi
    rhs = np.eye(system.shape[0])[:, :n]
    try:
        inv = np.linalg.solve(system, rhs)
        if not np.all(np.isfinite(inv)):
            raise np.linalg.LinAlgError
    except np.linalg.LinAlgError:
        inv = np.linalg.lstsq(system, rhs, rcond=None)[0]
    vertices = np.asarray(vertices, dtype=np.float64)
    out = np.empty((len(vertices), n), dtype=np.float32)
    for start in range(0, len(vertices), chunk):
        x = vertices[start : start + chunk]
        r = (
            vertex_distances[start : start + chunk]
            if vertex_distances is not None
            else np.linalg.norm(x[:, None] - centres[None], axis=2)
        )
        basis = _kernel(r, kernel, c)
        if affine:
            basis = np.c_[basis, _poly_basis(x, mean, axes)]
        out[start : start + chunk] = basis @ inv
    return out


def rbf_operator(
    vertices: np.ndarray,
    triangles: np.ndarray,
    control_vertices: np.ndarray,
    *,
    constrained: np.ndarray | None = None,
    deformable: np.ndarray | None = None,
    rigid_group: np.ndarray | None = None,
    kernel: str = "imq",
    shape: float = 1.0,
    affine: bool = False,
    distance: str = "surface",
    attach_distance: float | None = None,
    inner: str = "copy",
    inner_vertices: np.ndarray | None = None,
) -> Operator:
    """Build the RBF operator (dense ``(V, K)`` when all axes share their constraints).

    Args as ``feature_point_operator``, plus ``kernel`` (``"imq"``/``"r"``), ``shape`` (IMQ shape
    factor s), ``affine`` (add the affine part) and ``distance`` (``"euclidean"``/``"surface"``);
    ``inner``/``inner_vertices`` as there (eyelashes and the mouth socket as membranes).
    The defaults (IMQ over surface distance, no affine part) had the lowest skin error on the ICT
    expressions (``bench/fidelity.py``): with sparse controls the affine part extrapolates the
    controls' mean stretch over the whole scalp and neck.
    """
    if kernel not in KERNELS:
        raise InputError(
            f"kernel must be one of {', '.join(KERNELS)}, not {kernel!r}", where="kernel"
        )
    if distance not in DISTANCES:
        raise InputError(
            f"distance must be one of {', '.join(DISTANCES)}, not {distance!r}", where="distance"
        )
    if kernel == "r" and distance == "surface":
        # φ(r) = r is conditionally positive definite only for Euclidean r; with surface distances
        # the system is indefinite and, on the ICT head, the warp explodes (bench/fidelity.py).
        raise InputError(
            "kernel 'r' needs distance='euclidean' (use kernel 'imq' for surface distances)",
            where="distance",
        )
    vertices, triangles, controls, constrained, deformable = engine_inputs(
        vertices, triangles, control_vertices, constrained, deformable
    )
    n_vertices, n_controls = len(vertices), len(controls)
    meta = {
        "engine": "rbf",
        "kernel": kernel,
        "shape": float(shape),
        "affine": bool(affine),
        "distance": distance,
        "attach_distance": None if attach_distance is None else float(attach_distance),
        "inner": inner,
    }
    membrane = inner_is_membrane(inner)
    graph, attach_distance, usable, sites, site_of = control_sites(
        vertices, triangles, controls, deformable, rigid_group, attach_distance
    )
    site_ok = deformable[sites]
    warped = np.flatnonzero(deformable & seeded_components(graph, sites[site_ok])[1])

    surface = between = None
    column = np.cumsum(site_ok) - 1  # site index -> column of the surface-distance arrays
    if distance == "surface":
        surface, between = _surface_distances(graph, sites[site_ok], warped)

    def axis_columns(ctl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(ctl, (len(warped), len(ctl)))``: the warp of the controls ``ctl`` of one axis."""
        members = np.unique(site_of[ctl])
        cpos = vertices[sites[members]]
        if surface is not None:
            cols = column[members]
            # Centres in different components are treated as very far apart.
            rcc = between[np.ix_(cols, cols)]
            finite = np.isfinite(rcc)
            far = (rcc[finite].max() if finite.any() else 1.0) * 1e3 + 1.0
            rcc = np.where(finite, rcc, far)
            rvx = surface[:, cols]
            rvx[~np.isfinite(rvx)] = far
        else:
            rcc = rvx = None
        b = rbf_matrix(
            vertices[warped],
            cpos,
            kernel=kernel,
            shape=shape,
            affine=affine,
            centre_distances=rcc,
            vertex_distances=rvx,
        )
        return ctl, expand_sites(b, members, site_of[ctl])

    per_axis = by_axis(constrained, usable, axis_columns)
    orphans, src, free, floating = attached_rows(
        vertices, graph, deformable, sites[site_ok], rigid_group, attach_distance, membrane=membrane
    )
    if all(np.array_equal(per_axis[0][0], p[0]) for p in per_axis):
        ctl, vals = per_axis[0]
        dense = np.zeros((n_vertices, n_controls), dtype=np.float32)
        dense[np.ix_(warped, ctl)] = vals
        dense[orphans] = dense[src]
        op = Operator(n_vertices, n_controls, dense=dense, meta=meta)
    else:
        triples = [
            (np.repeat(warped, len(ctl)), np.tile(ctl, len(warped)), vals.ravel())
            for ctl, vals in per_axis
        ]
        op = assemble_per_axis(copy_rows(triples, orphans, src), n_vertices, n_controls, meta)
    if not membrane:
        return op
    held = np.zeros(n_vertices, dtype=bool)
    held[controls[usable]] = True
    return fill_inner(
        op,
        graph,
        free,
        inner_vertices,
        held,
        deformable,
        vertices,
        triangles,
        deformable & ~floating,
    )
