"""``bench/web_viewer.py``'s CPU accounting per Chromium process type, read through the harness's
/proc helpers (``descendants``, ``process_cpu_seconds``); no browser: a stand-in process named
``chromium`` with a ``--type=`` switch, as Chromium's helper processes have."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import bench_module

from facecast.server.harness import descendants

#: Burns 0.2 s of its own CPU time, says so, then waits for its stdin to close.
BURN = (
    "import sys, time\n"
    "while time.process_time() < 0.2: pass\n"
    "print('burnt', flush=True)\n"
    "sys.stdin.read()\n"
)


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc")
def test_chromium_cpu_is_summed_by_process_type_over_descendants(tmp_path):
    fake = tmp_path / "chromium"
    fake.symlink_to(sys.executable)
    # a child that starts the stand-in renderer as its own child: a grandchild of this process
    launcher = (
        "import subprocess, sys\n"
        f"p = subprocess.Popen([{str(fake)!r}, '-c', {BURN!r}, '--type=renderer'])\n"
        "sys.exit(p.wait())\n"
    )
    with subprocess.Popen(
        [sys.executable, "-c", launcher], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    ) as proc:
        assert proc.stdin is not None and proc.stdout is not None
        try:
            assert proc.stdout.readline().strip() == "burnt"
            below = descendants(os.getpid())
            assert proc.pid in below and len(below) >= 2, below
            cpu = bench_module("web_viewer").process_cpu()
            assert cpu.get("renderer", 0.0) >= 0.15, cpu  # the stand-in's 0.2 s (10 ms clock ticks)
            assert "browser" not in cpu, cpu  # the python launcher is not Chromium
        finally:
            proc.stdin.close()
            proc.wait(timeout=30)
