"""Automatic annotation of head meshes without a ``.face.json`` ("bring your own head").

The heads of ``../shared/data/heads`` (a body, a face mask, a statue, an ICT shape variant) and the
built-in head at another resolution are annotated once per module (each takes seconds); the tests
then check what a user relies on: the annotation loads, FAPs animate the right way (the jaw opens
downwards, a smile widens the mouth), full-strength expressions flip no triangle, seams stay closed.
"""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from facecast.server.deform.quality import QualityMesh, measure
from facecast.server.errors import InputError
from facecast.server.faces import load_face
from facecast.server.faces.annotate import annotate_mesh, merge
from facecast.server.faces.annotate.orient import frame
from facecast.server.faces.loaders import face_from_annotation
from facecast.server.mpeg4 import measure_fapu
from facecast.server.pipeline import Animator
from facecast.server.state import FaceState

HEADS = {
    "body": "makehuman-base/base.obj.xz",
    "mask": "mediapipe-face/canonical_face_model.obj",
    "statue": "demosthenes/demosthenes-low-res.obj.xz",
    "ict": "ict-identities/identity002.obj.xz",
}


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    import os

    old = os.environ.get("FACECAST_CACHE")
    os.environ["FACECAST_CACHE"] = str(tmp_path_factory.mktemp("cache"))
    yield
    if old is None:
        os.environ.pop("FACECAST_CACHE", None)
    else:
        os.environ["FACECAST_CACHE"] = old


@pytest.fixture(scope="module")
def faces(cache):
    """name -> Face loaded through the automatic annotation (mesh files with no annotation beside)."""
    from facecast.server.paths import shared_data

    data = shared_data()
    out = {"builtin-3k": _builtin_face(3000)}
    if data is not None:
        for name, rel in HEADS.items():
            if (
                name == "ict"
            ):  # ICT's topology is recognised: annotate it automatically all the same
                shipped = load_face(data / "heads" / rel)
                ann = annotate_mesh(shipped.vertices, shipped.triangles)
                out[name] = (
                    face_from_annotation(
                        "ict (automatic)", shipped.vertices, shipped.triangles, ann, where="test"
                    ),
                    shipped,
                )
            else:
                out[name] = load_face(data / "heads" / rel)
    return out


def _builtin_face(n: int):
    f = load_face(f"default:{n // 1000}k")
    ann = annotate_mesh(f.vertices, f.triangles)
    _REPORTS[f"builtin-{n // 1000}k"] = ann["automatic"]
    return face_from_annotation(
        f"default:{n // 1000}k (automatic)", f.vertices, f.triangles, ann, where="test"
    ), f


_REPORTS: dict = {}


def _face(faces, name):
    if name not in faces:
        pytest.skip("../shared/data/heads is not present")
    face = faces[name]
    return face[0] if isinstance(face, tuple) else face


NAMES = ["builtin-3k", *HEADS]


@pytest.mark.parametrize("name", NAMES)
def test_annotation_gives_fapu_and_the_points_on_the_right_side(faces, name):
    face = _face(faces, name)
    fapu = measure_fapu(face)  # raises when a FAPU point is missing or misplaced
    assert all(v > 0 for v in fapu.values())
    v, fp = face.vertices, face.feature_points
    assert v[fp["3.5"], 0] > v[fp["3.6"], 0]  # left eye on +x (MPEG-4 axes)
    assert v[fp["8.3"], 0] > v[fp["8.4"], 0]
    assert v[fp["4.3"], 1] > v[fp["9.3"], 1] > v[fp["2.2"], 1]  # brow above nose tip above mouth
    assert len(set(fp.values())) == len(fp)  # no two points share a vertex
    assert len(fp) >= 55


def _deformed(face, state):
    anim = Animator(face, backend="numpy")
    return anim.frame(state)


@pytest.mark.parametrize("name", NAMES)
def test_jaw_opens_downwards_and_a_smile_widens_the_mouth(faces, name):
    face = _face(faces, name)
    fp = face.feature_points
    faps = np.zeros(69)
    faps[3] = 400  # open_jaw, in MNS
    opened = _deformed(face, FaceState(faps=faps))
    chin = fp.get("2.1", fp.get("2.10"))  # the jaw FAP moves the chin (lips have their own FAPs)
    mns = face.vertices[fp["9.15"], 1] - face.vertices[fp["2.2"], 1]
    assert opened[chin, 1] < face.vertices[chin, 1] - 0.2 * mns
    smile = _deformed(face, FaceState(expression=(1, 63, 0, 0)))  # joy at full strength
    assert smile[fp["8.3"], 0] > face.vertices[fp["8.3"], 0]
    assert smile[fp["8.4"], 0] < face.vertices[fp["8.4"], 0]


