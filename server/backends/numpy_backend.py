"""The NumPy/SciPy reference backend: the results every other backend must reproduce."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ...protocol.quantize import dequantize_int16, quantize_int16  # noqa: F401  (re-exported)
from ..deform.normals import incidence_matrix, vertex_normals
from ..deform.operator import Operator


class NumpyDeformer:
    """Per-frame deformation on the CPU with NumPy/SciPy.

    ``out[v] = T[g[v]] · [rest[v] + (B·D)[v]; 1]`` where ``g`` is the vertex's rigid group and ``T``
    the frame's ``(G, 3, 4)`` transforms (head, jaw, eye_l, eye_r, each already composed with the
    head pose).

    Args:
        rest: ``(V, 3) float32`` neutral vertices.
        triangles: ``(F, 3) int32``.
        rigid_group: ``(V,) uint8`` group index per vertex.
        operator: the compiled ``Operator`` (K controls).
    """

    name = "numpy"

    def __init__(
        self, rest: np.ndarray, triangles: np.ndarray, rigid_group: np.ndarray, operator: Operator
    ):
        self.rest = np.ascontiguousarray(rest, dtype=np.float32)
        self.triangles = np.ascontiguousarray(triangles, dtype=np.int32)
        self.operator = operator
        self.n_vertices = self.rest.shape[0]
        self.n_controls = operator.n_controls
        group = np.asarray(rigid_group, dtype=np.uint8)
        self.groups = [np.flatnonzero(group == g) for g in range(int(group.max(initial=0)) + 1)]
        if operator.is_sparse:
            self._B = [
                sp.csr_matrix(
                    (operator.weights[:, a], operator.indices, operator.indptr),
                    shape=(self.n_vertices, self.n_controls),
                )
                for a in range(3)
            ]
        self._incidence: sp.csr_matrix | None = None

    def displacements(self, D: np.ndarray) -> np.ndarray:
        """``u = B·D``: ``D (K, 3)`` -> ``(V, 3) float32``."""
        D = np.asarray(D, dtype=np.float32).reshape(self.n_controls, 3)
        if self.operator.is_sparse:
            return np.stack([self._B[a] @ D[:, a] for a in range(3)], axis=1).astype(
                np.float32, copy=False
            )
        return self.operator.dense @ D

    def deform(self, D: np.ndarray, transforms: np.ndarray) -> np.ndarray:
        """One frame: ``D (K, 3)``, ``transforms (G, 3, 4)`` -> vertices ``(V, 3) float32``."""
        p = self.rest + self.displacements(D)
        T = np.asarray(transforms, dtype=np.float32)
        out = np.empty_like(p)
        for g, ids in enumerate(self.groups):
            if len(ids):
                out[ids] = p[ids] @ T[g, :, :3].T + T[g, :, 3]
        return out

    def deform_batch(
        self, D: np.ndarray, transforms: np.ndarray, out: np.ndarray | None = None
    ) -> np.ndarray:
        """Many frames: ``D (T, K, 3)``, ``transforms (T, G, 3, 4)`` -> ``(T, V, 3) float32`` (into ``out``)."""
        if out is None:
            out = np.empty((len(D), self.n_vertices, 3), dtype=np.float32)
        for i, (d, t) in enumerate(zip(D, transforms)):
            out[i] = self.deform(d, t)
        return out

    def normals(self, vertices: np.ndarray) -> np.ndarray:
        """Area-weighted unit vertex normals ``(V, 3) float32`` of deformed ``vertices (V, 3)``."""
        return vertex_normals(
            vertices, self.triangles, incidence=self._vertex_face_incidence(), dtype=np.float32
        )

    def _vertex_face_incidence(self) -> sp.csr_matrix:
        if self._incidence is None:
            self._incidence = incidence_matrix(self.triangles, self.n_vertices)
        return self._incidence
