"""One atomic-write helper per layer (server/output/atomic.py, client/files.py): every writer
leaves the old file or the whole new one, never a part, and nothing behind on failure."""

from __future__ import annotations

import stat

import httpx
import numpy as np
import pytest

from facecast.client import files as client_files
from facecast.client import jobs as client_jobs
from facecast.protocol.markers_file import MarkerTake
from facecast.server.api.security import resolve_admin_key
from facecast.server.mocap.io import write_take
from facecast.server.output import atomic


def _mode(path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


@pytest.mark.parametrize("helper", [atomic.atomic_path, client_files.atomic_path])
def test_both_helpers_keep_the_old_file_on_failure_and_replace_it_on_success(tmp_path, helper):
    target = tmp_path / "out.bin"
    target.write_bytes(b"old")

    def write_then_fail() -> None:
        with helper(target) as tmp:
            tmp.write_bytes(b"partial")
            raise RuntimeError("boom")

    with pytest.raises(RuntimeError):
        write_then_fail()
    assert target.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == ["out.bin"]
    with helper(target) as tmp:
        assert tmp.parent == tmp_path and tmp.name.startswith(".out.bin.")
        tmp.write_bytes(b"new")
    assert target.read_bytes() == b"new" and _mode(target) == 0o644
    assert [p.name for p in tmp_path.iterdir()] == ["out.bin"]


def test_a_secret_is_never_readable_by_others(tmp_path):
    atomic.write_bytes_atomic(tmp_path / "s", b"x", mode=0o600)
    assert _mode(tmp_path / "s") == 0o600
    key, created = resolve_admin_key(None, tmp_path / "data")
    assert created and _mode(tmp_path / "data" / "admin.key") == 0o600
    assert [p.name for p in (tmp_path / "data").iterdir()] == ["admin.key"]
    assert resolve_admin_key(None, tmp_path / "data") == (key, False)


def test_a_take_whose_write_fails_leaves_the_old_file_and_nothing_else(tmp_path, monkeypatch):
    take = MarkerTake(["A", "B"], np.ones((3, 2, 3)), 60.0, "mm")
    path = write_take(take, tmp_path / "t.c3d")
    old = path.read_bytes()

    def disk_full(self, data):
        with open(self, "wb") as fh:
            fh.write(data[: len(data) // 2])
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(type(path), "write_bytes", disk_full)
    with pytest.raises(OSError, match="No space"):
        write_take(MarkerTake(["A", "B"], np.zeros((5, 2, 3)), 60.0, "mm"), path)
    assert path.read_bytes() == old and [p.name for p in tmp_path.iterdir()] == ["t.c3d"]


def test_a_failed_download_leaves_nothing(tmp_path):
    def handler(request: httpx.Request) -> httpx.Response:
        return httpx.Response(
            404, json={"error": "no such job", "detail": "no such job", "status": 404}
        )

    with (
        httpx.Client(transport=httpx.MockTransport(handler), base_url="http://x") as client,
        pytest.raises(Exception, match="no such job"),
    ):
        client_jobs.download(client, "j1", tmp_path / "r.glb")
    assert list(tmp_path.iterdir()) == []
