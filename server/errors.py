"""One root for the errors a user sees. Messages say what was wrong and what to do.

Parsers in ``facecast.protocol`` raise ``ProtocolError`` subclasses (``FileFormatError`` for .fap,
C3D/TRC/CSV takes and topology blobs); those are the caller's fault too. ``CLIENT_ERRORS`` catches
both kinds, and ``as_facecast_error`` turns a protocol error into an ``InputError`` (same status).
"""

from ..protocol.errors import ProtocolError


class FacecastError(Exception):
    """A user-facing error: bad input, a missing resource, an unusable device.

    ``where`` names the file, line or field at fault (may be empty); ``status`` is the HTTP status a
    server maps it to (4xx: the caller's fault).
    """

    status = 400

    def __init__(self, message: str, *, where: str = "") -> None:
        self.where = where
        super().__init__(f"{where}: {message}" if where else message)


class InputError(FacecastError):
    """Malformed or unsupported input (file, frame, parameter)."""


class NotFound(FacecastError):
    status = 404


#: Every error that is the caller's fault (a 4xx): the server's own and the protocol's parsers'.
CLIENT_ERRORS: tuple[type[Exception], ...] = (FacecastError, ProtocolError)


def as_facecast_error(e: Exception) -> FacecastError:
    """``e`` itself if it is a FacecastError; a ProtocolError as an InputError with its status."""
    if isinstance(e, FacecastError):
        return e
    if isinstance(e, ProtocolError):
        err = InputError(str(e))  # the message already names the file, line or field
        err.where, err.status = e.where, e.status
        return err
    raise TypeError(f"{type(e).__name__} is not a user-facing error")
