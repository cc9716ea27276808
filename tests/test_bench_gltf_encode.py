"""``bench/gltf_encode.py``'s old encoder from git history: the default baseline (the last Gram-matrix
encoder) and a recent revision both load against today's package and encode a small clip (no timing)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest
from conftest import bench_module

from facecast.server.output import gltf

ROOT = Path(__file__).resolve().parents[1]


def _has_revision(rev: str) -> bool:
    r = subprocess.run(
        ["git", "cat-file", "-e", f"{rev}:server/output/gltf.py"],
        cwd=ROOT,
        capture_output=True,
        check=False,
    )
    return r.returncode == 0


def _clip() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A closed tetrahedron (mm) and 6 frames of it stretching: (frames (6, 4, 3), rest, triangles)."""
    rest = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]], dtype=np.float32)
    tri = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=np.uint32)
    t = np.linspace(0, 1, 6, dtype=np.float32)[:, None, None]
    frames = rest + t * np.array([[0, 0, 0], [2, 0, 0], [0, -1, 0], [0, 0, 3]], dtype=np.float32)
    return frames, rest, tri


@pytest.mark.parametrize("rev", ["default", "HEAD"])
def test_the_baseline_encoder_runs_against_todays_package(rev):
    bench = bench_module("gltf_encode")
    rev = bench.BASELINE if rev == "default" else rev
    if not _has_revision(rev):
        pytest.skip(f"git history without {rev} (a shallow clone)")
    old = bench.baseline_module(rev)
    frames, rest, tri = _clip()
    data, record = old.encode_glb(frames, rest, tri, 25.0, mm_per_unit=1.0)
    assert data[:4] == b"glTF" and record["max_error_mm"] <= 0.01, record
    # the basis alone, with the keyword arguments the bench passes to this revision and to today's
    for mod in (old, gltf):
        assert mod.morph_basis(frames, rest, 0.01, **bench.basis_options(mod)) is not None
    assert bench.basis_options(gltf) == {"normals": None}
