"""The vectorised FAP rig (``FapRig.solve_batch``): the same bits as the plain one-state reference,
whatever the batch, and the live batcher's use of it (a bad state fails alone)."""

from __future__ import annotations

import asyncio
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from facecast.protocol import frames as fr
from facecast.server.errors import InputError
from facecast.server.faces import load_face
from facecast.server.live.batcher import DeformBatcher
from facecast.server.mpeg4 import FapRig
from facecast.server.mpeg4 import rig as rig_mod
from facecast.server.state import FaceState, zero_faps

#: FAPs the rig turns into rigid transforms or special terms (jaw, eyes, tongue roll, head).
_SPECIAL = [3, 14, 15, 23, 24, 25, 26, 27, 28, 47, 48, 49, 50]


@pytest.fixture(scope="module")
def face():
    return load_face("default:2k")


def _random_states(rng, n: int, *, head_every: int = 0) -> list[FaceState]:
    out = []
    for i in range(n):
        faps = zero_faps()
        k = rng.choice(np.arange(3, 69), size=int(rng.integers(0, 30)), replace=False)
        faps[k] = rng.normal(0.0, 400.0, size=len(k))
        special = rng.choice(_SPECIAL, size=4, replace=False)
        faps[special] = rng.normal(0.0, 3000.0, size=4) * (rng.random(4) < 0.7)
        if i % 9 == 0:
            faps[3] = 0.0  # a closed jaw: no rotation at all
        s = FaceState(t=i / 60, faps=faps)
        if i % 5 == 1:
            s.viseme = (
                int(rng.integers(0, 15)),
                int(rng.integers(0, 15)),
                int(rng.integers(0, 64)),
            )
        if i % 7 == 2:
            s.expression = (
                int(rng.integers(0, 7)),
                int(rng.integers(0, 64)),
                int(rng.integers(0, 7)),
                int(rng.integers(0, 64)),
            )
        if head_every and i % head_every == 3:
            q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
            s.head = np.c_[q, rng.normal(size=3)]
        out.append(s)
    return out


def solve_reference(rig: FapRig, state: FaceState) -> tuple[np.ndarray, np.ndarray]:
    """``rig.solve`` of one state, written plainly: the reference ``solve_batch`` matches bit for
    bit, up to the sign of a zero; 10x slower per state than ``solve_batch`` in batches of 20."""
    faps = rig.faps(state)
    local = rig.local_transforms(faps)
    H = rig.head_transform(state, faps)
    transforms = np.stack([H] + [rig_mod.compose(H, local[g]) for g in range(1, rig_mod.G)])
    if rig.explicit:
        if state.controls is None:
            D = np.zeros((rig.n_controls, 3), dtype=np.float32)
        else:
            D = np.asarray(state.controls, dtype=np.float32).reshape(rig.n_controls, 3)
        return D, transforms.astype(np.float32)
    D = rig._M @ faps
    if len(rig._jaw_riders):
        J = local[rig_mod._JAW]
        D[rig._jaw_riders] += rig._rider_pos @ J[:, :3].T + J[:, 3] - rig._rider_pos
    ids, arms = rig._roll
    if len(ids) and faps[47]:
        D[ids, 1] += np.tan(faps[47] * rig.fapu["AU"]) * arms
    return D.astype(np.float32), transforms.astype(np.float32)


def _assert_rows_equal_reference(rig: FapRig, states: list[FaceState]) -> None:
    D, T = rig.solve_batch(states)
    assert D.shape == (len(states), rig.n_controls, 3) and D.dtype == np.float32
    assert T.shape == (len(states), 4, 3, 4) and T.dtype == np.float32
    for i, s in enumerate(states):
        d, t = solve_reference(rig, s)
        np.testing.assert_array_equal(D[i], d, err_msg=f"D of state {i}")
        np.testing.assert_array_equal(T[i], t, err_msg=f"transforms of state {i}")


def test_solve_batch_equals_the_reference_bit_for_bit(face, rng):
    rig = FapRig(face)
    states = _random_states(rng, 150, head_every=4)
    _assert_rows_equal_reference(rig, states)
    D, T = rig.solve_batch(states)
    assert np.abs(D).max() > 1 and not np.allclose(T[:, 1], T[:, 0])  # the states did move things


