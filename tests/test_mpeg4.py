"""MPEG-4 tables, FAPU, high-level FAPs and the FAP rig (on a synthetic face and on the ICT head)."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.server.errors import InputError
from facecast.server.faces.face import RIGID_GROUPS, Face
from facecast.server.mpeg4 import (
    EXPRESSIONS,
    FAP_GROUPS,
    FAPS,
    FEATURE_POINTS,
    FP_FAPS,
    VISEMES,
    FapRig,
    expression_faps,
    fap,
    fap_controls,
    measure_fapu,
    viseme_faps,
)
from facecast.server.state import FaceState

# Feature point template of the synthetic face: (x, y) in mm on the front of a sphere (x = face's left).
_TEMPLATE = {
    "2.1": (0, -70),
    "2.2": (0, -33),
    "2.3": (0, -47),
    "2.4": (22, -40),
    "2.5": (-22, -40),
    "2.6": (11, -33),
    "2.7": (-11, -33),
    "2.8": (11, -47),
    "2.9": (-11, -47),
    "2.10": (0, -58),
    "2.11": (18, -62),
    "2.12": (-18, -62),
    "2.13": (58, -45),
    "2.14": (-58, -45),
    "3.1": (30, 24),
    "3.2": (-30, 24),
    "3.3": (30, 4),
    "3.4": (-30, 4),
    "3.7": (48, 14),
    "3.8": (-14, 14),
    "3.9": (30, -4),
    "3.10": (-30, -4),
    "3.11": (14, 14),
    "3.12": (-48, 14),
    "3.13": (30, 32),
    "3.14": (-30, 32),
    "4.1": (12, 40),
    "4.2": (-12, 40),
    "4.3": (30, 46),
    "4.4": (-30, 46),
    "4.5": (50, 40),
    "4.6": (-50, 40),
    "5.1": (42, -22),
    "5.2": (-42, -22),
    "5.3": (44, 0),
    "5.4": (-44, 0),
    "8.1": (0, -26),
    "8.2": (0, -54),
    "8.3": (30, -40),
    "8.4": (-30, -40),
    "8.5": (15, -27),
    "8.6": (-15, -27),
    "8.7": (15, -52),
    "8.8": (-15, -52),
    "8.9": (-6, -24),
    "8.10": (6, -24),
    "9.1": (12, -10),
    "9.2": (-12, -10),
    "9.3": (0, -4),
    "9.4": (-8, -16),
    "9.5": (8, -16),
    "9.6": (-7, 14),
    "9.7": (7, 14),
    "9.12": (0, 6),
    "9.13": (6, 0),
    "9.14": (-6, 0),
    "9.15": (0, -16),
    "10.1": (80, 20),
    "10.2": (-80, 20),
    "10.3": (84, 6),
    "10.4": (-84, 6),
    "10.5": (78, -20),
    "10.6": (-78, -20),
    "10.7": (74, -12),
    "10.8": (-74, -12),
    "10.9": (74, 12),
    "10.10": (-74, 12),
    "11.1": (0, 70),
    "11.2": (-40, 62),
    "11.3": (40, 62),
    "11.4": (0, 96),
    "11.5": (0, 98),
    "11.6": (0, 60),
}


def _sphere(centre, radius, n_lat, n_lon):
    lat = np.linspace(0, np.pi, n_lat)[1:-1]
    lon = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    pts = np.c_[
        (np.sin(la) * np.sin(lo)).ravel(), np.cos(la).ravel(), (np.sin(la) * np.cos(lo)).ravel()
    ]
    pts = np.r_[[[0, 1, 0]], pts, [[0, -1, 0]]] * radius + centre
    tris = []
    rows = n_lat - 2
    for i in range(rows - 1):
        for j in range(n_lon):
            a, b = 1 + i * n_lon + j, 1 + i * n_lon + (j + 1) % n_lon
            c, d = a + n_lon, b + n_lon
            tris += [[a, c, b], [b, c, d]]
    for j in range(n_lon):
        tris.append([0, 1 + j, 1 + (j + 1) % n_lon])
        last = 1 + (rows - 1) * n_lon
        tris.append([len(pts) - 1, last + (j + 1) % n_lon, last + j])
    return pts, np.array(tris)


def synthetic_face(n_lat: int = 40, n_lon: int = 72) -> Face:
    """A ~3k-vertex test head in mm: a skin sphere (r = 100), two eyeballs, lower teeth and a tongue,
    with all 84 MPEG-4 feature points and the pivots it needs."""
    R = 100.0
    parts_pts, parts_tri, parts = [], [], {}
    n = 0
    for name, (c, r, la, lo) in {
        "skin": ((0, 0, 0), R, n_lat, n_lon),
        "eye_l": ((30, 14, 82), 12, 10, 12),
        "eye_r": ((-30, 14, 82), 12, 10, 12),
        "teeth_lower": ((0, -44, 84), 8, 6, 8),
        "tongue": ((0, -44, 70), 10, 8, 10),
    }.items():
        p, t = _sphere(np.array(c, float), r, la, lo)
        parts_pts.append(p)
        parts_tri.append(t + n)
        parts[name] = np.arange(n, n + len(p))
        n += len(p)
    vertices = np.concatenate(parts_pts)
    fps: dict[str, int] = {}
    taken: set[int] = set()

    def nearest(ids, target):
        order = ids[np.argsort(np.linalg.norm(vertices[ids] - target, axis=1))]
        v = next(int(i) for i in order if int(i) not in taken)
        taken.add(v)
        return v

    for fp, (x, y) in _TEMPLATE.items():
        fps[fp] = nearest(parts["skin"], np.array([x, y, np.sqrt(max(R**2 - x**2 - y**2, 0.0))]))
    fps["3.5"] = nearest(parts["eye_l"], np.array([30, 14, 100.0]))
    fps["3.6"] = nearest(parts["eye_r"], np.array([-30, 14, 100.0]))
    fps["7.1"] = nearest(parts["skin"], np.array([0, -40, -100.0]))
    for fp, tgt in {"9.8": (0, -30, 95), "9.10": (0, -36, 95)}.items():
        fps[fp] = nearest(parts["skin"], np.array(tgt, float))
    fps["9.9"] = nearest(parts["teeth_lower"], np.array([0, -52, 90.0]))
    fps["9.11"] = nearest(parts["teeth_lower"], np.array([0, -36, 90.0]))
    for fp, tgt in {
        "6.1": (0, -44, 80),
        "6.2": (0, -38, 70),
        "6.3": (9, -44, 70),
        "6.4": (-9, -44, 70),
    }.items():
        fps[fp] = nearest(parts["tongue"], np.array(tgt, float))
    return Face(
        "synthetic",
        vertices,
        np.concatenate(parts_tri),
        units="mm",
        parts=parts,
        feature_points=fps,
        pivots={"jaw": np.array([0.0, -10.0, 0.0]), "head": vertices[fps["7.1"]]},
    )


@pytest.fixture(scope="module")
def face() -> Face:
    return synthetic_face()


# -- tables -------------------------------------------------------------------------------------


def test_fap_table_has_68_rows_in_10_groups():
    assert [f.number for f in FAPS] == list(range(1, 69))
    assert {g: len(v) for g, v in FAP_GROUPS.items()} == {
        1: 2,
        2: 16,
        3: 12,
        4: 8,
        5: 4,
        6: 5,
        7: 3,
        8: 10,
        9: 4,
        10: 4,
    }
    assert fap("open_jaw").number == 3 and fap(3).unit == "MNS" and not fap(3).bidirectional
    assert [f.number for f in FAPS if not f.bidirectional and f.unit] == [3, 14, 41, 42, 47]
    assert {f.unit for f in FAPS if f.unit} == {"MNS", "MW", "ES", "ENS", "IRISD", "AU"}
    for f in FAPS[2:]:
        assert np.isclose(np.linalg.norm(f.vector), 1.0) or f.direction == "growing", f
    np.testing.assert_array_equal(fap("stretch_l_cornerlip").vector, [1, 0, 0])
    np.testing.assert_array_equal(fap("open_jaw").vector, [0, -1, 0])
    np.testing.assert_array_equal(fap("push_t_lip").vector, [0, 0, 1])


def test_84_feature_points_and_the_45_fap_points():
    assert len(FEATURE_POINTS) == len(set(FEATURE_POINTS)) == 84
    assert set(FP_FAPS) <= set(FEATURE_POINTS)
    assert len(FP_FAPS) == 45  # 2.1-2.10, 3.1-3.6, 4.x, 5.x, 6.x, 8.1-8.8, 9.1-9.3, 10.1-10.4


def test_high_level_blend_formulas():
    assert VISEMES.shape == (15, 69) and EXPRESSIONS.shape == (7, 69)
    assert not VISEMES[0].any() and not EXPRESSIONS[0].any()
    np.testing.assert_allclose(viseme_faps(10, 1, 63), VISEMES[10])
    np.testing.assert_allclose(viseme_faps(10, 1, 0), VISEMES[1])
    np.testing.assert_allclose(
        viseme_faps(10, 1, 21), VISEMES[10] / 3 + VISEMES[1] * 2 / 3, atol=1e-9
    )
    np.testing.assert_allclose(expression_faps(1, 63, 6, 63), EXPRESSIONS[1] + EXPRESSIONS[6])
    assert VISEMES[10][3] > VISEMES[1][3]  # "aa" opens the jaw more than "PP"
    assert (
        EXPRESSIONS[6][31] > 0 > EXPRESSIONS[3][31]
    )  # surprise raises, anger lowers the inner brows


# -- FAPU and controls --------------------------------------------------------------------------


def test_fapu_measured_from_the_feature_points(face):
    u = measure_fapu(face)
    p = face.fp_position
    assert u["ES"] == pytest.approx((p("3.5")[0] - p("3.6")[0]) / 1024)
    assert u["MNS"] == pytest.approx((p("9.15")[1] - p("2.2")[1]) / 1024)
    assert u["IRISD"] == pytest.approx((p("3.1")[1] - p("3.3")[1]) / 1024)
    assert u["AU"] == 1e-5 and all(v > 0 for v in u.values())


def test_fapu_rejects_a_mirrored_face(face):
    mirrored = Face(
        "mirrored",
        face.vertices * [-1, 1, 1],
        face.triangles,
        parts=face.parts,
        feature_points=face.feature_points,
    )
    with pytest.raises(InputError, match=r"ES .*3\.5.*3\.6") as e:
        measure_fapu(mirrored)
    assert "mirrored" in str(e.value)
    lacking = Face("lacking", face.vertices, face.triangles, feature_points={"3.1": 0})
    with pytest.raises(InputError, match="3.3"):
        measure_fapu(lacking)


def test_controls_cover_deformable_feature_points_with_per_axis_constraints(face):
    ids, verts, constrained = fap_controls(face)
    assert len(ids) == len(verts) == len(constrained) == len(set(verts.tolist()))
    assert "3.5" not in ids and "3.6" not in ids  # on the rigid eyeballs
    assert all(face.deformable[verts]) and constrained.all()
    ids2, verts2, constrained = fap_controls(face, per_axis=True)
    assert ids2 == ids and (verts2 == verts).all()
    c = dict(zip(ids, constrained.tolist()))
    assert c["2.2"] == [False, True, True]  # FAP 4 (y) and 17 (z)
    assert c["5.1"] == [True, False, False]  # puff: x only
    assert c["2.1"] == c["3.7"] == c["6.1"] == [True, True, True]  # jaw rider, anchor, tongue tip


# -- the rig ------------------------------------------------------------------------------------


def _state(**faps) -> FaceState:
    s = FaceState()
    for k, v in faps.items():
        s.faps[int(k[1:])] = v
    return s


def test_translation_faps_move_their_feature_point_by_value_times_fapu(face):
    rig = FapRig(face)
    u = rig.fapu
    ids = {fp: i for i, name in enumerate(rig.fp_ids) for fp in name.split("+")}
    D, T = rig.solve(_state(f4=200, f6=-100, f31=512, f39=300))
    np.testing.assert_allclose(D[ids["2.2"]], [0, -200 * u["MNS"], 0], atol=1e-5)
    np.testing.assert_allclose(D[ids["2.4"]], [-100 * u["MW"], 0, 0], atol=1e-5)
    np.testing.assert_allclose(D[ids["4.1"]], [0, 512 * u["ENS"], 0], atol=1e-5)
    np.testing.assert_allclose(D[ids["5.1"]], [300 * u["ES"], 0, 0], atol=1e-5)
    assert np.abs(D[ids["3.7"]]).max() == 0  # anchor
    np.testing.assert_allclose(T, np.tile(np.eye(3, 4), (len(RIGID_GROUPS), 1, 1)), atol=1e-7)


def test_open_jaw_drops_the_chin_by_the_fap_amount_and_carries_the_jaw_group(face):
    rig = FapRig(face)
    ids = {fp: i for i, name in enumerate(rig.fp_ids) for fp in name.split("+")}
    D, T = rig.solve(_state(f3=512))
    drop = 512 * rig.fapu["MNS"]
    assert D[ids["2.1"], 1] == pytest.approx(-drop, rel=1e-4)
    chin = face.fp_position("2.1")
    jaw = T[RIGID_GROUPS.index("jaw")]
    assert (jaw[:, :3] @ chin + jaw[:, 3])[1] == pytest.approx(chin[1] - drop, rel=1e-4)
    R = jaw[:, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-6)
    assert R[1, 2] < 0  # rotation about +x that turns the chin down
    np.testing.assert_allclose(T[0], np.eye(3, 4), atol=1e-7)
    # thrust and shift translate the jaw: +z and -x
    _, T2 = rig.solve(_state(f14=100, f15=100))
    np.testing.assert_allclose(
        T2[1][:, 3], [-100 * rig.fapu["MW"], 0, 100 * rig.fapu["MNS"]], atol=1e-5
    )


def test_head_and_eye_rotations_compose(face):
    rig = FapRig(face)
    a = 0.1 / 1e-5  # 0.1 rad in AU
    _, T = rig.solve(_state(f49=a))  # head yaw left: the nose turns toward +x
    head = T[0]
    nose = face.fp_position("9.3")
    assert (head[:, :3] @ nose + head[:, 3])[0] > nose[0] + 1.0
    pivot = face.pivot("head")
    np.testing.assert_allclose(head[:, :3] @ pivot + head[:, 3], pivot, atol=1e-4)
    for g in range(1, 4):  # every group carries the head pose
        np.testing.assert_allclose(T[g], head, atol=1e-6)
    _, T = rig.solve(_state(f25=a))  # left eyeball pitches down about its centre, right one still
    eye = T[RIGID_GROUPS.index("eye_l")]
    pupil = face.fp_position("3.5")
    assert (eye[:, :3] @ pupil + eye[:, 3])[1] < pupil[1] - 0.5
    c = face.pivot("eye_l")
    np.testing.assert_allclose(eye[:, :3] @ c + eye[:, 3], c, atol=1e-4)
    np.testing.assert_allclose(T[RIGID_GROUPS.index("eye_r")], np.eye(3, 4), atol=1e-7)
    head_pose = np.eye(3, 4)
    head_pose[:, 3] = [0, 5, 0]
    s = _state(f49=a)
    s.head = head_pose
    _, T = rig.solve(s)  # an explicit head pose replaces FAPs 48-50
    np.testing.assert_allclose(T[0], head_pose, atol=1e-7)


def test_visemes_and_expressions_drive_the_same_points_as_low_level_faps(face):
    rig = FapRig(face)
    s = FaceState(viseme=(10, 0, 63))
    D, T = rig.solve(s)
    D2, T2 = rig.solve(FaceState(faps=VISEMES[10].copy()))
    np.testing.assert_allclose(D, D2, atol=1e-6)
    np.testing.assert_allclose(T, T2, atol=1e-6)
    D3, _ = rig.solve(FaceState(expression=(1, 63, 0, 0)))
    assert np.abs(D3).max() > 0
    with pytest.raises(InputError, match="viseme id 20"):
        rig.solve(FaceState(viseme=(20, 0, 0)))


def test_explicit_controls_replace_feature_points_but_faps_still_move_rigid_parts(face):
    verts = face.part("skin")[:5]
    rig = FapRig(face, control_vertices=verts)
    s = _state(f3=400)
    D, T = rig.solve(s)
    assert D.shape == (5, 3) and not D.any()
    assert not np.allclose(T[1], np.eye(3, 4))
    s.controls = np.ones((5, 3), np.float32)
    np.testing.assert_array_equal(rig.solve(s)[0], 1.0)


def test_ict_head_fapu_is_anatomically_plausible(data_dir):
    from facecast.server.faces import load_face
    from facecast.server.mpeg4 import fapu_mm

    face = load_face(data_dir / "ict-facekit" / "generic_neutral_mesh.obj")
    mm = fapu_mm(face)
    assert 8 < mm["IRISD0"] < 14 and 50 < mm["ES0"] < 75 and 40 < mm["MW0"] < 65
    assert 10 < mm["MNS0"] < 30 and 30 < mm["ENS0"] < 60


def test_jaw_drop_is_exact_even_when_the_pivot_sits_almost_above_the_chin(face):
    above = Face(
        "above",
        face.vertices,
        face.triangles,
        parts=face.parts,
        feature_points=face.feature_points,
        pivots={**face.pivots, "jaw": face.fp_position("2.1") + [0, 80, -5]},
    )
    rig = FapRig(above)
    ids = {fp: i for i, name in enumerate(rig.fp_ids) for fp in name.split("+")}
    D, T = rig.solve(_state(f3=1000))
    assert D[ids["2.1"], 1] == pytest.approx(-1000 * rig.fapu["MNS"], rel=1e-4)
    assert np.isfinite(T).all()


def test_high_level_tables_can_be_replaced_per_face(face):
    custom = np.zeros((15, 69))
    custom[5, 3] = 700
    rig = FapRig(face, visemes=custom)
    D, T = rig.solve(FaceState(viseme=(5, 0, 63)))
    D2, T2 = rig.solve(_state(f3=700))
    np.testing.assert_allclose(D, D2, atol=1e-6)
    np.testing.assert_allclose(T, T2, atol=1e-6)
    with pytest.raises(ValueError, match="shape"):
        FapRig(face, expressions=np.zeros((6, 69)))
