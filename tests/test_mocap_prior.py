"""The mocap face prior: bounded shape fit, virtual controls, the per-vertex channel, trust, folds,
render and live."""

from __future__ import annotations

import json

import numpy as np
import pytest

from facecast.server.errors import InputError
from facecast.server.faces.face import Face
from facecast.server.mocap.prior import (
    ExpressionBasis,
    ExpressionPrior,
    fit_weights,
    load_basis,
    mirror_map,
)
from facecast.server.mocap.variants import family, fold_protocol
from facecast.server.state import Animation


def test_fit_weights_recovers_bounded_weights():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(60, 8))
    w = rng.uniform(0.0, 1.0, (5, 8))
    w[0, 2] = 1.6  # outside the bounds: the fit stops at 1
    gram = a.T @ a
    got = fit_weights(gram, (w @ a.T) @ a, float(np.linalg.eigvalsh(gram)[-1]), iters=3000)
    assert np.allclose(got[1:], w[1:], atol=1e-4)
    assert got.min() >= 0.0 and got.max() <= 1.0 and got[0, 2] == pytest.approx(1.0)


NAMES = [
    "PupilDilate_L",
    "browDown_L",
    "browDown_R",
    "eyeBlink_L",
    "jawOpen",
    "mouthLeft",
    "mouthRight",
    "mouthSmile_L",
    "mouthSmile_R",
    "cheekPuff_L",
]


def test_strict_folds_keep_held_out_families_out_of_the_prior():
    folds = fold_protocol(NAMES, "strict", 3)
    assert sorted(np.concatenate([h for h, _ in folds])) == list(range(1, len(NAMES)))
    for held, known in folds:
        assert not set(held) & set(known)
        assert not {family(NAMES[i]) for i in held} & {family(NAMES[i]) for i in known}


def test_mirror_folds_hold_one_side_and_keep_the_other():
    for held, known in fold_protocol(NAMES, "mirror"):
        assert len(held) == 3 and not set(held) & set(known)
        for i in held:  # the other side is in the prior
            assert any(family(NAMES[j]) == family(NAMES[i]) for j in known)


@pytest.fixture(scope="module")
def ict(ict_head):
    """``(face, names, deltas, markers, anchors)``: the ICT head, its shapes, the issue16 layout's
    face markers and their anchors."""
    from facecast.server.mocap.rig import anchor_vertices
    from facecast.server.mocap.variants import VARIANTS, choose_layout

    face, names, deltas = ict_head
    _, verts, _, stable = choose_layout(face, deltas, VARIANTS["issue16"])
    markers = verts[len(stable) :]
    return face, names, deltas, markers, anchor_vertices(face, markers)


def test_ict_is_mirror_symmetric(ict):
    face = ict[0]
    m = mirror_map(face)
    assert m is not None
    skin = face.part("skin")
    assert np.mean(m[m[skin]] == skin) > 0.95


def test_shapes_the_prior_knows_reach_the_virtual_controls(ict):
    face, names, deltas, markers, anchors = ict
    basis = ExpressionBasis(names[2:20], deltas[2:20])
    prior = ExpressionPrior(face, basis, markers, anchors, mirror=False, n_virtual=200)
    assert not np.isin(prior.vertices, np.r_[markers, anchors]).any()
    w = np.zeros(len(prior.shapes))
    w[[1, 5]] = [0.7, 0.4]
    d = np.einsum("e,ekc->kc", w, prior.shapes[:, markers])[None]
    virtual, trust = prior.virtual(d)
    want = np.einsum("e,enc->nc", w, prior.shapes[:, prior.vertices])
    assert trust[0] == 1.0
    err = np.linalg.norm(virtual[0] - want, axis=1).mean() * face.mm_per_unit
    assert err < 0.05 * np.linalg.norm(want, axis=1).mean() * face.mm_per_unit + 1e-3


