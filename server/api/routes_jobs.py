"""``/v1/jobs``: batch rendering. Upload an input file, poll its status, download the result, cancel.

All routes need the admin key. The upload is streamed to the job's folder with a size limit by
kind (``max_fap_bytes``, ``max_markers_bytes``, ``max_audio_bytes``, all at most ``max_upload_bytes``;
413 beyond it). A mocap take comes with its marker layout as content (a ``layout`` part holding the
layout's JSON), never as a path. The job runs in a worker process (see ``server/jobs``), so a
decoder that crashes or hangs on a hostile file costs that process, never the server; a job over
``job_timeout_seconds`` is failed and its worker killed. In a cluster (``FACECAST_REDIS_URL``) the
same routes answer on every node (``jobs.redis_manager``); store calls go through ``jobs.io`` (a
thread when the store is a network away) and a lost broker answers 503.
"""

from __future__ import annotations

import asyncio
import json
import logging
import shutil
from functools import partial

from fastapi import APIRouter, Depends, Request, Response, status
from fastapi.responses import FileResponse
from pydantic import ValidationError

from ...protocol.rest import RESULT_MEDIA_TYPES, ErrorBody, JobList, JobOptions, JobStatus
from ..drivers import input_kind
from ..errors import Conflict, InputError, NotFound
from ..jobs.store import JOB_ID, JobFiles, JobRecord, new_job_id
from ..jobs.upload import (
    LAYOUT_PART,
    UploadParser,
    boundary_of,
    input_suffix,
    multipart_doc,
    receive,
    refuse_declared_oversize,
    safe_display_name,
    upload_layout,
)
from .security import require_admin

log = logging.getLogger(__name__)

router = APIRouter(
    prefix="/v1/jobs",
    tags=["jobs"],
    dependencies=[Depends(require_admin)],
    responses={401: {"model": ErrorBody, "description": "admin key missing or wrong"}},
)

#: Room for the multipart framing and form fields around the file.
FORM_OVERHEAD = 64 * 1024

#: Name of an uploaded marker layout in a job's folder.
LAYOUT_FILE = "layout.json"

_UPLOAD_DOC = multipart_doc(
    file={
        "type": "string",
        "format": "binary",
        "description": "input: .fap, .wav/.flac/.ogg, .c3d/.trc/.csv or .bml (type from the file "
        "name's suffix, else from its content)",
    },
    audio={
        "type": "array",
        "items": {"type": "string", "format": "binary"},
        "description": "a .bml input's recordings, each named as its speech's audio names it",
    },
    face={"type": "string", "description": "face name (GET /v1/faces)"},
    engine={"type": "string", "enum": ["fp", "rbf", "shell"], "default": "fp"},
    format={"type": "string", "enum": ["glb", "npz", "fap"], "default": "glb"},
    layout=LAYOUT_PART,
)


def result_sizes(files: JobFiles, jobs: list[JobRecord]) -> dict[str, int]:
    """Bytes of each done job's result file that is there, by job id. A ``stat`` per job, in a
    local or shared folder (a network away): the routes run it in a thread, off the event loop."""
    out = {}
    for job in jobs:
        if job.status == "done":
            path = files.result_path(job)
            if path.is_file():
                out[job.id] = path.stat().st_size
    return out


async def job_statuses(request: Request, jobs: list[JobRecord]) -> list[JobStatus]:
    """``jobs``' statuses with their result sizes (read in a thread)."""
    done = any(j.status == "done" for j in jobs)
    sizes = (
        await asyncio.to_thread(result_sizes, request.app.state.jobs.store, jobs) if done else {}
    )
    return [job_status(j, sizes.get(j.id)) for j in jobs]


