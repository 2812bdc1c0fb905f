"""Flights: which stored agent id each flight of an agent id is.

An agent numbers its keyframes and map points from 0 in every flight (they are its own
small integers, ``shared/ids.py``). An agent id flown again against the same Redis (the
data directory ``hivemap up`` keeps by default) would send the ids of its first flight
again, and the mapper took the second flight's keyframes for resends of the first:
acknowledged as duplicates and dropped, the new flight's map lost without a word.

So every agent process draws a random session id when it starts and sends it in each
keyframe batch and pose (``KeyframeBatch.session``). A session the mapper has not seen
is a new flight: it is named once, in Redis, by a Lua script (atomic across mappers;
``Store.flight``), and stored under its own agent id -- the agent id itself for its
first flight, ``{agent}.s2``, ``{agent}.s3``, ... for later ones. To the server a new
flight is a new agent: its own agent index (so its own keyframe and point gids), its own
handler and map, which place recognition merges with the earlier flights' maps where they
overlap, as CCM-SLAM treats a new session. A resend within a flight carries the same
session, so it reaches the same handler and is deduplicated as before; a mapper that
restarts (``kill -9``, resume from Redis) reads the same name back, so an agent in
flight goes on in its flight. Acks and map chunks still go to the id the agent flies
as (the handler's ``name``); keyframes and points of its earlier flights reach it in
map chunks as another agent's.

Batches without a session (agents of the first wire version) are stored under the
agent id, as before. The REST API lists each flight as an agent with its ``name`` and
``flight`` number.
"""

from __future__ import annotations

import logging
import threading

from shared import keys
from shared.store import Store

log = logging.getLogger(__name__)


class Flights:
    def __init__(self, store: Store) -> None:
        self.store = store
        self._names: dict[tuple[str, int], str] = {}
        self._lock = threading.Lock()

    def known(self, agent: str, session: int | None) -> str | None:
        """The stored agent id of this flight if it is named already (a dictionary
        look-up, then one Redis read per new flight); ``agent`` for no session."""
        if session is None:
            return agent
        got = self._names.get((agent, session))
        if got is None:
            try:
                keys.check_id(agent, "agent")
            except ValueError:
                return None  # the decode rejects it
            got = self.store.flight_of(agent, session)
            if got is not None:
                with self._lock:
                    self._names[(agent, session)] = got
        return got

    def name(self, agent: str, session: int | None) -> str:
        """The stored agent id of this flight, named now if it is new (call it with a
        decoded batch only: garbage must not name flights)."""
        got = self.known(agent, session)
        if got is not None:
            return got
        got = self.store.flight(agent, session)
        with self._lock:
            self._names[(agent, session)] = got
        if got != agent:
            log.info("agent %s: a new flight (session %d), stored as agent %s", agent, session,
                     got, extra={"agent": agent})  # fmt: skip
        return got
