"""Smoothing of an operator's weight field over the mesh, and rows copied from other vertices.

The feature-point weights are only piecewise smooth: the sine fall-off ends with a kink at each
FP's radius, the choice of FP_2/FP_3 jumps with the direction, the clamped normalisation kinks
where ΣW crosses 1. Each kink or jump is a line along which the deformed skin folds (a crease).
``smooth_rows`` diffuses every control's weight field along the mesh edges:
``B ← (1 − λ) B + λ S B`` (S: the average over a vertex's edge neighbours), ``iterations`` times,
with the rows of the controls held fixed (so they still reproduce their D exactly) and paths
restricted to the edge graph the engine used (deformable vertices, one rigid group: nothing
crosses the lip slit except around its corners). Tiny weights are dropped afterwards to bound
the fill-in.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .operator import Operator


def averaging_matrix(graph: sp.csr_matrix) -> sp.csr_matrix:
    """``(V, V)`` row-stochastic neighbour average over ``graph``'s edges (identity on isolated rows)."""
    a = graph.copy().tocsr()
    a.data[:] = 1.0
    deg = np.asarray(a.sum(axis=1)).ravel()
    iso = deg == 0
    inv = np.divide(1.0, deg, out=np.zeros_like(deg), where=~iso)
    return (sp.diags(inv) @ a + sp.diags(iso.astype(np.float64))).tocsr()


def smooth_rows(
    op: Operator,
    graph: sp.csr_matrix,
    fixed: np.ndarray,
    iterations: int,
    *,
    lam: float = 0.5,
    prune: float = 1e-4,
) -> Operator:
    """Diffuse the sparse operator's rows over ``graph``.

    Args:
        op: sparse ``Operator``.
        graph: ``(V, V)`` edge graph (only its pattern is used).
        fixed: ``(V, 3) bool``, rows/axes kept as they are (the controls on their driven axes).
        iterations: Jacobi steps.
        lam: step size (0.5: each step moves a row half way to its neighbours' average).
        prune: weights below this (absolute) are dropped after smoothing.
    """
    if iterations <= 0 or not op.is_sparse:
        return op
    n, k = op.n_vertices, op.n_controls
    s = averaging_matrix(graph)
    step = ((1.0 - lam) * sp.identity(n, format="csr") + lam * s).tocsr()
    keep = [~fixed[:, a] for a in range(3)]
    out = []
    cache: dict[bytes, sp.csr_matrix] = {}
    for a in range(3):
        b0 = op.axis_matrix(a)
        key = op.weights[:, a].tobytes() + keep[a].tobytes()
        if key in cache:
            out.append(cache[key])
            continue
        free = sp.diags(keep[a].astype(np.float64))
        held = sp.diags((~keep[a]).astype(np.float64)) @ b0
        b = b0
        for _ in range(iterations):
            b = (free @ (step @ b) + held).tocsr()
        b.data[np.abs(b.data) < prune] = 0.0
        b.eliminate_zeros()
        cache[key] = b
        out.append(b)
    return _merge(out, n, k, op.meta)


def _merge(mats: list[sp.csr_matrix], n: int, k: int, meta: dict) -> Operator:
    """Three ``(V, K)`` CSR matrices -> one Operator with per-axis weights on the union pattern."""
    pattern = (abs(mats[0]) + abs(mats[1]) + abs(mats[2])).tocsr()
    pattern.sort_indices()
    weights = np.zeros((pattern.nnz, 3))
    rows = np.repeat(np.arange(n), np.diff(pattern.indptr))
    key = rows.astype(np.int64) * k + pattern.indices
    for a, m in enumerate(mats):
        m = m.tocsr()
        m.eliminate_zeros()
        m = m.tocoo()
        pos = np.searchsorted(key, m.row.astype(np.int64) * k + m.col)
        weights[pos, a] = m.data
    return Operator(
        n, k, indptr=pattern.indptr, indices=pattern.indices, weights=weights, meta=meta
    )


