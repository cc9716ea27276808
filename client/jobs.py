"""Batch rendering on a facecast server: submit a file, follow its progress, download the result.

``render_remote(url, input, output, options={...})`` is what ``facecast render --server URL`` calls.
Synchronous (httpx); the result appears at ``output`` atomically (a partial download never does).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx

from ..protocol.errors import UpstreamError
from .files import atomic_path

FINAL = ("done", "failed", "cancelled")
#: Render options that only make sense locally (the server picks its own backend and device).
LOCAL_ONLY = frozenset({"backend", "device"})
#: Input suffixes of mocap takes, which need a marker layout.
MOCAP_SUFFIXES = frozenset({".c3d", ".trc", ".csv"})
#: Largest layout file sent (the server's limit for the ``layout`` part).
MAX_LAYOUT_BYTES = 1024 * 1024


class RemoteJobError(UpstreamError):
    """The server refused the job, the job failed, or the server could not be reached.

    ``code`` is the server's HTTP status (``status=`` here; 0 when there was no answer); ``job`` the
    job id if one exists. (``status``, as on every facecast error, is what a facecast server relaying
    this error would answer: 502.)
    """

    def __init__(
        self, message: str, *, status: int = 0, job: str | None = None, where: str = ""
    ) -> None:
        super().__init__(message, status, where=where)
        self.job = job


def _error_text(resp: httpx.Response) -> str:
    try:
        body = resp.json()
    except ValueError:
        return resp.text.strip()[:300] or resp.reason_phrase
    if isinstance(body, dict):
        return str(body.get("error") or body.get("detail") or body)
    return str(body)


def _check(resp: httpx.Response, what: str, job: str | None = None) -> httpx.Response:
    if resp.status_code >= 400:
        hint = (
            " (set FACECAST_ADMIN_KEY to the server's admin key)" if resp.status_code == 401 else ""
        )
        raise RemoteJobError(
            f"{what}: HTTP {resp.status_code}: {_error_text(resp)}{hint}",
            status=resp.status_code,
            job=job,
        )
    return resp


def find_layout(take: Path) -> Path | None:
    """The layout beside a mocap take, as the local renderer looks for it: ``<stem>.layout.json``,
    else ``layout.json`` in its folder; None when there is neither."""
    for cand in (take.with_name(take.stem + ".layout.json"), take.with_name("layout.json")):
        if cand.is_file():
            return cand
    return None


def read_layout(layout: str | Path) -> bytes:
    """The content of a local layout file, to upload (the server never opens a client's paths)."""
    path = Path(layout)
    if not path.is_file():
        raise RemoteJobError(f"{path}: no such layout file")
    data = path.read_bytes()
    if len(data) > MAX_LAYOUT_BYTES:
        raise RemoteJobError(
            f"{path}: a layout is JSON of a few KiB, this file has {len(data)} bytes"
        )
    return data


def bml_recordings(input: Path) -> list[str]:
    """The recordings a ``.bml`` file's speeches name (none for other inputs); RemoteJobError when
    the BML is malformed or one is missing beside it."""
    if input.suffix.lower() != ".bml":
        return []
    from ..protocol.bml import BmlError, Speech, parse_bml

    try:
        block = parse_bml(input.read_bytes(), where=str(input))
    except BmlError as e:
        raise RemoteJobError(str(e)) from None
    names = sorted({b.audio for b in block.behaviours if isinstance(b, Speech) and b.audio})
    for name in names:
        if not (input.parent / name).is_file():
            raise RemoteJobError(f"{input}: audio {name!r} is not a file next to the BML file")
    return names


def submit(client: httpx.Client, input: Path, options: dict[str, Any]) -> dict[str, Any]:
    """POST the file and options; the job's status as the server returned it.

    ``options["layout"]`` is a local layout file: its content is uploaded as the ``layout`` part;
    a ``.bml`` performance's recordings (beside it, as locally) go as ``audio`` parts.
    """
    data = {k: str(v) for k, v in options.items() if v is not None and k != "layout"}
    files: list[tuple[str, Any]] = []
    if options.get("layout") is not None:
        files.append(
            ("layout", ("layout.json", read_layout(options["layout"]), "application/json"))
        )
    for name in bml_recordings(input):
        files.append(("audio", (Path(name).name, (input.parent / name).read_bytes())))
    with open(input, "rb") as fh:
        files.append(("file", (input.name, fh, "application/octet-stream")))
        resp = client.post("/v1/jobs", files=files, data=data)
    job: dict[str, Any] = _check(resp, f"the server refused {input.name}").json()
    return job


def wait(
    client: httpx.Client,
    job_id: str,
    *,
    progress: Callable[[float, str], None] | None = None,
    poll: float = 0.5,
    timeout: float | None = None,
) -> dict[str, Any]:
    """Poll a job until it is done, failed or cancelled; ``progress(fraction, status)`` on each poll."""
    deadline = None if timeout is None else time.monotonic() + timeout
    delay = min(poll, 0.1)
    while True:
        job: dict[str, Any] = _check(
            client.get(f"/v1/jobs/{job_id}"), f"job {job_id}", job_id
        ).json()
        if progress is not None:
            progress(float(job.get("progress") or 0.0), job["status"])
        if job["status"] in FINAL:
            return job
        if deadline is not None and time.monotonic() > deadline:
            raise RemoteJobError(
                f"job {job_id} still {job['status']} after {timeout:g} s; it keeps running on "
                f"the server (GET /v1/jobs/{job_id})",
                job=job_id,
            )
        time.sleep(delay)
        delay = min(delay * 1.5, poll)


def download(client: httpx.Client, job_id: str, output: Path) -> Path:
    """Stream a job's result to ``output`` through a temporary file in the same folder, then rename."""
    output.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(output) as tmp, client.stream("GET", f"/v1/jobs/{job_id}/result") as resp:
        if resp.status_code >= 400:
            resp.read()
            _check(resp, f"result of job {job_id}", job_id)
        with open(tmp, "wb") as fh:
            fh.writelines(resp.iter_bytes(1 << 16))
    return output


def render_remote(
    url: str,
    input: str | Path,
    output: str | Path,
    *,
    options: dict[str, Any] | None = None,
    progress: Callable[[int, int], None] | None = None,
    admin_key: str | None = None,
    poll: float = 0.5,
    timeout: float | None = None,
) -> Path:
    """Render ``input`` on the server at ``url`` and write the result to ``output``.

    ``options``: ``face``, ``engine``, ``format`` (default: ``output``'s suffix), ``layout`` (a local
    layout file, uploaded with the take; default for a mocap take: the one beside it, as locally);
    ``backend``/``device`` are ignored (the server uses its own).
    ``progress(done, total)`` is called with ``total = 1000`` as the job advances (like the local
    renderer's callback). ``admin_key`` defaults to ``$FACECAST_ADMIN_KEY``. Raises
    ``RemoteJobError`` with the server's message when the job is refused or fails.
    """
    input, output = Path(input), Path(output)
    if not input.is_file():
        raise RemoteJobError(f"{input}: no such file")
    # The server deforms on its own backend and device; those local options do not apply.
    opts = {k: v for k, v in (options or {}).items() if k not in LOCAL_ONLY}
    if not opts.get("format"):
        suffix = output.suffix.lower().lstrip(".")
        if suffix not in ("glb", "npz", "fap"):
            raise RemoteJobError(
                f"{output}: cannot tell the output format from the suffix; use .glb, .npz or .fap"
            )
        opts["format"] = suffix
    if opts.get("layout") is None and input.suffix.lower() in MOCAP_SUFFIXES:
        opts["layout"] = find_layout(input)
        if opts["layout"] is None:
            raise RemoteJobError(
                f"{input}: a mocap take needs a marker layout: pass --layout layout.json "
                f"(or put {input.stem}.layout.json beside the take)"
            )
    key = admin_key or os.environ.get("FACECAST_ADMIN_KEY")
    headers = {"Authorization": f"Bearer {key}"} if key else {}
    report = None
    if progress is not None:

        def report(fraction: float, status: str) -> None:
            progress(int(round(fraction * 1000)), 1000)

    try:
        with httpx.Client(
            base_url=url.rstrip("/"), headers=headers, timeout=httpx.Timeout(60.0, connect=10.0)
        ) as client:
            job = submit(client, input, opts)
            job_id = job["id"]
            try:
                job = wait(client, job_id, progress=report, poll=poll, timeout=timeout)
            except KeyboardInterrupt:
                client.delete(f"/v1/jobs/{job_id}")
                raise
            if job["status"] != "done":
                why = job.get("error") or job["status"]
                raise RemoteJobError(f"job {job_id} {job['status']}: {why}", job=job_id)
            return download(client, job_id, output)
    except httpx.HTTPError as e:
        raise RemoteJobError(f"cannot talk to the facecast server at {url}: {e}") from e
