"""Where ``facecast serve --workers N`` puts its node processes (``cluster.workers.placement``)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from facecast.server.cluster import workers


@pytest.fixture
def cpus(monkeypatch):
    """Pretend this process may run on the CPUs given."""
    monkeypatch.delenv(workers.PIN_ENV, raising=False)
    monkeypatch.delenv("POCL_MAX_PTHREAD_COUNT", raising=False)

    def use(ids: set[int]) -> None:
        monkeypatch.setattr(workers.os, "sched_getaffinity", lambda pid: set(ids))

    return use


def test_one_node_per_core_pins_each_to_its_core_with_one_pocl_thread(cpus):
    cpus({0, 1})
    assert workers.placement(0, 2) == ({0}, {"POCL_MAX_PTHREAD_COUNT": "1", "POCL_AFFINITY": "0"})
    assert workers.placement(1, 2) == ({1}, {"POCL_MAX_PTHREAD_COUNT": "1", "POCL_AFFINITY": "0"})


def test_fewer_nodes_than_cores_share_them_out(cpus):
    cpus({2, 3, 5, 7, 8})  # only the CPUs this process may use, in order; one left over
    assert workers.placement(0, 2) == (
        {2, 3},
        {"POCL_MAX_PTHREAD_COUNT": "2", "POCL_AFFINITY": "0"},
    )
    assert workers.placement(1, 2) == (
        {5, 7},
        {"POCL_MAX_PTHREAD_COUNT": "2", "POCL_AFFINITY": "0"},
    )


@pytest.mark.parametrize(("available", "n"), [({0, 1}, 3), ({0, 1}, 1), ({0}, 1)])
def test_one_node_or_more_nodes_than_cores_are_not_pinned(cpus, available, n):
    cpus(available)
    assert all(workers.placement(i, n) == (None, {}) for i in range(n))


def test_pinning_can_be_switched_off_and_a_chosen_pocl_pool_is_kept(cpus, monkeypatch):
    cpus({0, 1})
    monkeypatch.setenv(workers.PIN_ENV, "0")
    assert workers.placement(0, 2) == (None, {})
    monkeypatch.setenv(workers.PIN_ENV, "1")
    monkeypatch.setenv("POCL_MAX_PTHREAD_COUNT", "2")
    assert workers.placement(1, 2) == ({1}, {"POCL_AFFINITY": "0"})


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs 2 CPUs")
def test_a_pinned_child_runs_on_its_cpus_only():
    """What ``supervise`` runs before exec: the affinity survives it (PoCL's threads inherit it)."""
    cpu = max(os.sched_getaffinity(0))
    out = subprocess.run(
        [sys.executable, "-c", "import os; print(sorted(os.sched_getaffinity(0)))"],
        preexec_fn=workers.before_exec({cpu}),
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert out.strip() == f"[{cpu}]"