def harmonic_fill(
    op: Operator,
    graph: sp.csr_matrix,
    free: np.ndarray,
    *,
    front: np.ndarray | None = None,
    alpha: float = 1.0,
    prune: float = 1e-4,
) -> Operator:
    """Replace the rows of the ``free (V,) bool`` vertices by the harmonic extension of the others.

    Each free row becomes the average of its edge neighbours' rows (graph Laplacian = 0 on the
    free set), the non-free rows being the boundary values: an inner surface attached to the skin
    (the mouth socket behind the lips, an eyelash strip on its lid) then moves like a membrane
    spanned by the skin it hangs from, smoothly, instead of copying a few unrelated rows. Free
    vertices of a piece that touches no boundary keep their rows.

    ``front (V,)``: for a free vertex, the id of the skin vertex in front of it (or -1); the row is
    then also pulled, with weight ``alpha`` against its neighbours' 1 each, towards that vertex's row
    (a screened membrane: ``(L + alpha P) X = A_fb B_b + alpha B_front``), so a pocket behind the
    chin moves down with the chin instead of half as much.
    """
    from scipy.sparse.csgraph import connected_components
    from scipy.sparse.linalg import splu

    free = np.asarray(free, dtype=bool).copy()
    if not free.any():
        return op
    a = graph.copy().tocsr()
    a.data[:] = 1.0
    n, k = op.n_vertices, op.n_controls
    # free pieces with no edge to a boundary vertex stay as they are
    ff = a[free][:, free]
    _, lab = connected_components(ff, directed=False)
    fid = np.flatnonzero(free)
    touches = np.asarray(a[free][:, ~free].sum(axis=1)).ravel() > 0
    ok = np.zeros(lab.max() + 1, bool)
    ok[lab[touches]] = True
    free[fid[~ok[lab]]] = False
    fid = np.flatnonzero(free)
    if not len(fid):
        return op
    bid = np.flatnonzero(~free)
    deg = np.asarray(a[fid].sum(axis=1)).ravel()
    fr = np.full(len(fid), -1) if front is None else np.asarray(front)[fid]
    pull = alpha * (fr >= 0)
    lap = (sp.diags(deg + pull) - a[fid][:, fid]).tocsc()
    lu = splu(lap)
    afb = a[fid][:, bid]
    if (fr >= 0).any():  # the front rows enter like extra boundary neighbours of weight alpha
        extra = sp.csr_matrix(
            (pull[fr >= 0], (np.flatnonzero(fr >= 0), fr[fr >= 0])), shape=(len(fid), n)
        )
        afb = (afb + extra[:, bid]).tocsr()
    if not op.is_sparse:
        dense = op.dense.copy()
        dense[fid] = lu.solve(np.asarray(afb @ op.dense[bid], dtype=np.float64)).astype(np.float32)
        return Operator(n, k, dense=dense, meta=op.meta)
    mats = []
    done: dict[bytes, sp.csr_matrix] = {}
    for ax in range(3):
        key = op.weights[:, ax].tobytes()
        if key in done:  # axes with the same weights (all controls constrained on all axes)
            mats.append(done[key])
            continue
        b = op.axis_matrix(ax)
        rhs = (afb @ b[bid]).tocsc()
        cols = np.flatnonzero(np.diff(rhs.indptr))  # only controls that reach the boundary
        x = np.zeros((len(fid), k))
        if len(cols):
            x[:, cols] = lu.solve(rhs[:, cols].toarray())
        x[np.abs(x) < prune] = 0.0
        keep = sp.diags((~free).astype(np.float64)) @ b
        put = sp.csr_matrix((np.ones(len(fid)), (fid, np.arange(len(fid)))), shape=(n, len(fid)))
        m = (keep + put @ sp.csr_matrix(x)).tocsr()
        m.eliminate_zeros()
        done[key] = m
        mats.append(m)
    return _merge(mats, n, k, op.meta)
