"""Batch jobs across nodes: the queue is a Redis Stream, job state Redis hashes, files a shared folder.

With ``FACECAST_REDIS_URL`` every node accepts jobs, every node's workers take them, every node
answers their status and serves their results:

- ``facecast:jobs:queue``: a Stream, one entry ``{"id": <job id>}`` per submitted job, read by the
  consumer group ``workers`` (one consumer per node process). An entry stays *pending* until the
  node that read it acknowledges it (XACK) once the job is over; the node renews its entries
  while it runs them (XCLAIM of its own entries, which resets their idle time). A node that dies
  stops renewing: after ``claim_seconds`` idle any node takes the entry (XAUTOCLAIM) and runs the
  job again. Delivery is at least once.
- ``facecast:jobs:job:<id>``: the job's state, a hash of strings (options as JSON; never pickle).
  Every change is one Lua script (atomic in Redis): a claim bumps ``attempts``; progress and the
  verdict of an attempt are compare-and-set on (status, attempts), so a superseded or cancelled
  attempt writes nothing, and a job is ``done`` once.
- ``facecast:jobs:status:<state>``: sorted sets of ids by creation time (listing and counts).
- ``<results_dir>/<id>/``: input, layout and result, on storage all nodes share. Results are
  written atomically (temporary name, fsync, rename), so a second completion of the same job
  renames the same bytes over the first. ``job.json`` there keeps the record (written at submit
  and at the verdict): a status still answers, and queued work is put back, after Redis lost its
  data.

Why Streams and not a queue library (rq, arq, celery): consumer groups already give what is
needed, at-least-once delivery with a pending list per consumer and claiming of stale entries, in
the Redis the cluster has anyway; rq and celery move pickled Python objects (this project sends no
pickle through Redis); and the state machine (attempts, cancel, compare-and-set verdicts) stays the
one ``store.JobStore`` has, in a few scripts, with no extra dependency or daemon.
"""

from __future__ import annotations

import builtins
import json
import logging
import shutil
import time
from collections.abc import Callable
from functools import wraps
from pathlib import Path
from typing import Any, TypeVar
from urllib.parse import urlsplit

import redis

from ..errors import Unavailable
from ..output.atomic import fsync_path, write_bytes_atomic
from .store import COLUMNS, JOB_ID, JobFiles, JobRecord

log = logging.getLogger(__name__)

PREFIX = "facecast:jobs"
STREAM = f"{PREFIX}:queue"
GROUP = "workers"
STATES = ("queued", "running", "done", "failed", "cancelled")
FINISHED = ("done", "failed", "cancelled")
#: The job's record in its folder (JSON), for when Redis has lost it.
RECORD = "job.json"
#: Seconds a Redis command may take (connect, then reply) before the store says it is unreachable.
CONNECT_TIMEOUT = 2.0
SOCKET_TIMEOUT = 5.0

F = TypeVar("F", bound=Callable[..., Any])

# Moving a job between the status sets, with its hash: shared by the scripts below.
_MOVE = """
local function move(key, id, old, new)
  redis.call('ZREM', ARGV[1] .. ':status:' .. old, id)
  redis.call('ZADD', ARGV[1] .. ':status:' .. new, redis.call('HGET', key, 'created'), id)
  redis.call('HSET', key, 'status', new)
end
"""

#: KEYS: hash. ARGV: prefix, id, created, field, value, ... -> 1 added, 0 exists.
ADD = """
if redis.call('EXISTS', KEYS[1]) == 1 then return 0 end
redis.call('HSET', KEYS[1], unpack(ARGV, 4))
redis.call('ZADD', ARGV[1] .. ':status:queued', ARGV[3], ARGV[2])
redis.call('XADD', ARGV[1] .. ':queue', '*', 'id', ARGV[2])
return 1
"""

#: KEYS: hash. ARGV: prefix, id, now -> the new attempt number, or nil if the job is over.
CLAIM = (
    _MOVE
    + """
local st = redis.call('HGET', KEYS[1], 'status')
if st ~= 'queued' and st ~= 'running' then return false end
local n = redis.call('HINCRBY', KEYS[1], 'attempts', 1)
redis.call('HSET', KEYS[1], 'started', ARGV[3], 'progress', '0', 'error', '')
move(KEYS[1], ARGV[2], st, 'running')
return n
"""
)

