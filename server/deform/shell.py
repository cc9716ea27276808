"""Bickel et al.'s linear thin shell (2008, §4) as a precomputed dense operator.

The displacement field ``u`` of the skin minimises a simplified quadratic shell energy

    E(u) = k_s ∫ ‖∇u‖² + k_b ∫ (Δu)²         (Euler-Lagrange: −k_s Δu + k_b Δ²u = 0)

with the control displacements as hard constraints, the same scalar operator for x, y and z.
Discretisation (the paper only names the cotangent Laplacian [Meyer et al. 2003]):

- ``L`` the cotangent stiffness matrix (symmetric, positive semi-definite, ``uᵀLu`` = Dirichlet
  energy), ``M`` the lumped barycentric mass (a third of each adjacent triangle's area), so
  ``A = k_s L + k_b L M⁻¹ L`` (symmetric positive semi-definite: ``‖M^-½ L u‖²`` is the integrated
  squared Laplacian);
- boundaries (the lip slit, the eye openings, the neck) are *free*: the energy simply has no
  triangle beyond them (the natural boundary conditions of the discrete energy). The lip slit is
  a hole of the skin, so upper and lower lip are coupled only around the mouth corners;
- ``k_b = 1`` and ``k_s = stretch / s²`` with ``s`` the median distance from a control to its
  nearest other control: ``stretch`` is dimensionless and independent of the mesh's units and
  resolution (0: pure bending, a thin plate; large: a membrane, harmonic, with cusps at the
  controls). The value is chosen with ``bench/fidelity.py`` (see ``build.DEFAULTS``);
- handles fix one vertex each (as the paper's markers). Ordering the unknowns as (free,
  constrained): ``A_ff u_f = −A_fc u_c``; ``A_ff`` is factorised once (SuperLU) and solved with one
  right-hand side per control, giving the dense ``(V, K)`` basis ``B = −A_ff⁻¹ A_fc`` (the paper's
  precomputation), so a frame is one ``u = B·D``.

The shell covers the skin only (``surface``, the face's ``skin`` part; every deformable vertex when
not given) in the components that hold a control; rigid parts (eyeballs, teeth: not deformable)
get zero rows and follow their rigid groups. Deformable vertices beside the shell (the mouth and eye
sockets, ``inner_vertices``) and unreachable components (eyelashes) are attached as in the other
engines (``controls.fill_inner``: harmonic membranes hanging from the skin, pulled towards the
skin in front of them). Per-axis constraints: on axis a, only the controls constrained on a are
handles; when the axes differ the operator is stored sparse with full per-axis rows.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree

from ..errors import InputError
from .controls import (
    attached_rows,
    by_axis,
    control_sites,
    engine_inputs,
    expand_sites,
    fill_inner,
    inner_is_membrane,
    seeded_components,
)
from .operator import Operator

log = logging.getLogger(__name__)

__all__ = ["cotangent_laplacian", "shell_matrix", "shell_operator"]


def cotangent_laplacian(
    vertices: np.ndarray, triangles: np.ndarray
) -> tuple[sp.csr_matrix, np.ndarray]:
    """``(L (V, V) CSR float64, mass (V,) float64)``: cotangent stiffness (positive semi-definite,
    rows sum to 0) and lumped barycentric vertex areas (mesh units²; 0 for vertices in no triangle).

    Cotangents of degenerate corners are bounded (|cot| ≤ 1e4) so sliver triangles stay finite.
    """
    v = np.asarray(vertices, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    n = len(v)
    rows, cols, vals = [], [], []
    area2 = np.linalg.norm(
        np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]]), axis=1
    )
    for k in range(3):
        i, j, o = tri[:, (k + 1) % 3], tri[:, (k + 2) % 3], tri[:, k]
        a, b = v[i] - v[o], v[j] - v[o]
        cross = np.linalg.norm(np.cross(a, b), axis=1)
        dot = np.einsum("ij,ij->i", a, b)
        scale = np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1)
        cot = np.clip(dot / np.maximum(cross, 1e-12 * np.maximum(scale, 1e-300)), -1e4, 1e4)
        w = 0.5 * cot
        rows += [i, j, i, j]
        cols += [j, i, i, j]
        vals += [-w, -w, w, w]
    lap = sp.coo_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    ).tocsr()
    lap.sum_duplicates()
    mass = np.bincount(tri.ravel(), weights=np.repeat(area2 / 6.0, 3), minlength=n)
    return lap, mass


def shell_matrix(
    vertices: np.ndarray, triangles: np.ndarray, ks: float, kb: float
) -> sp.csr_matrix:
    """``A = ks·L + kb·L M⁻¹ L`` ``(V, V)`` for the mesh (masses floored at 1e-6 of their mean)."""
    lap, mass = cotangent_laplacian(vertices, triangles)
    used = mass > 0
    floor = 1e-6 * (mass[used].mean() if used.any() else 1.0)
    inv = sp.diags(np.where(used, 1.0 / np.maximum(mass, floor), 0.0))
    return (ks * lap + kb * (lap @ inv @ lap)).tocsr()


def _spacing(points: np.ndarray) -> float:
    """Median distance from each point to its nearest other point (1.0 for fewer than two)."""
    if len(points) < 2:
        return 1.0
    d = cKDTree(points).query(points, k=2)[0][:, 1]
    d = d[d > 0]
    return float(np.median(d)) if len(d) else 1.0


def _solve_sites(
    a: sp.csr_matrix, domain: np.ndarray, sites: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Harmonic-in-``A`` basis on ``domain (n,)`` vertex ids with ``sites (S,)`` (vertex ids in the
    domain) held: ``(rows (m,) vertex ids, X (m, S) float32)``; ``X[site s, s] = 1``. Vertices of
    domain components with no site are left out (they are not determined)."""
    local = np.full(a.shape[0], -1, dtype=np.int64)
    local[domain] = np.arange(len(domain))
    sub = a[domain][:, domain].tocsr()
    adj = sub.copy()
    adj.data = np.ones_like(adj.data)
    n_comp, label = connected_components(adj, directed=False)
    has = np.zeros(n_comp, dtype=bool)
    has[label[local[sites]]] = True
    keep = has[label]
    held = np.zeros(len(domain), dtype=bool)
    held[local[sites]] = True
    free = keep & ~held
    out = np.zeros((int(keep.sum()), len(sites)), dtype=np.float32)
    kept = np.flatnonzero(keep)
    pos = np.full(len(domain), -1, dtype=np.int64)
    pos[kept] = np.arange(len(kept))
    out[pos[local[sites]], np.arange(len(sites))] = 1.0
    if free.any():
        ff = sub[free][:, free].tocsc()
        rhs = -(sub[free][:, local[sites]]).toarray()
        # symmetric positive definite: no pivoting needed, which keeps the fill-reducing ordering
        lu = splu(
            ff, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
        )
        out[pos[np.flatnonzero(free)]] = lu.solve(rhs).astype(np.float32)
    return domain[kept], out


