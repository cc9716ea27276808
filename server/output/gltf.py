"""Animated meshes as binary glTF 2.0 (``.glb``): neutral mesh + morph targets + a weights animation.

Layout: one node (scaled from mesh units to metres), one mesh with one triangle primitive holding
every part (``POSITION``, ``NORMAL``, ``uint32`` indices), ``M`` morph targets (``POSITION`` and
``NORMAL`` deltas) and one animation whose ``LINEAR`` sampler holds the ``M`` weights of every frame
at the frame rate (keyframe i at ``i / fps`` seconds).

Compression: the per-frame displacements ``X (T, 3V)`` from the neutral mesh are factored with a
truncated SVD (eigen-decomposition of the ``T x T`` Gram matrix). The targets are the leading
``M`` components (scaled so that the weights stay in [-1, 1]); ``M`` is the smallest rank whose
largest per-frame residual norm ``max_t sqrt(sum_{i>=M} U[t,i]^2 lambda_i)`` -- an upper bound on
every vertex's error in every frame -- is within ``tolerance_mm``, capped at ``max_targets``. The same basis is
used for every length (a short clip simply needs fewer components; ``M <= T``). The measured
maximum vertex error (mm) and the bound are recorded in ``extras.facecast`` with the frame count,
fps and target count. Normal deltas per target are the least-squares fit of the per-frame normal
changes to the same weights.

Axes: MPEG-4 and glTF agree (+y up, +z = the face's front, +x = the face's left).
"""
from __future__ import annotations

import json
import logging
import struct
from pathlib import Path

import numpy as np

from ..backends.numpy_backend import incidence_matrix, vertex_normals
from .atomic import write_bytes_atomic

log = logging.getLogger(__name__)

_FLOAT, _UINT = 5126, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963


