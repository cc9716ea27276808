"""What every deformation engine does around its own weights (``feature_point``, ``rbf``,
``shell``): check the controls and place them on the mesh, attach the components no control
reaches, fill inner surfaces (eyelash strips, the mouth socket) with harmonic rows, and assemble
per-axis ``(vertex, control, weight)`` triples into an ``Operator``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from ..errors import InputError
from .mesh_graph import components, edge_graph
from .normals import vertex_normals
from .operator import Operator
from .smoothing import harmonic_fill

log = logging.getLogger(__name__)

#: One axis of an operator as COO triples: ``(vertex (n,), control (n,), weight (n,))``.
Triples = tuple[np.ndarray, np.ndarray, np.ndarray]

T = TypeVar("T")


def control_sites(
    vertices: np.ndarray,
    triangles: np.ndarray,
    controls: np.ndarray,
    deformable: np.ndarray,
    rigid_group: np.ndarray | None,
    attach_distance: float | None,
) -> tuple[sp.csr_matrix, float, np.ndarray, np.ndarray, np.ndarray]:
    """What every engine starts from: ``(graph, attach_distance, usable, sites, site_of)``.

    ``graph`` is the deformable edge graph (no edge across rigid groups); ``attach_distance``
    defaults to 3 median edge lengths; ``usable (K,) bool`` marks controls on deformable vertices
    (the others are logged and ignored); ``sites (n,)`` are the distinct control vertices and
    ``site_of (K,)`` maps each control to its site.
    """
    graph = edge_graph(vertices, triangles, deformable, rigid_group)
    if attach_distance is None:
        attach_distance = 3.0 * float(np.median(graph.data)) if graph.nnz else 0.0
    usable = deformable[controls]
    if not usable.all():
        log.warning(
            "%d control(s) sit on non-deformable vertices and are ignored", int((~usable).sum())
        )
    sites, site_of = np.unique(controls, return_inverse=True)
    return graph, attach_distance, usable, sites, site_of.reshape(-1)


def engine_inputs(
    vertices: Any, triangles: Any, control_vertices: Any, constrained: Any, deformable: Any
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(vertices (V, 3) float64, triangles (F, 3) int64, controls (K,) int64, constrained (K, 3)
    bool, deformable (V,) bool)`` from the engines' arguments (``None``: every axis constrained,
    every vertex deformable); ``InputError`` when a vertex id is out of range or a shape is wrong."""
    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    n_vertices = len(vertices)
    controls = np.asarray(control_vertices, dtype=np.int64).reshape(-1)
    if len(controls) and (controls.min() < 0 or controls.max() >= n_vertices):
        raise InputError(
            f"control vertex ids must lie in 0..{n_vertices - 1}", where="control_vertices"
        )
    if constrained is None:
        constrained = np.ones((len(controls), 3), dtype=bool)
    constrained = np.asarray(constrained, dtype=bool)
    if constrained.shape != (len(controls), 3):
        raise InputError(
            f"constrained must have shape ({len(controls)}, 3), not {constrained.shape}",
            where="constrained",
        )
    if deformable is None:
        deformable = np.ones(n_vertices, dtype=bool)
    deformable = np.asarray(deformable, dtype=bool)
    if deformable.shape != (n_vertices,):
        raise InputError(f"deformable must have shape ({n_vertices},)", where="deformable")
    return vertices, triangles, controls, constrained, deformable


