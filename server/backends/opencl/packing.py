"""The device format of an ``Operator`` (``pack_operator``): what the deform kernel reads.

Per slice of ``SLICE`` consecutive vertices, columns of 16 weights (one per vertex; three planes
when the operator's axis columns differ, else one). A *shared* slice stores one control id per
column: neighbouring vertices are moved by the same feature points, so the union of the 16 rows is
rarely wider than the longest row (100% of the slices of the built-in 500k head, with 1.12 stored
weights per non-zero), and each column costs one ``D`` load for 16 vertices. Other slices are ELL
(16 ids per column). Ids are ``uchar`` for ``K < 256`` (else ``ushort``/``uint``); ELL padding
points at an extra all-zero control ``K``; shared columns hold zero weights for vertices that do
not use the control. A dense operator (RBF, linear shell) is K shared columns per slice. Weights
stay float32, so results equal NumPy's to float32 rounding (different summation order and FMA).
Pure NumPy: no device needed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...deform.operator import Operator

#: Vertices per slice: one work-item deforms one slice as float16 vectors (two AVX2 registers,
#: two independent chains). 8 (float8) also works; 16 measured 10-20% less CPU per frame here.
SLICE = 16


@dataclass
class PackedOperator:
    """An ``Operator`` in the device's format (see the module docstring).

    Slice ``s`` (vertices ``S*s .. S*s+S-1``, ``S = slice``) owns columns ``col_ptr[s] ..
    col_ptr[s+1]`` of ``weights`` (``S * axes`` floats per column: lane-major, one plane per axis
    when ``axes == 3``) and ids ``id_ptr[s] .. id_ptr[s+1]``: one per column for a *shared* slice
    (each column is one control for all S vertices), or S per column for an *ELL* slice (column j
    is entry j of each vertex;
    padding points at the all-zero control ``K``). A dense operator is K shared columns per slice
    with implicit ids (``col_ptr``/``id_ptr``/``ids`` unused).
    """

    n_vertices: int
    n_controls: int
    n_padded: int
    slice: int
    dense: bool
    axes: int
    col_ptr: np.ndarray
    id_ptr: np.ndarray
    ids: np.ndarray
    weights: np.ndarray

    @property
    def idx_ctype(self) -> str:
        return {1: "uchar", 2: "ushort", 4: "uint"}[self.ids.dtype.itemsize]

    @property
    def n_columns(self) -> int:
        return int(self.weights.size // (self.slice * self.axes))

    @property
    def shared_fraction(self) -> float:
        """Fraction of the non-empty slices stored as shared columns."""
        if self.dense:
            return 1.0
        ncol = np.diff(self.col_ptr.astype(np.int64))
        nid = np.diff(self.id_ptr.astype(np.int64))
        busy = ncol > 0
        return float(np.mean(nid[busy] == ncol[busy])) if busy.any() else 1.0

    @property
    def nbytes(self) -> int:
        """Bytes of operator data one frame reads."""
        meta = 0 if self.dense else self.ids.nbytes + self.col_ptr.nbytes + self.id_ptr.nbytes
        return int(self.weights.nbytes + meta)


def index_dtype(n_ids: int) -> np.dtype:
    for dt in (np.uint8, np.uint16, np.uint32):
        if n_ids <= np.iinfo(dt).max + 1:
            return np.dtype(dt)
    raise ValueError("too many controls")


#: A slice is stored as shared columns when that needs at most this many times the columns of
#: ELL (neighbouring vertices mostly share their controls: on the built-in 500k head every slice
#: qualifies). Shared columns cost one D load per column instead of one per vertex.
SHARED_MAX_RATIO = 1.5


def pack_operator(op: Operator, slice_size: int = SLICE) -> PackedOperator:
    """Convert ``op`` to the device format for slices of ``slice_size`` (pure NumPy, vectorised)."""
    V, K, S = op.n_vertices, op.n_controls, slice_size
    n_slices = max(1, -(-V // S))
    Vp = n_slices * S
    id_dtype = index_dtype(K + 1)
    if op.dense is not None:
        # weights[s, k, lane] = dense[s * S + lane, k]
        B = np.zeros((Vp, K), dtype=np.float32)
        B[:V] = op.dense
        w = np.ascontiguousarray(B.reshape(n_slices, S, K).transpose(0, 2, 1)).ravel()
        z = np.zeros(1, np.uint32)
        return PackedOperator(V, K, Vp, S, True, 1, z, z, np.zeros(1, id_dtype), w)
    W, indptr32, indices = op.weights, op.indptr, op.indices
    if W is None or indptr32 is None or indices is None:
        raise ValueError("a sparse operator needs indptr, indices and weights")
    same = bool(np.array_equal(W[:, 0], W[:, 1]) and np.array_equal(W[:, 0], W[:, 2]))
    A = 1 if same else 3
    indptr = indptr32.astype(np.int64)
    rows = np.repeat(np.arange(V, dtype=np.int64), np.diff(indptr))
    pos = np.arange(indptr[-1], dtype=np.int64) - indptr[rows]  # entry's position in its row
    s, lane = rows // S, rows % S
    k = indices.astype(np.int64)
    lengths = np.zeros(Vp, dtype=np.int64)
    lengths[:V] = np.diff(indptr)
    ell_width = lengths.reshape(n_slices, S).max(axis=1)
    # Shared columns: the sorted distinct controls of each slice.
    pairs, rank_of = np.unique(s * (K + 1) + k, return_inverse=True)
    pair_slice = pairs // (K + 1)
    union = np.bincount(pair_slice, minlength=n_slices)
    first = np.zeros(n_slices + 1, dtype=np.int64)
    np.cumsum(union, out=first[1:])
    rank = rank_of.reshape(-1) - first[s]  # column of each entry
    shared = union <= SHARED_MAX_RATIO * ell_width
    ncol = np.where(shared, union, ell_width)
    nid = np.where(shared, union, S * ell_width)
    col_ptr = np.zeros(n_slices + 1, dtype=np.int64)
    np.cumsum(ncol, out=col_ptr[1:])
    id_ptr = np.zeros(n_slices + 1, dtype=np.int64)
    np.cumsum(nid, out=id_ptr[1:])
    if max(col_ptr[-1] * S * A, id_ptr[-1]) >= 2**32:
        raise ValueError("operator too large for 32-bit offsets")
    ids = np.full(int(id_ptr[-1]), K, dtype=id_dtype)  # ELL padding -> zero control K
    w = np.zeros(int(col_ptr[-1]) * S * A, dtype=np.float32)
    # shared slices
    ps = shared[pair_slice]
    ids[id_ptr[pair_slice[ps]] + (np.arange(len(pairs)) - first[pair_slice])[ps]] = (
        pairs % (K + 1)
    )[ps]
    es = shared[s]
    col = np.where(es, col_ptr[s] + rank, col_ptr[s] + pos)
    base = col * (S * A) + lane
    eg = ~es
    ids[id_ptr[s[eg]] + pos[eg] * S + lane[eg]] = k[eg]
    for a in range(A):
        np.add.at(w, base + a * S, W[:, a])
    return PackedOperator(
        V, K, Vp, S, False, A, col_ptr.astype(np.uint32), id_ptr.astype(np.uint32), ids, w
    )
