"""``/healthz`` (liveness with readiness details) and ``/metrics`` (Prometheus text)."""

from __future__ import annotations

import time

from fastapi import APIRouter, Request
from fastapi.responses import Response

from ...protocol.rest import Health
from .metrics import CONTENT_TYPE

router = APIRouter(tags=["health"])


@router.api_route("/healthz", methods=["GET", "HEAD"], response_model=Health)
async def healthz(request: Request) -> Health:
    """200 as soon as the server answers. ``ready`` turns true once the default face is loaded and
    the backend probed (start-up warm-up runs in the background); details say what is in use."""
    st = request.app.state
    r = dict(st.readiness)
    return Health(
        status="ok",
        ready=bool(r.get("ready")),
        version=request.app.version,
        uptime_seconds=round(time.time() - getattr(st, "started", time.time()), 3),
        backend=r.get("backend"),
        device=r.get("device"),
        face=r.get("face"),
        animator=bool(r.get("animator")),
        warmup_seconds=r.get("warmup_seconds"),
        errors={k: v for k, v in r.items() if k.endswith("_error")},
        job_workers=st.jobs.workers,
        jobs=st.jobs.store.counts(),
    )


@router.api_route(
    "/readyz",
    methods=["GET", "HEAD"],
    response_model=Health,
    responses={
        503: {"model": Health, "description": "still warming up, or the default face failed"}
    },
)
async def readyz(request: Request, response: Response) -> Health:
    """Like ``/healthz``, but 503 until the default face is loaded, and while a cluster node's
    Redis is unreachable (``errors.broker_error``), for load balancers."""
    health = await healthz(request)
    if not health.ready or "broker_error" in health.errors:
        response.status_code = 503
    return health


@router.get(
    "/metrics",
    response_class=Response,
    responses={200: {"content": {"text/plain": {}}, "description": "Prometheus text format"}},
)
async def metrics(request: Request) -> Response:
    """Sessions, viewers, frames sent and dropped, deform time, jobs by state (Prometheus text)."""
    live = getattr(request.app.state, "live", None)
    if live is not None:  # the sessions' batched frame counts, up to now
        live.meter()
    return Response(request.app.state.metrics.render(), media_type=CONTENT_TYPE)
