"""Server side of batch jobs: hands queued jobs to spawned worker processes, watches, cancels.

At start-up, jobs left ``running`` by a stopped server go back to ``queued`` and run again (their
results are written atomically, so a half-finished attempt leaves nothing behind). A job whose
worker died ``MAX_ATTEMPTS`` times is failed rather than retried forever.
"""
from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
import shutil
from pathlib import Path

from .store import JobStore

log = logging.getLogger(__name__)

MAX_ATTEMPTS = 3
POLL_SECONDS = 0.2


class JobManager:
    """Runs up to ``workers`` jobs at a time, each in its own ``spawn`` process."""

    def __init__(self, data_dir: Path, *, workers: int = 1, backend: str = "auto", device: str | None = None):
        self.store = JobStore(data_dir)
        self.workers = max(0, int(workers))
        self.backend = backend
        self.device = device
        self._ctx = multiprocessing.get_context("spawn")
        self._running: dict[str, multiprocessing.process.BaseProcess] = {}
        self._wake = asyncio.Event()
        self._task: asyncio.Task | None = None

    async def start(self) -> None:
        again = self.store.requeue_running()
        if again:
            log.info("resuming %d job(s) interrupted by the last shutdown: %s", len(again), ", ".join(again))
        self._task = asyncio.create_task(self._loop(), name="facecast-jobs")

    async def stop(self) -> None:
        """Stop dispatching and end running workers (their jobs resume at the next start)."""
        if self._task:
            self._task.cancel()
            try:
                await self._task
            except asyncio.CancelledError:
                pass
        for job_id, proc in list(self._running.items()):
            log.info("stopping worker for job %s (it resumes at the next start)", job_id)
            proc.terminate()
        for proc in self._running.values():
            await asyncio.to_thread(proc.join, 5)
            if proc.is_alive():
                proc.kill()
        self._running.clear()
        self.store.close()

    def wake(self) -> None:
        """Look for queued jobs now (after a submit)."""
        self._wake.set()

    def cancel(self, job_id: str) -> bool:
        """Cancel a queued or running job; False if it had already finished."""
        changed = self.store.cancel(job_id)
        proc = self._running.pop(job_id, None)
        if proc is not None:
            proc.terminate()
            proc.join(2)
            if proc.is_alive():
                proc.kill()
        if changed:
            self._cleanup_partial(job_id)
        self.wake()
        return changed

    def _cleanup_partial(self, job_id: str) -> None:
        """Remove temporary files an interrupted worker left in the job folder."""
        folder = self.store.folder(job_id)
        for p in folder.glob(".*"):
            if p.is_file():
                p.unlink(missing_ok=True)

    def delete_files(self, job_id: str) -> None:
        shutil.rmtree(self.store.folder(job_id), ignore_errors=True)

    async def _loop(self) -> None:
        while True:
            try:
                self._reap()
                self._dispatch()
            except Exception:  # never let the dispatcher die silently
                log.exception("job dispatcher error")
            try:
                await asyncio.wait_for(self._wake.wait(), POLL_SECONDS)
            except asyncio.TimeoutError:
                pass
            self._wake.clear()

    def _reap(self) -> None:
        for job_id, proc in list(self._running.items()):
            if proc.is_alive():
                continue
            proc.join()
            del self._running[job_id]
            job = self.store.get(job_id)
            if job is None or job.status != "running":
                continue
            code = proc.exitcode
            if job.attempts >= MAX_ATTEMPTS:
                self.store.fail(job_id, f"the worker process died {job.attempts} times (last exit code "
                                        f"{code}); the input may be too large for this server")
            else:
                log.warning("worker for job %s exited with %s; retrying", job_id, code)
                self.store.requeue(job_id)

    def _dispatch(self) -> None:
        free = self.workers - len(self._running)
        if free <= 0:
            return
        for job in self.store.list("queued", limit=free):
            attempt = self.store.claim(job.id)
            if attempt is None:
                continue
            if attempt > MAX_ATTEMPTS:
                self.store.fail(job.id, f"gave up after {MAX_ATTEMPTS} attempts (the worker kept dying)")
                continue
            from . import worker

            proc = self._ctx.Process(target=worker.main, name=f"facecast-job-{job.id[:8]}",
                                     args=(str(self.store.data_dir), job.id, attempt, self.backend,
                                           self.device, os.getpid()), daemon=True)
            proc.start()
            self._running[job.id] = proc
            log.info("job %s started (attempt %d, worker pid %s)", job.id, attempt, proc.pid)
