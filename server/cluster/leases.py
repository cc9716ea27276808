"""Session leases: one owner per session, decided atomically by Redis (Lua scripts).

A lease is ``lease:<id> = <node id>`` with a time to live of ``keys.LEASE_MS``. Taking one is
``SET NX PX`` and, in the same script, a new owner generation (``epoch:<id>``, incremented); the
owner renews all its leases in one call each tick; a node that finds a lease gone takes it. Two
nodes claiming one session: Redis runs one script at a time, so exactly one gets it.
"""

from __future__ import annotations

from typing import Any

from . import keys

#: KEYS: lease, epoch. ARGV: node, ttl ms, floor. Returns the new epoch (taken now), -1 (held by
#: this node already: renewed) or 0 (held by another node). ``floor``: the epoch this node last
#: knew (after Redis lost its data, generations keep growing).
ACQUIRE = """
if redis.call('SET', KEYS[1], ARGV[1], 'NX', 'PX', ARGV[2]) then
  local e = tonumber(redis.call('GET', KEYS[2]) or '0')
  local floor = tonumber(ARGV[3])
  if e < floor then redis.call('SET', KEYS[2], floor) end
  return redis.call('INCR', KEYS[2])
end
if redis.call('GET', KEYS[1]) == ARGV[1] then
  redis.call('PEXPIRE', KEYS[1], ARGV[2])
  return -1
end
return 0
"""

#: KEYS: leases. ARGV: node, ttl ms. Returns 1 per lease still this node's (renewed), else 0.
RENEW = """
local out = {}
for i, k in ipairs(KEYS) do
  if redis.call('GET', k) == ARGV[1] then
    redis.call('PEXPIRE', k, ARGV[2])
    out[i] = 1
  else
    out[i] = 0
  end
end
return out
"""

#: KEYS: lease. ARGV: node. Deletes the lease if this node holds it; 1 if it did.
RELEASE = """
if redis.call('GET', KEYS[1]) == ARGV[1] then return redis.call('DEL', KEYS[1]) end
return 0
"""


async def acquire(r: Any, sid: str, node: str, floor: int = 0, ttl_ms: int = keys.LEASE_MS) -> int:
    """Take (new epoch > 0) or renew (-1) the lease of ``sid`` for ``node``; 0 if another holds it."""
    return int(await r.eval(ACQUIRE, 2, keys.lease(sid), keys.epoch(sid), node, ttl_ms, floor))


async def renew(r: Any, sids: list[str], node: str, ttl_ms: int = keys.LEASE_MS) -> list[str]:
    """Renew ``node``'s leases of ``sids``; the ids whose lease it no longer holds."""
    if not sids:
        return []
    held = await r.eval(RENEW, len(sids), *(keys.lease(s) for s in sids), node, ttl_ms)
    return [s for s, ok in zip(sids, held) if not int(ok)]


async def release(r: Any, sid: str, node: str) -> bool:
    """Give up ``node``'s lease of ``sid`` now (another node may take it at once)."""
    return bool(await r.eval(RELEASE, 1, keys.lease(sid), node))


async def holders(r: Any, sids: list[str]) -> dict[str, str | None]:
    """The node holding each session's lease (None: nobody, the session is orphaned)."""
    if not sids:
        return {}
    values = await r.mget([keys.lease(s) for s in sids])
    return {s: (v.decode() if v is not None else None) for s, v in zip(sids, values)}
