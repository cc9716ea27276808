"""REST API against a real ``facecast serve``: faces, topology, auth, upload limits, metrics, OpenAPI."""

from __future__ import annotations

import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from conftest import RunningServer
from hypothesis import given, settings
from hypothesis import strategies as st
from prometheus_client.parser import text_string_to_metric_families

from facecast.protocol.topology import (
    NO_PART,
    Topology,
    TopologyError,
    decode_topology,
    encode_topology,
)
from facecast.server.api.store import parse_faces_env
from facecast.server.errors import InputError
from facecast.server.paths import shared_data

FACE = "default:2k"
UPLOAD_LIMIT = 128 * 1024


ICT_MESH = (shared_data() / "ict-facekit" / "generic_neutral_mesh.obj") if shared_data() else None


@pytest.fixture(scope="module")
def srv(tmp_path_factory) -> RunningServer:
    env = {"FACECAST_MAX_UPLOAD_BYTES": str(UPLOAD_LIMIT)}
    if ICT_MESH is not None and ICT_MESH.is_file():
        env["FACECAST_FACES"] = f"ict={ICT_MESH}"
    s = RunningServer(
        tmp_path_factory.mktemp("rest"), "--face", FACE, "--job-workers", "0", env=env
    ).start()
    yield s
    s.stop()


def get(srv: RunningServer, path: str, **kw) -> httpx.Response:
    return httpx.get(srv.url + path, timeout=60.0, **kw)


def wait_ready(srv: RunningServer) -> dict:
    for _ in range(600):
        h = get(srv, "/healthz").json()
        if h["ready"] or h["errors"]:
            return h
        time.sleep(0.1)
    return h


def assert_error(resp: httpx.Response, status: int, *words: str) -> dict:
    assert resp.status_code == status, resp.text
    assert resp.headers["content-type"].startswith("application/json")
    body = resp.json()
    assert body["status"] == status and body["error"]
    for w in words:
        assert w.lower() in body["error"].lower(), body
    return body


# ----------------------------------------------------------------------------------- health, docs


def test_healthz_reports_readiness_backend_and_face(srv):
    assert httpx.head(srv.url + "/healthz").status_code == 200
    h = wait_ready(srv)
    assert h["status"] == "ok"
    assert h["ready"], h
    assert h["backend"] in ("numpy", "opencl")
    assert h["face"]["name"] == FACE and h["face"]["vertices"] > 100
    assert h["job_workers"] == 0
    assert get(srv, "/readyz").status_code == 200


def test_openapi_and_docs(srv):
    spec = get(srv, "/openapi.json").json()
    for path in (
        "/v1/faces",
        "/v1/faces/{name}",
        "/v1/faces/{name}/topology",
        "/v1/jobs",
        "/v1/jobs/{job_id}",
        "/v1/jobs/{job_id}/result",
        "/healthz",
        "/metrics",
    ):
        assert path in spec["paths"], path
    body = spec["paths"]["/v1/jobs"]["post"]["requestBody"]["content"]
    assert "file" in body["multipart/form-data"]["schema"]["properties"]
    docs = get(srv, "/docs")
    assert docs.status_code == 200 and "swagger" in docs.text.lower()


def test_metrics_parse_as_prometheus_text(srv):
    resp = get(srv, "/metrics")
    assert resp.status_code == 200 and resp.headers["content-type"].startswith("text/plain")
    families = {f.name: f for f in text_string_to_metric_families(resp.text)}
    for name in (
        "facecast_sessions",
        "facecast_viewers",
        "facecast_frames_sent",
        "facecast_frames_dropped",
        "facecast_deform_seconds",
        "facecast_jobs",
    ):
        assert name in families, sorted(families)
    states = {s.labels["state"] for s in families["facecast_jobs"].samples}
    assert states == {"queued", "running", "done", "failed", "cancelled"}


def test_unknown_route_is_json_404(srv):
    assert_error(get(srv, "/v1/nothing-here"), 404)


# ------------------------------------------------------------------------------------------ faces


def test_faces_list_names_the_default(srv):
    body = get(srv, "/v1/faces").json()
    names = [f["name"] for f in body["faces"]]
    assert "default" in names
    assert body["default"] == FACE


def test_face_describe_matches_its_topology(srv):
    info = get(srv, f"/v1/faces/{FACE}").json()
    topo = decode_topology(get(srv, info["topology_url"]).content)
    assert info["vertices"] == topo.n_vertices > 100
    assert info["triangles"] == topo.triangles.shape[0]
    assert sum(info["rigid_groups"].values()) == info["vertices"]
    assert list(info["rigid_groups"]) == topo.group_names == ["head", "jaw", "eye_l", "eye_r"]
    assert list(info["parts"]) == topo.part_names
    assert info["feature_points"] == len(info["feature_point_ids"]) > 0
    lo, hi = np.array(info["bounds"])
    assert np.allclose(lo, topo.vertices.min(axis=0)) and np.allclose(hi, topo.vertices.max(axis=0))