def _flips(face) -> list[int]:
    qm = QualityMesh.of(face)
    anim = Animator(face, backend="numpy")
    return [
        measure(anim.frame(FaceState(expression=(e, 63, 0, 0))), qm)["flips"] for e in range(1, 7)
    ]


#: Flipped triangles allowed per expression at full strength on heads without a hand-made annotation
#: to compare with. The engine flips some with hand-made annotations too (built-in 3k head: 2 in
#: anger; ICT identity002 with the shipped annotation: 74 over the six expressions; automatic: 31),
#: so those two heads are held to their shipped annotation's count (+2; measured: built-in 3 against
#: 2, ICT 31 against 74); measured here: mask 3, body 6.
FLIPS_ALLOWED = 6


@pytest.mark.parametrize("name", NAMES)
def test_full_strength_expressions_flip_no_more_triangles_than_the_shipped_annotation(faces, name):
    face = _face(faces, name)
    flips = _flips(face)
    if name in ("builtin-3k", "ict"):
        shipped = _flips(faces[name][1])
        assert sum(flips) <= sum(shipped) + 2, (flips, shipped)
    else:
        assert max(flips) <= FLIPS_ALLOWED, flips


def test_builtin_head_points_land_near_its_own(faces):
    # Was mean 0.78, worst 9.1 mm: the mouth corners were anchored 6 mm inside the template's own,
    # and a coarse mesh's lip and eye-corner vertices (where the surface folds, facing away from
    # the template's normal, or inside the eye-socket test) were passed over for far ones.
    auto, truth = faces["builtin-3k"]
    d = np.array(
        [
            np.linalg.norm(auto.vertices[v] - truth.vertices[truth.feature_points[k]])
            for k, v in auto.feature_points.items()
        ]
    )
    assert len(d) == 84 and d.mean() < 1.0 and d.max() < 6.0, (d.mean(), d.max())
    assert _REPORTS["builtin-3k"]["template"] == "default"


