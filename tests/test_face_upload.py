"""``POST /v1/faces`` on a real server: upload a head mesh, get it annotated, use it by name or id.

Real heads from ``../shared/data/heads`` (skipped when absent) and the built-in head exported as a
file; hostile uploads (garbage, mutated meshes, external glTF buffers, oversized meshes) get a 4xx
with a JSON body, never a 5xx.
"""

from __future__ import annotations

import io
import json
import lzma
import time

import httpx
import numpy as np
import pytest
from conftest import RunningServer
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from facecast.server.faces import load_face
from facecast.server.faces.upload import MAX_VERTICES, sniff_format


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    cache = tmp_path_factory.mktemp("cache")
    s = RunningServer(
        tmp_path_factory.mktemp("server-data"),
        "--face",
        "default:2k",
        "--backend",
        "numpy",
        env={"FACECAST_CACHE": str(cache)},
    ).start()
    yield s
    s.stop()


def post(srv, files: dict, data: dict | None = None, auth: bool = True) -> httpx.Response:
    return httpx.post(
        srv.url + "/v1/faces",
        files=files,
        data=data or {},
        headers=srv.admin_headers if auth else {},
        timeout=300,
    )


def obj_bytes(v: np.ndarray, t: np.ndarray) -> bytes:
    buf = io.StringIO()
    np.savetxt(buf, v, fmt="v %.6f %.6f %.6f")
    np.savetxt(buf, t + 1, fmt="f %d %d %d")
    return buf.getvalue().encode()


@pytest.fixture(scope="module")
def head2k():
    return load_face("default:2k")


def heads_file(data_dir, rel: str) -> bytes:
    path = data_dir / "heads" / rel
    if not path.is_file():
        pytest.skip(f"{rel} is not in ../shared/data/heads")
    raw = path.read_bytes()
    return lzma.decompress(raw) if path.suffix == ".xz" else raw


def test_uploading_a_mesh_without_annotation_annotates_it_and_the_face_is_offered(srv, head2k):
    data = obj_bytes(head2k.vertices, head2k.triangles)
    assert post(srv, {"file": ("head.obj", data)}, auth=False).status_code == 401
    r = post(srv, {"file": ("head.obj", data)}, {"name": "my-head"})
    assert r.status_code == 201, r.text
    body = r.json()
    assert body["name"] == "my-head" and body["annotation"] == "automatic" and body["created"]
    assert body["face"]["vertices"] == head2k.n_vertices and body["face"]["feature_points"] >= 60
    assert r.headers["location"] == "/v1/faces/my-head"
    names = [f["name"] for f in httpx.get(srv.url + "/v1/faces", timeout=30).json()["faces"]]
    assert "my-head" in names
    by_id = httpx.get(f"{srv.url}/v1/faces/{body['id']}", timeout=60)
    assert by_id.status_code == 200 and by_id.json()["vertices"] == head2k.n_vertices
    # The same mesh again is the same face; the automatic annotation now comes from the cache.
    again = post(srv, {"file": ("other-name.obj", data)})
    assert again.status_code == 200 and again.json()["id"] == body["id"] and again.json()["cached"]
    assert not again.json()["created"] and again.json()["name"] == "my-head"
    # The annotation is kept beside the mesh in the data directory (never at a client's path).
    kept = json.loads((srv.data_dir / "faces" / body["id"] / "mesh.face.json").read_text())
    assert kept["final"] is True and len(kept["feature_points"]) == body["face"]["feature_points"]
    assert str(srv.data_dir) not in r.text


def test_an_uploaded_face_plays_in_sessions_and_renders_in_jobs(srv, head2k, data_dir):
    data = obj_bytes(head2k.vertices, head2k.triangles)
    face_id = post(srv, {"file": ("head.obj", data)}).json()["id"]
    fap = data_dir / "xface" / "faps" / "joy.fap"
    s = httpx.post(
        srv.url + "/v1/sessions",
        json={"input": "fap", "fps": 30, "face": face_id},
        headers=srv.admin_headers,
        timeout=120,
    )
    assert s.status_code == 201, s.text
    r = httpx.post(
        f"{srv.url}/v1/sessions/{s.json()['id']}/play",
        headers=srv.admin_headers,
        files={"file": ("joy.fap", fap.read_bytes())},
        timeout=120,
    )
    assert r.status_code == 202, r.text
    job = httpx.post(
        srv.url + "/v1/jobs",
        files={"file": ("joy.fap", fap.read_bytes())},
        data={"face": face_id, "format": "npz"},
        headers=srv.admin_headers,
        timeout=60,
    )
    assert job.status_code == 202, job.text
    for _ in range(3000):
        st_ = httpx.get(
            f"{srv.url}/v1/jobs/{job.json()['id']}", headers=srv.admin_headers, timeout=30
        ).json()
        if st_["status"] in ("done", "failed"):
            break
        time.sleep(0.1)
    assert st_["status"] == "done", st_
    res = httpx.get(f"{srv.url}{st_['result_url']}", headers=srv.admin_headers, timeout=60)
    frames = np.load(io.BytesIO(res.content))
    key = "vertices" if "vertices" in frames else next(iter(frames.keys()))
    moved = np.abs(frames[key] - frames[key][0]).max()
    assert frames[key].shape[1] == head2k.n_vertices and moved > 0.1


