"""Animated meshes as binary glTF 2.0 (``.glb``): neutral mesh + morph targets + a weights animation.

Layout: one node (scaled from mesh units to metres), one mesh with one triangle primitive holding
every part (``POSITION``, ``NORMAL``, ``uint32`` indices), ``M`` morph targets (``POSITION`` and
``NORMAL`` deltas) and one animation whose ``LINEAR`` sampler holds the ``M`` weights of every frame
at the frame rate (keyframe i at ``i / fps`` seconds).

Compression: a truncated SVD of the per-frame displacements ``X (T, 3V)`` from the neutral mesh,
computed in streaming passes over frame chunks, so time grows linearly with ``T`` and memory is
bounded (no ``T x T`` or ``T x 3V`` array; frames may come as a re-iterable chunk source). Every
criterion is the largest *vertex* error (mm), never a whole-frame norm: a frame norm grows with the
vertex count, and at 500k vertices float32 rounding alone exceeds a 0.01 mm frame-norm budget (the
old criterion then piled up rounding-noise directions to the cap and wrote a shredded head).

1. *Basis*: an orthonormal float32 ``Q (k, 3V)`` grows chunk by chunk; while a chunk's residual
   ``R = X_c - X_c Q^T Q`` (projected twice) leaves a vertex further than ``tau = basis_slack *
   tolerance`` from its place, the residual's next leading singular direction (orthogonalised twice,
   skipped when only rounding is left of it) is added. Each frame's coefficients are kept
   (``(T, k)``, small), and ``Q`` is rotated to its principal directions (eigenvectors of ``B^T B``).
2. *Verification*: a second pass fits every frame's weights on the (power-of-two scaled, hence exactly
   representable) float32 targets by least squares in float64, stores them as float32, and measures
   the largest vertex error exactly (float64, in vertex blocks) as a reader will see it: with all
   ``k`` targets and with up to 9 fewer counts; the fewest that meet ``tolerance`` are kept, and the
   normal deltas fitted. Should none meet it, the basis is gathered finer (``tau / 4``) and verified
   again, up to ``rounds`` times, within ``max_targets`` directions.
3. *Fallback*: a clip of at most ``max_targets`` frames gets exact per-frame targets (weight 1 at its
   keyframe; float32 rounding is the only error). Otherwise ``encode_glb`` refuses (``OutputError``:
   what failed, the size, what to do) and nothing is written; so is a file over glTF's 4 GiB.

Targets are scaled so that every weight lies in [-1, 1]. The measured maximum vertex error (mm) is
recorded (``max_error_mm`` = ``error_bound_mm``) with the tolerance (``tolerance_mm``), the largest
per-frame residual norm, frame count, fps, target count, method and passes in ``extras.facecast``
(tolerance and error also in ``asset.extras``). Normal deltas per target are the least-squares fit of
the per-frame normal changes to the same weights.

Axes: MPEG-4 and glTF agree (+y up, +z = the face's front, +x = the face's left).
"""

from __future__ import annotations

import json
import logging
import struct
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..deform.normals import incidence_matrix, vertex_normals
from ..errors import Unprocessable
from .atomic import atomic_path

log = logging.getLogger(__name__)

_FLOAT, _UINT = 5126, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963

#: Frames: a ``(T, V, 3)`` array, or a callable returning a fresh iterable of ``(c, V, 3)`` chunks
#: (called once per pass, it must yield the same frames each time).
FrameSource = np.ndarray | Callable[[], Iterable[np.ndarray]]


@dataclass
class MorphBasis:
    """A morph basis: ``frames ~ rest + weights @ targets``.

    ``targets (M, V, 3) float32`` (scaled so that ``|weights| <= 1``), ``weights (T, M) float32``,
    ``normals (M, V, 3) float32`` normal deltas (zeros if not asked for), ``max_error``: measured
    largest vertex error, ``frame_error``: measured largest per-frame residual norm (mesh units),
    ``capped``: the tolerance was not met within ``max_targets``, ``passes``: passes over the frames,
    ``basis_size``: directions gathered before truncation.
    """

    targets: np.ndarray
    weights: np.ndarray
    normals: np.ndarray
    max_error: float
    frame_error: float
    capped: bool
    passes: int
    basis_size: int
    method: str = "svd"