def _bench():
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location(
        "bench_annotate", Path(__file__).parents[1] / "bench" / "annotate.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_a_remeshed_ict_variant_is_fitted_with_the_ict_template_within_2mm(cache):
    # Was mean 3.2-3.6 mm, worst 13 mm with the built-in head as the only template.
    from facecast.server.faces.obj import read_obj
    from facecast.server.paths import shared_data

    data = shared_data()
    if (
        data is None
        or not (data / "ict-facekit" / "generic_neutral_mesh.obj").is_file()
        or not (data / "heads" / HEADS["ict"]).is_file()
    ):
        pytest.skip("../shared/data has no ICT FaceKit")
    bench = _bench()
    shipped = json.loads(
        (__import__("facecast.server.faces.ict", fromlist=["x"]).ANNOTATION).read_text()
    )
    v, tri = read_obj(data / "heads" / "ict-identities" / "identity003.obj.xz")
    truth = {k: v[i].astype(np.float64) for k, i in shipped["feature_points"].items()}
    rv, rt = bench.remesh(v.astype(np.float64), tri, 0.15, seed=3)
    auto = annotate_mesh(rv, rt)
    assert auto["automatic"]["template"] == "ict", auto["automatic"]["template_scores_mm"]
    s = bench.score(auto, rv, truth, 10.0, bench.DEFINITIONAL)
    assert s["n"] >= 40 and s["mean_mm"] < 2.0 and s["max_mm"] < 6.0, s["worst"]


def test_the_builtin_template_on_a_remeshed_ict_head_finds_its_mouth_corners_and_incisors(cache):
    # A template of another family (the built-in head's slit fades 7 mm inside its own corners;
    # its teeth are short; ICT's are one piece a tooth). Was: corners 11 mm, 9.11 10 mm (9.10 19 mm
    # on the other identities).
    from facecast.server.faces.obj import read_obj
    from facecast.server.paths import shared_data

    data = shared_data()
    if data is None or not (data / "heads" / "ict-identities" / "identity000.obj.xz").is_file():
        pytest.skip("../shared/data has no ICT identities")
    bench = _bench()
    shipped = json.loads(
        (__import__("facecast.server.faces.ict", fromlist=["x"]).ANNOTATION).read_text()
    )
    v, tri = read_obj(data / "heads" / "ict-identities" / "identity000.obj.xz")
    truth = {k: v[i].astype(np.float64) for k, i in shipped["feature_points"].items()}
    rv, rt = bench.remesh(v.astype(np.float64), tri, 0.15, seed=0)
    auto = annotate_mesh(rv, rt, template="default")
    s = bench.score(auto, rv, truth, 10.0, bench.DEFINITIONAL)
    d = s["per_point_mm"]
    # (the built-in head's 9.10 sits 4.4 mm off the midline, ICT's on it)
    assert max(d["8.3"], d["8.4"]) < 6.0 and max(d["9.10"], d["9.11"]) < 10.0, d
    assert s["mean_mm"] < 4.0 and s["max_mm"] < 12.0, s["worst"]


def test_an_unknown_template_is_refused(faces):
    _, truth = faces["builtin-3k"]
    with pytest.raises(InputError, match="unknown template"):
        annotate_mesh(truth.vertices, truth.triangles, template="bogus")


def test_ict_variant_points_land_near_the_shipped_ones(faces):
    face = _face(faces, "ict")
    shipped = json.loads(
        (__import__("facecast.server.faces.ict", fromlist=["x"]).ANNOTATION).read_text()
    )
    core = ("9.3", "9.15", "2.2", "8.1", "8.2", "3.5", "3.6", "8.3", "8.4", "3.7", "3.12")
    d = [
        np.linalg.norm(
            face.vertices[face.feature_points[k]] - face.vertices[shipped["feature_points"][k]]
        )
        * 10
        for k in core
        if k in face.feature_points
    ]
    assert len(d) == len(core) and np.mean(d) < 8.0, d


def test_a_mask_says_what_it_left_out(faces):
    face = _face(faces, "mask")
    assert (
        "7.1" not in face.feature_points and "11.6" not in face.feature_points
    )  # no back of the head
    assert "teeth_upper" not in face.parts


def test_a_body_is_cropped_to_its_head(faces):
    face = _face(faces, "body")
    fp = np.array([face.vertices[v] for v in face.feature_points.values()])
    assert np.ptp(fp[:, 1]) * face.mm_per_unit < 300  # all points on the head, none on the body
    assert face.units == "dm"


def test_a_head_on_its_side_facing_minus_z_is_turned_upright(faces):
    _, builtin = faces["builtin-3k"]
    rot = frame("+x", "-z")  # up along +x, facing -z
    v = builtin.vertices.astype(np.float64) @ rot
    ann = annotate_mesh(v, builtin.triangles)
    assert ann["axes"] == {"up": "+x", "forward": "-z"}
    face = face_from_annotation("turned", v, builtin.triangles, ann, where="test")
    measure_fapu(face)
    assert (
        face.vertices[face.feature_points["9.3"], 2] > face.vertices[face.feature_points["7.1"], 2]
    )


def test_user_landmarks_give_the_alignment(faces, tmp_path):
    from facecast.server.faces.annotate.landmarks import read_landmarks

    _, builtin = faces["builtin-3k"]
    rot = frame("-z", "+x")
    v = builtin.vertices.astype(np.float64) @ rot * 0.1  # cm, lying on its back... upside down
    keys = ("9.3", "3.7", "3.12", "8.3", "8.4", "2.1")
    (tmp_path / "lm.json").write_text(
        json.dumps({k: v[builtin.feature_points[k]].tolist() for k in keys})
    )
    lm = read_landmarks(tmp_path / "lm.json", len(v))
    ann = annotate_mesh(v, builtin.triangles, landmarks=lm)
    assert ann["axes"] == {"up": "-z", "forward": "+x"} and ann["units"] == "cm"
    for k in keys:
        assert (
            np.linalg.norm(v[ann["feature_points"][k]] - v[builtin.feature_points[k]]) < 0.4
        )  # 4 mm


def test_units_come_from_the_head_size(faces):
    _, builtin = faces["builtin-3k"]
    ann = annotate_mesh(builtin.vertices / 1000.0, builtin.triangles)  # metres
    assert ann["units"] == "m"


def test_seams_split_in_a_glb_move_together(tmp_path, faces, cache):
    """A glTF file splits vertices at UV seams; the loader welds them, so a seam cannot open."""
    _, builtin = faces["builtin-3k"]
    skin = builtin.part("skin")
    tri = builtin.triangles[np.isin(builtin.triangles, skin).all(axis=1)]
    used = np.unique(tri)
    v = builtin.vertices[used] / 1000.0  # glTF is in metres
    t = np.searchsorted(used, tri)
    left = v[t].mean(axis=1)[:, 0] < 0  # a seam down the middle of the face
    n = len(v)
    t[left] += n
    path = tmp_path / "seam.glb"
    trimesh.Trimesh(np.r_[v, v], t, process=False).export(path)
    face = load_face(path)
    assert face.units == "m"
    rounded = np.round(face.vertices / 1e-7).astype(np.int64)
    assert len(np.unique(rounded, axis=0)) == face.n_vertices  # no split vertex left
    moved = _deformed(face, FaceState(expression=(1, 63, 0, 0)))
    assert np.all(np.isfinite(moved)) and np.abs(moved - face.vertices).max() > 0


def test_a_users_partial_annotation_wins(tmp_path, cache, faces):
    _, builtin = faces["builtin-3k"]
    path = tmp_path / "head.ply"
    trimesh.Trimesh(builtin.vertices, builtin.triangles, process=False).export(path)
    face = load_face(path)  # automatic
    corner = face.feature_points["8.3"]
    neighbour = int(builtin.triangles[np.any(builtin.triangles == corner, axis=1)][0].max())
    (tmp_path / "head.face.json").write_text(json.dumps({"feature_points": {"8.3": neighbour}}))
    corrected = load_face(path)
    assert corrected.feature_points["8.3"] == neighbour
    assert set(corrected.feature_points) == set(face.feature_points)


def test_merge_drops_an_automatic_point_on_the_users_vertex():
    auto = {"units": "cm", "feature_points": {"2.1": 5, "2.2": 7}, "parts": {"skin": [[0, 9]]}}
    out = merge(auto, {"feature_points": {"2.3": 5}, "units": "mm"})
    assert out["feature_points"] == {"2.2": 7, "2.3": 5} and out["units"] == "mm"
    assert out["parts"] == {"skin": [[0, 9]]}


def test_annotating_a_non_head_is_refused():
    box = trimesh.creation.box(extents=(1, 2, 3)).subdivide().subdivide().subdivide()
    with pytest.raises(InputError):
        annotate_mesh(np.asarray(box.vertices), np.asarray(box.faces))


def test_cli_writes_an_annotation_and_a_preview(tmp_path, cache, faces, capsys):
    from facecast.server.cli import main

    _, builtin = faces["builtin-3k"]
    path = tmp_path / "head.obj"
    trimesh.Trimesh(builtin.vertices, builtin.triangles, process=False).export(path)
    assert main(["faces", "annotate", str(path), "--preview", str(tmp_path / "p.png")]) == 0
    ann = json.loads((tmp_path / "head.face.json").read_text())
    assert len(ann["feature_points"]) == 84 and (tmp_path / "p.png").read_bytes()[:4] == b"\x89PNG"
    assert main(["faces", "annotate", str(path)]) == 2  # the user's annotation is never overwritten
    assert "already exists" in capsys.readouterr().err


def test_loading_a_mesh_without_annotation_says_so_once(tmp_path, cache, faces, caplog):
    _, builtin = faces["builtin-3k"]
    path = tmp_path / "again.ply"
    trimesh.Trimesh(builtin.vertices * 1.01, builtin.triangles, process=False).export(path)
    with caplog.at_level(logging.WARNING):
        load_face(path)
        load_face(path)  # from the cache
    said = [r for r in caplog.records if "annotated it automatically" in r.getMessage()]
    assert len(said) == 1


_json = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5),
    lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=5), c, max_size=4),
    max_leaves=12,
)


