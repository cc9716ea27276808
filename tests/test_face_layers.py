"""Face layers (issue 18): the mixing rules, speech keeping its closures under a smile (real
speech), idle blinks at human rates, gaze on the deformed mesh, the Mixer, and `render --layer`."""

from __future__ import annotations

import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from facecast.server.errors import Conflict, InputError, NotFound
from facecast.server.layers import (
    Contribution,
    Envelope,
    ExpressionLayer,
    GazeLayer,
    GazeTarget,
    Geometry,
    HeadGesture,
    HeadPose,
    IdleLayer,
    Mixer,
    Role,
    TrackLayer,
    combine,
    mix,
    mix_states,
    parse_gaze,
    region_mask,
)
from facecast.server.layers.head import AU_PER_DEG
from facecast.server.layers.mix import (
    LID_PER_CHEEK,
    LIDS_MEET,
    LIP_PAIRS,
    WIDTH,
    head_angles,
    head_transform,
    keep_closures,
)
from facecast.server.layers.model import REGIONS
from facecast.server.mpeg4.highlevel import EXPRESSIONS, VISEMES, expand
from facecast.server.state import FaceState, zero_faps

ROOT = Path(__file__).resolve().parents[1]


def faps(**values: float) -> np.ndarray:
    f = zero_faps()
    for k, v in values.items():
        f[int(k[1:])] = v
    return f


# -- mixing rules -----------------------------------------------------------------------------


def test_no_layers_returns_the_primary_itself():
    p = FaceState(t=0.5, faps=faps(f31=10), viseme=(1, 0, 63))
    assert mix(p, []) is p
    assert mix_states([p], []) == [p]


def test_offsets_add_and_the_primary_keeps_its_high_level_faps():
    p = FaceState(t=0.0, faps=faps(f31=100), viseme=(10, 0, 63))
    items = [
        (Role.EXPRESSION, Contribution(faps=faps(f41=30))),
        (Role.HEAD, Contribution(faps=faps(f31=50, f48=1000))),
    ]
    out = combine(p, items)
    assert out.viseme == (10, 0, 63)
    assert np.allclose(expand(out), expand(p) + faps(f31=50, f41=30, f48=1000))


def test_an_overlay_competes_with_the_primary_except_in_a_speaking_mouth():
    p = FaceState(t=0.0, faps=faps(f31=100), viseme=(10, 0, 63))
    over = Contribution(faps=faps(f31=300, f33=40, f12=100))
    out = expand(combine(p, [(Role.EXPRESSION, over)]))
    assert out[31] == pytest.approx(200.0)  # both move it: their mean
    assert out[33] == pytest.approx(40.0)  # only the overlay moves it
    assert out[12] == pytest.approx(VISEMES[10][12] + 100)  # speech and expression add
    half = expand(combine(p, [(Role.EXPRESSION, Contribution(faps=faps(f31=300), weight=0.5))]))
    assert half[31] == pytest.approx((100 + 150) / 1.5)
    mute = expand(combine(p, [(Role.EXPRESSION, over)], closures=False))
    assert mute[12] == pytest.approx((VISEMES[10][12] + 100) / 2)  # not speech: they compete


def test_layers_of_one_role_compete_and_average_by_weight_roles_add():
    a = Contribution(faps=faps(f31=100, f33=40))
    b = Contribution(faps=faps(f31=300))
    out = combine(None, [(Role.EXPRESSION, a), (Role.EXPRESSION, b)])
    assert out.faps[31] == pytest.approx(200.0)  # both at full weight: the mean
    assert out.faps[33] == pytest.approx(40.0)  # only one layer weighs on it, still averaged by Σw
    half = combine(None, [(Role.EXPRESSION, Contribution(faps=faps(f31=100), weight=0.5))])
    assert half.faps[31] == pytest.approx(50.0)  # one layer below full weight: scaled
    two = combine(
        None,
        [
            (Role.EXPRESSION, Contribution(faps=faps(f31=100), weight=0.25)),
            (Role.EXPRESSION, Contribution(faps=faps(f31=300), weight=0.25)),
        ],
    )
    assert two.faps[31] == pytest.approx(100.0)  # Σw ≤ 1: weighted offsets add
    roles = combine(None, [(Role.EXPRESSION, a), (Role.HEAD, b)])
    assert roles.faps[31] == pytest.approx(400.0)  # different roles add


def test_region_masks_limit_a_layer():
    joy = ExpressionLayer(1, regions=("eyebrows",))
    out = mix(None, [joy], 0.0)
    brows = list(range(31, 39))
    assert np.allclose(out.faps[brows], EXPRESSIONS[1][brows])
    assert not np.any(out.faps[3:19]) and not np.any(out.faps[39:43])
    with pytest.raises(KeyError, match="unknown face region"):
        region_mask(["chin"])


def test_amount_scales_and_envelope_times_the_overlay():
    env = Envelope(start=1.0, attack_peak=1.5, relax=3.0, end=4.0)
    layer = ExpressionLayer(6, amount=0.5, envelope=env)
    assert mix(None, [layer], 0.9).faps[31] == 0.0
    assert mix(None, [layer], 2.0).faps[31] == pytest.approx(0.5 * EXPRESSIONS[6][31])
    assert 0 < mix(None, [layer], 1.25).faps[31] < 0.5 * EXPRESSIONS[6][31]
    assert mix(None, [layer], 4.0).faps[31] == 0.0
    assert [env(t) for t in (0.0, 1.0, 1.5, 2.0, 3.0, 3.5, 4.0)] == pytest.approx(
        [0, 0, 1, 1, 1, 0.5, 0]
    )
    assert Envelope()(123.0) == 1.0
    with pytest.raises(ValueError):
        Envelope(start=2.0, end=1.0)


def test_overrides_replace_what_is_below():
    # a blink closes the lids over an expression that opens them wide (surprise)
    idle = IdleLayer(seed=3)
    t = next(t for t in np.arange(0, 30, 0.001) if idle.closure(t) == 1.0)
    out = mix(FaceState(t=t), [ExpressionLayer(6), idle], t, closures=False)
    assert out.faps[19] == pytest.approx(1024.0) and out.faps[20] == pytest.approx(1024.0)
    # head pose replaces the primary's head FAPs; a nod adds on top
    p = FaceState(t=0.0, faps=faps(f48=5000, f49=-7000))
    pose = HeadPose(pitch=0.0, yaw=10.0)
    out = mix(p, [pose], 0.0)
    assert out.faps[49] == pytest.approx(10 * AU_PER_DEG) and out.faps[48] == pytest.approx(0.0)
    nod = HeadGesture("nod", envelope=Envelope(start=0.0, end=0.6))
    out = mix(p, [pose, nod], 0.3)
    assert out.faps[48] == pytest.approx(8 * AU_PER_DEG)  # the nod's bottom, over the pose
    half = mix(p, [HeadPose(yaw=10.0, amount=0.5)], 0.0)
    assert half.faps[49] == pytest.approx(0.5 * (-7000) + 0.5 * 10 * AU_PER_DEG)


