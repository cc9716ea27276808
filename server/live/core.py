"""What the live connections' state machines return, and the decisions they share (sans-I/O).

A connection's core (``producer.ProducerCore``, ``watch.ViewerCore``) never touches a socket and
never awaits: fed what the peer sent, it returns a ``Step`` — messages to send, a ``Close``
decision, and at most one piece of blocking ``Work`` whose result the shell feeds back (drivers
and animators may take milliseconds to seconds: the shell runs them in a thread). The shell
(``api.routes_sessions``) only receives, feeds and carries out steps.

Also here: an error's close code (``client_error``, over the project's one mapping), the token
check of both roles (``authorise``) and the budget step both roles share (``Gate``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from typing import Any

from ...protocol.errors import INTERNAL_MESSAGE, CloseCode, error_reply
from ...protocol.messages import ErrorMessage, dump_message
from .budget import Budget, Limits, Verdict
from .tokens import same

log = logging.getLogger(__name__)


class Event(Enum):
    """What a step did (for the shell's logs and for tests)."""

    NONE = "none"  #: nothing of note (a frame taken, a message read and ignored)
    HELLO = "hello"  #: a well-formed hello: its input is being opened (``Step.work``)
    READY = "ready"  #: the input is open; ``ready`` is sent
    DROPPED = "dropped"  #: a message over the rate was dropped (maybe with a warning)
    REJECTED = "rejected"  #: a frame was refused (malformed, or the driver failed); non-fatal
    CLOSED = "closed"  #: the connection ends (``Step.close``)


def error_json(
    code: int, message: str, *, where: str = "", fatal: bool = False, seq: int | None = None
) -> str:
    """One JSON ``error`` message."""
    return dump_message(
        ErrorMessage(code=int(code), message=message, where=where, fatal=fatal, seq=seq)
    )


def close_reason(message: str) -> str:
    """``message`` cut to fit a close frame's reason (123 bytes of UTF-8)."""
    raw = message.encode("utf-8", "replace")
    return raw.decode() if len(raw) <= 123 else raw[:120].decode("utf-8", "ignore") + "..."


@dataclass(frozen=True, slots=True)
class Close:
    """The decision to end a connection: one fatal ``error`` message, then a close with ``code``.

    ``cut_off``: stop reading now and drop the connection after a grace period whatever the peer
    does (a flood, an oversized message: its queued bytes are never parsed).
    """

    code: int
    message: str
    where: str = ""
    cut_off: bool = False

    @property
    def error(self) -> str:
        """The fatal JSON ``error`` message sent before the close frame."""
        return error_json(self.code, self.message, where=self.where, fatal=True)

    @property
    def reason(self) -> str:
        """The close frame's reason: the message, cut to fit."""
        return close_reason(self.message)


@dataclass(frozen=True, slots=True)
class Work:
    """Blocking work for the shell: run ``run()`` (in a thread if ``offload``, else inline) and feed
    its result to ``then``, which returns the next step. ``run`` never raises for the client's
    faults (they come back as results)."""

    run: Callable[[], Any]
    then: Callable[[Any], Step]
    offload: bool = True


@dataclass(frozen=True, slots=True)
class Step:
    """What to do after feeding a core: send ``send`` (JSON texts, in order), then carry out
    ``work`` or ``close`` (never both)."""

    send: tuple[str, ...] = ()
    close: Close | None = None
    work: Work | None = None
    event: Event = Event.NONE


#: The step of a message taken with nothing to answer (shared: the hot path allocates nothing).
NOTHING = Step()


def closing(close: Close) -> Step:
    return Step(close=close, event=Event.CLOSED)


def client_error(exc: BaseException) -> tuple[int, str, str] | None:
    """``(close code, message, where)`` of a facecast error (``protocol.errors.error_reply``, the
    one mapping REST shares: a protocol error or a bad hello is 4400, a missing driver 4503...), or
    None for an error outside the tree: a server fault, logged and answered vaguely with 4500."""
    r = error_reply(exc)
    if r.unexpected:
        return None
    return r.close_code, r.message, r.where


#: The answer to a server fault (the details go to the log, never to the client).
INTERNAL = Close(CloseCode.INTERNAL, INTERNAL_MESSAGE)


def authorise(
    session_id: str,
    found: bool,
    token: str | None,
    mine: str,
    other: str,
    role: str,
) -> Close | None:
    """None if ``token`` is the session's ``role`` token (``mine``); else why not, as a ``Close``.

    ``found``: the session exists; ``other`` is the other role's token (a mix-up gets 4403).
    """
    if not found:
        return Close(
            CloseCode.NOT_FOUND, f"no live session {session_id!r}; it was closed or never existed"
        )
    if same(token, mine):
        return None
    if same(token, other):
        return Close(
            CloseCode.FORBIDDEN,
            f"this token is the session's {'viewer' if role == 'producer' else 'producer'}"
            f" token; {role}s need the {role} token",
            where="token",
        )
    return Close(
        CloseCode.UNAUTHORIZED,
        f"missing or wrong {role} token: send 'Authorization: Bearer <{role}_token from "
        "POST /v1/sessions>' (browsers: the subprotocols 'facecast.v1' and "
        f"'facecast.token.<{role}_token>')",
        where="token",
    )


#: Close code of a budget verdict that ends the connection.
_CLOSE = {Verdict.TOO_BIG: CloseCode.TOO_BIG, Verdict.FLOOD: CloseCode.POLICY_VIOLATION}


class Gate:
    """One connection's budget (``budget.Budget``) as decisions, checked on each raw message
    before it is decoded.

    ``check`` returns None for a message to decode; else the step: a drop (counted, and answered
    with a 4429 warning at most once a second, if ``warn``; else ignored), or the close of a
    flood (1008) or an oversized message (1009), with ``cut_off``.
    """

    __slots__ = ("budget", "label", "metrics", "prefix", "warn")

    def __init__(
        self,
        limits: Limits,
        now: float,
        *,
        label: str,
        metrics: Any = None,
        warn: bool = True,
        prefix: str = "",
    ) -> None:
        self.budget = Budget(limits, now)
        self.label = label  # for the log: "session <id>: producer"
        self.metrics = metrics
        self.warn = warn
        self.prefix = prefix

    def check(self, nbytes: int, text: bool, now: float) -> Step | None:
        verdict, why = self.budget.check(nbytes, text, now)
        return None if verdict is Verdict.OK else self.decide(verdict, why, now)

    def decide(self, verdict: Verdict, why: str, now: float) -> Step:
        """The step for a verdict other than OK (``check`` inlined by a hot loop)."""
        if verdict is Verdict.DROP and not self.warn:  # viewers: read and ignored anyway
            return _DROPPED
        if self.metrics:
            self.metrics.live_refused.labels(verdict.name.lower()).inc()
        if verdict is Verdict.DROP:
            if self.budget.warn_now(now):
                return Step(send=(error_json(CloseCode.TOO_MANY, why),), event=Event.DROPPED)
            return _DROPPED
        code = _CLOSE[verdict]
        log.warning("%s disconnected (%d): %s", self.label, code, why)
        return closing(Close(code, self.prefix + why, cut_off=True))


_DROPPED = Step(event=Event.DROPPED)
