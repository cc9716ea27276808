"""``facecast bench deform``: its records, its bandwidth bound and its batch test (no timing checks)."""

from __future__ import annotations

import json

import pytest

from facecast.server.bench import deform as bench
from facecast.server.cli import main


def bench_json(capsys, *args: str) -> list[dict]:
    assert main(["bench", "deform", *args, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_records_per_backend_and_size_with_the_faster_copy_as_bound(capsys):
    records = bench_json(
        capsys,
        "--vertices",
        "2k",
        "--frames",
        "3",
        "--rounds",
        "1",
        "--batch-frames",
        "4",
        "--backends",
        "opencl,numpy,scipy",
    )
    singles = [r for r in records if not r["backend"].endswith("-batch")]
    assert {r["backend"] for r in singles} >= {"numpy", "scipy"}
    for r in singles:
        assert "loadavg_1min" in r
        for key in ("ms_per_frame", "bytes_per_frame", "bandwidth_bound_ms"):
            assert r[key] > 0, (r["backend"], key)
        # (both times are rounded to 0.1 us in the record)
        rounding = 1e-4 / r["bandwidth_bound_ms"] + 1e-4 / r["ms_per_frame"]
        assert r["x_bound"] == pytest.approx(
            r["ms_per_frame"] / r["bandwidth_bound_ms"], rel=0.01 + rounding, abs=0.01
        )
        # The bound is the faster of the two plain copies (NumPy's, and the device's when there is one).
        fastest = max(r["copy_gbps_numpy"], r.get("copy_gbps_device", 0.0))
        assert r["copy_gbps"] == pytest.approx(fastest, rel=0.02, abs=0.02)
    if any(r["backend"] == "opencl" for r in singles):
        cl = next(r for r in singles if r["backend"] == "opencl")
        # The device format's own bytes, at least the rest positions read and the vertices written.
        assert cl["bytes_per_frame"] >= 24 * cl["vertices"]
        assert cl["kernel_ms"] > 0 and cl["speedup_vs_scipy"] > 0
        batch = next(r for r in records if r["backend"] == "opencl-batch")
        assert batch["frames"] == 4 and batch["realtime_factor"] > 0


def test_batch_runs_at_the_smallest_size_and_stays_within_its_memory_cap(capsys, monkeypatch):
    monkeypatch.setattr(
        bench, "BATCH_MAX_BYTES", 12 * 2100 * 3
    )  # three frames of a ~2k-vertex face
    records = bench_json(
        capsys,
        "--vertices",
        "3k",
        "2k",
        "--frames",
        "2",
        "--rounds",
        "1",
        "--batch-frames",
        "10",
        "--backends",
        "numpy",
    )
    batch = [r for r in records if r["backend"].endswith("-batch")]
    sizes = {r["vertices"] for r in records}
    assert len(sizes) == 2 and len(batch) == 1
    assert batch[0]["vertices"] == min(sizes)
    assert batch[0]["frames"] == (12 * 2100 * 3) // (12 * min(sizes))