def test_head_pose_over_a_primary_head_transform():
    pivot = np.array([0.0, -50.0, -10.0])
    geo = Geometry(head_pivot=pivot)
    M = head_transform([3000.0, -12000.0, 2000.0], pivot, np.array([1.0, 2.0, 3.0]))
    ang, rest = head_angles(M, pivot)
    assert np.allclose(ang, [3000.0, -12000.0, 2000.0]) and np.allclose(rest, [1.0, 2.0, 3.0])
    p = FaceState(t=0.0, head=M)
    out = mix(p, [HeadPose(yaw=20.0)], 0.0, geometry=geo)
    want = head_transform([0.0, 20 * AU_PER_DEG, 0.0], pivot)
    assert np.allclose(out.head, want)
    assert mix(p, [ExpressionLayer(1)], 0.0).head is M  # layers that leave the head alone


def test_closures_keep_the_lips_shut_and_the_smile_corners():
    pp = FaceState(t=0.0, viseme=(1, 0, 63))  # /p/: lips pressed
    out = mix(pp, [ExpressionLayer(1)], 0.0)
    F = expand(out)
    gap = -(F[4] + F[5])
    assert gap <= -(VISEMES[1][4] + VISEMES[1][5]) + 1e-9  # no more open than the /p/
    for k in (12, 13, 59, 60):  # the corners' raise: the smile's
        assert F[k] == pytest.approx(VISEMES[1][k] + EXPRESSIONS[1][k])
    for k in WIDTH:  # the lips' width (the corners' stretch): the mean of speech and smile
        assert F[k] == pytest.approx((VISEMES[1][k] + EXPRESSIONS[1][k]) / 2)
    assert F[3] == pytest.approx(0.0)  # no jaw drop under closed lips
    free = expand(mix(pp, [ExpressionLayer(1)], 0.0, closures=False))
    assert -(free[4] + free[5]) > 0  # without the rule the smile parts a /p/
    A = EXPRESSIONS[1].copy()
    A[[3, 4, 5, 8, 9, 10, 11, 51, 52, 55, 56, 57, 58]] = 0.0  # corners and cheeks only
    assert keep_closures(VISEMES[10], A) is A


def test_over_open_speech_a_smile_moves_the_mouth_no_further_than_the_larger_of_the_two():
    """Rule 4's other half: over an open vowel, a mouth FAP that the smile moves the speech's way
    goes as far as the larger of the two, not their sum (which creased the chin: issue 18); the
    smile's corner raise, which the speech leaves alone, adds; the mouth opens as far as the
    wider of the two. Outside the mouth the smile adds as before."""
    V, X = VISEMES[10], EXPRESSIONS[1]  # "aa", joy
    F = expand(mix(FaceState(t=0.0, viseme=(10, 0, 63)), [ExpressionLayer(1)], 0.0))
    mouth = list(REGIONS["mouth"] + REGIONS["tongue"])
    for k in range(3, 69):
        if k in WIDTH:
            assert F[k] == pytest.approx((V[k] + X[k]) / 2), k
        elif k in mouth and V[k] * X[k] > 0:
            assert F[k] == pytest.approx(V[k] if abs(V[k]) > abs(X[k]) else X[k]), k
        else:
            assert F[k] == pytest.approx(V[k] + X[k]), k
    for top, bottom in LIP_PAIRS:
        gap = -(F[top] + F[bottom])
        assert gap <= max(-(V[top] + V[bottom]), -(X[top] + X[bottom])) + 1e-9
    assert F[3] == pytest.approx(max(V[3], X[3]))
    half = FaceState(t=0.0, faps=np.where(np.arange(69) == 3, X[3] / 2, 0.0))  # jaw half of joy's
    half.faps[[5, 52]] = -400.0  # the lower lip well open
    F = expand(mix(half, [ExpressionLayer(1)], 0.0))
    assert F[3] == pytest.approx(X[3])  # the jaw opens to the smile's, the larger


def test_in_a_speaking_mouth_the_lips_width_is_the_mean_of_speech_and_overlay():
    """Rule 4's width: the corners' stretch (FAPs 6, 7, 53, 54) is the speech's articulation
    (spread, rounded) as much as the smile's, so where an overlay moves it the two compete and
    average, whichever way each goes (summed, a smile's stretch over closed, rounded or open
    lips pulled the ICT lips through the teeth: issue 18); where the overlay leaves it, the
    speech's width stays whole. A primary that does not speak competes the same way where it
    moves its lips (its mouth's shape: ICT's ``beg`` pressed lips under a smile poked the teeth
    through); with its lips at rest the overlay's width adds."""
    smile = np.zeros(69)
    smile[WIDTH] = 120.0
    smile[[12, 13]] = 200.0
    for width in (0.0, 40.0, -100.0):  # neutral, spread, rounded
        speech = FaceState(t=0.0, faps=faps(f3=150.0, f5=-200.0))
        speech.faps[WIDTH] = width
        F = mix(speech, [ExpressionLayer(0, faps=smile)], 0.0).faps
        assert np.allclose(F[WIDTH], (width + 120.0) / 2)
        assert np.allclose(F[[12, 13]], 200.0)  # the corners' raise adds
        idle = mix(speech, [ExpressionLayer(0, faps=faps(f12=200.0))], 0.0).faps
        assert np.allclose(idle[WIDTH], width)  # the speech's width, whole
        free = mix(speech, [ExpressionLayer(0, faps=smile)], 0.0, closures=False).faps
        assert np.allclose(free[WIDTH], (width + 120.0) / 2)
    still = FaceState(t=0.0, faps=faps(f3=150.0, f19=300.0))  # a jaw and lids, lips at rest
    free = mix(still, [ExpressionLayer(0, faps=smile)], 0.0, closures=False).faps
    assert np.allclose(free[WIDTH], 120.0)


