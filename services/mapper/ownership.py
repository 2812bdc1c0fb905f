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
map it owns, reading the agent id from the key before decoding anything (a per-agent
key expression, so the others' batches cost a dictionary look-up). Why not per-map key
expressions or a forwarding mapper: an agent learns its map id from its acks, and a
merge changes it, so an agent publishing per map would lose batches at every merge
until it heard the new id; forwarding would add a hop and a second copy of each batch
on the network. An agent's owner is known locally for the agents of local maps; for the
others it is read from Redis (the agent's map, then that map's lease) and cached for
half a second.

New agents go to the least-loaded mapper: each mapper publishes its load (agents and
maps it serves) in ``hm:mappers`` every renewal, and a mapper takes a new agent only
when it is the least loaded of the live ones (fewest agents, then fewest maps, then
lowest id); two that both think so race for the new map's lease, and the loser drops
the batch (the agent resends it to the winner). The same rule takes over the maps of
a mapper that died: a map whose lease expired is taken by the least-loaded live mapper,
one map per renewal round, and rebuilt from Redis.

Merges across owners: when a match names a map this mapper owns and one another owns,
the owner of the map with the smaller id asks for the other (``hm:handover:{m}``); its
owner drains the map's queued batches, releases the lease and drops the map; the asker
takes it, loads it from Redis and applies the match as if both had been its own.

Keys (beside ``shared/leases.py``'s ``hm:lease:{m}``, ``hm:fence:{m}``):

    hm:mappers        HASH  mapper id -> JSON {t: unix ms, agents, maps}: live mappers
                            and their load, rewritten every renewal
    hm:handover:{m}   STR   the mapper id that asked for map m; expires after 10 leases
"""

from __future__ import annotations

import json
import logging
import time

from shared.leases import Leases
from shared.store import Store

log = logging.getLogger(__name__)

K_MAPPERS = "hm:mappers"


def k_handover(map_id: str) -> str:
    return f"hm:handover:{map_id}"


class Ownership:
    def __init__(self, store: Store, instance: str, lease_s: float) -> None:
        self.r = store.r
        self.id = instance
        self.lease_s = lease_s
        self.leases = Leases(self.r, instance, lease_s)
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
