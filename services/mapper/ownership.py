"""Several mappers: which one owns each map, and which one serves each agent.

Each server map has one owning mapper at a time, through a lease in Redis with a
fencing token (``shared/leases.py``): the owner renews it every third of
``mapper.lease_s``, and every write of the map goes through a pipeline that checks the
token under ``WATCH`` (``Ownership.pipeline``), so a mapper paused past its lease and
resumed has its writes refused. A mapper whose renewal fails drops the map from its
registry at once (its queued batches are not acknowledged: the agents resend them to
the new owner).

How an agent's traffic reaches its map's owner: every mapper subscribes to every
agent's keys (``hivemap/agent/*/up/kf``) and each keeps the batches of the agents whose
map it owns, reading the agent id from the key and its session from the payload
(``shared.messages.peek_session``, a few microseconds) before decoding anything: the pair
names the flight, whose stored agent id is what owns a map (``sessions``), so the others'
batches cost a dictionary look-up (a flight not named yet is decoded first). Why not per-map key
expressions or a forwarding mapper: an agent learns its map id from its acks, and a
merge changes it, so an agent publishing per map would lose batches at every merge
until it heard the new id; forwarding would add a hop and a second copy of each batch
on the network. An agent's owner is known locally for the agents of local maps; for the
others it is read from Redis (the agent's map, then that map's lease) and cached for
half a second.

New agents go to the least-loaded mapper: each mapper publishes that it lives in
``hm:mappers`` every renewal, and the first mapper to see a new agent's batch assigns
it, in one Lua script, to the live mapper with the fewest agents assigned so far
(``hm:assigned``; ties to the lowest id) -- atomic, so a burst of new agents spreads
over the mappers instead of all going to whoever looked least loaded a second ago; the
others read the same assignment. The maps of a mapper that died are taken by the
least-loaded live mapper (fewest agents it serves, then maps), one map per renewal
round, and rebuilt from Redis.

Merges across owners: when a match names a map this mapper owns and one another owns,
the owner of the map with the smaller id asks for the other (``hm:handover:{m}``); its
owner drains the map's queued batches, releases the lease and drops the map; the asker
takes it, loads it from Redis and applies the match as if both had been its own.

Keys (``hm:mappers``, ``hm:assign``, ``hm:assigned``, ``hm:handover:{m}``; and
``shared/leases.py``'s): laid out in ``shared/store.py``.
"""

from __future__ import annotations

import json
import logging
import time

from shared.leases import Leases
from shared.store import K_ASSIGN, K_ASSIGNED, K_MAPPERS, Store, k_handover

log = logging.getLogger(__name__)

# KEYS: assign, assigned, mappers. ARGV: agent, now ms, live window ms.
_ASSIGN = """
local got = redis.call('HGET', KEYS[1], ARGV[1])
if got then return got end
local best, best_n = nil, nil
local all = redis.call('HGETALL', KEYS[3])
for i = 1, #all, 2 do
  local d = cjson.decode(all[i + 1])
  if tonumber(ARGV[2]) - d.t <= tonumber(ARGV[3]) then
    local n = tonumber(redis.call('HGET', KEYS[2], all[i]) or '0')
    if best == nil or n < best_n or (n == best_n and all[i] < best) then
      best, best_n = all[i], n
    end
  end
end
if best == nil then return false end
redis.call('HSET', KEYS[1], ARGV[1], best)
redis.call('HINCRBY', KEYS[2], best, 1)
return best
"""


class Ownership:
    def __init__(self, store: Store, instance: str, lease_s: float) -> None:
        self.r = store.r
        self.id = instance
        self.lease_s = lease_s
        self.leases = Leases(self.r, instance, lease_s)
        self._assign = self.r.register_script(_ASSIGN)
        self.handovers = 0  # maps given to another mapper
        self.takeovers = 0  # maps taken whose owner had stopped renewing

    def heartbeat(self, agents: int, maps: int) -> None:
        doc = {"t": int(time.time() * 1000), "agents": agents, "maps": maps}
        self.r.hset(K_MAPPERS, self.id, json.dumps(doc))

    def live(self) -> dict[str, dict]:
        """Mappers that said they were alive within a lease time (they say so every
        third of it), with their load: a dead one must drop out before its maps'
        leases expire, or it could look least loaded and nobody would take them."""
        now = time.time() * 1000
        out = {}
        for k, v in self.r.hgetall(K_MAPPERS).items():
            d = json.loads(v)
            if now - d["t"] <= 1000 * self.lease_s:
                out[k.decode()] = d
        return out

    def least_loaded(self) -> str:
        live = self.live()
        live.setdefault(self.id, {"agents": 0, "maps": 0})
        return min(live, key=lambda m: (live[m]["agents"], live[m]["maps"], m))

    def assign(self, agent: str) -> str | None:
        """The mapper a new agent goes to (assigned once, by whoever asks first)."""
        now_ms, live_ms = int(time.time() * 1000), int(1000 * self.lease_s)
        got = self._assign(keys=[K_ASSIGN, K_ASSIGNED, K_MAPPERS], args=[agent, now_ms, live_ms])
        return None if got is None else (got.decode() if isinstance(got, bytes) else got)

    def is_least_loaded(self) -> bool:
        return self.least_loaded() == self.id

    def owner(self, map_id: str) -> str | None:
        got = self.leases.owner_of(map_id)
        return None if got is None else got[0]

    def request_handover(self, map_id: str) -> None:
        self.r.set(k_handover(map_id), self.id, px=int(10_000 * self.lease_s))

    def handover_asked(self, map_id: str) -> str | None:
        v = self.r.get(k_handover(map_id))
        return None if v is None else v.decode()

    def handover_done(self, map_id: str) -> None:
        self.r.delete(k_handover(map_id))

    def pipeline(self, map_id: str, *more: str):
        return self.leases.pipeline(map_id, *more)
