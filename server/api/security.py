"""Credentials: the admin key (REST admin routes) and per-session producer/viewer tokens."""

from __future__ import annotations

import logging
import stat
from pathlib import Path

from fastapi import HTTPException, Request, status

from ..live.tokens import new_token, same
from ..output.atomic import write_bytes_atomic

log = logging.getLogger(__name__)


def resolve_admin_key(configured: str | None, data_dir: Path) -> tuple[str, bool]:
    """The admin key: ``configured`` if set, else the one kept in ``data_dir/admin.key`` (created).

    The file is readable by its owner only (mode 0600): created so, and put back so with a warning
    if someone widened it. Returns ``(key, generated_now)``.
    """
    if configured:
        return configured, False
    path = data_dir / "admin.key"
    if path.exists():
        mode = stat.S_IMODE(path.stat().st_mode)
        if mode & 0o077:
            log.warning("%s was readable by others (mode %o); setting it to 0600", path, mode)
            path.chmod(0o600)
        key = path.read_text().strip()
        if key:
            return key, False
    data_dir.mkdir(parents=True, exist_ok=True)
    key = new_token()
    write_bytes_atomic(
        path, (key + "\n").encode(), mode=0o600
    )  # never readable by others, not even briefly
    return key, True


def bearer(request: Request) -> str | None:
    """The token of an ``Authorization: Bearer <token>`` header, or None."""
    auth = request.headers.get("authorization", "")
    scheme, _, token = auth.partition(" ")
    return token.strip() if scheme.lower() == "bearer" and token else None


def require_admin(request: Request) -> None:
    """FastAPI dependency: the request must carry ``Authorization: Bearer <admin key>``."""
    if not same(bearer(request), request.app.state.admin_key):
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            detail="admin key required: send 'Authorization: Bearer <key>' (the key is FACECAST_ADMIN_KEY, "
            "or the one the server printed at start-up and keeps in its data directory)",
        )


#: The WebSocket subprotocol of facecast. Browsers cannot set headers on a WebSocket, so a page
#: offers ``[WS_SUBPROTOCOL, WS_TOKEN_PREFIX + token]``; the server accepts with ``WS_SUBPROTOCOL``.
WS_SUBPROTOCOL = "facecast.v1"
WS_TOKEN_PREFIX = "facecast.token."


def ws_token(
    headers, subprotocols: list[str], query_token: str | None
) -> tuple[str | None, str | None]:
    """A live WebSocket's token and the subprotocol to accept (or None).

    The token comes from ``Authorization: Bearer``, else a ``facecast.token.<token>`` subprotocol,
    else (kept for old clients) the ``?token=`` query parameter, which servers log (masked).
    """
    offered = [p for p in subprotocols if p.startswith(WS_TOKEN_PREFIX)]
    accept = WS_SUBPROTOCOL if WS_SUBPROTOCOL in subprotocols else None
    auth = headers.get("authorization", "")
    scheme, _, token = auth.partition(" ")
    if scheme.lower() == "bearer" and token.strip():
        return token.strip(), accept
    if offered:
        return offered[0][len(WS_TOKEN_PREFIX) :], accept
    return query_token, accept