def morph_basis(frames: np.ndarray, rest: np.ndarray, tolerance: float, max_targets: int = 128
                ) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Truncated SVD of the per-frame displacements ``frames - rest``.

    Args:
        frames: ``(T, V, 3)`` vertices per frame; ``rest``: ``(V, 3)`` neutral mesh (mesh units).
        tolerance: wanted bound on any vertex's error (mesh units).
        max_targets: most components kept.

    Returns:
        ``targets (M, V, 3) float32``, ``weights (T, M) float32`` with ``targets`` scaled so that
        ``|weights| <= 1``, the measured max vertex error and the energy bound (mesh units).
    """
    T = frames.shape[0]
    F = np.asarray(frames, dtype=np.float32).reshape(T, -1)
    r = np.asarray(rest, dtype=np.float32).reshape(-1)
    n_cols = F.shape[1]
    step = max(3, 4_000_000 // max(T, 1) // 3 * 3)  # whole vertices per column chunk

    def cols(c: int) -> np.ndarray:  # displacement columns c:c+step in float64 (no full copy)
        return F[:, c:c + step].astype(np.float64) - r[c:c + step]

    gram = np.zeros((T, T))
    for c in range(0, n_cols, step):
        xc = cols(c)
        gram += xc @ xc.T
    lam, U = np.linalg.eigh(gram)
    lam, U = np.clip(lam[::-1], 0.0, None), U[:, ::-1]
    # Frame t's residual keeping m components has norm^2 = sum_{i>=m} U[t,i]^2 lam[i]; its max over
    # frames bounds every vertex's error in every frame. tail[m] = that bound.
    energy = (U**2) * lam
    per_frame = np.cumsum(energy[:, ::-1], axis=1)[:, ::-1]
    tail = np.append(np.sqrt(np.maximum(per_frame.max(axis=0), 0.0)), 0.0)
    ok = np.flatnonzero(tail[: min(T, max_targets) + 1] <= tolerance)
    M = int(ok[0]) if len(ok) else min(T, max_targets)
    M = max(M, 1)
    if not len(ok):
        log.warning("glTF morph basis capped at %d targets; energy bound %.3g > tolerance %.3g",
                    M, tail[M], tolerance)
    Um = U[:, :M]
    scale = np.abs(Um).max(axis=0)
    scale[scale == 0] = 1.0
    weights = (Um / scale).astype(np.float32)
    targets = np.empty((M, n_cols), dtype=np.float32)
    err = 0.0
    w64 = weights.astype(np.float64)
    for c in range(0, n_cols, step):
        xc = cols(c)
        tc = ((Um * scale).T @ xc).astype(np.float32)
        targets[:, c:c + step] = tc
        diff = (xc - w64 @ tc.astype(np.float64)).reshape(T, -1, 3)  # exact float32 reconstruction error
        err = max(err, float(np.sqrt((diff**2).sum(axis=2)).max(initial=0.0)))
    return targets.reshape(M, -1, 3), weights, err, float(tail[M])


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


def encode_glb(frames: np.ndarray, rest: np.ndarray, triangles: np.ndarray, fps: float, *,
               mm_per_unit: float = 1.0, tolerance_mm: float = 0.01, max_targets: int = 128,
               name: str = "facecast", extras: dict | None = None) -> tuple[bytes, dict]:
    """The ``.glb`` bytes of an animation and its ``extras.facecast`` record (see module docstring).

    Args:
        frames: ``(T, V, 3)`` vertices per frame (mesh units); ``rest``: ``(V, 3)`` neutral mesh.
        triangles: ``(F, 3)``; ``fps``: frames per second; ``mm_per_unit``: mesh unit size.
        tolerance_mm: error bound for the morph basis; ``max_targets``: cap on targets.
    """
    frames = np.asarray(frames, dtype=np.float32)
    rest = np.asarray(rest, dtype=np.float32)
    tri = np.ascontiguousarray(triangles, dtype=np.uint32)
    T, V = frames.shape[0], rest.shape[0]
    if T < 1 or frames.shape[1:] != (V, 3):
        raise ValueError(f"frames must be (T>=1, {V}, 3), not {frames.shape}")
    if not np.all(np.isfinite(frames)):
        raise ValueError("frames contain NaN or infinite values")
    targets, weights, err, bound = morph_basis(frames, rest, tolerance_mm / mm_per_unit, max_targets)
    M = targets.shape[0]

    inc = incidence_matrix(tri.astype(np.int32), V)

    def normals(v: np.ndarray) -> np.ndarray:  # glTF needs unit normals, also on loose vertices
        n = vertex_normals(v, tri, inc)
        n[~(np.abs(n).sum(axis=1) > 0)] = (0.0, 0.0, 1.0)
        return n

    n0 = normals(rest)
    pinv = np.linalg.pinv(weights.astype(np.float64)).astype(np.float32)  # (M, T)
    ntargets = np.zeros((M, V * 3), dtype=np.float32)
    for t0 in range(0, T, 32):  # least-squares normal deltas, accumulated 32 frames at a time
        dn = np.stack([(normals(f) - n0).reshape(-1) for f in frames[t0:t0 + 32]])
        ntargets += pinv[:, t0:t0 + 32] @ dn
    ntargets = ntargets.reshape(M, V, 3)

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
              "method": "svd", "tolerance_mm": float(tolerance_mm), "max_error_mm": err * mm_per_unit,
              "error_bound_mm": bound * mm_per_unit, "mm_per_unit": float(mm_per_unit), **(extras or {})}
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


def write_glb(path: str | Path, frames: np.ndarray, rest: np.ndarray, triangles: np.ndarray, fps: float,
              **options) -> dict:
    """Write ``encode_glb(...)`` to ``path`` atomically; returns the ``extras.facecast`` record."""
    data, record = encode_glb(frames, rest, triangles, fps, **options)
    write_bytes_atomic(path, data)
    log.info("wrote %s: %d frames, %d morph targets, max error %.4f mm, %.1f MB", path, record["frames"],
             record["targets"], record["max_error_mm"], len(data) / 1e6)
    return record
