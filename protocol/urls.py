"""Server URLs as people type them: ``127.0.0.1:8000`` means ``http://127.0.0.1:8000``.

Pure (no I/O): the CLI normalises every ``--url``/``--server`` with it, the client library every URL.
"""

from __future__ import annotations

import re
from urllib.parse import urlsplit, urlunsplit

_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*://")
#: WebSocket schemes name the same server over HTTP(S).
_HTTP_SCHEME = {"http": "http", "https": "https", "ws": "http", "wss": "https"}


def server_url(text: str) -> str:
    """The base URL of a facecast server from what a user typed.

    Adds ``http://`` when no scheme is given, maps ``ws``/``wss`` to ``http``/``https`` and drops a
    trailing slash: ``"localhost:8000/"`` -> ``"http://localhost:8000"``. Raises ``ValueError`` with
    a sentence saying what is wrong for a scheme other than those, a missing host or a bad port.
    """
    raw = text.strip()
    if not raw:
        raise ValueError("empty server URL; give one like http://127.0.0.1:8000")
    if not _SCHEME.match(raw):
        raw = "http://" + raw
    parts = urlsplit(raw)
    scheme = _HTTP_SCHEME.get(parts.scheme.lower())
    if scheme is None:
        raise ValueError(f"'{text}' is not an http(s) URL; give one like http://127.0.0.1:8000")
    try:
        port = parts.port
    except ValueError:
        port = -1
    if not parts.hostname or port == -1 or (port is not None and not 0 < port < 65536):
        raise ValueError(
            f"'{text}' names no host and valid port; give one like http://127.0.0.1:8000"
        )
    return urlunsplit((scheme, parts.netloc, parts.path.rstrip("/"), parts.query, ""))
