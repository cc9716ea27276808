"""SQLite job store: ``<data_dir>/jobs.sqlite`` plus ``<results_dir>/<id>/`` for input and result.

``results_dir`` (``FACECAST_RESULTS_DIR``) defaults to ``<data_dir>/jobs``. ``JobFiles`` (the job
folders) is shared with the Redis store of a cluster (``redis_queue.RedisJobStore``).

Every state change is one SQL statement, so a job's state is never half-written. Workers update
their row only while it still carries their attempt number: a worker orphaned by a crashed server
cannot overwrite a later attempt's state.
"""

from __future__ import annotations

import json
import re
import shutil
import sqlite3
import threading
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

JOB_ID = re.compile(r"^[0-9a-f]{32}$")

SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id          TEXT PRIMARY KEY,
    status      TEXT NOT NULL,
    progress    REAL NOT NULL DEFAULT 0,
    error       TEXT,
    input_name  TEXT NOT NULL,
    input_kind  TEXT NOT NULL,
    input_file  TEXT NOT NULL,
    input_bytes INTEGER NOT NULL,
    result_file TEXT NOT NULL,
    options     TEXT NOT NULL,
    attempts    INTEGER NOT NULL DEFAULT 0,
    created     REAL NOT NULL,
    started     REAL,
    finished    REAL
);
CREATE INDEX IF NOT EXISTS jobs_status ON jobs(status, created);
"""

COLUMNS = (
    "id",
    "status",
    "progress",
    "error",
    "input_name",
    "input_kind",
    "input_file",
    "input_bytes",
    "result_file",
    "options",
    "attempts",
    "created",
    "started",
    "finished",
)


@dataclass
class JobRecord:
    """One row of the ``jobs`` table. ``input_file``/``result_file`` are names inside the job folder."""

    id: str
    status: str
    progress: float
    error: str | None
    input_name: str
    input_kind: str
    input_file: str
    input_bytes: int
    result_file: str
    options: dict
    attempts: int
    created: float
    started: float | None
    finished: float | None

    @classmethod
    def from_row(cls, row: tuple) -> JobRecord:
        d = dict(zip(COLUMNS, row))
        d["options"] = json.loads(d["options"])
        return cls(**d)


def new_job_id() -> str:
    return uuid.uuid4().hex


class JobFiles:
    """The job folders ``<root>/<id>/``: each holds a job's input, options files and result."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)

    def folder(self, job_id: str) -> Path:
        """``<root>/<id>`` (``job_id`` must be a job id, never client text)."""
        if not JOB_ID.match(job_id):
            raise ValueError(f"not a job id: {job_id!r}")
        return self.root / job_id

    def input_path(self, job: JobRecord) -> Path:
        return self.folder(job.id) / job.input_file

    def result_path(self, job: JobRecord) -> Path:
        return self.folder(job.id) / job.result_file


def results_root(data_dir: Path, results_dir: Path | None = None) -> Path:
    """Where job folders live: ``results_dir`` if set, else ``<data_dir>/jobs``."""
    return Path(results_dir) if results_dir else Path(data_dir) / "jobs"


