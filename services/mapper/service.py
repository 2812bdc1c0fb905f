"""The mapper service: Zenoh in, Redis and acks out.

Who owns what: ``registry.MapRegistry`` holds the maps, agent handlers, actors, locks
and merge chains; this module wires them to the wire (dispatch of keyframe batches and
poses, the actors that register them, feedback, the optimization scheduler), ``collab``
handles matches, merges, loops and corrections on the registry's maps, ``capture``
copies a map for the optimizer, ``persist`` turns map changes into ``shared.store``
writes (whose docstring is the Redis schema), ``registration`` / ``server_map`` are the
algorithms, free of transport.

Concurrency: one actor per server map. A dispatcher thread decodes every keyframe
batch (so garbage costs one decode and never reaches a map) and queues it on the
actor of the agent's map; each actor thread owns its map and applies batches one at
a time, so the map's invariants hold without fine-grained locks. We chose this over
CSfM's keyframe-neighbourhood locks (§V) because in CPython the GIL already
serializes the Python-level graph updates: neighbourhood locks would add lock
traffic and deadlock risk without buying parallel CPU, while actors still overlap
where time is really spent outside the GIL (Redis round trips, OpenCV, numpy) and
keep agents on different maps fully independent. An agent that floods or stalls
only fills its own map's queue.

Every batch is stored in one MULTI/EXEC transaction before its ack is sent, so an
ack always means "stored". On start, maps and handlers are rebuilt from Redis.

Several mappers share the maps (``ownership``): each owns some through leases in Redis,
keeps only the batches of its maps' agents, writes through pipelines fenced by the
map's token, and takes over the maps of a mapper that stopped renewing them.

Redundant-keyframe rejection (CCM-SLAM §4.6) runs when an actor is idle and, in a map
several agents share, between batches too (see ``MapActor._run``): agents flying the
same place keep adding observers to the same points, and every later keyframe pays for
them, so there culling keeps pace with insertion. Point fusion, feedback (slower while
the actor is over half busy) and keyframe events for place recognition are deferred
behind queued batches. Collaboration work on a map (copies, corrections, loop fusion)
takes the same lock in short holds (see ``collab``) and, between them, sleeps while
batches are queued (``wait_for_batches``): in one process the GIL is shared, and a
lock alone does not give the actor priority.
"""

from __future__ import annotations

import logging
import queue
import random
import socket
import threading
import time
from dataclasses import dataclass

import numpy as np
import redis

from shared import keys
from shared.geometry import Sim3
from shared.leases import Fenced
from shared.messages import Ack, DecodeError, KeyframeBatch, Match, PoseUpdate, packb, peek_session
from shared.metrics import KEYFRAME_LATENCY, MAP_SIZE, PROCESSING, REJECTED, STORED, UP
from shared.settings import Settings
from shared.store import LivePose, Store, connect
from shared.transport import Bus, Received, drain, get_all, open_session

from . import persist
from .agent_health import HEALTH
from .collab import Collaboration
from .feedback import build_chunk
from .locks import MapLock
from .metrics import (
    CULLED,
    FEEDBACK_BYTES,
    FENCED_WRITES,
    HANDOVERS,
    LEASE_RENEWALS,
    LEASES_LOST,
    LEASES_RETAKEN,
    MAP_POINTS,
    MAPS_OWNED,
    OVERLOAD_LEVEL,
    QUEUE_DEPTH,
    REFINEMENTS,
    REGISTRATION,
    SHED,
    TAKEOVERS,
)
from .overload import BACKGROUND, BUSY_LOAD, FEEDBACK, LEVELS, POSES, Overload
from .ownership import Ownership
from .redundancy import find_redundant
from .registration import AgentHandler, IngestFailed, IngestResult, MapperParams
from .registry import MapRegistry
from .server_map import ServerMap, digest
from .sessions import Flights

log = logging.getLogger(__name__)
SERVICE = "mapper"
CULL_EVERY = 4  # batches between rejection rounds while a shared map's queue is full
EVENT_MAX_DELAY_S = 0.5  # keyframe events wait at most this long behind queued batches
EVENTS_PER_BATCH = 4
# With no batch queued, at most this many per call (the actor calls again at least every
# 50 ms): events deferred through an overload (up to EVENT_MAX_DEFER_S of them) were
# published in one hold of the map's lock, 1.8 s at 32 agents (bench_ramp, 32 agents).
EVENTS_PER_IDLE = 16
# Under overload (level background) keyframe events wait, but not longer than this:
# place recognition deferred is merges and loops late, deferred for ever is lost.
EVENT_MAX_DEFER_S = 30.0
POSE_INTERVAL_SHED_S = 1.0  # an agent's live pose stored at most this often when shedding
LOAD_WINDOW_S = 2.0  # an actor's load is its busy share over about this long
# Feedback (map chunks to agents) is spare-capacity work, but each chunk of a big merged
# map costs milliseconds, and an actor serves every agent of its map: at 32 agents x
# 2 Hz it took 46 % of the mapper's busy time (py-spy, bench_ramp.py --profile). An
# actor spends at most this share of its time on feedback; within that, the agents
# longest without a chunk go first, so each agent's rate falls evenly as agents are
# added.
FEEDBACK_SHARE = 0.15
FEEDBACK_SLICE_S = 0.02  # one feedback round stops after this long (batches come first)
# A map actor registers the batches queued for its map together, up to this many and
# while their registration took less than GROUP_BUDGET_S, and stores them in one
# transaction (see ``MapActor._apply_queued``).
GROUP_MAX = 8
GROUP_BUDGET_S = 0.05
# The mapper process's GIL switch interval (CPython's default is 5 ms). Every Redis round
# trip and Zenoh put of a map actor gives the GIL away; getting it back from a thread
# that computes (another map's actor, a merge, a map copy) took up to the interval each
# time, several times per batch. Set by ``hivemap mapper`` for its process.
GIL_SWITCH_S = 0.001


