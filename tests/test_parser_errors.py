"""Each parser defect of issue 12: malformed input gives the project's error naming what is wrong,
never a raw ValueError/TypeError/KeyError/UnicodeDecodeError. (C3D: test_c3d.py; fuzzing:
test_fuzz_parsers.py.)"""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from facecast.protocol.errors import FileFormatError, ProtocolError
from facecast.protocol.fap_file import FapFile, FapFormatError, FapFrame, read_fap, write_fap
from facecast.protocol.markers_file import MarkerFileError, read_csv, read_trc
from facecast.protocol.topology import TopologyError
from facecast.server.drivers import fap as fap_driver
from facecast.server.errors import CLIENT_ERRORS, InputError, as_facecast_error
from facecast.server.faces import load_face
from facecast.server.faces.loaders import face_from_annotation, parse_annotation

# ------------------------------------------------------------------------------------- error tree


@pytest.mark.parametrize("cls", [FapFormatError, MarkerFileError, TopologyError])
def test_file_format_errors_are_protocol_errors_the_api_maps_to_400(cls):
    assert issubclass(cls, FileFormatError) and issubclass(cls, ProtocolError)
    assert issubclass(cls, ValueError)  # existing `except ValueError` callers still catch them
    err = as_facecast_error(cls("bad"))
    assert isinstance(err, InputError) and err.status == 400
    assert isinstance(cls("bad"), CLIENT_ERRORS)


def test_fap_error_keeps_its_line_and_file():
    e = FapFormatError("bad", line=3, where="x.fap")
    assert (e.line, e.where, e.reason, str(e)) == (3, "x.fap", "bad", "x.fap:3: bad")
    assert str(as_facecast_error(e)) == "x.fap:3: bad"


# -------------------------------------------------------------------------------------------- FAP

HEADER = "2.1 test 25 1\n"
MASK = " ".join(["0"] * 2 + ["1"] + ["0"] * 65) + "\n"


@pytest.mark.parametrize(
    ("text", "words"),
    [
        (
            HEADER + MASK + "0 " + "9" * 4301 + "\n",
            "value '99999",
        ),  # over Python's int-string limit
        (HEADER + MASK + "9" * 4301 + " 5\n", "frame number '9999"),
        ("2.1 test 25 " + "9" * 4301 + "\n", "number of frames '9999"),
        ("2.1 test " + "9" * 4301 + " 0\n", "frame rate '9999"),
        (HEADER + MASK + "0 1234567890123456789\n", "19 digits"),
    ],
)
def test_huge_fap_integers_are_format_errors_with_a_line(text, words):
    with pytest.raises(FapFormatError, match=words) as e:
        read_fap(text, where="big.fap")
    assert e.value.line in (1, 3) and len(str(e.value)) < 300


def test_huge_fap_integer_through_the_server_reader(tmp_path):
    path = tmp_path / "big.fap"
    path.write_text(HEADER + MASK + "0 " + "9" * 4301 + "\n")
    with pytest.raises(InputError, match=r"big\.fap:3: value"):
        fap_driver.read(path)


def test_write_fap_refuses_integers_it_could_not_read_back():
    frame = FapFrame.build(0, {3: 10**18})
    with pytest.raises(FapFormatError, match="digits"):
        write_fap(FapFile(frames=(frame,)))
    assert read_fap(write_fap(FapFile(frames=(FapFrame.build(0, {3: 10**18 - 1}),)))).frames[
        0
    ].values == (10**18 - 1,)


# ------------------------------------------------------------------------------------- annotation

VERTS = np.zeros((4, 3), np.float32)
TRIS = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int32)


@pytest.mark.parametrize(
    ("annotation", "field"),
    [
        ({"units": {}}, "'units'"),
        ({"units": ["mm"]}, "'units'"),
        (
            {"pivots": 1},
            "'pivots' must be a JSON object like {\"jaw\": [0, -1.5, 2.0]}, not a number",
        ),
        ({"pivots": {"jaw": "abc"}}, "'pivots.jaw'"),
        ({"pivots": {"jaw": [1, [2], 3]}}, "'pivots.jaw'"),
        ({"pivots": {"jaw": [True, 0, 0]}}, "'pivots.jaw'"),
        ({"parts": [1, 2]}, "'parts'"),
        ({"parts": {"skin": 5}}, "'parts.skin'"),
        ({"parts": {"skin": [[0, 1, 2]]}}, "'parts.skin'"),
        ({"parts": {"skin": [99]}}, "'parts.skin': vertex id 99 is outside 0..3"),
        ({"parts": {"skin": [-1]}}, "'parts.skin'"),
        ({"parts": {"skin": [[2, 1]]}}, "'parts.skin'"),
        ({"parts": {f"p{i}": [0] for i in range(300)}}, "'parts': 300 parts"),
        ({"feature_points": [1]}, "'feature_points'"),
        (
            {"feature_points": {"2.1": True}},
            "'feature_points.2.1': True must be a vertex id in 0..3",
        ),
        ({"feature_points": {"2.1": 1.5}}, "'feature_points.2.1'"),
        ({"feature_points": {"2.1": 10**30}}, "'feature_points.2.1'"),
        ({"axes": "up"}, "'axes'"),
        ({"axes": {"up": ["+y"]}}, "'axes'"),
        ({"axes": {"up": {}, "forward": "+z"}}, "'axes'"),
        ({"axes": {"up": "+y", "forward": "y"}}, "'axes'"),
    ],
)
def test_wrong_types_and_ids_in_an_annotation_name_the_field(annotation, field):
    with pytest.raises(InputError, match="ann.json") as e:
        face_from_annotation("t", VERTS, TRIS, annotation, where="ann.json")
    assert field in str(e.value) and len(str(e.value)) < 400


