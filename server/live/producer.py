"""A producer connection as a sans-I/O state machine: text and bytes in, steps out.

States: ``AWAITING_HELLO`` → (``OPENING``, while its input is made off the event loop) → ``READY``
→ ``STREAMING`` (a frame was taken) → ``CLOSED``. The core decides everything about a producer:
whether its token carries the role its hello names (else 4403), whether it may have that role's
slot (one producer per role: a second is refused, 4409), whether its hello is usable (a
secondary role sends FAP frames of its own FAPs only, ``protocol.layers.ROLE_FAPS``), each
message's budget (dropped with a 4429 warning, or the connection closed on a
flood, 1008, or an oversized message, 1009), what a malformed frame is answered with (a non-fatal
4400 naming its ``seq``), when the session's animator must follow the input's control vertices
(mocap), and the close code and message of every refusal (``core.client_error``).

The shell (``api.routes_sessions.produce``) receives, calls ``receive_text``/``receive_bytes``, and
carries out the returned ``core.Step``: it sends ``send``, runs ``work`` (in a thread when
``offload``) and feeds its result back, or closes as ``close`` says. The hot path of a FAP producer
(a binary frame decoded and submitted inline) allocates no step: it returns ``core.NOTHING``.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable
from enum import Enum
from functools import partial
from typing import Any

import numpy as np

from ...protocol import frames
from ...protocol.errors import CloseCode, Forbidden, FrameError, MessageError
from ...protocol.layers import role_refusal
from ...protocol.messages import (
    FapMessage,
    ProducerHello,
    Ready,
    Role,
    dump_message,
    parse_message,
)
from ..state import FaceState
from .budget import Verdict, producer_limits
from .core import (
    INTERNAL,
    NOTHING,
    Close,
    Event,
    Gate,
    Step,
    Work,
    client_error,
    closing,
    error_json,
)
from .inputs import make_input
from .ports import Animators, Input, ProducerSlot
from .roles import ALL_ROLES
from .session import LiveSession

log = logging.getLogger(__name__)

#: Seconds a producer has to send its hello.
HELLO_TIMEOUT = 10.0


class State(Enum):
    AWAITING_HELLO = "awaiting hello"
    OPENING = "opening"  #: the hello was good; its input (and maybe animator) is being made
    READY = "ready"
    STREAMING = "streaming"
    CLOSED = "closed"


class ProducerCore:
    """One producer connection of ``session``, held by ``slot`` (the shell's connection object).

    Args:
        session: the session it produces into.
        slot: what ``session.producer`` is while it is connected (``end`` closes the connection).
        animators: builds animators and their batchers for explicit control vertices (the registry).
        max_fps: the server's producer frame-rate limit (``ServerConfig.max_producer_fps``).
        metrics: the app's ``Metrics`` or None.
        clock: monotonic seconds (tests pass their own).
        roles: the roles its token may drive (``roles.Grants.roles_of``; default: all).
    """

    def __init__(
        self,
        session: LiveSession,
        slot: ProducerSlot,
        *,
        animators: Animators,
        max_fps: float,
        metrics: Any = None,
        clock: Callable[[], float] = time.monotonic,
        roles: frozenset[str] = ALL_ROLES,
    ) -> None:
        self.session = session
        self.roles = roles
        self.role: Role = "primary"  # the role its hello names (a slot is held once it is claimed)
        self.slot = slot
        self.animators = animators
        self.max_fps = max_fps
        self.metrics = metrics
        self.clock = clock
        self.state = State.AWAITING_HELLO
        self.input: Input | None = None
        self._gate: Gate | None = None
        # the hot path's bound methods, set when the input is ready (no None checks per frame)
        self._check: Callable[[int, bool, float], tuple[Verdict, str]] = _never_checked
        self._kinds: frozenset[frames.Kind] = frozenset()
        self._push_frame: Callable[[frames.Frame], list[FaceState]] = _never_pushed
        # audio / mocap drivers do real work: their frames are pushed in a thread
        self._offload = session.spec.input != "fap"
        self._connected = False
        self._claimed = False  # it holds its role's slot
        self._check_faps: Callable[[Any], str | None] | None = None  # a secondary role's FAPs
        self._label = f"session {session.spec.id}: producer"

    # -- connection --------------------------------------------------------------------------------
    def connect(self) -> Step:
        """The connection is accepted and authorised; its role's slot is taken at the hello."""
        self._connected = True
        if self.metrics:
            self.metrics.producers.inc()
        return NOTHING

    def _claim(self, hello: ProducerHello) -> Close | None:
        """Take the slot of the hello's role (no await before: a second producer is refused), or
        why not: the token lacks the role (4403), a secondary role sends other than FAPs (4403),
        the slot is taken (4409)."""
        role = hello.layer
        if role not in self.roles:
            return Close(
                CloseCode.FORBIDDEN,
                f"this token may drive the role(s) {', '.join(sorted(self.roles))}, not "
                f"'{role}'; ask for a token with that role (POST /v1/sessions/ID/tokens)",
                where="hello.role",
            )
        if role != "primary" and hello.input != "fap":
            return Close(
                CloseCode.FORBIDDEN,
                f"a '{role}' producer sends FAP frames (input 'fap'), not {hello.input}; only "
                "the primary producer sends the session's input",
                where="hello.input",
            )
        if not self.session.claim(self.slot, role):
            return Close(
                CloseCode.CONFLICT,
                f"this session already has a '{role}' producer; only one per role may send at a "
                "time (connect again once it has disconnected)",
                where="hello.role",
            )
        self.role = role
        return None

    @property
    def open(self) -> bool:
        """More messages are wanted: neither the connection nor the session is closed."""
        return self.state is not State.CLOSED and not self.session.closed

    def timeout(self) -> Step:
        """No hello within ``HELLO_TIMEOUT`` seconds."""
        return self._close(
            Close(
                CloseCode.TIMEOUT,
                f"no hello within {HELLO_TIMEOUT:g} s; send "
                '{"type": "hello", "role": "producer", "input": ...} first',
            )
        )

    def disconnected(self) -> Step:
        """The producer left: the states its input held back (look-ahead) still go out."""
        inp, was = self.input, self.state
        self.state = State.CLOSED
        if inp is None or was not in (State.READY, State.STREAMING):
            return NOTHING
        return Step(work=Work(partial(_flush, inp), self._flushed, self._offload))

    def failed(self, exc: BaseException) -> Step:
        """The shell met an error of its own while carrying out a step: a server fault (4500)."""
        log.error("session %s: producer failed", self.session.spec.id, exc_info=exc)
        return self._close(INTERNAL)

    def close(self) -> None:
        """The connection is gone: free the producer slot (idempotent)."""
        self.state = State.CLOSED
        if self._claimed:
            self._claimed = False
            self.session.release(self.slot)
        if self._connected:
            self._connected = False
            if self.metrics:
                self.metrics.producers.dec()

    # -- messages ----------------------------------------------------------------------------------
    def receive_text(self, text: str) -> Step:
        """A JSON text message: the hello, then ``fap`` messages."""
        state = self.state
        if state is State.AWAITING_HELLO:
            return self._hello(text)
        if state is not State.READY and state is not State.STREAMING:
            return NOTHING
        assert self._gate is not None and self.input is not None
        over = self._gate.check(len(text), True, self.clock())
        if over is not None:
            return self._over(over)
        seq: int | None = None
        try:
            m = parse_message(text)
            if not isinstance(m, FapMessage):
                raise MessageError(
                    f"producers send 'fap' messages or binary frames after the hello, "
                    f"not '{getattr(m, 'type', '?')}'",
                    where="type",
                )
            seq = m.seq
            if self._check_faps is not None:
                self._forbid(self._check_faps(m.faps), m.viseme, m.expression)
            states = self.input.push_message(m)
        except Exception as e:  # noqa: BLE001 - a message's or driver's error: mapped to its reply (_rejected)
            return self._rejected(e, seq)
        self._take(states, m.wall)
        return NOTHING

    def receive_bytes(self, data: bytes) -> Step:
        """A binary message: a frame of the input's kinds (FAPs, PCM, markers)."""
        state = self.state
        if state is not State.STREAMING and state is not State.READY:
            if state is State.AWAITING_HELLO:
                return self._refuse(
                    MessageError("the first message must be a JSON hello, not a binary frame")
                )
            return NOTHING
        now = self.clock()
        verdict, why = self._check(len(data), False, now)  # ``Gate.check``, inlined: hot path
        if verdict is not Verdict.OK:
            assert self._gate is not None
            return self._over(self._gate.decide(verdict, why, now))
        try:
            frame = frames.decode(data, kinds=self._kinds)
        except Exception as e:  # noqa: BLE001 - a frame the decoder refuses: mapped to its reply
            return self._rejected(e, None, data)
        if self._offload:
            return Step(work=Work(partial(_push_into, self._push_frame, frame), self._pushed))
        try:
            if self._check_faps is not None:
                self._check_frame(frame)
            states = self._push_frame(frame)
        except Exception as e:  # noqa: BLE001 - a driver's error costs this frame only (_rejected)
            return self._rejected(e, frame.header.seq)
        self.state = State.STREAMING
        session = self.session
        session.count_in()
        session.submit(states, frame.header.wall, self.role)
        return NOTHING

    def take_bytes(self, data: bytes) -> Step | None:
        """``receive_bytes`` for a message taken as it arrives, outside the connection's task:
        None when nothing is left for the task to do."""
        step = self.receive_bytes(data)
        return step if step is not NOTHING or not self.open else None

    def _check_frame(self, frame: frames.Frame) -> None:
        """A secondary role's binary FAP frame drives only that role's FAPs (else ``Forbidden``)."""
        assert isinstance(frame, frames.FapFrame) and self._check_faps is not None
        sent = np.flatnonzero(~np.isnan(frame.values[2:])) + 3
        self._forbid(self._check_faps(sent.tolist()), frame.viseme, frame.expression)

    def _forbid(self, why: str | None, viseme: Any, expression: Any) -> None:
        if why is None and viseme is not None:
            why = f"a '{self.role}' producer may not send visemes (the primary's mouth shapes)"
        if why is None and expression is not None and self.role != "expression":
            why = f"a '{self.role}' producer may not send expressions (the expression role's)"
        if why is not None:
            raise _NotItsRole(why, where="faps")

    # -- the hello ---------------------------------------------------------------------------------
    def _hello(self, text: str) -> Step:
        try:
            hello = parse_message(text)
            if not isinstance(hello, ProducerHello):
                raise MessageError(
                    "the first message must be a producer hello, got "
                    f"'{getattr(hello, 'type', '?')}'"
                )
            if hello.protocol != frames.VERSION:
                raise MessageError(
                    f"protocol version {hello.protocol} is not supported (server speaks "
                    f"{frames.VERSION})",
                    where="hello.protocol",
                )
        except MessageError as e:
            return self._refuse(e)
        refused = self._claim(hello)
        if refused is not None:
            return self._close(refused)
        self._claimed = True
        self.state = State.OPENING
        spec = self.session.spec
        kind = spec.input if self.role == "primary" else "fap"
        if self.role != "primary":
            self._offload = False  # FAP frames: decoded and taken inline
            self._check_faps = partial(role_refusal, self.role)
        run = partial(_open, kind, self.session.face, hello, spec.fps)
        return Step(work=Work(run, partial(self._opened, hello)), event=Event.HELLO)

    def _opened(self, hello: ProducerHello, result: Input | BaseException) -> Step:
        if self.state is not State.OPENING or self.session.closed:  # closed meanwhile: it was told
            self.state = State.CLOSED
            return NOTHING
        if isinstance(result, BaseException):
            return self._refuse(result)
        self.input = result
        return self._follow(partial(self._ready, hello))

    def _ready(self, hello: ProducerHello) -> Step:
        spec = self.session.spec
        limits = producer_limits(
            spec.input if self.role == "primary" else "fap",
            self.max_fps,
            rate=hello.rate,
            sample_format=hello.sample_format,
            markers=len(hello.markers or ()),
        )
        self._gate = Gate(limits, self.clock(), label=self._label, metrics=self.metrics)
        assert self.input is not None
        self._check = self._gate.budget.check
        self._kinds = self.input.kinds
        self._push_frame = self.input.push_frame
        self.state = State.READY
        self.session.announce(self.slot)  # tells viewers
        ready = Ready(
            session=spec.id,
            input=spec.input if self.role == "primary" else "fap",
            fps=spec.fps,
            max_fps=self.max_fps,
            vertex_count=self.session.vertex_count,
            role=None if self.role == "primary" else self.role,
        )
        return Step(send=(dump_message(ready),), event=Event.READY)

    # -- the control set ---------------------------------------------------------------------------
    def _follow(self, then: Callable[[], Step]) -> Step:
        """Give the session an animator over the input's explicit control vertices (mocap) when they
        are new, then ``then()``; the animator is built off the event loop."""
        assert self.input is not None
        cv = self.input.control_vertices
        if not self.session.needs_controls(cv):
            return then()
        cv = np.array(cv)
        run = partial(_build, self.animators, self.session, cv)
        return Step(work=Work(run, partial(self._swap, cv, then)))

    def _swap(self, cv: np.ndarray, then: Callable[[], Step], animator: Any) -> Step:
        if self.state is State.CLOSED or self.session.closed:
            self.state = State.CLOSED
            return NOTHING
        if isinstance(animator, BaseException):
            return self._refuse(animator)
        self.session.deform_with(self.animators.batcher_for(animator), cv)
        return then()

    # -- frames ------------------------------------------------------------------------------------
    def _pushed(self, result: tuple[list[FaceState], float] | tuple[BaseException, int]) -> Step:
        if self.state is State.CLOSED:
            return NOTHING
        if isinstance(result[0], BaseException):
            return self._rejected(result[0], int(result[1]))
        states, wall = result
        return self._follow(partial(self._take_step, states, float(wall)))

    def _take_step(self, states: list[FaceState], wall: float) -> Step:
        self._take(states, wall)
        return NOTHING

    def _take(self, states: list[FaceState], wall: float) -> None:
        self.state = State.STREAMING
        self.session.count_in()
        self.session.submit(states, wall, self.role)

    def _flushed(self, tail: list[FaceState]) -> Step:
        if tail:
            self.session.submit(tail, time.time(), self.role)
        return NOTHING

    # -- refusals ----------------------------------------------------------------------------------
    def _over(self, step: Step) -> Step:
        """A message over the budget: counted; a close ends the connection."""
        self.session.count_rejected()
        if step.close is not None:
            self.state = State.CLOSED
        return step

    def _rejected(self, exc: BaseException, seq: int | None, data: bytes | None = None) -> Step:
        """A frame or message dropped (non-fatal): the client's fault (4400, named), or the
        driver's (4500, vague; logged)."""
        self.session.count_rejected()
        if seq is None and data is not None:
            with contextlib.suppress(FrameError):  # name the frame when its header is readable
                seq = frames.parse_header(data).seq
        mapped = client_error(exc)
        if mapped is None:
            log.error(
                "session %s: the %s driver failed on a frame",
                self.session.spec.id,
                self.session.spec.input,
                exc_info=exc,
            )
            text = error_json(
                CloseCode.INTERNAL, "frame dropped: the driver failed (see the server log)", seq=seq
            )
        else:
            code, message, where = mapped
            text = error_json(code, f"frame dropped: {message}", where=where, seq=seq)
        return Step(send=(text,), event=Event.REJECTED)

    def _refuse(self, exc: BaseException) -> Step:
        """End the connection over ``exc``: its code if it is the client's fault, else 4500."""
        mapped = client_error(exc)
        if mapped is None:
            return self.failed(exc)
        code, message, where = mapped
        return self._close(Close(code, message, where))

    def _close(self, close: Close) -> Step:
        self.state = State.CLOSED
        return closing(close)


class _NotItsRole(Forbidden):
    """A secondary producer's frame drives what its role may not (a non-fatal 4403)."""

    status = 403


# -- blocking work (the shell runs it, in a thread when offloaded); client faults are returned --


def _open(kind: str, face: Any, hello: ProducerHello, fps: float) -> Input | BaseException:
    try:
        return make_input(kind, face, hello, fps)
    except Exception as e:  # noqa: BLE001 - handed back to the core, which maps it (_opened)
        return e


def _build(animators: Animators, session: LiveSession, cv: np.ndarray) -> Any:
    try:
        return animators.animator_for(session, cv)
    except Exception as e:  # noqa: BLE001 - handed back to the core, which maps it (_swap)
        return e


def _push_into(
    push: Callable[[frames.Frame], list[FaceState]], frame: frames.Frame
) -> tuple[list[FaceState], float] | tuple[Exception, int]:
    try:
        return push(frame), frame.header.wall
    except Exception as e:  # noqa: BLE001 - handed back to the core, which maps it (_pushed)
        return e, frame.header.seq


def _never_checked(nbytes: int, text: bool, now: float) -> tuple[Verdict, str]:
    raise AssertionError("no budget before the input is ready")


def _never_pushed(frame: frames.Frame) -> list[FaceState]:
    raise AssertionError("no input before the hello")


def _flush(inp: Input) -> list[FaceState]:
    try:
        return inp.flush()
    except Exception:
        log.exception("flushing a producer's input failed")
        return []