def test_a_users_annotation_wins_complete_or_partial(srv, head2k):
    from facecast.server.faces.annotate.core import ranges

    v = head2k.vertices * 0.1  # in cm: another mesh (another hash) with the same topology
    data = obj_bytes(v, head2k.triangles)
    full = {
        "units": "cm",
        "feature_points": dict(head2k.feature_points),
        "parts": {k: ranges(ids) for k, ids in head2k.parts.items()},
        "pivots": {k: (np.asarray(p) * 0.1).tolist() for k, p in head2k.pivots.items()},
    }
    r = post(srv, {"file": ("cm.obj", data), "annotation": ("cm.face.json", json.dumps(full))})
    assert r.status_code == 201, r.text
    assert r.json()["annotation"] == "user" and r.json()["face"]["units"] == "cm"
    # A partial annotation: the user's one point wins, the annotator fills in the rest.
    partial = {"feature_points": {"9.3": int(head2k.feature_points["9.15"])}}
    r = post(srv, {"file": ("cm.obj", data)}, {"annotation": json.dumps(partial)})
    assert r.status_code == 201, r.text
    assert r.json()["annotation"] == "user+automatic"
    kept = json.loads((srv.data_dir / "faces" / r.json()["id"] / "mesh.face.json").read_text())
    assert (
        kept["feature_points"]["9.3"] == head2k.feature_points["9.15"]
        and len(kept["feature_points"]) > 60
    )
    # A bad annotation names its field.
    bad = post(
        srv, {"file": ("cm.obj", data)}, {"annotation": '{"feature_points": {"2.1": 10000000}}'}
    )
    assert bad.status_code == 400 and "feature_points.2.1" in bad.json()["error"]


@pytest.mark.parametrize(
    ("rel", "fmt"),
    [
        ("demosthenes/demosthenes-low-res.obj.xz", "ply"),
        ("mediapipe-face/canonical_face_model.obj", "glb"),
    ],
)
def test_real_heads_upload_in_other_formats(srv, data_dir, rel, fmt):
    import trimesh

    from facecast.server.faces.obj import read_obj

    raw = heads_file(data_dir, rel)
    v, t = read_obj("x.obj", text=raw.decode("utf-8", "replace"))
    blob = trimesh.Trimesh(v, t, process=False).export(file_type=fmt)
    r = post(srv, {"file": (f"head.{fmt}", blob)})
    assert r.status_code == 201, r.text
    body = r.json()
    assert body["annotation"] == "automatic" and body["face"]["fapu"] is not None
    if "mediapipe" in rel:
        assert body["left_out"], (
            "a face mask has no back of the head: the annotation says what it left out"
        )