@pytest.mark.parametrize(
    ("raw", "words"),
    [
        (b"\xff", "not UTF-8"),
        (b"{", "not valid JSON"),
        (b"[1, 2]", "must be a JSON object"),
        (b"[" * 100_000, "nested too deeply|not valid JSON"),
        (b"", "not valid JSON"),
        (b'{"units": ' + b"9" * 4301 + b"}", "not valid JSON: Exceeds the limit"),  # a ValueError
    ],
)
def test_annotation_bytes_that_are_not_a_json_object(raw, words):
    with pytest.raises(InputError, match=words):
        parse_annotation(raw, where="ann.json")


def test_a_binary_annotation_beside_a_mesh_is_an_input_error(tmp_path):
    mesh = trimesh.Trimesh(
        vertices=VERTS + np.eye(4, 3, dtype=np.float32), faces=TRIS, process=False
    )
    mesh.export(tmp_path / "head.ply")
    (tmp_path / "head.face.json").write_bytes(b"\xff")
    with pytest.raises(InputError, match=r"head\.face\.json: annotation is not UTF-8"):
        load_face(tmp_path / "head.ply")
    (tmp_path / "head.face.json").write_text(json.dumps({"units": {}}))
    with pytest.raises(InputError, match=r"head\.face\.json: field 'units'"):
        load_face(tmp_path / "head.ply")


def test_overlapping_part_ranges_cost_one_mask_not_a_copy_per_range():
    ann = {"parts": {"skin": [[0, 3]] * 10_000 + [1, 2]}}
    face = face_from_annotation("t", VERTS, TRIS, ann, where="ann.json")
    assert face.part("skin").tolist() == [0, 1, 2, 3]


# -------------------------------------------------------------------------------------- TRC / CSV


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("time,A_x,A_y,A_z\nnan,1,2,3\nnan,1,2,3\n", ":2: time 'nan' must be finite"),
        ("time,A_x,A_y,A_z\n0,1,2,3\n1e-320,1,2,3\n", "frame rate of inf"),
        ("time,_x,_y,_z\n0,1,2,3\n1,1,2,3\n", "must be <name>_x"),
        ("time,A_x,A_y,A_z\n0,1,2,3\n1,x" + "9" * 5000 + ",2,3\n", ":3: coordinate 'x999"),
        ("# units=" + "z" * 5000 + "\ntime,A_x,A_y,A_z\n0,1,2,3\n", "unknown length unit 'zzz"),
    ],
)
def test_csv_errors_are_project_errors(text, words):
    with pytest.raises(MarkerFileError, match=words) as e:
        read_csv(text)
    assert len(str(e.value)) < 300


def test_trc_with_a_nan_time_is_refused():
    text = (
        "PathFileType\t4\t(X/Y/Z)\tt.trc\nDataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n"
        "60\t60\t1\t1\tmm\nFrame#\tTime\tA\t\t\n\t\tX1\tY1\tZ1\n1\tnan\t1\t2\t3\n"
    )
    with pytest.raises(MarkerFileError, match=r"t\.trc:6: time 'nan' must be finite"):
        read_trc(text, where="t.trc")


def test_a_long_non_number_token_is_refused_without_backtracking():
    """A 200,000-digit run then a letter: the old number pattern backtracked quadratically (found
    by bench/fuzz_parsers.py: 1.8 s for 37 kB). In a subprocess, so a regression cannot hang pytest."""
    import subprocess
    import sys

    code = (
        "from facecast.protocol.fap_file import read_fap, FapFormatError\n"
        "text = '2.1 t 25 1\\n' + ' '.join(['0', '0', '1'] + ['0'] * 65) + '\\n0 ' + '9' * 200000 + 'x\\n'\n"
        "try:\n    read_fap(text)\nexcept FapFormatError as e:\n    print(e)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert "3: value '9999" in out.stdout and "is not a number" in out.stdout, out.stderr[-500:]
