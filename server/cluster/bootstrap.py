"""Before a node serves (``facecast serve --redis``): is Redis there, and which admin key to use.

Blocking (``redis``'s synchronous client), run once at start-up: an unreachable Redis is one
clear error (exit status 2), not a server that starts and then fails every request.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ..errors import LocalError
from . import keys
from .node import redacted


class BrokerUnreachable(LocalError):
    """The cluster's Redis does not answer."""

    status = 503


def connect(url: str, timeout: float = 3.0) -> Any:
    """A connected ``redis.Redis`` for ``url``; ``BrokerUnreachable`` if it does not answer PING."""
    import redis
    from redis.exceptions import RedisError

    try:
        r = redis.Redis.from_url(url, socket_timeout=timeout, socket_connect_timeout=timeout)
        r.ping()
    except (RedisError, OSError, ValueError) as e:
        raise BrokerUnreachable(
            f"cannot reach the cluster's Redis at {redacted(url)} ({e}); start it, or fix --redis "
            "/ FACECAST_REDIS_URL",
            where="--redis",
        ) from None
    return r


def admin_key(r: Any, configured: str | None, data_dir: Path) -> tuple[str, str]:
    """The admin key of this node and where it came from: ``"configured"`` (FACECAST_ADMIN_KEY;
    it becomes the cluster's if the cluster has none), ``"cluster"`` (the cluster's, adopted), or
    ``"generated"``/``"file"`` (this node's own, from ``data_dir/admin.key``, now the cluster's)."""
    from ..api.security import resolve_admin_key

    if configured:
        r.set(keys.ADMIN_KEY, configured, nx=True)
        return configured, "configured"
    shared = r.get(keys.ADMIN_KEY)
    if shared:
        return _keep(shared.decode(), data_dir), "cluster"
    key, generated = resolve_admin_key(None, data_dir)
    r.set(keys.ADMIN_KEY, key, nx=True)
    winner = r.get(keys.ADMIN_KEY)
    if winner and winner.decode() != key:  # another node was quicker
        return _keep(winner.decode(), data_dir), "cluster"
    return key, "generated" if generated else "file"


def _keep(key: str, data_dir: Path) -> str:
    """Keep the cluster's ``key`` in ``data_dir/admin.key`` (mode 0600), where a node keeps its own."""
    from ..output.atomic import write_bytes_atomic

    path = data_dir / "admin.key"
    if not path.exists() or path.read_text().strip() != key:
        data_dir.mkdir(parents=True, exist_ok=True)
        write_bytes_atomic(path, (key + "\n").encode(), mode=0o600)
    return key
