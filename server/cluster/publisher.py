"""One writer of a node's pub/sub messages: queued on the event loop, sent in batches.

``put`` never blocks (the frame path calls it from a batch's callback); one task sends what is
queued in one round trip, in order: one call of a Lua script that publishes them all
(``PUBLISH_MANY``, up to ``CHUNK`` messages a call), which costs the client one command and one
reply per batch instead of one of each per message (a pipeline of ``PUBLISH``). The queue is
bounded: when Redis falls behind, the oldest messages go (frames are replaced by newer ones
anyway), and while the broker is down everything is dropped (viewers on other nodes see a gap).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import deque
from collections.abc import Callable
from typing import Any

log = logging.getLogger(__name__)

#: Messages waiting to be published; beyond this the oldest are dropped.
MAX_QUEUED = 2048
#: Publishes ``ARGV``'s (channel, message) pairs in order; returns how many went out.
PUBLISH_MANY = (
    "for i = 1, #ARGV, 2 do redis.call('PUBLISH', ARGV[i], ARGV[i + 1]) end return #ARGV / 2"
)
#: Most messages one script call carries.
CHUNK = 64


class Publisher:
    """Publishes ``(channel, bytes)`` messages through ``redis`` (``redis.asyncio.Redis``).

    ``failed(exc)``: called when a batch fails (the broker is gone).
    """

    def __init__(self, redis: Any, failed: Callable[[BaseException], None]) -> None:
        self.redis = redis
        self._publish_many = redis.register_script(PUBLISH_MANY)  # EVALSHA, loaded on NOSCRIPT
        self._failed = failed
        self._queue: deque[tuple[str, bytes]] = deque(maxlen=MAX_QUEUED)
        self._wake = asyncio.Event()
        self._idle = asyncio.Event()  # nothing queued nor being sent
        self.enabled = False
        self._stopped = False
        self.dropped = 0
        self.sent = 0
        self._task: asyncio.Task[None] | None = None

    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._run())

    async def stop(self) -> None:
        self._stopped = True
        if self._task is not None:
            self._task.cancel()
            await asyncio.wait({self._task}, timeout=3.0)
            self._task = None

    def put(self, channel: str, data: bytes) -> None:
        if not self.enabled:
            self.dropped += 1
            return
        if len(self._queue) == MAX_QUEUED:
            self.dropped += 1
        self._queue.append((channel, data))
        self._idle.clear()
        self._wake.set()

    def clear(self) -> None:
        self.dropped += len(self._queue)
        self._queue.clear()

    async def flush(self, timeout: float = 2.0) -> None:
        """Wait (at most ``timeout`` s) until what is queued is sent."""
        if self._queue:
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self._idle.wait(), timeout)

    async def _run(self) -> None:
        from redis.exceptions import RedisError

        while not self._stopped:
            if not self._queue:
                self._idle.set()
                self._wake.clear()
                await self._wake.wait()
                continue
            batch = list(self._queue)
            self._queue.clear()
            try:
                for at in range(0, len(batch), CHUNK):
                    args = [x for pair in batch[at : at + CHUNK] for x in pair]
                    await self._publish_many(args=args)
                self.sent += len(batch)
            except (RedisError, OSError) as e:
                self.dropped += len(batch)
                self._failed(e)
            except asyncio.CancelledError:
                raise
            except Exception:  # never let the writer die
                log.exception("publishing %d cluster messages failed", len(batch))
