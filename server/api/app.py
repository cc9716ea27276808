"""The FastAPI application: ``create_app(config)`` wires faces, jobs, sessions, health and the web page.

Who needs the admin key (``Authorization: Bearer <key>``):

- ``/v1/jobs`` (submit, status, result, cancel) and creating/closing sessions: **admin**;
- live WebSockets: the session's producer or viewer token (see ``routes_sessions``);
- ``/v1/faces...``, ``/healthz``, ``/metrics``, ``/docs``, ``/openapi.json``, ``/``: public, read-only
  (except that building a not-yet-loaded resolution of a built-in face, ``default:N``, needs the key).

Every error is JSON: ``{"error": "<what was wrong and what to do>", "where": "...", "status": N}``.
"""

from __future__ import annotations

import logging
import sys
import tempfile
import threading
import time
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException

from ..errors import FacecastError
from ..jobs.upload import clear_upload_dir, upload_dir
from . import (
    routes_faces,
    routes_health,
    routes_jobs,
    routes_layers,
    routes_playback,
    routes_sessions,
    routes_web,
)
from .config import ServerConfig
from .errors import error_body, error_response, reply
from .metrics import Metrics
from .redact import path_scrubber
from .responses import SafeJSONResponse, safe_json, safe_text
from .routes_cluster import router as cluster_routes
from .security import resolve_admin_key
from .store import FaceStore, parse_faces_env

log = logging.getLogger(__name__)


DESCRIPTION = """\
Networked facial-animation server: MPEG-4 FAPs, mocap markers and speech in; deformed vertex
streams (WebSocket) and animation files (REST jobs) out.

| Routes | Credential |
|---|---|
| `/v1/jobs…` (submit, list, status, result, cancel) | admin key |
| `POST/GET/DELETE /v1/sessions…` | admin key |
| `/v1/sessions/{id}/produce`, `/watch` (WebSocket) | the session's producer / viewer token \
(`Authorization: Bearer`, or the subprotocol `facecast.token.<token>`) |
| `/v1/faces…`, `/healthz`, `/metrics`, `/docs`, `/` | none (building a new `default:N` \
resolution needs the admin key) |

The admin key goes in `Authorization: Bearer <key>`; it is `FACECAST_ADMIN_KEY`, or the key the
server generated, printed at start-up and keeps in `<data dir>/admin.key`. Errors are JSON:
`{"error": "<what was wrong and what to do>", "detail": <same>, "status": N, "where": "<field>"}`.
"""


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("facecast")
    except Exception:
        return "0+unknown"


def scrub_paths(text: str, app: FastAPI) -> str:
    """``text`` with server paths (the data directory, the temporary folder) cut to their last part."""
    return app.state.scrub_paths(text)


__all__ = ["create_app", "error_body", "scrub_paths"]


def _warm_up(app: FastAPI) -> None:
    """Load the default face and probe the compute backend once (runs in a thread at start-up)."""
    cfg: ServerConfig = app.state.config
    ready = app.state.readiness
    t0 = time.perf_counter()
    try:
        ready["backend"], ready["device"] = _probe_backend(cfg.backend, cfg.device)
        log.info("backend: %s, device: %s", ready["backend"], ready["device"])
    except Exception as e:  # a broken device must not stop the server; NumPy still works
        ready["backend"], ready["device"] = "numpy", None
        ready["backend_error"] = f"{type(e).__name__}: {e}"
        log.warning("OpenCL backend unavailable (%s); using numpy", e)
    try:
        face = app.state.store.face(None)
        ready["face"] = {"name": app.state.store.default, "vertices": face.n_vertices}
        log.info("default face %s: %d vertices", app.state.store.default, face.n_vertices)
    except Exception as e:
        ready["face_error"] = f"{type(e).__name__}: {e}"
        log.error("cannot load the default face %r: %s", cfg.face, e)
    ready["ready"] = "face_error" not in ready
    if ready["ready"]:
        # Build the default face's animator (operator from the disk cache, kernels on the device)
        # so that the first live session starts at once. The server is usable meanwhile.
        try:
            app.state.store.animator(None)
            ready["animator"] = True
        except Exception as e:
            ready["animator_error"] = f"{type(e).__name__}: {e}"
            log.warning("cannot prepare the animator of the default face: %s", e)
    ready["warmup_seconds"] = round(time.perf_counter() - t0, 3)
    log.info("warm-up done in %.2f s", ready["warmup_seconds"])


def _probe_backend(backend: str, device: str | None) -> tuple[str, str | None]:
    """``(backend, device description)`` the server will use; builds the OpenCL context once."""
    if backend == "numpy":
        return "numpy", None
    try:
        from ..backends.opencl import default_context
    except ImportError as e:
        if backend == "opencl":
            raise FacecastError(f"OpenCL backend not available: {e}") from e
        return "numpy", None
    ctx = default_context(device)
    if ctx is None:
        if backend == "opencl":
            raise FacecastError(
                "no working OpenCL device; install pocl-opencl-icd or use --backend numpy"
            )
        return "numpy", None
    devs = getattr(ctx, "devices", None) or []
    names = ", ".join(f"{d.name.strip()} ({d.platform.name.strip()})" for d in devs) or str(ctx)
    return "opencl", names


