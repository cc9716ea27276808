"""`facecast bench serve` at a tiny load point: every viewer's frames are counted, including the
viewers that run in other client processes."""
from __future__ import annotations

import json

import pytest
from facecast.server.cli import main


@pytest.mark.slow
def test_viewers_in_other_processes_are_measured(tmp_path):
    out = tmp_path / "serve.json"
    rc = main(["bench", "serve", "--face", "default:2k", "--sessions", "", "--viewers", "3",
               "--viewer-processes", "2", "--warmup", "1", "--seconds", "2", "--out", str(out)])
    assert rc == 0
    point = json.loads(out.read_text())["viewers_sweep"][0]
    assert point["viewers_total"] == 3 and point["client_failures"] == 0
    # a viewer whose frames stayed in its process would count 0 fps here
    assert point["fps_min"] > 20 and point["frames_received"] > 3 * 20
    assert point["latency_ms_p95"] < 10_000