#: KEYS: hash. ARGV: attempt, fraction -> 1 recorded, 0 the job is no longer this attempt's.
PROGRESS = """
if redis.call('HGET', KEYS[1], 'status') ~= 'running' then return 0 end
if redis.call('HGET', KEYS[1], 'attempts') ~= ARGV[1] then return 0 end
redis.call('HSET', KEYS[1], 'progress', ARGV[2])
return 1
"""

#: KEYS: hash. ARGV: prefix, id, attempt, status, error, now -> 1 set, 0 not (over, or superseded).
#: 'done' is taken from any attempt of a running job (its result is the same bytes); 'failed'
#: only from the current one.
FINISH = (
    _MOVE
    + """
if redis.call('HGET', KEYS[1], 'status') ~= 'running' then return 0 end
if ARGV[4] ~= 'done' and redis.call('HGET', KEYS[1], 'attempts') ~= ARGV[3] then return 0 end
redis.call('HSET', KEYS[1], 'error', ARGV[5], 'finished', ARGV[6])
if ARGV[4] == 'done' then redis.call('HSET', KEYS[1], 'progress', '1') end
move(KEYS[1], ARGV[2], 'running', ARGV[4])
return 1
"""
)

#: KEYS: hash. ARGV: prefix, id, status (failed | cancelled), error, now -> 1 set, 0 already over.
STOP = (
    _MOVE
    + """
local st = redis.call('HGET', KEYS[1], 'status')
if st ~= 'queued' and st ~= 'running' then return 0 end
redis.call('HSET', KEYS[1], 'error', ARGV[4], 'finished', ARGV[5])
move(KEYS[1], ARGV[2], st, ARGV[3])
return 1
"""
)


def redis_location(url: str) -> str:
    """``host:port`` of a Redis URL, for messages (never its password)."""
    try:
        u = urlsplit(url)
        return f"{u.hostname or '?'}:{u.port or 6379}"
    except ValueError:
        return "the configured Redis"


def _unreachable(fn: F) -> F:
    """Turn a lost Redis into ``Unavailable`` (503) naming the broker, never a 500."""

    @wraps(fn)
    def call(self: RedisJobStore, *args: Any, **kwargs: Any) -> Any:
        try:
            return fn(self, *args, **kwargs)
        except (redis.ConnectionError, redis.TimeoutError) as e:
            raise Unavailable(
                f"the job queue (Redis at {self.where}) is unreachable ({type(e).__name__}); "
                "try again in a moment",
                where="redis",
            ) from None

    return call  # type: ignore[return-value]


def _text(v: bytes | str | None) -> str:
    return v.decode("utf-8", "replace") if isinstance(v, bytes) else (v or "")


def record_from_hash(job_id: str, h: dict) -> JobRecord:
    """A ``JobRecord`` from a job hash (bytes or str fields); ValueError if it is malformed."""
    d = {_text(k): _text(v) for k, v in h.items()}
    try:
        return JobRecord(
            id=job_id,
            status=d["status"],
            progress=float(d.get("progress") or 0.0),
            error=d.get("error") or None,
            input_name=d["input_name"],
            input_kind=d["input_kind"],
            input_file=d["input_file"],
            input_bytes=int(d["input_bytes"]),
            result_file=d["result_file"],
            options=json.loads(d.get("options") or "{}"),
            attempts=int(d.get("attempts") or 0),
            created=float(d["created"]),
            started=float(d["started"]) if d.get("started") else None,
            finished=float(d["finished"]) if d.get("finished") else None,
        )
    except (KeyError, ValueError, TypeError) as e:
        raise ValueError(f"malformed job {job_id}: {type(e).__name__}: {e}") from None


def hash_of(job: JobRecord) -> dict[str, str]:
    """The hash fields of a job (strings; options as JSON)."""
    out: dict[str, str] = {}
    for k in COLUMNS:
        v = getattr(job, k)
        out[k] = json.dumps(v) if k == "options" else ("" if v is None else str(v))
    return out