def test_topology_is_the_face_the_server_loaded(srv):
    from facecast.server.faces import RIGID_GROUPS, load_face

    resp = get(srv, f"/v1/faces/{FACE}/topology")
    assert resp.status_code == 200
    assert resp.headers["content-type"] == "application/vnd.facecast.topology"
    topo = decode_topology(resp.content)
    face = load_face(FACE)
    np.testing.assert_array_equal(topo.vertices, face.vertices)
    np.testing.assert_array_equal(topo.triangles, face.triangles)
    np.testing.assert_array_equal(topo.rigid_group, face.rigid_group)
    assert topo.group_names == list(RIGID_GROUPS)
    assert topo.mm_per_unit == face.mm_per_unit
    for i, name in enumerate(topo.part_names):  # every vertex tagged with a part belongs to it
        tagged = np.flatnonzero(topo.part_ids == i)
        assert np.isin(tagged, face.parts[name]).all(), name
    if "eye_l" in topo.part_names:  # the eyeball's vertices outside its iris (a sub-part) are eye_l
        sclera = np.setdiff1d(face.parts["eye_l"], face.parts.get("iris_l", []))
        assert (topo.part_ids[sclera] == topo.part_names.index("eye_l")).all()


def test_configured_mesh_face(srv, data_dir):
    assert "ict" in [f["name"] for f in get(srv, "/v1/faces").json()["faces"]]
    info = get(srv, "/v1/faces/ict").json()
    assert info["units"] == "cm" and info["mm_per_unit"] == 10.0
    assert {"eye_l", "eye_r", "teeth_lower", "tongue"} <= set(info["parts"])
    assert info["rigid_groups"]["jaw"] > 0 and info["feature_points"] > 0
    if info["fapu"] is not None:
        assert all(v > 0 for v in info["fapu"].values())
    topo = decode_topology(get(srv, "/v1/faces/ict/topology").content)
    assert topo.n_vertices == info["vertices"] and topo.mm_per_unit == 10.0


def test_faces_env_parsing():
    assert parse_faces_env("ict=/a/b.obj; x-1 = /c.obj,") == {
        "ict": Path("/a/b.obj"),
        "x-1": Path("/c.obj"),
    }
    assert parse_faces_env(None) == {}
    for bad in ("ict", "=/a.obj", "a b=/c.obj", "ict="):
        with pytest.raises(InputError, match="FACECAST_FACES"):
            parse_faces_env(bad)


def test_face_store_names_and_resolution(tmp_path):
    from facecast.server.api.store import FaceStore
    from facecast.server.errors import NotFound

    mesh = tmp_path / "my_head.obj"
    store = FaceStore(default=str(mesh), configured={"ict": Path("/x/ict.obj")})
    assert store.default == "my_head" and store.names()[:1] == ["default"]
    assert set(store.names()) == {"default", "ict", "my_head"}
    assert store.resolve(None) == str(mesh) and store.resolve("ict") == "/x/ict.obj"
    assert store.resolve("default:2k") == "default:2k"
    for bad in ("../my_head.obj", str(mesh), "/etc/passwd", "default:2k:3", "ict.obj"):
        with pytest.raises(NotFound):
            store.resolve(bad)
    with pytest.raises(InputError, match="out of range"):
        store.resolve("default:50M")


def test_new_builtin_resolution_needs_the_admin_key(srv):
    assert_error(get(srv, "/v1/faces/default:1k"), 403, "admin key")
    assert_error(get(srv, "/v1/faces/default:1k/topology"), 403, "admin key")
    assert get(srv, "/v1/faces/default:1k", headers=srv.admin_headers).status_code == 200
    assert get(srv, "/v1/faces/default:1k/topology").status_code == 200  # loaded now: public


@pytest.mark.parametrize("name", ["nope", "..", "default:9", "etc%2Fpasswd"])
def test_unknown_or_path_like_face_is_a_json_error(srv, name):
    resp = get(srv, f"/v1/faces/{name}")
    assert resp.status_code in (400, 404), resp.text
    assert resp.json()["error"]


