"""The compact encoder's shared per-thread scratch: sessions whose frames interleave on one
thread, or spread over several, get exactly the bytes each session's encoder gives alone."""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor

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
