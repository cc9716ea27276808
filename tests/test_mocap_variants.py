"""Takes unlike facecast's own (``mocap.variants``): files, stable markers that are not, no neutral
hold, a known rigid motion."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from facecast.server.mocap.stabilise import check_stable, matrix_from_euler


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(Rotation.from_matrix(np.einsum("tji,tjk->tik", a, b)).magnitude())


def test_check_stable_names_and_drops_a_marker_that_moves(rng):
    n = 200
    ref = rng.normal(size=(6, 3)) * 60
    r = matrix_from_euler(np.stack([np.sin(np.arange(n) / 20) * 0.2, np.zeros(n), np.zeros(n)], -1))
    local = np.repeat(ref[None], n, 0)
    local[:, 2, 1] += 4.0 * np.sin(np.arange(n) / 7)  # "stable", but on the jaw
    xyz = np.einsum("tij,tmj->tmi", r, local) + rng.normal(0, 0.5, (n, 6, 3))
    names = [f"S{i}" for i in range(6)]
    keep, dropped, added = check_stable(xyz, np.arange(5), names)
    assert dropped == ["S2"] and added == []
    assert sorted(keep.tolist()) == [0, 1, 3, 4]
    # all rigid: nothing dropped
    assert check_stable(xyz, np.array([0, 1, 3, 4]), names)[1] == []
    # three declared, one bad: named, left out, and the most rigid other marker stands in
    keep, dropped, added = check_stable(xyz, np.array([0, 1, 2]), names)
    assert dropped == ["S2"] and len(added) == 1 and sorted(keep.tolist()) != [0, 1, 2]
    # two declared: the marker most rigid with them stands in (never the moving one)
    keep, dropped, added = check_stable(xyz, np.array([0, 1]), names)
    assert len(keep) == 3 and added and added[0] != "S2"


def test_variants_round_trip_through_c3d_trc_and_csv(tmp_path, ict_head):
    from facecast.server.mocap.io import read_take
    from facecast.server.mocap.variants import VARIANTS, make_take

    face = ict_head[0]
    for name, v in VARIANTS.items():
        truth = make_take(v, tmp_path / name, seconds=0.25, fps=60.0, face=face)
        takes = {fmt: read_take(truth.paths[fmt]) for fmt in ("c3d", "trc", "csv")}
        ref = takes["trc"].in_mm()
        assert ref.shape == (15, v.markers, 3), name
        layout = json.loads(truth.paths["layout"].read_text())
        assert len(layout["stable"]) == v.stable and set(layout["markers"]) == set(truth.names)
        for fmt, take in takes.items():
            assert take.names == truth.names, (name, fmt)
            got = take.in_mm()
            assert np.array_equal(np.isnan(got), np.isnan(ref)), (name, fmt)
            assert np.nanmax(np.abs(got - ref)) < 0.01, (name, fmt)  # C3D stores float32


def _process(truth, face, layout=None):
    from facecast.server.mocap.driver import process
    from facecast.server.mocap.io import read_take

    lay = layout or json.loads(truth.paths["layout"].read_text())
    return process(read_take(truth.paths["c3d"], default_units=lay["units"]), face, lay)


@pytest.mark.parametrize("variant", ["issue16", "sparse30"])
def test_a_wrong_stable_marker_is_named_and_left_out(tmp_path, ict_head, variant):
    """issue16: a fifth "stable" marker on the mouth; sparse30: one of three replaced by it."""
    from facecast.server.mocap.variants import make_take

    face, _, deltas = ict_head
    truth = make_take(variant, tmp_path, seconds=1.5, face=face)
    layout = json.loads(truth.paths["layout"].read_text())
    assert _process(truth, face, layout).info["stable_dropped"] == []  # the true ones are rigid
    local = truth.local(face, deltas)[:, truth.vertices]
    motion = np.linalg.norm(local - local.mean(axis=0), axis=2).std(axis=0)
    wrong = truth.names[int(np.argmax(motion))]  # the marker that moves most in this take
    layout["stable"] = (layout["stable"] if variant == "issue16" else layout["stable"][:2]) + [
        wrong
    ]
    proc = _process(truth, face, layout)
    assert proc.info["stable_dropped"] == [wrong]
    assert len(proc.info["stable_added"]) == (0 if variant == "issue16" else 1)
    assert _angle_deg(proc.rig.head_matrix(proc.r, proc.t)[:, :, :3], truth.r).mean() < 0.3


def test_a_take_without_a_neutral_hold_stabilises(tmp_path, ict_head):
    from facecast.server.mocap.variants import make_take

    face = ict_head[0]
    truth = make_take("issue16", tmp_path, seconds=1.5, face=face)  # moves from frame 0
    proc = _process(truth, face)
    head = proc.rig.head_matrix(proc.r, proc.t)
    err = _angle_deg(head[:, :, :3], truth.r)
    assert np.degrees(Rotation.from_matrix(truth.r).magnitude()).max() > 3.0  # the head does move
    assert err[0] < 0.15 and err.mean() < 0.2  # was 0.77 deg on every frame before re-anchoring
    _r, t = truth.head(face)
    np.testing.assert_allclose(head[:, :, 3], t, atol=0.15)  # cm (ICT units): 1.5 mm
    assert 0 < proc.info["pose_frame_sd_deg"] < 1.0
    # the neutral is not averaged over the expression that starts at frame 0 (that left a constant
    # 0.48 mm on every marker's displacement; 0.54 mm mean on this take, 0.37 now)
    deltas = ict_head[2]
    pv = proc.rig.placement.vertices
    got = np.stack([st.controls[: len(pv)] for st in proc.states]) * face.mm_per_unit
    want = (truth.local(face, deltas)[:, pv] - face.vertices[pv]) * face.mm_per_unit
    assert np.linalg.norm(got - want, axis=2).mean() < 0.45


def test_batch_head_poses_refined_in_several_passes_beat_one(tmp_path, ict_head, monkeypatch):
    """``driver.REFINE_PASSES``: the poses refined with every marker again from the last pass's
    poses, neutral and principal motions. Three headband markers (sparse30) leave one pass 0.143 deg
    off on this take; six passes 0.094 (three 0.113)."""
    from facecast.server.mocap import driver
    from facecast.server.mocap.variants import make_take

    face = ict_head[0]
    truth = make_take("sparse30", tmp_path, seed=2, seconds=1.5, face=face, formats=("c3d",))

    def pose_error() -> float:
        proc = _process(truth, face)
        return float(_angle_deg(proc.rig.head_matrix(proc.r, proc.t)[:, :, :3], truth.r).mean())

    several = pose_error()
    monkeypatch.setattr(driver, "REFINE_PASSES", 1)
    assert several < 0.8 * pose_error()


def test_a_late_neutral_with_the_head_turned_keeps_the_start_as_the_heads_rest(tmp_path, ict_head):
    """A fast-expression take whose face passes through neutral late, with the head turned 13.8
    degrees (strict fold 1's expressions): the automatic neutral takes that frame's shape, but the
    head's rest stays frame 0's, the pose squarer to the capture axes (``neutral.rest_frame``).
    Taking the neutral frame's pose as the rest turned every output frame by 13.8 degrees."""
    from facecast.server.mocap.variants import fold_protocol, make_take

    face, names, _ = ict_head
    held = fold_protocol(names, "strict", 3)[1][0]
    truth = make_take(
        "fast-large", tmp_path, seed=2, seconds=2.0, face=face, expressions=held, formats=("c3d",)
    )
    proc = _process(truth, face)
    nf = proc.neutral_frame
    assert nf > 100 and truth.weights[nf].sum() < 0.01  # a neutral, late
    assert np.degrees(Rotation.from_matrix(truth.r[nf]).magnitude()) > 10.0  # the head turned
    err = _angle_deg(proc.rig.head_matrix(proc.r, proc.t)[:, :, :3], truth.r)
    assert err.mean() < 0.3  # 13.8 before


def test_a_neutral_held_at_the_end_with_the_head_at_rest_is_the_heads_rest():
    """``rest_frame`` between the default frame and the automatic neutral: the one whose head is
    squarer to the capture axes (any axes: here Z up), by more than the margin."""
    from facecast.server.mocap.neutral import axis_deviation, rest_frame

    rng = np.random.default_rng(4)
    target = rng.normal(size=(20, 3)) * 5.0
    zup = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    turn = Rotation.from_euler("y", 8.0, degrees=True).as_matrix()
    square = target @ zup.T * 10.0 + 300.0  # mm, 10 mm a face unit
    turned = target @ (zup @ turn).T * 10.0 + 300.0
    assert axis_deviation(square, target) < 1e-6
    assert axis_deviation(turned, target) == pytest.approx(8.0, abs=1e-6)
    raw = np.stack([turned, square, square])
    assert rest_frame(raw, target, nf=2, default=0) == 2  # the neutral's head is square: its own
    raw = np.stack([square, turned, turned])
    assert rest_frame(raw, target, nf=2, default=0) == 0  # the neutral's head turned: the start's
    assert rest_frame(raw, target, nf=0, default=0) == 0


def test_pose_error_of_a_known_rigid_motion_is_below_the_noise_share(tmp_path, ict_head):
    """A rigid head (no expression): the pose error at the face markers is below what the noise
    alone would leave on one frame's markers (0.5 mm per axis), and matches the reported error."""
    from dataclasses import replace

    from facecast.server.mocap.variants import VARIANTS, make_take

    face = ict_head[0]
    v = replace(VARIANTS["issue16"], expr_max=0.0)
    truth = make_take(v, tmp_path, seconds=1.5, face=face, gaps=False)
    proc = _process(truth, face)
    head = proc.rig.head_matrix(proc.r, proc.t)
    mm = face.mm_per_unit
    pts = face.vertices[truth.vertices].astype(np.float64)
    got = np.einsum("tij,pj->tpi", head[:, :, :3], pts) + head[:, None, :, 3]
    r, t = truth.head(face)
    want = np.einsum("tij,pj->tpi", r, pts) + t[:, None]
    err = np.linalg.norm(got - want, axis=2).mean() * mm
    assert err < 0.5 * np.sqrt(3) / 4  # a quarter of the noise's per-marker displacement


def test_live_driver_takes_its_neutral_on_a_take_moving_from_frame_0(tmp_path, ict_head):
    """The live neutral is in the first frame's head pose, the head's motion over the gathered frames
    removed (a plain average left every later pose 0.43 deg off on this take)."""
    from facecast.server.mocap.io import read_take
    from facecast.server.mocap.live import MarkerLiveDriver
    from facecast.server.mocap.variants import make_take

    face = ict_head[0]
    truth = make_take("issue16", tmp_path, seconds=1.5, face=face)
    layout = json.loads(truth.paths["layout"].read_text())
    take = read_take(truth.paths["trc"], default_units=layout["units"])
    drv = MarkerLiveDriver(face, take.names, layout, units=take.units, fps=take.fps)
    heads, frames = [], []
    for i, f in enumerate(take.xyz):
        out = drv.push(f, i / take.fps)
        if out:
            heads.append(out[0].head)
            frames.append(i)
    heads = np.asarray(heads)
    assert len(frames) > 150
    assert _angle_deg(heads[:, :, :3], truth.r[frames]).mean() < 0.3


def _live_heads(drv, take) -> tuple[np.ndarray, list[int]]:
    """``(heads (N, 3, 4), frames)``: the live driver's head of each state it gives for ``take``'s
    frames pushed in turn, and the frame each came from."""
    heads, frames = [], []
    for i, f in enumerate(take.xyz):
        for s in drv.push(f, i / take.fps):
            heads.append(s.head)
            frames.append(i)
    return np.asarray(heads), frames


def test_live_head_pose_uses_the_face_prior(tmp_path, ict_head):
    """With the face's shapes explaining its markers' motion (``stabilise.ShapePose``), every
    marker steadies the live head pose: its error falls well below the stable markers' own."""
    from facecast.server.mocap.io import read_take
    from facecast.server.mocap.live import MarkerLiveDriver
    from facecast.server.mocap.variants import make_take

    face = ict_head[0]
    truth = make_take("issue16", tmp_path, seed=3, seconds=1.0, face=face, formats=("trc",))
    layout = json.loads(truth.paths["layout"].read_text())
    take = read_take(truth.paths["trc"], default_units=layout["units"])
    err = {}
    for prior in ("off", "auto"):
        drv = MarkerLiveDriver(face, take.names, layout, fps=take.fps, prior=prior)
        heads, frames = _live_heads(drv, take)
        err[prior] = _angle_deg(heads[:, :, :3], truth.r[frames]).mean()
    assert err["auto"] < 0.7 * err["off"]


def test_live_takes_the_neutral_again_at_a_later_hold(tmp_path, ict_head):
    """A take that starts on an expression and holds the neutral at its end (``neutral-last``):
    the live driver's first neutral is the expression; after ``neutral.HOLD_S`` of the hold it
    takes the neutral shape again there: the face at rest is still again, and the head goes on
    without a jump (its rest stays the start's)."""
    from facecast.server.mocap.io import read_take
    from facecast.server.mocap.live import MarkerLiveDriver
    from facecast.server.mocap.variants import make_take

    face, _, deltas = ict_head
    truth = make_take("neutral-last", tmp_path, seed=1, seconds=2.0, face=face, formats=("trc",))
    layout = json.loads(truth.paths["layout"].read_text())
    take = read_take(truth.paths["trc"], default_units=layout["units"])
    drv = MarkerLiveDriver(face, take.names, layout, fps=take.fps, prior="off")
    states, frames, retaken = [], [], None
    for i, f in enumerate(take.xyz):
        out = drv.push(f, i / take.fps)
        states += out
        frames += [i] * len(out)
        if drv.retakes and retaken is None:
            retaken = len(states)
    assert drv.retakes == 1 and retaken is not None
    # the markers' true displacements from the face at rest (face units) against the output's
    at = deltas[truth.expressions][:, drv.rig.placement.vertices]  # (E, K, 3)
    want = np.einsum("te,ekc->tkc", truth.weights[frames], at)
    got = np.stack([s.controls[: len(drv.rig.control)] for s in states])
    err = np.linalg.norm(got - want, axis=2).mean(axis=1) * face.mm_per_unit
    after, before = err[retaken:].mean(), err[retaken - 10 : retaken].mean()
    assert after < 0.7 * before  # at rest against the new neutral, not the expression taken first
    heads = np.stack([s.head[:, :3] for s in states[retaken - 3 : retaken + 3]])
    assert _angle_deg(heads[1:], heads[:-1]).max() < 0.5


def test_live_take_starting_with_the_head_turned_renders_it_turned(tmp_path, ict_head):
    """A live take whose head starts turned from the capture axes (``neutral-last``: its rest is the
    hold at the end, 6-9 deg away): the layout's face positions give the start's turn
    (``neutral.square_rest``), so the output's head is turned as the actor's from the first state,
    not taken for the rest (every frame 6-9 deg off before). A take starting square keeps its
    start for the rest."""
    from facecast.server.mocap.io import read_take
    from facecast.server.mocap.live import MarkerLiveDriver
    from facecast.server.mocap.variants import make_take

    face = ict_head[0]
    for name, seed in (("neutral-last", 0), ("neutral-last", 1), ("issue16", 0)):
        truth = make_take(name, tmp_path / f"{name}{seed}", seed=seed, seconds=1.0, face=face)
        layout = json.loads(truth.paths["layout"].read_text())
        take = read_take(truth.paths["trc"], default_units=layout["units"])
        drv = MarkerLiveDriver(face, take.names, layout, fps=take.fps, prior="off")
        heads, frames = _live_heads(drv, take)
        err = _angle_deg(heads[:, :, :3], truth.r[frames])
        assert err.mean() < 0.5, (name, seed, err.mean())
        assert (drv.rest_turn_deg > 1.0) == (name == "neutral-last")


def test_live_rest_slides_to_a_square_neutral_hold_after_a_turned_start(tmp_path, ict_head):
    """A take that starts turned and on an expression, and holds its neutral square to the axes at
    the end (``neutral-last``): no layout tells where the head rests, so the start's position is
    kept until the hold, then the rest slides there (``MarkerLiveDriver._retake``) over
    ``REST_SLIDE_S``: the head ends nearer where the actor's is (it stayed ~5 mm off without the
    slide), and no frame steps by more than the slide's share."""
    from facecast.server.mocap.io import read_take
    from facecast.server.mocap.live import REST_SLIDE_S, MarkerLiveDriver
    from facecast.server.mocap.variants import make_take

    face = ict_head[0]
    truth = make_take("neutral-last", tmp_path, seed=3, seconds=2.0, face=face, formats=("trc",))
    layout = json.loads(truth.paths["layout"].read_text())
    take = read_take(truth.paths["trc"], default_units=layout["units"])
    drv = MarkerLiveDriver(face, take.names, layout, fps=take.fps, prior="off")
    h, frames = _live_heads(drv, take)
    assert drv.retakes >= 1
    r, t = truth.head(face, np.asarray(frames))
    v = face.vertices[face.part("skin")].astype(np.float64)
    got = np.einsum("tij,vj->tvi", h[:, :, :3], v) + h[:, None, :, 3]
    want = np.einsum("tij,vj->tvi", r, v) + t[:, None]
    off = np.linalg.norm(got - want, axis=2).mean(axis=1) * face.mm_per_unit
    # (the hold starts 0.5 s before the end; the slide begins 0.4 s into it)
    assert off[-5:].mean() < 0.7 * off[: len(off) // 2].mean()
    step = np.linalg.norm(np.diff(h[:, :, 3], axis=0), axis=1) * face.mm_per_unit
    slide = 15.0 / (REST_SLIDE_S * take.fps)  # mm per frame of a 15 mm slide
    assert step.max() < slide + 2.0  # the head's own motion: well under 2 mm a frame


def test_render_exposes_the_mocap_cleaning_choices(tmp_path, ict_head, capsys):
    from facecast.server.cli import main
    from facecast.server.mocap.variants import make_take

    face = ict_head[0]
    truth = make_take("sparse30", tmp_path, seconds=0.5, face=face)
    from facecast.server.paths import shared_data

    mesh = str(shared_data() / "ict-facekit" / "generic_neutral_mesh.obj")
    base = [
        "render",
        str(truth.paths["trc"]),
        "--layout",
        str(truth.paths["layout"]),
        "--face",
        mesh,
        "--backend",
        "numpy",
        "-o",
        str(tmp_path / "out.npz"),
    ]
    assert main([*base, "--filter", "kalman", "--lowrank", "off", "--neutral-frame", "3"]) == 0
    assert main([*base, "--neutral-frame", "auto"]) == 0
    with np.load(tmp_path / "out.npz") as z:
        assert z["vertices"].shape[0] == 60
    assert main([*base, "--lowrank", "many"]) == 2
    assert "lowrank must be auto, off or a positive count" in capsys.readouterr().err
    assert main([*base, "--stable", "HB1,NOPE"]) == 2
    assert "NOPE" in capsys.readouterr().err


def test_neutral_frame_auto_takes_the_neutral_where_the_markers_say_it_is(tmp_path, ict_head):
    """A take that starts on an expression and holds the neutral at its end: ``auto`` (the default
    when neither the flag nor the layout names a frame) finds the hold, frame 0 is an expression; a
    take moving from its neutral frame 0 keeps frame 0."""
    from facecast.server.errors import InputError
    from facecast.server.mocap.layout import load_layout
    from facecast.server.mocap.variants import make_take

    face, _, deltas = ict_head
    truth = make_take("neutral-last", tmp_path, seconds=1.5, face=face, formats=("trc",))
    layout = json.loads(truth.paths["layout"].read_text())
    local = truth.local(face, deltas)
    found = {}
    for nf in (0, "auto", None):
        proc = _process_fmt(truth, face, "trc", neutral_frame=nf)
        pv = proc.rig.placement.vertices
        got = np.stack([st.controls[: len(pv)] for st in proc.states]) * face.mm_per_unit
        want = (local[:, pv] - face.vertices[pv]) * face.mm_per_unit
        found[nf] = (proc.neutral_frame, np.linalg.norm(got - want, axis=2).mean())
    assert truth.weights[0].sum() > 0.5  # frame 0 is an expression
    assert truth.weights[found["auto"][0]].sum() < 1e-3  # auto's frame is in the neutral hold
    assert found[None] == found["auto"]
    assert found["auto"][1] < 0.5 * found[0][1]
    # in the layout too; anything else is refused with the field named
    lay = {**layout, "neutral_frame": "auto"}
    assert _process_fmt(truth, face, "trc", layout=lay).neutral_frame == found["auto"][0]
    with pytest.raises(InputError, match="neutral_frame"):
        load_layout({**layout, "neutral_frame": "soon"})
    moving = make_take("issue16", tmp_path / "m", seconds=1.5, face=face, formats=("trc",))
    assert _process_fmt(moving, face, "trc").neutral_frame == 0


def _process_fmt(truth, face, fmt, layout=None, **kw):
    from facecast.server.mocap.driver import process
    from facecast.server.mocap.io import read_take

    lay = layout or json.loads(truth.paths["layout"].read_text())
    return process(read_take(truth.paths[fmt], default_units=lay["units"]), face, lay, **kw)


def test_exaggeration_masks_scale_their_region_only(tmp_path, ict_head):
    """A layout's ``exaggerate`` region scales its markers' displacements (batch and live share the
    rig); the other markers and the head are untouched; bad regions are refused, the field named."""
    from facecast.server.errors import InputError
    from facecast.server.mocap.layout import load_layout
    from facecast.server.mocap.variants import make_take

    face = ict_head[0]

    truth = make_take("sparse30", tmp_path, seconds=0.5, face=face, formats=("trc",))
    layout = json.loads(truth.paths["layout"].read_text())
    region = [n for n in layout["markers"] if n not in layout["stable"]][:6]
    plain = _process_fmt(truth, face, "trc")
    lay = {**layout, "exaggerate": {"mouth": {"gain": 2.0, "markers": region}}}
    more = _process_fmt(truth, face, "trc", layout=lay)
    names = plain.rig.control_names
    inside = np.array(
        [n in region for n in names] + [False] * (len(plain.states[0].controls) - len(names))
    )
    a = np.stack([s.controls for s in plain.states])
    b = np.stack([s.controls for s in more.states])
    np.testing.assert_allclose(b[:, inside], 2.0 * a[:, inside], rtol=1e-5, atol=1e-7)
    np.testing.assert_array_equal(b[:, ~inside], a[:, ~inside])
    np.testing.assert_array_equal(
        np.stack([s.head for s in more.states]), np.stack([s.head for s in plain.states])
    )
    for bad, what in (
        ({"m": {"gain": 9, "markers": region}}, "gain"),
        ({"m": {"gain": 1.2, "markers": ["NOPE"]}}, "NOPE"),
        (
            {"m": {"gain": 1.2, "markers": region}, "n": {"gain": 1.1, "markers": region[:1]}},
            "already in region",
        ),
        ([1, 2], "exaggerate"),
    ):
        with pytest.raises(InputError, match=what):
            load_layout({**layout, "exaggerate": bad})


def test_batch_head_poses_refit_to_every_marker_the_prior_explains(tmp_path, ict_head, monkeypatch):
    """``driver.fit_pose``: where the face prior explains a frame, the head pose is refit rigidly to
    every control marker (their expression taken as the prior's fit), not the three headband
    markers alone (sparse30, a mirror fold: the held-out shapes' other sides in the prior)."""
    from facecast.server.mocap import driver
    from facecast.server.mocap.clean import CleanParams
    from facecast.server.mocap.io import read_take
    from facecast.server.mocap.prior import ExpressionBasis
    from facecast.server.mocap.variants import fold_protocol, make_take

    face, names, deltas = ict_head
    held, known = fold_protocol(names, "mirror")[0]
    truth = make_take(
        "sparse30", tmp_path, seed=1, seconds=1.5, face=face, expressions=held, formats=("c3d",)
    )
    lay = json.loads(truth.paths["layout"].read_text())
    basis = ExpressionBasis([names[i] for i in known], deltas[known])

    def pose_error() -> float:
        take = read_take(truth.paths["c3d"], default_units=lay["units"])
        proc = driver.process(take, face, lay, clean_params=CleanParams(filter="rts"), prior=basis)
        return float(_angle_deg(proc.rig.head_matrix(proc.r, proc.t)[:, :, :3], truth.r).mean())

    refit = pose_error()
    monkeypatch.setattr(driver, "FIT_POSE_PASSES", 0)
    headband = pose_error()
    print(f"pose error: headband {headband:.4f} deg, refit {refit:.4f} deg")
    assert refit < 0.9 * headband  # 0.198 -> 0.130 deg (2 passes: 0.167)