def create_app(config: ServerConfig | None = None) -> FastAPI:
    """The facecast HTTP/WebSocket application for ``config`` (jobs start with the app's lifespan)."""
    config = config or ServerConfig()
    config.data_dir.mkdir(parents=True, exist_ok=True)
    admin_key, _ = resolve_admin_key(config.admin_key, config.data_dir)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        app.state.started = time.time()
        left = clear_upload_dir(config.data_dir)  # uploads a crashed server left behind
        if left:
            log.info(
                "removed %d upload(s) left by the last run in %s", left, upload_dir(config.data_dir)
            )
        # A daemon thread: stopping the server never waits for a warm-up still in progress.
        threading.Thread(target=_warm_up, args=(app,), name="facecast-warm-up", daemon=True).start()
        await app.state.jobs.start()
        if config.redis_url:  # a cluster node (server/cluster); else one process, in memory
            await _join_cluster(app, config)
        try:
            yield
        finally:
            if app.state.cluster is not None:
                await app.state.cluster.stop()
            live = getattr(app.state, "live", None)
            if live is not None:
                try:
                    await live.close_all()
                except Exception:
                    log.exception("closing live sessions")
            await app.state.jobs.stop()

    app = FastAPI(
        title="facecast",
        version=_version(),
        description=DESCRIPTION,
        lifespan=lifespan,
        default_response_class=SafeJSONResponse,
        docs_url=None,
        redoc_url=None,  # served by routes_web from local assets (no CDN)
    )
    app.state.config = config
    app.state.admin_key = admin_key
    app.state.cluster = None
    app.state.metrics = Metrics()
    app.state.store = FaceStore(
        default=config.face,
        backend=config.backend,
        device=config.device,
        configured=parse_faces_env(config.faces),
        uploads=config.data_dir / "faces",
    )
    # Folders whose paths never reach a client: the data directory, the temporary folder, the
    # operator's mesh folders (a message keeps only a file's own name).
    roots = {
        str(config.data_dir.expanduser().resolve()),
        str(config.data_dir),
        tempfile.gettempdir(),
        *(str(p.expanduser().parent) for p in app.state.store.configured.values()),
    }
    # ... and where facecast and its Python live (a message may name a file of the package).
    roots |= {str(Path(__file__).resolve().parents[2]), sys.prefix}
    app.state.private_roots = sorted((r for r in roots if len(r) > 1), key=len, reverse=True)
    app.state.scrub_paths = path_scrubber(app.state.private_roots)
    app.state.readiness = {"ready": False, "backend": None, "device": None}

    from ..jobs import make_manager

    app.state.jobs = make_manager(config)  # SQLite, or Redis when config.redis_url is set
    app.state.metrics.watch_jobs(app.state.jobs.store.counts)

    def _answer(exc: Exception, **extra: Any) -> JSONResponse:
        r = reply(exc, app)  # the one mapping, as on WebSockets: status from the error's class
        app.state.metrics.http_errors.labels(str(r.status)).inc()
        return error_response(r, **extra)

    @app.exception_handler(FacecastError)
    async def _project_error(request: Request, exc: FacecastError) -> JSONResponse:
        return _answer(exc)

    @app.exception_handler(HTTPException)
    async def _http_error(request: Request, exc: HTTPException) -> JSONResponse:
        extra: dict[str, Any] = (
            {} if isinstance(exc.detail, str) else {"problems": safe_json(jsonable(exc.detail))}
        )
        return _answer(exc, **extra)

    @app.exception_handler(Exception)
    async def _server_error(request: Request, exc: Exception) -> JSONResponse:
        # Last resort: the details (paths, traceback) go to the server log, never to the client.
        log.error(
            "unhandled error on %s %s",
            request.method,
            safe_text(request.url.path, 200),
            exc_info=exc,
        )
        return _answer(exc)

    @app.exception_handler(RequestValidationError)
    async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        # Client input echoed here may be NaN, bytes, lone surrogates or huge: safe_json copes.
        errors = safe_json(jsonable(exc.errors()))
        problems = "; ".join(
            f"{'.'.join(str(p) for p in e.get('loc', ()))}: {e.get('msg', '')}"
            for e in errors
            if isinstance(e, dict)
        )
        return _answer(
            HTTPException(422, f"invalid request: {problems}; see /docs for the schema"),
            problems=errors,
        )

    app.include_router(routes_health.router)
    app.include_router(routes_faces.router)
    app.include_router(routes_jobs.router)
    app.include_router(routes_sessions.router)
    app.include_router(cluster_routes)
    app.include_router(routes_playback.router)
    app.include_router(routes_layers.router)
    app.include_router(routes_layers.router)
    app.include_router(routes_web.router)
    return app


async def _join_cluster(app: FastAPI, config: ServerConfig) -> None:
    """Make this process a node of the cluster at ``config.redis_url`` (``app.state.cluster``)."""
    from ..cluster.node import Cluster

    assert config.redis_url is not None
    cluster = Cluster(
        config.redis_url,
        routes_sessions.registry(app),
        admin_key=app.state.admin_key,
        url=f"http://{config.host}:{config.port}",
        readiness=app.state.readiness,
    )
    await cluster.start()
    app.state.cluster = cluster
    app.state.metrics.watch_cluster(cluster.id, cluster.gauges)


def jsonable(obj):
    from fastapi.encoders import jsonable_encoder

    try:
        return jsonable_encoder(obj)
    except Exception:
        return str(obj)
