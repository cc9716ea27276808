"""Shared fixtures: the real data in ../shared/data, a seeded RNG, a real server and a real Redis on
loopback."""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest

from facecast.server.harness import LocalServer, RedisServer
from facecast.server.paths import shared_data

ARTIFACTS = Path(__file__).parent / "artifacts"


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """``../shared/data``; tests that need it skip with a reason when it is absent."""
    d = shared_data()
    if d is None:
        pytest.skip("../shared/data is not beside this checkout (CI always has it)")
    return d


@pytest.fixture(scope="session")
def ict_head(data_dir: Path):
    """The ICT FaceKit head and its expression shapes: ``(face, names, deltas (E, V, 3))``."""
    if not (data_dir / "ict-facekit" / "expressions").is_dir():
        pytest.skip("../shared/data/ict-facekit is not beside this checkout")
    from facecast.server.mocap.generate import load_expressions, load_ict

    face = load_ict()
    names, deltas = load_expressions(face)
    return face, names, deltas


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261121)


@pytest.fixture(scope="session")
def artifacts() -> Path:
    """Folder for screenshots and other files a person should look at after a run."""
    ARTIFACTS.mkdir(exist_ok=True)
    return ARTIFACTS


class RunningServer(LocalServer):
    """A real ``facecast serve`` process on a free loopback port, admin key ``test-admin-key``."""

    def __init__(self, data_dir: Path, *extra: str, env: dict | None = None):
        super().__init__(data_dir, *extra, env=env, admin_key="test-admin-key")


def live_server(root: Path, face: str, *extra: str, env: dict | None = None) -> RunningServer:
    """A started server for live tests: one ``face``, the NumPy backend (frames comparable with a batch
    render) and no job workers; ``extra`` CLI options, ``env`` extra environment."""
    return RunningServer(
        root, "--face", face, "--backend", "numpy", "--job-workers", "0", *extra, env=env
    ).start()


def bench_module(name: str):
    """``bench/<name>.py`` loaded as a module (bench/ is not a package), for tests of a bench's
    own helpers."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        f"_bench_{name}", Path(__file__).resolve().parents[1] / "bench" / f"{name}.py"
    )
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def run(coro, timeout: float = 120):
    """Run ``coro`` to completion in a fresh event loop, at most ``timeout`` seconds."""
    return asyncio.run(asyncio.wait_for(coro, timeout))


@pytest.fixture(scope="module")
def server(tmp_path_factory) -> RunningServer:
    """One real server per test module (data directory in a temporary folder)."""
    s = RunningServer(tmp_path_factory.mktemp("server-data")).start()
    yield s
    s.stop()


@pytest.fixture
def redis_server() -> RedisServer:
    """A real, empty ``redis-server`` on a free loopback port for one test (``.ci/setup`` installs
    it; the test skips with a reason where it is missing). ``kill()``/``start()`` restart it."""
    if not RedisServer.available():
        pytest.skip("redis-server is not installed (bash .ci/setup installs it)")
    r = RedisServer().start()
    yield r
    r.stop()
