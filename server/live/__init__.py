"""Live sessions: the registry, one session's deform-once fan-out, and producer inputs.

``SessionRegistry`` lives on ``app.state.live``; ``routes_sessions`` is its HTTP/WebSocket shell.
"""

from __future__ import annotations

from .registry import SessionRegistry, TooMany, Unavailable
from .session import LiveSession, Viewer

__all__ = ["SessionRegistry", "LiveSession", "Viewer", "TooMany", "Unavailable"]