def test_gaze_target_parsing():
    assert np.allclose(parse_gaze("camera").direction, [0, 0, 1])
    assert np.allclose(parse_gaze(" 1, -2.5,300 ").point, [1, -2.5, 300])
    for bad in ("", "1,2", "a,b,c", "1,2,nan", "1,2,3,4"):
        with pytest.raises(ValueError, match="camera"):
            parse_gaze(bad)
    with pytest.raises(ValueError):
        GazeTarget()


# -- mixer ------------------------------------------------------------------------------------


def test_mixer_add_change_remove_and_ended_layers():
    m = Mixer(max_layers=3)
    m.add("smile", ExpressionLayer(1, envelope=Envelope(end=2.0)))
    with pytest.raises(Conflict):
        m.add("smile", ExpressionLayer(2))
    m.set("brow", ExpressionLayer(6, regions=("eyebrows",)))
    m.set("idle", IdleLayer())
    with pytest.raises(Conflict):
        m.set("fourth", IdleLayer())
    assert m.change("brow", amount=0.5).amount == 0.5
    with pytest.raises(NotFound):
        m.change("nope", amount=1.0)
    with pytest.raises(InputError):
        m.change("brow", colour=3)
    with pytest.raises(InputError):
        m.change("brow", amount=float("nan"))
    with pytest.raises(InputError):
        m.set("", IdleLayer())
    with pytest.raises(TypeError):
        m.set("x", object())  # type: ignore[arg-type]
    assert list(m.layers()) == ["smile", "brow", "idle"]
    m.mix(FaceState(t=1.0))
    assert "smile" in m.layers()
    m.mix(FaceState(t=2.5))
    assert "smile" not in m.layers()  # its envelope ended
    assert isinstance(m.remove("brow"), ExpressionLayer) and m.remove("brow") is None
    assert len(m) == 1


def test_mixer_mixes_while_another_thread_changes_it():
    m = Mixer()
    m.set("idle", IdleLayer())
    stop = threading.Event()
    errors: list[BaseException] = []

    def churn() -> None:
        i = 0
        while not stop.is_set():
            try:
                m.set(f"e{i % 5}", ExpressionLayer(1 + i % 6, amount=0.5))
                m.remove(f"e{(i + 2) % 5}")
            except BaseException as e:  # noqa: BLE001 - reported by the test
                errors.append(e)
            i += 1

    th = threading.Thread(target=churn)
    th.start()
    try:
        for k in range(2000):
            out = m.mix(FaceState(t=k / 100))
            assert np.all(np.isfinite(out.faps))
    finally:
        stop.set()
        th.join()
    assert not errors


# -- idle -------------------------------------------------------------------------------------


def _blinks(layer: IdleLayer, seconds: float, dt: float = 0.001):
    t = np.arange(0.0, seconds, dt)
    c = np.array([layer.closure(x) for x in t])
    moving = c > 0
    starts = np.flatnonzero(moving[1:] & ~moving[:-1]) + 1
    ends = np.flatnonzero(~moving[1:] & moving[:-1]) + 1
    ends = ends[ends > starts[0]]
    return t, c, starts, ends


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_idle_blinks_at_human_rates_and_durations(seed):
    layer = IdleLayer(seed=seed)
    minutes = 3.0
    t, c, starts, ends = _blinks(layer, 60 * minutes)
    rate = len(starts) / minutes
    assert 10 <= rate <= 25
    gaps = np.diff(t[starts])
    assert gaps.min() >= layer.refractory
    assert gaps.std() / gaps.mean() > 0.4  # irregular (Poisson-like), not a metronome
    for s, e in zip(starts, ends, strict=False):  # (a blink cut by the window's end: left out)
        blink = c[s:e]
        peak = np.flatnonzero(blink >= 0.999)
        closing = peak[0] * 0.001
        opening = (len(blink) - peak[-1]) * 0.001
        closed = (peak[-1] - peak[0]) * 0.001
        assert 0.09 <= closing <= 0.16
        assert closed <= 0.07
        assert opening > 1.5 * closing
    assert np.array_equal(c, _blinks(IdleLayer(seed=seed), 60 * minutes)[1])  # deterministic


def test_idle_saccades_fixations_sway():
    layer = IdleLayer(seed=4)
    t = np.arange(0.0, 120.0, 0.005)
    yaw = np.array([layer.gaze(x)[0] for x in t])
    still = np.abs(np.diff(yaw)) < 1e-9
    # fixations: runs of no eye motion, 0.3-3 s
    edges = np.flatnonzero(np.diff(still.astype(int)))
    runs = np.diff(edges)[still[edges[:-1] + 1]] * 0.005
    assert runs.min() >= 0.25 and runs.max() <= 3.0
    assert np.abs(yaw).max() < 12.0  # small amplitudes
    out = [layer.sample(x).faps for x in (0.0, 2.0, 4.0)]
    assert all(abs(f[48]) < 4 * AU_PER_DEG and abs(f[49]) < 4 * AU_PER_DEG for f in out)
    assert len({round(f[49]) for f in out}) == 3  # the head sways


def test_demo_is_its_script_over_the_idle_layer():
    from facecast.server.drivers.demo import demo_states

    states = list(demo_states(30, loops=1))
    lids = np.array([s.faps[19] for s in states])
    assert (lids > 1000).sum() > 0  # blinks
    assert any(s.expression for s in states) and any(s.viseme for s in states)
    assert np.ptp([s.faps[49] for s in states]) > AU_PER_DEG  # sway


# -- speech keeps its closures (real speech) ---------------------------------------------------


@pytest.fixture(scope="module")
def lipsync_bench():
    sys.path.insert(0, str(ROOT / "bench" / "lipsync"))
    import classes
    import textgrid

    return classes, textgrid