@dataclass
class Ingested:
    """One batch registered in memory, not stored yet: what changed and its ack."""

    res: IngestResult
    ack: Ack
    seconds: float  # registration time


def initial_map_id(agent: str) -> str:
    return f"map-{agent}"


class MapActor:
    """Owns one server map: applies batches in order, stores, acks; when idle, culls
    redundant keyframes and sends feedback."""

    def __init__(self, svc: MapperService, smap: ServerMap, stop: threading.Event) -> None:
        self.svc = svc
        self.reg = svc.registry
        self.stop = stop
        self.smap = smap
        self.q: queue.Queue = svc.registry.new_queue()
        self.lock = MapLock(smap.map_id)
        self.rng = random.Random(smap.map_id)
        self._cull_version = -1
        self._batches = 0
        self._busy, self._busy_t = 0.0, time.monotonic()
        self._fb_busy, self._fb_t = 0.0, time.monotonic()
        self.events: list[tuple[str, int]] = []  # (map, keyframe) for place recognition
        self._events_since = 0.0
        self.thread = threading.Thread(target=self._run, name=f"map-{smap.map_id}", daemon=True)
        self.retired_into: str | None = None  # set when this map was merged into another
        self.dropped = False  # set when another mapper took the map: stop at once

    def start(self) -> None:
        self.thread.start()

    def _run(self) -> None:
        svc = self.svc
        while not self.stop.is_set():
            if self.dropped:
                return
            try:
                item = self.q.get(timeout=0.05)
            except queue.Empty:
                self._publish_events(force=True)
                if self.retired_into is not None:
                    return  # merged away and drained
                self._idle()
                continue
            t_batch = time.monotonic()
            n = self._apply_queued(item, t_batch)
            if not n:
                continue
            QUEUE_DEPTH.labels(self.smap.map_id).set(self.q.qsize())
            cull_due = self._batches // CULL_EVERY != (self._batches + n) // CULL_EVERY
            self._batches += n
            self._note_busy(t_batch, time.monotonic())
            # Keyframe events for place recognition wait while batches are queued (a
            # burst's acks go first), but not past EVENT_MAX_DELAY_S.
            self._publish_events(force=self.q.empty())
            svc.note_level()
            # In a map several agents share, rejection rounds run between batches as
            # well, not only when idle: agents flying the same place keep adding observers
            # to the same points, and every later keyframe, fusion and map copy pays for
            # them. When such a map is busiest (8 agents in one hall) idle time never
            # comes, and this is what keeps it small: a round after every group of batches
            # that empties the queue, and after every CULL_EVERY-th batch during a burst.
            # A one-agent map culls when idle.
            if self._shared() and (self.q.empty() or cull_due):
                self._cull_round()
            # Feedback is spare-capacity work: queued batches (other agents of a merged
            # map) are registered first; it runs once the queue is drained.
            if self.q.empty():
                self._feedback()

    def _apply_queued(self, item, t_batch: float) -> int:
        """Registers ``item`` and the batches queued behind it (up to GROUP_MAX, while
        their registration took less than GROUP_BUDGET_S) in one hold of the map's lock,
        stores them in one transaction and then acknowledges each: under load every
        batch paid three Redis round trips of its own, and each round trip gave the GIL
        away to the other map actors' threads and waited to get it back. Returns how
        many batches were registered."""
        svc = self.svc
        group: list[tuple] = []
        try:
            with self.lock:
                t_in = time.monotonic()  # the budget counts from here, not the wait
                while True:
                    h, batch, recv_ns, key, pre = item
                    if h.smap is not self.smap:
                        # The agent's map was merged into another after this batch was
                        # queued.
                        if self.reg.is_local(h.map_id):
                            self.reg.actor(h.map_id).q.put(item)
                    elif svc.admit(h, batch, recv_ns, t_batch, self.smap.map_id):
                        try:
                            group.append((h, batch, recv_ns, svc.ingest(h, batch, pre)))
                        except Exception:
                            REJECTED.labels(SERVICE, key, "internal").inc()
                            log.exception("keyframe batch failed", extra={"agent": h.agent})
                    if (len(group) >= GROUP_MAX
                            or time.monotonic() - t_in > GROUP_BUDGET_S):  # fmt: skip
                        break
                    try:
                        item = self.q.get_nowait()
                    except queue.Empty:
                        break
                if group:
                    svc.store_and_ack(group)
        except Fenced as e:
            log.warning("%d batch(es) of map %s not stored: %s", len(group),
                        self.smap.map_id, e)  # fmt: skip
        except redis.WatchError:
            log.warning("%d batch(es) not stored: map %s taken by another mapper",
                        len(group), self.smap.map_id)  # fmt: skip
        except redis.RedisError:
            log.exception("redis write failed; %d batch(es) not acknowledged", len(group))
        except Exception:
            log.exception("storing keyframe batches failed")
        return len(group)

    def queue_events(self, map_id: str, gids: list[int]) -> None:
        """Keyframe events to publish after the batch (see ``_publish_events``)."""
        if not self.events:
            self._events_since = time.monotonic()
        self.events.extend((map_id, g) for g in gids)

    def _publish_events(self, force: bool = False) -> None:
        """Keyframe events of the batches registered so far, under the map's lock (an
        event carries the keyframe's points as they are now). ``force=False`` defers
        them while batches wait, up to EVENT_MAX_DELAY_S."""
        if not self.events:
            return
        now = time.monotonic()
        if not force and now - self._events_since < EVENT_MAX_DELAY_S:
            return
        if (self.svc.level >= BACKGROUND and now - self._events_since < EVENT_MAX_DEFER_S
                and not self.stop.is_set()):  # fmt: skip
            SHED.labels("placerec").inc()
            return
        # Overdue during a burst: a few per batch (each is ~4 ms), oldest first.
        n = EVENTS_PER_IDLE if self.q.empty() else EVENTS_PER_BATCH
        events, self.events = self.events[:n], self.events[n:]
        by_map: dict[str, list[int]] = {}
        for map_id, g in events:
            # Merged away since: the keyframe moved along.
            by_map.setdefault(self.reg.resolve(map_id), []).append(g)
        try:
            for map_id, gids in by_map.items():
                if self.reg.is_local(map_id):
                    with self.reg.lock(map_id):
                        self.svc.collab.publish_events(map_id, gids)
        except Exception:
            log.exception("keyframe events failed")

    def _idle(self) -> None:
        # Idle work holds the GIL for milliseconds at a time: it waits while any map has
        # a batch queued, so it never slows down another agent's registration.
        if self.reg.batches_waiting():
            return
        # One keyframe's fusion at a time (~10-30 ms in a dense merged map), so a batch
        # that arrives meanwhile waits for at most one of them, not for the whole backlog.
        try:
            while not self.reg.batches_waiting():
                with self.lock:
                    if not self.svc.fuse(self.smap, max_kfs=1):
                        break
        except Exception:
            log.exception("point fusion failed")
        if self.reg.batches_waiting():
            return
        # One rejection round per change of the map, not one per 50 ms poll (with 8
        # agents, idle rounds on unchanged maps took most of the mapper's CPU).
        if self.smap.version != self._cull_version:
            self._cull_round()
        self._feedback()

    def _shared(self) -> bool:
        return self.reg.n_agents(self.smap.map_id) > 1

    def _cull_round(self) -> None:
        if not self.svc.settings.mapper.redundancy:
            return
        self._cull_version = self.smap.version
        try:
            with self.lock:
                self.svc.cull(self.smap, self.rng)
        except Exception:
            log.exception("keyframe rejection failed")

    def _note_busy(self, t0: float, t1: float) -> None:
        """Share of the last LOAD_WINDOW_S spent registering batches (decayed sum)."""
        decay = np.exp(-(t1 - self._busy_t) / LOAD_WINDOW_S)
        self._busy = self._busy * decay + (t1 - t0) / LOAD_WINDOW_S
        self._busy_t = t1

    def load(self) -> float:
        return self._busy * np.exp(-(time.monotonic() - self._busy_t) / LOAD_WINDOW_S)

    def _feedback(self) -> None:
        # Feedback is spare-capacity work (up to 16 chunks a second for 8 agents, each
        # several ms in a dense merged map): while registration keeps the actor over
        # half busy, each agent gets it at a quarter of its rate; and it never takes
        # more than FEEDBACK_SHARE of the actor's time.
        t0 = time.monotonic()
        if self._fb_load(t0) > FEEDBACK_SHARE:
            return
        slow = self.load() > BUSY_LOAD or self.svc.level >= FEEDBACK
        if self.svc.level >= FEEDBACK:
            SHED.labels("feedback").inc()
        try:
            self.svc.send_feedback(self.smap, should_yield=self.reg.batches_waiting,
                                   rate_factor=0.25 if slow else 1.0,
                                   max_s=FEEDBACK_SLICE_S)  # fmt: skip
        except Exception:
            log.exception("feedback failed")
        t1 = time.monotonic()
        self._fb_busy = self._fb_load(t1) + (t1 - t0) / LOAD_WINDOW_S
        self._fb_t = t1

    def _fb_load(self, now: float) -> float:
        """Share of the last LOAD_WINDOW_S spent on feedback (decayed sum)."""
        return self._fb_busy * np.exp(-(now - self._fb_t) / LOAD_WINDOW_S)


