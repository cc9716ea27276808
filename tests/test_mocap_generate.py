"""Marker placement of generated takes: the technician's layout sheet and the motion-weighted one."""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.slow  # the ICT head and its 45 expressions (cached after the first load)


@pytest.fixture(scope="module")
def ict(data_dir):
    from facecast.server.mocap.generate import load_expressions, load_ict

    face = load_ict()
    return face, load_expressions(face)[1]


def test_technician_layout_follows_the_sheet(ict):
    from facecast.server.mocap.generate import TECHNICIAN_LAYOUT, choose_markers

    face, deltas = ict
    names, verts, spec, _ = choose_markers(face, deltas, 60, 5, "technician")
    assert len(names) == len(set(names)) == 60 and len(set(verts.tolist())) == 60
    assert np.isin(verts, face.part("skin")).all()
    sheet = [n for n, _ in TECHNICIAN_LAYOUT]
    assert names[5:] == sheet[:55]  # in the sheet's order, after the 5 stable markers
    assert (
        spec["LIP_CORNER_L"] == {"fp": "8.3"} and face.vertices[face.feature_points["8.3"], 0] > 0
    )
    motion = np.linalg.norm(deltas, axis=2).max(axis=0) * face.mm_per_unit
    assert motion[verts[:5]].max() < 0.01  # stable markers: skin no expression moves
    # the headband spreads round the head: front to back, far wider than the forehead alone
    assert np.ptp(face.vertices[verts[:5], 2]) * face.mm_per_unit > 80.0
    # the face markers crowd the mouth: a third of them within a mouth width of its centre
    mouth = (face.fp_position("8.1") + face.fp_position("8.2")) / 2
    width = np.linalg.norm(face.fp_position("8.3") - face.fp_position("8.4"))
    near = np.linalg.norm(face.vertices[verts[5:]] - mouth, axis=1) < width
    assert near.sum() >= 55 // 3


def test_fewer_markers_keep_the_sheet_priority_and_motion_placement_still_works(ict):
    from facecast.server.errors import InputError
    from facecast.server.mocap.generate import choose_markers

    face, deltas = ict
    names, _, _, _ = choose_markers(face, deltas, 20, 4, "technician")
    assert names[4:8] == ["LIP_UP", "LIP_LO", "LIP_CORNER_L", "LIP_CORNER_R"]
    names, verts, spec, _ = choose_markers(face, deltas, 60, 5, "motion")
    assert len(set(verts.tolist())) == 60 and "FP2_1" in spec
    with pytest.raises(InputError):
        choose_markers(face, deltas, 60, 5, "uniform")


def test_a_take_shorter_than_the_neutral_hold_is_written_whole(ict, tmp_path):
    from facecast.server.mocap.generate import generate, load_truth
    from facecast.server.mocap.io import read_take

    paths = generate(tmp_path, n_markers=20, seconds=0.2, fps=120.0, seed=3, formats=("trc",))
    take = read_take(paths["trc"])
    assert take.xyz.shape == (24, 20, 3)
    assert np.isfinite(take.xyz).all()  # no gaps or spikes: the whole take is the neutral hold
    assert not load_truth(paths["truth"]).weights.any()
