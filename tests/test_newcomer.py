"""The README's first-run commands and the CI entry point agree, and the setup makes a venv."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def readme_commands() -> list[str]:
    return re.findall(
        r"^    (bash \.ci/setup && .+)$", (ROOT / "README.md").read_text(), re.MULTILINE
    )


def test_readme_gives_a_serve_a_test_and_a_gates_command_through_the_setups_venv():
    serve, test, gates = readme_commands()
    assert serve == "bash .ci/setup && .venv/bin/facecast serve"
    assert test == "bash .ci/setup && .venv/bin/python -m pytest -q"
    assert gates == "bash .ci/setup && bash .ci/gates"
    assert "virtual" in (ROOT / "README.md").read_text()


def test_ci_runs_exactly_the_readmes_gates_and_test_commands_and_fails_with_either():
    lines = (ROOT / ".ci" / "run").read_text().splitlines()
    _, test, gates = readme_commands()
    assert "set -euo pipefail" in lines
    assert lines[-3:] == [f"{gates} || status=1", f"{test} || status=1", "exit $status"]
    assert "status=0" in lines[: lines.index(f"{gates} || status=1")]


def test_setup_installs_into_a_venv_never_the_system_python():
    setup = (ROOT / ".ci" / "setup").read_text()
    assert "-m venv" in setup
    pip_lines = [
        line for line in setup.splitlines() if "pip install" in line and not line.startswith("#")
    ]
    assert pip_lines and all(
        line.strip().startswith('"$VENV/bin/python" -m pip') for line in pip_lines
    )


def test_setup_installs_the_gate_tools_and_the_gates_run_each_one():
    assert '-e ".[test,dev]"' in (ROOT / ".ci" / "setup").read_text()
    gates = (ROOT / ".ci" / "gates").read_text()
    for command in ("-m ruff check", "-m ruff format --check", "-m mypy", "lint_imports_command()"):
        assert command in gates
    assert "all=(ruff format mypy imports)" in gates


def test_gates_refuse_an_unknown_gate_by_name():
    gates = ROOT / ".ci" / "gates"
    run = subprocess.run(
        ["bash", str(gates), "nonsense"], capture_output=True, text=True, check=False
    )
    if "bash .ci/setup" in run.stderr:
        pytest.skip("the venv lacks the gate tools (bash .ci/setup installs them)")
    assert run.returncode == 2 and "unknown gate 'nonsense'" in run.stderr