def job_status(job: JobRecord, result_bytes: int | None = None) -> JobStatus:
    opts = {k: v for k, v in job.options.items() if k in JobOptions.model_fields}
    if job.options.get("layout_file"):
        opts["layout"] = (
            "uploaded"  # the content stays on the server; the status only says it is there
        )
    return JobStatus(
        id=job.id,
        status=job.status,
        progress=job.progress,
        error=job.error or None,
        input_name=job.input_name,
        input_kind=job.input_kind,
        input_bytes=job.input_bytes,
        options=JobOptions(**opts),
        attempts=job.attempts,
        created=job.created,
        started=job.started,
        finished=job.finished,
        result_url=f"/v1/jobs/{job.id}/result" if job.status == "done" else None,
        result_bytes=result_bytes,
    )


async def _job(request: Request, job_id: str) -> JobRecord:
    jobs = request.app.state.jobs
    job = await jobs.io(jobs.store.get, job_id) if JOB_ID.match(job_id) else None
    if job is None:
        raise NotFound(
            f"no job {job_id!r} on this server; POST /v1/jobs returns the ids", where="job"
        )
    return job


@router.post(
    "",
    status_code=status.HTTP_202_ACCEPTED,
    response_model=JobStatus,
    openapi_extra=_UPLOAD_DOC,
    responses={
        413: {"model": ErrorBody, "description": "upload larger than the server's limit"},
        415: {"model": ErrorBody, "description": "not multipart, or unknown input type"},
        404: {"model": ErrorBody, "description": "no such face"},
        422: {"model": ErrorBody, "description": "bad option"},
    },
)
async def submit_job(request: Request, response: Response) -> JobStatus:
    """Submit a job: multipart form with ``file`` and options ``face``, ``engine``, ``format``, ``layout``,
    ``text`` (audio: its transcript).

    Answers 202 with the job's status; poll ``GET /v1/jobs/{id}`` until ``done``, then fetch
    ``result_url``.
    """
    app = request.app
    cfg = app.state.config
    jobs = app.state.jobs
    limit = int(cfg.max_upload_bytes)
    boundary = boundary_of(request.headers.get("content-type", ""))
    await refuse_declared_oversize(
        request,
        limit,
        FORM_OVERHEAD,
        "a file; send a smaller file or raise FACECAST_MAX_UPLOAD_BYTES on the server",
    )
    job_id = new_job_id()
    folder = jobs.store.folder(job_id)
    folder.mkdir(parents=True)
    parser = UploadParser(
        boundary, folder / ".upload", limit, kind_limit=cfg.upload_limit, attachment_field="audio"
    )
    try:
        await receive(request, parser)
        try:
            opts = JobOptions(
                **{k: v for k, v in parser.fields.items() if k in JobOptions.model_fields}
            )
        except ValidationError as e:
            problems = "; ".join(f"{'.'.join(map(str, x['loc']))}: {x['msg']}" for x in e.errors())
            raise InputError(f"bad job option: {problems}", where="form") from None
        unknown = sorted(set(parser.fields) - set(JobOptions.model_fields))
        if unknown:
            raise InputError(
                f"unknown form field(s) {', '.join(unknown)}; known: file, "
                f"{', '.join(JobOptions.model_fields)}",
                where="form",
            )
        if parser.size == 0:
            raise InputError("the uploaded file is empty", where="file")
        face_spec = app.state.store.resolve(opts.face)
        suffix = input_suffix(parser.filename, parser.head)
        input_file = f"input{suffix}"
        kind = input_kind(input_file)
        options = {**opts.model_dump(exclude={"layout"}), "face_spec": face_spec}
        layout = upload_layout(kind, opts.layout)
        if opts.text is not None:
            from ..audio.align import check_text

            if kind != "audio":
                raise InputError(
                    f"a transcript ('text') applies to audio input only, not {kind}", where="text"
                )
            check_text(opts.text)
        if layout is not None:
            (folder / LAYOUT_FILE).write_text(json.dumps(layout), encoding="utf-8")
            options["layout_file"] = LAYOUT_FILE
        if parser.attachments and kind != "bml":
            raise InputError("'audio' parts go with a .bml performance only", where="audio")
        (folder / ".upload").replace(folder / input_file)
        display = safe_display_name(parser.filename, f"upload{suffix}")
        if kind == "bml":  # its recordings, matched to the 'audio' parts, kept beside it
            from ..bml.upload import match_media

            match_media(folder / input_file, parser.attachments, display=display, into=folder)
        job = await jobs.io(
            partial(
                jobs.store.add,
                job_id,
                input_name=display,
                input_kind=kind,
                input_file=input_file,
                input_bytes=parser.size,
                result_file=f"result.{opts.format}",
                options=options,
            )
        )
    except BaseException:
        parser.abort()
        shutil.rmtree(folder, ignore_errors=True)
        raise
    app.state.metrics.jobs_submitted.inc()
    jobs.wake()
    log.info("job %s queued: %s (%d bytes) -> %s", job_id, display, parser.size, opts.format)
    response.headers["Location"] = f"/v1/jobs/{job_id}"
    return job_status(job)


