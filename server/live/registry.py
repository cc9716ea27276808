"""The server's live sessions: create (with limits), look up by id, list, close.

One registry per app (``app.state.live``); it owns the thread pools that deform live frames and run
producer drivers off the event loop (NumPy/SciPy and OpenCL release the GIL while they work).
"""

from __future__ import annotations

import asyncio
import logging
import secrets
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from ...protocol.errors import CloseCode
from ...protocol.messages import (
    ErrorMessage,
    SessionCreate,
    SessionCreated,
    SessionInfo,
    dump_message,
)
from .. import errors
from ..errors import NotFound
from .batcher import DeformBatcher
from .session import LiveSession, SessionSpec
from .settings import LiveSettings
from .tokens import new_token

log = logging.getLogger(__name__)


class TooMany(errors.TooMany):
    status = 429


class Unavailable(errors.Unavailable):
    status = 503


class SessionRegistry:
    """Live sessions of one server.

    Args:
        store: the app's ``FaceStore`` (face names -> faces and shared animators).
        max_sessions, max_viewers, max_fps: the server's limits (``ServerConfig``).
        metrics: the app's ``Metrics`` (or None).
        idle_seconds: a session not ``busy`` (no viewer, no client producer) this long is closed
            (``ServerConfig.session_idle_seconds``; 0 = never).
        settings: tuning of the live path (``ServerConfig.live_settings()``).
    """

    def __init__(
        self,
        store: Any,
        *,
        max_sessions: int,
        max_viewers: int,
        max_fps: float,
        metrics: Any = None,
        threads: int | None = None,
        idle_seconds: float = 0.0,
        settings: LiveSettings | None = None,
    ) -> None:
        self.settings = settings = settings or LiveSettings()
        self.store = store
        self.max_sessions = max_sessions
        self.max_viewers = max_viewers
        self.max_fps = max_fps
        self.metrics = metrics
        self.sessions: dict[str, LiveSession] = {}
        self.executor = ThreadPoolExecutor(
            threads or settings.deform_threads, thread_name_prefix="live-deform"
        )
        #: The threads that solve, deform and encode live frames (``DeformBatcher`` drains); apart
        #: from ``executor`` so that drains busy under load never delay a producer's hello.
        self.batch_executor = ThreadPoolExecutor(
            settings.batch_threads, thread_name_prefix="live-batch"
        )
        self._batchers: dict[int, DeformBatcher] = {}
        self._creating = 0
        self.idle_seconds = idle_seconds
        self._reaper: asyncio.Task[None] | None = None
        #: Cluster: told of every session closed here (``server/cluster``); None in one process.
        self.on_close: Callable[[LiveSession], None] | None = None

    def batcher_for(self, animator: Any) -> DeformBatcher:
        """The one ``DeformBatcher`` of ``animator`` (sessions of the same face share it)."""
        b = self._batchers.get(id(animator))
        if b is None or b.animator is not animator:
            b = self._batchers[id(animator)] = DeformBatcher(
                animator, self.batch_executor, settings=self.settings
            )
        return b

    def meter(self) -> None:
        """Bring every session's frames taken and sent to the Prometheus counters now (sessions
        add them in batches: ``LiveSession.meter``), before ``/metrics`` renders them."""
        for s in list(self.sessions.values()):
            s.meter()

    def get(self, session_id: str) -> LiveSession:
        s = self.sessions.get(session_id)
        if s is None:
            raise NotFound(
                f"no live session {session_id!r}; it was closed or never existed "
                "(GET /v1/sessions lists them)",
                where="session",
            )
        return s

    async def create(self, req: SessionCreate) -> LiveSession:
        """A new session; raises ``TooMany`` (429), ``NotFound`` (unknown face), ``Unavailable`` (503)."""
        if len(self.sessions) + self._creating >= self.max_sessions:
            raise TooMany(
                f"this server already has {len(self.sessions)} live sessions (its limit is "
                f"{self.max_sessions}, FACECAST_MAX_SESSIONS); close one with DELETE /v1/sessions/ID"
            )
        if req.input != "fap":
            from .inputs import InputUnavailable, load_driver_class

            try:
                load_driver_class("audio" if req.input == "audio" else "markers")
            except InputUnavailable as e:
                raise Unavailable(str(e), where="input") from None
        face_name = req.face or self.store.default
        self.store.resolve(face_name)  # NotFound / InputError before any work
        self._creating += 1
        try:
            loop = asyncio.get_running_loop()
            face, animator = await loop.run_in_executor(
                self.executor, self._load, face_name, req.engine
            )
            if len(self.sessions) >= self.max_sessions:
                raise TooMany(
                    f"session limit {self.max_sessions} reached while this one was being set up"
                )
            _check_tolerance(req.tolerance, face)
            sid = secrets.token_hex(8)
            spec = SessionSpec(
                id=sid,
                face=face_name,
                input=req.input,
                fps=req.fps,
                engine=req.engine,
                max_viewers=min(req.max_viewers or self.max_viewers, self.max_viewers),
                producer_token=new_token(),
                viewer_token=new_token(),
                tolerance=req.tolerance,
            )
            session = LiveSession(spec, face, self.batcher_for(animator), self.metrics)
            self.sessions[sid] = session
            self._start_reaper()
            if self.metrics:
                self.metrics.sessions.set(len(self.sessions))
            log.info(
                "live session %s: face %s, input %s, %g fps", sid, face_name, req.input, req.fps
            )
            return session
        finally:
            self._creating -= 1

    async def restore(self, spec: SessionSpec, session: LiveSession | None = None) -> LiveSession:
        """Cluster: open a session another node owned, from its ``spec``; ``session``: this node's
        copy of it (a mirror with viewers), which from now on deforms its frames here."""
        loop = asyncio.get_running_loop()
        face, animator = await loop.run_in_executor(
            self.executor, self._load, spec.face, spec.engine
        )
        if session is None:
            session = LiveSession(spec, face, self.batcher_for(animator), self.metrics)
        else:
            session.deform_with(self.batcher_for(animator), None)
        self.sessions[spec.id] = session
        self._start_reaper()
        if self.metrics:
            self.metrics.sessions.set(len(self.sessions))
        log.info("live session %s taken over: face %s, input %s", spec.id, spec.face, spec.input)
        return session

    def _load(self, face_name: str, engine: str) -> tuple[Any, Any]:
        face = self.store.face(face_name)
        try:
            animator = self.store.animator(face_name, engine)
        except ImportError as e:
            raise Unavailable(f"the deformation pipeline is not available: {e}") from None
        return face, animator

    def animator_for(self, session: LiveSession, control_vertices: Any) -> Any:
        """An animator of the session's face with explicit control vertices (mocap); blocking."""
        from ..pipeline import Animator

        backend = getattr(self.store, "backend", "auto")
        device = getattr(self.store, "device", None)
        return Animator(
            session.face,
            engine=session.spec.engine,
            backend=backend,
            device=device,
            control_vertices=control_vertices,
        )

    def created(self, s: LiveSession) -> SessionCreated:
        """The answer to creating ``s``: its id, both tokens (shown only then) and its URLs."""
        sp = s.spec
        base = f"/v1/sessions/{sp.id}"
        return SessionCreated(
            id=sp.id,
            producer_token=sp.producer_token,
            viewer_token=sp.viewer_token,
            face=sp.face,
            input=sp.input,
            fps=sp.fps,
            vertex_count=s.vertex_count,
            produce_url=base + "/produce",
            watch_url=base + "/watch",
        )

    def info(self, s: LiveSession) -> SessionInfo:
        sp = s.spec
        return SessionInfo(
            id=sp.id,
            face=sp.face,
            input=sp.input,
            fps=sp.fps,
            engine=sp.engine,
            created=sp.created,
            vertex_count=s.vertex_count,
            max_viewers=sp.max_viewers,
            stats=s.snapshot(),
        )

    async def close(
        self, session_id: str, reason: str = "the session was closed by an admin"
    ) -> None:
        s = self.get(session_id)
        del self.sessions[session_id]
        if self.on_close is not None:
            self.on_close(s)
        in_use = {id(x.batcher.animator) for x in self.sessions.values()}
        for key in [
            k for k in self._batchers if k not in in_use
        ]:  # mocap animators die with their session
            del self._batchers[key]
        if self.metrics:
            self.metrics.sessions.set(len(self.sessions))
        await s.close(
            CloseCode.SESSION_CLOSED,
            dump_message(
                ErrorMessage(code=CloseCode.SESSION_CLOSED, message=reason, fatal=True, seq=None)
            ),
        )
        log.info("live session %s closed", session_id)

    # -- idle expiry -------------------------------------------------------------------------------
    def _start_reaper(self) -> None:
        if self.idle_seconds > 0 and self._reaper is None:
            self._reaper = asyncio.get_running_loop().create_task(self._reap())

    async def _reap(self) -> None:
        """Every quarter of the idle time (at most 30 s): close the sessions idle for it."""
        interval = min(30.0, max(0.05, self.idle_seconds / 4))
        while True:
            await asyncio.sleep(interval)
            try:
                await self.expire_idle(time.monotonic())
            except Exception:  # never let the reaper die
                log.exception("expiring idle sessions")

    async def expire_idle(self, now: float) -> list[str]:
        """Close the sessions nobody used for ``idle_seconds`` (monotonic ``now``); their ids."""
        idle = [sid for sid, s in self.sessions.items() if s.idle_for(now) >= self.idle_seconds]
        for sid in idle:
            if sid in self.sessions:
                await self.close(
                    sid,
                    f"the session expired: no viewer and no producer for {self.idle_seconds:g} s "
                    "(FACECAST_SESSION_IDLE_SECONDS); create a new one",
                )
                log.info("live session %s expired after %g s idle", sid, self.idle_seconds)
                if self.metrics:
                    self.metrics.sessions_expired.inc()
        return idle

    async def close_all(self) -> None:
        if self._reaper is not None:
            self._reaper.cancel()
            self._reaper = None
        for sid in list(self.sessions):
            await self.close(sid, "the server is shutting down")
        self.executor.shutdown(wait=False, cancel_futures=True)
        self.batch_executor.shutdown(wait=False, cancel_futures=True)


def _check_tolerance(tolerance_mm: float, face: Any) -> None:
    """Refuse (``InputError``, 400) a compact tolerance no float32 grid of ``face`` can keep:
    else every compact viewer of the session would fail (``protocol.compact.float_margin``)."""
    from ...protocol.compact import float_margin

    extent = 2.0 * float(abs(face.vertices).max())  # as the session's CompactEncoder takes it
    try:
        float_margin(tolerance_mm / face.mm_per_unit, extent)
    except ValueError:
        raise errors.InputError(
            f"tolerance {tolerance_mm:g} mm is too small for this face's compact grid in float32 "
            f"(coordinates up to {extent * face.mm_per_unit:g} mm from its origin)",
            where="tolerance",
        ) from None
