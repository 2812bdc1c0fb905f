"""Map ownership through leases in Redis, with a fencing token every write checks.

One owner per map at a time. The lease is a key taken with ``SET NX PX``; its holder
renews it (``PEXPIRE``, every third of the lease time) while it lives, and a holder
that stops renewing -- killed, or paused (``SIGSTOP``, a long GC, a frozen VM) -- loses
it when it expires, after which another instance may take it. Each taking increments
the map's fencing counter, and the lease's value carries the token it got, so an old
owner that wakes up after the map was taken holds a token that is no longer the map's.

Writes of a map go through :meth:`Leases.write`: ``WATCH`` the map's fencing counter,
check that the lease still holds this owner's token, then ``MULTI`` ... ``EXEC``. If
another instance took the map between the check and ``EXEC``, the counter changed and
``EXEC`` fails; if the check fails the write is refused before it starts. Either way
:class:`Fenced` is raised and nothing is written. Renewals touch only the lease key,
not the counter, so they never make a write retry. A lease that expired unrenewed (an
owner without a renewal thread, or one back from a pause) and that nobody took since --
the map's fencing counter still at the owner's token, so nobody else wrote -- is taken
again by the owner's next write, with a new token; one another owner took refuses it.

The acquisition, renewal and release are Lua scripts: each is a compare-and-set that
must be atomic (``GET``-then-``SET`` from Python would let two instances both believe
they took a map). Everything here is Redis's own atomicity; no clock of ours is trusted
beyond the lease time being much longer than a round trip.

Keys: ``hm:lease:{m}`` (STR "owner token", expires after the lease time unless renewed)
and ``hm:fence:{m}`` (the map's fencing counter), laid out in ``shared/store.py``.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass

import redis

from shared.store import k_fence, k_lease

log = logging.getLogger(__name__)


class Fenced(Exception):
    """This instance does not own the map (any more): the write was not made."""


# KEYS: lease, fence. ARGV: owner, lease ms. Returns the token (> 0) or 0 when another
# owner holds the lease. An owner asking again for a lease it holds keeps its token.
_ACQUIRE = """
local v = redis.call('GET', KEYS[1])
if v then
  local owner, token = string.match(v, '^(.*) (%d+)$')
  if owner == ARGV[1] then
    redis.call('PEXPIRE', KEYS[1], ARGV[2])
    return tonumber(token)
  end
  return 0
end
local token = redis.call('INCR', KEYS[2])
redis.call('SET', KEYS[1], ARGV[1] .. ' ' .. token, 'PX', ARGV[2])
return token
"""
# KEYS: lease, fence. ARGV: owner, lease ms, the token held. A lease that lapsed with
# nobody taking the map since (the counter still at the token) is taken again: nobody
# else wrote. Returns the new token, or 0.
_RETAKE = """
if redis.call('EXISTS', KEYS[1]) == 1 then return 0 end
if tonumber(redis.call('GET', KEYS[2]) or '0') ~= tonumber(ARGV[3]) then return 0 end
local token = redis.call('INCR', KEYS[2])
redis.call('SET', KEYS[1], ARGV[1] .. ' ' .. token, 'PX', ARGV[2])
return token
"""
# KEYS: lease. ARGV: "owner token", lease ms. 1 when renewed, 0 when it is not ours.
_RENEW = """
if redis.call('GET', KEYS[1]) == ARGV[1] then
  return redis.call('PEXPIRE', KEYS[1], ARGV[2])
end
return 0
"""
# KEYS: lease. ARGV: "owner token".
_RELEASE = """
if redis.call('GET', KEYS[1]) == ARGV[1] then
  return redis.call('DEL', KEYS[1])
