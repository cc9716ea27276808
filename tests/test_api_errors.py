"""Hostile requests get a JSON 4xx (never a 500, never a server path), in-process with TestClient."""

from __future__ import annotations

import json
import math

import pytest
from fastapi.testclient import TestClient

from facecast.protocol.fap_file import FapFormatError
from facecast.protocol.markers_file import MarkerFileError
from facecast.server.api.app import create_app
from facecast.server.api.config import ServerConfig
from facecast.server.api.responses import SafeJSONResponse, safe_json

KEY = "test-key"
ADMIN = {"Authorization": f"Bearer {KEY}"}


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    data = tmp_path_factory.mktemp("api-errors")
    return create_app(
        ServerConfig(
            data_dir=data, admin_key=KEY, job_workers=0, face="default:2k", backend="numpy"
        )
    )


@pytest.fixture(scope="module")
def client(app):
    return TestClient(app, raise_server_exceptions=False)


def json_error(resp, *statuses: int) -> dict:
    assert resp.status_code in statuses, (resp.status_code, resp.text)
    assert resp.headers["content-type"].startswith("application/json")
    body = resp.json()
    assert body["status"] == resp.status_code and body["error"]
    return body


def test_a_face_count_of_400_digits_is_a_400_without_a_key(client):
    body = json_error(client.get("/v1/faces/default:" + "9" * 400), 400)
    assert "out of range" in body["error"] and len(body["error"]) < 400
    json_error(client.get("/v1/faces/default:" + "9" * 400 + "/topology"), 400)
    json_error(client.get("/v1/faces/default:" + "1." * 300 + "k"), 400)


@pytest.mark.parametrize("fps", ["NaN", "Infinity", "-Infinity", "1e309"])
def test_non_finite_numbers_in_a_body_are_a_422(client, fps):
    resp = client.post(
        "/v1/sessions",
        content=f'{{"fps": {fps}}}',
        headers={**ADMIN, "content-type": "application/json"},
    )
    body = json_error(resp, 422)
    assert "fps" in body["error"]


@pytest.mark.parametrize(
    "raw",
    [
        b'{"face": "\\udcff"}',
        b'{"face": "\\ud800x", "engine": "\\udfff"}',
        b'{"engine": "\xff\xfe"}',
        b'{"max_viewers": ' + b"9" * 5000 + b"}",
    ],
)
def test_lone_surrogates_bad_bytes_and_huge_integers_are_a_4xx(client, raw):
    resp = client.post(
        "/v1/sessions", content=raw, headers={**ADMIN, "content-type": "application/json"}
    )
    json_error(resp, 400, 404, 422)


def test_surrogates_in_paths_and_queries_are_a_4xx(client):
    json_error(client.get("/v1/faces/%ED%A0%80"), 400, 404)
    json_error(client.get("/v1/sessions/%ED%A0%80", headers=ADMIN), 400, 404)
    json_error(client.get("/v1/jobs/%ED%A0%80", headers=ADMIN), 400, 404)
    resp = client.get("/v1/jobs?status=%ED%A0%80&limit=%ED", headers=ADMIN)
    json_error(resp, 400, 422)


@pytest.mark.parametrize(
    "path", ["/static/%00", "/static/" + "a/" * 3000, "/static/..%2F..%2Fpyproject.toml"]
)
def test_odd_static_paths_are_a_404(client, path):
    json_error(client.get(path), 404)


def test_project_errors_are_4xx_and_unexpected_ones_a_500_without_details(app, client):
    secret = str(app.state.config.data_dir / "jobs" / "x" / "input.fap")

    @app.get("/_test/fap")
    async def fap_error():
        raise FapFormatError(f"line 3: integer too long in {secret}")

    @app.get("/_test/markers")
    async def marker_error():
        raise MarkerFileError("bad header")

    @app.get("/_test/boom")
    async def boom():
        raise RuntimeError(f"disk trouble at {secret}")

    body = json_error(client.get("/_test/fap"), 400)
    assert (
        "integer too long" in body["error"] and str(app.state.config.data_dir) not in body["error"]
    )
    assert "input.fap" in body["error"]  # the file's own name stays
    json_error(client.get("/_test/markers"), 400)
    body = json_error(client.get("/_test/boom"), 500)
    assert "disk trouble" not in resp_text(body) and "Traceback" not in resp_text(body)


def resp_text(body: dict) -> str:
    return json.dumps(body)


def test_safe_json_makes_any_echo_serialisable():
    weird = {
        "nan": math.nan,
        "inf": [math.inf, -math.inf],
        "bytes": b"\xff\x00",
        "s": "a\udcffb",
        "big": 10**5000,
        b"k": {"\ud800": "x" * 10_000},
        "obj": object(),
    }
    text = json.dumps(safe_json(weird), allow_nan=False, ensure_ascii=False)
    text.encode("utf-8")
    assert len(text) < 2000
    assert SafeJSONResponse(weird).body  # renders instead of raising


def test_an_operator_mesh_path_never_reaches_a_client(tmp_path, monkeypatch):
    import tempfile

    monkeypatch.setattr(
        tempfile, "tempdir", "/nonexistent-facecast-tmp"
    )  # /tmp alone must not hide it
    hidden = tmp_path / "operator-only" / "meshes"
    hidden.mkdir(parents=True)
    (hidden / "broken.obj").write_text("v 0 0\nf 1 2 3\n")
    app = create_app(
        ServerConfig(
            data_dir=tmp_path / "data",
            admin_key=KEY,
            job_workers=0,
            backend="numpy",
            faces=f"broken={hidden / 'broken.obj'}",
        )
    )
    resp = TestClient(app, raise_server_exceptions=False).get("/v1/faces/broken", headers=ADMIN)
    assert resp.status_code == 400 and "broken.obj" in resp.json()["error"], resp.text
    assert "operator-only" not in resp.text and str(tmp_path) not in resp.text


def test_upload_limits_by_kind_never_exceed_the_overall_limit(tmp_path):
    cfg = ServerConfig(data_dir=tmp_path)
    fap, markers, audio = (cfg.upload_limit(k)[0] for k in ("fap", "markers", "audio"))
    assert fap < markers < audio <= cfg.max_upload_bytes
    assert cfg.upload_limit("markers")[1] == "FACECAST_MAX_MARKERS_BYTES"
    small = ServerConfig(data_dir=tmp_path, max_upload_bytes=1000)
    assert all(
        small.upload_limit(k) == (1000, "FACECAST_MAX_UPLOAD_BYTES")
        for k in ("fap", "markers", "audio")
    )
