"""Animated vertices as NumPy ``.npz``: ``vertices (T, V, 3) float32``, ``faces (F, 3) int32``, ``fps``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .atomic import atomic_path


def write_npz(path: str | Path, vertices: np.ndarray, triangles: np.ndarray, fps: float) -> None:
    """Write frames to ``path`` atomically (uncompressed, so it can be memory-mapped per array)."""
    vertices = np.asarray(vertices, dtype=np.float32)
    if vertices.ndim != 3 or vertices.shape[2] != 3:
        raise ValueError(f"vertices must be (T, V, 3), not {vertices.shape}")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(
                fh,
                vertices=vertices,
                faces=np.asarray(triangles, dtype=np.int32),
                fps=np.float64(fps),
            )


def read_npz(path: str | Path) -> tuple[np.ndarray, np.ndarray, float]:
    """``(vertices (T, V, 3) float32, faces (F, 3) int32, fps)`` from a file ``write_npz`` wrote."""
    with np.load(path) as z:
        return z["vertices"], z["faces"], float(z["fps"])
