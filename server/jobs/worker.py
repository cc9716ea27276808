"""One worker process runs one job: ``render_file(input, result, ...)``, with progress in SQLite.

Started with the ``spawn`` method by ``JobManager``. The worker stops by itself when the job is
cancelled (its progress update no longer matches) or when the server that started it has gone.
"""
from __future__ import annotations

import logging
import os
import sys
import time
import traceback
from pathlib import Path

from .store import JobStore

log = logging.getLogger(__name__)

#: Least time between two progress writes (seconds); the last one is always written.
PROGRESS_INTERVAL = 0.2


class Stop(BaseException):
    """Raised inside ``render_file`` through the progress callback to abandon the job."""


def main(data_dir: str, job_id: str, attempt: int, backend: str = "auto", device: str | None = None,
         parent_pid: int | None = None) -> None:
    """Run job ``job_id`` (attempt ``attempt``) and record done/failed in the store."""
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format=f"%(asctime)s %(levelname)s worker[{os.getpid()}] %(name)s: %(message)s")
    store = JobStore(Path(data_dir))
    try:
        job = store.get(job_id)
        if job is None or job.attempts != attempt or job.status != "running":
            return
        last = [0.0]

        def progress(done: int, total: int) -> None:
            if parent_pid is not None and os.getppid() != parent_pid:
                raise Stop("server gone")
            now = time.monotonic()
            if now - last[0] < PROGRESS_INTERVAL and done < total:
                return
            last[0] = now
            if not store.progress(job_id, attempt, done / total if total else 0.0):
                raise Stop("job cancelled or taken over")

        status, error = run(store, job, backend, device, progress)
        if status is not None:
            store.finish(job_id, attempt, status, error)
            log.info("job %s %s%s", job_id, status, f": {error}" if error else "")
    finally:
        store.close()


def run(store: JobStore, job, backend: str, device: str | None, progress) -> tuple[str | None, str | None]:
    """``(status, error)`` of running ``job``; ``(None, None)`` when the job was abandoned."""
    opts = job.options
    src = store.input_path(job)
    dst = store.result_path(job)
    try:
        from ..errors import FacecastError
        from ..render import render_file
    except ImportError as e:
        return "failed", f"the render engine is not available on this server ({e})"
    try:
        render_file(src, dst, face=opts.get("face_spec") or "default", engine=opts.get("engine", "fp"),
                    backend=backend, device=device, layout=opts.get("layout"), progress=progress)
    except Stop as e:
        log.info("job %s abandoned: %s", job.id, e)
        return None, None
    except FacecastError as e:
        # The message names the uploaded file by its server path; show the client's name instead.
        msg = str(e).replace(str(src), job.input_name)
        return "failed", msg
    except Exception as e:
        log.error("job %s crashed:\n%s", job.id, traceback.format_exc())
        msg = f"{type(e).__name__}: {e}".replace(str(src), job.input_name)
        return "failed", f"could not process {job.input_name!r}: {msg}"
    if not dst.exists():
        return "failed", "the renderer finished without writing a result (server bug; please report)"
    return "done", None