@pytest.mark.parametrize(
    ("wav", "grid", "alphabet"),
    [
        ("mary.wav", "mary.TextGrid", "ipa"),
        ("bobby_16bit_16khz.wav", "bobby_phones.TextGrid", "arpabet"),
    ],
)
def test_speech_with_a_smile_keeps_its_lip_closures(data_dir, lipsync_bench, wav, grid, alphabet):
    """Closed-frame accuracy (the lip-sync bench's open/closed classes as truth, the lip-contact
    distance between the inner lip midpoints 2.2/2.3 of the face as the measure) does not drop
    with a smile over the speech; without the closure rule it would."""
    from facecast.server.drivers import load_animation
    from facecast.server.faces import load_face
    from facecast.server.mpeg4.rig import FapRig

    classes, textgrid = lipsync_bench
    face = load_face("default")
    rig = FapRig(face)
    geo = Geometry.of_rig(rig)
    speech = load_animation(data_dir / "speech" / wav, face)
    tiers = textgrid.read_tiers(data_dir / "speech" / grid)
    tier = tiers.get("phone") or tiers.get("phones") or next(iter(tiers.values()))
    truth = classes.frames_from_intervals(
        tier, alphabet, len(speech.states) / speech.fps, speech.fps
    )[: len(speech.states)]
    known = truth >= 0
    closed = known & ~classes.OPEN[np.maximum(truth, 0)]
    ids = [next(i for i, n in enumerate(rig.fp_ids) if fp in n.split("+")) for fp in ("2.2", "2.3")]
    rest = face.vertices[rig.control_vertices[ids], 1].astype(np.float64)

    def closed_accuracy(states) -> float:
        D, _ = rig.solve_batch(states)
        gap_mm = ((rest[0] + D[:, ids[0], 1]) - (rest[1] + D[:, ids[1], 1])) * face.mm_per_unit
        return float((gap_mm < 1.0)[closed].mean())

    joy = load_animation(data_dir / "xface" / "faps" / "joy.fap", None)
    base = closed_accuracy(speech.states)
    assert base > 0.5  # the measure sees the speech's closures
    for layer in (ExpressionLayer(1), TrackLayer(joy.states, joy.fps, loop=True)):
        assert closed_accuracy(mix_states(speech.states, [layer], geometry=geo)) >= base
        free = mix_states(speech.states, [layer], geometry=geo, closures=False)
        assert closed_accuracy(free) < base


# -- gaze on the deformed mesh ----------------------------------------------------------------


def _sphere_centre(P: np.ndarray) -> np.ndarray:
    A = np.c_[2 * P, np.ones(len(P))]
    return np.linalg.lstsq(A, (P**2).sum(1), rcond=None)[0][:3]


def _gaze_errors(face, animator, geo, layers, target: GazeTarget) -> list[float]:
    """Angle (°) between each deformed eyeball's axis (centre -> pupil vertex) and the target."""
    V = animator.frame(mix(FaceState(t=0.0), layers, 0.0, geometry=geo)).astype(np.float64)
    out = []
    for part, fp in (("eye_l", "3.5"), ("eye_r", "3.6")):
        c = _sphere_centre(V[face.part(part)])
        axis = V[face.feature_points[fp]] - c
        want = target.point - c if target.point is not None else target.direction
        cos = axis @ want / np.linalg.norm(axis) / np.linalg.norm(want)
        out.append(float(np.degrees(np.arccos(np.clip(cos, -1, 1)))))
    return out


TARGETS = [
    GazeTarget.camera(),
    GazeTarget(point=np.array([0.0, 40.0, 250.0])),  # close, above: converging
    GazeTarget(point=np.array([300.0, 100.0, 600.0])),
    GazeTarget(point=np.array([-200.0, -150.0, 400.0])),
    GazeTarget(direction=np.array([-0.3, 0.2, 1.0])),
]


@pytest.fixture(scope="module")
def default_head():
    from facecast.server.faces import load_face
    from facecast.server.pipeline import Animator

    face = load_face("default")
    animator = Animator(face, backend="numpy")
    return face, animator, Geometry.of_rig(animator.rig)


@pytest.mark.parametrize("head", [None, HeadPose(pitch=10, yaw=-12, roll=5)])
@pytest.mark.parametrize("target", TARGETS, ids=range(len(TARGETS)))
def test_gaze_points_the_deformed_eyes_at_the_target(default_head, target, head):
    face, animator, geo = default_head
    assert face.feature_points["3.5"] in set(face.part("eye_l").tolist())
    layers = [GazeLayer(target), IdleLayer(seed=1)] + ([head] if head else [])
    errors = _gaze_errors(face, animator, geo, layers, target)
    assert max(errors) < 2.0, errors
    # without the gaze layer the eyes look elsewhere (the check is not vacuous)
    if target.point is not None and head is not None:
        assert max(_gaze_errors(face, animator, geo, layers[1:], target)) > 2.0


# -- render CLI -------------------------------------------------------------------------------