class RedisJobStore(JobFiles):
    """Job state in Redis, job folders in ``results_dir``: the same calls as ``JobStore``.

    Safe in threads and processes (each process opens its own). A lost broker raises ``Unavailable``.
    ``counts()`` answers the last ``refresh_counts()`` (health and metrics never wait on Redis).
    """

    def __init__(self, url: str, results_dir: Path):
        super().__init__(results_dir)
        self.url = url
        self.where = redis_location(url)
        self.r: Any = redis.Redis.from_url(  # Any: the client's stubs do not type replies
            url,
            socket_connect_timeout=CONNECT_TIMEOUT,
            socket_timeout=SOCKET_TIMEOUT,
            health_check_interval=30,
        )
        self._add = self.r.register_script(ADD)
        self._claim = self.r.register_script(CLAIM)
        self._progress = self.r.register_script(PROGRESS)
        self._finish = self.r.register_script(FINISH)
        self._stop = self.r.register_script(STOP)
        self._counts: dict[str, int] = {}

    def close(self) -> None:
        self.r.close()

    @staticmethod
    def key(job_id: str) -> str:
        return f"{PREFIX}:job:{job_id}"

    # -- the queue -------------------------------------------------------------------------------
    @_unreachable
    def ensure_group(self) -> bool:
        """Create the stream and its consumer group if missing; True if it was created (a new or
        emptied Redis: ``recover()`` puts back what the job folders say was still to do)."""
        try:
            self.r.xgroup_create(STREAM, GROUP, id="0", mkstream=True)
        except redis.ResponseError as e:
            if "BUSYGROUP" in str(e):
                return False
            raise
        return True

    @_unreachable
    def ping(self) -> bool:
        return bool(self.r.ping())

    # -- rows ------------------------------------------------------------------------------------
    @_unreachable
    def add(
        self,
        job_id: str,
        *,
        input_name: str,
        input_kind: str,
        input_file: str,
        input_bytes: int,
        result_file: str,
        options: dict,
    ) -> JobRecord:
        """Record a queued job whose input is already in its folder, and put it on the queue."""
        job = JobRecord(
            id=job_id,
            status="queued",
            progress=0.0,
            error=None,
            input_name=input_name,
            input_kind=input_kind,
            input_file=input_file,
            input_bytes=int(input_bytes),
            result_file=result_file,
            options=options,
            attempts=0,
            created=time.time(),
            started=None,
            finished=None,
        )
        fsync_path(self.folder(job_id) / input_file)  # on the shared volume before anyone reads it
        self.write_record(job)
        self._enqueue(job)
        return job

    def _enqueue(self, job: JobRecord) -> bool:
        fields = [x for kv in hash_of(job).items() for x in kv]
        return bool(
            self._add(keys=[self.key(job.id)], args=[PREFIX, job.id, repr(job.created), *fields])
        )

    @_unreachable
    def get(self, job_id: str) -> JobRecord | None:
        """The job's state; from its folder's record when Redis has none (lost or purged); None
        when unknown or malformed."""
        h = self.r.hgetall(self.key(job_id))
        if not h:
            return self.read_record(job_id)
        try:
            return record_from_hash(job_id, h)
        except ValueError as e:  # not written by facecast: unknown, never a crash
            log.warning("%s", e)
            return None

    @_unreachable
    def list(self, status: str | None = None, limit: int = 100) -> list[JobRecord]:
        """Jobs in ``status`` oldest first, or the newest jobs of any status."""
        if status:
            if status not in STATES:
                return []
            ids = [_text(x) for x in self.r.zrange(f"{PREFIX}:status:{status}", 0, limit - 1)]
        else:
            pipe = self.r.pipeline(transaction=False)
            for st in STATES:
                pipe.zrevrange(f"{PREFIX}:status:{st}", 0, limit - 1, withscores=True)
            both = [(score, _text(i)) for got in pipe.execute() for i, score in got]
            ids = [i for _, i in sorted(both, reverse=True)[:limit]]
        pipe = self.r.pipeline(transaction=False)
        for job_id in ids:
            pipe.hgetall(self.key(job_id))
        out = []
        for job_id, h in zip(ids, pipe.execute()):
            try:
                if h:
                    out.append(record_from_hash(job_id, h))
            except ValueError as e:
                log.warning("skipping %s", e)
        return out

    def counts(self) -> dict[str, int]:
        """Job state -> number of jobs, as of the last ``refresh_counts()`` (no Redis call)."""
        return dict(self._counts)

    @_unreachable
    def refresh_counts(self) -> dict[str, int]:
        pipe = self.r.pipeline(transaction=False)
        for st in STATES:
            pipe.zcard(f"{PREFIX}:status:{st}")
        self._counts = {st: int(n) for st, n in zip(STATES, pipe.execute()) if n}
        return self.counts()

    @_unreachable
    def claim(self, job_id: str) -> int | None:
        """queued | running -> running (a running job's last worker died); the new attempt number,
        or None if the job is over or unknown."""
        try:
            n = self._claim(keys=[self.key(job_id)], args=[PREFIX, job_id, repr(time.time())])
        except redis.ResponseError as e:  # a hash facecast did not write (attempts not a number)
            log.warning("job %s cannot be claimed: %s", job_id, e)
            return None
        return int(n) if n is not None else None

    @_unreachable
    def progress(self, job_id: str, attempt: int, fraction: float) -> bool:
        """Record progress of a running attempt; False if the job is no longer this attempt's."""
        frac = min(max(float(fraction), 0.0), 1.0)
        return bool(self._progress(keys=[self.key(job_id)], args=[str(attempt), repr(frac)]))

    @_unreachable
    def finish(self, job_id: str, attempt: int, status: str, error: str | None = None) -> bool:
        """running -> done | failed, once (compare-and-set); False if over or superseded meanwhile."""
        ok = bool(
            self._finish(
                keys=[self.key(job_id)],
                args=[PREFIX, job_id, str(attempt), status, error or "", repr(time.time())],
            )
        )
        if ok:
            self._save_record(job_id)
        return ok

    def fail(self, job_id: str, error: str) -> bool:
        """queued | running -> failed (the server's verdict, e.g. a worker that crashed)."""
        return self._end(job_id, "failed", error)

    def cancel(self, job_id: str) -> bool:
        """queued | running -> cancelled; False if the job had already finished."""
        return self._end(job_id, "cancelled", "")

    @_unreachable
    def _end(self, job_id: str, status: str, error: str) -> bool:
        ok = bool(
            self._stop(
                keys=[self.key(job_id)],
                args=[PREFIX, job_id, status, error, repr(time.time())],
            )
        )
        if ok:
            self._save_record(job_id)
        return ok

    @_unreachable
    def purge(self, finished_before: float) -> builtins.list[str]:
        """Delete finished jobs (state and folder) that finished before Unix time ``finished_before``."""
        gone = []
        for st in FINISHED:
            for raw in self.r.zrange(f"{PREFIX}:status:{st}", 0, -1):
                job_id = _text(raw)
                finished = _text(self.r.hget(self.key(job_id), "finished"))
                try:
                    old = float(finished) < finished_before
                except ValueError:
                    old = True  # a finished job with no time: malformed, gone too
                if old and JOB_ID.match(job_id):
                    shutil.rmtree(self.folder(job_id), ignore_errors=True)
                    self.r.delete(self.key(job_id))
                    self.r.zrem(f"{PREFIX}:status:{st}", job_id)
                    gone.append(job_id)
        return gone

    # -- the record in the job's folder ----------------------------------------------------------
    def write_record(self, job: JobRecord) -> None:
        write_bytes_atomic(self.folder(job.id) / RECORD, json.dumps(hash_of(job)).encode())

    def read_record(self, job_id: str) -> JobRecord | None:
        """The job as its folder last recorded it (None when there is no readable record)."""
        try:
            data = json.loads((self.folder(job_id) / RECORD).read_text(encoding="utf-8"))
            return record_from_hash(job_id, data)
        except (OSError, ValueError, AttributeError):
            return None

    def _save_record(self, job_id: str) -> None:
        """Copy the job's verdict to its folder (best effort: the state lives in Redis)."""
        try:
            h = self.r.hgetall(self.key(job_id))
            if h and self.folder(job_id).is_dir():
                self.write_record(record_from_hash(job_id, h))
        except (OSError, ValueError, redis.RedisError) as e:
            log.warning("job %s: cannot save its record: %s", job_id, e)

    @_unreachable
    def recover(self) -> builtins.list[str]:
        """Queue again the jobs whose folder says queued or running but Redis has no trace of (it
        restarted empty); their ids."""
        back = []
        for folder in self.root.iterdir():
            if not JOB_ID.match(folder.name) or self.r.exists(self.key(folder.name)):
                continue
            job = self.read_record(folder.name)
            if job is None or job.status not in ("queued", "running"):
                continue
            job.status, job.progress, job.started = "queued", 0.0, None
            if self._enqueue(job):
                back.append(job.id)
        return back