def test_solve_batch_equals_the_reference_on_the_ict_head_with_real_fap_files(data_dir):
    from facecast.server.drivers import load_animation

    face = load_face(data_dir / "ict-facekit" / "generic_neutral_mesh.obj")
    rig = FapRig(face)
    files = sorted((data_dir / "xface" / "faps").glob("*.fap"))[:4]
    assert files
    states = [s for f in files for s in load_animation(f, face).states]
    _assert_rows_equal_reference(rig, states)


def test_per_axis_and_explicit_control_rigs(face, rng):
    states = _random_states(rng, 40)
    _assert_rows_equal_reference(FapRig(face, per_axis=True), states)
    verts = face.part("skin")[:6]
    rig = FapRig(face, control_vertices=verts)
    for i, s in enumerate(states):
        if i % 2:
            s.controls = rng.normal(size=(6, 3)).astype(np.float32)
    _assert_rows_equal_reference(rig, states)
    D, _ = rig.solve_batch(states)
    assert not D[0].any() and np.array_equal(D[1], states[1].controls)


def test_a_row_does_not_depend_on_the_rest_of_the_batch(face, rng):
    rig = FapRig(face)
    states = _random_states(rng, 33, head_every=5)
    D, T = rig.solve_batch(states)
    for a, b in [(0, 1), (5, 6), (3, 20), (0, 33)]:
        d, t = rig.solve_batch(states[a:b])
        np.testing.assert_array_equal(d, D[a:b])
        np.testing.assert_array_equal(t, T[a:b])
    d, t = rig.solve(states[7])
    np.testing.assert_array_equal(d, D[7])
    np.testing.assert_array_equal(t, T[7])


def test_solve_batch_refuses_invalid_states(face):
    rig = FapRig(face)
    with pytest.raises(InputError, match="viseme id 20"):
        rig.solve_batch([FaceState(), FaceState(viseme=(20, 0, 0))])
    with pytest.raises(ValueError, match="69"):
        rig.solve_batch([FaceState(faps=np.zeros(12))])
    D, T = rig.solve_batch([])
    assert D.shape == (0, rig.n_controls, 3) and T.shape == (0, 4, 3, 4)


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")
def test_batcher_fails_a_bad_state_alone_and_renders_the_others_exactly(face, rng):
    from facecast.server.pipeline import Animator

    animator = Animator(face, backend="numpy")
    states = _random_states(rng, 6)
    states[2] = FaceState(t=0.1, viseme=(20, 0, 0))  # invalid viseme id
    states[4].faps[3] = 1e308  # overflows to inf in the rig: the deformer would refuse the batch

    pool = ThreadPoolExecutor(1)

    async def go():
        batcher = DeformBatcher(animator, pool)
        return await asyncio.gather(
            *(
                batcher.submit(s, seq=i, wall=0.0, encodings=frozenset({"f32"}))
                for i, s in enumerate(states)
            ),
            return_exceptions=True,
        )

    results = asyncio.run(go())
    assert isinstance(results[2], InputError) and isinstance(results[4], InputError)
    for i in (0, 1, 3, 5):
        encoded, seconds = results[i]
        frame = fr.decode(encoded["f32"][0])
        assert frame.header.seq == i and seconds >= 0
        np.testing.assert_array_equal(frame.positions(), animator.frame(states[i]))