class MapperService:
    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.params = MapperParams.from_settings(settings.mapper)
        self.store = Store(connect(settings.redis_url))
        self.flights = Flights(self.store)
        self._stop = threading.Event()
        self.registry = MapRegistry(self._new_actor)
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()
        self.session = None
        self.bus: Bus | None = None
        self._fb_last: dict[str, float] = {}
        self._fb_sent: dict[str, set[int]] = {}
        self.overload = Overload.from_shed_after(settings.mapper.shed_after_s)
        self.level = 0
        self._level_lock = threading.Lock()
        self._pose_last: dict[str, float] = {}
        # Per agent: (handler, result) registered in memory whose store failed (see
        # ``store_and_ack``).
        self._unstored: dict[str, list] = {}
        self.collab = Collaboration(
            self.registry,
            self.store,
            settings.mapper.optimize_min_interval_s,
            settle_after_kfs=settings.mapper.settle_after_kfs,
            settle_window_kfs=settings.mapper.settle_window_kfs,
            window_odometry=settings.mapper.window_odometry,
            window_odometry_trans_share=settings.mapper.window_odometry_trans_share,
            local_ba_time_budget_s=settings.optimizer.local_ba_time_budget_s,
        )
        m = settings.mapper
        self.own = Ownership(self.store, m.instance or socket.gethostname(), m.lease_s)
        self.collab.pipeline = self.own.pipeline
        self.collab.remote_match = self._remote_match
        self.collab.retired = self.own.leases.release
        self._routes: dict[str, tuple[bool, float]] = {}  # agent -> (ours, until)
        self._pending_merges: dict[str, Match] = {}  # map asked for -> the match
        self._take_lock = threading.Lock()

    # --- state (owned by the registry; these read it) ------------------------------------
    @property
    def maps(self) -> dict[str, ServerMap]:
        return self.registry.maps

    @property
    def handlers(self) -> dict[str, AgentHandler]:
        return self.registry.handlers()

    @property
    def names(self) -> dict[int, str]:
        return self.registry.names

    def load(self) -> None:
        """The maps this mapper owns, from Redis: the ones whose lease names it (a
        restart) and, when it is the least loaded, the ones nobody holds."""
        self._heartbeat()
        mine = {m for m in self.store.maps() if self._may_own(m)}
        maps, handlers = persist.load_all(self.store, self.params, only=mine)
        self.registry.load(maps, handlers, self.store.agent_names(), self.store.merges())
        self.collab.load(set(maps))
        for h in handlers.values():
            log.info("resumed agent %s: map %s, %d keyframes", h.agent, h.map_id,
                     sum(1 for k in h.smap.kfs.values() if k.agent == h.agent),
                     extra={"agent": h.agent})  # fmt: skip

    def handler(
        self,
        agent: str,
        map_id: str | None = None,
        S_m_l: Sim3 | None = None,
        name: str | None = None,
    ) -> AgentHandler:
        """The agent's handler, created on first contact with a map of its own, or
        in ``map_id`` through ``S_m_l`` (an agent joining a known map). ``agent``: the
        stored agent id of the flight; ``name``: the id it flies as (default
        ``agent``; see ``sessions``)."""
        reg = self.registry
        h = reg.handler(agent)
        if h is not None:
            return h
        with self._lock:
            h = reg.handler(agent)
            if h is None:
                new_map = map_id or initial_map_id(agent)
                if not reg.is_local(new_map) and self.own.leases.acquire(new_map) is None:
                    raise Fenced(f"map {new_map} of new agent {agent} is another mapper's")
                idx = self.store.agent_index(agent)
                reg.names[idx] = agent
                smap = reg.ensure_map(new_map)
                h = AgentHandler(agent, idx, smap, S_m_l or Sim3.identity(), self.params)
                h.name = name or agent
                h.aliases = reg.aliases
                pipe = self.own.pipeline(smap.map_id)
                persist.write_handler(pipe, h, new=True)
                pipe.execute()
                reg.add_handler(h)
                log.info("new agent %s with map %s", agent, map_id, extra={"agent": agent})
        return h

    def actor(self, map_id: str) -> MapActor:
        return self.registry.actor(map_id)

    def _new_actor(self, smap: ServerMap) -> MapActor:
        a = MapActor(self, smap, self._stop)
        if self.session is not None:
            a.start()
        return a

    # --- processing (transport-free parts are called directly by tests) -----------------
    def decode_kf(self, key: str, payload: bytes) -> KeyframeBatch | None:
        agent_key = keys.agent_of(key) or "?"
        try:
            batch = KeyframeBatch.decode(payload)
            if batch.agent != agent_key:
                raise DecodeError(f"agent {batch.agent!r} sent on the key of {agent_key!r}")
            keys.check_id(batch.agent, "agent")
        except (DecodeError, ValueError) as e:
            reason = _reason(e)
            REJECTED.labels(SERVICE, key, reason).inc()
            log.warning("rejected keyframe message on %s: %s", key, e,
                        extra={"key": key, "reason": reason})  # fmt: skip
            return None
        return batch

    def process_kf_bytes(self, key: str, payload: bytes, recv_ns: int) -> Ack | None:
        """Decode and apply synchronously (tests; the service queues on map actors)."""
        batch = self.decode_kf(key, payload)
        if batch is None:
            return None
        h = self.handler(self.flights.name(batch.agent, batch.session), name=batch.agent)
        with self.actor(h.map_id).lock:
            ack = self.apply(h, batch, recv_ns)
            self.fuse(h.smap)
            return ack

    def apply(self, h: AgentHandler, batch: KeyframeBatch, recv_ns: int) -> Ack:
        """Registers, stores and acknowledges one batch (the actor does several at once,
        see ``MapActor._apply_queued``)."""
        return self.store_and_ack([(h, batch, recv_ns, self.ingest(h, batch))])[0]

    def ingest(self, h: AgentHandler, batch: KeyframeBatch, undistorted=None) -> Ingested:
        """Registration of one batch, in memory (``store_and_ack`` writes it out);
        ``undistorted``: its keypoints undistorted ahead (``AgentHandler.undistorted``)."""
        t0 = time.perf_counter()
        try:
            res = h.ingest(batch, time.monotonic(), undistorted)
        except IngestFailed as e:
            # Not acknowledged; what it did change is written with the agent's next
            # batch that stores, before that batch's ack (as a failed store's is).
            if e.partial.changed:
                self._unstored.setdefault(h.agent, []).append((h, e.partial))
            raise
        held, missing = h.blocked()
        ack = Ack(batch.agent, h.map_id, np.array(res.ack_kf_ids, np.int64),
                  np.array(res.ack_mp_ids, np.int64), h.kf_high, 0,
                  np.array(held, np.int64), np.array(missing, np.int64), batch.seq)  # fmt: skip
        return Ingested(res, ack, time.perf_counter() - t0)

    def store_and_ack(self, group: list[tuple[AgentHandler, KeyframeBatch, int, Ingested]]
                      ) -> list[Ack]:  # fmt: skip
        """Stores what the batches of ``group`` (all of one map) changed in one
        transaction, then acknowledges each: an ack always means "stored". Returns the
        acks in order."""
        t0 = time.perf_counter()
        # What an earlier store of these agents failed to write goes first: it is in the
        # map in memory, so a resend of it is only acknowledged (a duplicate), and that
        # ack would say "stored" for a keyframe Redis never got.
        # (The same handler only: a map taken over and back is a new one, from Redis.)
        changed = [(h, res) for h in {id(h): h for h, _, _, _ in group}.values()
                   for hu, res in self._unstored.pop(h.agent, []) if hu is h]  # fmt: skip
        changed += [(h, ing.res) for h, _, _, ing in group if ing.res.changed]
        if changed:
            try:
                pipe = self.own.pipeline(changed[0][0].map_id)
                for h, res in changed:
                    persist.write_result(pipe, h, res, self.names, handler=False)
                persist.write_handlers(pipe, [h for h, _ in changed])
                pipe.execute()
            except Exception:
                # Not acknowledged; written (as the map is then) with the agent's next
                # batch that stores, before its ack.
                for h, res in changed:
                    self._unstored.setdefault(h.agent, []).append((h, res))
                raise
        t_store = (time.perf_counter() - t0) / len(group)
        acks = []
        for h, batch, recv_ns, ing in group:
            res, ack = ing.res, ing.ack
            ack.sent_ns = time.time_ns()
            if recv_ns > 0:  # 0: not received off the wire (fed in directly)
                ack.held_s = min(max(ack.sent_ns - recv_ns, 0) * 1e-9, 3600.0)
            acks.append(ack)
            if self.bus is not None:
                self.bus.put(keys.agent_ack(batch.agent), ack.encode())
                if res.new_kfs:
                    a = self.registry.actors.get(h.map_id)
                    if a is None or not a.thread.is_alive():
                        self.collab.publish_events(h.map_id, res.new_kfs)
                    else:
                        a.queue_events(h.map_id, res.new_kfs)
            now_ns = time.time_ns()
            for _ in res.new_kfs:
                KEYFRAME_LATENCY.labels(batch.agent).observe((now_ns - recv_ns) * 1e-9)
            for what, n in (("duplicate", res.duplicates), ("stale", res.stale),
                            ("early", res.early), ("orphan", res.orphans_anchored),
                            ("rechained", res.rechained)):  # fmt: skip
                if n:
                    REGISTRATION.labels(what).inc(n)
            for what, n in (("accepted", res.refined), ("gated", res.refine_gated)):
                if n:
                    REFINEMENTS.labels(what).inc(n)
            STORED.labels(SERVICE, "keyframe").inc(len(res.new_kfs))
            STORED.labels(SERVICE, "map_point").inc(len(res.new_mps))
            PROCESSING.labels(SERVICE, "kf_batch").observe(ing.seconds + t_store)
        h = group[-1][0]
        MAP_SIZE.labels(h.map_id).set(len(h.smap.kfs))
        MAP_POINTS.labels(h.map_id).set(len(h.smap.mps))
        CULLED.labels(h.map_id)  # exists at 0 from the map's first keyframe on
        return acks

    def fuse(self, smap: ServerMap, max_kfs: int | None = None) -> int:
        """Point fusion for keyframes registered since the last call (idle work, so it
        never sits between a batch and its ack, nor between two agents' batches).
        Returns how many keyframes were processed (at most ``max_kfs``)."""
        n = 0
        for h in [h for h in self.registry.handlers_of(smap.map_id) if h.to_fuse]:
            left = None if max_kfs is None else max_kfs - n
            if left is not None and left <= 0:
                break
            n += min(len(h.to_fuse), left) if left is not None else len(h.to_fuse)
            fres = h.fuse_new(left)
            if fres.changed:
                pipe = self.own.pipeline(smap.map_id)
                persist.write_result(pipe, h, fres, self.names)
                pipe.execute()
        return n

    def cull(self, smap: ServerMap, rng: random.Random) -> int:
        """One round of redundant-keyframe rejection on ``smap``."""
        mine = self.registry.handlers_of(smap.map_id)
        protected = set()
        for h in mine:
            for i in (h.kf_ref, h.latest_kf, h.first_kf):
                if i >= 0:
                    protected.add(h.kf_gid(i))
            # Keyframes still waited on as predecessors must stay.
            protected.update(h.kf_gid(k.pred_id) for k in h.pending_kfs.values())
        m = self.settings.mapper
        victims = find_redundant(smap, rng, protected, m.redundancy_ratio)
        if not victims:
            return 0
        by_agent = {h.agent: h for h in mine}
        pipe = self.own.pipeline(smap.map_id)
        for g in victims:
            kf = smap.kfs[g]
            h = by_agent.get(kf.agent)
            # Only the children get a new spanning-tree parent (observers' own point
            # lists are untouched), so only theirs is rewritten.
            children = list(kf.children)
            if h is not None:
                h.on_removed(kf)
            dead = smap.remove_keyframe(g)
            if h is not None:
                persist.write_removed_kf(pipe, h, kf, dead, self.names)
            for o in children:
                if o in smap.kfs:
                    ok = smap.kfs[o]
                    Store.set_keyframe_parent(pipe, ok.agent, ok.id, ok.parent)
            CULLED.labels(smap.map_id).inc()
        pipe.execute()
        MAP_SIZE.labels(smap.map_id).set(len(smap.kfs))
        return len(victims)

    def send_feedback(
        self, smap: ServerMap, should_yield=None, rate_factor: float = 1.0,
        max_s: float | None = None,
    ) -> None:  # fmt: skip
        """Map chunks to the agents of ``smap`` that are due one, longest waiting first;
        ``should_yield`` is asked between agents (the actor stops when batches are
        waiting), and the round stops after ``max_s`` seconds."""
        if self.bus is None:
            return
        m = self.settings.mapper
        now = time.monotonic()
        handlers = sorted(self.registry.handlers_of(smap.map_id),
                          key=lambda h: self._fb_last.get(h.agent, -1e9))  # fmt: skip
        for h in handlers:
            if should_yield is not None and should_yield():
                return
            if max_s is not None and time.monotonic() - now > max_s:
                return
            if m.feedback_k <= 0 or now - self._fb_last.get(h.agent, -1e9) < 1.0 / (
                m.feedback_rate_hz * rate_factor
            ):
                continue
            a = self.registry.actors.get(smap.map_id)
            with a.lock if a else _null():
                sent = self._fb_sent.setdefault(h.agent, set())
                chunk = build_chunk(h, m.feedback_k, sent, time.time_ns(), self.names,
                                    m.feedback_correction_kfs)  # fmt: skip
            if chunk is None:
                continue  # nothing sent (KF_ref not registered yet): no rate limit either
            self._fb_last[h.agent] = now
            data = chunk.encode()
            self.bus.put(keys.agent_map(h.name), data, reliable=False)
            FEEDBACK_BYTES.labels(h.agent).inc(len(data))

    def process_pose_bytes(self, key: str, payload: bytes, recv_ns: int) -> LivePose | None:
        p = self.decode_pose(key, payload)
        return None if p is None else self.store_pose(p, recv_ns)

    def decode_pose(self, key: str, payload: bytes) -> PoseUpdate | None:
        agent_key = keys.agent_of(key) or "?"
        try:
            p = PoseUpdate.decode(payload)
            if p.agent != agent_key:
                raise DecodeError(f"agent {p.agent!r} sent on the key of {agent_key!r}")
        except (DecodeError, ValueError) as e:
            REJECTED.labels(SERVICE, key, _reason(e)).inc()
            log.warning("rejected pose on %s: %s", key, e, extra={"key": key})
            return None
        HEALTH.report(p)
        return p

    def store_pose(self, p: PoseUpdate, recv_ns: int) -> LivePose | None:
        pose = self.live_pose(p, recv_ns)
        if pose is not None:
            self.store.put_pose(pose)
        return pose

    def live_pose(self, p: PoseUpdate, recv_ns: int) -> LivePose | None:
        """``p`` in its agent's map frame; None before the agent's first keyframe (no map
        frame to place it in) or when its reference keyframe is unknown."""
        agent = self.flights.known(p.agent, p.session)
        h = None if agent is None else self.registry.handler(agent)
        if h is None:
            return None
        T = h.pose_of(p.kf_ref, p.T_ref_c)
        if T is None:
            return None
        return LivePose(h.agent, h.map_id, p.stamp_ns, T, p.kf_ref, p.tracking, p.fps, recv_ns)

    def state_digest(self) -> dict:
        """Digest of every map and agent handler (answered on ``hivemap/mapper/state``)."""
        maps = {}
        for map_id, smap in list(self.registry.maps.items()):
            a = self.registry.actors.get(map_id)
            with a.lock if a else _null():
                maps[map_id] = digest(smap)
        agents = {
            h.agent: {"map": h.map_id, "S_m_l": h.S_m_l.to_array().round(12).tolist(),
                      "lam": round(h.lam, 12), "removed": sorted(h.removed)}
            for h in self.registry.handlers().values()
        }  # fmt: skip
        return {"maps": maps, "agents": agents}

    def _on_state_query(self, query) -> None:
        try:
            query.reply(keys.MAPPER_STATE, packb(self.state_digest()))
        except Exception:
            log.exception("state query failed")

    # --- service loop -------------------------------------------------------------------
    def start(self) -> None:
        self.load()
        self.session = open_session(self.settings.zenoh)
        self.bus = Bus(self.session, SERVICE, self.settings.inject)
        self.collab.bus = self.bus
        for map_id in list(self.registry.maps):
            self.registry.actor(map_id)  # starts its thread now that the session is open
        self._queryable = self.session.declare_queryable(keys.MAPPER_STATE, self._on_state_query)
        self.kf_q = self.bus.subscribe(keys.ALL_AGENT_KF)
        self.pose_q = self.bus.subscribe(keys.ALL_AGENT_POSE, maxsize=256)
        c = self.collab
        loops = [
            ("kf", drain, (self.kf_q, self._stop, self._dispatch, SERVICE, "dispatch")),
            ("match", drain, (self.bus.subscribe(keys.MATCH), self._stop,
                              lambda it: c.on_match_bytes(it.key, it.payload), SERVICE,
                              "match")),
            ("correction", drain, (self.bus.subscribe(keys.ALL_MAP_CORRECTION), self._stop,
                                   lambda it: c.on_correction_bytes(it.key, it.payload),
                                   SERVICE, "correction")),
            ("pose", self._pose_worker, ()),
            ("leases", self._keep_leases, ()),
            ("optimize", self._optimize_scheduler, ()),
        ]  # fmt: skip
        for name, fn, args in loops:
            t = threading.Thread(target=fn, args=args, name=f"mapper-{name}", daemon=True)
            t.start()
            self._threads.append(t)
        UP.labels(SERVICE).set(1)
        log.info("mapper running")

    # --- overload (services/mapper/overload.py) ------------------------------------------
    def admit(self, h: AgentHandler, batch: KeyframeBatch, recv_ns: int, now: float,
              map_id: str = "") -> bool:  # fmt: skip
        """Whether the actor of ``map_id`` registers this batch now. A shed one is
        answered with a NACK (an ack of no keyframe that names the batch and says when
        to send it again), so the agent resends it then instead of after its backed-off
        timeout."""
        waited = max(time.time_ns() - recv_ns, 0) * 1e-9
        self.overload.observe(waited, now, map_id)
        # Keyframes the map has (a resend whose ack was late) are only acknowledged: they
        # cost nothing, and a hole opened at one of them would never be filled (the agent
        # has its ack and sends it no more).
        new = [k.id for k in batch.new_kfs if not h.has_kf(k.id)]
        if self.overload.admit(h.agent, new, waited, now, map_id):
            return True
        SHED.labels("keyframe_batch").inc()
        retry = self.overload.retry_after(now, map_id)
        if self.bus is not None:
            nack = Ack(batch.agent, h.map_id, np.zeros(0, np.int64), np.zeros(0, np.int64),
                       h.kf_high, time.time_ns(), seq=batch.seq, retry_after_s=retry)  # fmt: skip
            self.bus.put(keys.agent_ack(batch.agent), nack.encode())
        self.note_level()
        return False

    def note_level(self) -> None:
        """Publish the overload level; say so in the log when it changes."""
        with self._level_lock:
            self._note_level()

    def _note_level(self) -> None:
        now = time.monotonic()
        level = self.overload.level(now)
        if level != self.level:
            wait = self.overload.wait(now)
            shed = ", ".join(LEVELS[1 : level + 1]) or "nothing"
            logf = log.warning if level > self.level else log.info
            logf("overload level %d (%s): keyframe batches waited up to %.2f s; shedding %s",
                 level, LEVELS[level], wait, shed)  # fmt: skip
            self.level = level
        OVERLOAD_LEVEL.set(level)

    def _dispatch(self, item: Received) -> None:
        # The flight's stored agent id, from the key and the session read ahead of the
        # decode (``sessions``): a flight named already is routed without decoding.
        agent = keys.agent_of(item.key)
        name = None if agent is None else self.flights.known(agent, peek_session(item.payload))
        if name is not None and not self.serves(name):
            return  # another mapper owns this flight's map
        batch = self.decode_kf(item.key, item.payload)
        if batch is None:
            return
        if name is None:  # a new flight: named once its first batch decodes
            name = self.flights.name(batch.agent, batch.session)
            if not self.serves(name):
                return
        try:
            h = self.handler(name, name=batch.agent)
        except Fenced as e:
            log.info("batch of %s left to another mapper: %s", name, e)
            return
        if self.registry.is_local(h.map_id):
            # Keypoints undistorted here, not on the map's actor: OpenCV releases the GIL,
            # so this overlaps with registration instead of adding to it.
            pre = h.undistorted(batch)
            self.actor(h.map_id).q.put((h, batch, item.recv_ns, item.key, pre))

    # --- ownership (services/mapper/ownership.py) ---------------------------------------
    def serves(self, agent: str) -> bool:
        """Whether this mapper takes ``agent``'s batches: it owns the agent's map, or
        the agent is new (or its map orphaned) and this mapper is the least loaded."""
        h = self.registry.handler(agent)
        if h is not None:
            return h.map_id in self.own.leases.tokens
        now = time.monotonic()
        got = self._routes.get(agent)
        if got is not None and got[1] > now:
            return got[0]
        st = self.store.agent_state(agent)
        if st is None:
            ours = self.own.assign(agent) in (self.own.id, None)
        else:
            ours = self._may_own(st.map_id) and self.take_map(st.map_id)
        self._routes[agent] = (ours, now + 0.5)
        return ours

    def _may_own(self, map_id: str) -> bool:
        """Takes the map's lease if it names this mapper, or if nobody holds it, nobody
        asked for it and this mapper is the least loaded. A map released for a merge is
        left to the mapper that asked (it takes it in its lease round): its old owner,
        least loaded once it dropped the map and hearing the agent's next batch first,
        would otherwise take it back, hand it over again at the next round, and so on
        (a ping-pong that delayed merges by seconds, and in compose stopped them)."""
        owner = self.own.owner(map_id)
        if owner is not None and owner != self.own.id:
            return False
        if owner is None and (self.own.handover_asked(map_id) is not None
                              or not self.own.is_least_loaded()):  # fmt: skip
            return False
        return self.own.leases.acquire(map_id) is not None

    def take_map(self, map_id: str) -> bool:
        """Loads a map this mapper holds the lease of (taken over, handed over) from
        Redis into the registry, and starts its actor."""
        with self._take_lock:  # the dispatcher and the lease keeper both take maps
            return self._take_map(map_id)

    def _take_map(self, map_id: str) -> bool:
        if self.registry.is_local(map_id):
            return True
        if self.own.leases.acquire(map_id) is None:
            return False
        maps, handlers = persist.load_all(self.store, self.params, only={map_id})
        if map_id not in maps:
            self.own.leases.release(map_id)  # merged away or empty meanwhile
            return False
        with self._lock:
            self.registry.load(maps, handlers, self.store.agent_names(), self.store.merges())
            self.collab.load({map_id})
        if self.session is not None:
            self.registry.actor(map_id)
        self._routes.clear()
        log.info("took map %s (%d keyframes, agents %s)", map_id, len(maps[map_id].kfs),
                 ", ".join(sorted(handlers)))  # fmt: skip
        return True

    def drop_map(self, map_id: str, why: str) -> None:
        dropped = self.registry.drop(map_id)
        self.collab.forget_map(map_id, [h.agent for h in dropped])
        self._routes.clear()
        log.warning("dropped map %s (%s); agents %s", map_id, why,
                    ", ".join(h.agent for h in dropped))  # fmt: skip

    def _heartbeat(self) -> None:
        self.own.heartbeat(len(self.registry.handlers()), len(self.registry.maps))
        for g, v in ((MAPS_OWNED, len(self.own.leases.held())),
                     (LEASE_RENEWALS, self.own.leases.stats.renewals),
                     (LEASES_LOST, self.own.leases.stats.lost),
                     (LEASES_RETAKEN, self.own.leases.stats.retaken),
                     (TAKEOVERS, self.own.takeovers), (HANDOVERS, self.own.handovers),
                     (FENCED_WRITES, self.own.leases.stats.refused_writes)):  # fmt: skip
            g.set(v)

    def _keep_leases(self) -> None:
        """Every third of the lease: renew, drop what was lost, give maps asked for,
        take what was handed over, and take one orphaned map when least loaded."""
        own = self.own
        while not self._stop.wait(own.lease_s / 3):
            try:
                for m in own.leases.renew():
                    self.drop_map(m, "lease lost")
                for m in list(self.registry.maps):
                    asker = own.handover_asked(m)
                    if asker is not None and asker != own.id:
                        self._hand_over(m, asker)
                for m, match in list(self._pending_merges.items()):
                    if own.owner(m) is None and self.take_map(m):
                        del self._pending_merges[m]
                        own.handover_done(m)
                        self.collab.on_match(match)
                for m in self.store.maps():
                    if self.registry.is_local(m) or own.owner(m) is not None:
                        continue
                    if own.handover_asked(m) not in (None, own.id):
                        continue  # released for another mapper's merge: it takes it
                    if own.is_least_loaded() and self.take_map(m):
                        own.takeovers += 1
                        break  # one per round: the next goes to whoever is least loaded
                self._heartbeat()
            except Exception:
                log.exception("lease upkeep failed")

    def _hand_over(self, map_id: str, asker: str) -> None:
        """Gives ``map_id`` to ``asker``: what is queued is applied and acknowledged
        first, then the lease is released and the map dropped."""
        a = self.registry.actors.get(map_id)
        deadline = time.monotonic() + 2.0
        while a is not None and a.q.qsize() and time.monotonic() < deadline:
            time.sleep(0.01)
        with self.registry.lock(map_id):
            self.own.leases.release(map_id)
            self.drop_map(map_id, f"handed over to {asker}")
        self.own.handovers += 1

    def _remote_match(self, m: Match, qm: str | None, cm: str | None) -> bool:
        """A match between a map of this mapper and one another owns: the owner of the
        map with the smaller id asks for the other (see ``ownership``)."""
        if qm is None and cm is None:
            return True  # neither map is ours: the owners deal with it
        local = qm if qm is not None else cm
        other = self._current_map(m.cand_map if qm is not None else m.query_map)
        if other is None or other == local or self.registry.is_local(other):
            return False
        if local < other and other not in self._pending_merges:
            self._pending_merges[other] = m
            self.own.request_handover(other)
            log.info("asked for map %s (owner %s) to merge it with %s", other,
                     self.own.owner(other), local)  # fmt: skip
        return True

    def _current_map(self, map_id: str) -> str | None:
        for _ in range(64):
            info = self.store.map_info(map_id)
            if info is None:
                return None
            if info["merged_into"] is None:
                return map_id
            map_id = info["merged_into"]
        return None

    def _optimize_scheduler(self) -> None:
        """Sends debounced optimization requests (a copy of the map each)."""
        while not self._stop.wait(0.25):
            self.note_level()  # also how the level comes down when batches stop coming
            if self.level >= BACKGROUND:
                SHED.labels("optimize").inc()
                continue  # what is due stays due
            now = time.monotonic()
            self.collab.mark_unsettled(now)
            for map_id, reason in self.collab.due(now):
                try:
                    self.collab.request(map_id, reason)
                except Exception:
                    log.exception("optimization request failed", extra={"map": map_id})

    def _pose_worker(self) -> None:
        """Poses are best effort and only an agent's newest one is kept: what queued up
        while keyframe batches had the GIL is coalesced to one per agent (8 agents send
        160 a second, each a Redis round trip)."""
        while not self._stop.is_set():
            try:
                items: list[Received] = [self.pose_q.get(timeout=0.2)]
            except queue.Empty:
                continue
            self.registry.wait_for_batches(max_s=0.1)
            items += get_all(self.pose_q)
            # Every message is decoded (bad ones are counted); the newest good one per
            # agent is stored.
            newest: dict[tuple[str, int | None], tuple[PoseUpdate, int]] = {}
            for item in items:
                try:
                    p = self.decode_pose(item.key, item.payload)
                except Exception:
                    log.exception("pose failed", extra={"key": item.key})
                    continue
                if p is not None:
                    newest[(p.agent, p.session)] = (p, item.recv_ns)
            now = time.monotonic()
            poses = []
            for p, recv_ns in newest.values():
                if self.level >= POSES:
                    if now - self._pose_last.get(p.agent, -1e18) < POSE_INTERVAL_SHED_S:
                        SHED.labels("pose").inc()
                        continue
                    self._pose_last[p.agent] = now
                try:
                    pose = self.live_pose(p, recv_ns)
                except Exception:
                    log.exception("pose failed", extra={"agent": p.agent})
                    continue
                if pose is not None:
                    poses.append(pose)
            try:
                self.store.put_poses(poses)  # one round trip for all agents
            except Exception:
                log.exception("storing %d poses failed", len(poses))

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=5)
        for a in list(self.registry.actors.values()):
            if a.thread.is_alive():
                a.thread.join(timeout=5)
        UP.labels(SERVICE).set(0)
        if getattr(self, "_queryable", None) is not None:
            self._queryable.undeclare()
        if self.bus:
            self.bus.close()
        if self.session is not None:
            self.session.close()
            self.session = None
        self.store.close()


class _null:
    def __enter__(self):
        return self

    def __exit__(self, *a):
        return False


def _reason(e: Exception) -> str:
    msg = str(e)
    if "not msgpack" in msg:
        return "malformed"
    if "version" in msg:
        return "version"
    if "schema" in msg:
        return "schema"
    return "invalid"
