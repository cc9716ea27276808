"""Producer tokens and the roles they carry (pure; the session holds one ``Grants``).

The token made with a session carries every role (``protocol.messages.ROLES``): older clients, the
page and the admin keep full rights. ``mint`` makes a token that may drive only some roles (an
operator's page adding expressions, a script driving gaze); ``roles_of`` reads a token's roles,
comparing in constant time against every token.
"""

from __future__ import annotations

from collections.abc import Iterable

from ...protocol.errors import TooMany
from ...protocol.messages import ROLES
from .tokens import new_token, same

#: Scoped producer tokens a session holds at most.
MAX_SCOPED_TOKENS = 32
#: Every role: what the session's own producer token may drive.
ALL_ROLES: frozenset[str] = frozenset(ROLES)


class TooManyTokens(TooMany):
    """The session's scoped-token limit is reached (HTTP 429)."""

    status = 429


class Grants:
    """A session's producer tokens: the full one (``full``) and scoped ones."""

    __slots__ = ("_scoped", "full")

    def __init__(self, full: str) -> None:
        self.full = full
        self._scoped: list[tuple[str, frozenset[str]]] = []

    def roles_of(self, token: str | None) -> frozenset[str] | None:
        """The roles ``token`` may drive, or None if it is none of this session's producer tokens."""
        found = ALL_ROLES if same(token, self.full) else None
        for t, roles in self._scoped:  # every token is compared: the time says nothing of which
            if same(token, t):
                found = roles
        return found

    def mint(self, roles: Iterable[str]) -> str:
        """A new producer token for ``roles`` (each in ``ROLES``); ``TooManyTokens`` past the limit."""
        wanted = frozenset(roles)
        unknown = wanted - ALL_ROLES
        if unknown or not wanted:
            raise ValueError(f"roles must be some of {', '.join(ROLES)}, not {sorted(unknown)}")
        if len(self._scoped) >= MAX_SCOPED_TOKENS:
            raise TooManyTokens(
                f"this session has {MAX_SCOPED_TOKENS} scoped producer tokens already, its limit; "
                "reuse one, or create a new session",
                where="roles",
            )
        token = new_token()
        self._scoped.append((token, wanted))
        return token

    def scoped(self) -> list[tuple[str, list[str]]]:
        """The scoped tokens and their roles, to keep elsewhere (a cluster's Redis)."""
        return [(t, sorted(roles)) for t, roles in self._scoped]

    def keep(self, token: str, roles: Iterable[str]) -> None:
        """Hold the scoped ``token`` again (a session taken over from another node); a token held
        already, unknown roles and tokens past the limit are skipped."""
        wanted = frozenset(roles) & ALL_ROLES
        held = any(same(token, t) for t, _ in self._scoped)
        if wanted and token and not held and len(self._scoped) < MAX_SCOPED_TOKENS:
            self._scoped.append((token, wanted))
