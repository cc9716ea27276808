"""int16 quantisation on the OpenCL device (live frames): the same bits as the NumPy path."""

from __future__ import annotations

import numpy as np
import pytest
from websockets.frames import Frame, Opcode

from facecast.protocol import frames as fr
from facecast.protocol.quantize import dequantize_int16, quantize_int16
from facecast.server.backends.opencl import ALIGN, DeviceQuantizer, aligned_empty
from facecast.server.live.batcher import encode_batch

cl_backend = pytest.importorskip("facecast.server.backends.opencl")

pytestmark = pytest.mark.opencl


@pytest.fixture(scope="module")
def quantizer() -> DeviceQuantizer:
    ctx = cl_backend.default_context()
    if ctx is None:
        pytest.skip("no working OpenCL device (install pocl-opencl-icd)")
    return DeviceQuantizer(ctx)


def _frames(rng, n: int, v: int) -> np.ndarray:
    """``(n, v, 3)`` float32 frames of different extents and centres per frame and axis."""
    scale = rng.uniform(0.01, 300.0, size=(n, 1, 3))
    centre = rng.uniform(-500.0, 500.0, size=(n, 1, 3))
    return (rng.normal(size=(n, v, 3)) * scale + centre).astype(np.float32)


@pytest.mark.parametrize(
    ("n", "v"), [(1, 1), (3, 7), (2, 16), (4, 17), (2, 255), (5, 1000), (2, 4099)]
)
def test_device_quantisation_equals_numpy_bit_for_bit(quantizer, rng, n, v):
    verts = _frames(rng, n, v)
    q, offset, scale = quantizer.quantize(verts)
    assert q.shape == (n, v, 3) and q.dtype == np.int16
    for i in range(n):
        q0, o0, s0 = quantize_int16(verts[i])
        np.testing.assert_array_equal(offset[i], o0)
        np.testing.assert_array_equal(scale[i], s0)
        np.testing.assert_array_equal(q[i], q0)
        err = np.abs(dequantize_int16(q[i], offset[i], scale[i]) - verts[i])
        ulp = np.spacing(np.abs(verts[i]).max(axis=0))  # float32 rounding of the positions
        assert (err <= s0 / 2 + 4 * ulp).all()  # half a step


def test_flat_axis_and_extreme_values(quantizer):
    v = np.zeros((2, 40, 3), np.float32)
    v[0, :, 0] = np.linspace(-1e6, 1e6, 40)  # y and z constant: scale 1e-12, q 0
    v[1] = 7.5
    v[1, 3] = [7.5, -3e4, 2e-3]
    q, offset, scale = quantizer.quantize(v)
    for i in range(2):
        q0, o0, s0 = quantize_int16(v[i])
        np.testing.assert_array_equal(q[i], q0)
        np.testing.assert_array_equal(offset[i], o0)
        np.testing.assert_array_equal(scale[i], s0)
    assert q[0, :, 0].min() == -32767 and q[0, :, 0].max() == 32767


def test_halves_round_to_even(quantizer):
    """offset 0 and scale 1 exactly (bounds -32767, 32767), so ``k + 0.5`` values are ties."""
    halves = np.array(
        [0.5, 1.5, 2.5, -0.5, -1.5, -2.5, 32766.5, -32766.5, 100.5, 101.5], np.float32
    )
    v = np.zeros((1, 50, 3), np.float32)  # 50: three 16-vertex units, then a tail of 2
    v[0, 0], v[0, 1] = -32767.0, 32767.0
    v[0, 48], v[0, 49] = 2.5, -32766.5
    v[0, 2 : 2 + len(halves)] = halves[:, None]
    v[0, 30 : 30 + len(halves)] = -halves[:, None]
    q, _, _ = quantizer.quantize(v)
    q0, o0, s0 = quantize_int16(v[0])
    assert (o0 == 0).all() and (s0 == 1).all()
    np.testing.assert_array_equal(q[0], q0)
    assert q[0, 2, 0] == 0 and q[0, 3, 0] == 2 and q[0, 4, 0] == 2 and q[0, 8, 0] == 32766
    assert q[0, 48, 0] == 2 and q[0, 49, 0] == -32766