def test_render_with_layers_writes_a_valid_glb(data_dir, tmp_path):
    from test_render import _cli, frames_of, read_glb

    from facecast.server.render import render_file

    wav = data_dir / "speech" / "bobby_16bit_16khz.wav"
    joy = data_dir / "xface" / "faps" / "joy.fap"
    plain, layered = tmp_path / "plain.glb", tmp_path / "layered.glb"
    common = ["--face", "default:2k", "--backend", "numpy"]
    render_file(wav, plain, face="default:2k", backend="numpy")
    r = _cli(
        "render", str(wav), "-o", str(layered), *common,
        "--layer", f"{joy}@0.8", "--idle", "--seed", "3", "--gaze", "camera",
        cwd=tmp_path,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    a, b = read_glb(plain), read_glb(layered)
    assert b["extras"]["layers"] == ["TrackLayer", "IdleLayer", "GazeLayer"]
    fa, fb = frames_of(a), frames_of(b)
    assert fa.shape == fb.shape and np.all(np.isfinite(fb))
    assert np.abs(fb - fa).max() > 1.0  # the layers show (mm)
    import argparse

    from facecast.server.commands.render import add_arguments, build_layers

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    for bad, where in (
        (["--layer", str(tmp_path / "none.fap")], "none.fap"),
        (["--layer", str(wav)], ".wav"),
        (["--layer", f"{joy}@nan"], "@nan"),
        (["--gaze", "1,2"], "--gaze"),
        (["--seed", "3"], "--seed"),
    ):
        args = parser.parse_args([str(wav), "-o", str(tmp_path / "x.glb"), *bad])
        with pytest.raises(InputError) as e:
            build_layers(args)
        assert where in str(e.value), str(e.value)


def test_render_without_layers_is_unchanged(data_dir, tmp_path):
    from facecast.server.render import render_file

    src = data_dir / "xface" / "faps" / "joy.fap"
    a, b = tmp_path / "a.glb", tmp_path / "b.glb"
    render_file(src, a, face="default:2k", backend="numpy")
    render_file(src, b, face="default:2k", backend="numpy", layers=[])
    assert a.read_bytes() == b.read_bytes()


def test_gaze_on_the_ict_head(data_dir):
    """The ICT head (centimetres; its pupils 7° from +z at rest) looks at its targets too."""
    from facecast.server.faces import load_face
    from facecast.server.pipeline import Animator

    face = load_face(data_dir / "ict-facekit" / "generic_neutral_mesh.obj")
    animator = Animator(face, backend="numpy")
    geo = Geometry.of_rig(animator.rig)
    for head in (None, HeadPose(pitch=-8, yaw=-12, roll=-4)):
        for target in TARGETS:
            if target.point is not None:  # the targets are in mm
                target = GazeTarget(point=target.point / face.mm_per_unit)
            layers = [GazeLayer(target), IdleLayer(seed=5)] + ([head] if head else [])
            errors = _gaze_errors(face, animator, geo, layers, target)
            assert max(errors) < 2.0, (target, head, errors)


def test_layers_refuse_bad_values_and_gaze_stays_in_the_eyes_range():
    for make in (
        lambda: ExpressionLayer(7),
        lambda: ExpressionLayer("1"),  # type: ignore[arg-type]
        lambda: ExpressionLayer(1, amount=float("inf")),
        lambda: ExpressionLayer(1, envelope="soon"),  # type: ignore[arg-type]
        lambda: ExpressionLayer(1, regions=("chin",)),
        lambda: ExpressionLayer(1, regions="mouth"),  # type: ignore[arg-type]
        lambda: ExpressionLayer(faps=np.zeros(5)),
        lambda: HeadGesture("wink"),
        lambda: HeadGesture("nod", repetitions=0),
        lambda: HeadPose(yaw=200.0),
        lambda: GazeLayer(amount=2.0),
        lambda: GazeLayer(target=(1, 2, 3)),  # type: ignore[arg-type]
        lambda: IdleLayer(blink_rate=0.0),
        lambda: IdleLayer(seed=1.5),  # type: ignore[arg-type]
        lambda: Envelope(start=float("nan")),
        lambda: TrackLayer([], 25.0),
        lambda: TrackLayer([FaceState()], 0.0),
    ):
        with pytest.raises(ValueError):
            make()
    # a target inside an eye, or behind the head: finite, within the eyes' range
    geo = Geometry(eye_pivots=np.array([[30.0, 0, 70], [-30.0, 0, 70]]))
    for point in ([30.0, 0, 70], [0.0, 0, -500]):
        out = mix(None, [GazeLayer(GazeTarget(point=np.array(point)))], 0.0, geometry=geo)
        assert np.all(np.isfinite(out.faps))
        assert np.all(np.abs(out.faps[23:27]) <= np.radians(50) / 1e-5 + 1e-6)


# -- layers from plain data -------------------------------------------------------------------


def test_layers_from_specs():
    from facecast.server.layers import from_spec

    smile = from_spec(
        {"kind": "expression", "expression": "joy", "amount": 0.5, "envelope": {"end": 2}}, t0=10
    )
    assert isinstance(smile, ExpressionLayer) and smile.expression == 1
    assert smile.envelope == Envelope(start=10.0, end=12.0) and smile.end == 12.0
    brow = from_spec(
        {"kind": "expression", "faps": {"31": 100, "32": 100}, "regions": ["eyebrows"]}
    )
    assert brow.faps[31] == 100 and brow.regions == ("eyebrows",)
    assert isinstance(from_spec({"kind": "idle", "seed": 2}), IdleLayer)
    g = from_spec({"kind": "gaze", "target": [1, 2, 300]})
    assert isinstance(g, GazeLayer) and np.allclose(g.target.point, [1, 2, 300])
    assert np.allclose(from_spec({"kind": "gaze"}).target.direction, [0, 0, 1])
    nod = from_spec({"kind": "head", "gesture": "nod", "repetitions": 2})
    assert isinstance(nod, HeadGesture) and nod.end == pytest.approx(1.2)
    pose = from_spec({"kind": "head", "pose": {"yaw": 10}, "amount": 0.5})
    assert isinstance(pose, HeadPose) and pose.yaw == 10.0
    for bad in (
        [],
        {"kind": "smile"},
        {"kind": "expression"},
        {"kind": "expression", "expression": "glee"},
        {"kind": "expression", "expression": 1, "colour": "red"},
        {"kind": "expression", "faps": {"1": 5}},
        {"kind": "expression", "expression": 1, "envelope": {"start": 3, "end": 1}},
        {"kind": "expression", "expression": 1, "envelope": {"start": "now"}},
        {"kind": "idle", "blink_rate": 1000},
        {"kind": "gaze", "target": [1, 2]},
        {"kind": "head"},
        {"kind": "head", "gesture": "nod", "pose": {}},
        {"kind": "head", "pose": {"yaw": 400}},
    ):
        with pytest.raises(InputError):
            from_spec(bad)


def test_a_rest_layer_model_is_built_without_a_second_validation(monkeypatch):
    """``from_spec`` takes the API's validated model as it is (the model is the one check); plain
    data goes through the model first."""
    from facecast.protocol import layers as wire
    from facecast.server.layers import from_spec

    body = {"kind": "expression", "expression": "joy", "envelope": {"end": 2}, "regions": ["lips"]}
    model = wire.parse_layer(body)
    calls = []
    real = wire.parse_layer
    monkeypatch.setattr(wire, "parse_layer", lambda x: calls.append(x) or real(x))
    layer = from_spec(model, t0=5.0)
    assert calls == []
    assert layer.expression == 1 and layer.regions == ("lips",)
    assert layer.envelope == Envelope(start=5.0, end=7.0)
    assert from_spec(body, t0=5.0).envelope == layer.envelope and len(calls) == 1
    idle = from_spec(wire.parse_layer({"kind": "idle", "seed": 4, "blink_rate": 12}))
    assert isinstance(idle, IdleLayer) and idle.seed == 4 and idle.blink_rate == 12
    gaze = from_spec(wire.parse_layer({"kind": "gaze", "target": {"direction": [0, 1, 1]}}))
    assert np.allclose(gaze.target.direction, [0, 1, 1])
    pose = from_spec(wire.parse_layer({"kind": "head", "pose": {"pitch": 5}, "amount": 0.5}))
    assert isinstance(pose, HeadPose) and pose.pitch == 5 and pose.amount == 0.5


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4)
    ),
    max_leaves=12,
)


@settings(max_examples=150, deadline=None)
@given(
    kind=st.sampled_from(["expression", "idle", "gaze", "head", "x"]),
    fields=st.dictionaries(
        st.sampled_from(
            ["expression", "faps", "amount", "envelope", "regions", "seed", "blink_rate",
             "target", "gesture", "pose", "repetitions", "blinks", "other"]
        ),
        json_values,
        max_size=4,
    ),
)  # fmt: skip
def test_layer_specs_raise_only_input_errors(kind, fields):
    from facecast.server.layers import from_spec

    try:
        layer = from_spec({"kind": kind, **fields})
    except InputError:
        return
    out = mix(FaceState(t=0.5), [layer], 0.5, geometry=Geometry())
    assert np.all(np.isfinite(out.faps))


