"""The placerec service: keyframe events in, verified matches out; a pool.

The mapper's ``KeyframeEvent`` arrives on ``hivemap/map/{map}/kf``; a verified ``Match``
goes to the mapper on ``hivemap/match`` (both in ``shared/messages.py``). Map ids are
followed through merges the way the mapper follows them (``shared.ids.resolve_map``).

Zenoh callbacks only enqueue; one worker recognizes places, keyframe by keyframe in
arrival order (consistency checks need the order). Map-merge notes go on the same
queue, so a relabel is never overtaken by a keyframe of the merged map.

Several instances share the work as a pool with a *replicated database, partitioned
queries*: Zenoh delivers every keyframe event to every instance, each adds it to its
own database (BoW conversion and insertion, the cheap part), and only the instance
that owns the keyframe's map -- rendezvous hashing of the (merge-resolved) map id over
the pool's live members, membership by Zenoh liveliness (``shared/members.py``) --
queries the database and verifies candidates (the costly part: scoring, consistency,
Sim(3) RANSAC, neighbour confirmation). Why not partition the database by map and
fan inter-map queries out through a queryable: a merge query must reach every other
map, so every keyframe would cost a round of queries to all members plus shipping
candidate keyframes' features back for verification; and a member's death would lose
its partition until rebuilt from Redis. With the database replicated, a query is
local, and when a member dies (its liveliness token is withdrawn) its maps pass to
the others, which hold every keyframe already. The cost: each member holds the whole
database (every keyframe's features, points and BoW vector) and converts every
keyframe to BoW. A map whose
owner changes starts its consistency check afresh (``consistency`` keyframes).
"""

from __future__ import annotations

import logging
import queue
import threading
import time

from shared import keys
from shared.geometry import Sim3
from shared.members import Members
from shared.messages import DecodeError, KeyframeEvent, MapMerged
from shared.metrics import PROCESSING, REJECTED, UP
from shared.settings import Settings
from shared.transport import Bus, drain, open_session

from .metrics import DB_KEYFRAMES, KEYFRAMES, MATCHES_PUBLISHED, QUERY_SECONDS, VERIFIED
from .recognizer import PlaceRecognizer, RecognizerParams
from .vocabulary import Vocabulary

log = logging.getLogger(__name__)
SERVICE = "placerec"


class PlacerecService:
    def __init__(self, settings: Settings, voc: Vocabulary | None = None) -> None:
        self.settings = settings
        path = settings.placerec.vocabulary or None
        self.rec = PlaceRecognizer(
            voc or Vocabulary.load(path), RecognizerParams.from_settings(settings.placerec)
        )
        self.q: queue.Queue = queue.Queue()
        self._stop = threading.Event()
        self.session = None
        self.bus: Bus | None = None
        self._thread = threading.Thread(target=self._run, name="placerec", daemon=True)
        self.members: Members | None = None  # alone (tests) when None
        self.queried: dict[str, int] = {}  # map -> keyframes this instance queried

    def handle(self, key: str, payload: bytes) -> list:
        """Decode and process one sample (the worker's body; tests call it directly)."""
        if key.endswith("/merged"):
            try:
                m = MapMerged.decode(payload)
            except DecodeError as e:
                REJECTED.labels(SERVICE, key, "invalid").inc()
                log.warning("rejected merge note on %s: %s", key, e)
                return []
            n = self.rec.on_merged(m.source, m.target, m.S_t_s)
            log.info("map %s merged into %s: %d keyframes relabelled", m.source, m.target, n)
            return []
        try:
            ev = KeyframeEvent.decode(payload)
            if keys.map_of(key) not in (None, ev.map_id):
                raise DecodeError(f"map {ev.map_id!r} sent on the key of {keys.map_of(key)!r}")
        except (DecodeError, ValueError) as e:
            REJECTED.labels(SERVICE, key, "invalid").inc()
            log.warning("rejected keyframe event on %s: %s", key, e)
            return []
        t0 = time.perf_counter()
        mine = self.members is None or self.members.mine(self.rec.resolve(ev.map_id))
        matches = self.rec.process(ev, query=mine)
        KEYFRAMES.labels("queried" if mine else "stored").inc()
        if mine:
            m = self.rec.resolve(ev.map_id)
            self.queried[m] = self.queried.get(m, 0) + 1
        t = self.rec.last
        QUERY_SECONDS.observe(t.query_s)
        PROCESSING.labels(SERVICE, "keyframe").observe(time.perf_counter() - t0)
        VERIFIED.labels("accepted").inc(t.accepted)
        VERIFIED.labels("rejected").inc(t.verified - t.accepted)
        DB_KEYFRAMES.set(len(self.rec.db))
        for m in matches:
            kind = "merge" if m.query_map != m.cand_map else "loop"
            MATCHES_PUBLISHED.labels(kind).inc()
            log.info("%s match: kf %d (%s) <-> kf %d (%s), %d inliers, scale %.3f", kind,
                     m.query_gid, m.query_map, m.cand_gid, m.cand_map, m.inliers,
                     Sim3.from_matrix(m.S_q_c).s)  # fmt: skip
            if self.bus is not None:
                self.bus.put(keys.MATCH, m.encode())
        return matches

    def _run(self) -> None:
        drain(self.q, self._stop, lambda item: self.handle(item.key, item.payload), SERVICE,
              "place recognition")  # fmt: skip

    def start(self) -> None:
        self.session = open_session(self.settings.zenoh)
        self.bus = Bus(self.session, SERVICE, self.settings.inject)
        self.members = Members(self.session, SERVICE)
        self.bus.subscribe(keys.ALL_MAP_KF, q=self.q)
        self.bus.subscribe(keys.ALL_MAP_MERGED, q=self.q)
        self._thread.start()
        UP.labels(SERVICE).set(1)
        log.info("placerec %s running: vocabulary of %d words", self.members.id,
                 self.rec.voc.n_words)  # fmt: skip

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=10)
        UP.labels(SERVICE).set(0)
        if self.members is not None:
            self.members.close()
        if self.bus:
            self.bus.close()
        if self.session is not None:
            self.session.close()
            self.session = None
