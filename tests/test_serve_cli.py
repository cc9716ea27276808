"""``facecast serve``: admin key generation, loopback-only default, flags, and a clean restart."""

from __future__ import annotations

import re
import subprocess
import sys
import time

import httpx
import pytest
from conftest import RunningServer

from facecast.server.cli import build_parser
from facecast.server.commands.serve import is_loopback, make_config
from facecast.server.errors import InputError

FACE = "default:2k"


def parse(*argv: str):
    argv = ["serve", *argv]
    return build_parser(argv).parse_args(argv)


@pytest.mark.slow
def test_generated_admin_key_is_printed_kept_and_required(tmp_path):
    srv = RunningServer(
        tmp_path / "d", "--face", FACE, "--job-workers", "0", env={"FACECAST_ADMIN_KEY": ""}
    )
    srv.start()
    try:
        printed = re.findall(r"FACECAST_ADMIN_KEY=(\S+)", srv.log.read_text())
        kept = (tmp_path / "d" / "admin.key").read_text().strip()
        assert printed == [kept] and len(kept) >= 32
        assert (tmp_path / "d" / "admin.key").stat().st_mode & 0o077 == 0
        assert (
            httpx.get(srv.url + "/v1/jobs", headers={"Authorization": f"Bearer {kept}"}).status_code
            == 200
        )
        assert srv.admin_key == kept  # what the harness read from the data dir
        assert (
            httpx.get(
                srv.url + "/v1/jobs", headers={"Authorization": "Bearer test-admin-key"}
            ).status_code
            == 401
        )
    finally:
        srv.stop()
    # A restart on the same data directory keeps the key and does not show it again, only where it is;
    # a key file someone made readable to others is put back to 0600. Uploads a crash left behind
    # (a /play upload, a job folder whose upload never finished) are removed.
    (tmp_path / "d" / "admin.key").chmod(0o644)
    stale = tmp_path / "d" / "tmp" / "facecast-play-old"
    stale.mkdir(parents=True)
    (stale / "upload").write_bytes(b"x" * 1000)
    orphan = tmp_path / "d" / "jobs" / ("ab" * 16)
    orphan.mkdir(parents=True)
    (orphan / ".upload").write_bytes(b"x" * 1000)
    again = RunningServer(
        tmp_path / "d", "--face", FACE, "--job-workers", "0", env={"FACECAST_ADMIN_KEY": ""}
    )
    again.start()
    try:
        assert (tmp_path / "d" / "admin.key").read_text().strip() == kept
        assert (tmp_path / "d" / "admin.key").stat().st_mode & 0o777 == 0o600
        assert (
            httpx.get(
                again.url + "/v1/jobs", headers={"Authorization": f"Bearer {kept}"}
            ).status_code
            == 200
        )
        log = again.log.read_text()
        assert (
            "FACECAST_ADMIN_KEY=" not in log and kept not in log
        )  # not generated, so not shown again
        assert str(tmp_path / "d" / "admin.key") in log  # but where it is
        assert not stale.exists() and not orphan.exists()
    finally:
        again.stop()


def test_non_loopback_address_needs_allow_remote(tmp_path):
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "facecast.server.cli",
            "serve",
            "--host",
            "0.0.0.0",
            "--data-dir",
            str(tmp_path),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 2
    assert "--allow-remote" in run.stderr and "0.0.0.0" in run.stderr
    assert not (tmp_path / "admin.key").exists()  # refused before doing anything
    with pytest.raises(InputError, match="allow-remote"):
        make_config(parse("--host", "192.0.2.7"))
    assert make_config(parse("--host", "0.0.0.0", "--allow-remote")).allow_remote


@pytest.mark.parametrize(
    ("host", "loop"),
    [
        ("127.0.0.1", True),
        ("127.1.2.3", True),
        ("::1", True),
        ("localhost", True),
        ("0.0.0.0", False),
        ("192.0.2.7", False),
        ("::", False),
    ],
)
def test_is_loopback(host, loop):
    assert is_loopback(host) is loop


def test_flags_override_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("FACECAST_PORT", "9001")
    monkeypatch.setenv("FACECAST_JOB_WORKERS", "3")
    monkeypatch.setenv("FACECAST_BACKEND", "opencl")
    cfg = make_config(
        parse(
            "--port",
            "9100",
            "--data-dir",
            str(tmp_path),
            "--face",
            FACE,
            "--backend",
            "numpy",
            "--device",
            "1",
            "--job-workers",
            "2",
        )
    )
    assert (cfg.port, cfg.data_dir, cfg.face, cfg.backend, cfg.device, cfg.job_workers) == (
        9100,
        tmp_path,
        FACE,
        "numpy",
        "1",
        2,
    )
    cfg = make_config(parse())
    assert (cfg.port, cfg.job_workers, cfg.backend, cfg.host) == (9001, 3, "opencl", "127.0.0.1")
    with pytest.raises(InputError, match="job-workers"):
        make_config(parse("--job-workers", "-1"))


