"""The built-in procedural head (``default``): counts, parts, feature points, FAPU, topology, previews."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest

from facecast.server.errors import InputError
from facecast.server.faces import load_face
from facecast.server.faces.procedural import (
    SKIN_SUBSETS,
    Conformation,
    build_default_head,
    head_colors,
)
from facecast.server.output.preview import render_image, render_png

# MPEG-4 feature points (mpeg4-reference §3): 84 ids.
FP_IDS = (
    [f"2.{i}" for i in range(1, 15)]
    + [f"3.{i}" for i in range(1, 15)]
    + [f"4.{i}" for i in range(1, 7)]
    + [f"5.{i}" for i in range(1, 5)]
    + [f"6.{i}" for i in range(1, 5)]
    + ["7.1"]
    + [f"8.{i}" for i in range(1, 11)]
    + [f"9.{i}" for i in range(1, 16)]
    + [f"10.{i}" for i in range(1, 11)]
    + [f"11.{i}" for i in range(1, 7)]
)
PART_OF = {
    "3.5": "eye_l",
    "3.6": "eye_r",
    "6.1": "tongue",
    "6.2": "tongue",
    "6.3": "tongue",
    "6.4": "tongue",
    "9.8": "teeth_upper",
    "9.10": "teeth_upper",
    "9.9": "teeth_lower",
    "9.11": "teeth_lower",
}
LEFT_RIGHT = [
    ("2.4", "2.5"),
    ("2.6", "2.7"),
    ("2.8", "2.9"),
    ("2.11", "2.12"),
    ("2.13", "2.14"),
    ("3.1", "3.2"),
    ("3.3", "3.4"),
    ("3.5", "3.6"),
    ("3.7", "3.12"),
    ("3.11", "3.8"),
    ("3.9", "3.10"),
    ("3.13", "3.14"),
    ("4.1", "4.2"),
    ("4.3", "4.4"),
    ("4.5", "4.6"),
    ("5.1", "5.2"),
    ("5.3", "5.4"),
    ("6.3", "6.4"),
    ("8.3", "8.4"),
    ("8.5", "8.6"),
    ("8.7", "8.8"),
    ("8.10", "8.9"),
    ("9.1", "9.2"),
    ("9.5", "9.4"),
    ("9.7", "9.6"),
    ("9.13", "9.14"),
    ("10.1", "10.2"),
    ("10.3", "10.4"),
    ("10.5", "10.6"),
    ("10.7", "10.8"),
    ("10.9", "10.10"),
    ("11.3", "11.2"),
]
RIGID_AND_SKIN = (
    "skin",
    "eye_l",
    "eye_r",
    "teeth_upper",
    "teeth_lower",
    "gums_upper",
    "gums_lower",
    "tongue",
)


@pytest.fixture(scope="module")
def head2k():
    return load_face("default:2k")


@pytest.fixture(scope="module")
def head25k():
    return load_face("default")


def _edges(tris: np.ndarray) -> np.ndarray:
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]).astype(np.int64)
    return np.unique(np.sort(e, axis=1), axis=0)


def _fapu(f):
    p = f.fp_position
    return {
        "ES0": p("3.5")[0] - p("3.6")[0],
        "IRISD0": p("3.1")[1] - p("3.3")[1],
        "ENS0": p("3.5")[1] - p("9.15")[1],
        "MNS0": p("9.15")[1] - p("2.2")[1],
        "MW0": p("8.3")[0] - p("8.4")[0],
    }


@pytest.mark.parametrize("n", [2_000, 25_000, 100_000])
def test_vertex_count_follows_the_request(n):
    f = build_default_head(n)
    assert abs(f.n_vertices - n) <= 0.15 * n
    assert f.units == "mm" and f.vertices.dtype == np.float32 and f.triangles.dtype == np.int32


def test_load_face_names(head2k, head25k):
    assert head2k.n_vertices < 3_000
    assert head25k.n_vertices > 20_000
    assert head25k.name.startswith("default")


def test_all_84_feature_points_on_distinct_vertices_of_the_right_parts(head2k, head25k):
    assert len(FP_IDS) == 84
    for f in (head2k, head25k):
        assert sorted(f.feature_points) == sorted(FP_IDS)
        ids = list(f.feature_points.values())
        assert len(set(ids)) == 84
        skin = set(f.part("skin").tolist())
        for fp, vid in f.feature_points.items():
            part = PART_OF.get(fp, "skin")
            assert vid in set(f.part(part).tolist()), (fp, part)
            if part == "skin":
                assert vid in skin


def test_left_points_have_positive_x_and_mirror_the_right(head25k):
    f = head25k
    for left, right in LEFT_RIGHT:
        pl, pr = f.fp_position(left), f.fp_position(right)
        assert pl[0] > 0 > pr[0], (left, right)
        np.testing.assert_allclose(pl * [-1, 1, 1], pr, atol=1e-3)
    for mid in (
        "2.1",
        "2.2",
        "2.3",
        "2.10",
        "8.1",
        "8.2",
        "9.3",
        "9.12",
        "9.15",
        "11.1",
        "11.4",
        "11.6",
        "7.1",
    ):
        assert abs(f.fp_position(mid)[0]) < 1.0, mid


def test_axes_are_mpeg4(head25k):
    p = head25k.fp_position
    assert p("11.4")[1] > p("3.5")[1] > p("9.3")[1] > p("2.2")[1] > p("2.1")[1]  # y up
    assert p("9.3")[2] > p("3.5")[2] > p("10.1")[2] > p("11.6")[2]  # z out of the face
    assert p("9.3")[2] == pytest.approx(max(head25k.vertices[head25k.part("skin"), 2]), abs=25)
    assert p("3.1")[1] > p("3.5")[1] > p("3.3")[1]
    assert p("8.1")[1] > p("2.2")[1] >= p("2.3")[1] > p("8.2")[1]
    assert p("4.3")[1] > p("3.13")[1] > p("3.1")[1]
    assert p("9.8")[1] > p("9.10")[1] >= p("9.11")[1] > p("9.9")[1]


def test_fapu_are_plausible_adult_values(head2k, head25k):
    for f in (head2k, head25k):
        u = _fapu(f)
        assert 60 <= u["ES0"] <= 66
        assert u["IRISD0"] == pytest.approx(11.6, abs=0.05)  # lids tangent to the iris
        assert 38 <= u["ENS0"] <= 55
        assert 15 <= u["MNS0"] <= 30
        assert 45 <= u["MW0"] <= 55


def test_conformation_changes_the_shape_and_rejects_unknown_names():
    wide = build_default_head(2_000, eye_spacing=68.0, mouth_width=56.0)
    u = _fapu(wide)
    assert u["ES0"] == pytest.approx(68.0, abs=0.01)
    assert u["MW0"] > _fapu(build_default_head(2_000))["MW0"] + 4
    assert wide.name != build_default_head(2_000).name
    with pytest.raises(InputError):
        build_default_head(2_000, nose_size=3)
    with pytest.raises(InputError):
        build_default_head(10)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_varied_conformations_stay_valid(seed):
    rng = np.random.default_rng(seed)
    names = [
        "face_width",
        "face_height",
        "jaw_width",
        "nose_length",
        "lip_thickness",
        "eye_spacing",
        "chin_length",
        "mouth_width",
        "brow_height",
        "ear_size",
        "nose_width",
        "head_height",
    ]
    defaults = Conformation()
    kw = {k: float(getattr(defaults, k) * rng.uniform(0.87, 1.13)) for k in names}
    f = build_default_head(2_500, **kw)
    v = f.vertices.astype(np.float64)
    t = f.triangles
    assert np.isfinite(v).all() and len(set(f.feature_points.values())) == 84
    area = np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)
    assert area.min() > 1e-6
    u = _fapu(f)
    assert u["ES0"] == pytest.approx(kw["eye_spacing"], abs=0.01)
    assert all(x > 0 for x in u.values())
    assert f.fp_position("2.2")[1] - f.fp_position("2.1")[1] == pytest.approx(
        kw["chin_length"], abs=12
    )


def test_feature_points_agree_across_resolutions(head2k, head25k):
    big = build_default_head(100_000)
    for fp in FP_IDS:
        for f in (head2k, big):
            d = np.linalg.norm(f.fp_position(fp) - head25k.fp_position(fp))
            assert d < 1.0, (fp, f.n_vertices, d)


def test_deterministic_and_callers_get_their_own_copy():
    a = build_default_head(2_000)
    a.vertices[:] = 0
    b = build_default_head(2_000)
    assert np.abs(b.vertices).max() > 50
    assert b.mesh_hash == build_default_head(2_000).mesh_hash


def test_parts_are_disjoint_and_cover_the_mesh(head2k, head25k):
    for f in (head2k, head25k):
        seen = np.zeros(f.n_vertices, dtype=int)
        for p in RIGID_AND_SKIN:
            assert len(f.part(p)) > 0, p
            seen[f.part(p)] += 1
        assert (seen == 1).all()
        skin = set(f.part("skin").tolist())
        for p in SKIN_SUBSETS:
            assert len(f.part(p)) and set(f.part(p).tolist()) <= skin


def test_triangles_are_valid_and_consistently_oriented(head2k, head25k):
    for f in (head2k, head25k):
        v = f.vertices.astype(np.float64)
        t = f.triangles
        assert np.isfinite(v).all()
        assert t.min() >= 0 and t.max() < f.n_vertices
        area = 0.5 * np.linalg.norm(
            np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1
        )
        assert area.min() > 1e-6
        e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]).astype(np.int64)
        key = e[:, 0] * f.n_vertices + e[:, 1]
        assert len(np.unique(key)) == len(key), (
            "some directed edge is used twice: orientation flips"
        )
        # every edge is shared by exactly two triangles: all parts are closed (the skin too, with
        # the mouth cavity and the sacs behind the eyelids) ...
        und = np.sort(e, axis=1)
        _, counts = np.unique(und[:, 0] * f.n_vertices + und[:, 1], return_counts=True)
        assert (counts == 2).all()
        # ... and each part encloses a positive volume (normals point outwards)
        for p in RIGID_AND_SKIN:
            ids = f.part(p)
            mask = np.isin(t[:, 0], ids)
            tv = v[t[mask]]
            vol = np.einsum("ij,ij->i", tv[:, 0], np.cross(tv[:, 1], tv[:, 2])).sum() / 6
            assert vol > 0, p


def test_lips_touch_but_share_no_edge(head2k, head25k):
    for f in (head2k, head25k):
        up, lo = f.part("lip_upper"), f.part("lip_lower")
        assert len(up) > 10 and len(lo) > 10
        assert not set(up.tolist()) & set(lo.tolist())
        is_up = np.zeros(f.n_vertices, bool)
        is_lo = np.zeros(f.n_vertices, bool)
        is_up[up], is_lo[lo] = True, True
        e = _edges(f.triangles)
        across = (is_up[e[:, 0]] & is_lo[e[:, 1]]) | (is_lo[e[:, 0]] & is_up[e[:, 1]])
        assert not across.any()
        # in contact: the inner lip points sit on top of each other
        assert np.linalg.norm(f.fp_position("2.2") - f.fp_position("2.3")) < 1e-3
        assert f.feature_points["2.2"] in set(up.tolist()) and f.feature_points["2.3"] in set(
            lo.tolist()
        )
        for fp in ("2.6", "2.7"):
            assert f.feature_points[fp] in set(up.tolist())
        for fp in ("2.8", "2.9"):
            assert f.feature_points[fp] in set(lo.tolist())


def test_mouth_cavity_holds_teeth_and_tongue(head25k):
    f = head25k
    lips_z = f.fp_position("2.2")[2]
    for p in ("teeth_upper", "teeth_lower", "tongue", "gums_upper", "gums_lower"):
        assert f.vertices[f.part(p), 2].max() < lips_z - 3, p
    # tongue tip rests behind the lower incisors, at the biting edge
    assert np.linalg.norm(f.fp_position("6.1") - f.fp_position("9.11")) < 10
    assert f.fp_position("6.1")[2] < f.fp_position("9.11")[2]
    socket = f.part("mouth_socket")
    assert f.vertices[socket, 2].min() < lips_z - 40  # the skin turns inward, deep into the head


def _farthest_hits(origin, dirs, v, tris, chunk=128):
    """Distance to the farthest triangle hit along each ray (Moller-Trumbore, vectorised), -inf if none."""
    a, b, c = v[tris[:, 0]], v[tris[:, 1]], v[tris[:, 2]]
    e1, e2 = b - a, c - a
    out = np.full(len(dirs), -np.inf)
    for s in range(0, len(dirs), chunk):
        d = dirs[s : s + chunk][:, None, :]
        pv = np.cross(d, e2[None])
        det = (e1[None] * pv).sum(-1)
        tv = (origin - a)[None]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = (tv * pv).sum(-1) / det
            qv = np.cross(tv, e1[None])
            w = (d * qv).sum(-1) / det
            t = (e2[None] * qv).sum(-1) / det
        hit = (np.abs(det) > 1e-12) & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 0)
        out[s : s + chunk] = np.where(hit, t, -np.inf).max(1)
    return out


def test_inner_parts_stay_inside_the_head(head2k):
    """Cast rays from inside the head: the cavity, teeth, gums and tongue are never beyond the outer skin."""
    f = head2k
    v = f.vertices.astype(np.float64)
    outer = np.zeros(f.n_vertices, bool)
    outer[f.part("skin")] = True
    outer[f.part("mouth_socket")] = False
    tris = f.triangles[outer[f.triangles].all(1)]
    origin = np.array([0.0, -30.0, 20.0])
    for part in (
        "mouth_socket",
        "teeth_upper",
        "teeth_lower",
        "gums_upper",
        "gums_lower",
        "tongue",
        "eye_l",
    ):
        p = v[f.part(part)]
        d = p - origin
        dist = np.linalg.norm(d, axis=1)
        beyond = dist > _farthest_hits(origin, d / dist[:, None], v, tris) + 0.01
        if part == "eye_l":  # the eyeball shows through the lids (and only there)
            assert 0 < beyond.sum() < 0.75 * len(p)
        else:
            assert not beyond.any(), part


def test_eyeballs_are_separate_spheres_seen_through_the_lids(head25k):
    f = head25k
    e = _edges(f.triangles)
    for eye, pupil, up, lo in (("eye_l", "3.5", "3.1", "3.3"), ("eye_r", "3.6", "3.2", "3.4")):
        mask = np.zeros(f.n_vertices, bool)
        mask[f.part(eye)] = True
        assert not (mask[e[:, 0]] ^ mask[e[:, 1]]).any(), "eyeball connected to the skin"
        c = f.pivot(eye)
        r = np.linalg.norm(f.vertices[f.part(eye)] - c, axis=1)
        assert r.min() > 11 and r.max() < 14
        # the pupil looks straight ahead (+z) and the lids are tangent to the iris
        d = f.fp_position(pupil) - c
        assert d[2] > 0.99 * np.linalg.norm(d)
        assert f.fp_position(up)[1] > c[1] > f.fp_position(lo)[1]
        assert f.fp_position(up)[2] > c[2] and f.fp_position(lo)[2] > c[2]
    assert f.fp_position("3.5")[2] > f.fp_position("3.11")[2] - 5


def test_pivots(head25k):
    f = head25k
    for name in ("head", "jaw", "eye_l", "eye_r"):
        assert name in f.pivots
    assert f.pivot("jaw")[2] < f.fp_position("2.2")[2] - 50  # hinge well behind the lips ...
    assert f.pivot("jaw")[1] > f.fp_position("2.2")[1]  # ... and above them
    assert f.pivot("head")[1] < f.fp_position("9.15")[1]
    assert abs(f.pivot("eye_l")[0] - f.fp_position("3.5")[0]) < 0.01


def _read_png(path):
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat, header = 8, b"", None
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + n]
        assert (
            zlib.crc32(kind + body) & 0xFFFFFFFF
            == struct.unpack(">I", data[pos + 8 + n : pos + 12 + n])[0]
        )
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat += body
        pos += 12 + n
    w, h = header[0], header[1]
    raw = np.frombuffer(zlib.decompress(idat), dtype=np.uint8).reshape(h, 1 + w * 3)
    assert (raw[:, 0] == 0).all()
    return raw[:, 1:].reshape(h, w, 3)


def test_preview_png_shows_the_head(head2k, tmp_path):
    out = render_png(
        head2k.vertices,
        head2k.triangles,
        tmp_path / "front.png",
        size=(96, 128),
        colors=head_colors(head2k),
    )
    img = _read_png(out)
    assert img.shape == (128, 96, 3)
    assert (img[0, 0] == (40, 44, 52)).all()  # background in the corner
    assert (img[64, 48] != (40, 44, 52)).any()  # the face in the middle
    side = render_image(head2k.vertices, head2k.triangles, size=(64, 64), view="side")
    front = render_image(head2k.vertices, head2k.triangles, size=(64, 64), view="front")
    assert not np.array_equal(side, front)
    with pytest.raises(ValueError):
        render_image(head2k.vertices, head2k.triangles, view="upside-down")


def test_preview_z_buffer_keeps_the_nearest_triangle():
    # two overlapping squares: red in front (z = 1), blue behind (z = -1), seen from the front
    sq = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
    v = np.concatenate([sq + [0, 0, 1], sq * 2 + [0, 0, -1]])
    t = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    colors = np.array([[1, 0, 0], [1, 0, 0], [0, 0, 1], [0, 0, 1]], float)
    img = render_image(v, t, size=(40, 40), colors=colors)
    centre, edge = img[20, 20], img[20, 2]
    assert centre[0] > centre[2] and edge[2] > edge[0]
