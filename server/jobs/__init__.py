"""Batch jobs: state in SQLite in the data directory (survives restarts), work in spawned processes;
in a cluster (``FACECAST_REDIS_URL``) queue and state in Redis, files in a shared folder.

- ``store.JobStore``: the ``jobs`` table (one row per job) and each job's folder of files;
- ``manager.JobManager``: the server-side dispatcher (start, monitor, cancel worker processes);
- ``worker.serve``: the entry point of one worker process (runs ``render_file`` for each job);
- ``redis_queue.RedisJobStore`` / ``redis_manager.RedisJobManager``: the same over Redis Streams.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

from .store import JobRecord, JobStore, results_root

if TYPE_CHECKING:
    from ..api.config import ServerConfig
    from .manager import JobManager

__all__ = ["RESULTS_DIR_UNSET", "JobRecord", "JobStore", "make_manager", "results_root"]
log = logging.getLogger(__name__)

#: The warning, with the folder used, when a cluster node has no shared results folder set.
RESULTS_DIR_UNSET = (
    "FACECAST_RESULTS_DIR is unset: job folders are in %s; every node must see the same folder "
    "there, or jobs sent to one node fail on another"
)


def make_manager(config: ServerConfig) -> JobManager:
    """The job manager ``config`` asks for: over Redis when ``redis_url`` is set, else SQLite."""
    from .manager import JobManager

    kwargs = {
        "workers": config.job_workers,
        "backend": config.backend,
        "device": config.device,
        "retention_hours": config.job_retention_hours,
        "job_timeout": config.job_timeout_seconds,
        "memory_mb": config.job_memory_mb,
        "results_dir": config.results_dir,
    }
    if config.redis_url:
        from .redis_manager import RedisJobManager

        if config.results_dir is None:
            log.warning(RESULTS_DIR_UNSET, results_root(config.data_dir))

        return RedisJobManager(
            config.redis_url,
            config.data_dir,
            claim_seconds=config.job_claim_seconds,
            **kwargs,
        )
    return JobManager(config.data_dir, **kwargs)  # type: ignore[arg-type]
