"""The live marker driver: causal per-frame states, bad frames, changed marker counts."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.server.errors import InputError
from facecast.server.mocap.live import MarkerLiveDriver
from facecast.server.mocap.synthetic import ellipsoid_face, synthetic_take


@pytest.fixture(scope="module")
def setup():
    face = ellipsoid_face(3)
    syn = synthetic_take(face, n_markers=20, seconds=1.5, noise_mm=0.2, seed=3)
    return face, syn


def _run(drv, xyz, fps, start=0):
    out = []
    for i, f in enumerate(xyz):
        out += drv.push(f.astype(np.float32), (start + i) / fps)
    return out


def test_live_states_follow_the_markers_with_head_motion_removed(setup):
    face, syn = setup
    drv = MarkerLiveDriver(face, syn.take.names, syn.layout, neutral_frames=8)
    assert drv.control_vertices is not None and len(drv.control_vertices) >= 20
    states = _run(drv, syn.take.xyz, syn.take.fps)
    n = len(syn.take.xyz)
    assert len(states) == n - 7  # none while the neutral is taken
    assert states[0].t == pytest.approx(7 / syn.take.fps)
    d = np.stack([s.controls for s in states])
    assert len(drv.control_vertices) == d.shape[1]
    assert not d[:, 20:].any()  # anchors (skin far from every marker) stay put
    d = d[:, :20]
    np.testing.assert_array_equal(drv.control_vertices[:20], syn.vertices)
    truth = (syn.local - syn.local[0])[7:]  # face units are mm here
    err = np.linalg.norm(d - truth, axis=2)
    assert err.mean() < 0.35 * np.linalg.norm(truth, axis=2).mean()
    heads = np.stack([s.head for s in states])
    assert heads.shape == (n - 7, 3, 4)
    np.testing.assert_allclose(heads[-1, :, :3], syn.head_r[-1], atol=0.02)


def test_live_driver_survives_occluded_and_empty_frames(setup):
    face, syn = setup
    drv = MarkerLiveDriver(face, syn.take.names, syn.layout, neutral_frames=4)
    xyz = syn.take.xyz.copy()
    xyz[30:40, 6] = np.nan  # a marker lost for a while
    xyz[50] = np.nan  # nothing visible
    xyz[60, :4] = np.inf  # stable markers garbage
    states = _run(drv, xyz[:80], syn.take.fps)
    assert all(np.isfinite(s.controls).all() and np.isfinite(s.head).all() for s in states)
    assert len(states) == 80 - 3


def test_changed_marker_count_is_refused_clearly_and_the_driver_goes_on(setup):
    face, syn = setup
    drv = MarkerLiveDriver(face, syn.take.names, syn.layout, neutral_frames=2)
    _run(drv, syn.take.xyz[:10], syn.take.fps)
    with pytest.raises(InputError, match=r"frame 10.*\(19, 3\).*20 markers"):
        drv.push(syn.take.xyz[10, :19].astype(np.float32), 10 / syn.take.fps)
    assert len(drv.push(syn.take.xyz[10].astype(np.float32), 10 / syn.take.fps)) == 1


def test_live_driver_refuses_a_hello_that_misses_layout_markers(setup):
    face, syn = setup
    with pytest.raises(InputError, match="lacks 1 marker.*HEAD2"):
        MarkerLiveDriver(face, [n for n in syn.take.names if n != "HEAD2"], syn.layout)


def test_automatic_placement_waits_for_the_neutral(setup):
    face, syn = setup
    layout = {**syn.layout, "markers": {**syn.layout["markers"], "M10": {}, "M11": {}}}
    drv = MarkerLiveDriver(face, syn.take.names, layout, neutral_frames=3)
    assert drv.control_vertices is None
    _run(drv, syn.take.xyz[:5], syn.take.fps)
    assert drv.ready and len(drv.control_vertices) >= 20
    names = syn.take.names
    # the automatic placement finds the vertices the markers were generated on
    auto = [int(drv.control_vertices[drv.rig.control_names.index(n)]) for n in ("M10", "M11")]
    assert auto == [int(syn.vertices[names.index(n)]) for n in ("M10", "M11")]


def test_neutral_ignores_frames_where_a_marker_was_hidden(setup):
    face, syn = setup
    xyz = syn.take.xyz.copy()
    xyz[:3, 0] = (
        np.nan
    )  # a stable marker (a jig marker, not on the face) hidden in the first frames
    layout = {**syn.layout, "markers": {**syn.layout["markers"], "HEAD1": {"control": False}}}
    drv = MarkerLiveDriver(face, syn.take.names, layout, neutral_frames=8)
    _run(drv, xyz[:8], syn.take.fps)
    assert drv.ready
    # averaged over the frames that saw it, carried into the first frame's head pose
    # (stabilise.start_neutral): near its plain average, and finite
    assert np.isfinite(drv.rig.neutral).all()
    np.testing.assert_allclose(drv.rig.neutral[0], syn.take.xyz[3:8, 0].mean(axis=0), atol=0.5)
    np.testing.assert_allclose(drv.rig.neutral[1], syn.take.xyz[:8, 1].mean(axis=0), atol=0.5)


def test_wrong_units_are_refused_with_a_clear_message(setup):
    face, syn = setup
    drv = MarkerLiveDriver(
        face, syn.take.names, syn.layout, units="m", neutral_frames=2
    )  # frames are mm
    drv.push(syn.take.xyz[0].astype(np.float32), 0.0)
    with pytest.raises(ValueError, match="not a face; they look like mm"):
        drv.push(syn.take.xyz[1].astype(np.float32), 1 / 120)
    assert not drv.ready


def test_an_unknown_hello_unit_is_refused_at_the_hello(setup):
    face, syn = setup
    with pytest.raises(InputError, match="unknown length unit 'furlong'"):
        MarkerLiveDriver(face, syn.take.names, syn.layout, units="furlong")


@pytest.mark.parametrize(
    ("units", "name"),
    [("mm", "mm"), (" MM ", "mm"), ("Millimeters", "mm"), ("dm", "dm"), ("inches", "in")],
)
def test_hello_units_are_read_by_the_one_unit_table(setup, units, name):
    face, syn = setup
    assert MarkerLiveDriver(face, syn.take.names, syn.layout, units=units).units == name


def test_rotvec_matches_scipy_up_to_a_half_turn():
    """The live pose filter's own matrix -> rotation vector (scipy's cost ~80 us a frame) gives
    scipy's rotation for tiny, ordinary and nearly half turns."""
    from scipy.spatial.transform import Rotation

    from facecast.server.mocap.live import rotvec

    rng = np.random.default_rng(4)
    for angle in (0.0, 1e-9, 1e-4, 0.2, 1.5, 3.0, 3.1, np.pi - 1e-6, np.pi):
        axis = rng.normal(size=3)
        r = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()
        got = rotvec(r)
        assert np.allclose(Rotation.from_rotvec(got).as_matrix(), r, atol=1e-9)
        assert np.linalg.norm(got) <= np.pi + 1e-9
