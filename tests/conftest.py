"""Shared fixtures: the real data in ../shared/data, a seeded RNG, and a real server on loopback."""
from __future__ import annotations

import asyncio
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from facecast.server.paths import shared_data

ARTIFACTS = Path(__file__).parent / "artifacts"


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """``../shared/data``; tests that need it skip with a reason when it is absent."""
    d = shared_data()
    if d is None:
        pytest.skip("../shared/data is not beside this checkout (CI always has it)")
    return d


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261121)


@pytest.fixture(scope="session")
def artifacts() -> Path:
    """Folder for screenshots and other files a person should look at after a run."""
    ARTIFACTS.mkdir(exist_ok=True)
    return ARTIFACTS


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class RunningServer:
    """A real ``facecast serve`` process on a free loopback port."""

    def __init__(self, data_dir: Path, *extra: str, env: dict | None = None):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.data_dir = data_dir
        self.admin_key = "test-admin-key"
        self.extra = extra
        self.env = {**os.environ, "FACECAST_ADMIN_KEY": self.admin_key, **(env or {})}
        self.proc: subprocess.Popen | None = None
        self.log = data_dir / f"server-{self.port}.log"

    def start(self, timeout: float = 120.0) -> "RunningServer":
        cmd = [sys.executable, "-m", "facecast.server.cli", "serve", "--port", str(self.port),
               "--data-dir", str(self.data_dir), *self.extra]
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self._logf = open(self.log, "ab")
        self.proc = subprocess.Popen(cmd, env=self.env, stdout=self._logf, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited with {self.proc.returncode}:\n{self.log.read_text()[-4000:]}")
            try:
                if httpx.get(self.url + "/healthz", timeout=1.0).status_code == 200:
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        self.stop()
        raise RuntimeError(f"server did not become healthy in {timeout}s:\n{self.log.read_text()[-4000:]}")

    @property
    def admin_headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.admin_key}"}

    def stop(self) -> None:
        if self.proc and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        if getattr(self, "_logf", None):
            self._logf.close()


def live_server(root: Path, face: str, *extra: str, env: dict | None = None) -> RunningServer:
    """A started server for live tests: one ``face``, the NumPy backend (frames comparable with a batch
    render) and no job workers; ``extra`` CLI options, ``env`` extra environment."""
    return RunningServer(root, "--face", face, "--backend", "numpy", "--workers", "0", *extra, env=env).start()


def run(coro, timeout: float = 120):
    """Run ``coro`` to completion in a fresh event loop, at most ``timeout`` seconds."""
    return asyncio.run(asyncio.wait_for(coro, timeout))


@pytest.fixture(scope="module")
def server(tmp_path_factory) -> RunningServer:
    """One real server per test module (data directory in a temporary folder)."""
    s = RunningServer(tmp_path_factory.mktemp("server-data")).start()
    yield s
    s.stop()