def test_gaze_compensates_a_head_given_as_a_transform_as_one_given_as_faps(default_head):
    _, _, geo = default_head
    angles = [4000.0, -15000.0, 3000.0]
    gaze = [GazeLayer(GazeTarget(point=np.array([50.0, 30.0, 500.0])))]
    by_faps = mix(
        FaceState(faps=faps(f48=angles[0], f49=angles[1], f50=angles[2])), gaze, 0.0, geometry=geo
    )
    M = head_transform(angles, geo.head_pivot)
    by_matrix = mix(FaceState(head=M), gaze, 0.0, geometry=geo)
    assert by_matrix.head is M
    assert np.allclose(by_faps.faps[23:27], by_matrix.faps[23:27])
    assert abs(by_faps.faps[23]) > 1000  # the eyes did turn


def test_in_a_speaking_mouth_an_overlay_competes_with_the_primary_expression_not_the_speech():
    p = FaceState(t=0.0, viseme=(10, 0, 63), expression=(6, 63, 0, 0))  # "aa" while surprised
    out = expand(mix(p, [ExpressionLayer(1)], 0.0))
    k = 6  # a lip corner stretch (the width): the mean of speech and the two expressions' mean
    both = (EXPRESSIONS[6][k] + EXPRESSIONS[1][k]) / 2
    assert out[k] == pytest.approx((VISEMES[10][k] + both) / 2)


# -- many frames at once ----------------------------------------------------------------------


def _random_frame(rng: np.random.Generator, geo: Geometry):
    """A primary (or None) and random contributions of every kind, as a live batch may hold."""
    kind = rng.integers(6)
    f = rng.normal(0.0, 150.0, 69) * (rng.random(69) < 0.6)
    t = float(rng.uniform(0, 100))
    primary = [
        None,
        FaceState(t=t, faps=f),
        FaceState(t=t, faps=f, viseme=(int(rng.integers(15)), int(rng.integers(15)), 40)),
        FaceState(t=t, faps=f, expression=(int(rng.integers(1, 7)), 50, 0, 0)),
        FaceState(t=t, faps=np.zeros(69)),  # closed lips: closures cut the overlays
        FaceState(t=t, faps=f, head=head_transform([3000.0, -2000.0, 500.0], geo.head_pivot)),
    ][kind]
    target = GazeTarget(point=rng.normal(0, 200, 3) + [0, 0, 500])
    layers = [
        ExpressionLayer(int(rng.integers(7)), amount=float(rng.uniform(0, 1.5))),
        ExpressionLayer(int(rng.integers(1, 7)), regions=("eyebrows", "lips"), amount=0.7),
        ExpressionLayer(
            0, faps=rng.normal(0, 300, 69), envelope=Envelope(start=t - 0.1, attack_peak=t + 0.2)
        ),
        IdleLayer(seed=int(rng.integers(100))),
        GazeLayer(target, amount=float(rng.uniform(0.2, 1.0))),
        GazeLayer(GazeTarget.camera()),
        HeadGesture("nod", envelope=Envelope(start=t - 0.5, end=t + 1.0)),
        HeadPose(pitch=10, yaw=-5, amount=float(rng.uniform(0.3, 1.0))),
        TrackLayer([FaceState(faps=rng.normal(0, 100, 69), viseme=(3, 0, 63))], fps=25, loop=True),
    ]
    chosen = [layers[i] for i in rng.choice(len(layers), int(rng.integers(0, 5)), replace=False)]
    items = [(layer.role, layer.sample(t)) for layer in chosen]
    # producers' layers: a gaze producer's override, an idle producer's weighted offsets
    if rng.random() < 0.3:
        items.append((Role.GAZE, Contribution(override=f, override_weight=(f != 0) * 1.0)))
    if rng.random() < 0.3:
        items.append((Role.IDLE, Contribution(faps=f[::-1].copy(), weight=(f != 0) * 1.0)))
    if rng.random() < 0.2:
        items.append((Role.IDLE, Contribution(faps=f, weight=1.7)))
    return primary, items, (None if rng.random() < 0.3 else t + 0.01)


@pytest.mark.parametrize("closures", [True, False])
def test_combine_batch_equals_combine_frame_by_frame(default_head, closures):
    """The batched mix of the live path gives each frame what ``combine`` gives it alone."""
    from facecast.server.layers.batch import combine_batch

    _, _, geo = default_head
    rng = np.random.default_rng(18)
    for _ in range(40):
        frames = [_random_frame(rng, geo) for _ in range(int(rng.integers(1, 33)))]
        batch = combine_batch(frames, geometry=geo, closures=closures)
        for (p, items, t), got in zip(frames, batch, strict=True):
            want = combine(p, items, t, geometry=geo, closures=closures)
            assert got.t == want.t
            assert got.viseme == want.viseme and got.expression == want.expression
            assert got.controls is want.controls
            np.testing.assert_allclose(got.faps, want.faps, rtol=1e-9, atol=1e-6)
            if want.head is None:
                assert got.head is None
            else:
                np.testing.assert_allclose(got.head, want.head, rtol=1e-9, atol=1e-9)


def test_mix_batch_equals_each_mixer_alone(default_head):
    from facecast.server.layers.batch import mix_batch

    _, _, geo = default_head
    mixers = []
    for k in range(20):  # (fewer than BATCH_MIN frames are mixed one by one: both ways here)
        m = Mixer(geo if k % 3 else None, closures=k % 6 != 4)
        m.set("idle", IdleLayer(seed=k))
        m.set("smile", ExpressionLayer(1, amount=0.5, envelope=Envelope(end=3.0)))
        m.set("gaze", GazeLayer(GazeTarget.camera()))
        mixers.append(m)
    rng = np.random.default_rng(1)
    states = [FaceState(t=0.04 * k, faps=rng.normal(0, 100, 69)) for k in range(20)]
    for t in (1.0, 2.5, 4.0):  # the smile ends at 3 s: the mixers drop it
        for n in (3, 20):
            got = mix_batch([(m, s, t) for m, s in zip(mixers[:n], states[:n])])
            for m, s, g in zip(mixers, states, got):
                np.testing.assert_allclose(g.faps, m.mix(s, t).faps, rtol=1e-9, atol=1e-6)
    assert all("smile" not in m.layers() for m in mixers)


