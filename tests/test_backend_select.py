"""Device probing, backend choice and the NumPy fallback (real OpenCL stack; failures made real by
pointing the ICD loader at no vendors, or by giving PoCL a build flag its compiler rejects)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from facecast.server.backends import NumpyDeformer, make_deformer
from facecast.server.deform.operator import Operator
from facecast.server.errors import FacecastError
from facecast.server.faces.face import Face

select = pytest.importorskip("facecast.server.backends.select")


def tiny_face() -> tuple[Face, Operator]:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    tri = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]], np.int32)
    face = Face("tiny", v, tri, "mm", {"eye_l": np.array([3])})
    op = Operator(
        4,
        2,
        indptr=np.array([0, 1, 2, 2, 2]),
        indices=np.array([0, 1]),
        weights=np.ones((2, 3), np.float32),
    )
    return face, op


@pytest.fixture(scope="module")
def working():
    probes = select.probe_devices()
    if not any(p.ok for p in probes):
        pytest.skip("no working OpenCL device (install pocl-opencl-icd)")
    return probes


def run_py(code: str, **env: str) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter (OpenCL platforms are fixed per process)."""
    full = {**os.environ, **env}
    return subprocess.run(
        [sys.executable, "-c", code], env=full, capture_output=True, text=True, timeout=120
    )


def test_probe_lists_devices_and_auto_picks_a_working_one(working):
    face, op = tiny_face()
    d = make_deformer(face, op, "auto")
    assert d.name.startswith("opencl:")
    first_ok = next(p for p in working if p.ok)
    assert d.name == f"opencl:{first_ok.name}"
    assert make_deformer(face, op, "numpy").name == "numpy"


def test_device_by_index_and_by_name(working):
    p = next(p for p in working if p.ok)
    assert select.default_context(p.key).devices[0].name.strip() == p.name
    assert select.default_context(str(working.index(p))).devices[0].name.strip() == p.name
    assert select.default_context(str(len(working))) is None
    assert select.default_context(p.name[:5].upper()).devices[0].name.strip() == p.name


def test_unknown_device_falls_back_or_raises(working):
    face, op = tiny_face()
    assert select.default_context("no-such-device-xyz") is None
    assert isinstance(make_deformer(face, op, "auto", device="no-such-device-xyz"), NumpyDeformer)
    with pytest.raises(FacecastError, match="no-such-device-xyz"):
        make_deformer(face, op, "opencl", device="no-such-device-xyz")
    with pytest.raises(FacecastError):
        make_deformer(face, op, "cuda")


FALLBACK = """
import logging, numpy as np
logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
from facecast.server.backends import make_deformer
from facecast.server.faces.face import Face
from facecast.server.deform.operator import Operator
v = np.eye(3, dtype=np.float32); face = Face("t", v, np.array([[0, 1, 2]], np.int32))
op = Operator(3, 1, indptr=np.array([0, 1, 1, 1]), indices=np.array([0]), weights=np.ones((1, 3), np.float32))
names = [make_deformer(face, op, "auto").name for _ in range(3)]
d = make_deformer(face, op, "auto")
out = d.deform(np.ones((1, 3), np.float32), np.tile(np.eye(3, 4, dtype=np.float32), (4, 1, 1)))
print("NAMES", names, out[0].tolist())
try:
    make_deformer(face, op, "opencl")
except Exception as e:
    print("OPENCL-ERROR", type(e).__name__, e)
"""


def _check_fallback(proc: subprocess.CompletedProcess) -> None:
    assert proc.returncode == 0, proc.stderr
    assert "NAMES ['numpy', 'numpy', 'numpy'] [2.0, 1.0, 1.0]" in proc.stdout
    assert "OPENCL-ERROR FacecastError" in proc.stdout
    # NumPy is announced exactly once, however many deformers are made.
    assert proc.stderr.count("using NumPy") == 1, proc.stderr


def test_without_any_opencl_platform_facecast_runs_on_numpy(tmp_path):
    _check_fallback(run_py(FALLBACK, OCL_ICD_VENDORS=str(tmp_path)))


def test_device_that_fails_to_build_is_skipped(working, tmp_path):
    """PoCL rejects the extra build flag, so the probe kernel fails to build on the real device."""
    proc = run_py(
        FALLBACK,
        POCL_EXTRA_BUILD_FLAGS="-Werror=no-such-warning-flag",
        POCL_CACHE_DIR=str(tmp_path / "pocl"),
        POCL_KERNEL_CACHE="0",
    )
    _check_fallback(proc)
    assert "INVALID_BUILD_OPTIONS" in proc.stderr or "build" in proc.stderr.lower()


def test_info_reports_backend_and_devices(working):
    proc = subprocess.run(
        [sys.executable, "-m", "facecast.server.cli", "info", "--json"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    info = json.loads(proc.stdout)
    assert info["backend"] == "opencl"
    assert info["device"]["name"] == next(p for p in working if p.ok).name
    assert any(d["ok"] for d in info["devices"])


def test_info_without_opencl_says_numpy(tmp_path):
    env = {**os.environ, "OCL_ICD_VENDORS": str(tmp_path)}
    proc = subprocess.run(
        [sys.executable, "-m", "facecast.server.cli", "info"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert "backend: numpy (no working OpenCL device)" in proc.stdout
    proc = subprocess.run(
        [sys.executable, "-m", "facecast.server.cli", "info", "--backend", "opencl"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2


@pytest.mark.slow
def test_pocl_caches_kernels_under_the_facecast_cache(working, tmp_path):
    """With POCL_CACHE_DIR unset, PoCL's compiled kernels land in cache_dir("pocl")."""
    proc = run_py(
        "from facecast.server.backends.select import probe_devices; import os; probe_devices();"
        "print(os.environ['POCL_CACHE_DIR'])",
        FACECAST_CACHE=str(tmp_path),
        POCL_CACHE_DIR="",
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == str(tmp_path / "pocl")
    assert any(p.is_file() for p in (tmp_path / "pocl").rglob("*"))