def test_motion_the_shapes_cannot_explain_falls_back_to_the_markers_own(ict):
    face, names, deltas, markers, anchors = ict
    prior = ExpressionPrior(
        face, ExpressionBasis(names[2:20], deltas[2:20]), markers, anchors, n_virtual=100
    )
    rows = np.random.default_rng(0).uniform(0, 1, (prior.n_virtual, len(markers), 3))
    prior.set_interpolation(rows)
    d = np.random.default_rng(1).normal(0, 0.1, (1, len(markers), 3))  # no expression's pattern
    virtual, trust = prior.virtual(d)
    assert trust[0] == 0.0
    assert np.allclose(virtual[0], np.einsum("nkc,kc->nc", rows, d[0]), atol=1e-5)


def test_basis_sources(ict, tmp_path):
    face, names, deltas = ict[:3]
    auto = load_basis(face, "auto")
    assert auto is not None and auto.names == names
    path = ExpressionBasis(names[:3], deltas[:3]).save(tmp_path / "b.npz")
    assert load_basis(face, path).names == names[:3]
    np.savez(tmp_path / "bad.npz", names=np.array(["a"]), deltas=np.zeros((1, 10, 3)))
    with pytest.raises(InputError, match="vertices"):
        load_basis(face, tmp_path / "bad.npz")
    with pytest.raises(InputError, match="prior must be"):
        load_basis(face, tmp_path / "missing.npz")
    from facecast.server.faces import load_face

    assert load_basis(load_face("default"), "auto") is None  # the built-in head has no shapes


def test_render_with_the_prior_beats_the_engine_on_mirrored_shapes(ict, tmp_path):
    """A take blending left-side shapes; the prior knows only their right sides (mirrored)."""
    from facecast.server.cli import main
    from facecast.server.mocap.variants import make_take

    face, names, deltas = ict[:3]
    held, known = fold_protocol(names, "mirror")[0]
    tr = make_take(
        "issue16", tmp_path, seed=2, seconds=0.6, fps=60, expressions=held, face=face,
        formats=("trc",),
    )  # fmt: skip
    basis = ExpressionBasis([names[i] for i in known], deltas[known]).save(tmp_path / "p.npz")
    truth = tr.posed(face, deltas)
    skin = face.part("skin")
    errs = {}
    for prior in ("off", str(basis)):
        out = tmp_path / "out.npz"
        argv = ["render", str(tr.paths["trc"]), "--layout", str(tr.paths["layout"])]
        argv += ["--face", str(face.name), "--prior", prior, "-o", str(out)]
        assert main(argv) == 0
        with np.load(out) as z:
            errs[prior] = np.linalg.norm(z["vertices"][:, skin] - truth[:, skin], axis=2).mean()
    assert errs[str(basis)] < 0.95 * errs["off"]


def test_live_driver_drives_the_channel(ict, tmp_path):
    from facecast.server.mocap.io import read_take
    from facecast.server.mocap.live import MarkerLiveDriver
    from facecast.server.mocap.variants import make_take

    face = ict[0]
    tr = make_take("technician", tmp_path, seed=1, seconds=1.2, fps=60, face=face, formats=("trc",))
    layout = json.loads(tr.paths["layout"].read_text())
    take = read_take(tr.paths["trc"], default_units=layout["units"])
    drv = MarkerLiveDriver(face, take.names, layout, fps=60.0, prior="auto")
    before = drv.control_vertices.copy()
    states = [s for i, f in enumerate(take.xyz) for s in drv.push(f, i / 60.0)]
    assert states and np.array_equal(drv.control_vertices, before)
    assert len(before) == len(drv.rig.control) + drv.prior.n_virtual + len(drv.rig.anchor_vertices)
    assert all(s.controls.shape == (len(before), 3) for s in states)
    assert all(s.shapes is drv.prior.channel for s in states)
    assert all(s.offsets() is None or np.isfinite(s.offsets()).all() for s in states)
    assert max(np.abs(s.shape_weights).max() for s in states) > 0


