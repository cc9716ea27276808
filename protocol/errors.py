"""facecast's one error tree, the WebSocket close codes, and the one mapping from an error to what a
client hears (HTTP status, close code, message).

Every error facecast raises on purpose is a ``FacecastError``; it carries its HTTP ``status`` and
WebSocket ``close_code`` as class attributes (one place), and a message that says what was wrong and
what to do. As in h11 and websockets, the tree splits on whose fault it is::

    Exception
     └── FacecastError            root (raised directly: this side's fault, 500 / 4500)
          ├── RemoteError         the peer sent something wrong: 4xx / 4xxx, 1003, 1008, 1009
          │    ├── InputError     malformed or unsupported input (file, frame, parameter): 400 / 4400
          │    │    └── ProtocolError  (also a ValueError) bytes or text that do not decode
          │    │         ├── FrameError       a binary frame (vertices, PCM, markers, FAPs)
          │    │         ├── MessageError     a JSON control message (BadHello: a hello unfit
          │    │         │                    for the session)
          │    │         └── FileFormatError  a file: FapFormatError, MarkerFileError
          │    │                              (C3D/TRC/CSV), TopologyError, BmlError
          │    └── Unauthorized 401, Forbidden 403, NotFound 404, TimedOut 408, Conflict 409,
          │        PayloadTooLarge 413, UnsupportedMedia 415, Unprocessable 422, TooMany 429 (Flood)
          └── LocalError          this side cannot do it: 5xx / 45xx
               ├── InternalError  500 / 4500
               ├── UpstreamError  a facecast server this side called refused or failed: 502 / 4502
               └── Unavailable    a driver, device or slot is missing or busy: 503 / 4503

``error_reply(exc)`` maps any exception to an ``ErrorReply``: the REST exception handlers and the
WebSocket shells both use it (through ``server.api.errors``), so a client hears the same status,
close code and message on either. An exception outside the tree is a server fault: 500 / 4500 and a
deliberately vague message (the details belong in the server log).

``ProtocolError`` stays a ``ValueError``, as Python's own decoding errors are (``json``,
``UnicodeDecodeError``, ``tomllib``): code that catches ``ValueError`` around a decoder still works.
Encoders raise plain ``ValueError`` / ``TypeError`` for arrays of the wrong shape (a programming error
on the sending side), never a ``ProtocolError``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import IntEnum
from types import MappingProxyType
from typing import ClassVar

__all__ = [
    "INTERNAL_MESSAGE",
    "BmlError",
    "CloseCode",
    "Conflict",
    "ErrorReply",
    "FacecastError",
    "FileFormatError",
    "Flood",
    "Forbidden",
    "FrameError",
    "InputError",
    "InternalError",
    "LocalError",
    "MessageError",
    "NotFound",
    "PayloadTooLarge",
    "ProtocolError",
    "RemoteError",
    "TimedOut",
    "TooMany",
    "Unauthorized",
    "Unavailable",
    "Unprocessable",
    "UnsupportedMedia",
    "UpstreamError",
    "close_code_for",
    "error_reply",
    "show_token",
]


class CloseCode(IntEnum):
    """WebSocket close codes (4000-4999 are for applications; 4xxx mirrors HTTP status xxx).

    Before closing with any code other than ``NORMAL``/``GOING_AWAY``, the server sends one JSON
    ``error`` message whose ``code`` is the same number and whose ``message`` says what to do.
    """

    NORMAL = 1000  #: the stream ended normally
    GOING_AWAY = 1001  #: the server is shutting down
    UNSUPPORTED_DATA = 1003  #: a kind of data this endpoint does not take (HTTP 415)
    POLICY_VIOLATION = 1008  #: messages far over the connection's rate budget (a flood)
    TOO_BIG = 1009  #: a message over the size limit of its kind (e.g. an audio chunk over 1 s)
    SESSION_CLOSED = 4000  #: the session was closed (DELETE /v1/sessions/{id}) while connected
    BAD_REQUEST = 4400  #: bad query parameter, hello, or a frame that makes the stream unusable
    UNAUTHORIZED = 4401  #: token missing or wrong
    FORBIDDEN = 4403  #: a valid token for the other role (e.g. a viewer token on /produce)
    NOT_FOUND = 4404  #: no such session
    TIMEOUT = 4408  #: no hello within the time limit
    CONFLICT = 4409  #: a producer is already connected to this session
    UNPROCESSABLE = (
        4422  #: well-formed, but asks for what cannot be done (e.g. an output format limit)
    )
    TOO_MANY = 4429  #: too many viewers, or frames sent faster than the session's limit
    INTERNAL = 4500  #: a server fault; the message is deliberately vague
    UPSTREAM = 4502  #: a facecast server this one called refused or failed
    UNAVAILABLE = 4503  #: the input kind's driver is not installed on this server, or it is busy


#: HTTP status -> the close code of an error with that status (the codes above, one table).
_CLOSE_FOR_STATUS: Mapping[int, CloseCode] = MappingProxyType(
    {
        400: CloseCode.BAD_REQUEST,
        401: CloseCode.UNAUTHORIZED,
        403: CloseCode.FORBIDDEN,
        404: CloseCode.NOT_FOUND,
        408: CloseCode.TIMEOUT,
        409: CloseCode.CONFLICT,
        413: CloseCode.TOO_BIG,
        415: CloseCode.UNSUPPORTED_DATA,
        422: CloseCode.UNPROCESSABLE,
        429: CloseCode.TOO_MANY,
        500: CloseCode.INTERNAL,
        502: CloseCode.UPSTREAM,
        503: CloseCode.UNAVAILABLE,
    }
)


def close_code_for(status: int) -> CloseCode:
    """The close code of an error with HTTP ``status`` (an unlisted 4xx: 4400, else 4500)."""
    code = _CLOSE_FOR_STATUS.get(status)
    if code is not None:
        return code
    return CloseCode.BAD_REQUEST if 400 <= status < 500 else CloseCode.INTERNAL


#: What a client hears about an error outside the tree (a server fault).
INTERNAL_MESSAGE = "internal server error; the server log has the details"


class FacecastError(Exception):
    """Root of every error facecast raises on purpose; its message is meant for the user.

    Class attributes (one place per error; a subclass that sets only ``status`` gets the close code
    of ``close_code_for(status)``):
        status: the HTTP status a REST endpoint answers with.
        close_code: the WebSocket close code if the error ends the connection.
        headers: extra HTTP response headers (e.g. ``Retry-After``).

    Attributes:
        where: the file, line, field or byte offset at fault (may be empty).
    """

    status: ClassVar[int] = 500
    close_code: ClassVar[int] = CloseCode.INTERNAL
    headers: ClassVar[Mapping[str, str]] = MappingProxyType({})

    def __init__(self, message: str, *, where: str = "") -> None:
        self.where = where
        super().__init__(f"{where}: {message}" if where else message)

    def __init_subclass__(cls, **kwargs: object) -> None:
        super().__init_subclass__(**kwargs)
        if "status" in cls.__dict__ and "close_code" not in cls.__dict__:
            cls.close_code = close_code_for(cls.status)
        for branch, low in (
            (globals().get("RemoteError"), 400),
            (globals().get("LocalError"), 500),
        ):
            if branch is not None and issubclass(cls, branch) and not low <= cls.status < low + 100:
                raise TypeError(
                    f"{cls.__qualname__}: status {cls.status} does not fit its branch of "
                    f"the error tree ({branch.__name__}: {low // 100}xx)"
                )


class RemoteError(FacecastError):
    """The peer sent something wrong (malformed, unauthorised, too much): a 4xx, its fault."""

    status = 400


class LocalError(FacecastError):
    """This side cannot do what was asked (a driver missing, a device failing): a 5xx."""

    status = 500


# -------------------------------------------------------------------------------------- remote (4xx)


class InputError(RemoteError):
    """Malformed or unsupported input (file, frame, parameter)."""


class ProtocolError(InputError, ValueError):
    """Bytes or text that do not decode (also a ``ValueError``, like Python's own decoding errors)."""


class FrameError(ProtocolError):
    """A binary frame is truncated, too long, of an unknown kind/version, or inconsistent."""


class MessageError(ProtocolError):
    """A JSON control message is not JSON, has an unknown ``type``, or fails validation."""


class FileFormatError(ProtocolError):
    """A file (or file-like blob) a client sent or named is malformed; HTTP 400 / close 4400."""


class BmlError(FileFormatError):
    """A BML script that is malformed or asks for what facecast does not support.

    Attributes: ``line`` (1-based, 0 when not tied to a line), ``element`` (the XML element's name,
    may be empty) and ``reason``; the message reads ``[where: ]line L: <element>: reason``.
    """

    def __init__(self, reason: str, *, line: int = 0, element: str = "", where: str = "") -> None:
        self.line, self.element, self.reason = line, element, reason
        at = ": ".join(
            x for x in (f"line {line}" if line else "", f"<{element}>" if element else "") if x
        )
        super().__init__(f"{at}: {reason}" if at else reason, where=where)


class Unauthorized(RemoteError):
    """A credential (admin key, session token) is missing or wrong."""

    status = 401


class Forbidden(RemoteError):
    """A valid credential that does not allow this (e.g. a viewer token on /produce)."""

    status = 403


class NotFound(RemoteError):
    """No such face, job or session."""

    status = 404


class TimedOut(RemoteError):
    """The peer did not send in time (e.g. no hello within the limit)."""

    status = 408


class Conflict(RemoteError):
    """The resource's state does not allow this now (a producer already connected, a job done)."""

    status = 409


class PayloadTooLarge(RemoteError):
    """An upload or message over its size limit."""

    status = 413


class UnsupportedMedia(RemoteError):
    """A kind of content this endpoint does not take."""

    status = 415


class Unprocessable(RemoteError):
    """Well-formed, but asks for what cannot be done as asked (change the request: e.g. a shorter
    clip, or another output format)."""

    status = 422


class TooMany(RemoteError):
    """Over a limit of count or rate (sessions, viewers, frames per second)."""

    status = 429


class Flood(TooMany):
    """Messages far over the connection's rate budget: the connection is closed (1008)."""

    close_code = CloseCode.POLICY_VIOLATION


# --------------------------------------------------------------------------------------- local (5xx)


class InternalError(LocalError):
    """A fault of this side that it detected itself (the message says what to do)."""


class UpstreamError(LocalError):
    """A facecast server this side called refused or failed, or could not be reached.

    ``code`` is what that server answered: its HTTP status or WebSocket close code, 0 if none.
    """

    status = 502

    def __init__(self, message: str, code: int = 0, *, where: str = "") -> None:
        super().__init__(message, where=where)
        self.code = code


class Unavailable(LocalError):
    """A part this needs is not installed or is busy (a driver, a device, every decode slot)."""

    status = 503


# ------------------------------------------------------------------------------------------ mapping


@dataclass(frozen=True)
class ErrorReply:
    """What a client hears about an error, on REST and WebSocket alike.

    Attributes:
        status: HTTP status.
        close_code: WebSocket close code (after an ``error`` message with the same ``code``).
        message: what was wrong and what to do (vague for a server fault).
        where: the field, file or byte offset at fault (may be empty).
        headers: extra HTTP response headers.
        remote: the peer's fault (a 4xx).
        unexpected: not a facecast error: a server fault whose details go to the log only.
    """

    status: int
    close_code: int
    message: str
    where: str = ""
    headers: Mapping[str, str] = field(default_factory=dict)
    remote: bool = False
    unexpected: bool = False


def error_reply(exc: BaseException) -> ErrorReply:
    """The status, close code and message of ``exc`` (read from its class: one place per error)."""
    if isinstance(exc, FacecastError):
        cls = type(exc)
        return ErrorReply(
            cls.status,
            int(cls.close_code),
            str(exc),
            exc.where,
            dict(cls.headers),
            remote=isinstance(exc, RemoteError),
        )
    return ErrorReply(500, int(CloseCode.INTERNAL), INTERNAL_MESSAGE, unexpected=True)


def show_token(text: str, limit: int = 40) -> str:
    """A client's token for an error message (``repr``), cut to ``limit`` characters or so."""
    return repr(text if len(text) <= limit else text[: limit - 4] + "...")
