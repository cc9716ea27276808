"""A live session's layers: secondary producers' latest states and REST layers, mixed into each
frame with the session's ``layers.Mixer`` (``server/layers/``), and the clock of frames when no
primary clocks them.

The primary producer's states clock the frames: each goes to the deformer with the session's
``SessionMix``, and the deform thread mixes the states of a whole batch together (``mix_jobs``,
``layers.mix_batch``: vectorised across sessions), off the event loop. While the
session holds layers and no primary state came for ``HOLD_SECONDS`` (no primary producer, a FAP
producer that sends only on change, a pause in the speech), a task ticks at the session's rate
and queues the last primary state (or the neutral face), to be mixed with the layers in the
deform thread like the primary's, as the demo producer clocks its frames (``server_producer``);
those frames continue the primary's media time.
Layer time is the session clock: seconds since the session was made (monotonic), so REST timings
("start in 0.5 s") are real time.

Everything here runs on the event loop, except ``mix_jobs`` (a deform thread; the ``Mixer`` is
thread-safe): no frame is mixed on the event loop.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
import weakref
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from ...protocol.layers import (
    MAX_LAYERS,
    ROLE_FAPS,
    ExpressionLayer,
    GazeLayer,
    HeadLayer,
    IdleLayer,
    LayerInfo,
)
from ..errors import NotFound, TooMany
from ..state import FaceState

if TYPE_CHECKING:
    from ..layers import Contribution, Mixer
    from .session import LiveSession

log = logging.getLogger(__name__)

Spec = IdleLayer | ExpressionLayer | GazeLayer | HeadLayer
#: Prefix of the mixer's names of producers' layers (REST names cannot hold it).
PRODUCER = "@"
#: While the primary sent a state this recently (s), it clocks the frames and the layer clock
#: waits (audio producers send a few states per chunk, tens of milliseconds apart).
HOLD_SECONDS = 0.25


class TooManyLayers(TooMany):
    status = 429


class Neutral(FaceState):
    """The neutral face the layer clock sends when no primary ever came: mixed as no primary
    (``mix``'s None: no closures to keep)."""


def _masks() -> dict[str, np.ndarray]:
    out = {}
    for role, faps in ROLE_FAPS.items():
        m = np.zeros(69)
        m[sorted(faps)] = 1.0
        out[role] = m
    return out


#: Per role, ``(69,)`` 1 on the FAPs a producer of that role may drive.
_MASK = _masks()


def contribution_of(role: str, state: FaceState) -> Contribution:
    """A secondary producer's state as its layer's contribution: expression and idle FAPs are
    offsets (weighed on the FAPs it moves), gaze FAPs replace the eyes', head FAPs the head pose."""
    from ..layers import Contribution

    faps = np.array(state.faps, dtype=np.float64)
    faps[:3] = 0.0
    faps *= _MASK[role]
    if role == "head":
        return Contribution(head=faps[48:51].copy())
    if role == "gaze":
        return Contribution(override=faps, override_weight=_MASK["gaze"] * (faps != 0))
    if state.expression is not None:
        return Contribution(faps=faps, expression=state.expression)
    return Contribution(faps=faps, weight=(faps != 0).astype(np.float64))


@dataclass(frozen=True)
class Held:
    """A producer's layer: its newest contribution, the same at every time (``layers.Layer``)."""

    role: Any  # ``layers.Role``
    contribution: Any  # ``layers.Contribution``
    end: float | None = None

    def sample(self, t: float) -> Any:
        return self.contribution


@dataclass
class _Rest:
    spec: Spec
    set_at: float  # session seconds


class SessionMix:
    """The layers of ``session`` and their mixing (see the module)."""

    def __init__(self, session: LiveSession, clock: Any = time.monotonic) -> None:
        self.session = session
        self.clock = clock
        self.t0 = clock()
        self._mixer: Mixer | None = None
        self._held: dict[str, float] = {}  # role -> session time of its newest state
        self._rest: dict[str, _Rest] = {}
        self.primary_at: float | None = None  # session time of the newest mixed primary state
        self.primary: FaceState | None = None  # the newest primary state (held between states)
        self._task: asyncio.Task[None] | None = None
        self.mixed = 0  # states mixed (for tests and stats)

    # -- state -------------------------------------------------------------------------------------
    @property
    def active(self) -> bool:
        """The session holds layers: each frame is mixed, and the layer clock runs."""
        return bool(self._held or self._rest)

    def now(self) -> float:
        """Session time, seconds (layer time)."""
        return self.clock() - self.t0

    @property
    def mixer(self) -> Mixer:
        if self._mixer is None:
            from ..layers import Mixer

            self._mixer = Mixer(self._geometry(), max_layers=MAX_LAYERS + len(ROLE_FAPS))
        return self._mixer

    def _geometry(self) -> Any:
        rig = getattr(getattr(self.session.batcher, "animator", None), "rig", None)
        return geometry_of(rig, self.session.spec.id)

    # -- producers ---------------------------------------------------------------------------------
    def put(self, role: str, state: FaceState) -> None:
        """The newest state of the secondary producer of ``role``: its layer from now on."""
        from ..layers import Role

        self.mixer.set(PRODUCER + role, Held(Role(role), contribution_of(role, state)))
        self._held[role] = self.now()
        self._start()

    def drop(self, role: str) -> None:
        """The ``role`` producer left: its layer leaves the mix."""
        if self._held.pop(role, None) is not None:
            self.mixer.remove(PRODUCER + role)

    # -- REST layers -------------------------------------------------------------------------------
    def spec(self, name: str) -> Spec | None:
        self._prune()
        r = self._rest.get(name)
        return None if r is None else r.spec

    def set(self, name: str, spec: Spec) -> LayerInfo:
        """Set the REST layer ``name`` (its times count from now)."""
        self._prune()
        if name not in self._rest and len(self._rest) >= MAX_LAYERS:
            raise TooManyLayers(
                f"a session holds at most {MAX_LAYERS} layers; DELETE one first", where="name"
            )
        now = self.now()
        self.mixer.set(name, layer_of(spec, now))
        self._rest[name] = _Rest(spec, now)
        self._start()
        return self.info(name)

    def remove(self, name: str) -> None:
        if self._rest.pop(name, None) is None:
            raise self.missing(name)
        self.mixer.remove(name)

    def clear(self, kinds: frozenset[str]) -> None:
        """Remove the REST layers of these kinds."""
        for name, r in list(self._rest.items()):
            if r.spec.kind in kinds:
                self.remove(name)

    def info(self, name: str) -> LayerInfo:
        self._prune()
        r = self._rest.get(name)
        if r is None:
            raise self.missing(name)
        return LayerInfo(
            name=name,
            source="rest",
            kind=r.spec.kind,
            spec=r.spec.model_dump(mode="json", exclude_none=True),
            age=round(self.now() - r.set_at, 3),
        )

    def infos(self) -> list[LayerInfo]:
        """Every layer: the producers' (named by role) and the REST ones."""
        self._prune()
        now = self.now()
        out = [
            LayerInfo(name=role, source="producer", kind=role, spec=None, age=round(now - at, 3))
            for role, at in self._held.items()
        ]
        return out + [self.info(name) for name in self._rest]

    def missing(self, name: str) -> NotFound:
        """The error of a missing REST layer ``name``, naming the session's layers."""
        known = ", ".join(self._rest) or "none"
        return NotFound(f"no layer {name!r} in this session (its layers: {known})", where="name")

    def _prune(self) -> None:
        """Forget REST layers the mixer dropped at their end."""
        if self._rest and self._mixer is not None:
            live = self._mixer.layers()
            for name in [n for n in self._rest if n not in live]:
                del self._rest[name]

    # -- frames ------------------------------------------------------------------------------------
    def held(self, state: FaceState) -> None:
        """The primary's newest state (cheap: on every primary submit)."""
        self.primary = state
        if self._task is not None:
            self.primary_at = self.clock() - self.t0

    def _start(self) -> None:
        if self._task is not None and not self._task.done():
            return
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:  # no loop (a test of the core): frames only come from the primary
            return
        self._task = loop.create_task(self._clock(), name=f"layers-{self.session.spec.id}")

    async def _clock(self) -> None:
        """While the session holds layers: a frame each period no primary state clocked. While
        the primary clocks, it sleeps until the primary may have stopped (no wake-up per frame)."""
        session = self.session
        period = 1.0 / session.spec.fps
        hold = max(HOLD_SECONDS, 2 * period)
        try:
            due = self.clock()
            while self.active and not session.closed:
                now, at = self.now(), self.primary_at
                if at is not None and now - at < hold:
                    await asyncio.sleep(at + hold - now)
                    due = self.clock()
                    continue
                if session.viewers:  # nobody watching: nothing to mix (the session still runs)
                    p = self.primary
                    if p is None:
                        state: FaceState = Neutral(t=now)
                    else:  # its media time goes on
                        state = replace(p, t=p.t + (now - (now if at is None else at)))
                    session.queue([state], time.time(), True)  # mixed in the deform thread
                due += period
                delay = due - self.clock()
                if delay < -1.0:  # a stalled loop: skip ahead rather than rush frames out
                    due, delay = self.clock(), 0.0
                await asyncio.sleep(max(0.0, delay))
        except Exception:
            log.exception("session %s: the layer clock failed", session.spec.id)
        finally:
            self._task = None

    def stop(self) -> None:
        """The session closes: stop the clock."""
        if self._task is not None:
            self._task.cancel()
            self._task = None


def layer_of(spec: Spec, now: float) -> Any:
    """The mixer's layer for a REST ``spec`` (validated already: the model is the one check) set
    at session time ``now`` (its times count from ``now``): ``layers.from_spec`` builds it."""
    from ..layers.spec import from_spec

    return from_spec(spec, now)


_geometries: dict[int, Any] = {}  # id(rig) -> its Geometry, while the rig lives
_geometries_lock = threading.Lock()


def geometry_of(rig: Any, sid: str = "?") -> Any:
    """The ``layers.Geometry`` of ``rig`` (None: the default), one per rig while it lives: the
    sessions of a face share it, so that their frames mix together (``layers.mix_batch`` groups
    by geometry)."""
    from ..layers import Geometry

    if rig is None:
        return Geometry()
    with _geometries_lock:
        geo = _geometries.get(id(rig))
        if geo is None:
            try:
                geo = Geometry.of_rig(rig)
            except Exception:  # noqa: BLE001 - a face without eyes still mixes (no gaze)
                log.warning("session %s: no face geometry for gaze", sid)
                geo = Geometry()
            try:  # forgotten with the rig (a mocap session's own animator), so ids stay unique
                weakref.finalize(rig, _geometries.pop, id(rig), None)
            except TypeError:  # not weakly referable: not shared
                return geo
            _geometries[id(rig)] = geo
        return geo


class MixJob(Protocol):
    """What ``mix_jobs`` needs of a deform job: its state and its session's mix (or None)."""

    state: FaceState
    mix: SessionMix | None


def mix_jobs(jobs: Sequence[MixJob]) -> dict[int, Exception]:
    """Mix the states of a deform batch's ``jobs`` that carry their session's ``SessionMix`` with
    its layers at the session's time now, all together (``layers.mix_batch``), in place: such a
    job's ``state`` becomes the mix (keeping its ``t``). Runs in a deform thread. Returns the
    failures by job index (those jobs keep their state; the others are mixed)."""
    from ..layers.batch import mix_batch

    todo = [i for i, j in enumerate(jobs) if j.mix is not None]
    frames = []
    for i in todo:
        sm = jobs[i].mix
        assert sm is not None
        s = jobs[i].state
        frames.append((sm.mixer, None if type(s) is Neutral else s, sm.now()))
    mixed: list[FaceState | Exception]
    try:
        mixed = list(mix_batch(frames))
    except Exception:  # find the frame that fails: one at a time
        log.exception("mixing a batch of %d frames failed; one at a time", len(frames))
        mixed = []
        for mixer, state, t in frames:
            try:
                mixed.append(mixer.mix(state, t))
            except Exception as e:  # noqa: BLE001 - that frame fails alone
                mixed.append(e)
    failed: dict[int, Exception] = {}
    for i, m in zip(todo, mixed, strict=True):
        job = jobs[i]
        if isinstance(m, Exception):
            failed[i] = m
            continue
        if m is not job.state:
            m.t = job.state.t
            job.state = m
        assert job.mix is not None
        job.mix.mixed += 1
    return failed