def _tilted(geo: Geometry) -> Geometry:
    """``geo`` with eyes that do not look along z (the gaze's general path)."""
    return Geometry(
        eye_pivots=geo.eye_pivots,
        eye_axes=[[0.2, 0.1, 1.0], [-0.15, 0.05, 1.0]],
        head_pivot=geo.head_pivot,
        visemes=geo.visemes,
        expressions=geo.expressions,
    )


@pytest.mark.parametrize("tilted", [False, True])
def test_mix_batch_equals_each_mixer_alone_in_blinks_and_shared_overlays(default_head, tilted):
    """The live path's batch (``mix_batch``) against each session's own mix (``combine``), in the
    cases its shortcuts take: rows in a blink (one override a row), overlays sharing their offsets
    (one expression and amount), a masked one, lids closing over raised cheeks, gaze at the camera
    and at points, eyes looking straight ahead (the built-in head) or not (tilted axes)."""
    from facecast.server.layers.batch import BATCH_MIN, mix_batch

    _, _, geo = default_head
    if tilted:
        geo = _tilted(geo)
    rng = np.random.default_rng(7)
    frames = []
    for k in range(12):
        idle = IdleLayer(seed=k)
        t = float(rng.uniform(0, 60))
        if k % 2:  # in a blink
            t = next(x for x in np.arange(t, t + 60, 0.01) if 0 < idle.closure(x) <= 1)
        m = Mixer(geo, closures=k % 5 != 3)
        m.set("idle", idle)
        m.set("smile", ExpressionLayer(1, amount=0.5))
        if k % 4 == 1:
            m.set("brows", ExpressionLayer(4, amount=0.8, regions=("eyebrows",)))
        target = GazeTarget.camera() if k % 3 else GazeTarget(point=rng.normal(0, 200, 3) + 600)
        m.set("gaze", GazeLayer(target, amount=1.0 if k % 4 else 0.6))
        f = rng.normal(0, 150, 69) * (rng.random(69) < 0.5)
        f[19] = f[20] = 900.0 if k % 3 == 0 else f[19]
        frames.append((m, FaceState(t=t, faps=f), t))
    for n in (BATCH_MIN, 12):
        got = mix_batch(frames[:n])
        for (m, s, t), g in zip(frames, got):
            np.testing.assert_allclose(g.faps, m.mix(s, t).faps, rtol=0, atol=1e-6)


def test_closed_lids_meet_the_cheeks_a_layer_raised(default_head):
    """Rule 5: a blink over a smile, or a smile over a stream's closed lids, closes the upper lids
    onto the lower lids the smile's cheeks lifted, not the full way: the full way folded the skin
    at the eye's outer corner of the built-in head (issue 18)."""
    from facecast.server.deform.quality import QualityMesh, measure

    face, animator, geo = default_head
    idle = IdleLayer(seed=3)
    t = next(t for t in np.arange(0, 30, 0.001) if idle.closure(t) == 1.0)
    cheek = float(EXPRESSIONS[1][41])
    met = LIDS_MEET - LID_PER_CHEEK * cheek
    blink_over_joy = mix(FaceState(t=t, expression=(1, 63, 0, 0)), [idle], t, geometry=geo)
    joy_over_closed = mix(FaceState(t=t, faps=faps(f19=1024, f20=1024)), [ExpressionLayer(1)], t)
    for out in (blink_over_joy, joy_over_closed):
        assert out.faps[19] == pytest.approx(met) and out.faps[20] == pytest.approx(met)
    # below the meeting point (a sad droop under the smile) the lids are the mix's
    sad = mix(FaceState(t=t, faps=faps(f19=250, f20=250)), [ExpressionLayer(1)], t)
    assert sad.faps[19] == pytest.approx(250.0)
    # what the layers do not touch stays the primary's, whatever it is
    own = mix(FaceState(t=t, faps=faps(f19=1024, f41=200)), [GazeLayer(GazeTarget.camera())], t)
    assert own.faps[19] == 1024.0
    qm = QualityMesh.of(face)
    rest = face.vertices
    for out in (blink_over_joy, joy_over_closed):
        points = rest + animator.operator.apply(animator.solve(out)[0])
        assert measure(points, qm)["flips"] == 0


def test_mix_states_equals_mix_frame_by_frame(default_head):
    """The batch render's ``mix_states`` (sampled and combined together, in chunks) gives each
    state what ``mix`` gives it alone, a state with a head transform included."""
    _, _, geo = default_head
    rng = np.random.default_rng(5)
    states = [FaceState(t=i / 30, faps=rng.normal(0, 60, 69)) for i in range(1100)]
    states[7].head = np.hstack([np.eye(3), np.zeros((3, 1))])
    layers = [
        IdleLayer(seed=3),
        GazeLayer(GazeTarget.camera(), envelope=Envelope(start=2.0, end=20.0)),
        ExpressionLayer(1, amount=0.6, envelope=Envelope(end=30.0)),
        HeadPose(pitch=5, yaw=-8),
    ]
    for closures in (True, False):
        got = mix_states(states, layers, geometry=geo, closures=closures)
        for s, g in zip(states, got, strict=True):
            want = mix(s, layers, s.t, geometry=geo, closures=closures)
            assert g.t == want.t and g.expression == want.expression
            np.testing.assert_allclose(g.faps, want.faps, rtol=1e-9, atol=1e-6)
            if want.head is None:
                assert g.head is None
            else:
                np.testing.assert_allclose(g.head, want.head, rtol=1e-9, atol=1e-9)


