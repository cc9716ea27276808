"""Worker processes: each runs jobs one at a time with ``render_file``, progress going to SQLite.

Started with the ``spawn`` method by ``JobManager`` and kept for many jobs, so imports, faces and
the OpenCL device probe are paid once. The manager sends ``(job_id, attempt)`` over a pipe; the
worker answers with the job id when it is finished with it. A worker exits when the pipe closes
(the server has gone) and stops a job by itself when the job was cancelled or taken over (its
progress update no longer matches); the manager also terminates it to cancel at once.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import sys
import threading
import time
import traceback
from collections import OrderedDict
from pathlib import Path

from ..errors import Unavailable
from .store import JobRecord, JobStore, results_root

log = logging.getLogger(__name__)

#: Least time between two progress writes (seconds); the last one is always written.
PROGRESS_INTERVAL = 0.2
#: Faces a worker keeps in memory between jobs.
FACE_CACHE = 2


class Stop(BaseException):
    """Raised inside ``render_file`` through the progress callback to abandon the job."""


def serve(
    data_dir: str,
    conn,
    backend: str = "auto",
    device: str | None = None,
    parent_pid: int | None = None,
    memory_mb: int = 0,
    spec: dict | None = None,
) -> None:
    """Worker process entry point: run the jobs the manager sends until the pipe closes.

    ``memory_mb``: address-space limit of this process (0: none); a job over it fails with a
    MemoryError message, and the server is not affected. ``spec``: the manager's store
    (``JobManager.store_spec``; None: SQLite in ``data_dir``).
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the server, which stops us
    die_with_parent(parent_pid)
    limit_resources(memory_mb)
    logging.basicConfig(
        level=logging.INFO,
        stream=sys.stderr,
        format=f"%(asctime)s %(levelname)s worker[{os.getpid()}] %(name)s: %(message)s",
    )
    store = open_store(Path(data_dir), spec)
    faces: OrderedDict[str, object] = OrderedDict()
    try:
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                break
            if msg is None:
                break
            job_id, attempt = msg
            try:
                run_job(store, job_id, attempt, backend, device, parent_pid, faces)
            except (
                Unavailable
            ) as e:  # the job queue's broker is away: no verdict, the server retries
                log.warning("job %s: %s", job_id, e)
            except Exception:  # noqa: BLE001 - the worker outlives a job's failure; logged, failed
                log.error("job %s: worker error:\n%s", job_id, traceback.format_exc())
                try:
                    store.finish(
                        job_id,
                        attempt,
                        "failed",
                        "internal error in the job worker; the server log has the details",
                    )
                except Unavailable as e:
                    log.warning("job %s: %s", job_id, e)
            try:
                conn.send(job_id)
            except (EOFError, OSError):
                break
    finally:
        store.close()


def open_store(data_dir: Path, spec: dict | None = None) -> JobStore:
    """The job store a manager's ``store_spec()`` describes: Redis when it names a URL, else SQLite."""
    spec = spec or {}
    results_dir = Path(spec["results_dir"]) if spec.get("results_dir") else None
    if spec.get("redis_url"):
        from .redis_queue import RedisJobStore

        return RedisJobStore(spec["redis_url"], results_root(data_dir, results_dir))  # type: ignore[return-value]
    return JobStore(data_dir, results_dir)


#: Seconds between two checks that the server is still there (where the kernel cannot tell us).
PARENT_POLL_SECONDS = 1.0
PR_SET_PDEATHSIG = 1


def die_with_parent(parent_pid: int | None) -> None:
    """End this process when the server that started it dies, even by SIGKILL.

    On Linux the kernel sends SIGKILL at once (``prctl(PR_SET_PDEATHSIG)``); elsewhere, and as a
    second line, a daemon thread checks the parent pid every ``PARENT_POLL_SECONDS``. A worker that
    outlived its server would race the attempt the next server starts for the same job.
    """
    if parent_pid is None:
        return
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
        except (OSError, AttributeError):
            log.warning("cannot ask the kernel to end this worker with the server; polling instead")
    if os.getppid() != parent_pid:  # the server died before we got here
        os._exit(1)

    def watch() -> None:
        while True:
            time.sleep(PARENT_POLL_SECONDS)
            if os.getppid() != parent_pid:
                os._exit(1)

    threading.Thread(target=watch, name="facecast-parent-watch", daemon=True).start()