end
return 0
"""


@dataclass
class LeaseStats:
    """Per instance, for its metrics."""

    acquired: int = 0  # maps taken that had no live owner (new, or a dead owner's)
    renewals: int = 0
    lost: int = 0  # leases found taken by another owner at renewal
    retaken: int = 0  # leases found lapsed at renewal, nobody having taken the map since
    released: int = 0  # hand-overs: leases given up on purpose
    refused_writes: int = 0


class Leases:
    """The leases one owner (a mapper instance) holds, and its fenced writes."""

    def __init__(self, r: redis.Redis, owner: str, lease_s: float = 3.0) -> None:
        if " " in owner:
            raise ValueError(f"owner {owner!r}: no spaces")
        self.r = r
        self.owner = owner
        self.lease_ms = max(int(lease_s * 1000), 10)
        self.tokens: dict[str, int] = {}  # map -> token of the lease this owner holds
        self.stats = LeaseStats()
        self._lock = threading.Lock()
        self._acquire = r.register_script(_ACQUIRE)
        self._renew = r.register_script(_RENEW)
        self._release = r.register_script(_RELEASE)
        self._retake = r.register_script(_RETAKE)

    def _value(self, map_id: str, token: int) -> str:
        return f"{self.owner} {token}"

    # --- ownership ---------------------------------------------------------------------
    def acquire(self, map_id: str) -> int | None:
        """Takes (or keeps) the map's lease; its token, or None when another owner
        holds it."""
        token = int(self._acquire(keys=[k_lease(map_id), k_fence(map_id)],
                                  args=[self.owner, self.lease_ms]))  # fmt: skip
        if token == 0:
            return None
        with self._lock:
            if self.tokens.get(map_id) != token:
                self.stats.acquired += 1
            self.tokens[map_id] = token
        return token

    def owner_of(self, map_id: str) -> tuple[str, int] | None:
        v = self.r.get(k_lease(map_id))
        if v is None:
            return None
        owner, _, token = v.decode().rpartition(" ")
        return owner, int(token)

    def renew(self) -> list[str]:
        """Renews every lease held; returns the maps whose lease was lost (expired and
        maybe taken by another owner), which this owner must stop serving."""
        with self._lock:
            held = dict(self.tokens)
        lost = []
        for map_id, token in held.items():
            ok = self._renew(keys=[k_lease(map_id)],
                             args=[self._value(map_id, token), self.lease_ms])  # fmt: skip
            if ok:
                self.stats.renewals += 1
                continue
            # Lapsed while this owner could not renew (its process starved of CPU, Redis
            # busy with a long command). In a 48-agent load test the only mapper dropped
            # the team's merged map this way, while it was building and writing 120-160
            # MB optimization copies of it; nobody else wanted the map, nobody took it
            # back within a minute, and 319 keyframes stayed unacknowledged. Nobody took
            # it since -- the fencing counter is still at this owner's token -- so it is
            # taken again, as a write would (``_current``); one another owner took is lost.
            new = int(self._retake(keys=[k_lease(map_id), k_fence(map_id)],
                                   args=[self.owner, self.lease_ms, token]))  # fmt: skip
            if new:
                with self._lock:
                    if self.tokens.get(map_id) == token:
                        self.tokens[map_id] = new
                self.stats.retaken += 1
                log.warning("lease of map %s lapsed unrenewed; nobody took it, taken again",
                            map_id)  # fmt: skip
            else:
                lost.append(map_id)
        if lost:
            with self._lock:
                for m in lost:
                    if self.tokens.get(m) == held[m]:
                        del self.tokens[m]
                self.stats.lost += len(lost)
            log.warning("leases lost: %s", ", ".join(lost))
        return lost

    def release(self, map_id: str) -> bool:
        """Gives the map up (a hand-over): another owner can take it at once."""
        with self._lock:
            token = self.tokens.pop(map_id, None)
        if token is None:
            return False
        ok = bool(self._release(keys=[k_lease(map_id)], args=[self._value(map_id, token)]))
        self.stats.released += ok
        return ok

    def held(self) -> list[str]:
        with self._lock:
            return sorted(self.tokens)

    # --- fenced writes -----------------------------------------------------------------
    def pipeline(self, map_id: str, *more: str) -> redis.client.Pipeline:
        """A transaction pipeline for writes of ``map_id`` (and of ``more`` maps, all
        held): the maps' fencing counters are watched and the leases checked now, so
        its ``execute()`` fails with ``redis.WatchError`` if another owner took one of
        them meanwhile; raises :class:`Fenced` if this owner holds them no longer."""
        maps = (map_id, *more)
        with self._lock:
            tokens = [self.tokens.get(m) for m in maps]
        if any(t is None for t in tokens):
            self.stats.refused_writes += 1
            raise Fenced(f"{self.owner} holds no lease on map(s) {', '.join(maps)}")
        n = len(maps)
        for attempt in range(2):
            p = self.r.pipeline(transaction=True)
            try:
                p.watch(*(k_fence(m) for m in maps))
                # Leases and fences in one round trip (this runs before every batch's
                # write: five round trips each were a tenth of the mapper's Redis time).
                vals = p.mget([k_lease(m) for m in maps] + [k_fence(m) for m in maps])
                if attempt == 0 and any(v is None for v in vals[:n]):
                    # A lease lapsed unrenewed: taken again if nobody took it (_current).
                    p.reset()
                    tokens = [self._current(m, t) for m, t in zip(maps, tokens, strict=True)]
                    continue
                for m, token, lv, fv in zip(maps, tokens, vals[:n], vals[n:], strict=True):
                    if lv != self._value(m, token).encode() or int(fv or 0) != token:
                        self.stats.refused_writes += 1
                        raise Fenced(f"map {m} is no longer {self.owner}'s (token {token})")
            except BaseException:
                p.reset()
                raise
            p.multi()
            return p
        raise AssertionError("unreachable")  # the second attempt returns or raises

    def _current(self, map_id: str, token: int) -> int:
        """The token to write with: a lease that lapsed unrenewed (an owner without a
        renewal thread, or one just back from a pause) and that nobody took since is
        taken again with a new token; otherwise the one held (checked next)."""
        if self.r.exists(k_lease(map_id)):
            return token
        new = int(self._retake(keys=[k_lease(map_id), k_fence(map_id)],
                               args=[self.owner, self.lease_ms, token]))  # fmt: skip
        if new == 0:
            return token
        with self._lock:
            if self.tokens.get(map_id) == token:
                self.tokens[map_id] = new
        return new

    def write(self, map_id: str, fill: Callable[[redis.client.Pipeline], None]) -> list:
        """Runs the writes ``fill`` queues on a pipeline as one transaction, only if this
        owner holds the map's lease; raises :class:`Fenced` otherwise (nothing written).
        ``fill`` may be called again (it must only queue commands)."""
        with self._lock:
            token = self.tokens.get(map_id)
        if token is None:
            self.stats.refused_writes += 1
            raise Fenced(f"{self.owner} holds no lease on map {map_id}")
        token = self._current(map_id, token)
        mine = self._value(map_id, token).encode()
        with self.r.pipeline(transaction=True) as p:
            p.watch(k_fence(map_id))
            if p.get(k_lease(map_id)) != mine or int(p.get(k_fence(map_id)) or 0) != token:
                p.unwatch()
                self.stats.refused_writes += 1
                raise Fenced(f"map {map_id} is no longer {self.owner}'s (token {token})")
            p.multi()
            fill(p)
            try:
                return p.execute()
            except redis.WatchError:
                self.stats.refused_writes += 1
                raise Fenced(f"map {map_id} was taken during a write of {self.owner}") from None