def test_a_coalescing_batcher_waits_for_the_other_sessions_frame(face, rng, monkeypatch):
    import facecast.server.live.batcher as batcher_mod
    from facecast.server.pipeline import Animator

    monkeypatch.setattr(batcher_mod, "ACTIVE_WINDOW", 60.0)
    animator = Animator(face, backend="numpy")
    states = _random_states(rng, 4)

    class Session:  # the batcher tells sessions apart by their bound ``done`` methods
        def __init__(self) -> None:
            self.results: list = []
            self.arrived = asyncio.Event()

        def done(self, result) -> None:
            self.results.append(result)
            self.arrived.set()

    pool = ThreadPoolExecutor(1)

    async def go():
        batcher = DeformBatcher(animator, pool)
        batcher.coalesce = (
            30.0  # longer than the test: only the second session's frame ends the wait
        )
        a, b = Session(), Session()
        enc = frozenset({"f32"})
        batcher.submit_nowait(states[0], seq=0, wall=0.0, encodings=enc, done=a.done)
        batcher.submit_nowait(states[1], seq=1, wall=0.0, encodings=enc, done=b.done)
        await asyncio.wait_for(asyncio.gather(a.arrived.wait(), b.arrived.wait()), 60)
        a.arrived.clear()
        b.arrived.clear()
        first = batcher.batches  # (1 or 2: the drain may start before the second submit)
        batcher.submit_nowait(states[2], seq=2, wall=0.0, encodings=enc, done=a.done)
        await asyncio.sleep(0.3)  # a drain that did not wait would deform frame 2 alone now
        assert not a.arrived.is_set()
        batcher.submit_nowait(states[3], seq=3, wall=0.0, encodings=enc, done=b.done)
        await asyncio.wait_for(asyncio.gather(a.arrived.wait(), b.arrived.wait()), 60)
        n = batcher.batches
        batcher.coalesce = 0.0  # the drain waits for the next round: one more, unwaited, ends it
        a.arrived.clear()
        b.arrived.clear()
        batcher.submit_nowait(states[0], seq=4, wall=0.0, encodings=enc, done=a.done)
        batcher.submit_nowait(states[1], seq=5, wall=0.0, encodings=enc, done=b.done)
        await asyncio.wait_for(asyncio.gather(a.arrived.wait(), b.arrived.wait()), 60)
        a.results.pop()
        b.results.pop()
        return batcher, a, b, first, n

    batcher, a, b, first, n = asyncio.run(go())
    pool.shutdown(wait=False)
    for thread in list(pool._threads):  # no drain outlives the test (it held pytest's exit)
        thread.join(30)
        assert not thread.is_alive()
    assert n == first + 1 and batcher.frames == 6  # frames 2 and 3: one batch
    got = [fr.decode(r[0]["f32"][0]) for r in a.results + b.results]
    assert sorted(f.header.seq for f in got) == [0, 1, 2, 3]


def test_a_coalescing_batcher_waits_for_coalesce_frames_at_most(face, rng, monkeypatch):
    """``LiveSettings.coalesce_frames``: with three sessions active and a target of 2 frames, a
    batch goes as soon as two frames wait (it does not wait for the third session's)."""
    import facecast.server.live.batcher as batcher_mod
    from facecast.server.live.settings import LiveSettings
    from facecast.server.pipeline import Animator

    monkeypatch.setattr(batcher_mod, "ACTIVE_WINDOW", 600.0)
    animator = Animator(face, backend="numpy")
    states = _random_states(rng, 5)
    settings = LiveSettings(coalesce_ms=600_000.0, coalesce_frames=2)  # only frames end a wait

    class Session:
        def __init__(self) -> None:
            self.arrived = asyncio.Event()

        def done(self, result) -> None:
            self.arrived.set()

    pool = ThreadPoolExecutor(1)

    async def go() -> DeformBatcher:
        batcher = DeformBatcher(animator, pool, settings=settings)
        assert batcher.coalesce_frames == 2
        a, b, c = Session(), Session(), Session()
        enc = frozenset({"f32"})
        for k, s in enumerate((a, b, c)):  # all three active
            batcher.submit_nowait(states[k], seq=k, wall=0.0, encodings=enc, done=s.done)
        await asyncio.wait_for(asyncio.gather(*(s.arrived.wait() for s in (a, b, c))), 60)
        a.arrived.clear()
        b.arrived.clear()
        batcher.submit_nowait(states[3], seq=3, wall=0.0, encodings=enc, done=a.done)
        batcher.submit_nowait(states[4], seq=4, wall=0.0, encodings=enc, done=b.done)
        await asyncio.wait_for(asyncio.gather(a.arrived.wait(), b.arrived.wait()), 60)
        # the drain now waits (up to the 10 minutes) for the next round: without waits, one more
        # round ends it, so no thread outlives the test (it held pytest's exit for minutes)
        batcher.coalesce = 0.0
        a.arrived.clear()
        c.arrived.clear()
        batcher.submit_nowait(states[0], seq=5, wall=0.0, encodings=enc, done=a.done)
        batcher.submit_nowait(states[1], seq=6, wall=0.0, encodings=enc, done=c.done)
        await asyncio.wait_for(asyncio.gather(a.arrived.wait(), c.arrived.wait()), 60)
        return batcher

    batcher = asyncio.run(go())
    assert batcher.frames == 7
    pool.shutdown(wait=False)
    for thread in list(pool._threads):
        thread.join(30)
        assert not thread.is_alive()
    assert (
        DeformBatcher(animator, None, settings=LiveSettings(coalesce_frames=99)).coalesce_frames
        == 32
    )