def test_malformed_and_hostile_uploads_get_a_clear_4xx(srv, tmp_path):
    cases = {
        "garbage.ply": b"ply\nformat binary_little_endian 1.0\nelement vertex 99999999999\nend_header\n\x00\x01",
        "empty.obj": b"",
        "text.obj": b"hello world\n",
        "nan.obj": b"v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
        "range.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n",
        "tiny.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
        "trunc.glb": b"glTF\x02\x00\x00\x00",
        "ext.gltf": json.dumps(
            {
                "asset": {"version": "2.0"},
                "buffers": [{"uri": "../../../etc/passwd", "byteLength": 10}],
            }
        ).encode(),
        "bin.stl": b"\x00" * 80 + (10**6).to_bytes(4, "little") + b"\x00" * 100,
        "noext": b"\x89PNG\r\n\x1a\n" + bytes(100),
    }
    for name, blob in cases.items():
        r = post(srv, {"file": (name, blob)})
        assert 400 <= r.status_code < 500, (name, r.status_code, r.text)
        assert r.json()["error"], name
        assert "/etc/passwd" not in r.text or name == "ext.gltf"
    huge = b"v 0 0 0\n" * (MAX_VERTICES + 1) + b"f 1 2 3\n"
    r = post(srv, {"file": ("huge.obj", huge)})
    assert r.status_code == 413 and "at most" in r.json()["error"]
    assert (
        httpx.post(srv.url + "/v1/faces", content=b"x", headers=srv.admin_headers).status_code
        == 415
    )
    r = post(srv, {"file": ("a.obj", b"v 0 0 0\n")}, {"path": "/etc/passwd"})
    assert r.status_code == 400 and "unknown form field" in r.json()["error"]
    for bad_name in ("../../x", "..", "a" * 65):
        r = post(srv, {"file": ("a.obj", b"v 0 0 0\n")}, {"name": bad_name})
        assert r.status_code == 400 and "face name" in r.json()["error"], bad_name
    assert httpx.get(srv.url + "/healthz", timeout=10).status_code == 200


def _small_meshes() -> dict[str, bytes]:
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=1)
    return {
        f"s.{fmt}": ico.export(file_type=fmt)
        if fmt != "obj"
        else obj_bytes(np.asarray(ico.vertices), np.asarray(ico.faces))
        for fmt in ("obj", "ply", "stl", "glb")
    }


SMALL = _small_meshes()


@settings(max_examples=12, deadline=None, suppress_health_check=list(HealthCheck))
@given(name=st.sampled_from(sorted(SMALL)), data=st.data())
def test_fuzzed_mesh_uploads_never_give_a_5xx(srv, name, data):
    blob = bytearray(SMALL[name])
    for _ in range(data.draw(st.integers(1, 8))):
        op = data.draw(st.sampled_from(["flip", "cut", "insert"]))
        i = data.draw(st.integers(0, max(len(blob) - 1, 0)))
        if op == "flip" and blob:
            blob[i] ^= data.draw(st.integers(1, 255))
        elif op == "cut":
            del blob[i : i + data.draw(st.integers(1, 64))]
        else:
            blob[i:i] = data.draw(st.binary(min_size=1, max_size=16))
    r = post(srv, {"file": (name if data.draw(st.booleans()) else "upload", bytes(blob))})
    assert r.status_code < 500, r.text
    assert r.headers["content-type"].startswith("application/json")


def test_sniffing_tells_the_formats_apart():
    assert sniff_format("x.OBJ", b"") == "obj"
    assert sniff_format(None, b"glTF\x02") == "glb"
    assert sniff_format("upload", b"ply\nformat ascii 1.0") == "ply"
    assert sniff_format("upload", b"# comment\nv 0 0 0\n") == "obj"
    assert sniff_format("upload", b'  {"asset": {}}') == "gltf"


def test_deleting_an_uploaded_face(srv, head2k):
    v = head2k.vertices * 1.01
    r = post(srv, {"file": ("del.obj", obj_bytes(v, head2k.triangles))}, {"name": "to-delete"})
    assert r.status_code == 201, r.text
    assert httpx.delete(srv.url + "/v1/faces/to-delete", timeout=30).status_code == 401
    assert (
        httpx.delete(
            srv.url + "/v1/faces/to-delete", headers=srv.admin_headers, timeout=30
        ).status_code
        == 204
    )
    assert httpx.get(srv.url + "/v1/faces/to-delete", timeout=30).status_code == 404
    assert (
        httpx.delete(
            srv.url + "/v1/faces/default", headers=srv.admin_headers, timeout=30
        ).status_code
        == 404
    )
    assert not (srv.data_dir / "faces" / r.json()["id"]).exists()


def test_a_worker_that_overruns_its_time_is_replaced(tmp_path, head2k):
    from facecast.server.errors import InputError
    from facecast.server.faces.upload import MeshWorker, Unprocessable

    path = tmp_path / "head.obj"
    path.write_bytes(obj_bytes(head2k.vertices, head2k.triangles))
    worker = MeshWorker(timeout=0.01)  # less than the worker's start-up: it always overruns
    try:
        with pytest.raises(Unprocessable, match="took longer than"):
            worker.prepare(path, "obj", None)
        assert worker._proc is None  # killed
        worker.timeout = 300.0
        with pytest.raises(
            InputError, match="not valid JSON"
        ):  # a fresh worker answers the next upload
            worker.prepare(path, "obj", '{"feature_points": ')
    finally:
        worker.stop()
