"""The one owner of the mapper's state (COVINS's map manager is the model).

:class:`MapRegistry` alone holds the server maps, the agent handlers (indexed by the
map they register into), one actor per map (its thread and lock), the merge chains
between map ids, the fused-point aliases and the agent names. Everything else asks it:
the service's dispatch, collaboration (merges, loops, corrections), persistence and
feedback get maps, handlers and locks from here, and only :meth:`MapRegistry.merge`
re-points agents from one map to another.

Locks: :meth:`lock` takes the actors' locks of several maps in map-id order, so two
merges never deadlock. Merge chains: a map merged into another keeps resolving to the
survivor (:meth:`resolve`, built on ``shared.ids.resolve_map`` which place recognition
uses too).

Maps other processes own: today this process holds every map it has heard of. A map is
*local* when it is in :attr:`maps`; :meth:`resolve` and :meth:`is_local` are the two
questions callers ask about a map id, so an ownership lease per map (a Redis key with a
TTL the owning mapper renews) attaches here: :meth:`is_local` would check the lease,
and a batch for a map held elsewhere would be forwarded instead of queued.
"""

from __future__ import annotations

import contextlib
import queue
import threading
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING

from shared.geometry import Sim3
from shared.ids import resolve_map, resolve_map_scale

from .registration import AgentHandler
from .server_map import ServerMap

if TYPE_CHECKING:
    from .service import MapActor


class Backlog:
    """Keyframe batches queued on all map actors together: a count kept by the actors'
    queues (:class:`BatchQueue`), and a condition to sleep on until it is zero. Asked
    for between every step of background work; polling every actor's queue size every
    2 ms instead took a tenth of the mapper's samples at 16 agents."""

    def __init__(self) -> None:
        self._n = 0
        self._cv = threading.Condition(threading.Lock())

    def add(self, d: int) -> None:
        with self._cv:
            self._n += d
            if self._n <= 0:
                self._n = 0
                self._cv.notify_all()

    def __bool__(self) -> bool:
        return self._n > 0

    def wait_clear(self, timeout: float) -> bool:
        """Sleeps until no batch is queued, at most ``timeout`` seconds; True if none is."""
        with self._cv:
            return self._cv.wait_for(lambda: self._n <= 0, timeout)


class BatchQueue(queue.Queue):
    """A map actor's queue of keyframe batches, counted in the registry's backlog."""

    def __init__(self, backlog: Backlog) -> None:
        super().__init__()
        self._backlog = backlog

    def _put(self, item) -> None:  # under the queue's mutex, as queue.Queue calls it
        super()._put(item)
        self._backlog.add(1)

    def _get(self):
        item = super()._get()
        self._backlog.add(-1)
        return item


