"""What a session's owner adds to it while it runs, kept in Redis for the node that takes it over.

Scoped producer tokens (``POST /v1/sessions/{id}/tokens``) and REST layers (``PUT .../layers/{name}``)
live on the owner's ``LiveSession``. The owner writes them to ``keys.extras(sid)`` at its heartbeat
when they changed (so at most ``HEARTBEAT_SECONDS`` of changes can be lost with it); a node taking
the session over puts them back: the scoped tokens work again, the layers mix again (their
timings restart from the take-over, as after a ``PUT``).
"""

from __future__ import annotations

import logging
from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError

from ...protocol.errors import MessageError, TooMany
from ...protocol.layers import parse_layer

log = logging.getLogger(__name__)


class SessionExtras(BaseModel):
    """A session's scoped producer tokens ``(token, roles)`` and REST layers ``(name, spec)``."""

    model_config = ConfigDict(extra="ignore")

    tokens: list[tuple[str, list[str]]] = []
    layers: list[tuple[str, dict[str, Any]]] = []


def snapshot(session: Any) -> str:
    """The JSON ``SessionExtras`` of ``session`` (a ``LiveSession``)."""
    layers = [(i.name, i.spec or {}) for i in session.mix.infos() if i.source == "rest"]
    return SessionExtras(tokens=session.grants.scoped(), layers=layers).model_dump_json()


def restore(session: Any, raw: bytes | str | None) -> int:
    """Put the extras ``raw`` (a ``snapshot``) back into ``session``; how many were restored. What
    does not fit (another version's record, a layer this node refuses) is logged and skipped."""
    if not raw:
        return 0
    try:
        extras = SessionExtras.model_validate_json(raw)
    except ValidationError as e:
        log.warning("cluster: the extras of session %s are unreadable (%s)", session.spec.id, e)
        return 0
    n = 0
    for token, roles in extras.tokens:
        session.grants.keep(token, roles)
        n += 1
    for name, spec in extras.layers:
        try:
            session.mix.set(name, parse_layer(spec))
            n += 1
        except (MessageError, ValueError, TooMany) as e:
            log.warning(
                "cluster: layer %r of session %s not restored: %s", name, session.spec.id, e
            )
    return n