def test_hostile_requests_of_the_issue_are_json_4xx_on_the_real_server(srv):
    assert_error(get(srv, "/v1/faces/default:" + "9" * 400), 400, "out of range")  # no key needed
    for raw in (b'{"fps": NaN}', b'{"fps": Infinity}', b'{"fps": 1e309}', b'{"face": "\\udcff"}'):
        resp = httpx.post(
            srv.url + "/v1/sessions",
            content=raw,
            timeout=60,
            headers={**srv.admin_headers, "Content-Type": "application/json"},
        )
        assert 400 <= resp.status_code < 500 and resp.json()["error"], (raw, resp.text)
    assert get(srv, "/healthz").status_code == 200


# ------------------------------------------------------------------------------- auth and uploads


def small_fap() -> bytes:
    return b"# tiny\n2.1 tiny 25 2\n" + b"0 " * 68 + b"\n0\n" + b"0 " * 68 + b"\n0\n"


@pytest.mark.parametrize(
    "headers", [{}, {"Authorization": "Bearer wrong"}, {"Authorization": "Basic eA=="}]
)
def test_jobs_need_the_admin_key(srv, headers):
    assert_error(
        httpx.post(srv.url + "/v1/jobs", files={"file": ("a.fap", small_fap())}, headers=headers),
        401,
        "admin key",
    )
    assert_error(httpx.get(srv.url + "/v1/jobs", headers=headers), 401)


