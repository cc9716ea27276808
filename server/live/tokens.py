"""Session and admin tokens: minting and comparing (pure; used by the live core, the registry
and ``api.security``)."""

from __future__ import annotations

import hmac
import secrets


def new_token() -> str:
    """A fresh random token (URL-safe, 32 bytes of entropy) that does not start with ``-``, so that
    it can follow a command-line flag (``--token T``) without being taken for an option."""
    while True:
        token = secrets.token_urlsafe(32)
        if not token.startswith("-"):
            return token


def same(a: str | None, b: str | None) -> bool:
    """Constant-time comparison of two optional secrets (text a client sent may hold lone
    surrogates: they compare as replacement characters instead of raising)."""
    return (
        a is not None
        and b is not None
        and hmac.compare_digest(a.encode("utf-8", "replace"), b.encode("utf-8", "replace"))
    )
