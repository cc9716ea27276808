"""Server side of batch jobs: hands queued jobs to worker processes, watches them, cancels.

Workers are ``spawn``-ed on first need and kept for later jobs (``workers`` of them at most). At
start-up, jobs left ``running`` by a stopped server go back to ``queued`` and run again (results
are written atomically, so a half-finished attempt leaves nothing behind). A job whose worker died
``MAX_ATTEMPTS`` times is failed rather than retried forever. Finished jobs are deleted after
``retention_hours`` (``ServerConfig.job_retention_hours``, ``FACECAST_JOB_RETENTION_HOURS``; a week).
A worker that crashes in native code (SIGSEGV...) fails its job at once. A job running longer than
``job_timeout`` (``FACECAST_JOB_TIMEOUT_SECONDS``) is failed and its worker
killed. Workers die with the server (``worker.serve``), so none outlives it to race a resumed job.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from .store import JobStore

log = logging.getLogger(__name__)
T = TypeVar("T")

MAX_ATTEMPTS = 3
#: Signals of a worker that faulted in native code (a decoder on a malformed file): no retry.
CRASH_SIGNALS = {
    int(getattr(signal, n)): n
    for n in ("SIGSEGV", "SIGBUS", "SIGILL", "SIGFPE", "SIGABRT")
    if hasattr(signal, n)
}
POLL_SECONDS = 0.2
#: Finished jobs (and their files) are deleted this long after they finished (0 keeps them).
DEFAULT_RETENTION_HOURS = 7 * 24.0
PURGE_EVERY_SECONDS = 600.0


@dataclass
class _Slot:
    """One worker process (None until needed or after it died) and the job it is running."""

    proc: multiprocessing.process.BaseProcess | None = None
    conn: object | None = None
    job_id: str | None = None
    started: float = 0.0  # time.monotonic() when the job was handed to the worker

    def alive(self) -> bool:
        return self.proc is not None and self.proc.is_alive()

    def kill(self, wait: float = 2.0) -> None:
        if self.proc is not None:
            self.proc.terminate()
            self.proc.join(wait)
            if self.proc.is_alive():
                self.proc.kill()
                self.proc.join(wait)
        if self.conn is not None:
            self.conn.close()
        self.proc = self.conn = self.job_id = None


class JobManager:
    """Runs up to ``workers`` jobs at a time in ``spawn``-ed worker processes (0: queue only)."""

    def __init__(
        self,
        data_dir: Path,
        *,
        workers: int = 1,
        backend: str = "auto",
        device: str | None = None,
        retention_hours: float = DEFAULT_RETENTION_HOURS,
        job_timeout: float = 0.0,
        memory_mb: int = 0,
        results_dir: Path | None = None,
    ):
        """``job_timeout``: seconds a job may run before it is failed and its worker killed (0: no limit);
        ``memory_mb``: address space of a worker process in MiB (0: no limit); ``results_dir``:
        where job folders live (None: ``<data_dir>/jobs``)."""
        self.store: JobStore = self._open_store(data_dir, results_dir)
        self.data_dir = Path(data_dir)
        self.workers = max(0, int(workers))
        self.backend = backend
        self.device = device
        self._ctx = multiprocessing.get_context("spawn")
        self._slots = [_Slot() for _ in range(self.workers)]
        self._wake = asyncio.Event()
        self._task: asyncio.Task | None = None
        self.retention = max(float(retention_hours), 0.0) * 3600.0  # seconds; 0 = keep forever
        self._next_purge = 0.0
        self.job_timeout = max(float(job_timeout), 0.0)
        self.memory_mb = max(int(memory_mb), 0)

    def _open_store(self, data_dir: Path, results_dir: Path | None) -> JobStore:
        return JobStore(data_dir, results_dir)

    def store_spec(self) -> dict:
        """What a worker process needs to open the same store (``worker.open_store``); JSON only."""
        return {"results_dir": str(self.store.root)}

    async def io(self, fn: Callable[..., T], *args: Any) -> T:
        """``fn(*args)`` for a route: SQLite calls are quick and run here (subclasses whose store
        waits on the network run them in a thread)."""
        return fn(*args)

    # -- lifecycle -------------------------------------------------------------------------------
    async def start(self) -> None:
        orphans = self.store.sweep_orphans()
        if orphans:
            log.info("removed %d unfinished upload(s) left by the last run", len(orphans))
        again = self.store.requeue_running()
        if again:
            log.info(
                "resuming %d job(s) interrupted by the last shutdown: %s",
                len(again),
                ", ".join(again),
            )
        self._task = asyncio.create_task(self._loop(), name="facecast-jobs")

    async def stop(self) -> None:
        """Stop dispatching and end the workers (running jobs resume at the next start)."""
        await self._stop_loop()
        for slot in self._slots:
            if slot.job_id:
                log.info(
                    "stopping the worker of job %s (it resumes at the next start)", slot.job_id
                )
            elif slot.alive():
                try:
                    slot.conn.send(None)  # idle: ask it to leave
                except OSError:
                    pass
        await asyncio.gather(*(asyncio.to_thread(s.kill, 5.0) for s in self._slots))
        self.store.close()

    async def _stop_loop(self) -> None:
        """Cancel the dispatcher task and wait for it to end."""
        if self._task:
            self._task.cancel()
            try:
                await self._task
            except asyncio.CancelledError:
                pass

    def wake(self) -> None:
        """Look for queued jobs now (after a submit)."""
        self._wake.set()

    def running(self) -> list[str]:
        """Ids of the jobs workers are running now."""
        return [s.job_id for s in self._slots if s.job_id]

    # -- cancel ----------------------------------------------------------------------------------
    def cancel(self, job_id: str) -> bool:
        """Cancel a queued or running job (its worker is terminated); False if it had finished."""
        changed = self.store.cancel(job_id)
        for slot in self._slots:
            if slot.job_id == job_id:
                log.info("job %s cancelled; stopping its worker (pid %s)", job_id, slot.proc.pid)
                slot.kill()
        if changed:
            folder = self.store.folder(job_id)
            for p in folder.glob(".*"):  # partial files of an interrupted atomic write
                if p.is_file():
                    p.unlink(missing_ok=True)
        self.wake()
        return changed

    # -- dispatch loop ---------------------------------------------------------------------------
    async def _step(self) -> None:
        """One round of the dispatcher (subclasses whose store is a network away use a thread)."""
        self._reap()
        self._dispatch()
        self._purge()

    async def _loop(self) -> None:
        while True:
            try:
                await self._step()
            except Exception:  # never let the dispatcher die silently
                log.exception("job dispatcher error")
            try:
                await asyncio.wait_for(self._wake.wait(), POLL_SECONDS)
            except asyncio.TimeoutError:
                pass
            self._wake.clear()

    def _reap(self) -> None:
        for slot in self._slots:
            if slot.job_id is None:
                if slot.proc is not None and not slot.proc.is_alive():
                    slot.kill(0)  # an idle worker died: forget it, a new one starts when needed
                continue
            finished = False
            try:
                while slot.conn.poll():
                    finished = slot.conn.recv() == slot.job_id or finished
            except (EOFError, OSError):
                pass
            if (
                not finished
                and self.job_timeout
                and time.monotonic() - slot.started > self.job_timeout
            ):
                self._time_out(slot)
                continue
            if finished:
                job_id, slot.job_id = slot.job_id, None
                self._finished(job_id)
            elif not slot.proc.is_alive():
                job_id, code = slot.job_id, slot.proc.exitcode
                slot.kill(0)
                self._worker_died(job_id, code)

    def _finished(self, job_id: str) -> None:
        """A worker says it is done with ``job_id`` (its verdict is recorded, or it gave up)."""
        job = self.store.get(job_id)
        if job is not None and job.status == "running":  # abandoned without a verdict
            self.store.fail(job_id, "the worker gave up on this job; submit it again")
        self._over(job_id)

    def _over(self, job_id: str) -> None:
        """This server is done with ``job_id`` (a queue that delivers jobs acknowledges it here)."""

    def _time_out(self, slot: _Slot) -> None:
        """Fail the slot's job for running too long and kill its worker (a new one starts when needed)."""
        job_id = slot.job_id
        self.store.fail(
            job_id,
            f"the job ran longer than this server's limit of {self.job_timeout:g} s and was "
            "stopped; send a shorter input, or ask the operator to raise "
            "FACECAST_JOB_TIMEOUT_SECONDS",
        )
        log.warning(
            "job %s exceeded %g s; killing its worker (pid %s)",
            job_id,
            self.job_timeout,
            slot.proc.pid if slot.proc else None,
        )
        slot.kill(1.0)
        if job_id:
            self._over(job_id)

    def _purge(self) -> None:
        now = time.time()
        if not self.retention or now < self._next_purge:
            return
        self._next_purge = now + PURGE_EVERY_SECONDS
        gone = self.store.purge(now - self.retention)
        if gone:
            log.info("deleted %d finished job(s) older than %g h", len(gone), self.retention / 3600)

    def _worker_died(self, job_id: str, code: int | None) -> None:
        job = self.store.get(job_id)
        if job is None or job.status != "running":
            return
        crash = CRASH_SIGNALS.get(-code) if code is not None and code < 0 else None
        if crash:  # native code faulted on this input: running it again would fault again
            log.warning("worker for job %s crashed (%s) on %s input", job_id, crash, job.input_kind)
            self.store.fail(
                job_id,
                f"reading {job.input_name!r} crashed the decoder ({crash}); the file is "
                f"probably damaged: check it or export it again",
            )
        elif job.attempts >= MAX_ATTEMPTS:
            self.store.fail(
                job_id,
                f"the worker process died {job.attempts} times (last exit code {code}); "
                "the input may be too large for this server",
            )
        else:
            log.warning("worker for job %s exited with %s; running the job again", job_id, code)
            self.store.requeue(job_id)

    def _dispatch(self) -> None:
        idle = [s for s in self._slots if s.job_id is None]
        if not idle:
            return
        for job in self.store.list("queued", limit=len(idle)):
            attempt = self.store.claim(job.id)
            if attempt is None:
                continue
            if attempt > MAX_ATTEMPTS:
                self.store.fail(
                    job.id, f"gave up after {MAX_ATTEMPTS} attempts (the worker kept dying)"
                )
                continue
            slot = idle.pop()
            if not slot.alive():
                self._spawn(slot)
            slot.job_id = job.id
            slot.started = time.monotonic()
            slot.conn.send((job.id, attempt))
            log.info("job %s started (attempt %d, worker pid %s)", job.id, attempt, slot.proc.pid)

    def _spawn(self, slot: _Slot) -> None:
        from . import worker

        slot.kill(0)
        mine, theirs = self._ctx.Pipe()
        slot.proc = self._ctx.Process(
            target=worker.serve,
            name="facecast-job-worker",
            daemon=True,
            args=(
                str(self.data_dir),
                theirs,
                self.backend,
                self.device,
                os.getpid(),
                self.memory_mb,
                self.store_spec(),
            ),
        )
        slot.proc.start()
        theirs.close()
        slot.conn = mine