def test_quantize_into_writes_only_its_frames(quantizer, rng):
    verts = aligned_empty((3, 50, 3), np.float32)
    verts[...] = _frames(rng, 3, 50)
    stride, start = 400, 22
    out = aligned_empty((start + 3 * stride,), np.uint8)
    out[...] = 0xAB
    offset, _ = quantizer.quantize_into(verts, out, start, stride)
    written = np.zeros(out.shape, bool)
    for i in range(3):
        a = start + i * stride
        q = out[a : a + 300].view("<i2").reshape(50, 3)
        q0, o0, _ = quantize_int16(verts[i])
        np.testing.assert_array_equal(q, q0)
        np.testing.assert_array_equal(offset[i], o0)
        written[a : a + 300] = True
    assert (out[~written] == 0xAB).all()


def test_quantize_into_checks_its_buffers(quantizer):
    verts = aligned_empty((2, 10, 3), np.float32)
    verts[...] = 1.0
    out = aligned_empty((200,), np.uint8)
    quantizer.quantize_into(verts, out, 0, 100)  # 2 frames of 60 bytes at 0 and 100: fits
    with pytest.raises(ValueError):
        quantizer.quantize_into(verts, out, 0, 160)  # the second frame would end past the buffer
    with pytest.raises(ValueError):
        quantizer.quantize_into(verts, out, 1, 100)  # odd start: int16 data must be aligned
    misaligned = np.empty(2 * 10 * 3 + 1, np.float32)
    m = misaligned[1:] if misaligned.ctypes.data % ALIGN == 0 else misaligned[:-1]
    with pytest.raises(ValueError):
        quantizer.quantize_into(m.reshape(2, 10, 3), out, 0, 60)


def test_encode_batch_on_the_device_gives_the_protocol_bytes(quantizer, rng):
    v = aligned_empty((4, 700, 3), np.float32)
    v[...] = _frames(rng, 4, 700)
    jobs = [
        (7, 0.5, 1700000000.25, frozenset({"i16"})),
        (8, 0.6, 1700000000.5, frozenset({"f32", "i16"})),
        (9, 0.7, 0.0, frozenset({"f32"})),  # no int16 for this one: frames are picked out
        (4294967295, 0.8, 1.0, frozenset({"i16"})),
    ]
    device = encode_batch(v, jobs, quantizer)
    host = encode_batch(v, jobs)
    for i, (seq, t, wall, encodings) in enumerate(jobs):
        assert set(device[i]) == set(encodings)
        for e in encodings:
            payload, framed = device[i][e]
            want = fr.encode_vertices(v[i], e, seq=seq, t=t, wall=wall)
            assert bytes(payload) == want == bytes(host[i][e][0])
            assert bytes(framed) == Frame(Opcode.BINARY, want).serialize(mask=False)


def test_batcher_quantises_on_the_device_and_falls_back_to_numpy(quantizer, rng, monkeypatch):
    import asyncio
    from concurrent.futures import ThreadPoolExecutor

    import facecast.server.live.batcher as batcher_mod
    from facecast.server.faces import load_face
    from facecast.server.live.batcher import DeformBatcher
    from facecast.server.pipeline import Animator
    from facecast.server.state import FaceState, zero_faps

    monkeypatch.setattr(batcher_mod, "DEVICE_MIN_FRAMES", 1)  # every batch on the device
    animator = Animator(load_face("default:2k"), backend="opencl")
    states = []
    for i in range(6):
        faps = zero_faps()
        faps[[3, 5, 12, 13, 19]] = rng.normal(0.0, 300.0, size=5)
        states.append(FaceState(t=i / 60, faps=faps))

    def fail(*args, **kwargs):
        raise RuntimeError("device lost")

    async def go(batcher):
        return await asyncio.gather(
            *(
                batcher.submit(s, seq=i, wall=0.0, encodings=frozenset({"i16", "f32"}))
                for i, s in enumerate(states)
            )
        )

    batcher = DeformBatcher(animator, ThreadPoolExecutor(1))
    assert batcher.quantizer is not None  # a zero-copy OpenCL deformer: quantised on the device
    rounds = [asyncio.run(go(batcher))]
    monkeypatch.setattr(batcher.quantizer, "quantize_into", fail)  # later batches: NumPy
    rounds.append(asyncio.run(go(batcher)))
    assert batcher.quantizer is None
    for results in rounds:
        for i, (encoded, _) in enumerate(results):
            f32 = fr.decode(encoded["f32"][0])
            np.testing.assert_array_equal(f32.positions(), animator.frame(states[i]))
            want = fr.encode_vertices(f32.positions(), "i16", seq=i, t=states[i].t, wall=0.0)
            assert bytes(encoded["i16"][0]) == want