def limit_resources(memory_mb: int = 0) -> None:
    """Limits for a process that parses hostile files: no core files (a decoder crashing must not
    fill the disk) and, if ``memory_mb`` > 0, at most that many MiB of address space."""
    try:
        import resource
    except ImportError:  # not on this platform
        return
    limits = [(resource.RLIMIT_CORE, 0)]
    if memory_mb > 0:
        limits.append((resource.RLIMIT_AS, int(memory_mb) * 1024 * 1024))
    for which, value in limits:
        try:
            hard = resource.getrlimit(which)[1]
            value = value if hard == resource.RLIM_INFINITY else min(value, hard)
            resource.setrlimit(which, (value, hard))
        except (ValueError, OSError) as e:
            log.warning("cannot set resource limit %s: %s", which, e)


def run_job(
    store: JobStore,
    job_id: str,
    attempt: int,
    backend: str,
    device: str | None,
    parent_pid: int | None,
    faces: OrderedDict,
) -> None:
    """Run attempt ``attempt`` of job ``job_id`` and record done/failed (nothing if abandoned)."""
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
        try:
            mine = store.progress(job_id, attempt, done / total if total else 0.0)
        except Unavailable:
            raise Stop("the job queue is unreachable") from None
        if not mine:
            raise Stop("job cancelled or taken over")

    status, error = render(store, job, backend, device, progress, faces)
    if status is not None:
        store.finish(job_id, attempt, status, error)
        log.info("job %s %s%s", job_id, status, f": {error}" if error else "")


def _face(spec: str, faces: OrderedDict):
    from ..faces import load_face

    if spec in faces:
        faces.move_to_end(spec)
        return faces[spec]
    face = load_face(spec)
    faces[spec] = face
    while len(faces) > FACE_CACHE:
        faces.popitem(last=False)
    return face


def render(
    store: JobStore,
    job: JobRecord,
    backend: str,
    device: str | None,
    progress,
    faces: OrderedDict | None = None,
) -> tuple[str | None, str | None]:
    """``(status, error)`` of running ``job``; ``(None, None)`` when the job was abandoned."""
    opts = job.options
    src = store.input_path(job)
    dst = store.result_path(job)

    def client_view(text: str) -> str:
        # Messages name the upload by its server path; show the client's file name instead.
        return text.replace(str(src), job.input_name).replace(str(store.folder(job.id)), "")

    if not src.is_file():  # a cluster node that does not see the folder the job was sent to
        return "failed", (
            "the input of this job is not in the job folders of the server that ran it; "
            "the operator must give every node the same FACECAST_RESULTS_DIR (a shared folder)"
        )
    try:
        from ..errors import FacecastError
        from ..render import render_file
    except ImportError as e:
        return "failed", f"the render engine is not available on this server ({e})"
    try:
        face = _face(
            opts.get("face_spec") or "default", faces if faces is not None else OrderedDict()
        )
        layout = None
        if opts.get("layout_file"):  # the client's layout content, checked and saved at submit
            layout = json.loads(
                (store.folder(job.id) / opts["layout_file"]).read_text(encoding="utf-8")
            )
        render_file(
            src,
            dst,
            face=face,
            engine=opts.get("engine", "fp"),
            backend=backend,
            device=device,
            layout=layout,
            progress=progress,
            text=opts.get("text"),
        )
    except Stop as e:
        log.info("job %s abandoned: %s", job.id, e)
        return None, None
    except FacecastError as e:
        return "failed", client_view(str(e))
    except MemoryError:
        return (
            "failed",
            f"{job.input_name!r} needs more memory than this server has; send a shorter input",
        )
    except Exception as e:  # noqa: BLE001 - reported as the job's failure (below)
        # A decoder's own error (FapFormatError...) or a low-level one it let through (ValueError,
        # struct.error, OverflowError...): the input's fault, most likely. The traceback stays here.
        own = type(e).__module__.startswith("facecast.")
        if not own:
            log.warning("job %s: %s", job.id, traceback.format_exc())
        detail = str(e) if own else f"{type(e).__name__}: {e}"
        return "failed", client_view(
            f"could not read {job.input_name!r} as {job.input_kind} input: {detail[:500]}"
        )
    if not dst.is_file():
        return (
            "failed",
            "the renderer finished without writing a result (server bug; please report)",
        )
    return "done", None
