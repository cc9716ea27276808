"""Batch jobs: state in SQLite in the data directory (survives restarts), work in spawned processes.

- ``store.JobStore``: the ``jobs`` table (one row per job) and each job's folder of files;
- ``manager.JobManager``: the server-side dispatcher (start, monitor, cancel worker processes);
- ``worker.main``: the entry point of one worker process (runs ``render_file`` for one job).
"""

from .store import JobRecord, JobStore

__all__ = ["JobRecord", "JobStore"]
