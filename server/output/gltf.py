"""Animated meshes as binary glTF 2.0 (``.glb``): neutral mesh + morph targets + a weights animation.

Layout: one node (scaled from mesh units to metres), one mesh with one triangle primitive holding
every part (``POSITION``, ``NORMAL``, ``uint32`` indices), ``M`` morph targets (``POSITION`` and
``NORMAL`` deltas) and one animation whose ``LINEAR`` sampler holds the ``M`` weights of every frame
at the frame rate (keyframe i at ``i / fps`` seconds).

Compression: a truncated SVD of the per-frame displacements ``X (T, 3V)`` from the neutral mesh,
computed in two streaming passes over frame chunks, so time grows linearly with ``T`` and memory is
bounded (no ``T x T`` or ``T x 3V`` float64 array; frames may come as a re-iterable chunk source):

1. *Basis*: an orthonormal ``Q (3V, k)`` grows chunk by chunk; a chunk's residual ``R = X_c - X_c Q Q^T``
   that leaves some frame further than ``tau = basis_slack * tolerance`` (per-frame norm) from
   ``span(Q)`` adds the fewest leading singular vectors of ``R`` that bring every frame of the chunk
   within ``tau``. The coefficients ``B = X_c Q`` and the left-over residual energy ``rho_t`` of
   every frame are kept (``(T, k)``, small).
2. The principal directions of ``span(Q)`` (eigenvectors of ``B^T B``) are ordered; ``M`` is the smallest
   count whose per-frame bound ``sqrt(sum_{i>=M} (BV)[t,i]^2) + sqrt(rho_t)`` (>= every vertex's error)
   is within ``tolerance`` in every frame, capped at ``max_targets``.
3. *Verification*: a second pass projects every frame on the ``M`` targets (the stored float32
   weights and targets) and measures the largest vertex error exactly (float64) with ``M`` and with
   up to 9 smaller counts (the first ``m`` targets: the per-frame bound is loose per vertex); the
   fewest that meet ``tolerance`` are kept, and the normal deltas fitted. Should even ``M`` miss it,
   ``M`` grows (and the basis, with a smaller ``tau``) until it holds or ``max_targets`` is reached;
   a capped result says so (``capped`` in the record and a log warning).

The targets are scaled so that every weight lies in [-1, 1]. The measured maximum vertex error (mm)
is the recorded bound (``max_error_mm`` = ``error_bound_mm``), with the largest per-frame residual
norm, frame count, fps, target count and passes in ``extras.facecast``. Normal deltas per target are
the least-squares fit of the per-frame normal changes to the same weights.

Axes: MPEG-4 and glTF agree (+y up, +z = the face's front, +x = the face's left).
"""
from __future__ import annotations

import json
import logging
import math
import struct
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..backends.numpy_backend import incidence_matrix
from .atomic import write_bytes_atomic

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


def frame_chunks(frames: FrameSource, chunk: int) -> Iterator[np.ndarray]:
    """``(c, V, 3) float32`` chunks of at most ``chunk`` frames of ``frames`` (an array or a source)."""
    if callable(frames):
        for c in frames():
            for s in range(0, len(c), chunk):
                yield np.asarray(c[s:s + chunk], dtype=np.float32)
    else:
        for s in range(0, len(frames), chunk):
            yield np.asarray(frames[s:s + chunk], dtype=np.float32)


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
    V = len(rest) // 3
    if chunk.ndim != 3 or chunk.shape[1:] != (V, 3):
        raise ValueError(f"frames must be (T>=1, {V}, 3), not {chunk.shape}")
    if not np.all(np.isfinite(chunk)):
        raise ValueError("frames contain NaN or infinite values")
    return _planar(chunk, rest)