def frame_chunks(frames: FrameSource, chunk: int) -> Iterator[np.ndarray]:
    """``(c, V, 3) float32`` chunks of at most ``chunk`` frames of ``frames`` (an array or a source)."""
    if callable(frames):
        for c in frames():
            for s in range(0, len(c), chunk):
                yield np.asarray(c[s : s + chunk], dtype=np.float32)
    else:
        for s in range(0, len(frames), chunk):
            yield np.asarray(frames[s : s + chunk], dtype=np.float32)


def _chunk_rows(n_cols: int) -> int:
    """Frames per chunk: about 4M values (16 MB float32, 32 MB float64), 16-256 frames."""
    return int(min(256, max(16, 4_000_000 // max(n_cols, 1))))


def _planar(a: np.ndarray, sub: np.ndarray | None = None, dtype=np.float32) -> np.ndarray:
    """``(c, V, 3)`` -> ``(c, 3V)`` in planar order (all x, all y, all z: the basis works in this
    order, so per-vertex norms are sums of three contiguous blocks), minus ``sub`` (planar ``(3V,)``)."""
    c, V = a.shape[:2]
    t = a.transpose(0, 2, 1)
    out = np.subtract(t, sub.reshape(3, V), dtype=dtype) if sub is not None else t.astype(dtype)
    return out.reshape(c, 3 * V)


def _interleaved(a: np.ndarray) -> np.ndarray:
    """Planar ``(M, 3V)`` -> ``(M, V, 3)`` contiguous."""
    return np.ascontiguousarray(a.reshape(len(a), 3, -1).transpose(0, 2, 1))


def _displacements(chunk: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """``(c, 3V) float32`` planar displacements of a chunk from planar ``rest``; ValueError on a wrong
    shape or non-finite values."""
    _check(chunk, len(rest) // 3)
    return _planar(chunk, rest)


def _check(chunk: np.ndarray, V: int) -> None:
    """ValueError unless ``chunk`` is ``(c, V, 3)`` and finite."""
    if chunk.ndim != 3 or chunk.shape[1:] != (V, 3):
        raise ValueError(f"frames must be (T>=1, {V}, 3), not {chunk.shape}")
    if not np.all(np.isfinite(chunk)):
        raise ValueError("frames contain NaN or infinite values")


#: Largest float64 temporary of the error measurement, in values (32 MB): vertex blocks are sized to it.
_BLOCK_VALUES = 1 << 22


def _vertex_max(R: np.ndarray) -> np.ndarray:
    """Largest vertex norm in each planar row of ``R (c, 3V)`` -> ``(c,) float64``."""
    V = R.shape[1] // 3
    d2 = np.square(R[:, :V], dtype=np.float64)
    d2 += np.square(R[:, V : 2 * V], dtype=np.float64)
    d2 += np.square(R[:, 2 * V :], dtype=np.float64)
    return np.sqrt(d2.max(axis=1, initial=0.0))


def _vertex_blocks(V: int, rows: int) -> Iterator[slice]:
    """Vertex ranges whose ``(rows, 3, n) float64`` blocks hold at most ``_BLOCK_VALUES`` values."""
    n = max(1024, _BLOCK_VALUES // max(3 * rows, 1))
    for a in range(0, V, n):
        yield slice(a, min(a + n, V))


class _Basis:
    """Pass 1's orthonormal directions: float32 planar rows ``(j, 3V)`` in blocks (one per chunk
    that added any), ``k`` rows in all, at most ``kmax``."""

    def __init__(self, n_cols: int, kmax: int) -> None:
        self.blocks: list[np.ndarray] = []
        self.k, self.kmax, self.n_cols = 0, kmax, n_cols
        self.full = False  # a chunk wanted more than kmax directions

    def project(self, X: np.ndarray, extra: list[np.ndarray] = ()) -> tuple[np.ndarray, np.ndarray]:
        """Coefficients ``(c, k) float32`` of ``X (c, 3V)`` on the basis and its residual ``(c, 3V)``,
        projected twice (float32 products over millions of values leave ~1e-5 of ``X`` in the span)."""
        R = np.array(X, dtype=np.float32, copy=True)
        C = [np.zeros((len(X), len(Q)), np.float32) for Q in self.blocks]
        for _ in range(2):
            for c, Q in zip(C, self.blocks):
                cb = R @ Q.T
                R -= cb @ Q
                c += cb
        return (np.concatenate(C, axis=1) if C else np.zeros((len(X), 0), np.float32)), R

    def _orthonormal(self, v: np.ndarray, new: list[np.ndarray]) -> np.ndarray | None:
        """``v (3V,)`` orthogonalised (twice) against the basis and ``new`` rows, unit length; None
        when little of it is left (it lies in the span up to rounding)."""
        n0 = float(np.sqrt(np.dot(v, v)))
        blocks = [*self.blocks, np.stack(new)] if new else self.blocks
        for _ in range(2):
            for Q in blocks:
                v -= (Q @ v) @ Q
        n = float(np.sqrt(np.dot(v, v)))
        if not n > 1e-3 * n0:
            return None
        return (v / n).astype(np.float32)

    def sweep(
        self, frames: FrameSource, r: np.ndarray, tau: float, chunk: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """One pass: for each chunk whose residual leaves a vertex further than ``tau`` from where it
        belongs, add the chunk residual's leading singular directions, one at a time, until no vertex
        is (or ``kmax`` is reached, or rounding is all that is left).

        Returns ``B (T, k) float64``: each frame's coefficients as of its chunk (zero on directions
        added later), and ``rho (T,) float64``: its squared residual norm then.
        """
        rows_b: list[np.ndarray] = []
        rows_rho: list[np.ndarray] = []
        for fc in frame_chunks(frames, chunk):
            X = _displacements(fc, r)
            C, R = self.project(X)
            err = _vertex_max(R)
            new: list[np.ndarray] = []
            coef: list[np.ndarray] = []
            if err.max(initial=0.0) > tau and not self.full:
                lam, U = np.linalg.eigh((R @ R.T).astype(np.float64))
                for i in np.argsort(lam)[::-1]:
                    if err.max(initial=0.0) <= tau or not lam[i] > 0:
                        break
                    if self.k + len(new) >= self.kmax:
                        self.full = True
                        break
                    v = self._orthonormal(U[:, i].astype(np.float32) @ R, new)
                    if v is None:
                        continue
                    cn = R @ v
                    R -= np.outer(cn, v)
                    new.append(v)
                    coef.append(cn)
                    err = _vertex_max(R)
            if new:
                self.blocks.append(np.stack(new))
                self.k += len(new)
                C = np.concatenate([C, np.stack(coef, axis=1)], axis=1)
            rows_b.append(C.astype(np.float64))
            rows_rho.append(np.einsum("ij,ij->i", R, R, dtype=np.float64))
        B = np.zeros((sum(len(b) for b in rows_b), self.k))
        s = 0
        for b in rows_b:
            B[s : s + len(b), : b.shape[1]] = b
            s += len(b)
        return B, np.concatenate(rows_rho) if rows_rho else np.zeros(0)

    def rotate(self, V: np.ndarray) -> np.ndarray:
        """Replace the basis by ``V^T Q`` (``V (k, k)`` orthogonal: the same span, principal
        directions first); returns it ``(k, 3V) float32``."""
        out = np.zeros((self.k, self.n_cols), dtype=np.float32)
        s = 0
        for Q in self.blocks:
            out += V[s : s + len(Q)].T.astype(np.float32) @ Q
            s += len(Q)
        self.blocks = [out]
        return out


def morph_basis(
    frames: FrameSource,
    rest: np.ndarray,
    tolerance: float,
    max_targets: int = 128,
    *,
    normals: Callable[[np.ndarray], np.ndarray] | None = None,
    basis_slack: float = 0.5,
    chunk: int | None = None,
    rounds: int = 5,
) -> MorphBasis:
    """Morph targets within ``tolerance`` of every vertex of every frame (see module docstring).

    Args:
        frames: ``(T, V, 3)`` vertices per frame, or a callable returning a fresh iterable of
            ``(c, V, 3)`` chunks (called once per pass, typically twice); ``rest``: ``(V, 3)`` (mesh units).
        tolerance: wanted bound on any vertex's error in any frame (mesh units).
        max_targets: most targets kept.
        normals: ``(c, V, 3) vertices -> (c, V, 3)`` normal deltas to fit per target (None: zeros).
        basis_slack: pass-1 per-vertex tolerance as a fraction of ``tolerance``.
        chunk: most frames per chunk (default: about 4M values per chunk, 16-256 frames).
        rounds: most basis passes (each followed by a verification pass).

    Returns the smallest verified basis; when none meets ``tolerance`` (``capped``), the best
    measured one (or exact per-frame targets when the clip has at most ``max_targets`` frames).
    """
    r = np.ascontiguousarray(np.asarray(rest, dtype=np.float32).T).reshape(-1)  # planar (3V,)
    n_cols = r.size
    chunk = chunk or _chunk_rows(n_cols)
    basis = _Basis(n_cols, kmax=max_targets)
    tau = basis_slack * tolerance
    passes = 0
    best: MorphBasis | None = None
    for _round in range(rounds):
        B, rho = basis.sweep(frames, r, tau, chunk)
        passes += 1
        T, k = B.shape
        if T < 1:
            raise ValueError("frames must hold at least one frame")
        if k:
            V = np.linalg.eigh(B.T @ B)[1][:, ::-1]
            Qv = basis.rotate(V)
            bound = np.abs(B @ V).max(axis=0) + np.sqrt(rho.max())  # >= every |weight| on Qv
        else:  # nothing moves further than tau: one zero target
            Qv, bound = np.zeros((1, n_cols), dtype=np.float32), np.ones(1)
        scale = np.exp2(np.ceil(np.log2(np.maximum(bound, 1e-30))))  # powers of 2: exact in float32
        targets = Qv * scale.astype(np.float32)[:, None]
        weights, errors, wtw, wtn = _verify(frames, r, targets, T, chunk, normals)
        passes += 1
        ok = [m for m, (e, _) in errors.items() if e <= tolerance]
        M = min(ok) if ok else len(targets)
        if best is None or errors[M][0] < best.max_error:
            best = _finish(targets, weights, M, errors[M], wtw, wtn, not ok, passes, k, "svd")
        if ok or basis.full:
            break
        tau *= 0.25  # every gathered direction is used and still too far: gather finer
    best.passes = passes
    if best.capped and best.weights.shape[0] <= max_targets:
        exact = _exact(frames, r, T, chunk, normals)
        exact.passes += passes
        if exact.max_error < best.max_error:
            best = exact
            best.capped = bool(best.max_error > tolerance)
    if best.capped:
        log.warning(
            "glTF morph basis capped at %d targets: max vertex error %.4g > tolerance %.4g "
            "(mesh units)",
            best.targets.shape[0],
            best.max_error,
            tolerance,
        )
    return best


def _finish(
    targets: np.ndarray,
    weights: np.ndarray,
    M: int,
    errors: tuple[float, float],
    wtw: np.ndarray,
    wtn: np.ndarray | None,
    capped: bool,
    passes: int,
    k: int,
    method: str,
) -> MorphBasis:
    """The ``MorphBasis`` of the first ``M`` targets (normal deltas: least squares on the weights)."""
    if wtn is not None:
        ntargets = (np.linalg.pinv(wtw[:M, :M], hermitian=True) @ wtn[:M]).astype(np.float32)
    else:
        ntargets = np.zeros((M, targets.shape[1]), dtype=np.float32)
    return MorphBasis(
        _interleaved(targets[:M]),
        np.ascontiguousarray(weights[:, :M]),
        _interleaved(ntargets),
        float(errors[0]),
        float(errors[1]),
        capped,
        passes,
        k,
        method,
    )


def _candidates(M: int) -> list[int]:
    """Target counts whose exact error the verification pass also measures: ``M`` and up to 9 below
    (denser near ``M``, where the fewest that suffice usually are)."""
    return sorted(
        {max(1, round(M * f)) for f in (0.2, 0.35, 0.5, 0.6, 0.7, 0.77, 0.84, 0.9, 0.95)} | {M}
    )


def _planar64(fc: np.ndarray, r3: np.ndarray, vb: slice) -> np.ndarray:
    """``(c, 3, n) float64`` displacements of vertices ``vb`` of frames ``fc (c, V, 3)`` from planar
    ``r3 (3, V)``: exact for float32 data."""
    return fc[:, vb].transpose(0, 2, 1).astype(np.float64) - r3[:, vb]


def _verify(
    frames: FrameSource,
    r: np.ndarray,
    targets: np.ndarray,
    T: int,
    chunk: int,
    normals: Callable[[np.ndarray], np.ndarray] | None,
) -> tuple[np.ndarray, dict[int, tuple[float, float]], np.ndarray, np.ndarray | None]:
    """Pass 2: each frame's least-squares weights on ``targets (M, 3V) float32`` (planar) in float64,
    stored as float32 ``(T, M)``; for each candidate count ``m`` (the first ``m`` targets and
    weights, as a reader sees them) the exact max vertex error and max per-frame residual norm
    (float64, in vertex blocks); and the normal-fit sums ``W^T W (M, M)``, ``W^T dN (M, 3V)``
    (None without ``normals``)."""
    M, n_cols = targets.shape
    V = n_cols // 3
    t3 = targets.reshape(M, 3, V)
    r3 = r.reshape(3, V).astype(np.float64)
    blocks = list(_vertex_blocks(V, max(M, chunk)))
    G = np.zeros((M, M))
    for vb in blocks:
        tb = t3[:, :, vb].reshape(M, -1).astype(np.float64)
        G += tb @ tb.T
    Ginv = np.linalg.pinv(G, hermitian=True)
    weights = np.empty((T, M), dtype=np.float32)
    wtw = np.zeros((M, M))
    wtn = np.zeros((M, n_cols), dtype=np.float32) if normals is not None else None
    cands = _candidates(M)[::-1]  # M first, then fewer
    errors = dict.fromkeys(cands, (0.0, 0.0))
    s = 0
    for fc in frame_chunks(frames, chunk):
        _check(fc, V)
        n = len(fc)
        if s + n > T:
            raise ValueError("the frame source yielded more frames on its second pass")
        num = np.zeros((n, M))
        for vb in blocks:
            num += (
                _planar64(fc, r3, vb).reshape(n, -1)
                @ t3[:, :, vb].reshape(M, -1).astype(np.float64).T
            )
        w = (num @ Ginv).astype(np.float32)
        weights[s : s + n] = w
        w64 = w.astype(np.float64)
        frame2 = {m: np.zeros(n) for m in cands}
        for vb in blocks:
            tb = t3[:, :, vb].astype(np.float64)  # (M, 3, nb)
            diff = _planar64(fc, r3, vb)
            diff -= (w64 @ tb.reshape(M, -1)).reshape(diff.shape)
            prev = M
            for (
                m
            ) in cands:  # residual with the first m targets = residual with M + the dropped ones
                if m < prev:
                    diff += (w64[:, m:prev] @ tb[m:prev].reshape(prev - m, -1)).reshape(diff.shape)
                    prev = m
                d2 = np.einsum("cxn,cxn->cn", diff, diff)
                e, f = errors[m]
                errors[m] = (max(e, float(np.sqrt(d2.max(initial=0.0)))), f)
                frame2[m] += d2.sum(axis=1)
        for m in cands:
            e, f = errors[m]
            errors[m] = (e, max(f, float(np.sqrt(frame2[m].max(initial=0.0)))))
        if wtn is not None:
            wtn += w.T @ _planar(normals(fc))
        wtw += w64.T @ w64
        s += n
    if s != T:
        raise ValueError(f"the frame source yielded {s} frames on its second pass, not {T}")
    return weights, errors, wtw, wtn


def _exact(
    frames: FrameSource,
    r: np.ndarray,
    T: int,
    chunk: int,
    normals: Callable[[np.ndarray], np.ndarray] | None,
) -> MorphBasis:
    """One target per frame (its float32 displacement, weight 1 at its keyframe): error is float32
    rounding alone, measured exactly; one pass."""
    n_cols = r.size
    V = n_cols // 3
    r3 = r.reshape(3, V).astype(np.float64)
    targets = np.empty((T, n_cols), dtype=np.float32)
    ntargets = np.zeros((T, n_cols), dtype=np.float32)
    err, frame_err, s = 0.0, 0.0, 0
    for fc in frame_chunks(frames, chunk):
        n = len(fc)
        if s + n > T:
            raise ValueError("the frame source yielded more frames on another pass")
        targets[s : s + n] = _displacements(fc, r)
        f2 = np.zeros(n)
        for vb in _vertex_blocks(V, n):
            diff = _planar64(fc, r3, vb) - targets[s : s + n].reshape(n, 3, V)[:, :, vb]
            d2 = np.einsum("cxn,cxn->cn", diff, diff)
            err = max(err, float(np.sqrt(d2.max(initial=0.0))))
            f2 += d2.sum(axis=1)
        frame_err = max(frame_err, float(np.sqrt(f2.max(initial=0.0))))
        if normals is not None:
            ntargets[s : s + n] = _planar(normals(fc))
        s += n
    if s != T:
        raise ValueError(f"the frame source yielded {s} frames on another pass, not {T}")
    return MorphBasis(
        _interleaved(targets),
        np.eye(T, dtype=np.float32),
        _interleaved(ntargets),
        err,
        frame_err,
        False,
        1,
        T,
        "exact",
    )


def unit_normals(frames: np.ndarray, triangles: np.ndarray, incidence) -> np.ndarray:
    """Area-weighted unit vertex normals of ``(c, V, 3)`` frames -> ``(c, V, 3) float32``
    (``deform.normals.vertex_normals``, 16 frames per sparse product); a vertex in no triangle gets
    ``+z`` (glTF needs unit normals everywhere). ``incidence``: ``(V, F)`` CSR."""
    out = np.empty((len(frames), frames.shape[1], 3), dtype=np.float32)
    for s in range(0, len(frames), 16):
        out[s : s + 16] = vertex_normals(
            frames[s : s + 16], triangles, incidence=incidence, dtype=np.float32
        )
    out[~(np.abs(out).sum(axis=2) > 0)] = (0.0, 0.0, 1.0)
    return out


class OutputError(Unprocessable):
    """The output cannot be written correctly (it would miss its tolerance or a format limit)."""

    status = 422


class _Bin:
    """Accumulates the binary chunk (as array views, not copies), buffer views and accessors."""

    def __init__(self) -> None:
        self.parts: list = []
        self.size = 0
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(
        self,
        array: np.ndarray,
        *,
        comp: int,
        type_: str,
        target: int | None = None,
        minmax: bool = False,
    ) -> int:
        data = memoryview(np.ascontiguousarray(array)).cast("B")
        view = {"buffer": 0, "byteOffset": self.size, "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        self.views.append(view)
        pad = (-len(data)) % 4
        self.parts.append(data)
        if pad:
            self.parts.append(b"\0" * pad)
        self.size += len(data) + pad
        ncomp = {"SCALAR": 1, "VEC3": 3}[type_]
        acc = {
            "bufferView": len(self.views) - 1,
            "componentType": comp,
            "count": int(array.size // ncomp),
            "type": type_,
        }
        if minmax:
            a = np.asarray(array).reshape(-1, ncomp)
            acc["min"] = [float(x) for x in a.min(axis=0)] if len(a) else [0.0] * ncomp
            acc["max"] = [float(x) for x in a.max(axis=0)] if len(a) else [0.0] * ncomp
        self.accessors.append(acc)
        return len(self.accessors) - 1


#: Most morph targets a .glb gets (viewers handle more, but files grow by 24 bytes per vertex each).
MAX_TARGETS = 128
#: The largest .glb: its header stores the total length in 32 bits.
GLB_MAX_BYTES = 2**32 - 1


def glb_parts(
    frames: FrameSource,
    rest: np.ndarray,
    triangles: np.ndarray,
    fps: float,
    *,
    mm_per_unit: float = 1.0,
    tolerance_mm: float = 0.01,
    max_targets: int | None = None,
    name: str = "facecast",
    extras: dict | None = None,
    where: str = "glTF",
) -> tuple[list, dict]:
    """The ``.glb`` of an animation as a list of byte buffers (header, JSON, binary pieces) and its
    ``extras.facecast`` record (see module docstring).

    Args:
        frames: ``(T, V, 3)`` vertices per frame (mesh units), or a callable returning a fresh
            iterable of ``(c, V, 3)`` chunks of them (called once per pass over the frames);
            ``rest``: ``(V, 3)`` neutral mesh.
        triangles: ``(F, 3)``; ``fps``: frames per second; ``mm_per_unit``: mesh unit size.
        tolerance_mm: largest vertex error allowed in any frame (mm); ``max_targets``: cap on targets
            (default ``MAX_TARGETS``). ``where``: what an error names.

    Raises OutputError (nothing written) when no basis of at most ``max_targets`` targets meets
    ``tolerance_mm``, or the file would pass the 4 GiB limit of the format.
    """
    if not callable(frames):
        frames = np.asarray(frames, dtype=np.float32)
        if frames.ndim != 3 or len(frames) < 1:
            raise ValueError(f"frames must be (T>=1, {len(rest)}, 3), not {frames.shape}")
    max_targets = MAX_TARGETS if max_targets is None else int(max_targets)
    rest = np.asarray(rest, dtype=np.float32)
    tri = np.ascontiguousarray(triangles, dtype=np.uint32)
    V = rest.shape[0]
    inc = incidence_matrix(tri.astype(np.int32), V)

    n0 = unit_normals(rest[None], tri, inc)[0]
    mb = morph_basis(
        frames,
        rest,
        tolerance_mm / mm_per_unit,
        max_targets,
        normals=lambda v: unit_normals(v, tri, inc) - n0,
    )
    targets, weights, ntargets = mb.targets, mb.weights, mb.normals
    T, M = weights.shape
    err_mm = mb.max_error * mm_per_unit
    if mb.capped:
        raise OutputError(
            f"refusing to write a wrong file: {T} frames of a {V:,}-vertex face need more than "
            f"{max_targets} morph targets to stay within {tolerance_mm:g} mm (the best basis found is off "
            f"by {err_mm:.3g} mm); write .npz instead (exact vertices), or use a smaller --face or a "
            "shorter clip",
            where=where,
        )
    size = 12 + 8 * 2 + 4096 + 4 * (2 * V * 3 * (M + 1) + tri.size + T * (M + 1))
    if size > GLB_MAX_BYTES:
        raise OutputError(
            f"the .glb would take {size / 2**30:.1f} GiB ({M} morph targets of a {V:,}-vertex face), over "
            "the format's 4 GiB limit; write .npz instead, or use a smaller --face or a shorter clip",
            where=where,
        )

    b = _Bin()
    pos = b.add(rest, comp=_FLOAT, type_="VEC3", target=_ARRAY_BUFFER, minmax=True)
    nrm = b.add(n0, comp=_FLOAT, type_="VEC3", target=_ARRAY_BUFFER)
    idx = b.add(tri.reshape(-1), comp=_UINT, type_="SCALAR", target=_ELEMENT_ARRAY_BUFFER)
    tgts = [
        {
            "POSITION": b.add(
                targets[m], comp=_FLOAT, type_="VEC3", target=_ARRAY_BUFFER, minmax=True
            ),
            "NORMAL": b.add(ntargets[m], comp=_FLOAT, type_="VEC3", target=_ARRAY_BUFFER),
        }
        for m in range(M)
    ]
    times = (np.arange(T, dtype=np.float64) / float(fps)).astype(np.float32)
    t_acc = b.add(times, comp=_FLOAT, type_="SCALAR", minmax=True)
    w_acc = b.add(weights.reshape(-1), comp=_FLOAT, type_="SCALAR")

    record = {
        "frames": T,
        "fps": float(fps),
        "duration_s": float(T / fps),
        "targets": M,
        "method": "svd-stream" if mb.method == "svd" else "exact",
        "tolerance_mm": float(tolerance_mm),
        "max_error_mm": err_mm,
        "error_bound_mm": err_mm,
        "verified": True,
        "frame_error_mm": mb.frame_error * mm_per_unit,
        "capped": mb.capped,
        "max_targets": int(max_targets),
        "passes": mb.passes,
        "mm_per_unit": float(mm_per_unit),
        **(extras or {}),
    }
    s = mm_per_unit / 1000.0
    doc = {
        "asset": {
            "version": "2.0",
            "generator": "facecast",
            "extras": {"tolerance_mm": float(tolerance_mm), "max_error_mm": err_mm},
        },
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"name": name, "mesh": 0, "scale": [s, s, s]}],
        "meshes": [
            {
                "name": name,
                "weights": [0.0] * M,
                "primitives": [
                    {
                        "attributes": {"POSITION": pos, "NORMAL": nrm},
                        "indices": idx,
                        "mode": 4,
                        "targets": tgts,
                    }
                ],
                "extras": {"targetNames": [f"pc{m:03d}" for m in range(M)]},
            }
        ],
        "animations": [
            {
                "name": name,
                "samplers": [{"input": t_acc, "output": w_acc, "interpolation": "LINEAR"}],
                "channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}],
            }
        ],
        "buffers": [{"byteLength": b.size}],
        "bufferViews": b.views,
        "accessors": b.accessors,
        "extras": {"facecast": record},
    }
    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * ((-len(js)) % 4)
    total = 12 + 8 + len(js) + 8 + b.size
    if total > GLB_MAX_BYTES:
        raise OutputError(
            f"the .glb would take {total / 2**30:.1f} GiB, over the format's 4 GiB limit; "
            "write .npz instead, or use a smaller --face or a shorter clip",
            where=where,
        )
    head = [
        struct.pack("<III", 0x46546C67, 2, total),
        struct.pack("<II", len(js), 0x4E4F534A),
        js,
        struct.pack("<II", b.size, 0x004E4942),
    ]
    return head + b.parts, record


def encode_glb(
    frames: FrameSource, rest: np.ndarray, triangles: np.ndarray, fps: float, **options: Any
) -> tuple[bytes, dict]:
    """The ``.glb`` bytes of an animation and its ``extras.facecast`` record: ``glb_parts`` joined
    (its arguments)."""
    parts, record = glb_parts(frames, rest, triangles, fps, **options)
    return b"".join(parts), record


def write_glb(
    path: str | Path,
    frames: FrameSource,
    rest: np.ndarray,
    triangles: np.ndarray,
    fps: float,
    **options: Any,
) -> dict:
    """Write the ``.glb`` of ``glb_parts(...)`` to ``path`` atomically, piece by piece (no copy of the
    whole file in memory); returns the ``extras.facecast`` record. OutputError: nothing is written."""
    parts, record = glb_parts(frames, rest, triangles, fps, where=str(path), **options)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.writelines(parts)
        size = f.tell()
    log.info(
        "wrote %s: %d frames, %d morph targets (%s), max error %.4f mm (tolerance %g mm), %.1f MB",
        path,
        record["frames"],
        record["targets"],
        record["method"],
        record["max_error_mm"],
        record["tolerance_mm"],
        size / 1e6,
    )
    return record