@router.get("", response_model=JobList)
async def list_jobs(request: Request, status: str | None = None, limit: int = 100) -> JobList:
    """The newest jobs (optionally only those in one ``status``)."""
    jobs = request.app.state.jobs
    found = await jobs.io(partial(jobs.store.list, status, limit=max(1, min(limit, 1000))))
    return JobList(jobs=await job_statuses(request, found))


@router.get("/{job_id}", response_model=JobStatus, responses={404: {"model": ErrorBody}})
async def get_job(job_id: str, request: Request) -> JobStatus:
    """Status, progress (0..1) and error message of a job."""
    (found,) = await job_statuses(request, [await _job(request, job_id)])
    return found


@router.get(
    "/{job_id}/result",
    response_class=FileResponse,
    responses={
        200: {
            "content": {t: {} for t in RESULT_MEDIA_TYPES.values()},
            "description": "the result file",
        },
        404: {"model": ErrorBody},
        409: {"model": ErrorBody, "description": "not done"},
    },
)
async def get_result(job_id: str, request: Request):
    """The result file of a finished job (409 while it is queued or running, or if it failed)."""
    job = await _job(request, job_id)
    if job.status != "done":
        what = {
            "queued": "is queued",
            "running": f"is running ({job.progress:.0%})",
            "cancelled": "was cancelled",
            "failed": f"failed: {job.error}",
        }[job.status]
        raise Conflict(
            f"job {job_id} {what}; "
            + (
                "poll GET /v1/jobs/{id} until status is 'done'"
                if job.status in ("queued", "running")
                else "submit it again"
            ),
            where="job",
        )
    path = request.app.state.jobs.store.result_path(job)
    if not path.is_file():
        raise NotFound(
            f"the result of job {job_id} is no longer on the server; submit the job again",
            where="job",
        )
    stem = safe_display_name(job.input_name, "result").rsplit(".", 1)[0] or "result"
    fmt = job.options.get("format", "glb")
    return FileResponse(
        path,
        media_type=RESULT_MEDIA_TYPES.get(fmt, "application/octet-stream"),
        filename=f"{stem}.{fmt}",
    )


@router.delete(
    "/{job_id}",
    response_model=JobStatus,
    responses={404: {"model": ErrorBody}, 409: {"model": ErrorBody}},
)
async def cancel_job(job_id: str, request: Request) -> JobStatus:
    """Cancel a queued or running job (its worker is stopped). Cancelling it again is harmless;
    a job that already finished (done or failed) answers 409."""
    job = await _job(request, job_id)
    if job.status in ("done", "failed"):
        raise Conflict(
            f"job {job_id} already {job.status}; there is nothing to cancel", where="job"
        )
    jobs = request.app.state.jobs
    await jobs.io(jobs.cancel, job_id)
    return job_status(await _job(request, job_id))
