"""The server's errors: the one tree of ``facecast.protocol.errors``, re-exported under the names the
server has always used. Messages say what was wrong and what to do.

``FacecastError`` is the root; ``RemoteError`` (the caller's fault, 4xx) and ``LocalError`` (this
server's, 5xx) split it; ``protocol.errors`` has the tree, its status and close codes, and
``error_reply`` (the one mapping to what a client hears).
"""

from ..protocol.errors import (
    Conflict,
    FacecastError,
    Flood,
    Forbidden,
    InputError,
    InternalError,
    LocalError,
    NotFound,
    PayloadTooLarge,
    ProtocolError,
    RemoteError,
    TimedOut,
    TooMany,
    Unauthorized,
    Unavailable,
    Unprocessable,
    UnsupportedMedia,
    UpstreamError,
)

__all__ = [
    "CLIENT_ERRORS",
    "Conflict",
    "FacecastError",
    "Flood",
    "Forbidden",
    "InputError",
    "InternalError",
    "LocalError",
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
    "as_facecast_error",
]

#: Every error that is the caller's fault (a 4xx), the protocol's parsers' included.
CLIENT_ERRORS: tuple[type[Exception], ...] = (RemoteError,)


def as_facecast_error(e: Exception) -> FacecastError:
    """``e`` itself: every project error is a ``FacecastError`` now (kept for old callers)."""
    if isinstance(e, FacecastError):
        return e
    raise TypeError(f"{type(e).__name__} is not a user-facing error")
