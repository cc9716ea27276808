"""The linear deformation operator every engine compiles to: vertex displacements u = B·D."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from ..output.atomic import atomic_path


@dataclass(eq=False)
class Operator:
    """B maps K control displacements ``D (K, 3)`` to V vertex displacements ``u (V, 3)``.

    Exactly one form is set:

    - sparse (feature-point engine): CSR over vertices with per-axis weights,
      ``u[v, a] = sum_e weights[e, a] * D[indices[e], a]`` for e in ``indptr[v]:indptr[v+1]``;
      ``indptr (V+1,) int32``, ``indices (nnz,) int32``, ``weights (nnz, 3) float32``;
    - dense (RBF, linear shell): ``dense (V, K) float32``, the same for all three axes, ``u = dense @ D``.

    ``meta`` records the engine and its parameters (it is part of the cache key).
    """

    n_vertices: int
    n_controls: int
    indptr: np.ndarray | None = None
    indices: np.ndarray | None = None
    weights: np.ndarray | None = None
    dense: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if (self.dense is None) == (self.indptr is None):
            raise ValueError("an Operator is either sparse (indptr/indices/weights) or dense")
        if self.dense is not None:
            self.dense = np.ascontiguousarray(self.dense, dtype=np.float32)
            assert self.dense.shape == (self.n_vertices, self.n_controls)
        else:
            self.indptr = np.ascontiguousarray(self.indptr, dtype=np.int32)
            self.indices = np.ascontiguousarray(self.indices, dtype=np.int32)
            self.weights = np.ascontiguousarray(self.weights, dtype=np.float32).reshape(-1, 3)
            assert self.indptr.shape == (self.n_vertices + 1,)
            assert self.indices.shape[0] == self.weights.shape[0] == self.indptr[-1]

    @property
    def is_sparse(self) -> bool:
        return self.dense is None

    @property
    def nnz(self) -> int:
        return int(self.indptr[-1]) if self.is_sparse else self.n_vertices * self.n_controls

    def axis_matrix(self, a: int) -> sp.csr_matrix:
        """Axis ``a`` of a sparse operator as a ``(V, K)`` CSR matrix with float64 weights."""
        return sp.csr_matrix(
            (self.weights[:, a].astype(np.float64), self.indices, self.indptr),
            shape=(self.n_vertices, self.n_controls),
        )

    def apply(self, D: np.ndarray) -> np.ndarray:
        """Reference product: ``D (K, 3)`` -> ``u (V, 3) float32`` (slow path, for tests)."""
        D = np.asarray(D, dtype=np.float32).reshape(self.n_controls, 3)
        if not self.is_sparse:
            return self.dense @ D
        rows = np.repeat(np.arange(self.n_vertices), np.diff(self.indptr))
        u = np.zeros((self.n_vertices, 3), dtype=np.float32)
        np.add.at(u, rows, self.weights * D[self.indices])
        return u

    def save(self, path: Path) -> None:
        """Write to ``path`` (.npz) atomically."""
        arrays = (
            {"dense": self.dense}
            if not self.is_sparse
            else {"indptr": self.indptr, "indices": self.indices, "weights": self.weights}
        )
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez(
                fh,
                n=np.array([self.n_vertices, self.n_controls]),
                meta=np.array(repr(self.meta)),
                **arrays,
            )

    @classmethod
    def load(cls, path: Path) -> Operator:
        import ast

        with np.load(path) as z:
            n_v, n_k = (int(x) for x in z["n"])
            meta = ast.literal_eval(str(z["meta"]))
            if "dense" in z:
                return cls(n_v, n_k, dense=z["dense"], meta=meta)
            return cls(
                n_v, n_k, indptr=z["indptr"], indices=z["indices"], weights=z["weights"], meta=meta
            )
