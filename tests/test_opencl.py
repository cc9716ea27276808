"""The OpenCL backend reproduces the NumPy reference (float32 tolerance) on a real OpenCL device."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from facecast.protocol.quantize import dequantize_int16, quantize_int16
from facecast.server.backends import NumpyDeformer
from facecast.server.deform.operator import Operator
from facecast.server.errors import InputError

cl_backend = pytest.importorskip("facecast.server.backends.opencl")

pytestmark = pytest.mark.opencl


@pytest.fixture(scope="module")
def ctx():
    c = cl_backend.default_context()
    if c is None:
        pytest.skip("no working OpenCL device (install pocl-opencl-icd)")
    return c


def random_transforms(rng, n_groups: int = 4, lead: tuple = ()) -> np.ndarray:
    """Rigid transforms ``lead + (G, 3, 4)``: random rotations (QR) and translations."""
    out = np.zeros(lead + (n_groups, 3, 4), np.float32)
    for idx in np.ndindex(*lead, n_groups):
        q, r = np.linalg.qr(rng.standard_normal((3, 3)))
        out[idx][:, :3] = q * np.sign(np.diag(r))
        out[idx][:, 3] = rng.standard_normal(3) * 5
    return out


def assert_close(a: np.ndarray, b: np.ndarray, scale: float) -> None:
    """Equal within float32 rounding of values of magnitude ``scale`` (a few hundred ulps)."""
    assert np.isfinite(b).all(), "the reference itself is not finite"
    np.testing.assert_allclose(a, b, rtol=0, atol=scale * 2e-6 + 1e-6, equal_nan=False)


def random_sparse(rng, V: int, K: int, max_row: int = 9, per_axis: bool = True) -> Operator:
    lengths = rng.integers(0, min(max_row, K) + 1, size=V)
    indptr = np.r_[0, np.cumsum(lengths)]
    indices = np.concatenate([np.sort(rng.choice(K, n, replace=False)) for n in lengths]).astype(
        np.int32
    )
    w = rng.random((indptr[-1], 3)).astype(np.float32)
    if not per_axis:
        w[:, 1] = w[:, 2] = w[:, 0]
    return Operator(V, K, indptr=indptr, indices=indices, weights=w)


def unpack_dense(p) -> np.ndarray:
    """``(V, K, 3) float32`` dense weights read back from packed operator ``p``'s layout."""
    K, A, S = p.n_controls, p.axes, p.slice
    out = np.zeros((p.n_padded, K + 1, 3), np.float32)
    w = p.weights.reshape(-1, A, S)
    for s in range(p.n_padded // S):
        lanes = np.arange(S) + S * s
        if p.dense:
            cols, ids = s * K + np.arange(K), np.arange(K)[:, None].repeat(S, 1)
        else:
            c0, c1 = int(p.col_ptr[s]), int(p.col_ptr[s + 1])
            i0, i1 = int(p.id_ptr[s]), int(p.id_ptr[s + 1])
            cols = np.arange(c0, c1)
            ids = p.ids[i0:i1].astype(np.int64)
            ids = ids[:, None].repeat(S, 1) if i1 - i0 == c1 - c0 else ids.reshape(-1, S)
        for j, c in enumerate(cols):
            for a in range(3):
                np.add.at(out, (lanes, ids[j], a), w[c, min(a, A - 1)])
    return out[: p.n_vertices, :K]


def random_mesh(rng, V: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rest = (rng.standard_normal((V, 3)) * 80).astype(np.float32)
    tri = rng.integers(0, V, size=(2 * V, 3)).astype(np.int32)
    groups = rng.integers(0, 4, size=V).astype(np.uint8)
    groups[:3] = [0, 1, 3][:V]  # the last group is present (when V > 2)
    return rest, tri, groups


def check_all(cl_def, ref: NumpyDeformer, rng, scale: float) -> None:
    """deform, displacements, batch and normals agree with the reference for random D."""
    K = ref.n_controls
    for _ in range(2):
        D = (rng.standard_normal((K, 3)) * scale / 50).astype(np.float32)
        T = random_transforms(rng)
        assert_close(cl_def.deform(D, T), ref.deform(D, T), scale)
        assert_close(cl_def.displacements(D), ref.displacements(D), scale)
    Db = (rng.standard_normal((3, K, 3)) * scale / 50).astype(np.float32)
    Tb = random_transforms(rng, lead=(3,))
    batch = cl_def.deform_batch(Db, Tb)
    assert batch.shape == (3, ref.n_vertices, 3)
    assert_close(batch, ref.deform_batch(Db, Tb), scale)
    v = ref.deform(Db[0], Tb[0])
    np.testing.assert_allclose(cl_def.normals(v), ref.normals(v), atol=2e-5)


@pytest.mark.parametrize("V", [1, 13, 1000])
@pytest.mark.parametrize("per_axis", [True, False])
def test_sparse_matches_numpy(ctx, rng, V, per_axis):
    rest, tri, groups = random_mesh(rng, V)
    op = random_sparse(rng, V, 40, per_axis=per_axis)
    d = cl_backend.OpenCLDeformer(rest, tri, groups, op, context=ctx)
    assert d.packed.axes == (3 if per_axis else 1)
    check_all(d, NumpyDeformer(rest, tri, groups, op), rng, 80)


def test_dense_matches_numpy(ctx, rng):
    rest, tri, groups = random_mesh(rng, 333)
    op = Operator(333, 21, dense=rng.standard_normal((333, 21)).astype(np.float32))
    d = cl_backend.OpenCLDeformer(rest, tri, groups, op, context=ctx)
    assert d.packed.dense
    check_all(d, NumpyDeformer(rest, tri, groups, op), rng, 80)


def test_many_controls_use_wider_ids(ctx, rng):
    rest, tri, groups = random_mesh(rng, 500)
    op = random_sparse(rng, 500, 300)
    d = cl_backend.OpenCLDeformer(rest, tri, groups, op, context=ctx)
    assert d.packed.ids.dtype == np.uint16
    check_all(d, NumpyDeformer(rest, tri, groups, op), rng, 80)


@pytest.mark.parametrize("dense", [False, True])
def test_float8_slices_match_too(ctx, rng, dense):
    rest, tri, groups = random_mesh(rng, 37)
    op = (
        Operator(37, 9, dense=rng.standard_normal((37, 9)).astype(np.float32))
        if dense
        else random_sparse(rng, 37, 9)
    )
    d = cl_backend.OpenCLDeformer(rest, tri, groups, op, context=ctx, slice_size=8)
    assert d.packed.slice == 8
    check_all(d, NumpyDeformer(rest, tri, groups, op), rng, 80)


def test_copying_readback_path_matches(ctx, rng):
    rest, tri, groups = random_mesh(rng, 200)
    op = random_sparse(rng, 200, 30)
    d = cl_backend.OpenCLDeformer(rest, tri, groups, op, context=ctx, zero_copy=False)
    check_all(d, NumpyDeformer(rest, tri, groups, op), rng, 80)


def test_rigid_parts_move_as_rigid_bodies(ctx, rng):
    """With D = 0 each vertex is its group's transform of its rest position."""
    rest, tri, groups = random_mesh(rng, 257)
    op = random_sparse(rng, 257, 10)
    d = cl_backend.OpenCLDeformer(rest, tri, groups, op, context=ctx)
    T = random_transforms(rng)
    out = d.deform(np.zeros((10, 3), np.float32), T)
    expect = np.einsum("vij,vj->vi", T[groups, :, :3], rest) + T[groups, :, 3]
    assert_close(out, expect, 80)


def test_out_parameter_receives_the_frame(ctx, rng):
    rest, tri, groups = random_mesh(rng, 64)
    op = random_sparse(rng, 64, 8)
    d = cl_backend.OpenCLDeformer(rest, tri, groups, op, context=ctx)
    D = rng.standard_normal((8, 3)).astype(np.float32)
    T = random_transforms(rng)
    out = np.full((64, 3), np.nan, np.float32)
    assert d.deform(D, T, out=out) is out
    assert_close(out, NumpyDeformer(rest, tri, groups, op).deform(D, T), 80)
    with pytest.raises(ValueError):
        d.deform(D, T, out=np.empty((64, 3), np.float64))
    with pytest.raises(ValueError):
        d.deform(D, T[:2])
    with pytest.raises(InputError, match="finite"):
        d.deform(np.full((8, 3), np.nan, np.float32), T)


@pytest.mark.parametrize("V", [1000, 1003])
def test_streaming_stores_match(ctx, rng, monkeypatch, V):
    """Large launches write with non-temporal stores (forced here for a small mesh): same results,
    also into a misaligned ``out`` and for batches whose frames are not 32-byte aligned (V = 1003),
    where the ordinary kernel must be used instead."""
    monkeypatch.setattr(cl_backend.deformer, "STREAM_FRACTION", 0.0)
    rest, tri, groups = random_mesh(rng, V)
    op = random_sparse(rng, V, 40)
    d = cl_backend.OpenCLDeformer(rest, tri, groups, op, context=ctx)
    if not d._cache_bytes:
        pytest.skip("not a CPU device with a reported cache size")
    ref = NumpyDeformer(rest, tri, groups, op)
    D = (rng.standard_normal((40, 3)) * 2).astype(np.float32)
    T = random_transforms(rng)
    assert d._streams(1)
    assert_close(d.deform(D, T), ref.deform(D, T), 80)
    raw = np.zeros(3 * V + 1, np.float32)
    skew = raw[1:] if raw.ctypes.data % 32 == 0 else raw[:-1]
    out = skew.reshape(V, 3)
    if out.ctypes.data % 32:
        assert not d._streams(1, out)
    assert_close(d.deform(D, T, out=out), ref.deform(D, T), 80)
    Db = (rng.standard_normal((3, 40, 3)) * 2).astype(np.float32)
    Tb = random_transforms(rng, lead=(3,))
    assert d._streams(3) == (V % 8 == 0)
    assert_close(d.deform_batch(Db, Tb), ref.deform_batch(Db, Tb), 80)
    d.upload_frame(D, T)
    d.run_kernel_resident(wait=True)
    assert_close(d.read_resident(), ref.deform(D, T), 80)


def test_device_quantised_frame_equals_protocol_quantisation(ctx, rng):
    """A deformed frame quantised on the device is ``protocol.quantize`` of it, bit for bit, so
    within half a step per axis of the NumPy reference."""
    rest, tri, groups = random_mesh(rng, 777)
    op = random_sparse(rng, 777, 33)
    d = cl_backend.OpenCLDeformer(rest, tri, groups, op, context=ctx)
    ref = NumpyDeformer(rest, tri, groups, op)
    D = rng.standard_normal((33, 3)).astype(np.float32)
    T = random_transforms(rng)
    v = d.deform_batch(D[None], T[None])
    q, offset, scale = cl_backend.DeviceQuantizer(ctx).quantize(v)
    assert q.dtype == np.int16 and q.shape == (1, 777, 3)
    q2, o2, s2 = quantize_int16(v[0])
    np.testing.assert_array_equal(q[0], q2)
    np.testing.assert_array_equal(offset[0], o2)
    np.testing.assert_array_equal(scale[0], s2)
    err = np.abs(dequantize_int16(q[0], offset[0], scale[0]) - ref.deform(D, T))
    assert np.all(err <= s2 / 2 + 80 * 2e-6 + 1e-6)


@pytest.mark.parametrize("per_axis", [True, False])
def test_pack_operator_keeps_every_entry(rng, per_axis):
    """The device layout, read back on the host, is the operator (pure NumPy; no device)."""
    op = random_sparse(rng, 100, 17, per_axis=per_axis)
    p = cl_backend.pack_operator(op)
    D = rng.standard_normal((op.n_controls, 3)).astype(np.float32)
    np.testing.assert_allclose(np.einsum("vka,ka->va", unpack_dense(p), D), op.apply(D), atol=1e-5)


def test_neighbours_sharing_controls_share_columns(rng):
    """Slices whose vertices use the same controls store one id per column, not eight."""
    V, K = 64, 10
    indptr = np.arange(V + 1) * 3
    indices = np.tile([1, 4, 7], V)
    op = Operator(
        V, K, indptr=indptr, indices=indices, weights=rng.random((3 * V, 3)).astype(np.float32)
    )
    p = cl_backend.pack_operator(op)
    assert p.shared_fraction == 1.0
    assert p.ids.size == 3 * (V // cl_backend.SLICE)
    D = rng.standard_normal((K, 3)).astype(np.float32)
    np.testing.assert_allclose(np.einsum("vka,ka->va", unpack_dense(p), D), op.apply(D), atol=1e-5)


# ---------------------------------------------------------------- real heads and real engines
def _engine_case(face, engine: str, ctx, rng) -> None:
    from facecast.server.deform.build import get_operator
    from facecast.server.mpeg4 import fap_controls

    _, vertex_ids, constrained = fap_controls(face)
    op = get_operator(face, vertex_ids, engine=engine, constrained=constrained)
    scale = float(np.abs(face.vertices).max())
    ref = NumpyDeformer(face.vertices, face.triangles, face.rigid_group, op)
    d = cl_backend.OpenCLDeformer(face.vertices, face.triangles, face.rigid_group, op, context=ctx)
    assert d.n_vertices == face.n_vertices and d.n_controls == op.n_controls
    assert d.name.startswith("opencl:")
    check_all(d, ref, rng, scale)


@pytest.mark.parametrize("engine", ["fp", "rbf"])
def test_builtin_head_every_engine(ctx, rng, engine):
    from facecast.server.faces import load_face

    _engine_case(load_face("default:2k"), engine, ctx, rng)


@pytest.mark.slow
@pytest.mark.parametrize("engine", ["fp", "rbf"])
def test_ict_head_every_engine(ctx, rng, data_dir, engine):
    from facecast.server.faces import load_face

    _engine_case(load_face(data_dir / "ict-facekit" / "generic_neutral_mesh.obj"), engine, ctx, rng)


def test_threads_share_a_deformer(ctx, rng):
    """Server sessions may call one deformer from several threads; every frame stays its own."""
    from concurrent.futures import ThreadPoolExecutor

    rest, tri, groups = random_mesh(rng, 500)
    op = random_sparse(rng, 500, 20)
    d = cl_backend.OpenCLDeformer(rest, tri, groups, op, context=ctx)
    ref = NumpyDeformer(rest, tri, groups, op)
    Ds = [(rng.standard_normal((20, 3))).astype(np.float32) for _ in range(24)]
    T = random_transforms(rng)
    with ThreadPoolExecutor(4) as pool:
        outs = list(pool.map(lambda D: d.deform(D, T), Ds))
    for D, out in zip(Ds, outs):
        assert_close(out, ref.deform(D, T), 80)


_THREADS_SCRIPT = """
import glob, os
from facecast.server.backends.select import default_context
if default_context() is None:
    print("no-device")
    raise SystemExit
single = []
for status in glob.glob(f"/proc/{os.getpid()}/task/*/status"):
    for line in open(status):
        if line.startswith("Cpus_allowed_list:") and line.split()[1].isdigit():
            single.append(int(line.split()[1]))
print(os.environ.get("POCL_AFFINITY"), sorted(single))
"""


@pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="reads thread CPU masks from /proc"
)
@pytest.mark.parametrize("preset", [None, "0"])
def test_pocl_worker_threads_are_pinned_unless_the_environment_says(preset):
    """facecast sets POCL_AFFINITY before PoCL starts (a fresh process): PoCL's worker threads run
    one per CPU; a POCL_AFFINITY already in the environment is left alone."""
    env = {k: v for k, v in os.environ.items() if k != "POCL_AFFINITY"}
    if preset is not None:
        env["POCL_AFFINITY"] = preset
    out = subprocess.run(
        [sys.executable, "-c", _THREADS_SCRIPT],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    ).stdout.strip()
    if out == "no-device":
        pytest.skip("no working OpenCL device")
    value, listed = out.split(" ", 1)
    pinned = json.loads(listed)  # the CPU of each thread that may run on one CPU only
    n = os.cpu_count() or 1
    if preset == "0":
        assert value == "0" and (n == 1 or pinned == [])
    elif os.sched_getaffinity(0) == set(range(n)):
        assert value == "1"
        if n > 1:  # one worker per CPU, each on its own
            assert (
                len(pinned) >= 2
                and len(set(pinned)) == len(pinned)
                and set(pinned) <= set(range(n))
            )
    else:  # this process may not run on every CPU: no pinning
        assert value == "None" and pinned == []