def test_oversized_upload_is_413_json_and_the_server_keeps_serving(srv):
    big = b"0" * (UPLOAD_LIMIT * 4)
    resp = httpx.post(
        srv.url + "/v1/jobs",
        files={"file": ("big.fap", big)},
        headers=srv.admin_headers,
        timeout=60.0,
    )
    body = assert_error(resp, 413, "limit")
    assert str(UPLOAD_LIMIT) in body["error"]

    # Without a Content-Length (chunked), the limit is enforced while streaming.
    def chunks():
        boundary = b"xyzzy"
        yield (
            b"--"
            + boundary
            + b'\r\nContent-Disposition: form-data; name="file"; filename="big.fap"\r\n\r\n'
        )
        for _ in range(8):
            yield b"1" * (UPLOAD_LIMIT // 2)
        yield b"\r\n--" + boundary + b"--\r\n"

    resp = httpx.post(
        srv.url + "/v1/jobs",
        content=chunks(),
        timeout=60.0,
        headers={**srv.admin_headers, "Content-Type": "multipart/form-data; boundary=xyzzy"},
    )
    assert_error(resp, 413, "limit")
    assert get(srv, "/healthz").status_code == 200
    ok = httpx.post(
        srv.url + "/v1/jobs", files={"file": ("ok.fap", small_fap())}, headers=srv.admin_headers
    )
    assert ok.status_code == 202, ok.text
    leftovers = [
        p
        for p in (srv.data_dir / "jobs").rglob("*")
        if (p.is_file() and "big" in p.name) or p.name == ".upload"
    ]
    assert leftovers == []


def test_upload_errors_say_what_to_do(srv):
    h = srv.admin_headers
    assert_error(httpx.post(srv.url + "/v1/jobs", json={"file": "x"}, headers=h), 415, "multipart")
    assert_error(
        httpx.post(
            srv.url + "/v1/jobs", data={"face": FACE}, files={"other": ("a", b"1")}, headers=h
        ),
        400,
        "file",
    )
    assert_error(
        httpx.post(
            srv.url + "/v1/jobs", files={"file": ("x.bin", b"\x00\x01\x02 nothing")}, headers=h
        ),
        415,
        ".fap",
    )
    assert_error(
        httpx.post(
            srv.url + "/v1/jobs",
            files={"file": ("a.fap", small_fap())},
            data={"format": "mp4"},
            headers=h,
        ),
        400,
        "format",
    )
    assert_error(
        httpx.post(
            srv.url + "/v1/jobs",
            files={"file": ("a.fap", small_fap())},
            data={"face": "/etc/passwd"},
            headers=h,
        ),
        404,
        "no face",
    )
    assert_error(
        httpx.post(
            srv.url + "/v1/jobs",
            files={"file": ("a.fap", small_fap())},
            data={"layout": "../../x"},
            headers=h,
        ),
        400,
        "layout",
    )


def test_client_file_names_never_become_paths(srv):
    resp = httpx.post(
        srv.url + "/v1/jobs",
        files={"file": ("../../evil/../x.fap", small_fap())},
        headers=srv.admin_headers,
    )
    assert resp.status_code == 202, resp.text
    job = resp.json()
    assert job["input_name"] == "x.fap" and job["input_kind"] == "fap"
    folder = srv.data_dir / "jobs" / job["id"]
    assert sorted(p.name for p in folder.iterdir()) == ["input.fap"]
    assert not (srv.data_dir.parent / "evil").exists()


def test_input_kind_from_content_when_the_name_says_nothing(srv):
    resp = httpx.post(
        srv.url + "/v1/jobs", files={"file": ("take", small_fap())}, headers=srv.admin_headers
    )
    assert resp.status_code == 202, resp.text
    assert resp.json()["input_kind"] == "fap"


def test_queued_job_status_result_and_cancel(srv):
    h = srv.admin_headers
    job = httpx.post(srv.url + "/v1/jobs", files={"file": ("q.fap", small_fap())}, headers=h).json()
    assert job["status"] == "queued" and job["progress"] == 0.0  # this server has no workers
    assert_error(httpx.get(f"{srv.url}/v1/jobs/{job['id']}/result", headers=h), 409, "queued")
    cancelled = httpx.delete(f"{srv.url}/v1/jobs/{job['id']}", headers=h)
    assert cancelled.status_code == 200 and cancelled.json()["status"] == "cancelled"
    assert httpx.get(f"{srv.url}/v1/jobs/{job['id']}", headers=h).json()["status"] == "cancelled"
    assert_error(httpx.get(f"{srv.url}/v1/jobs/{job['id']}/result", headers=h), 409, "cancelled")
    assert_error(httpx.get(f"{srv.url}/v1/jobs/{'0' * 32}", headers=h), 404, "no job")
    assert_error(httpx.get(f"{srv.url}/v1/jobs/..%2F..%2Fadmin.key", headers=h), 404)


# ------------------------------------------------------------------------------- topology codec


@st.composite
def topologies(draw):
    n = draw(st.integers(0, 40))
    f = draw(st.integers(0, 30)) if n else 0
    names = st.text(
        st.characters(blacklist_characters="\n", blacklist_categories=("Cs",)), max_size=12
    )
    parts = draw(st.lists(names, max_size=5))
    groups = draw(st.lists(names, min_size=1, max_size=4))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    part_ids = rng.integers(0, len(parts) + 1, n).astype(np.uint8)
    part_ids[part_ids == len(parts)] = NO_PART
    return Topology(
        rng.standard_normal((n, 3)).astype(np.float32),
        rng.integers(0, max(n, 1), (f, 3)),
        part_ids,
        parts,
        rng.integers(0, len(groups), n).astype(np.uint8),
        groups,
        draw(st.sampled_from([1.0, 10.0, 25.4])),
    )


@given(topologies())
@settings(max_examples=60, deadline=None)
def test_topology_round_trip(topo):
    blob = encode_topology(topo)
    assert len(blob) % 4 == 0
    back = decode_topology(blob)
    np.testing.assert_array_equal(back.vertices, topo.vertices)
    np.testing.assert_array_equal(back.triangles, topo.triangles)
    np.testing.assert_array_equal(back.part_ids, topo.part_ids)
    np.testing.assert_array_equal(back.rigid_group, topo.rigid_group)
    assert (back.part_names, back.group_names) == (topo.part_names, topo.group_names)
    assert back.mm_per_unit == float(np.float32(topo.mm_per_unit))


@given(topologies(), st.data())
@settings(max_examples=60, deadline=None)
def test_topology_decoder_rejects_damage_with_topology_error(topo, data):
    blob = bytearray(encode_topology(topo))
    cut = data.draw(st.integers(0, len(blob) - 1))
    with pytest.raises(TopologyError):
        decode_topology(bytes(blob[:cut]))
    pos = data.draw(st.integers(0, len(blob) - 1))
    blob[pos] ^= 0xFF
    try:
        decode_topology(bytes(blob))
    except TopologyError:
        pass  # anything else (IndexError, UnicodeError, numpy errors) fails the test


def test_topology_sections_are_4_byte_aligned():
    topo = Topology(
        np.zeros((5, 3), np.float32),
        np.array([[0, 1, 2]]),
        np.zeros(5, np.uint8),
        ["skin"],
        np.zeros(5, np.uint8),
        ["head"],
        10.0,
    )
    blob = encode_topology(topo)
    assert blob[:4] == b"FCTP"
    n_names = int.from_bytes(blob[20:24], "little")
    assert n_names == len(b"skin\nhead\n") and (32 + n_names + 2) % 4 == 0
    assert len(blob) == 32 + 12 + 60 + 12 + 8 + 8


def test_tokens_never_look_like_command_line_options():
    # `facecast watch --token T` must work for every token the server hands out: a token starting
    # with "-" was taken by argparse for an option (1 token in 64 with plain token_urlsafe).
    from facecast.server.live.tokens import new_token

    tokens = [new_token() for _ in range(3000)]
    assert not [t for t in tokens if t.startswith("-")]
    assert len(set(tokens)) == len(tokens) and min(map(len, tokens)) >= 43  # 32 random bytes each
