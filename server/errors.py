"""One root for the errors a user sees. Messages say what was wrong and what to do."""


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