def test_environment_settings_reach_the_server_and_bad_ones_are_named(tmp_path, monkeypatch):
    from facecast.server.api.app import create_app

    monkeypatch.setenv("FACECAST_FACES", f"ict={tmp_path / 'ict.obj'}")
    monkeypatch.setenv("FACECAST_JOB_RETENTION_HOURS", "2")
    app = create_app(make_config(parse("--data-dir", str(tmp_path), "--face", FACE)))
    assert "ict" in app.state.store.names()
    assert app.state.jobs.retention == 2 * 3600
    for name, value, says in [
        ("FACECAST_PORT", "abc", "valid integer"),
        ("FACECAST_JOB_RETENTION_HOURS", "-3", "greater than or equal to 0"),
    ]:
        monkeypatch.setenv(name, value)
        with pytest.raises(InputError, match=f"{name}='{value}': .*{says}"):
            make_config(parse("--data-dir", str(tmp_path)))
        monkeypatch.delenv(name)
    monkeypatch.setenv("FACECAST_FACES", "no-path-given")
    with pytest.raises(InputError, match="FACECAST_FACES"):
        create_app(make_config(parse("--data-dir", str(tmp_path))))


@pytest.mark.slow
def test_websockets_are_never_compressed(tmp_path):
    """Vertex streams must not use per-message deflate, even when the client offers it."""
    import asyncio

    from websockets.asyncio.client import connect

    srv = RunningServer(tmp_path, "--face", FACE, "--job-workers", "0").start()
    try:
        created = httpx.post(
            srv.url + "/v1/sessions", json={}, headers=srv.admin_headers, timeout=120
        )
        assert created.status_code == 201, created.text
        s = created.json()
        url = f"ws://127.0.0.1:{srv.port}{s['watch_url']}?token={s['viewer_token']}"

        async def handshake() -> tuple[dict, str | None]:
            async with connect(url, compression="deflate") as ws:
                assert "permessage-deflate" in ws.request.headers.get(
                    "Sec-WebSocket-Extensions", ""
                )
                hello = await asyncio.wait_for(ws.recv(), 30)
                return hello, ws.response.headers.get("Sec-WebSocket-Extensions")

        hello, extensions = asyncio.run(handshake())
        assert '"hello"' in hello  # a real viewer connection
        assert extensions is None
    finally:
        srv.stop()


def test_one_server_per_data_directory(tmp_path):
    from facecast.server.commands.serve import lock_data_dir

    held = lock_data_dir(tmp_path)
    try:
        run = subprocess.run(
            [
                sys.executable,
                "-m",
                "facecast.server.cli",
                "serve",
                "--port",
                "1",
                "--data-dir",
                str(tmp_path),
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert run.returncode == 2
        assert "another facecast server" in run.stderr and "--data-dir" in run.stderr
    finally:
        held.close()
    lock_data_dir(tmp_path).close()  # free again once the holder has gone


@pytest.mark.slow
def test_a_broken_default_face_is_reported_not_fatal(tmp_path):
    srv = RunningServer(
        tmp_path,
        "--face",
        "broken",
        "--job-workers",
        "0",
        env={"FACECAST_FACES": f"broken={tmp_path / 'missing.obj'}"},
    ).start()
    try:
        for _ in range(600):
            h = httpx.get(srv.url + "/healthz").json()
            if h["errors"]:
                break
            time.sleep(0.1)
        assert h["ready"] is False and "missing.obj" in h["errors"]["face_error"]
        assert httpx.get(srv.url + "/readyz").status_code == 503
        assert httpx.get(srv.url + "/v1/faces").status_code == 200  # still serving
    finally:
        srv.stop()


@pytest.mark.parametrize(
    ("name", "value", "says"),
    [
        ("FACECAST_MAX_AUDIO_SECONDS", "lots", "valid number"),
        ("FACECAST_MAX_AUDIO_SECONDS", "inf", "finite number"),
        ("FACECAST_MAX_SESSIONS", "many", "valid integer"),
        ("FACECAST_ALLOW_REMOTE", "perhaps", "valid boolean"),
    ],
)
def test_a_malformed_setting_is_refused_in_one_line_naming_it(tmp_path, name, value, says):
    import os

    env = {**os.environ, name: value}
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "facecast.server.cli",
            "serve",
            "--data-dir",
            str(tmp_path / "d"),
            "--port",
            "9",
        ],
        check=False,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert lines[0].startswith(f"facecast: environment: {name}={value!r}: ") and says in lines[0], (
        lines
    )
    assert lines[0].endswith("fix or unset the variable")
    assert not (tmp_path / "d").exists()  # refused before anything is written


def test_settings_outside_a_server_are_refused_the_same_way(tmp_path, data_dir):
    import os

    env = {**os.environ, "FACECAST_MAX_AUDIO_SECONDS": "-1"}
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "facecast.server.cli",
            "render",
            str(data_dir / "xface" / "faps" / "joy.fap"),
            "-o",
            str(tmp_path / "x.npz"),
            "--face",
            "default:2k",
        ],
        check=False,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 2 and r.stderr.strip() == (
        "facecast: environment: FACECAST_MAX_AUDIO_SECONDS='-1': Input should be greater than 0; "
        "fix or unset the variable"
    ), r.stderr
    assert not (tmp_path / "x.npz").exists()


def test_every_setting_is_in_the_readme_table_with_its_default():
    from pathlib import Path

    from facecast.server.api.config import ServerConfig

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    rows = {
        m[0]: m[1]
        for m in re.findall(r"^\| `(FACECAST_[A-Z_]+)` \| ([^|]*) \|", readme, re.MULTILINE)
    }
    for field, info in ServerConfig.model_fields.items():
        name = f"FACECAST_{field.upper()}"
        assert name in rows, f"{name} is missing from README.md's configuration table"
        if isinstance(info.default, bool):
            assert rows[name].strip() == f"`{str(info.default).lower()}`", name
        elif (
            isinstance(info.default, (int, float)) and "`" in rows[name]
        ):  # else said in words ("CPUs")
            assert float(rows[name].split("`")[1]) == info.default, name
