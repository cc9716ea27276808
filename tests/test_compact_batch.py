"""The live batcher's compact frames: the sessions of one batch encoded on the compact threads
give each session exactly the frames its own encoder gives alone, within tolerance."""

from __future__ import annotations

import math

import numpy as np
import pytest

from facecast.protocol.compact import CompactDecoder, CompactEncoder
from facecast.server.faces import load_face
from facecast.server.live import batcher as batcher_mod
from facecast.server.live.batcher import DeformBatcher, _Job
from facecast.server.live.settings import LiveSettings
from facecast.server.state import FaceState, zero_faps


@pytest.fixture(scope="module")
def face():
    return load_face("default:2k")


def _state(session: int, i: int) -> FaceState:
    faps = zero_faps()
    t = i / 60
    faps[3] = 300 + 300 * math.sin(2 * math.pi * (0.5 + 0.1 * session) * t)  # jaw
    faps[5] = 150 * math.sin(2 * math.pi * 1.3 * t + session)  # lower lip
    faps[48] = 2000 * math.sin(2 * math.pi * 0.3 * t)  # head pitch: a rigid motion
    return FaceState(t=t, faps=faps)


@pytest.mark.parametrize("threads", ["1", "3"])
def test_a_batch_of_compact_sessions_decodes_within_tolerance(face, monkeypatch, threads):
    from facecast.server.pipeline import Animator

    monkeypatch.setattr(batcher_mod, "_compact_pool", None)
    animator = Animator(face, backend="numpy")
    settings = LiveSettings(compact_threads=int(threads))  # FACECAST_LIVE_COMPACT_THREADS
    batcher = DeformBatcher(animator, None, settings=settings)  # type: ignore[arg-type]
    tol = 0.1 / face.mm_per_unit
    n_sessions, n_frames = 5, 12

    def encoder() -> CompactEncoder:
        return CompactEncoder(face.vertices, face.rigid_group, tolerance=tol, key_interval=5)

    live = [encoder() for _ in range(n_sessions)]
    alone = [encoder() for _ in range(n_sessions)]  # the same streams, one frame at a time
    decoders = [CompactDecoder(face.vertices, face.rigid_group) for _ in range(n_sessions)]
    enc = frozenset({"compact"})
    for i in range(n_frames):
        states = [_state(s, i) for s in range(n_sessions)]
        jobs = [_Job(st, i, 0.0, enc, None, None, live[s]) for s, st in enumerate(states)]  # type: ignore[arg-type]
        results = batcher._work(jobs)
        for s, (st, (encoded, _)) in enumerate(zip(states, results)):
            payload, framed = encoded["compact"]
            assert bytes(framed).endswith(bytes(payload))
            D, T = animator.solve_batch([st])
            want = np.asarray(animator.deformer.deform(D[0], T[0]), np.float32)
            assert bytes(payload) == alone[s].encode(want, T[0], seq=i, t=st.t)
            header, got = decoders[s].decode(payload)
            assert header.seq == i
            err = np.linalg.norm(got.astype(np.float64) - want, axis=1).max()
            assert err <= tol
