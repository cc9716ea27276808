"""A cluster node's job dispatcher: ``JobManager``'s worker processes, fed from the Redis Stream.

Each tick (in a thread: a slow or lost broker never holds the event loop) the node
- reaps its workers (a verdict acknowledges the job's entry; a worker killed from outside runs the
  job again here, up to ``MAX_ATTEMPTS`` attempts counted in Redis, over all nodes);
- renews its pending entries (``XCLAIM`` of its own entries resets their idle time) and stops a
  local worker whose job was cancelled on another node;
- takes work for its idle workers: entries idle longer than ``claim_seconds`` (their node died,
  ``XAUTOCLAIM``) first, then new ones (``XREADGROUP``). A malformed entry or one whose job is gone
  or over is acknowledged and dropped, so nothing sticks in the queue.

A node stopping cleanly hands its entries back at once (``XCLAIM ... IDLE``), a node killed after
``claim_seconds``. When Redis comes back empty (restarted without persistence), the node creates
the group again and queues what the shared job folders say was still to do.
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import redis

from ..errors import Unavailable
from .manager import CRASH_SIGNALS, MAX_ATTEMPTS, JobManager
from .redis_queue import GROUP, STREAM, RedisJobStore
from .store import JOB_ID, JobStore, results_root

log = logging.getLogger(__name__)
T = TypeVar("T")

#: Seconds an entry may go unrenewed before another node takes its job (its node is presumed dead).
DEFAULT_CLAIM_SECONDS = 30.0
#: Consumers of the group idle this long with nothing pending are removed (nodes long gone), ms.
CONSUMER_IDLE_MS = 3600 * 1000


class RedisJobManager(JobManager):
    """``JobManager`` for a node of a cluster: jobs from the Redis Stream, state in Redis."""

    def __init__(
        self,
        redis_url: str,
        data_dir: Path,
        *,
        claim_seconds: float = DEFAULT_CLAIM_SECONDS,
        **kwargs: Any,
    ):
        """``claim_seconds``: idle time after which another node takes a job whose node stopped
        renewing it. Other arguments: ``JobManager``'s."""
        self.redis_url = redis_url
        super().__init__(data_dir, **kwargs)
        self.claim_seconds = max(float(claim_seconds), 1.0)
        self.consumer = f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"
        self._held: dict[str, tuple[str, int]] = {}  # job id -> (our pending entry, attempt)
        self._todo: list[tuple[str, str]] = []  # (job id, entry) to run here, oldest first
        self._lock = threading.RLock()
        self._next_renew = 0.0
        self._broker_ok: bool | None = None  # None: not connected yet
        self._loop_ref: asyncio.AbstractEventLoop | None = None

    @property
    def rstore(self) -> RedisJobStore:
        return self.store  # type: ignore[return-value]

    def _open_store(self, data_dir: Path, results_dir: Path | None) -> JobStore:
        return RedisJobStore(self.redis_url, results_root(data_dir, results_dir))  # type: ignore[return-value]

    def store_spec(self) -> dict:
        return {"redis_url": self.redis_url, "results_dir": str(self.store.root)}

    async def io(self, fn: Callable[..., T], *args: Any) -> T:
        """``fn(*args)`` in a thread: Redis is a network away."""
        return await asyncio.to_thread(fn, *args)

    def wake(self) -> None:
        if self._loop_ref is not None:
            self._loop_ref.call_soon_threadsafe(self._wake.set)

    # -- lifecycle -------------------------------------------------------------------------------
    async def start(self) -> None:
        self._loop_ref = asyncio.get_running_loop()
        self._task = asyncio.create_task(self._loop(), name="facecast-jobs")

    async def stop(self) -> None:
        """Stop taking jobs, end the workers and hand their jobs back to the other nodes at once."""
        await self._stop_loop()
        await asyncio.to_thread(self._release)
        self.store.close()

    def _release(self) -> None:
        with self._lock:
            for slot in self._slots:
                if slot.job_id:
                    log.info("stopping the worker of job %s (another node takes it)", slot.job_id)
                slot.kill(5.0)
            entries = [e for e, _ in self._held.values()]
            self._held.clear()
            if entries:
                try:  # idle as if long unrenewed: any node's next XAUTOCLAIM takes them
                    self.rstore.r.xclaim(
                        STREAM,
                        GROUP,
                        self.consumer,
                        0,
                        entries,
                        idle=int(self.claim_seconds * 1000) + 1000,
                        justid=True,
                    )
                except redis.RedisError as e:
                    log.warning(
                        "cannot hand back %d job(s) (%s): taken after %g s",
                        len(entries),
                        e,
                        self.claim_seconds,
                    )

    async def _step(self) -> None:
        await asyncio.to_thread(self._tick)

    def _tick(self) -> None:
        with self._lock:
            try:
                if not self._broker_ok:
                    self._connect()
                self._reap()
                self._renew()
                self._dispatch()
                self._purge()
                self.rstore.refresh_counts()
            except redis.ResponseError as e:
                if "NOGROUP" not in str(e):
                    raise
                self._connect()  # Redis restarted empty
            except Unavailable as e:
                if self._broker_ok is not False:
                    log.warning("%s; jobs wait until it is back", e)
                self._broker_ok = False
                time.sleep(0.5)  # in the dispatcher's thread: the loop retries at its pace

    def _connect(self) -> None:
        """(Re)create the group; on a new or emptied Redis, queue again what the job folders
        say was still to do."""
        created = self.rstore.ensure_group()
        if self._broker_ok is False:
            log.info("the job queue (Redis at %s) is back", self.rstore.where)
        self._broker_ok = True
        if created:
            back = self.rstore.recover()
            if back:
                log.info(
                    "queued %d job(s) again from their folders: %s", len(back), ", ".join(back)
                )

    # -- our entries -----------------------------------------------------------------------------
    def _over(self, job_id: str) -> None:
        held = self._held.pop(job_id, None)
        if held is None:
            return
        r = self.rstore.r
        try:
            r.xack(STREAM, GROUP, held[0])
            r.xdel(STREAM, held[0])
        except redis.RedisError as e:  # it stays pending: whoever takes it finds the job over
            log.warning("job %s: cannot acknowledge its queue entry: %s", job_id, e)

    def _finished(self, job_id: str) -> None:
        _, attempt = self._held.get(job_id, ("", 0))
        try:
            job = self.store.get(job_id)
        except Unavailable:
            self._again(job_id)
            raise
        if job is not None and job.status == "running" and job.attempts != attempt:
            self._held.pop(job_id, None)  # another node took it over: its entry now, not ours
        elif job is not None and job.status == "running":
            self._again(job_id)  # no verdict (the broker went away mid-job?): run it again here
        else:
            self._over(job_id)  # a verdict, or the job was cancelled

    def _worker_died(self, job_id: str, code: int | None) -> None:
        try:
            job = self.store.get(job_id)
        except Unavailable:
            self._again(job_id)
            raise
        if job is None or job.status != "running":
            self._over(job_id)
            return
        if job.attempts != self._held.get(job_id, ("", 0))[1]:
            self._held.pop(job_id, None)  # another node took it over
            return
        crash = CRASH_SIGNALS.get(-code) if code is not None and code < 0 else None
        if crash:
            super()._worker_died(job_id, code)  # fails it, no retry
            self._over(job_id)
        else:
            log.warning("worker for job %s exited with %s; running the job again", job_id, code)
            self._again(job_id)  # the attempt limit is checked when it is claimed again

    def _again(self, job_id: str) -> None:
        held = self._held.get(job_id)
        if held is not None and all(j != job_id for j, _ in self._todo):
            self._todo.append((job_id, held[0]))

    def _renew(self) -> None:
        """Keep our entries ours (reset their idle time); stop local workers of cancelled jobs."""
        now = time.monotonic()
        if now < self._next_renew or not self._held:
            return
        self._next_renew = now + self.claim_seconds / 4
        r = self.rstore.r
        try:
            pending = r.xpending_range(
                STREAM, GROUP, "-", "+", len(self._held) + 100, consumername=self.consumer
            )
            mine = {_s(p["message_id"]) for p in pending}
            for job_id, (entry, _) in list(self._held.items()):
                if entry not in mine:  # we stalled and another node took it: theirs now
                    log.warning("job %s was taken over by another node", job_id)
                    self._held.pop(job_id)
                    self._todo = [(j, e) for j, e in self._todo if j != job_id]
            if self._held:
                r.xclaim(
                    STREAM,
                    GROUP,
                    self.consumer,
                    0,
                    [e for e, _ in self._held.values()],
                    justid=True,
                )
        except (redis.ConnectionError, redis.TimeoutError) as e:
            raise Unavailable(
                f"the job queue (Redis at {self.rstore.where}) is unreachable ({type(e).__name__})"
            ) from None
        for slot in self._slots:
            if slot.job_id:
                job = self.store.get(slot.job_id)
                if job is None or job.status != "running":
                    log.info("job %s is %s; stopping its worker", slot.job_id, job and job.status)
                    job_id = slot.job_id
                    slot.kill()
                    self._over(job_id)

    def _take(self, n: int) -> None:
        """Up to ``n`` entries onto ``_todo``: stale ones of dead nodes first, then new ones."""
        r = self.rstore.r
        got: list[Any] = []
        try:
            _, claimed, *_ = r.xautoclaim(
                STREAM, GROUP, self.consumer, int(self.claim_seconds * 1000), "0-0", count=n
            )
            got += claimed
            if len(got) < n:
                new = r.xreadgroup(GROUP, self.consumer, {STREAM: ">"}, count=n - len(got))
                got += new[0][1] if new else []
        except redis.ResponseError as e:
            if "NOGROUP" in str(e):  # Redis restarted empty
                self._connect()
                return
            raise
        except (redis.ConnectionError, redis.TimeoutError) as e:
            raise Unavailable(
                f"the job queue (Redis at {self.rstore.where}) is unreachable ({type(e).__name__})"
            ) from None
        for raw_entry, fields in got:
            entry = _s(raw_entry)
            job_id = _s((fields or {}).get(b"id", b""))
            if not JOB_ID.match(job_id) or job_id in self._held:
                log.warning("dropping a malformed or repeated queue entry %s: %r", entry, fields)
                r.xack(STREAM, GROUP, entry)
                r.xdel(STREAM, entry)
                continue
            self._held[job_id] = (entry, 0)
            self._todo.append((job_id, entry))

    def _dispatch(self) -> None:
        idle = [s for s in self._slots if s.job_id is None]
        if not idle:
            return
        if len(self._todo) < len(idle):
            self._take(len(idle) - len(self._todo))
        while idle and self._todo:
            job_id, entry = self._todo[0]
            attempt = self.store.claim(job_id)
            self._todo.pop(0)
            if attempt is None:  # unknown, cancelled or already over
                self._over(job_id)
                continue
            self._held[job_id] = (entry, attempt)
            if attempt > MAX_ATTEMPTS:
                self.store.fail(
                    job_id, f"gave up after {MAX_ATTEMPTS} attempts (the worker kept dying)"
                )
                self._over(job_id)
                continue
            slot = idle.pop()
            if not slot.alive():
                self._spawn(slot)
            slot.job_id = job_id
            slot.started = time.monotonic()
            slot.conn.send((job_id, attempt))  # type: ignore[attr-defined]
            log.info("job %s started (attempt %d, worker pid %s)", job_id, attempt, slot.proc.pid)  # type: ignore[union-attr]

    def cancel(self, job_id: str) -> bool:
        """Cancel a queued or running job; a worker running it here stops now, elsewhere at its
        next progress report (or that node's next renewal)."""
        changed = self.store.cancel(job_id)
        with self._lock:
            for slot in self._slots:
                if slot.job_id == job_id:
                    slot.kill()
                    self._over(job_id)
        if changed:
            for p in self.store.folder(job_id).glob(".*"):
                if p.is_file():
                    p.unlink(missing_ok=True)
        return changed

    def _purge(self) -> None:
        due = self.retention and time.time() >= self._next_purge
        super()._purge()
        if due:  # and forget consumers of nodes long gone (only those with nothing pending)
            r = self.rstore.r
            for c in r.xinfo_consumers(STREAM, GROUP):
                name = _s(c["name"])
                if name != self.consumer and not c["pending"] and c["idle"] > CONSUMER_IDLE_MS:
                    r.xgroup_delconsumer(STREAM, GROUP, name)


def _s(v: bytes | str) -> str:
    return v.decode("utf-8", "replace") if isinstance(v, bytes) else v
