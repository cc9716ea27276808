"""The live load generator (``python bench/serve.py``, run from the checkout as a user would) at a tiny
load point: every viewer's frames are counted, including the viewers that run in other client processes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from facecast.server.cli import main

ROOT = Path(__file__).resolve().parents[1]


def _serve(tmp_path: Path, *args: str) -> tuple[subprocess.CompletedProcess[str], Path]:
    """Run ``bench/serve.py`` with ``args`` for 2 s after 1 s of warm-up; (the run, its JSON)."""
    out = tmp_path / "serve.json"
    r = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "serve.py"), *args]
        + ["--warmup", "1", "--seconds", "2", "--out", str(out)],
        check=False,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )
    return r, out


@pytest.mark.slow
def test_viewers_in_other_processes_are_measured(tmp_path):
    r, out = _serve(
        tmp_path,
        *("--face", "default:2k", "--sessions", "", "--viewers", "3", "--viewer-processes", "2"),
    )
    assert r.returncode == 0, r.stderr[-4000:]
    point = json.loads(out.read_text())["viewers_sweep"][0]
    assert point["viewers_total"] == 3 and point["client_failures"] == 0, r.stderr[-4000:]
    # a viewer whose frames stayed in its process would count 0 fps here
    assert point["fps_min"] > 20 and point["frames_received"] > 3 * 20, r.stderr[-4000:]
    assert point["latency_ms_p95"] < 10_000
    assert "Viewers of one session" in r.stdout


@pytest.mark.slow
def test_cluster_mode_measures_two_nodes_beside_the_single_process(tmp_path):
    """``--cluster 2``: Redis and two nodes, every viewer on the node that does not own its
    session; reported side by side with the single process."""
    from facecast.server.harness import RedisServer

    if not RedisServer.available():
        pytest.skip("redis-server is not installed (bash .ci/setup installs it)")
    args = ["--face", "default:2k", "--sessions", "2", "--viewers", "", "--cluster", "2"]
    r, out = _serve(tmp_path, *args, "--viewer-processes", "1")
    assert r.returncode == 0, r.stderr[-4000:]
    report = json.loads(out.read_text())
    cluster = report["cluster"]["i16"]
    (point,) = cluster["sessions_sweep"]
    assert cluster["nodes"] == 2 and point["sessions"] == 2
    # both viewers got frames through Redis from the other node
    assert point["fps_min"] > 0 and point["frames_received"] > 0, r.stderr[-4000:]
    assert report["sessions_sweep"][0]["sessions"] == 2
    assert "one process vs 2 nodes + Redis" in r.stdout


def test_the_old_command_says_where_the_benchmark_went(capsys):
    assert main(["bench", "serve", "--sessions", "1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("facecast: bench serve: moved") and "python bench/serve.py" in err
