"""The live server's batched frame encoding: the same bytes as the protocol's one-frame encoders."""

from __future__ import annotations

import numpy as np
from websockets.frames import Frame, Opcode

from facecast.protocol import frames as fr
from facecast.server.live.batcher import encode_batch


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