class _Basis:
    """The growing orthonormal basis of pass 1: rows ``Qt[:k]`` of ``Qt (kmax, 3V) float32``."""

    def __init__(self, n_cols: int, kmax: int, keep: int) -> None:
        self.Qt = np.zeros((min(kmax, 32), n_cols), dtype=np.float32)  # grows by doubling up to kmax
        self.k, self.kmax, self.keep = 0, kmax, keep

    def _room(self, j: int) -> None:
        if self.k + j > len(self.Qt):
            grown = np.zeros((min(self.kmax, max(2 * len(self.Qt), self.k + j)), self.Qt.shape[1]), np.float32)
            grown[:self.k] = self.Qt[:self.k]
            self.Qt = grown

    def sweep(self, frames: FrameSource, rest: np.ndarray, tau: float, chunk: int
              ) -> tuple[np.ndarray, np.ndarray]:
        """One pass: grow the basis so every frame is within ``tau`` of its span (while room lasts).

        Returns ``B (T, k) float64`` coefficients (zero on directions added after a frame was seen)
        and ``rho (T,) float64``: each frame's squared distance to the span as it was after its chunk.
        """
        tau2 = tau * tau
        rows_b: list[np.ndarray] = []
        rows_rho: list[np.ndarray] = []
        for fc in frame_chunks(frames, chunk):
            X = _displacements(fc, rest)
            C, R, e = self._project(X)
            for _step in range(6):  # float32 deflation: each step resolves ~1e-6 of the residual energy
                if e.max(initial=0.0) <= tau2:
                    break
                if self.k >= self.kmax:  # full: keep the leading directions, then redo this chunk
                    self._compress(rows_b, rows_rho, C)
                    C, R, e = self._project(X)
                    continue
                lam, U = np.linalg.eigh((R @ R.T).astype(np.float64))
                lam, U = np.clip(lam[::-1], 0.0, None), np.ascontiguousarray(U[:, ::-1])
                tail = np.cumsum(((U**2) * lam)[:, ::-1], axis=1)[:, ::-1]  # tail[t, j]: left after j
                ok = np.flatnonzero(np.append(tail.max(axis=0), 0.0) <= tau2)
                j = int(ok[0]) if len(ok) else len(lam)
                j = max(1, min(j, int((lam > lam[0] * 1e-5).sum()), self.kmax - self.k))  # float32 floor
                Vn = (np.ascontiguousarray(U[:, :j].T, dtype=np.float32) @ R) / np.sqrt(lam[:j]).astype(np.float32)[:, None]
                Qk = self.Qt[:self.k]
                for _ in range(2):  # orthonormalise against the basis and among themselves (float32 drift)
                    Vn -= (Vn @ Qk.T) @ Qk
                    L = np.linalg.cholesky((Vn @ Vn.T).astype(np.float64) + 1e-30 * np.eye(j))
                    Vn = np.linalg.inv(L).astype(np.float32) @ Vn
                self._room(j)
                self.Qt[self.k:self.k + j] = Vn
                self.k += j
                Cn = R @ Vn.T
                R -= Cn @ Vn
                C = np.concatenate([C, Cn], axis=1)
                e = np.einsum("ij,ij->i", R, R).astype(np.float64)
            rows_b.append(C.astype(np.float64))
            rows_rho.append(e)
        B = np.zeros((sum(len(b) for b in rows_b), self.k))
        s = 0
        for b in rows_b:
            B[s:s + len(b), :b.shape[1]] = b[:, :self.k]
            s += len(b)
        return B, np.concatenate(rows_rho) if rows_rho else np.zeros(0)

    def _project(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Coefficients ``(c, k)``, residual ``(c, 3V)`` and residual energies ``(c,) float64`` of ``X``."""
        Qk = self.Qt[:self.k]
        C = X @ Qk.T
        R = X - C @ Qk
        return C, R, np.einsum("ij,ij->i", R, R).astype(np.float64)

    def _compress(self, rows_b: list[np.ndarray], rows_rho: list[np.ndarray], current: np.ndarray) -> None:
        """Full: keep the ``keep`` leading principal directions of the frames seen so far (and of the
        current chunk's coefficients); the energy dropped is added (as a norm, triangle inequality)
        to each earlier frame's residual bound."""
        k = self.k
        B = np.zeros((sum(len(b) for b in rows_b) + len(current), k))
        s = 0
        for b in [*rows_b, current]:
            B[s:s + len(b), :b.shape[1]] = b
            s += len(b)
        V = np.linalg.eigh(B.T @ B)[1][:, ::-1]
        P = B @ V
        keep = min(self.keep, k)
        dropped = (P[:, keep:] ** 2).sum(axis=1)
        self.Qt[:keep] = V[:, :keep].T.astype(np.float32) @ self.Qt[:k]
        self.Qt[keep:] = 0.0
        self.k = keep
        s = 0
        for i, b in enumerate(rows_b):
            rows_b[i] = P[s:s + len(b), :keep]
            rows_rho[i] = (np.sqrt(rows_rho[i]) + np.sqrt(dropped[s:s + len(b)])) ** 2
            s += len(b)


def morph_basis(frames: FrameSource, rest: np.ndarray, tolerance: float, max_targets: int = 128, *,
                normals: Callable[[np.ndarray], np.ndarray] | None = None, basis_slack: float = 0.5,
                chunk: int | None = None) -> MorphBasis:
    """Streaming truncated SVD of the per-frame displacements ``frames - rest`` (see module docstring).

    Args:
        frames: ``(T, V, 3)`` vertices per frame, or a callable returning a fresh iterable of
            ``(c, V, 3)`` chunks (called once per pass, typically twice); ``rest``: ``(V, 3)`` (mesh units).
        tolerance: wanted bound on any vertex's error in any frame (mesh units).
        max_targets: most targets kept.
        normals: ``(c, V, 3) vertices -> (c, V, 3)`` normal deltas to fit per target (None: zeros).
        basis_slack: pass-1 per-frame tolerance as a fraction of ``tolerance``.
        chunk: most frames per chunk (default: about 4M values per chunk, 16-256 frames).
    """
    r = np.ascontiguousarray(np.asarray(rest, dtype=np.float32).T).reshape(-1)  # planar (3V,)
    n_cols = r.size
    chunk = chunk or _chunk_rows(n_cols)
    basis = _Basis(n_cols, kmax=max_targets + max(16, max_targets // 2), keep=max_targets)
    tau = basis_slack * tolerance
    passes, M = 0, 0
    for _round in range(6):
        B, rho = basis.sweep(frames, r, tau, chunk)
        passes += 1
        T, k = B.shape
        if T < 1:
            raise ValueError("frames must hold at least one frame")
        if k:
            V = np.linalg.eigh(B.T @ B)[1][:, ::-1]
            P = B @ V  # coefficients on the principal directions of span(Q)
            tail = np.sqrt(np.append(np.cumsum((P**2)[:, ::-1], axis=1)[:, ::-1], np.zeros((T, 1)), axis=1))
            bound = (tail + np.sqrt(rho)[:, None]).max(axis=0)  # bound[m], m = 0..k
            ok = np.flatnonzero(bound[:min(k, max_targets) + 1] <= tolerance)
            M = max(M, int(ok[0]) if len(ok) else min(k, max_targets), 1)
            M = min(M, k)
        else:  # nothing moves: one zero target
            V, P, M = np.ones((1, 1)), np.zeros((T, 1)), 1
        while True:
            if k:  # (M, 3V) orthonormal rows: the M leading principal directions
                Qv = V[:, :M].T.astype(np.float32) @ basis.Qt[:k]
            else:
                Qv = np.zeros((1, n_cols), dtype=np.float32)
            scale = np.abs(P[:, :M]).max(axis=0) + np.sqrt(rho.max())  # >= every exact |X Qv^T|
            scale[scale == 0] = 1.0
            targets = Qv * scale.astype(np.float32)[:, None]  # (M, 3V) float32
            del Qv
            weights, errors, wtw, wtn = _verify(frames, r, scale, targets, T, chunk, normals)
            passes += 1
            err, frame_err = errors[M]
            if err <= tolerance or M >= max_targets or M >= k:
                break
            M = min(k, max_targets, M + max(1, math.ceil(M / 8)))
        if err <= tolerance or M >= max_targets:
            break
        tau *= 0.5  # every gathered direction is used and still too far: gather finer
    capped = bool(err > tolerance)
    if capped:
        log.warning("glTF morph basis capped at %d targets: max vertex error %.4g > tolerance %.4g "
                    "(mesh units)", M, err, tolerance)
    else:  # the per-frame bound is loose per vertex: keep the fewest measured counts that suffice
        M = min(m for m, (e, _) in errors.items() if e <= tolerance)
        err, frame_err = errors[M]
    if wtn is not None:
        ntargets = (np.linalg.pinv(wtw[:M, :M], hermitian=True) @ wtn[:M]).astype(np.float32)
    else:
        ntargets = np.zeros((M, n_cols), dtype=np.float32)
    return MorphBasis(_interleaved(targets[:M]), np.ascontiguousarray(weights[:, :M]), _interleaved(ntargets),
                      err, frame_err, capped, passes, k)


def _candidates(M: int) -> list[int]:
    """Target counts whose exact error the verification pass also measures: ``M`` and up to 9 below
    (denser near ``M``, where the fewest that suffice usually are)."""
    return sorted({max(1, round(M * f)) for f in (0.2, 0.35, 0.5, 0.6, 0.7, 0.77, 0.84, 0.9, 0.95)} | {M})


def _verify(frames: FrameSource, r: np.ndarray, scale: np.ndarray, targets: np.ndarray,
            T: int, chunk: int, normals: Callable[[np.ndarray], np.ndarray] | None
            ) -> tuple[np.ndarray, dict[int, tuple[float, float]], np.ndarray, np.ndarray | None]:
    """Pass 2: the weights ``(T, M) float32`` of every frame; for each candidate count ``m`` (the first
    ``m`` targets) the measured max vertex error and max per-frame residual norm; and the normal-fit
    sums ``W^T W (M, M)``, ``W^T dN (M, 3V)`` (None without ``normals``)."""
    M = targets.shape[0]
    t64 = targets.astype(np.float64)
    inv = (1.0 / scale**2).astype(np.float32)  # targets = directions * scale
    weights = np.empty((T, M), dtype=np.float32)
    wtw = np.zeros((M, M))
    wtn = np.zeros((M, r.size), dtype=np.float32) if normals is not None else None
    cands = _candidates(M)[::-1]  # M first, then fewer
    errors = {m: (0.0, 0.0) for m in cands}
    s = 0
    for fc in frame_chunks(frames, chunk):
        X = _displacements(fc, r)
        w = (X @ targets.T) * inv
        n = len(w)
        if s + n > T:
            raise ValueError("the frame source yielded more frames on its second pass")
        weights[s:s + n] = w
        w64 = w.astype(np.float64)
        diff = _planar(fc, r, np.float64)  # float64 throughout: exact for float32 data
        diff -= w64 @ t64
        V = r.size // 3
        prev = M
        for m in cands:  # residual with the first m targets = residual with M + the dropped ones
            if m < prev:
                diff += w64[:, m:prev] @ t64[m:prev]
                prev = m
            d2 = np.square(diff[:, :V])
            d2 += np.square(diff[:, V:2 * V])
            d2 += np.square(diff[:, 2 * V:])
            e, f = errors[m]
            errors[m] = (max(e, float(np.sqrt(d2.max(initial=0.0)))),
                         max(f, float(np.sqrt(d2.sum(axis=1).max(initial=0.0)))))
        if wtn is not None:
            wtn += w.T @ _planar(normals(fc))
        wtw += w64.T @ w64
        s += n
    if s != T:
        raise ValueError(f"the frame source yielded {s} frames on its second pass, not {T}")
    return weights, errors, wtw, wtn


def unit_normals(frames: np.ndarray, triangles: np.ndarray, incidence) -> np.ndarray:
    """Area-weighted unit vertex normals of ``(c, V, 3)`` frames -> ``(c, V, 3) float32``; a vertex in
    no triangle gets ``+z`` (glTF needs unit normals everywhere). ``incidence``: ``(V, F)`` CSR."""
    c, V = frames.shape[:2]
    F = len(triangles)
    i0, i1, i2 = (np.ascontiguousarray(triangles[:, i]) for i in range(3))
    out = np.empty((c, V, 3), dtype=np.float32)
    for s in range(0, c, 16):  # 16 frames per sparse product (V, F) @ (F, 3 * 16)
        p = np.ascontiguousarray(np.asarray(frames[s:s + 16], dtype=np.float32).transpose(2, 0, 1))  # (3, b, V)
        b = p.shape[1]
        p0 = p[:, :, i0]
        e1, e2 = p[:, :, i1] - p0, p[:, :, i2] - p0  # (3, b, F)
        fn = np.empty((F, 3, b), dtype=np.float32)  # face normals, length = 2 * area
        fn[:, 0] = (e1[1] * e2[2] - e1[2] * e2[1]).T
        fn[:, 1] = (e1[2] * e2[0] - e1[0] * e2[2]).T
        fn[:, 2] = (e1[0] * e2[1] - e1[1] * e2[0]).T
        n = np.asarray(incidence @ fn.reshape(F, 3 * b), dtype=np.float32).reshape(V, 3, b).transpose(2, 0, 1)
        length = np.sqrt(np.einsum("bvc,bvc->bv", n, n))[..., None]
        n = np.divide(n, length, out=np.zeros_like(n), where=length > 0)
        n[~(np.abs(n).sum(axis=2) > 0)] = (0.0, 0.0, 1.0)
        out[s:s + b] = n
    return out


class _Bin:
    """Accumulates the binary chunk, buffer views and accessors."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []
        self.size = 0
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(self, array: np.ndarray, *, comp: int, type_: str, target: int | None = None,
            minmax: bool = False) -> int:
        data = np.ascontiguousarray(array).tobytes()
        view = {"buffer": 0, "byteOffset": self.size, "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        self.views.append(view)
        pad = (-len(data)) % 4
        self.parts.append(data + b"\0" * pad)
        self.size += len(data) + pad
        ncomp = {"SCALAR": 1, "VEC3": 3}[type_]
        acc = {"bufferView": len(self.views) - 1, "componentType": comp, "count": int(array.size // ncomp),
               "type": type_}
        if minmax:
            a = np.asarray(array, dtype=np.float64).reshape(-1, ncomp)
            acc["min"] = [float(x) for x in a.min(axis=0)] if len(a) else [0.0] * ncomp
            acc["max"] = [float(x) for x in a.max(axis=0)] if len(a) else [0.0] * ncomp
        self.accessors.append(acc)
        return len(self.accessors) - 1


def encode_glb(frames: FrameSource, rest: np.ndarray, triangles: np.ndarray, fps: float, *,
               mm_per_unit: float = 1.0, tolerance_mm: float = 0.01, max_targets: int = 128,
               name: str = "facecast", extras: dict | None = None) -> tuple[bytes, dict]:
    """The ``.glb`` bytes of an animation and its ``extras.facecast`` record (see module docstring).

    Args:
        frames: ``(T, V, 3)`` vertices per frame (mesh units), or a callable returning a fresh
            iterable of ``(c, V, 3)`` chunks of them (called once per pass over the frames);
            ``rest``: ``(V, 3)`` neutral mesh.
        triangles: ``(F, 3)``; ``fps``: frames per second; ``mm_per_unit``: mesh unit size.
        tolerance_mm: error bound for the morph basis; ``max_targets``: cap on targets.
    """
    if not callable(frames):
        frames = np.asarray(frames, dtype=np.float32)
        if frames.ndim != 3 or len(frames) < 1:
            raise ValueError(f"frames must be (T>=1, {len(rest)}, 3), not {frames.shape}")
    rest = np.asarray(rest, dtype=np.float32)
    tri = np.ascontiguousarray(triangles, dtype=np.uint32)
    V = rest.shape[0]
    inc = incidence_matrix(tri.astype(np.int32), V)

    n0 = unit_normals(rest[None], tri, inc)[0]
    mb = morph_basis(frames, rest, tolerance_mm / mm_per_unit, max_targets,
                     normals=lambda v: unit_normals(v, tri, inc) - n0)
    targets, weights, ntargets = mb.targets, mb.weights, mb.normals
    T, M = weights.shape

    b = _Bin()
    pos = b.add(rest, comp=_FLOAT, type_="VEC3", target=_ARRAY_BUFFER, minmax=True)
    nrm = b.add(n0, comp=_FLOAT, type_="VEC3", target=_ARRAY_BUFFER)
    idx = b.add(tri.reshape(-1), comp=_UINT, type_="SCALAR", target=_ELEMENT_ARRAY_BUFFER)
    tgts = [{"POSITION": b.add(targets[m], comp=_FLOAT, type_="VEC3", target=_ARRAY_BUFFER, minmax=True),
             "NORMAL": b.add(ntargets[m], comp=_FLOAT, type_="VEC3", target=_ARRAY_BUFFER)} for m in range(M)]
    times = (np.arange(T, dtype=np.float64) / float(fps)).astype(np.float32)
    t_acc = b.add(times, comp=_FLOAT, type_="SCALAR", minmax=True)
    w_acc = b.add(weights.reshape(-1), comp=_FLOAT, type_="SCALAR")

    record = {"frames": T, "fps": float(fps), "duration_s": float(T / fps), "targets": M,
              "method": "svd-stream", "tolerance_mm": float(tolerance_mm),
              "max_error_mm": mb.max_error * mm_per_unit, "error_bound_mm": mb.max_error * mm_per_unit,
              "frame_error_mm": mb.frame_error * mm_per_unit, "capped": mb.capped,
              "max_targets": int(max_targets), "passes": mb.passes, "mm_per_unit": float(mm_per_unit),
              **(extras or {})}
    s = mm_per_unit / 1000.0
    doc = {
        "asset": {"version": "2.0", "generator": "facecast"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"name": name, "mesh": 0, "scale": [s, s, s]}],
        "meshes": [{"name": name, "weights": [0.0] * M,
                    "primitives": [{"attributes": {"POSITION": pos, "NORMAL": nrm}, "indices": idx,
                                    "mode": 4, "targets": tgts}],
                    "extras": {"targetNames": [f"pc{m:03d}" for m in range(M)]}}],
        "animations": [{"name": name, "samplers": [{"input": t_acc, "output": w_acc, "interpolation": "LINEAR"}],
                        "channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}]}],
        "buffers": [{"byteLength": b.size}],
        "bufferViews": b.views,
        "accessors": b.accessors,
        "extras": {"facecast": record},
    }
    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * ((-len(js)) % 4)
    binary = b"".join(b.parts)
    total = 12 + 8 + len(js) + 8 + len(binary)
    out = b"".join([struct.pack("<III", 0x46546C67, 2, total),
                    struct.pack("<II", len(js), 0x4E4F534A), js,
                    struct.pack("<II", len(binary), 0x004E4942), binary])
    return out, record


def write_glb(path: str | Path, frames: FrameSource, rest: np.ndarray, triangles: np.ndarray, fps: float,
              **options) -> dict:
    """Write ``encode_glb(...)`` to ``path`` atomically; returns the ``extras.facecast`` record."""
    data, record = encode_glb(frames, rest, triangles, fps, **options)
    write_bytes_atomic(path, data)
    log.info("wrote %s: %d frames, %d morph targets, max error %.4f mm, %.1f MB", path, record["frames"],
             record["targets"], record["max_error_mm"], len(data) / 1e6)
    return record