def test_live_markers_move_toward_the_fit_where_the_shapes_explain_them(ict, tmp_path, monkeypatch):
    """The live path has no look-ahead to clean the markers' noise (0.5 mm): where the prior's
    shapes explain a frame, its marker displacements move toward the fitted shapes' own
    (``live.TOWARD_FIT``), closer to the true skin motion at the markers than the filtered markers
    are (mirror folds of issue16 and technician, live: 0.897 -> 0.855x of not deforming)."""
    from facecast.server.mocap import live
    from facecast.server.mocap.io import read_take
    from facecast.server.mocap.variants import make_take

    face, _, deltas = ict[:3]
    tr = make_take("technician", tmp_path, seed=2, seconds=1.0, fps=60, face=face, formats=("trc",))
    layout = json.loads(tr.paths["layout"].read_text())
    take = read_take(tr.paths["trc"], default_units=layout["units"])
    errs = {}
    for amount in (None, live.TOWARD_FIT):
        monkeypatch.setattr(live, "TOWARD_FIT", amount)
        drv = live.MarkerLiveDriver(face, take.names, layout, fps=60.0, prior="auto")
        got, frames = [], []
        for i, f in enumerate(take.xyz):
            for s in drv.push(f, i / 60.0):
                got.append(s.controls[: len(drv.prior.markers)])
                frames.append(i)
        truth = np.einsum(
            "te,evc->tvc", tr.weights[frames], deltas[tr.expressions][:, drv.prior.markers]
        )
        errs[amount] = float(np.linalg.norm(np.stack(got) - truth, axis=2).mean())
    assert errs[live.TOWARD_FIT] < 0.9 * errs[None]


def _exact_fit(ict):
    """Markers moved exactly by three known shapes, a prior without virtual controls and its
    channel against the fp engine: ``(face, prior, truth (V, 3), engine (V, 3): the markers alone
    interpolated, prior.solve of the markers)``."""
    from facecast.server.deform.build import get_operator
    from facecast.server.mocap.prior import apply_operator

    face, names, deltas, markers, anchors = ict
    prior = ExpressionPrior(
        face, ExpressionBasis(names[2:30], deltas[2:30]), markers, anchors, n_virtual=0
    )
    controls = np.r_[markers, anchors].astype(np.int32)
    op = get_operator(face, controls, engine="fp")
    prior.set_channel(op, controls, face)
    w = np.zeros(len(prior.shapes))
    w[[3, 9, 20]] = [0.8, 0.5, 0.6]
    truth = np.einsum("e,evc->vc", w, prior.shapes)
    values = np.zeros((1, len(controls), 3))
    values[0, : len(markers)] = truth[markers]
    engine = apply_operator(op, values)[0]
    return face, prior, truth, engine, prior.solve(truth[markers][None])


def test_channel_carries_the_fitted_shapes_to_every_vertex(ict):
    """Markers moved exactly by known shapes: the engine plus the channel gives the shapes' own
    skin, far closer than the engine interpolating the markers alone (the defect the channel
    mends: the fit reached the output only through a few hundred interpolated points)."""
    face, prior, truth, engine, (virtual, weights) = _exact_fit(ict)
    assert virtual is None and weights.shape == (1, len(prior.shapes))
    out = engine.copy()
    out[prior.channel.vertices] += prior.channel.mix(weights[0])
    skin = face.part("skin")
    mm = face.mm_per_unit
    err = np.linalg.norm(out[skin] - truth[skin], axis=1).mean() * mm
    alone = np.linalg.norm(engine[skin] - truth[skin], axis=1).mean() * mm
    assert err < 0.3 * alone


def test_an_exact_fit_is_barely_shrunk_by_the_ridge(ict):
    """Markers moved exactly by three known shapes: the channel's skin is within a tenth of the
    engine's error alone (0.025 mm against 0.33; the ridge at 0.03 shrank the fit to 0.047 mm)."""
    face, prior, truth, engine, (_, weights) = _exact_fit(ict)
    assert weights is not None
    out = engine.copy()
    out[prior.channel.vertices] += prior.channel.mix(weights[0])
    skin = face.part("skin")
    err = np.linalg.norm(out[skin] - truth[skin], axis=1).mean()
    alone = np.linalg.norm(engine[skin] - truth[skin], axis=1).mean()
    assert err < 0.1 * alone