def shell_operator(
    vertices: np.ndarray,
    triangles: np.ndarray,
    control_vertices: np.ndarray,
    *,
    constrained: np.ndarray | None = None,
    deformable: np.ndarray | None = None,
    rigid_group: np.ndarray | None = None,
    surface: np.ndarray | None = None,
    stretch: float = 0.1,
    attach_distance: float | None = None,
    inner: str = "membrane",
    inner_vertices: np.ndarray | None = None,
) -> Operator:
    """Build the linear-shell operator (dense ``(V, K)`` when all axes share their constraints).

    Args:
        vertices, triangles: the rest mesh ``(V, 3)``, ``(F, 3)``.
        control_vertices: ``(K,)`` vertex ids of the handles.
        constrained: ``(K, 3) bool`` axes on which each control is driven (default all).
        deformable: ``(V,) bool`` vertices that may move (default all).
        rigid_group: ``(V,)`` rigid group per vertex; no triangle across groups enters the shell.
        surface: ``(n,)`` vertex ids the shell may cover (the skin); None = every deformable vertex.
        stretch: ``k_s / k_b`` times the squared control spacing (0 = pure bending).
        attach_distance, inner, inner_vertices: as in ``feature_point_operator``.
    """
    if not np.isfinite(stretch) or stretch < 0:
        raise InputError(f"stretch must be a number >= 0, not {stretch!r}", where="stretch")
    vertices, triangles, controls, constrained, deformable = engine_inputs(
        vertices, triangles, control_vertices, constrained, deformable
    )
    n_vertices, n_controls = len(vertices), len(controls)
    membrane = inner_is_membrane(inner)
    meta = {
        "engine": "shell",
        "stretch": float(stretch),
        "attach_distance": None if attach_distance is None else float(attach_distance),
        "inner": inner,
    }
    graph, attach_distance, usable, sites, site_of = control_sites(
        vertices, triangles, controls, deformable, rigid_group, attach_distance
    )
    label, seeded = seeded_components(graph, sites[deformable[sites]])
    reached = deformable & seeded
    # The shell's domain: the surface (skin) where a component has some, the whole component otherwise.
    on_surface = np.ones(n_vertices, dtype=bool)
    if surface is not None:
        on_surface[:] = False
        on_surface[np.asarray(surface, dtype=np.int64)] = True
        with_surface = np.zeros(label.max() + 1, dtype=bool)
        with_surface[label[on_surface & deformable]] = True
        on_surface |= ~with_surface[label]
    domain_mask = reached & on_surface
    if inner_vertices is not None and len(inner_vertices):
        domain_mask[np.asarray(inner_vertices, dtype=np.int64)] = False
    domain_mask[sites[deformable[sites]]] = True
    same_group = np.ones(len(triangles), dtype=bool)
    if rigid_group is not None:
        g = np.asarray(rigid_group)[triangles]
        same_group = (g[:, 0] == g[:, 1]) & (g[:, 1] == g[:, 2])
    shell_tris = triangles[domain_mask[triangles].all(axis=1) & same_group]
    ks_unit = _spacing(vertices[sites[deformable[sites]]]) ** -2
    a = shell_matrix(vertices, shell_tris, ks=stretch * ks_unit, kb=1.0)
    domain = np.flatnonzero(domain_mask)

    def axis_matrix(ctl: np.ndarray) -> np.ndarray:
        """``(V, K) float32`` for the controls ``ctl`` constrained on one axis (others: 0 columns)."""
        dense = np.zeros((n_vertices, n_controls), dtype=np.float32)
        if not len(ctl):
            return dense
        members = np.unique(site_of[ctl])
        rows, x = _solve_sites(a, domain, sites[members])
        dense[np.ix_(rows, ctl)] = expand_sites(x, members, site_of[ctl])
        solved = np.zeros(n_vertices, dtype=bool)
        solved[rows] = True
        # attach what the shell does not cover: floating components copy (their roots), sockets and
        # the rest of floating components hang as membranes from the skin
        orphans, src, free, _ = attached_rows(
            vertices,
            graph,
            deformable,
            sites[members],
            rigid_group,
            attach_distance,
            membrane=membrane,
        )
        dense[orphans] = dense[src]
        if not membrane:  # the other deformable vertices copy their nearest shell vertex
            other = np.flatnonzero(reached & ~solved)
            if len(other) and len(rows):
                dense[other] = dense[rows[cKDTree(vertices[rows]).query(vertices[other])[1]]]
            return dense
        free |= reached & ~solved  # sockets and other deformable non-shell vertices
        held = np.zeros(n_vertices, dtype=bool)
        held[controls[usable]] = True
        op = fill_inner(
            Operator(n_vertices, n_controls, dense=dense, meta=meta),
            graph,
            free,
            inner_vertices,
            held,
            deformable,
            vertices,
            triangles,
            solved,
        )
        return op.dense

    per_axis = by_axis(constrained, usable, axis_matrix)
    if per_axis[0] is per_axis[1] is per_axis[2]:
        return Operator(n_vertices, n_controls, dense=per_axis[0], meta=meta)
    nz = (per_axis[0] != 0) | (per_axis[1] != 0) | (per_axis[2] != 0)
    rows, cols = np.nonzero(nz)
    weights = np.stack([m[rows, cols] for m in per_axis], axis=1)
    indptr = np.r_[0, np.cumsum(np.bincount(rows, minlength=n_vertices))]
    return Operator(n_vertices, n_controls, indptr=indptr, indices=cols, weights=weights, meta=meta)