def seeded_components(
    graph: sp.csr_matrix, site_vertices: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(label (V,), seeded (V,) bool)``: each vertex's component of ``graph`` and whether that
    component holds one of ``site_vertices``."""
    label = components(graph)
    seeded = np.zeros(label.max() + 1 if len(label) else 0, dtype=bool)
    seeded[label[np.asarray(site_vertices, dtype=np.int64)]] = True
    return label, seeded[label]


def by_axis(
    constrained: np.ndarray, usable: np.ndarray, build: Callable[[np.ndarray], T]
) -> list[T]:
    """``[build(ctl) for each axis]``, ``ctl`` the usable controls constrained on that axis; built
    once per distinct set (axes with the same controls share the very same result)."""
    built: dict[bytes, T] = {}
    out = []
    for a in range(3):
        ctl = np.flatnonzero(constrained[:, a] & usable)
        key = ctl.tobytes()
        if key not in built:
            built[key] = build(ctl)
        out.append(built[key])
    return out


def expand_sites(x: np.ndarray, members: np.ndarray, ctl_site: np.ndarray) -> np.ndarray:
    """Per-site columns ``x (n, len(members))`` (``members`` sorted, distinct site ids) to
    per-control columns ``(n, len(ctl_site))``: a control at a site shared by m of them gets 1/m."""
    count = np.bincount(ctl_site)
    return x[:, np.searchsorted(members, ctl_site)] / count[ctl_site][None, :]


def inner_is_membrane(inner: str) -> bool:
    """Whether ``inner`` (``"copy"`` | ``"membrane"``) asks for membranes; refuses anything else."""
    if inner not in ("copy", "membrane"):
        raise InputError(f"inner must be 'copy' or 'membrane', not {inner!r}", where="inner")
    return inner == "membrane"


def fill_inner(
    op: Operator,
    graph: sp.csr_matrix,
    free: np.ndarray,
    inner_vertices: np.ndarray | None,
    controls: np.ndarray,
    deformable: np.ndarray,
    vertices: np.ndarray,
    triangles: np.ndarray,
    candidates: np.ndarray,
) -> Operator:
    """Harmonic rows (``smoothing.harmonic_fill``) for ``free`` plus the deformable
    ``inner_vertices``, never for control vertices (``controls (V,) bool``), each pulled towards
    the ``candidates (V,) bool`` vertex in front of it (``front_vertices``)."""
    free = free.copy()
    if inner_vertices is not None and len(inner_vertices):
        ids = np.asarray(inner_vertices, dtype=np.int64)
        free[ids[deformable[ids]]] = True
    free &= ~controls
    front = front_vertices(vertices, triangles, free, candidates & ~free)
    return harmonic_fill(op, graph, free, front=front)


def front_vertices(
    vertices: np.ndarray,
    triangles: np.ndarray,
    inner: np.ndarray,
    candidates: np.ndarray,
    k: int = 16,
) -> np.ndarray:
    """``(V,)`` for each ``inner`` vertex the nearest ``candidates`` vertex it lies behind (on the
    inner side of that vertex's tangent plane), else -1: the skin in front of a socket vertex.
    The side test keeps a lower socket vertex from picking the upper lip across the slit."""
    out = np.full(len(vertices), -1, dtype=np.int64)
    cand = np.flatnonzero(candidates)
    ids = np.flatnonzero(inner)
    if not len(cand) or not len(ids):
        return out
    normals = vertex_normals(vertices, triangles)
    k = min(k, len(cand))
    _, near = cKDTree(vertices[cand]).query(vertices[ids], k=k)
    near = cand[np.asarray(near).reshape(len(ids), k)]
    behind = np.einsum("ikj,ikj->ik", vertices[ids][:, None, :] - vertices[near], normals[near]) < 0
    first = behind.argmax(axis=1)
    ok = behind[np.arange(len(ids)), first]
    out[ids[ok]] = near[np.arange(len(ids)), first][ok]
    return out


def attached_rows(
    vertices: np.ndarray,
    graph: sp.csr_matrix,
    deformable: np.ndarray,
    site_vertices: np.ndarray,
    rigid_group: np.ndarray | None,
    attach_distance: float,
    *,
    membrane: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Vertices of unreachable components and the reached vertex whose row each one copies.

    A deformable component with no control is attached when it comes within ``attach_distance``
    of a reached vertex of the same rigid group; each of its vertices then copies its own nearest
    such vertex. With ``membrane`` only the vertices themselves within ``attach_distance`` (the
    anchors) copy. Returns ``(orphans (n,), sources (n,), free (V,) bool, floating (V,) bool)``:
    ``free`` the other vertices of attached components (with ``membrane``, for ``fill_inner``),
    ``floating`` all vertices of attached components.
    """
    n_vertices = len(vertices)
    free = np.zeros(n_vertices, dtype=bool)
    label, seeded = seeded_components(graph, site_vertices)
    floating = deformable & ~seeded
    reached = deformable & seeded
    if not floating.any() or not reached.any() or attach_distance <= 0:
        empty = np.zeros(0, np.int64)
        return empty, empty, free, free.copy()
    group = (
        np.zeros(n_vertices, np.int64) if rigid_group is None else np.asarray(rigid_group, np.int64)
    )
    src_of = np.full(n_vertices, -1)
    for g in np.unique(group[floating]):
        target = np.flatnonzero(reached & (group == g))
        orphans = np.flatnonzero(floating & (group == g))
        if not len(target) or not len(orphans):
            continue
        dist, nearest = cKDTree(vertices[target]).query(vertices[orphans])
        comp_min = np.full(label.max() + 1, np.inf)
        np.minimum.at(comp_min, label[orphans], dist)
        ok = comp_min[label[orphans]] <= attach_distance
        if membrane:
            free[orphans[ok & (dist > attach_distance)]] = True
            ok &= dist <= attach_distance
        src_of[orphans[ok]] = target[nearest[ok]]
    orphans = np.flatnonzero(src_of >= 0)
    if len(orphans):
        log.debug("attached %d vertices of unreachable components", len(orphans))
    attached = free.copy()
    attached[orphans] = True
    return orphans, src_of[orphans], free, attached


def copy_rows(per_axis: list[Triples], orphans: np.ndarray, src: np.ndarray) -> list[Triples]:
    """Append, per axis, a copy of the row of each vertex of ``src (n,)`` as the row of the vertex
    in ``orphans (n,)`` (``attached_rows``)."""
    if not len(orphans):
        return per_axis
    out = []
    for r, c, v in per_axis:
        order = np.argsort(r, kind="stable")
        r, c, v = r[order], c[order], v[order]
        start = np.searchsorted(r, src, side="left")
        stop = np.searchsorted(r, src, side="right")
        n = stop - start
        idx = np.repeat(start, n) + (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n))
        out.append((np.r_[r, np.repeat(orphans, n)], np.r_[c, c[idx]], np.r_[v, v[idx]]))
    return out


def assemble_per_axis(
    per_axis: list[Triples], n_vertices: int, n_controls: int, meta: dict[str, Any]
) -> Operator:
    """Merge per-axis COO triples ``(vertex, control, weight)`` into one CSR with ``(nnz, 3)`` weights."""
    keys = [r.astype(np.int64) * max(n_controls, 1) + c for r, c, _ in per_axis]
    union, inverse = np.unique(np.concatenate(keys), return_inverse=True)
    weights = np.zeros((len(union), 3))
    start = 0
    for a, (r, _, v) in enumerate(per_axis):
        np.add.at(weights[:, a], inverse[start : start + len(r)], v)
        start += len(r)
    rows = union // max(n_controls, 1)
    cols = union % max(n_controls, 1)
    nonzero = np.any(weights != 0, axis=1)
    rows, cols, weights = rows[nonzero], cols[nonzero], weights[nonzero]
    indptr = np.r_[0, np.cumsum(np.bincount(rows, minlength=n_vertices))]
    return Operator(n_vertices, n_controls, indptr=indptr, indices=cols, weights=weights, meta=meta)
