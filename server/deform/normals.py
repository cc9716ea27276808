"""Triangle and vertex normals of a triangle mesh: the one implementation every module uses."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numpy.typing import DTypeLike


def face_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit triangle normals: ``(V, 3)`` vertices, ``(F, 3)`` triangles -> ``(F, 3) float64``
    (zero for degenerate triangles)."""
    p = np.asarray(vertices, dtype=np.float64)
    n = np.cross(p[triangles[:, 1]] - p[triangles[:, 0]], p[triangles[:, 2]] - p[triangles[:, 0]])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    unit: np.ndarray = np.divide(n, length, out=np.zeros_like(n), where=length > 0)
    return unit


def incidence_matrix(triangles: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """``(V, F)`` 0/1 CSR matrix: vertex v touches triangle f."""
    f = np.repeat(np.arange(len(triangles)), 3)
    return sp.csr_matrix(
        (np.ones(f.size, dtype=np.float32), (np.asarray(triangles).ravel(), f)),
        shape=(n_vertices, len(triangles)),
    )


def vertex_normals(
    vertices: np.ndarray,
    triangles: np.ndarray,
    n_vertices: int | None = None,
    *,
    incidence: sp.csr_matrix | None = None,
    dtype: DTypeLike = np.float64,
) -> np.ndarray:
    """Area-weighted unit vertex normals: ``(..., V, 3)`` vertices (one mesh or a batch of frames),
    ``(F, 3)`` triangles -> ``(..., N, 3)``.

    ``N`` is ``n_vertices`` (default ``V``); a vertex in no triangle (or whose triangles cancel) gets
    ``(0, 0, 0)``. ``dtype``: of the arithmetic and the result (float32 on the live path).
    ``incidence``: ``incidence_matrix(triangles, N)``, made once by callers that repeat the call.
    A batch costs one sparse product; each frame's normals are those of a call on that frame alone.
    """
    v = np.asarray(vertices, dtype=dtype)
    lead, V = v.shape[:-2], v.shape[-2]
    p = np.ascontiguousarray(np.moveaxis(v.reshape(-1, V, 3), -1, 0))  # (3, frames, V)
    b, F = p.shape[1], len(triangles)
    i0, i1, i2 = (np.ascontiguousarray(triangles[:, k]) for k in range(3))
    p0 = p[:, :, i0]
    e1, e2 = p[:, :, i1] - p0, p[:, :, i2] - p0  # (3, frames, F)
    fn = np.empty((F, 3, b), dtype=v.dtype)  # triangle normals, length = 2 * area
    fn[:, 0] = (e1[1] * e2[2] - e1[2] * e2[1]).T
    fn[:, 1] = (e1[2] * e2[0] - e1[0] * e2[2]).T
    fn[:, 2] = (e1[0] * e2[1] - e1[1] * e2[0]).T
    if incidence is None:
        incidence = incidence_matrix(triangles, V if n_vertices is None else n_vertices)
    N = incidence.shape[0]
    n = np.asarray(incidence @ fn.reshape(F, 3 * b), dtype=dtype).reshape(N, 3, b)
    n = n.transpose(2, 0, 1).reshape(*lead, N, 3)
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    unit: np.ndarray = np.divide(n, length, out=np.zeros_like(n), where=length > 0)
    return unit