def test_animator_turns_the_shapes_with_the_head():
    """Per-vertex shapes are added before the rigid transforms: the head pose turns them."""
    from facecast.server.faces import load_face
    from facecast.server.pipeline import Animator
    from facecast.server.state import FaceState, Shapes

    face = load_face("default:2k")
    skin = np.flatnonzero(face.deformable & (face.rigid_group == 0))[:50]
    controls = skin[::10].astype(np.int32)
    anim = Animator(face, backend="numpy", control_vertices=controls)
    deltas = np.random.default_rng(2).normal(0, 0.01, (2, len(skin), 3)).astype(np.float32)
    shapes = Shapes(skin, deltas)
    a = np.radians(20.0)
    head = np.array([[np.cos(a), 0, np.sin(a), 0.1], [0, 1, 0, 0.0], [-np.sin(a), 0, np.cos(a), 0]])
    zero = np.zeros((len(controls), 3), np.float32)
    plain = anim.frame(FaceState(controls=zero, head=head))
    w = np.array([0.5, 0.25], np.float32)
    state = FaceState(controls=zero, head=head, shapes=shapes, shape_weights=w)
    got = anim.frame(state)
    want = plain.copy()
    want[skin] += shapes.mix(w) @ head[:, :3].T.astype(np.float32)
    assert np.allclose(got, want, atol=1e-6)
    assert not np.allclose(got, plain)
    batch = anim.render(Animation(fps=30.0, states=[state, state], control_vertices=controls))
    assert np.allclose(batch, got[None], atol=1e-6)


def test_turn_is_the_rotation_product():
    """``pipeline.turn`` (the channel's head rotation, column by column) is ``p @ R.T``."""
    from facecast.server.pipeline import turn

    rng = np.random.default_rng(5)
    p = rng.normal(size=(1000, 3)).astype(np.float32)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    r = q.astype(np.float32)
    assert np.allclose(turn(p, r), p @ r.T, atol=1e-6)


def test_live_batcher_adds_the_shapes_as_a_render_does():
    """The live deform thread (``live.batcher``) adds each state's shapes: its f32 frames equal
    ``Animator.frame``, singly and in a batch, and differ from the frames without shapes."""
    import asyncio
    from concurrent.futures import ThreadPoolExecutor

    from facecast.protocol import frames as fr
    from facecast.server.faces import load_face
    from facecast.server.live.batcher import DeformBatcher
    from facecast.server.pipeline import Animator
    from facecast.server.state import FaceState, Shapes

    face = load_face("default:2k")
    skin = np.flatnonzero(face.deformable & (face.rigid_group == 0))[:80]
    controls = skin[::10].astype(np.int32)
    anim = Animator(face, backend="numpy", control_vertices=controls)
    shapes = Shapes(skin, np.random.default_rng(4).normal(0, 0.01, (3, len(skin), 3)).astype("f4"))
    rng = np.random.default_rng(5)
    states = [
        FaceState(
            t=i / 30,
            controls=rng.normal(0, 0.002, (len(controls), 3)).astype(np.float32),
            shapes=shapes,
            shape_weights=rng.uniform(0, 1, 3).astype(np.float32),
        )
        for i in range(5)
    ]

    async def go(batcher, batch):
        return await asyncio.gather(
            *(
                batcher.submit(s, seq=i, wall=0.0, encodings=frozenset({"f32"}))
                for i, s in enumerate(batch)
            )
        )

    batcher = DeformBatcher(anim, ThreadPoolExecutor(1))
    for batch in (states[:1], states):
        for i, (encoded, _) in enumerate(asyncio.run(go(batcher, batch))):
            got = fr.decode(encoded["f32"][0]).positions()
            np.testing.assert_allclose(got, anim.frame(batch[i]), atol=1e-6)
            plain = FaceState(t=batch[i].t, controls=batch[i].controls)
            assert not np.allclose(got, anim.frame(plain))


def test_operator_rows_are_the_operators_own_axis_matrices(ict):
    """``rig.operator_rows`` (through ``Operator.axis_matrix``) gives, per axis, each vertex's
    weights on the first n controls, duplicates summed: the same as walking the CSR rows."""
    from facecast.server.deform.build import get_operator
    from facecast.server.mocap.rig import operator_rows

    face, _, _, markers, anchors = ict
    op = get_operator(face, np.r_[markers, anchors].astype(np.int32), engine="fp")
    verts = np.r_[markers[:5], face.part("skin")[::997]]
    n = len(markers)
    want = np.zeros((len(verts), n, 3))
    for i, v in enumerate(verts):  # the CSR rows by hand
        for e in range(op.indptr[v], op.indptr[v + 1]):
            if op.indices[e] < n:
                want[i, op.indices[e]] += op.weights[e]
    got = operator_rows(op, verts, n)
    assert got.shape == want.shape and np.allclose(got, want, rtol=0, atol=1e-12)


