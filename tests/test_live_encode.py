"""The live server's batched frame encoding: the same bytes as the protocol's one-frame encoders."""

from __future__ import annotations

import numpy as np
import pytest
from websockets.frames import Frame, Opcode

from facecast.protocol import frames as fr
from facecast.protocol.quantize import quantize_int16
from facecast.server.live.batcher import encode_batch


@pytest.mark.parametrize("n", [1, 255, 256, 257, 2000])
def test_quantize_int16_batch_is_quantize_int16_per_frame(rng, n):
    v = (rng.normal(size=(5, n, 3)) * [40, 60, 20] + [0, 150, 30]).astype(np.float32)
    v[1] *= np.float32(1e-4)  # tiny range
    v[2, :, 1] = 3.0  # flat axis: the minimum scale
    q, offset, scale = fr.quantize_int16_batch(v)
    for i in range(len(v)):
        eq, eo, es = quantize_int16(v[i])
        assert q[i].dtype == np.int16
        np.testing.assert_array_equal(q[i], eq)
        np.testing.assert_array_equal(offset[i], eo)
        np.testing.assert_array_equal(scale[i], es)


def test_encode_batch_frames_match_protocol_encoders(rng):
    v = (rng.normal(size=(3, 700, 3)) * 50).astype(np.float32)
    jobs = [
        (7, 0.5, 1700000000.25, frozenset({"i16"})),
        (8, 0.6, 1700000000.5, frozenset({"f32", "i16"})),
        (9, 0.7, 0.0, frozenset({"f32"})),
    ]
    out = encode_batch(v, jobs)
    for i, (seq, t, wall, encodings) in enumerate(jobs):
        assert set(out[i]) == set(encodings)
        for e in encodings:
            payload, framed = out[i][e]
            want = fr.encode_vertices(v[i], e, seq=seq, t=t, wall=wall)
            assert bytes(payload) == want
            assert bytes(framed) == Frame(Opcode.BINARY, want).serialize(mask=False)
            f = fr.decode(payload)
            assert f.header.seq == seq and f.header.wall == wall
