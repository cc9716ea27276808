"""The compact encoder's shared per-thread scratch: sessions whose frames interleave on one
thread, or spread over several, get exactly the bytes each session's encoder gives alone."""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from typing import ClassVar

import numpy as np
import pytest

from facecast.protocol.compact import CompactDecoder, CompactEncoder
from facecast.server.faces import load_face
from facecast.server.pipeline import Animator
from facecast.server.state import FaceState, zero_faps


@pytest.fixture(scope="module")
def face():
    return load_face("default:2k")


def _stream(face, session: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` frames ``(n, V, 3)`` and transforms ``(n, G, 3, 4)``: jaw, lips and a head turn."""
    states = []
    for i in range(n):
        faps = zero_faps()
        t = i / 60
        faps[3] = 300 + 300 * math.sin(2 * math.pi * (0.5 + 0.2 * session) * t)
        faps[5] = 150 * math.sin(2 * math.pi * 1.3 * t + session)
        faps[48] = 2000 * math.sin(2 * math.pi * 0.3 * t + session)
        states.append(FaceState(t=t, faps=faps))
    a = Animator(face, backend="numpy")
    D, T = a.solve_batch(states)
    return np.stack([a.deformer.deform(d, tr) for d, tr in zip(D, T)]).astype(np.float32), T


@pytest.mark.parametrize("threads", [1, 3])
def test_interleaved_sessions_encode_as_alone(face, threads):
    tol = 0.1 / face.mm_per_unit
    n_sessions, n = 4, 20
    streams = [_stream(face, s, n) for s in range(n_sessions)]

    def encoder() -> CompactEncoder:
        return CompactEncoder(face.vertices, face.rigid_group, tolerance=tol, key_interval=6)

    alone = []
    for vs, ts in streams:
        e = encoder()
        alone.append([e.encode(v, t, seq=i, t=i / 60) for i, (v, t) in enumerate(zip(vs, ts))])
    live = [encoder() for _ in range(n_sessions)]
    got: list[list[bytes]] = [[] for _ in range(n_sessions)]
    with ThreadPoolExecutor(threads) as pool:
        for i in range(n):  # one frame of every session per round, on any of the threads

            def one(s: int, i: int = i) -> bytes:
                vs, ts = streams[s]
                return live[s].encode(vs[i], ts[i], seq=i, t=i / 60)

            for s, data in enumerate(pool.map(one, range(n_sessions))):
                got[s].append(data)
    assert got == alone
    for s, (vs, _) in enumerate(streams):
        dec = CompactDecoder(face.vertices, face.rigid_group)
        for v, data in zip(vs, got[s]):
            out = dec.decode(data)
            assert out is not None
            assert np.linalg.norm(out[1].astype(np.float64) - v, axis=1).max() <= tol


# -- residual planes on the OpenCL device (backends/opencl/compact.py) -------------------------


@pytest.fixture(scope="module", params=["native", "portable"])
def device(request):
    """The kernel as built for this device (AVX-512 compress and mask tests where the device
    has them) and with its portable code only: both must give the host encoder's bytes."""
    cl_backend = pytest.importorskip("facecast.server.backends.opencl")
    ctx = cl_backend.default_context()
    if ctx is None:
        pytest.skip("no working OpenCL device (install pocl-opencl-icd)")
    from facecast.server.backends.opencl.compact import WG, DeviceCompact

    if request.param == "native":
        return DeviceCompact(ctx)

    class Portable(DeviceCompact):
        DEFINES: ClassVar[dict[str, object]] = {"WG": WG, "COMPACT_PORTABLE": 1}

    return Portable(ctx)


def _fap_stream(face, data_dir) -> tuple[np.ndarray, np.ndarray]:
    """The Xface joy FAP file rendered on ``face``: ``(T, V, 3)`` frames, ``(T, G, 3, 4)`` poses."""
    from facecast.server.drivers import load_animation

    anim = load_animation(data_dir / "xface" / "faps" / "joy.fap", face)
    anim.states = anim.states[:40]
    a = Animator(face, backend="numpy", control_vertices=anim.control_vertices)
    _, tr = a.solve_batch(anim.states)
    return np.asarray(a.render(anim), np.float32), tr


def _blas_fuses() -> bool:
    """Whether NumPy's float32 matmul rounds as the device kernel does (OpenBLAS on x86-64 with
    FMA: a fused multiply-add chain); elsewhere the device's frames are as valid but may differ
    from the host encoder's in a rounding tie, so only their decoded error is checked."""
    rng = np.random.default_rng(5)
    m = (rng.standard_normal((3, 4)) * 400).astype(np.float32)
    vt = np.ones((4, 4096), np.float32)
    vt[:3] = rng.standard_normal((3, 4096)) * 0.1
    got = np.matmul(m, vt)
    a, b = m.astype(np.float64), vt.astype(np.float64)

    def fma(x, y, z):  # exact product and sum in float64, one rounding (a double rounding is rare)
        return (x * y + z).astype(np.float32).astype(np.float64)

    c = fma(a[:, 1:2], b[1], (a[:, 0:1] * b[0]).astype(np.float32).astype(np.float64))
    c = fma(a[:, 3:4], b[3], fma(a[:, 2:3], b[2], c))
    return bool((c.astype(np.float32) == got).all())


def _device_vs_host(
    device, face, frames: np.ndarray, poses: np.ndarray, sessions: int = 3, pool=None
):
    """Each of ``sessions`` sessions (the stream from another start) encoded by the device, a
    batch per round, and by the host encoder: the same bytes (where the BLAS rounds as the
    device does), decoded within tolerance."""
    exact = _blas_fuses()
    from facecast.server.backends.opencl import aligned_empty
    from facecast.server.backends.opencl.compact import encode_batch

    tol = 0.1 / face.mm_per_unit
    kw = {"tolerance": tol, "key_interval": 7}
    host = [CompactEncoder(face.vertices, face.rigid_group, **kw) for _ in range(sessions)]
    dev = [CompactEncoder(face.vertices, face.rigid_group, **kw) for _ in range(sessions)]
    decs = [CompactDecoder(face.vertices, face.rigid_group) for _ in range(sessions)]
    buf = aligned_empty((sessions,) + frames.shape[1:], np.float32)
    n = len(frames)
    for i in range(n):
        idx = [(i + 5 * s) % n for s in range(sessions)]
        buf[:] = frames[idx]
        want = [host[s].encode(buf[s], poses[idx[s]], seq=i, t=i / 25) for s in range(sessions)]
        got = encode_batch(
            device,
            buf,
            [(dev[s], s, poses[idx[s]], i, i / 25, 0.0) for s in range(sessions)],
            pool,
        )
        if exact:
            assert got == want, f"frame {i}"
        for s in range(sessions):
            out = decs[s].decode(got[s])
            assert out is not None
            err = np.linalg.norm(out[1].astype(np.float64) - buf[s], axis=1).max()
            assert err <= tol


@pytest.mark.opencl
@pytest.mark.parametrize("face_name", ["default:2k", "default"])
def test_device_residuals_give_the_host_encoders_bytes_on_a_fap_stream(device, data_dir, face_name):
    face = load_face(face_name)
    frames, poses = _fap_stream(face, data_dir)
    _device_vs_host(device, face, frames, poses)


@pytest.mark.opencl
def test_device_frames_deflated_half_on_a_pool_are_the_same(device, face):
    frames, poses = _stream(face, 1, 20)
    with ThreadPoolExecutor(2) as pool:
        _device_vs_host(device, face, frames, poses, sessions=5, pool=pool)


@pytest.mark.opencl
def test_device_handles_odd_vertex_counts_large_motions_and_bad_frames(device, face):
    from facecast.server.backends.opencl import aligned_empty
    from facecast.server.backends.opencl.compact import encode_batch

    if not _blas_fuses():
        pytest.skip("NumPy's matmul rounds otherwise here: the bytes may differ in a tie")
    frames, poses = _stream(face, 0, 12)
    keep = len(face.vertices) - len(face.vertices) % 16 - 5  # a count that is not a multiple of 16
    rest, groups = face.vertices[:keep], face.rigid_group[:keep]
    frames = frames[:, :keep].copy()
    frames[6:9, 100:300] += 50 * 0.1 / face.mm_per_unit * 2**10  # residuals over 16 bits
    tol = 0.1 / face.mm_per_unit
    host = CompactEncoder(rest, groups, tolerance=tol, key_interval=4)
    dev = CompactEncoder(rest, groups, tolerance=tol, key_interval=4)
    buf = aligned_empty((1, keep, 3), np.float32)
    for i in range(len(frames)):
        buf[0] = frames[i]
        if i == 10:
            buf[0, 7] = np.nan  # a bad frame: refused alone, the encoder's state kept
        (got,) = encode_batch(device, buf, [(dev, 0, poses[i], i, i / 60, 0.0)])
        try:
            want: bytes | ValueError = host.encode(buf[0], poses[i], seq=i, t=i / 60)
        except ValueError as e:
            want = e
        if isinstance(want, ValueError):
            assert isinstance(got, ValueError) and str(got) == str(want)
        else:
            assert got == want, f"frame {i}"


@pytest.mark.opencl
def test_device_batch_refuses_only_the_frames_whose_transforms_are_not_rigid(device, face):
    """The batch's transforms are checked at once: a frame with a scaled, NaN or short set of
    transforms gets its encoder's ``ValueError`` alone; the others, the host encoder's bytes."""
    from facecast.server.backends.opencl import aligned_empty
    from facecast.server.backends.opencl.compact import encode_batch

    frames, poses = _stream(face, 0, 6)
    tol = 0.1 / face.mm_per_unit
    n = 5
    host = [CompactEncoder(face.vertices, face.rigid_group, tolerance=tol) for _ in range(n)]
    dev = [CompactEncoder(face.vertices, face.rigid_group, tolerance=tol) for _ in range(n)]
    buf = aligned_empty((n,) + frames.shape[1:], np.float32)
    for i in range(len(frames)):
        buf[:] = frames[i]
        trs = [poses[i].astype(np.float32).copy() for _ in range(n)]
        if i in (2, 4):
            trs[1][0, :, :3] *= 1.01  # not a rigid motion
            trs[3][-1, 0, 3] = np.nan
        if i == 3:
            trs[2] = trs[2][:1]  # too few groups: the encoder says so
        got = encode_batch(device, buf, [(dev[s], s, trs[s], i, i / 60, 0.0) for s in range(n)])
        for s in range(n):
            try:
                want: bytes | ValueError = host[s].encode(buf[s], trs[s], seq=i, t=i / 60)
            except ValueError as e:
                want = e
            if isinstance(want, ValueError):
                assert isinstance(got[s], ValueError) and str(got[s]) == str(want)
            elif _blas_fuses():
                assert got[s] == want, f"frame {i}, session {s}"
            else:
                assert isinstance(got[s], bytes)
        assert sum(isinstance(g, ValueError) for g in got) == {2: 2, 3: 1, 4: 2}.get(i, 0)


@pytest.mark.opencl
@pytest.mark.parametrize("n_vertices", [37, 1000, 1003])
def test_device_bitmaps_and_values_equal_the_hosts_two_planes_and_short_runs(
    device, face, n_vertices
):
    """Format 2 on the device: the per-axis bitmaps and the non-zero values the work-items compact
    (some with no units at all when V < 16 WG, the last with the tail) are the host encoder's,
    also for frames whose values need two bytes."""
    from facecast.server.backends.opencl import aligned_empty
    from facecast.server.backends.opencl.compact import encode_batch

    if not _blas_fuses():
        pytest.skip("NumPy's matmul rounds otherwise here: the bytes may differ in a tie")
    frames, poses = _stream(face, 0, 8)
    rest, groups = face.vertices[:n_vertices], face.rigid_group[:n_vertices]
    frames = frames[:, :n_vertices].copy()
    tol = 0.1 / face.mm_per_unit
    frames[2:5, n_vertices // 3 : n_vertices // 2] += 300 * 1.2 * tol  # ~300 cells: two planes
    host = CompactEncoder(rest, groups, tolerance=tol, key_interval=3)
    dev = CompactEncoder(rest, groups, tolerance=tol, key_interval=3)
    buf = aligned_empty((1, n_vertices, 3), np.float32)
    planes = set()
    for i in range(len(frames)):
        buf[0] = frames[i]
        (got,) = encode_batch(device, buf, [(dev, 0, poses[i], i, i / 60, 0.0)])
        assert got == host.encode(buf[0], poses[i], seq=i, t=i / 60), f"frame {i}"
        assert isinstance(got, bytes)
        planes.add(got[41])
    assert planes == {1, 2}


@pytest.mark.opencl
def test_batcher_encodes_compact_frames_on_the_device_as_alone(device, face, monkeypatch):
    from facecast.server.live import batcher as batcher_mod
    from facecast.server.live.batcher import DeformBatcher, _Job
    from facecast.server.live.settings import LiveSettings

    if not _blas_fuses():
        pytest.skip("NumPy's matmul rounds otherwise here: the bytes may differ in a tie")
    animator = Animator(face, backend="opencl")
    batcher = DeformBatcher(animator, None, settings=LiveSettings())  # type: ignore[arg-type]
    if batcher.quantizer is None:
        pytest.skip("the OpenCL deformer does not share host memory")
    calls = []
    real = batcher_mod._encode_compact_device
    monkeypatch.setattr(
        batcher_mod, "_encode_compact_device", lambda *a: calls.append(1) or real(*a)
    )
    tol = 0.1 / face.mm_per_unit
    n_sessions, n = batcher_mod.DEVICE_COMPACT_MIN_FRAMES, 10

    def encoder() -> CompactEncoder:
        return CompactEncoder(face.vertices, face.rigid_group, tolerance=tol, key_interval=4)

    live = [encoder() for _ in range(n_sessions)]
    alone = [encoder() for _ in range(n_sessions)]
    enc = frozenset({"compact", "i16"})
    for i in range(n):
        states = []
        for s in range(n_sessions):
            faps = zero_faps()
            faps[3] = 300 + 300 * math.sin(2 * math.pi * (0.5 + 0.2 * s) * i / 60)
            faps[48] = 2000 * math.sin(2 * math.pi * 0.3 * i / 60 + s)
            states.append(FaceState(t=i / 60, faps=faps))
        jobs = [_Job(st, i, 0.0, enc, None, None, live[s]) for s, st in enumerate(states)]  # type: ignore[arg-type]
        results = batcher._work(jobs)
        D, T = animator.solve_batch(states)
        for s, (encoded, _) in enumerate(results):
            payload, framed = encoded["compact"]
            assert bytes(framed).endswith(bytes(payload))
            want = np.asarray(animator.deformer.deform(D[s], T[s]), np.float32)
            assert bytes(payload) == alone[s].encode(want, T[s], seq=i, t=i / 60)
    assert len(calls) == n


@pytest.mark.opencl
def test_device_reference_pool_serves_many_sessions_in_changing_batches(face):
    """More sessions than the device's reference slots (16 at first), in batches of changing
    members and sizes: slots are reused and the pool grows, and every frame is still encoded
    against its own session's reference (the host encoder's bytes)."""
    from facecast.server.backends.opencl import aligned_empty, default_context
    from facecast.server.backends.opencl.compact import DeviceCompact, encode_batch

    if not _blas_fuses():
        pytest.skip("NumPy's matmul rounds otherwise here: the bytes may differ in a tie")
    device = DeviceCompact(default_context())  # a fresh pool
    frames, poses = _stream(face, 0, 24)
    tol = 0.1 / face.mm_per_unit
    sessions = 24

    def encoders() -> list[CompactEncoder]:
        kw = {"tolerance": tol, "key_interval": 3}
        return [CompactEncoder(face.vertices, face.rigid_group, **kw) for _ in range(sessions)]

    host, dev = encoders(), encoders()
    seq = [0] * sessions
    rng = np.random.default_rng(2)
    for r in range(10):
        members = sorted(rng.choice(sessions, size=(4, 9, 20)[r % 3], replace=False))
        buf = aligned_empty((len(members),) + frames.shape[1:], np.float32)
        idx = [(seq[s] + 3 * s) % len(frames) for s in members]
        buf[:] = frames[idx]
        want = [
            host[s].encode(buf[k], poses[idx[k]], seq=seq[s], t=seq[s] / 60)
            for k, s in enumerate(members)
        ]
        got = encode_batch(
            device,
            buf,
            [(dev[s], k, poses[idx[k]], seq[s], seq[s] / 60, 0.0) for k, s in enumerate(members)],
        )
        assert got == want, f"round {r}"
        for s in members:
            seq[s] += 1