class MapRegistry:
    def __init__(self, make_actor: Callable[[ServerMap], MapActor]) -> None:
        self._make_actor = make_actor
        self.backlog = Backlog()
        self.maps: dict[str, ServerMap] = {}
        self._handlers: dict[str, AgentHandler] = {}
        self._by_map: dict[str, set[str]] = {}  # map id -> agents registering into it
        self.actors: dict[str, MapActor] = {}
        self.merged_into: dict[str, str] = {}
        # map -> the scale its merge applied (from the store after a restart; unknown
        # for merges stored before scales were)
        self.merge_scale: dict[str, float] = {}
        self.aliases: dict[int, int] = {}  # fused point gid -> surviving gid (every handler's)
        self.names: dict[int, str] = {}  # agent index -> agent id
        self._lock = threading.Lock()

    # --- maps --------------------------------------------------------------------------
    def resolve(self, map_id: str) -> str:
        """The map ``map_id`` lives on as, following merges."""
        return resolve_map(self.merged_into, map_id)

    def resolve_scale(self, map_id: str) -> tuple[str, float | None]:
        """:meth:`resolve`, and the factor ``map_id``'s units were scaled by on the way
        (None when a merge's scale is not known here)."""
        return resolve_map_scale(self.merged_into, self.merge_scale, map_id)

    def is_local(self, map_id: str) -> bool:
        return map_id in self.maps

    def get(self, map_id: str) -> ServerMap | None:
        return self.maps.get(map_id)

    def ensure_map(self, map_id: str) -> ServerMap:
        with self._lock:
            return self.maps.setdefault(map_id, ServerMap(map_id))

    def map_of_kf(self, g: int) -> str | None:
        for map_id, smap in list(self.maps.items()):
            if g in smap.kfs or g in smap.culled:
                return map_id
        return None

    # --- agents ------------------------------------------------------------------------
    def handler(self, agent: str) -> AgentHandler | None:
        return self._handlers.get(agent)

    def handlers(self) -> dict[str, AgentHandler]:
        """Every agent's handler (a copy: safe to iterate while agents join)."""
        return dict(self._handlers)

    def add_handler(self, h: AgentHandler) -> None:
        h.aliases = self.aliases
        with self._lock:
            self._handlers[h.agent] = h
            self._by_map.setdefault(h.map_id, set()).add(h.agent)

    def handlers_of(self, map_id: str) -> list[AgentHandler]:
        """The agents registering into ``map_id``."""
        with self._lock:
            agents = sorted(self._by_map.get(map_id, ()))
        return [self._handlers[a] for a in agents]

    def n_agents(self, map_id: str) -> int:
        return len(self._by_map.get(map_id, ()))

    def load(self, maps: dict[str, ServerMap], handlers: dict[str, AgentHandler],
             names: dict[int, str],
             merges: dict[str, tuple[str, float | None]] | None = None) -> None:  # fmt: skip
        """State rebuilt from the store (before any actor runs); ``merges``: retired map
        -> (the map it went into, its merge's scale), as ``Store.merges`` reads them,
        so a match verified before a merge still finds its maps' units."""
        self.maps.update(maps)
        self.names.update(names)
        for source, (target, scale) in (merges or {}).items():
            self.merged_into.setdefault(source, target)
            if scale is not None:
                self.merge_scale.setdefault(source, scale)
        for h in handlers.values():
            self.aliases.update(h.aliases)
        for h in handlers.values():
            self.add_handler(h)

    # --- actors and locks --------------------------------------------------------------
    def actor(self, map_id: str) -> MapActor:
        a = self.actors.get(map_id)
        if a is None:
            with self._lock:
                a = self.actors.get(map_id)
                if a is None:
                    a = self._make_actor(self.maps[map_id])
                    self.actors[map_id] = a
        return a

    @contextlib.contextmanager
    def lock(self, *map_ids: str) -> Iterator[None]:
        """The maps' actor locks, taken in map-id order (no lock-order deadlock)."""
        locks = [self.actor(m).lock for m in sorted(set(map_ids))]
        for lk in locks:
            lk.acquire()
        try:
            yield
        finally:
            for lk in reversed(locks):
                lk.release()

    def batches_waiting(self) -> bool:
        """Whether any map actor has a keyframe batch queued."""
        return bool(self.backlog)

    def new_queue(self) -> BatchQueue:
        """A queue for a new map actor, counted in :attr:`backlog`."""
        return BatchQueue(self.backlog)

    def wait_for_batches(self, max_s: float = 1.0) -> None:
        """Background work (map copies, corrections, loop fusion) calls this between
        its steps: it sleeps while keyframe batches are queued, so the actors have the
        GIL to themselves then. A lock alone would not do it: a thread that releases the
        map's lock and takes it again at once usually wins over the actor it woke, and a
        CPU-bound thread off the lock still takes half the GIL. ``max_s`` bounds the
        wait, so background work still progresses under sustained load."""
        self.backlog.wait_clear(max_s)

    def drop(self, map_id: str) -> list[AgentHandler]:
        """Forget ``map_id`` and its agents: another mapper owns it now (its lease was
        lost or handed over). Its actor stops without applying what it has queued (those
        batches were never acknowledged: the agents resend them to the new owner)."""
        with self._lock:
            agents = self._by_map.pop(map_id, set())
            dropped = [self._handlers.pop(a) for a in sorted(agents) if a in self._handlers]
            self.maps.pop(map_id, None)
            a = self.actors.pop(map_id, None)
        if a is not None:
            a.dropped = True
            with contextlib.suppress(queue.Empty):
                while True:  # never applied (see above); and no longer in the backlog
                    a.q.get_nowait()
        return dropped

    # --- merges ------------------------------------------------------------------------
    def merge(self, source: str, target: str, S_t_s: Sim3) -> list[AgentHandler]:
        """Map ``source`` (already moved into ``target`` by ``merge.move_map``) is gone:
        its agents register into ``target`` through ``S_t_s``, its actor forwards what
        it still has queued and stops, and ``source`` resolves to ``target``. Called
        with both maps locked. Returns the agents moved."""
        tmap = self.maps[target]
        with self._lock:
            moved = [self._handlers[a] for a in sorted(self._by_map.pop(source, ()))]
            self._by_map.setdefault(target, set()).update(h.agent for h in moved)
        for h in moved:
            h.smap = tmap
            h.S_m_l = S_t_s @ h.S_m_l
        self.merged_into[source] = target
        self.merge_scale[source] = float(S_t_s.s)
        a = self.actors.get(source)
        if a is not None:
            a.retired_into = target
        self.maps.pop(source, None)
        return moved
