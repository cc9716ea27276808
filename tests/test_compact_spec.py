"""protocol/README.md's VERTICES_COMPACT section is enough to write a decoder: this one is written
from the document alone (plain Python, struct and zlib; it does not import compact.py) and decodes
a recorded stream, skipping frames as a slow viewer does."""

from __future__ import annotations

import math
import struct
import zlib

import numpy as np
from test_protocol_compact import synthetic_stream

from facecast.protocol.compact import CompactEncoder


class SpecDecoder:
    """README.md, section 3, ``VERTICES_COMPACT``, step by step."""

    def __init__(self, rest: list[tuple[float, float, float]], group: list[int]):
        self.rest, self.group = rest, group
        self.key_seq, self.key_q = None, None

    def decode(self, msg: bytes):
        magic, version, kind, flags, seq, count, t, _wall = struct.unpack_from("<4sBBHIIdd", msg, 0)
        assert (magic, version, kind) == (b"FCST", 1, 7) and flags in (0, 1)
        V = count
        assert len(self.rest) == V
        ref, step, G, P, fmt, zlen, K = struct.unpack_from("<IfBBHII", msg, 32)
        assert fmt == 2 and 1 <= P <= 4 and max(self.group) + 1 <= G and K <= 3 * V
        assert len(msg) == 52 + 48 * G + zlen
        transforms = [struct.unpack_from("<12f", msg, 52 + 48 * g) for g in range(G)]
        key = flags & 1
        if key:
            assert ref == seq
            base = [[math.floor(self.rest[i][a] / step + 0.5) for a in range(3)] for i in range(V)]
        elif ref != self.key_seq:
            return None  # wait for the next key frame
        else:
            base = self.key_q
        B = (V + 7) // 8
        z = zlib.decompressobj()
        raw = z.decompress(msg[52 + 48 * G :], 3 * B + P * K)
        assert len(raw) == 3 * B + P * K and z.eof and not z.unused_data
        # the bitmaps: bit i % 8 of byte a B + i // 8; none past V; K set
        n = 3 * V
        u = [0] * n
        c = 0
        for a in range(3):
            for i in range(8 * B):
                if raw[a * B + i // 8] >> (i % 8) & 1:
                    assert i < V
                    w = sum(raw[3 * B + k * K + c] << (8 * k) for k in range(P))
                    assert w != 0
                    u[a * V + i] = w
                    c += 1
        assert c == K
        q = [[0, 0, 0] for _ in range(V)]
        for a in range(3):
            acc = 0
            for i in range(V):
                j = a * V + i
                d = (u[j] >> 1) ^ -(u[j] & 1)
                acc = (acc + d + 2**31) % 2**32 - 2**31  # int32 wrap
                q[i][a] = (base[i][a] + acc + 2**31) % 2**32 - 2**31
        if key:
            self.key_seq, self.key_q = seq, q
        out = []
        for i in range(V):
            m = transforms[self.group[i]]
            p = [q[i][c] * step for c in range(3)]
            out.append(
                [sum(m[4 * b + c] * p[c] for c in range(3)) + m[4 * b + 3] for b in range(3)]
            )
        return seq, t, out


def test_a_decoder_written_from_the_document_decodes_a_recorded_stream():
    rest, groups, frames, transforms = synthetic_stream(n_vertices=400, n_frames=30, seed=5)
    enc = CompactEncoder(rest, groups, tolerance=0.1, key_interval=6)
    recorded = [
        enc.encode(v, tr, seq=1000 + i, t=i / 60)
        for i, (v, tr) in enumerate(zip(frames, transforms))
    ]
    dec = SpecDecoder([tuple(map(float, r)) for r in rest], [int(g) for g in groups])
    shown = 0
    for i, msg in enumerate(recorded):
        if i in (
            2,
            3,
            7,
            13,
            14,
            15,
            16,
            17,
            18,
            19,
        ):  # a slow viewer drops these (13-19: a key too)
            continue
        out = dec.decode(msg)
        if out is None:
            assert i in (20, 21, 22, 23)  # after the missed key at 18, until the key at 24
            continue
        seq, t, vertices = out
        assert seq == 1000 + i and t == i / 60
        err = np.linalg.norm(np.array(vertices) - frames[i].astype(np.float64), axis=1).max()
        assert err <= 0.1
        shown += 1
    assert shown == 30 - 10 - 4
