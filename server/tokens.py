"""Random credentials: admin keys and session tokens (below the API and the live core, which both mint them)."""

from __future__ import annotations

import secrets


def new_token() -> str:
    """A fresh random token (URL-safe, 32 bytes of entropy) that does not start with ``-``, so that
    it can follow a command-line flag (``--token T``) without being taken for an option."""
    while True:
        token = secrets.token_urlsafe(32)
        if not token.startswith("-"):
            return token
