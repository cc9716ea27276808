"""Faces from mesh files: annotations, their validation, axes, and the built-in ICT FaceKit annotation."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from facecast.server.errors import InputError
from facecast.server.faces import load_face
from facecast.server.faces.face import FEATURE_POINT_IDS


def tetra_mesh(tmp_path, annotation: dict | None, suffix=".ply"):
    mesh = trimesh.Trimesh(
        vertices=[[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]],
        faces=[[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        process=False,
    )
    path = tmp_path / f"head{suffix}"
    mesh.export(path)
    if annotation is not None:
        (tmp_path / "head.face.json").write_text(json.dumps(annotation))
    return path


def test_ict_topology_is_recognised_and_annotated(data_dir):
    face = load_face(data_dir / "ict-facekit" / "generic_neutral_mesh.obj")
    assert face.n_vertices == 26719 and face.units == "cm"
    assert set(face.feature_points) == set(FEATURE_POINT_IDS)
    assert len(set(face.feature_points.values())) == 84  # no two points share a vertex
    v = face.vertices
    fp = face.feature_points
    # Left is +x, up is +y, forward is +z, as MPEG-4 says.
    assert v[fp["3.5"], 0] > 0 > v[fp["3.6"], 0]
    assert v[fp["4.3"], 1] > v[fp["3.1"], 1] > v[fp["9.3"], 1] > v[fp["2.2"], 1] > v[fp["2.1"], 1]
    assert v[fp["9.3"], 2] == pytest.approx(
        v[face.part("skin"), 2].max(), abs=0.05
    )  # nose tip in front (0.5 mm)
    # Points land on the right parts.
    assert fp["3.5"] in face.part("eye_l") and fp["3.6"] in face.part("eye_r")
    assert all(fp[k] in face.part("tongue") for k in ("6.1", "6.2", "6.3", "6.4"))
    assert fp["9.10"] in face.part("teeth_upper") and fp["9.11"] in face.part("teeth_lower")
    # The jaw carries lower teeth and tongue; the eyes turn on their own.
    assert set(np.unique(face.rigid_group[face.part("teeth_lower")])) == {1}
    assert set(np.unique(face.rigid_group[face.part("eye_r")])) == {3}
    assert not face.deformable[face.part("teeth_upper")].any()
    # Each eyeball: a transparent cornea shell over an inner sphere whose front disc is the iris.
    for side in "lr":
        eye, cornea, iris = (face.part(f"{p}_{side}") for p in ("eye", "cornea", "iris"))
        assert (
            np.isin(cornea, eye).all()
            and np.isin(iris, eye).all()
            and not np.isin(iris, cornea).any()
        )
        pupil = v[fp["3.5" if side == "l" else "3.6"]]
        centre = v[np.setdiff1d(eye, cornea)].mean(axis=0)
        assert 50 < len(iris) < 0.5 * (len(eye) - len(cornea))  # a disc, not the whole sphere
        assert (((v[iris] - centre) @ (pupil - centre)) > 0).all()  # on the front, round the pupil
        assert (
            np.linalg.norm(v[cornea] - centre, axis=1).max()
            > np.linalg.norm(v[iris] - centre, axis=1).max()
        )


def test_annotation_with_axes_turns_mesh_into_mpeg4_axes(tmp_path):
    # A z-up, y-forward mesh (as many DCC tools export).
    path = tetra_mesh(
        tmp_path,
        {
            "units": "m",
            "axes": {"up": "+z", "forward": "-y"},
            "feature_points": {"2.1": 1},
            "parts": {"skin": [[0, 3]]},
        },
    )
    face = load_face(path)
    assert face.units == "m" and face.mm_per_unit == 1000
    # Old +z (vertex 3) is now +y; old +y (vertex 2) faced backwards, so it is now -z.
    np.testing.assert_allclose(face.vertices[3], [0, 1, 0], atol=1e-6)
    np.testing.assert_allclose(face.vertices[2], [0, 0, -1], atol=1e-6)
    np.testing.assert_allclose(
        face.vertices[1], [1, 0, 0], atol=1e-6
    )  # x = up × forward: +x stays left


@pytest.mark.parametrize(
    ("annotation", "message"),
    [
        ({"feature_points": {"2.99": 0}}, "unknown MPEG-4 feature point(s) 2.99"),
        ({"feature_points": {"2.1": 17}}, "'feature_points.2.1': vertex id 17 is outside 0..3"),
        ({"units": "furlong"}, "'units'"),
        ({"parts": {"skin": [[0, 9]]}}, "'parts.skin': range [0, 9] is outside 0..3"),
        ({"parts": {"tongue": ["a"]}}, "'parts.tongue'"),
        ({"axes": {"up": "+y", "forward": "-y"}}, "'axes'"),
        ({"pivots": {"jaw": [0, 1]}}, "'pivots.jaw'"),
    ],
)
def test_bad_annotations_name_the_field(tmp_path, annotation, message):
    path = tetra_mesh(tmp_path, annotation)
    with pytest.raises(InputError, match="head.face.json") as err:
        load_face(path)
    assert message in str(err.value)


def test_missing_annotation_says_what_to_write(tmp_path):
    path = tetra_mesh(tmp_path, None, suffix=".stl")
    with pytest.raises(InputError, match=r"head\.face\.json.*feature_points"):
        load_face(path)


def test_unknown_face_name_lists_builtins():
    with pytest.raises(InputError, match="built-in faces: default"):
        load_face("no-such-face")


def test_corrupt_obj_is_refused_with_its_line(tmp_path):
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n")
    with pytest.raises(InputError, match="line 4"):
        load_face(bad)