def test_a_frame_the_shapes_explain_but_for_noise_keeps_the_prior_fully(ict):
    """A brow raise of 0.3 mm under smoothed marker noise (0.15 mm) leaves a relative fit residual
    of about 0.4: the shapes explain the frame and the channel carries them fully (``TRUST``; at
    (0.3, 0.5) its weights were halved, and on held-out folds the output fell back towards the
    engine's interpolation: mirror folds of issue16 and technician 0.53 -> 0.52x)."""
    face, names, deltas, markers, anchors = ict
    prior = ExpressionPrior(
        face, ExpressionBasis(names[2:30], deltas[2:30]), markers, anchors, n_virtual=0
    )
    w = np.zeros(len(prior.shapes))
    w[prior.names.index("browOuterUp_L")] = 0.5
    d = (w @ prior.shapes[:, markers].reshape(len(w), -1)).astype(np.float64)
    a = prior.shapes[:, markers].reshape(len(w), -1).T.astype(np.float64)  # (3K, E)
    off = np.random.default_rng(0).normal(size=d.shape)
    off -= a @ np.linalg.lstsq(a, off, rcond=None)[0]  # what no shape explains
    noisy = d + 0.4 * np.linalg.norm(d) * off / np.linalg.norm(off)
    fitted, beta = prior.fit(noisy.reshape(1, -1, 3))
    assert beta[0] == 1.0
    assert np.linalg.norm(a @ fitted[0] - d) < 0.3 * np.linalg.norm(d)  # the brow, near enough


def _sheet(n: int = 21) -> tuple[Face, ExpressionBasis]:
    """A flat ``n x n`` sheet of skin (mm) and two smooth shapes on it (a brow-like band moving
    out, a mouth-like band moving up)."""
    g = np.linspace(-50.0, 50.0, n)
    x, y = np.meshgrid(g, g)
    verts = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], axis=1).astype(np.float32)
    i = np.arange(n - 1)
    a = (i[:, None] * n + i[None, :]).ravel()
    tris = np.concatenate([np.stack([a, a + 1, a + n], 1), np.stack([a + 1, a + n + 1, a + n], 1)])
    face = Face("sheet", verts, tris.astype(np.int32), units="mm", parts={"skin": np.arange(n * n)})
    deltas = np.zeros((2, n * n, 3), np.float32)
    deltas[0, :, 2] = 4.0 * np.exp(-((verts[:, 1] - 20.0) ** 2) / 400.0)
    deltas[1, :, 1] = 3.0 * np.exp(-((verts[:, 1] + 25.0) ** 2) / 300.0)
    return face, ExpressionBasis(["a", "b"], deltas)


def test_batch_markers_move_to_the_fit_where_the_shapes_explain_them():
    """``rig.toward_fit``: noisy markers of a known blend move to the fitted shapes' positions
    (their noise no longer reaches the skin); markers the shapes do not explain stay as they are."""
    from facecast.server.mocap.rig import toward_fit

    face, basis = _sheet()
    markers = np.arange(0, face.n_vertices, 7)
    prior = ExpressionPrior(face, basis, markers, mirror=False)
    rng = np.random.default_rng(5)
    clean = np.einsum("te,emc->tmc", rng.uniform(0.3, 1.0, (6, 2)), basis.deltas[:, markers])
    noisy = clean + rng.normal(0.0, 0.2, clean.shape)
    prior.fit(noisy)
    moved = toward_fit(noisy, prior, (0.3, 0.6))
    before = np.linalg.norm(noisy - clean, axis=2).mean()
    assert np.linalg.norm(moved - clean, axis=2).mean() < 0.3 * before
    other = rng.normal(0.0, 2.0, clean.shape)  # nothing the shapes span
    prior.fit(other)
    assert np.array_equal(toward_fit(other, prior, (0.3, 0.6)), other)
