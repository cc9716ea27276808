"""Marker layouts: parsing errors, placement on a face (vertex, FP, automatic), batch driver errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from facecast.server.errors import InputError
from facecast.server.faces.face import Face
from facecast.server.mocap.driver import process
from facecast.server.mocap.layout import load_layout, place_markers
from facecast.server.mocap.synthetic import ellipsoid_face, synthetic_take

GOOD = {
    "units": "mm",
    "stable": ["A", "B", "C"],
    "markers": {
        "A": {"vertex": 0},
        "B": {"vertex": 1},
        "C": {"vertex": 2},
        "D": {"fp": "2.1"},
        "E": {},
    },
}


def test_a_good_layout_parses_and_finds_the_jaw_marker(tmp_path):
    path = tmp_path / "layout.json"
    path.write_text(json.dumps(GOOD))
    lay = load_layout(path)
    assert lay.names == ["A", "B", "C", "D", "E"]
    assert lay.stable == ["A", "B", "C"] and lay.units == "mm" and lay.jaw == "D"
    assert load_layout(json.dumps(GOOD)).names == lay.names


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"stable": ["A", "B"]}, "at least 3 stable"),
        ({"stable": ["A", "B", "Z"]}, "Z are not in 'markers'"),
        ({"markers": {}}, "non-empty"),
        ({"markers": {**GOOD["markers"], "F": {"vertex": -3}}}, "markers.F.*non-negative"),
        (
            {"markers": {**GOOD["markers"], "F": {"vertex": 1, "fp": "2.1"}}},
            "either 'vertex' or 'fp'",
        ),
        ({"markers": {**GOOD["markers"], "F": {"vertx": 1}}}, "unknown key.*vertx"),
        ({"units": "furlongs"}, "unknown length unit"),
        ({"neutral_frame": -1}, "neutral_frame"),
        ({"jaw": "Q"}, "jaw marker 'Q'"),
        ({"extra": 1}, "unknown field"),
    ],
)
def test_layout_errors_name_the_field(change, message):
    with pytest.raises(InputError, match=message):
        load_layout({**GOOD, **change})


def test_bad_json_and_missing_file(tmp_path):
    p = tmp_path / "l.json"
    p.write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        load_layout(p)
    with pytest.raises(InputError, match="no such layout"):
        load_layout(tmp_path / "none.json")


def _face_with_fp() -> Face:
    f = ellipsoid_face(2)
    low = int(np.argmin(f.vertices[:, 1] - 0.5 * f.vertices[:, 2]))
    return Face("e", f.vertices, f.triangles, units="mm", feature_points={"2.1": low})


def test_placement_by_vertex_fp_and_automatic():
    face = _face_with_fp()
    v = face.vertices.astype(np.float64)
    front = np.argsort(-v[:, 2])[:12]
    markers = {f"T{i}": {"vertex": int(j)} for i, j in enumerate(front[:6])}
    markers["CHIN"] = {"fp": "2.1"}
    markers.update({f"U{i}": {} for i in range(4)})
    markers["JIG"] = {"control": False}
    lay = load_layout({"stable": ["T0", "T1", "T2"], "markers": markers})
    # the actor's face is the same shape, scaled to other units and moved
    neutral = {n: v[s["vertex"]] * 10 + 5 for n, s in markers.items() if "vertex" in s}
    neutral["CHIN"] = v[face.feature_points["2.1"]] * 10 + 5
    for i in range(4):
        neutral[f"U{i}"] = v[front[6 + i]] * 10 + 5
    neutral["JIG"] = np.array([0.0, 2000.0, 0.0])
    pl = place_markers(lay, face, neutral)
    assert "JIG" not in pl.names
    assert pl.how.count("auto") == 4 and pl.how.count("fp") == 1
    got = dict(zip(pl.names, pl.vertices.tolist()))
    assert got["CHIN"] == face.feature_points["2.1"]
    for i in range(4):
        assert got[f"U{i}"] == front[6 + i]  # the warp lands each on its own vertex


def test_placement_errors():
    face = _face_with_fp()
    with pytest.raises(InputError, match="out of range"):
        place_markers(
            load_layout(
                {
                    "stable": ["A", "B", "C"],
                    "markers": {"A": {"vertex": 0}, "B": {"vertex": 1}, "C": {"vertex": 10**6}},
                }
            ),
            face,
        )
    with pytest.raises(InputError, match="no feature point 9.9"):
        place_markers(
            load_layout({**GOOD, "markers": {**GOOD["markers"], "D": {"fp": "9.9"}}}),
            face,
            {n: np.zeros(3) for n in GOOD["markers"]},
        )
    three_tied = {**GOOD, "markers": {k: v for k, v in GOOD["markers"].items() if k != "D"}}
    with pytest.raises(InputError, match="at least 4 markers tied"):
        place_markers(
            load_layout(three_tied),
            face,
            {n: np.random.default_rng(0).normal(size=3) for n in GOOD["markers"]},
        )


def test_driver_refuses_takes_that_do_not_fit_the_layout():
    face = ellipsoid_face(2)
    syn = synthetic_take(face, n_markers=10, seconds=0.5)
    lay = dict(syn.layout)
    lay["markers"] = {**lay["markers"], "NOSE": {"vertex": 5}}
    with pytest.raises(InputError, match="lacks 1 marker.*NOSE"):
        process(syn.take, face, lay)
    syn.take.xyz[:, 5] = np.nan
    with pytest.raises(InputError, match="never visible.*M02"):
        process(syn.take, face, syn.layout)
    syn = synthetic_take(face, n_markers=10, seconds=0.5)
    syn.take.xyz[:, :4] = np.nan  # every stable marker lost
    with pytest.raises(InputError, match="never visible"):
        process(syn.take, face, syn.layout)
    syn = synthetic_take(face, n_markers=10, seconds=0.5)
    with pytest.raises(InputError, match="neutral_frame 999"):
        process(syn.take, face, syn.layout, neutral_frame=999)


def test_driver_ignores_markers_the_layout_does_not_name(caplog):
    face = ellipsoid_face(2)
    syn = synthetic_take(face, n_markers=10, seconds=0.5)
    lay = {**syn.layout, "markers": {k: v for k, v in syn.layout["markers"].items() if k != "M06"}}
    proc = process(syn.take, face, lay)
    assert len(proc.rig.control) == 9
    assert "ignoring 1 marker" in caplog.text


def test_anchors_pin_the_far_skin_and_the_neck_but_leave_the_markers_room(data_dir):
    from scipy.spatial import cKDTree

    from facecast.server.faces import load_face
    from facecast.server.mocap.generate import technician_markers
    from facecast.server.mocap.rig import anchor_vertices

    face = load_face(data_dir / "ict-facekit" / "generic_neutral_mesh.obj")
    _, markers, _ = technician_markers(face, 55, [])
    pins = anchor_vertices(face, np.asarray(markers))
    v = face.vertices
    spacing = np.median(cKDTree(v[markers]).query(v[markers], k=2)[0][:, 1])
    assert cKDTree(v[markers]).query(v[pins])[0].min() > 2.0 * spacing  # room round every marker
    below = v[pins, 1] < v[markers, 1].min() - 2.0 * spacing
    assert below.sum() >= 5  # the neck is held
    skin = face.part("skin")
    far = skin[cKDTree(v[markers]).query(v[skin])[0] > 2.0 * spacing]
    # every far skin vertex is within reach of a pin (the pins cover it, they are not just a few)
    assert cKDTree(v[pins]).query(v[far])[0].max() <= 2.0 * spacing + 1e-6
