"""Live sessions: the registry, one session's deform-once fan-out, producer inputs, and the
sans-I/O cores of the live connections (``producer.ProducerCore``, ``watch.ViewerCore``).

``SessionRegistry`` lives on ``app.state.live``; ``api.routes_sessions`` is the HTTP/WebSocket
shell that feeds the cores, and ``api.transport`` holds its socket tricks.
"""

from __future__ import annotations

from .registry import SessionRegistry, TooMany, Unavailable
from .session import LiveSession, Viewer

__all__ = ["LiveSession", "SessionRegistry", "TooMany", "Unavailable", "Viewer"]
