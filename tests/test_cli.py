"""The ``facecast`` command line itself: --version, server URLs as typed, log levels."""

from __future__ import annotations

import subprocess
import sys

import httpx
import pytest
from conftest import RunningServer

from facecast import server as server_package
from facecast.protocol.urls import server_url
from facecast.server.cli import parse_args


def cli(*argv: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "facecast.server.cli", *argv],
        capture_output=True,
        text=True,
        timeout=timeout,
    )


@pytest.mark.parametrize(
    ("typed", "url"),
    [
        ("127.0.0.1:8000", "http://127.0.0.1:8000"),
        ("localhost:8000/", "http://localhost:8000"),
        ("  example.org ", "http://example.org"),
        ("[::1]:8000", "http://[::1]:8000"),
        ("http://127.0.0.1:8000/", "http://127.0.0.1:8000"),
        ("HTTPS://facecast.example/prefix/", "https://facecast.example/prefix"),
        ("ws://127.0.0.1:8000", "http://127.0.0.1:8000"),
        ("wss://h:443", "https://h:443"),
    ],
)
def test_server_urls_are_taken_as_typed(typed, url):
    assert server_url(typed) == url


@pytest.mark.parametrize(
    "typed", ["", "   ", "ftp://h", "http://", "http://:8000", "h:0", "h:99999", "h:port"]
)
def test_unusable_server_urls_are_refused_with_an_example(typed):
    with pytest.raises(ValueError, match="http://127.0.0.1:8000"):
        server_url(typed)


def test_every_url_and_server_flag_is_normalised():
    args = parse_args(["session", "list", "--url", "127.0.0.1:8000"])
    assert args.url == "http://127.0.0.1:8000"
    args = parse_args(["watch", "--url", "localhost:9000/", "--session", "s", "--token", "t"])
    assert args.url == "http://localhost:9000"
    args = parse_args(
        ["stream", "x.fap", "--url", "127.0.0.1:8000", "--session", "s", "--token", "t"]
    )
    assert args.url == "http://127.0.0.1:8000"
    args = parse_args(["render", "x.fap", "-o", "x.glb", "--server", "127.0.0.1:8000"])
    assert args.server == "http://127.0.0.1:8000"
    assert parse_args(["render", "x.fap", "-o", "x.glb"]).server is None


def test_a_bad_url_exits_2_naming_the_flag():
    r = cli("session", "list", "--url", "ftp://127.0.0.1:8000")
    assert r.returncode == 2
    assert (
        "--url" in r.stderr and "http://127.0.0.1:8000" in r.stderr and "Traceback" not in r.stderr
    )


def test_a_url_without_scheme_reaches_the_server(tmp_path):
    srv = RunningServer(tmp_path / "d", "--face", "default:2k", "--job-workers", "0").start()
    try:
        import os

        env = {**os.environ, "FACECAST_ADMIN_KEY": srv.admin_key}
        r = subprocess.run(
            [
                sys.executable,
                "-m",
                "facecast.server.cli",
                "session",
                "list",
                "--url",
                f"127.0.0.1:{srv.port}",
            ],
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert r.returncode == 0, r.stderr
    finally:
        srv.stop()


def test_version():
    r = cli("--version")
    assert r.returncode == 0 and r.stdout.strip() == f"facecast {server_package.__version__}"


def test_verbosity_counts_before_or_after_the_command():
    assert parse_args(["info"]).verbose == 0
    assert parse_args(["-v", "info"]).verbose == 1
    assert parse_args(["info", "-vv"]).verbose == 2
    assert parse_args(["-v", "session", "list", "--url", "h:1", "--verbose"]).verbose == 2
    with pytest.raises(SystemExit):
        parse_args(["info", "--no-such-flag"])


def test_logs_are_quiet_by_default_and_v_shows_info():
    quiet, loud = cli("info"), cli("-v", "info")
    assert quiet.returncode == 0 and loud.returncode == 0, (quiet.stderr, loud.stderr)
    assert " INFO " not in quiet.stderr, quiet.stderr
    assert " INFO " in loud.stderr and " DEBUG " not in loud.stderr, loud.stderr


def test_serve_logs_neither_info_nor_requests_by_default(tmp_path):
    srv = RunningServer(tmp_path / "d", "--face", "default:2k", "--job-workers", "0").start()
    try:
        for path in ("/healthz", "/v1/faces", "/v1/sessions"):
            httpx.get(srv.url + path, headers=srv.admin_headers, timeout=30)
    finally:
        srv.stop()
    log = srv.log.read_text()
    assert "facecast: serving on" in log  # what the operator needs is still printed
    assert " INFO " not in log and "GET /" not in log, log


@pytest.mark.parametrize(
    ("argv", "where", "what"),
    [
        (["x.fap", "-o", "x.obj"], "x.obj", "unsupported output type '.obj'"),
        (["missing.fap", "-o", "x.glb"], "missing.fap", "input file not found"),
        (
            ["take.trc", "-o", "x.fap", "--filter", "kalman"],
            "--server",
            "apply to local renders only",
        ),
    ],
)
def test_render_on_a_server_refuses_like_a_local_render(tmp_path, argv, where, what):
    """``render --server`` runs the client's command module; its refusals are the local ones, one line."""
    (tmp_path / "x.fap").write_text("2.1 demo 25 1\n")
    (tmp_path / "take.trc").write_text("")
    r = subprocess.run(
        [sys.executable, "-m", "facecast.server.cli", "render", *argv, "--server", "127.0.0.1:9"],
        check=False,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2, r.stderr
    assert r.stderr.startswith(f"facecast: {where}: "), r.stderr
    assert what in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_an_unreachable_render_server_is_one_line_naming_it(tmp_path):
    (tmp_path / "x.fap").write_text("2.1 demo 25 1\n")
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "facecast.server.cli",
            "render",
            "x.fap",
            "-o",
            "x.glb",
            "--server",
            "127.0.0.1:9",
        ],
        check=False,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2 and r.stderr.startswith("facecast: http://127.0.0.1:9: "), r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr
    assert not (tmp_path / "x.glb").exists()
