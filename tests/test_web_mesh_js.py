"""The web viewer's pure mesh algorithms (client/web/js/mesh.js) under Node's test runner:
``node --test tests/js/`` (the tests are tests/js/*.test.mjs), run from here so CI runs them."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

JS_TESTS = Path(__file__).parent / "js"


def test_mesh_js_under_node():
    node = shutil.which("node")
    if node is None:
        pytest.skip("Node.js is not installed (apt-get install nodejs; .ci/setup installs it)")
    files = sorted(str(p) for p in JS_TESTS.glob("*.test.mjs"))
    assert files, f"no Node tests in {JS_TESTS}"
    out = subprocess.run(
        [node, "--test", *files], check=False, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, f"node --test failed:\n{out.stdout[-6000:]}\n{out.stderr[-2000:]}"
    assert "# fail 0" in out.stdout and "# pass 0" not in out.stdout, out.stdout[-2000:]