def _kernel_frames(rng: np.random.Generator, geo: Geometry, n: int, others: bool = False) -> list:
    """``n`` live frames ``(mixer, primary, t)``: idle layers (in blinks too, two at once),
    overlays (shared, masked, of their own FAPs, rising), gaze at the camera and at points
    (weights below 1, two at once); ``others``: and other layers (head gestures and poses,
    tracks, producers' layers, an idle layer in another role)."""
    from facecast.server.live.mixing import Held, contribution_of

    frames = []
    for k in range(n):
        t = float(rng.uniform(0, 60))
        idle = IdleLayer(seed=int(rng.integers(50)), amount=float(rng.uniform(0.3, 1.0)))
        if k % 3 == 1:  # in a blink
            t = next(x for x in np.arange(t, t + 60, 0.01) if 0 < idle.closure(x) <= 1)
        m = Mixer(geo, closures=k % 5 != 3)
        layers: list = [idle, ExpressionLayer(1, amount=0.5)]
        if k % 4 == 1:
            layers.append(ExpressionLayer(4, amount=0.8, regions=("eyebrows", "lips")))
        if k % 4 == 2:
            rise = Envelope(start=t - 0.1, attack_peak=t + 0.2)
            layers.append(ExpressionLayer(0, faps=rng.normal(0, 300, 69), envelope=rise))
        if k % 6 == 5:
            layers.append(IdleLayer(seed=k, blink_rate=40.0, refractory=0.2))
        target = GazeTarget.camera() if k % 3 else GazeTarget(point=rng.normal(0, 200, 3) + 600)
        layers.append(GazeLayer(target, amount=1.0 if k % 4 else 0.6))
        if k % 7 == 3:
            layers.append(GazeLayer(GazeTarget(point=np.array([50.0, -20.0, 700.0])), amount=0.5))
        if others:  # read through their contributions: head gestures and poses, tracks, producers
            g = rng.normal(0, 100, 69) * (rng.random(69) < 0.4)
            extra = [
                HeadGesture("nod", envelope=Envelope(start=t - 0.5, end=t + 1.0)),
                HeadPose(pitch=10, yaw=-5, amount=float(rng.uniform(0.3, 1.0))),
                TrackLayer([FaceState(faps=g, viseme=(3, 0, 63))], fps=25, loop=True),
                Held(Role.GAZE, contribution_of("gaze", FaceState(faps=g))),
                Held(Role.IDLE, contribution_of("idle", FaceState(faps=g))),
                Held(Role.HEAD, contribution_of("head", FaceState(faps=g))),
                Held(Role.EXPRESSION, contribution_of("expression", FaceState(faps=g))),
                Held(Role.IDLE, Contribution(faps=g, weight=1.7)),
                IdleLayer(seed=k, role=Role.EXPRESSION),
            ]
            layers += [extra[i] for i in rng.choice(len(extra), 1 + k % 3, replace=False)]
        rng.shuffle(layers)
        for i, layer in enumerate(layers):
            m.set(f"l{i}", layer)
        f = rng.normal(0, 150, 69) * (rng.random(69) < 0.5)
        f[19] = f[20] = 900.0 if k % 3 == 0 else f[19]
        primary = [
            FaceState(t=t, faps=f),
            FaceState(t=t, faps=np.zeros(69)),  # closed lips: closures cut the overlays
            FaceState(t=t, faps=f, viseme=(int(rng.integers(15)), int(rng.integers(15)), 40)),
            FaceState(t=t, faps=f, expression=(int(rng.integers(1, 7)), 50, 0, 0)),
            None,
        ][k % 5 if k % 11 else 4]
        frames.append((m, primary, t + 0.003 * k))
    return frames


@pytest.mark.parametrize("tilted", [False, True])
def test_the_compiled_mix_equals_each_mixer_alone(default_head, tilted):
    """The live path's compiled kernel (``layers.kernel``) gives each frame what its session's
    own mix (``combine``) gives it, within 1e-9 FAPU, whatever the batch's size (1 to 32 frames)
    and its layers (tilted: other kinds too, read through their contributions); a contribution
    that gazes but not from a ``GazeLayer`` takes the NumPy path, with the same result."""
    from facecast.server.layers import kernel
    from facecast.server.layers.batch import mix_batch
    from facecast.server.live.mixing import Held

    if not kernel.warm(block=True):
        pytest.skip("numba is not installed: the NumPy path mixes every batch")
    _, _, geo = default_head
    if tilted:
        geo = _tilted(geo)
    rng = np.random.default_rng(11 + tilted)
    frames = _kernel_frames(rng, geo, 32, others=tilted)
    packs = []
    real = kernel.pack

    def spy(*args):
        packed = real(*args)
        packs.append(packed)
        return packed

    kernel.pack = spy  # (which path mixed)
    try:
        for n in (1, 2, 5, 32):
            got = mix_batch(frames[:n])
            for (m, s, t), g in zip(frames, got):
                want = m.mix(s, t)
                assert g.t == want.t and g.viseme == want.viseme
                np.testing.assert_allclose(g.faps, want.faps, rtol=0, atol=1e-9)
        assert packs and all(p is not None for p in packs)
        odd = Held(Role.GAZE, Contribution(gaze=GazeTarget.camera(), gaze_weight=0.5))
        frames[0][0].set("odd", odd)
        packs.clear()
        got = mix_batch(frames[:8])
        assert None in packs  # (the group of frame 0's geometry and closures)
        for (m, s, t), g in zip(frames, got):
            np.testing.assert_allclose(g.faps, m.mix(s, t).faps, rtol=0, atol=1e-9)
    finally:
        kernel.pack = real


def test_a_kernel_that_refuses_its_arrays_leaves_the_mix_to_numpy(default_head, monkeypatch):
    """Arrays of a type the kernel was not compiled for (numba refuses them: TypeError) are a bug;
    the batch is mixed by NumPy, as are the next ones, with the same result."""
    from facecast.server.layers import kernel
    from facecast.server.layers.batch import mix_batch

    if not kernel.warm(block=True):
        pytest.skip("numba is not installed")
    _, _, geo = default_head
    frames = _kernel_frames(np.random.default_rng(3), geo, 6)

    def refuse(*args):
        raise TypeError("No matching definition")

    monkeypatch.setattr(kernel, "_compiled", refuse)
    got = mix_batch(frames)
    assert not kernel.ready()
    for (m, s, t), g in zip(frames, got):
        np.testing.assert_allclose(g.faps, m.mix(s, t).faps, rtol=0, atol=1e-9)


def test_idle_closure_and_gaze_remembering_their_spans_equal_the_lookups():
    """``IdleLayer.closure`` skips the blink lookup between the two blinks it last found the lids
    open between, ``gaze`` the fixation lookup in the fixation it last found the eyes holding; at
    every time, in order, out of order and across the horizon, they equal the lookups
    themselves (a fresh layer of the same seed, which remembers nothing: its first lookup)."""
    for seed in range(3):
        idle = IdleLayer(seed=seed, horizon=60.0)
        rng = np.random.default_rng(seed)
        times = [*np.arange(0, 130, 1 / 60), *rng.uniform(0, 200, 3000), *np.arange(59, 61, 1e-3)]
        for t in times:
            fresh = IdleLayer(seed=seed, horizon=60.0)
            assert idle.closure(t) == fresh.closure(t)
            assert idle.gaze(t) == fresh.gaze(t)
