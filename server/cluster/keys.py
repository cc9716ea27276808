"""Redis key and channel names of a cluster, and its timing (one place; ``docs/CLUSTER.md``)."""

from __future__ import annotations

#: Prefix of every key and channel facecast uses (a Redis database may hold other data).
PREFIX = "facecast:"

#: A session's lease lasts this long (ms) unless its owner renews it; failover follows its expiry.
LEASE_MS = 1000
#: The node's tick (s): renew leases, heartbeat, look for orphaned sessions, expire wants.
TICK_SECONDS = 0.2
#: A node's record lasts this long (ms) unless refreshed (every ``HEARTBEAT_SECONDS``).
NODE_TTL_MS = 3000
HEARTBEAT_SECONDS = 1.0
#: A node's wish for a session's encodings (``W``) lasts this long (s) unless repeated.
WANT_SECONDS = 3.0
#: A mirror with no viewer this long (s) is dropped (its subscription ends).
MIRROR_IDLE_SECONDS = 5.0

ADMIN_KEY = PREFIX + "admin_key"  #: the cluster's admin key (string)
SESSIONS = PREFIX + "sessions"  #: ids of the cluster's live sessions (set)


def node(node_id: str) -> str:
    """A node's record (JSON ``NodeRecord``, expires after ``NODE_TTL_MS``)."""
    return f"{PREFIX}node:{node_id}"


NODE_PATTERN = PREFIX + "node:*"


def session(sid: str) -> str:
    """A session's record (JSON ``SessionRecord``: face, settings, tokens)."""
    return f"{PREFIX}session:{sid}"


def lease(sid: str) -> str:
    """The id of the node owning a session (expires after ``LEASE_MS``)."""
    return f"{PREFIX}lease:{sid}"


def epoch(sid: str) -> str:
    """A session's owner generation: incremented at each take-over (integer)."""
    return f"{PREFIX}epoch:{sid}"


def stats(sid: str) -> str:
    """A session's counters as its owner last wrote them (JSON ``Stats``, every heartbeat)."""
    return f"{PREFIX}stats:{sid}"


def extras(sid: str) -> str:
    """What a session's owner adds to it while it runs, for a node that takes it over: scoped
    producer tokens and REST layers (JSON ``SessionExtras``, written at its owner's heartbeat)."""
    return f"{PREFIX}extras:{sid}"


def up(sid: str) -> str:
    """Channel to a session's owner: producer input forwarded, viewers' wishes, close requests."""
    return f"{PREFIX}up:{sid}"


def down(sid: str) -> str:
    """Channel from a session's owner: encoded frames, viewer texts, new owner, end."""
    return f"{PREFIX}down:{sid}"


def inbox(node_id: str) -> str:
    """Channel to one node: replies to the producers it forwards."""
    return f"{PREFIX}inbox:{node_id}"
