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
import threading
import time
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException

from ...protocol.errors import ProtocolError
from ..errors import FacecastError
from . import routes_faces, routes_health, routes_jobs, routes_playback, routes_sessions, routes_web
from .config import ServerConfig
from .metrics import Metrics
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
| `/v1/sessions/{id}/produce`, `/watch` (WebSocket) | the session's producer / viewer token (`Authorization: Bearer`, or the subprotocol `facecast.token.<token>`) |
| `/v1/faces…`, `/healthz`, `/metrics`, `/docs`, `/` | none (building a new `default:N` resolution needs the admin key) |

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


def error_body(status: int, message: str, where: str = "", **extra) -> dict:
    """The JSON body of every error response."""
    body = {"error": message, "detail": message, "status": status}
    if where:
        body["where"] = where
    body.update(extra)
    return body


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
        from ..backends.opencl_backend import default_context
    except ImportError as e:
        if backend == "opencl":
            raise FacecastError(f"OpenCL backend not available: {e}") from e
        return "numpy", None
    ctx = default_context(device)
    if ctx is None:
        if backend == "opencl":
            raise FacecastError("no working OpenCL device; install pocl-opencl-icd or use --backend numpy")
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
        # A daemon thread: stopping the server never waits for a warm-up still in progress.
        threading.Thread(target=_warm_up, args=(app,), name="facecast-warm-up", daemon=True).start()
        await app.state.jobs.start()
        try:
            yield
        finally:
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
    )
    app.state.config = config
    app.state.admin_key = admin_key
    app.state.metrics = Metrics()
    app.state.store = FaceStore(default=config.face, backend=config.backend, device=config.device,
                                configured=parse_faces_env(config.faces))
    app.state.readiness = {"ready": False, "backend": None, "device": None}

    from ..jobs.manager import JobManager

    app.state.jobs = JobManager(config.data_dir, workers=config.job_workers, backend=config.backend,
                                device=config.device, retention_hours=config.job_retention_hours)
    app.state.metrics.watch_jobs(app.state.jobs.store.counts)

    @app.exception_handler(FacecastError)
    async def _facecast_error(request: Request, exc: FacecastError) -> JSONResponse:
        app.state.metrics.http_errors.labels(str(exc.status)).inc()
        return JSONResponse(error_body(exc.status, str(exc), exc.where), status_code=exc.status)

    @app.exception_handler(ProtocolError)
    async def _protocol_error(request: Request, exc: ProtocolError) -> JSONResponse:
        app.state.metrics.http_errors.labels(str(exc.status)).inc()
        return JSONResponse(error_body(exc.status, str(exc), exc.where), status_code=exc.status)

    @app.exception_handler(HTTPException)
    async def _http_error(request: Request, exc: HTTPException) -> JSONResponse:
        app.state.metrics.http_errors.labels(str(exc.status_code)).inc()
        message = exc.detail if isinstance(exc.detail, str) else "request failed"
        extra = {} if isinstance(exc.detail, str) else {"problems": jsonable(exc.detail)}
        return JSONResponse(error_body(exc.status_code, message, **extra), status_code=exc.status_code,
                            headers=getattr(exc, "headers", None))

    @app.exception_handler(Exception)
    async def _server_error(request: Request, exc: Exception) -> JSONResponse:
        log.error("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
        app.state.metrics.http_errors.labels("500").inc()
        return JSONResponse(error_body(500, "internal server error; the server log has the details"),
                            status_code=500)

    @app.exception_handler(RequestValidationError)
    async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        app.state.metrics.http_errors.labels("422").inc()
        problems = "; ".join(
            f"{'.'.join(str(p) for p in e.get('loc', ()))}: {e.get('msg', '')}" for e in exc.errors())
        return JSONResponse(error_body(422, f"invalid request: {problems}; see /docs for the schema",
                                       problems=jsonable(exc.errors())), status_code=422)

    app.include_router(routes_health.router)
    app.include_router(routes_faces.router)
    app.include_router(routes_jobs.router)
    app.include_router(routes_sessions.router)
    app.include_router(routes_playback.router)
    app.include_router(routes_web.router)
    return app


def jsonable(obj):
    from fastapi.encoders import jsonable_encoder

    try:
        return jsonable_encoder(obj)
    except Exception:
        return str(obj)
