"""This process as a node of a cluster: identity, heartbeat, leases, pub/sub, take-over.

One ``Cluster`` per app (``app.state.cluster``, made when ``ServerConfig.redis_url`` is set). It
owns the sessions created here and those it took over (``owned``: their leases renewed every tick,
their frames published for other nodes' viewers, producers connected elsewhere fed in through
``inbound``), mirrors sessions other nodes own for its own viewers (``mirrors``), forwards its
producers of such sessions (``forwards``), and every tick takes over sessions whose lease lapsed.
While Redis is unreachable the sessions owned here keep serving their local viewers; new sessions
are refused (503) and the node reconnects by itself, writing its sessions back (Redis may have
restarted empty). ``docs/CLUSTER.md`` has the design.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import os
import random
import secrets
import socket
import time
from collections.abc import Coroutine
from dataclasses import dataclass, field
from typing import Any

from ...protocol.encoding import VERTEX_ENCODINGS
from ...protocol.errors import CloseCode
from ...protocol.messages import SessionInfo, Stats
from .. import errors
from ..live.core import authorise, error_json
from ..live.registry import SessionRegistry
from ..live.session import LiveSession
from . import envelope, extras, keys, leases
from .inbound import RemoteProducer, close_body, close_reply
from .mirror import MirrorSession
from .publisher import Publisher
from .records import ClusterView, NodeRecord, NodeView, SessionRecord

log = logging.getLogger(__name__)

BROKER_DOWN = (
    "the cluster's Redis is unreachable; new live sessions are refused until it is back (the "
    "sessions running on this node keep serving its viewers)"
)
OWNER_GONE = (
    "the session's owner node is not reachable (the session may be moving to another node); "
    "connect again in a moment"
)


class Unavailable(errors.Unavailable):
    status = 503


def redacted(url: str) -> str:
    """A Redis URL without its password."""
    head, sep, tail = url.rpartition("@")
    if not sep:
        return url
    scheme, _, _ = head.partition("://")
    return f"{scheme}://***@{tail}"


@dataclass
class Owned:
    """A session this node owns."""

    session: LiveSession
    epoch: int
    wants: dict[str, tuple[frozenset[str], float]] = field(default_factory=dict)
    producers: dict[str, RemoteProducer] = field(default_factory=dict)
    extras: str = ""  #: its tokens and layers as last written to Redis (``extras.snapshot``)


class OwnerRelay:
    """Publishes an owned session's frames (the encodings other nodes want) and viewer texts."""

    __slots__ = ("channel", "cluster", "owned")

    def __init__(self, cluster: Cluster, owned: Owned) -> None:
        self.cluster, self.owned = cluster, owned
        self.channel = keys.down(owned.session.spec.id)

    def frame(self, seq: int, encoded: dict[str, tuple[Any, Any]]) -> None:
        put, epoch = self.cluster.publisher.put, self.owned.epoch
        for enc in self.owned.session.remote_encodings:
            f = encoded.get(enc)
            if f is not None:
                put(self.channel, envelope.frame(epoch, seq, enc, f[1]))

    def text(self, text: str) -> None:
        self.cluster.publisher.put(self.channel, envelope.TEXT + text.encode())


class Forward:
    """A producer connected to this node for a session ``owner`` owns."""

    def __init__(self, conn: str, sid: str, owner: str) -> None:
        self.conn, self.sid, self.owner = conn, sid, owner
        self.replies: asyncio.Queue[tuple[bytes, bytes]] = asyncio.Queue()

    def lose(self, message: str = OWNER_GONE) -> None:
        """The owner is gone: the producer is closed (4503) and reconnects."""
        err = error_json(CloseCode.UNAVAILABLE, message, fatal=True)
        self.replies.put_nowait((envelope.R_CLOSE, close_body(CloseCode.UNAVAILABLE, err)))