@settings(max_examples=200, deadline=None)
@given(
    data=st.one_of(
        _json,
        st.dictionaries(
            st.sampled_from(["9.3", "3.7", "3.12", "8.3", "2.1", "x"]), _json, max_size=5
        ),
    )
)
def test_landmark_files_are_parsed_or_refused_with_a_project_error(data):
    from facecast.server.faces.annotate.landmarks import parse_landmarks

    try:
        out = parse_landmarks(data, 100)
    except InputError:
        return
    assert len(out) >= 3 and all(
        isinstance(p, int) or np.asarray(p).shape == (3,) for p in out.values()
    )


def test_a_piece_seen_only_at_its_back_is_not_shifted_to_the_template_pieces_front():
    # identity004 with the built-in template: its "upper teeth" were a few back teeth, and their
    # "front" pulled 9.10 51 mm back (60 mm off).
    from scipy.spatial import cKDTree

    from facecast.server.faces.annotate.core import _front_shift

    rng = np.random.default_rng(0)
    x = rng.uniform(-25, 25, 400)
    arch = np.c_[x, rng.uniform(-5, 5, 400), 90 - 0.08 * x**2]  # a dental arch, front at z = 90
    back = rng.uniform([-4, -5, 40], [4, 5, 52], (40, 3))  # the mesh's piece: a few back teeth
    assert np.allclose(_front_shift(arch, back, cKDTree(back)).translation, 0)
    ahead = arch + [0, 4, 3]  # the whole piece, 5 mm off: its front is matched
    shift = _front_shift(arch, ahead, cKDTree(ahead)).translation
    assert np.linalg.norm(shift - [0, 4, 3]) < 2.0, shift
