"""What a client hears about an error, for the REST exception handlers and the WebSocket shells alike.

``reply(exc, app)`` is the one mapping: ``protocol.errors.error_reply`` (status and close code from
the error's class, one place), Starlette's ``HTTPException`` by its status, anything else a server
fault (500 / 4500, a vague message); then server paths are cut from the message. REST answers with
``error_response(r)``, a WebSocket sends ``error_text(r)`` and closes with ``r.close_code``.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from starlette.exceptions import HTTPException

from ...protocol.errors import ErrorReply, close_code_for, error_reply
from ...protocol.messages import ErrorMessage, dump_message
from .responses import SafeJSONResponse

__all__ = ["ErrorReply", "error_body", "error_response", "error_text", "reply"]


def reply(exc: BaseException, app: Any = None) -> ErrorReply:
    """What a client hears about ``exc``, with ``app``'s private paths (``app.state.scrub_paths``)
    cut from the message and ``where``; the same on REST and WebSocket."""
    if isinstance(exc, HTTPException):
        status = exc.status_code
        message = exc.detail if isinstance(exc.detail, str) else "request failed"
        r = ErrorReply(
            status,
            int(close_code_for(status)),
            message,
            headers=dict(exc.headers or {}),
            remote=400 <= status < 500,
        )
    else:
        r = error_reply(exc)
    scrub = getattr(getattr(app, "state", None), "scrub_paths", None)
    if scrub is not None:
        r = replace(r, message=scrub(r.message), where=scrub(r.where))
    return r


def error_body(status: int, message: str, where: str = "", **extra: Any) -> dict[str, Any]:
    """The JSON body of every REST error: ``{"error", "detail" (the same), "status", "where"?}``."""
    body: dict[str, Any] = {"error": message, "detail": message, "status": status}
    if where:
        body["where"] = where
    body.update(extra)
    return body


def error_response(r: ErrorReply, **extra: Any) -> SafeJSONResponse:
    """The REST answer to ``r`` (``extra``: more body fields, e.g. validation ``problems``)."""
    return SafeJSONResponse(
        error_body(r.status, r.message, r.where, **extra),
        status_code=r.status,
        headers=dict(r.headers) or None,
    )


def error_text(
    r: ErrorReply, *, fatal: bool = True, seq: int | None = None, prefix: str = ""
) -> str:
    """The WebSocket ``error`` message of ``r`` (JSON text; ``code`` is ``r.close_code``; ``prefix``
    goes before the message, e.g. ``"frame dropped: "`` for a non-fatal error)."""
    return dump_message(
        ErrorMessage(
            code=r.close_code, message=prefix + r.message, where=r.where, fatal=fatal, seq=seq
        )
    )
