"""Errors of the wire protocol, and the WebSocket close codes a server uses.

Exception tree (all decoding failures are one of these; nothing else escapes a decoder)::

    ValueError
     └── ProtocolError          root: carries ``close_code`` (WebSocket) and ``status`` (HTTP) hints
          ├── FrameError        a binary frame (vertices, PCM, markers, FAPs) is malformed
          ├── MessageError      a JSON control message is malformed or of an unknown type
          └── FileFormatError   a file is malformed: FapFormatError (.fap), MarkerFileError
                                (C3D/TRC/CSV takes), TopologyError (topology blob)

Encoders raise ``ValueError`` / ``TypeError`` for arrays of the wrong shape (a programming error on
the sending side), never ``ProtocolError``.
"""

from __future__ import annotations

from enum import IntEnum

__all__ = ["CloseCode", "ProtocolError", "FrameError", "MessageError", "FileFormatError", "show_token"]


class CloseCode(IntEnum):
    """WebSocket close codes (4000-4999 are for applications; 4xxx mirrors HTTP status 4xx).

    Before closing with any code other than ``NORMAL``/``GOING_AWAY``, the server sends one JSON
    ``error`` message whose ``code`` is the same number and whose ``message`` says what to do.
    """

    NORMAL = 1000  #: the stream ended normally
    GOING_AWAY = 1001  #: the server is shutting down
    POLICY_VIOLATION = 1008  #: messages far over the connection's rate budget (a flood)
    TOO_BIG = 1009  #: a message over the size limit of its kind (e.g. an audio chunk over 1 s)
    SESSION_CLOSED = 4000  #: the session was closed (DELETE /v1/sessions/{id}) while connected
    BAD_REQUEST = 4400  #: bad query parameter, hello, or a frame that makes the stream unusable
    UNAUTHORIZED = 4401  #: token missing or wrong
    FORBIDDEN = 4403  #: a valid token for the other role (e.g. a viewer token on /produce)
    NOT_FOUND = 4404  #: no such session
    TIMEOUT = 4408  #: no hello within the time limit
    CONFLICT = 4409  #: a producer is already connected to this session
    TOO_MANY = 4429  #: too many viewers, or frames sent faster than the session's limit
    UNAVAILABLE = 4503  #: the input kind's driver is not installed on this server
    INTERNAL = 4500  #: a server fault; the message is deliberately vague


class ProtocolError(ValueError):
    """Root of protocol errors.

    Attributes:
        close_code: the WebSocket close code a server would use if the error ends the connection.
        status: the HTTP status a REST endpoint would use.
        where: the field or byte offset at fault (may be empty).
    """

    close_code: int = CloseCode.BAD_REQUEST
    status: int = 400

    def __init__(self, message: str, *, where: str = "") -> None:
        self.where = where
        super().__init__(f"{where}: {message}" if where else message)


class FrameError(ProtocolError):
    """A binary frame is truncated, too long, of an unknown kind/version, or inconsistent."""


class MessageError(ProtocolError):
    """A JSON control message is not JSON, has an unknown ``type``, or fails validation."""


class FileFormatError(ProtocolError):
    """A file (or file-like blob) a client sent or named is malformed; HTTP 400 / close 4400."""


def show_token(text: str, limit: int = 40) -> str:
    """A client's token for an error message (``repr``), cut to ``limit`` characters or so."""
    return repr(text if len(text) <= limit else text[: limit - 4] + "...")