class JobStore(JobFiles):
    """The job table of one data directory. Safe to use from several threads and processes."""

    def __init__(self, data_dir: Path, results_dir: Path | None = None):
        """``results_dir``: where job folders live (None: ``<data_dir>/jobs``)."""
        self.data_dir = Path(data_dir)
        super().__init__(results_root(self.data_dir, results_dir))
        self.path = self.data_dir / "jobs.sqlite"
        self._lock = threading.Lock()
        self._db = sqlite3.connect(
            self.path, timeout=30.0, check_same_thread=False, isolation_level=None
        )
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")
        self._db.executescript(SCHEMA)

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def _exec(self, sql: str, args: tuple = ()) -> sqlite3.Cursor:
        with self._lock:
            return self._db.execute(sql, args)

    # -- rows ------------------------------------------------------------------------------------
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
        """Insert a queued job whose input is already in its folder."""
        self._exec(
            "INSERT INTO jobs (id, status, progress, input_name, input_kind, input_file, input_bytes,"
            " result_file, options, created) VALUES (?, 'queued', 0, ?, ?, ?, ?, ?, ?, ?)",
            (
                job_id,
                input_name,
                input_kind,
                input_file,
                input_bytes,
                result_file,
                json.dumps(options),
                time.time(),
            ),
        )
        return self.get(job_id)

    def get(self, job_id: str) -> JobRecord | None:
        row = self._exec(
            f"SELECT {', '.join(COLUMNS)} FROM jobs WHERE id = ?", (job_id,)
        ).fetchone()
        return JobRecord.from_row(row) if row else None

    def list(self, status: str | None = None, limit: int = 100) -> list[JobRecord]:
        if status:
            rows = self._exec(
                f"SELECT {', '.join(COLUMNS)} FROM jobs WHERE status = ? ORDER BY created LIMIT ?",
                (status, limit),
            ).fetchall()
        else:
            rows = self._exec(
                f"SELECT {', '.join(COLUMNS)} FROM jobs ORDER BY created DESC LIMIT ?", (limit,)
            ).fetchall()
        return [JobRecord.from_row(r) for r in rows]

    def counts(self) -> dict[str, int]:
        """Job state -> number of jobs."""
        return dict(self._exec("SELECT status, COUNT(*) FROM jobs GROUP BY status").fetchall())

    def claim(self, job_id: str) -> int | None:
        """queued -> running; returns the new attempt number, or None if the job was not queued."""
        cur = self._exec(
            "UPDATE jobs SET status = 'running', attempts = attempts + 1, started = ?,"
            " progress = 0, error = NULL WHERE id = ? AND status = 'queued'",
            (time.time(), job_id),
        )
        if cur.rowcount != 1:
            return None
        return self.get(job_id).attempts

    def progress(self, job_id: str, attempt: int, fraction: float) -> bool:
        """Record progress of a running attempt; False if the job is no longer this attempt's."""
        cur = self._exec(
            "UPDATE jobs SET progress = ? WHERE id = ? AND attempts = ? AND status = 'running'",
            (min(max(float(fraction), 0.0), 1.0), job_id, attempt),
        )
        return cur.rowcount == 1

    def finish(self, job_id: str, attempt: int, status: str, error: str | None = None) -> bool:
        """running -> done | failed for this attempt; False if cancelled or superseded meanwhile."""
        cur = self._exec(
            "UPDATE jobs SET status = ?, error = ?, finished = ?,"
            " progress = CASE WHEN ? = 'done' THEN 1.0 ELSE progress END"
            " WHERE id = ? AND attempts = ? AND status = 'running'",
            (status, error, time.time(), status, job_id, attempt),
        )
        return cur.rowcount == 1

    def fail(self, job_id: str, error: str) -> bool:
        """queued | running -> failed (the server's verdict, e.g. a worker that crashed)."""
        cur = self._exec(
            "UPDATE jobs SET status = 'failed', error = ?, finished = ?"
            " WHERE id = ? AND status IN ('queued', 'running')",
            (error, time.time(), job_id),
        )
        return cur.rowcount == 1

    def cancel(self, job_id: str) -> bool:
        """queued | running -> cancelled; False if the job had already finished."""
        cur = self._exec(
            "UPDATE jobs SET status = 'cancelled', finished = ?"
            " WHERE id = ? AND status IN ('queued', 'running')",
            (time.time(), job_id),
        )
        return cur.rowcount == 1

    def purge(self, finished_before: float) -> list[str]:
        """Delete finished jobs (row and folder) that finished before Unix time ``finished_before``."""
        rows = self._exec(
            "SELECT id FROM jobs WHERE status IN ('done', 'failed', 'cancelled') AND finished < ?",
            (finished_before,),
        ).fetchall()
        ids = [r[0] for r in rows]
        for job_id in ids:
            shutil.rmtree(self.folder(job_id), ignore_errors=True)
            self._exec("DELETE FROM jobs WHERE id = ?", (job_id,))
        return ids

    def requeue(self, job_id: str) -> bool:
        """running -> queued (its worker died; run it again)."""
        cur = self._exec(
            "UPDATE jobs SET status = 'queued', progress = 0 WHERE id = ? AND status = 'running'",
            (job_id,),
        )
        return cur.rowcount == 1

    def sweep_orphans(self) -> list[str]:
        """Delete job folders with no row (an upload cut short by a crash); their names."""
        known = {r[0] for r in self._exec("SELECT id FROM jobs").fetchall()}
        gone = [p.name for p in self.root.iterdir() if p.is_dir() and p.name not in known]
        for name in gone:
            shutil.rmtree(self.root / name, ignore_errors=True)
        return gone

    def requeue_running(self) -> list[str]:
        """running -> queued for every job (at start-up: their workers died with the old server)."""
        ids = [r[0] for r in self._exec("SELECT id FROM jobs WHERE status = 'running'").fetchall()]
        self._exec("UPDATE jobs SET status = 'queued', progress = 0 WHERE status = 'running'")
        return ids