class Cluster:
    """This node. ``start()`` in the app's lifespan (raises ``Unavailable`` when Redis does not
    answer), ``stop()`` at its end (its sessions' leases are given up for others to take)."""

    def __init__(
        self,
        redis_url: str,
        registry: SessionRegistry,
        *,
        admin_key: str,
        url: str,
        readiness: dict[str, Any] | None = None,
    ) -> None:
        import redis.asyncio as aioredis

        self.id = secrets.token_hex(4)
        self.redis_url = redis_url
        self.redis: Any = aioredis.Redis.from_url(
            redis_url, socket_timeout=2.0, socket_connect_timeout=2.0
        )
        self.node_record = NodeRecord(
            id=self.id, url=url, host=socket.gethostname(), pid=os.getpid()
        )
        self.reg = registry
        self.admin_key = admin_key
        self.readiness = readiness if readiness is not None else {}
        self.up = False
        self.owned: dict[str, Owned] = {}
        self.mirrors: dict[str, MirrorSession] = {}
        self.forwards: dict[str, Forward] = {}
        self.publisher = Publisher(self.redis, self._down)
        self.takeovers = 0
        self._pubsub: Any = None
        self._reader: asyncio.Task[None] | None = None  # reads ``_pubsub``; one per connection
        self._tasks: list[asyncio.Task[None]] = []
        self._background: set[asyncio.Task[Any]] = set()
        self._adopting: set[str] = set()
        self._handoff: set[str] = set()
        self._last_beat = 0.0
        self._last_retry_log = 0.0
        self._stopping = False
        self._orphaned: list[Forward] = []  # forwards closed while Redis was unreachable
        registry.on_close = self._closed

    # -- life ---------------------------------------------------------------------------------------
    async def start(self) -> None:
        from redis.exceptions import RedisError

        try:
            await self.redis.ping()
        except (RedisError, OSError) as e:
            raise Unavailable(
                f"cannot reach Redis at {redacted(self.redis_url)} ({e}); start it or fix "
                "--redis / FACECAST_REDIS_URL"
            ) from None
        self.publisher.start()
        await self._connect()
        loop = asyncio.get_running_loop()
        self._tasks = [loop.create_task(self._ticks())]
        log.info("cluster node %s on %s", self.id, redacted(self.redis_url))

    async def stop(self) -> None:
        """Leave the cluster: other nodes take this node's sessions over at once."""
        self._stopping = True  # the loops end even if a client library swallows a cancellation
        tasks = [*self._tasks, *([self._reader] if self._reader is not None else [])]
        for t in tasks:
            t.cancel()
        if tasks:
            await asyncio.wait(tasks, timeout=3.0)
        self._handoff = set(self.owned)
        for o in self.owned.values():
            for p in list(o.producers.values()):
                await p.end(
                    CloseCode.UNAVAILABLE,
                    error_json(
                        CloseCode.UNAVAILABLE,
                        "this node is shutting down; connect again (another node takes over)",
                        fatal=True,
                    ),
                )
        for fwd in self.forwards.values():
            fwd.lose("this node is shutting down; connect again")
        if self.up:
            await self.publisher.flush()
            try:
                for sid in list(self.owned):
                    await leases.release(self.redis, sid, self.id)
                await self.redis.delete(keys.node(self.id))
            except Exception:  # leaving anyway; leases expire by themselves
                log.warning("could not give up this node's leases", exc_info=True)
        await self.publisher.stop()
        await self._close_pubsub()
        await self.redis.aclose()

    async def _close_pubsub(self) -> None:
        ps, self._pubsub = self._pubsub, None
        await self._close(ps, self._stop_reader())

    def _stop_reader(self) -> asyncio.Task[None] | None:
        """Stop reading the pub/sub connection (the reader, to wait for; None if none or this is
        it). Its read is cancelled before the connection is closed: a closed pub/sub gives its
        connection back to the pool, where the next one must not find a read still waiting."""
        reader, self._reader = self._reader, None
        if reader is None or reader is asyncio.current_task():
            return None
        reader.cancel()
        return reader

    @staticmethod
    async def _close(ps: Any, reader: asyncio.Task[None] | None = None) -> None:
        """Close a pub/sub connection once ``reader`` has stopped (at most 2 s each: the peer may
        be gone)."""
        if reader is not None:
            await asyncio.wait({reader}, timeout=2.0)
        if ps is not None:
            try:
                await asyncio.wait_for(ps.aclose(), 2.0)
            except Exception:  # noqa: BLE001 - the connection is gone already
                pass

    async def _connect(self) -> None:
        """(Re)join: subscribe, announce this node, share the admin key, write back owned sessions."""
        await self._close_pubsub()
        # idle pooled connections may point at a Redis that restarted: the next command would
        # find one closed and take the broker for lost again (a second 503 just after rejoining)
        await self.redis.connection_pool.disconnect(inuse_connections=False)
        ps = self.redis.pubsub()
        channels = [keys.inbox(self.id)]
        channels += [keys.up(s) for s in self.owned] + [keys.down(s) for s in self.mirrors]
        await ps.subscribe(*channels)
        self._pubsub = ps
        self._stop_reader()
        self._reader = asyncio.get_running_loop().create_task(self._read(ps))
        await self._beat()
        await self.redis.set(keys.ADMIN_KEY, self.admin_key, nx=True)
        for o in list(self.owned.values()):
            await self._reclaim(o)
        self.up = True
        self.publisher.enabled = True
        if self.readiness.pop("broker_error", None) is not None:
            log.warning("cluster: Redis is back; node %s rejoined", self.id)
        for m in self.mirrors.values():
            self._wants(m, True)
        for fwd in self._orphaned:  # closed while Redis was away: free their producer slots
            self.forward(fwd, envelope.P_GONE)
        self._orphaned.clear()

    def _down(self, exc: BaseException) -> None:
        """Redis failed: keep serving local viewers, refuse new sessions, reconnect later."""
        if not self.up:
            return
        self.up = False
        self.publisher.enabled = False
        self.publisher.clear()
        self.readiness["broker_error"] = f"{BROKER_DOWN} ({type(exc).__name__}: {exc})"
        log.warning("cluster: lost Redis (%s); reconnecting", exc)
        for fwd in list(self.forwards.values()):
            fwd.lose()
            self._orphaned.append(fwd)  # its owner hears it is gone once Redis is back
        for o in self.owned.values():  # producers on other nodes: those nodes close them too
            for p in o.producers.values():
                p.stop()
            o.producers.clear()
        ps, self._pubsub = self._pubsub, None  # this one, not the next connection's
        self._spawn(self._close(ps, self._stop_reader()))

    def _spawn(self, coro: Coroutine[Any, Any, Any]) -> None:
        """Run ``coro`` in the background (kept referenced until done)."""
        task = asyncio.get_running_loop().create_task(coro)
        self._background.add(task)
        task.add_done_callback(self._background.discard)

    def require(self) -> None:
        """Raise ``Unavailable`` (503) while Redis is unreachable."""
        if not self.up:
            raise Unavailable(BROKER_DOWN)

    async def _beat(self) -> None:
        await self.redis.set(
            keys.node(self.id), self.node_record.model_dump_json(), px=keys.NODE_TTL_MS
        )
        self._last_beat = time.monotonic()

    # -- the tick -----------------------------------------------------------------------------------
    async def _ticks(self) -> None:
        from redis.exceptions import RedisError

        while not self._stopping:
            await asyncio.sleep(keys.TICK_SECONDS)
            try:
                if not self.up:
                    await self.redis.ping()
                    await asyncio.wait_for(self._connect(), 10.0)
                else:
                    await self._tick()
            except (RedisError, OSError, asyncio.TimeoutError) as e:
                if not self.up and time.monotonic() - self._last_retry_log >= 10:
                    self._last_retry_log = time.monotonic()
                    log.warning("cluster: Redis still unreachable (%s)", e)
                self._down(e)
            except asyncio.CancelledError:
                raise
            except Exception:  # never let the tick die
                log.exception("cluster tick")

    async def _tick(self) -> None:
        now = time.monotonic()
        for sid in await leases.renew(self.redis, [*self.owned, *self._adopting], self.id):
            if sid in self.owned:
                await self._demote(sid)
        if now - self._last_beat >= keys.HEARTBEAT_SECONDS:
            await self._beat()
            await self._heartbeat_peers(now)
        for o in self.owned.values():
            if any(until < now for _, until in o.wants.values()):
                o.wants = {n: w for n, w in o.wants.items() if w[1] >= now}
                self._update_wants(o)
            elif o.session.remote_encodings:
                o.session.last_active = now
        if self.forwards:
            sids = sorted({f.sid for f in self.forwards.values()})
            held = await leases.holders(self.redis, sids)
            for fwd in list(self.forwards.values()):
                if held.get(fwd.sid) != fwd.owner:
                    self.forwards.pop(fwd.conn, None)
                    fwd.lose()
        await self._take_orphans()

    async def _heartbeat_peers(self, now: float) -> None:
        """Once a second: repeat mirrors' wishes, drop idle mirrors, free the producer slots of
        nodes that died."""
        for sid, m in list(self.mirrors.items()):
            if m.idle(now, keys.MIRROR_IDLE_SECONDS):
                del self.mirrors[sid]
                await self._unsubscribe(keys.down(sid))
            elif m.viewers:
                self._wants(m, False)
        if self.owned:
            pipe = self.redis.pipeline(transaction=False)
            for sid, o in self.owned.items():
                snap = o.session.snapshot().model_dump_json()
                pipe.set(keys.stats(sid), snap, px=keys.NODE_TTL_MS)
                more = extras.snapshot(o.session)
                if more != o.extras:  # scoped tokens or REST layers changed: for a takeover
                    pipe.set(keys.extras(sid), more)
                    o.extras = more
            await pipe.execute()
        nodes = {p.node for o in self.owned.values() for p in o.producers.values()}
        if nodes:
            alive = await self.redis.mget([keys.node(n) for n in sorted(nodes)])
            dead = {n for n, v in zip(sorted(nodes), alive) if v is None}
            for o in self.owned.values():
                for conn, p in list(o.producers.items()):
                    if p.done or p.node in dead:
                        p.stop()
                        del o.producers[conn]

    # -- owning -------------------------------------------------------------------------------------
    async def register(self, session: LiveSession) -> None:
        """A session created here: share its record and take its lease."""
        from redis.exceptions import RedisError

        self.require()
        sid = session.spec.id
        try:
            epoch = await leases.acquire(self.redis, sid, self.id)
            await self.redis.set(
                keys.session(sid),
                SessionRecord.of(session.spec, session.vertex_count).model_dump_json(),
            )
            await self.redis.sadd(keys.SESSIONS, sid)
            await self._own(session, max(epoch, 1))
        except (RedisError, OSError) as e:
            self._down(e)
            raise Unavailable(BROKER_DOWN) from None

    async def _own(self, session: LiveSession, epoch: int) -> None:
        sid = session.spec.id
        o = self.owned[sid] = Owned(session, epoch)
        session.relay = OwnerRelay(self, o)
        if session.compact is not None:
            session.compact.request_key()
        await self._subscribe(keys.up(sid))
        self.publisher.put(
            keys.down(sid), envelope.with_json(envelope.OWNER, {"epoch": epoch, "node": self.id})
        )

    async def _reclaim(self, o: Owned) -> None:
        """After Redis came back: write the session back and keep (or lose) its lease."""
        spec = o.session.spec
        epoch = await leases.acquire(self.redis, spec.id, self.id, floor=o.epoch)
        if epoch == 0:
            await self._demote(spec.id)
            return
        await self.redis.set(
            keys.session(spec.id), SessionRecord.of(spec, o.session.vertex_count).model_dump_json()
        )
        await self.redis.sadd(keys.SESSIONS, spec.id)
        if epoch > 0:
            o.epoch = epoch
            o.extras = ""  # Redis may have restarted empty: written again at the next heartbeat
            if o.session.compact is not None:
                o.session.compact.request_key()
            self.publisher.put(
                keys.down(spec.id),
                envelope.with_json(envelope.OWNER, {"epoch": epoch, "node": self.id}),
            )

    async def _demote(self, sid: str) -> None:
        """Another node holds the lease now: end the session here; its peers reconnect there."""
        log.warning("cluster: node %s lost the lease of session %s", self.id, sid)
        self._handoff.add(sid)
        if sid in self.reg.sessions:
            await self.reg.close(
                sid, "this node lost the session to another node; connect again to continue"
            )

    def _closed(self, session: LiveSession) -> None:
        """The registry closed a session (admin, idle, shutdown, demotion)."""
        sid = session.spec.id
        o = self.owned.pop(sid, None)
        session.relay = None
        if o is None:
            return
        self._spawn(self._unsubscribe(keys.up(sid)))
        if sid in self._handoff:
            self._handoff.discard(sid)
            return
        self._spawn(self._forget(sid))

    async def _forget(self, sid: str) -> None:
        """A session closed for good: tell mirrors, remove it from Redis."""
        end = error_json(CloseCode.SESSION_CLOSED, "the session was closed", fatal=True)
        self.publisher.put(
            keys.down(sid),
            envelope.with_json(envelope.END, {"code": int(CloseCode.SESSION_CLOSED), "error": end}),
        )
        if not self.up:
            return
        try:
            await self.publisher.flush()
            await self.redis.delete(
                keys.session(sid), keys.epoch(sid), keys.stats(sid), keys.extras(sid)
            )
            await self.redis.srem(keys.SESSIONS, sid)
            await leases.release(self.redis, sid, self.id)
        except Exception as e:  # noqa: BLE001 - the broker went away; nodes drop it on their own
            log.warning("cluster: could not remove session %s from Redis: %s", sid, e)

    def _update_wants(self, o: Owned, key: bool = False) -> None:
        encs = frozenset(e for w, _ in o.wants.values() for e in w)
        o.session.set_remote_encodings(encs, key)
        if encs:  # viewers on other nodes: the session is in use (idle expiry)
            o.session.last_active = time.monotonic()

    # -- taking over --------------------------------------------------------------------------------
    async def _take_orphans(self) -> None:
        sids = [s.decode() for s in await self.redis.smembers(keys.SESSIONS)]
        candidates = [s for s in sids if s not in self.owned and s not in self._adopting]
        held = await leases.holders(self.redis, candidates)
        orphans = [s for s, h in held.items() if h is None]
        if not orphans:
            return
        nodes = len([k async for k in self.redis.scan_iter(match=keys.NODE_PATTERN, count=100)])
        random.shuffle(orphans)
        for sid in orphans[: max(1, math.ceil(len(orphans) / max(1, nodes)))]:
            epoch = await leases.acquire(self.redis, sid, self.id)
            if epoch > 0:
                self._adopting.add(sid)
                self._spawn(self._adopt(sid, epoch))

    async def _adopt(self, sid: str, epoch: int) -> None:
        """This node took the lease of ``sid``: open the session from its record."""
        mirror: MirrorSession | None = None
        try:
            raw = await self.redis.get(keys.session(sid))
            if raw is None:
                await self.redis.srem(keys.SESSIONS, sid)
                await leases.release(self.redis, sid, self.id)
                return
            rec = SessionRecord.model_validate_json(raw)
            more = await self.redis.get(keys.extras(sid))
            mirror = self.mirrors.pop(sid, None)
            if mirror is not None:
                mirror.promote()
                await self._unsubscribe(keys.down(sid))
            session = await self.reg.restore(rec.spec(), mirror)
            session.seq = (epoch << 20) & 0xFFFFFFFF  # never a seq an old owner's key frame had
            self.takeovers += 1
            extras.restore(session, more)  # its scoped tokens and REST layers
            await self._own(session, epoch)
            self.owned[sid].extras = extras.snapshot(session)
            log.warning("cluster: node %s took over session %s (epoch %d)", self.id, sid, epoch)
        except Exception:  # e.g. a face only another node has: let another try
            log.exception("cluster: taking over session %s failed", sid)
            if mirror is not None:
                mirror.owned = False
                self.mirrors[sid] = mirror
                await self._subscribe(keys.down(sid))
            try:
                await leases.release(self.redis, sid, self.id)
            except Exception:  # noqa: BLE001 - the lease expires by itself
                pass
        finally:
            self._adopting.discard(sid)

    # -- other nodes' sessions ----------------------------------------------------------------------
    async def record(self, sid: str) -> SessionRecord | None:
        """The cluster's record of ``sid`` (None: no such session); 503 while Redis is down."""
        from redis.exceptions import RedisError

        self.require()
        try:
            raw = await self.redis.get(keys.session(sid))
        except (RedisError, OSError) as e:
            self._down(e)
            raise Unavailable(BROKER_DOWN) from None
        return None if raw is None else SessionRecord.model_validate_json(raw)

    async def mirror(self, sid: str) -> LiveSession | None:
        """This node's copy of session ``sid`` owned elsewhere, for viewers (None: no session)."""
        m = self.mirrors.get(sid)
        if m is not None:
            return m
        rec = await self.record(sid)
        if rec is None:
            return None
        loop = asyncio.get_running_loop()
        face = await loop.run_in_executor(self.reg.executor, self.reg.store.face, rec.face)
        local = self.reg.sessions.get(sid) or self.mirrors.get(sid)
        if local is not None:  # taken over or mirrored meanwhile
            return local
        m = self.mirrors[sid] = MirrorSession(rec.spec(), face, self._wants, self.reg.metrics)
        await self._subscribe(keys.down(sid))
        return m

    async def infos(self, sids: list[str] | None = None) -> list[SessionInfo]:
        """``SessionInfo`` of the cluster's sessions (``sids``, default all), with the counters
        their owners last wrote (zeros when none did yet)."""
        from redis.exceptions import RedisError

        self.require()
        try:
            if sids is None:
                sids = sorted(s.decode() for s in await self.redis.smembers(keys.SESSIONS))
            if not sids:
                return []
            recs = await self.redis.mget([keys.session(s) for s in sids])
            stats = await self.redis.mget([keys.stats(s) for s in sids])
        except (RedisError, OSError) as e:
            self._down(e)
            raise Unavailable(BROKER_DOWN) from None
        return [
            SessionRecord.model_validate_json(r).info(
                Stats.model_validate_json(st) if st is not None else Stats()
            )
            for r, st in zip(recs, stats)
            if r is not None
        ]

    def _wants(self, m: MirrorSession, key: bool) -> None:
        body = {"node": self.id, "encodings": sorted(m.encodings()), "key": key}
        self.publisher.put(keys.up(m.spec.id), envelope.with_json(envelope.WANT, body))

    async def forward_open(self, sid: str, token: str | None) -> Forward | None:
        """Start forwarding a producer of ``sid`` (its ``token``) to the owner, which authorises
        it; None when no owner listens."""
        from redis.exceptions import RedisError

        self.require()
        conn = secrets.token_hex(envelope.CONN_LEN // 2)
        try:
            owner = (await leases.holders(self.redis, [sid]))[sid]
            if owner is None or owner == self.id:
                return None
            fwd = self.forwards[conn] = Forward(conn, sid, owner)
            body = json.dumps({"node": self.id, "token": token}).encode()
            opened = envelope.producer(conn, envelope.OPEN, body)
            if await self.redis.publish(keys.up(sid), opened) == 0:
                del self.forwards[conn]
                return None
        except (RedisError, OSError) as e:
            self.forwards.pop(conn, None)
            self._down(e)
            raise Unavailable(BROKER_DOWN) from None
        return fwd

    def forward(self, fwd: Forward, kind: bytes, body: bytes = b"") -> None:
        self.publisher.put(keys.up(fwd.sid), envelope.producer(fwd.conn, kind, body))

    def forward_done(self, fwd: Forward, gone: bool) -> None:
        """The forwarded connection ended (``gone``: the producer left, tell the owner)."""
        if self.forwards.pop(fwd.conn, None) is not None and gone:
            self.forward(fwd, envelope.P_GONE)

    async def close_remote(self, sid: str, reason: str) -> None:
        """Close a session another node owns (``NotFound`` if there is none)."""
        if await self.record(sid) is None:
            raise errors.NotFound(f"no live session {sid!r}", where="session")
        ask = envelope.with_json(envelope.CLOSE, {"reason": reason})
        if await self.redis.publish(keys.up(sid), ask) == 0:  # no owner now: remove it here
            await self._forget(sid)

    # -- pub/sub ------------------------------------------------------------------------------------
    async def _subscribe(self, channel: str) -> None:
        if self._pubsub is not None:
            await self._pubsub.subscribe(channel)

    async def _unsubscribe(self, channel: str) -> None:
        if self._pubsub is not None:
            try:
                await self._pubsub.unsubscribe(channel)
            except Exception as e:  # noqa: BLE001 - the broker is gone; resubscribing skips it
                self._down(e)

    async def _read(self, ps: Any) -> None:
        """Read pub/sub connection ``ps`` until it is replaced or fails (then the broker is down).

        Each read blocks until a message comes: no timer per message. ``_connect`` starts a new
        reader for each new connection and cancels the old one, so a connection the client library
        reconnected by itself is never read beside its successor."""
        while not self._stopping and ps is self._pubsub:
            try:
                msg = await ps.get_message(ignore_subscribe_messages=True, timeout=None)
            except asyncio.CancelledError:
                raise
            except Exception as e:  # noqa: BLE001 - RedisError, OSError, closed under us...
                if ps is self._pubsub:
                    self._down(e)
                return
            if msg is None or msg.get("type") != "message":
                continue
            try:
                self._dispatch(msg["channel"].decode(), msg["data"])
            except Exception:  # one bad message must not stop the node
                log.exception("cluster: a message on %s could not be handled", msg["channel"])

    def _dispatch(self, channel: str, data: bytes) -> None:
        kind, _, sid = channel[len(keys.PREFIX) :].partition(":")
        if kind == "down":
            m = self.mirrors.get(sid)
            if m is not None and not m.receive(data):
                self.mirrors.pop(sid, None)
                self._spawn(self._unsubscribe(channel))
        elif kind == "up":
            self._on_up(sid, data)
        elif kind == "inbox" and data[:1] == envelope.REPLY:
            conn, k, body = envelope.parse_conn(data)
            fwd = self.forwards.get(conn)
            if fwd is not None:
                fwd.replies.put_nowait((k, body))

    def _on_up(self, sid: str, data: bytes) -> None:
        o = self.owned.get(sid)
        if o is None:
            return
        kind = data[:1]
        if kind == envelope.PRODUCER:
            conn, k, body = envelope.parse_conn(data)
            if k == envelope.OPEN:
                opened = json.loads(body)
                node, token = str(opened["node"]), opened.get("token")
                inbox = keys.inbox(node)
                send = lambda b: self.publisher.put(inbox, b)  # noqa: E731
                spec = o.session.spec
                roles = o.session.grants.roles_of(token)  # the full token, or a scoped one
                mine = (token or "") if roles else spec.producer_token
                refusal = authorise(sid, True, token, mine, spec.viewer_token, "producer")
                if refusal is not None:
                    send(envelope.reply(conn, envelope.R_CLOSE, close_reply(refusal)))
                    return
                p = RemoteProducer(self.reg, o.session, conn, node, send, roles or frozenset())
                if p.start():
                    o.producers[conn] = p
            else:
                p2 = o.producers.get(conn)
                if p2 is not None:
                    p2.feed(k, body)
        elif kind == envelope.WANT:
            w = envelope.parse_json(data)
            encs = frozenset(e for e in w.get("encodings", ()) if e in VERTEX_ENCODINGS)
            new = str(w["node"]) not in o.wants
            o.wants[str(w["node"])] = (encs, time.monotonic() + keys.WANT_SECONDS)
            self._update_wants(o, bool(w.get("key")))
            if new:  # a node's first viewers: tell them whether a producer is connected
                o.session.broadcast_status()
        elif kind == envelope.CLOSE:
            reason = str(envelope.parse_json(data).get("reason") or "the session was closed")
            self._spawn(self.reg.close(sid, reason))

    # -- GET /v1/cluster ----------------------------------------------------------------------------
    async def view(self) -> ClusterView:
        """The nodes with the sessions each owns, from Redis (503 while it is down)."""
        from redis.exceptions import RedisError

        self.require()
        try:
            names = [k async for k in self.redis.scan_iter(match=keys.NODE_PATTERN, count=100)]
            raw = await self.redis.mget(names) if names else []
            sids = sorted(s.decode() for s in await self.redis.smembers(keys.SESSIONS))
            held = await leases.holders(self.redis, sids)
        except (RedisError, OSError) as e:
            self._down(e)
            raise Unavailable(BROKER_DOWN) from None
        nodes = [NodeRecord.model_validate_json(r) for r in raw if r is not None]
        if not any(n.id == self.id for n in nodes):
            nodes.append(self.node_record)
        owns: dict[str, list[str]] = {}
        for sid, h in held.items():
            if h is not None:
                owns.setdefault(h, []).append(sid)
        views = [
            NodeView(**n.model_dump(), sessions=owns.get(n.id, []), is_self=n.id == self.id)
            for n in sorted(nodes, key=lambda n: n.started)
        ]
        orphans = [s for s, h in held.items() if h is None]
        return ClusterView(self_id=self.id, broker="up", nodes=views, orphans=orphans)

    def gauges(self) -> dict[str, float]:
        """Per-node numbers for ``/metrics``."""
        return {
            "sessions_owned": float(len(self.owned)),
            "sessions_mirrored": float(len(self.mirrors)),
            "producers_forwarded": float(len(self.forwards)),
            "broker_up": 1.0 if self.up else 0.0,
            "takeovers": float(self.takeovers),
            "messages_published": float(self.publisher.sent),
            "messages_dropped": float(self.publisher.dropped),
        }
