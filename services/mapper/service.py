"""The mapper service: Zenoh in, Redis and acks out.

Zenoh callbacks only enqueue. One worker drains keyframe batches in arrival order,
registers them through the agent's handler, writes the result to Redis in one
transaction and only then acknowledges, so an ack always means "stored". A second
worker turns live poses into map-frame poses for the API. Bad bytes are counted in
``hivemap_messages_rejected_total``, logged, and dropped; nothing already stored is
touched. On start the handlers are rebuilt from Redis, so a killed mapper resumes.
"""

from __future__ import annotations

import logging
import queue
import threading
import time

import numpy as np
import redis

from shared import keys
from shared.geometry import Sim3
from shared.messages import Ack, DecodeError, KeyframeBatch, PoseUpdate
from shared.metrics import KEYFRAME_LATENCY, MAP_SIZE, PROCESSING, REJECTED, STORED, UP
from shared.settings import Settings
from shared.store import Store, connect
from shared.transport import Bus, Received, open_session

from .registration import AgentHandler, IngestResult

log = logging.getLogger(__name__)
SERVICE = "mapper"


def initial_map_id(agent: str) -> str:
    return f"map-{agent}"


class MapperService:
    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.store = Store(connect(settings.redis_url))
        self.handlers: dict[str, AgentHandler] = {}
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.session = None
        self.bus: Bus | None = None
        self._pose_sent: dict[str, float] = {}

    # --- state ------------------------------------------------------------------------
    def load(self) -> None:
        """Rebuild every agent handler from Redis."""
        for agent in self.store.agents():
            info = self.store.agent_info(agent)
            if info is None:
                continue
            h = AgentHandler(agent, info["map_id"], info["S_m_l"])
            for kf in self.store.keyframes(agent):
                h.poses[kf.id] = kf.T_m_kf
                if kf.T_l_kf is not None:
                    h.local_poses[kf.id] = kf.T_l_kf
            h.mp_ids = set(self.store.mappoint_ids(agent))
            self.handlers[agent] = h
            log.info("resumed agent %s: %d keyframes, %d map points", agent, len(h.poses),
                     len(h.mp_ids), extra={"agent": agent})  # fmt: skip

    def handler(self, agent: str) -> AgentHandler:
        h = self.handlers.get(agent)
        if h is None:
            h = AgentHandler(agent, initial_map_id(agent), Sim3.identity())
            pipe = self.store.pipeline()
            Store.add_agent(pipe, agent, h.map_id, h.S_m_l, time.time_ns())
            pipe.execute()
            self.handlers[agent] = h
            log.info("new agent %s with map %s", agent, h.map_id, extra={"agent": agent})
        return h

    # --- processing (transport-free, called by the worker and by tests) ------------------
    def process_kf_bytes(self, key: str, payload: bytes, recv_ns: int) -> Ack | None:
        agent_key = keys.agent_of(key) or "?"
        t0 = time.perf_counter()
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
        h = self.handler(batch.agent)
        res = h.ingest(batch, time.monotonic())
        self._write(h, res)
        ack = Ack(batch.agent, h.map_id, np.array(res.ack_kf_ids, np.int64),
                  np.array(res.ack_mp_ids, np.int64), h.kf_high, time.time_ns())  # fmt: skip
        if self.bus is not None:
            self.bus.put(keys.agent_ack(batch.agent), ack.encode())
        now_ns = time.time_ns()
        for _kf in res.keyframes:
            KEYFRAME_LATENCY.labels(batch.agent).observe((now_ns - recv_ns) * 1e-9)
        STORED.labels(SERVICE, "keyframe").inc(len(res.keyframes))
        STORED.labels(SERVICE, "map_point").inc(len(res.mp_ids))
        MAP_SIZE.labels(h.map_id).set(len(h.poses))
        PROCESSING.labels(SERVICE, "kf_batch").observe(time.perf_counter() - t0)
        return ack

    def _write(self, h: AgentHandler, res: IngestResult) -> None:
        if not res.changed:
            return
        pipe = self.store.pipeline()
        for kf in res.keyframes:
            Store.put_keyframe(pipe, kf)
        for kid, T, upd in res.pose_updates:
            Store.set_keyframe_pose(pipe, h.agent, kid, T)
            pipe.hset(
                f"hm:kf:{h.agent}:{kid}",
                mapping={"pred": upd.pred_id, "parent": upd.parent_id,
                         "T_pred": upd.T_pred_kf.astype("<f8").tobytes(),
                         "T_par": upd.T_par_kf.astype("<f8").tobytes()},
            )  # fmt: skip
            if upd.mp_ids is not None:
                pipe.hset(f"hm:kf:{h.agent}:{kid}", "mpids", upd.mp_ids.astype("<i8").tobytes())
        if len(res.mp_ids):
            Store.put_map_points(pipe, h.agent, h.map_id, res.mp_ids, res.mp_ref, res.mp_p_ref,
                                 res.mp_pos, res.mp_desc)  # fmt: skip
        if len(res.upd_mp_ids):
            Store.put_map_points(pipe, h.agent, h.map_id, res.upd_mp_ids, res.upd_mp_ref,
                                 res.upd_mp_p_ref, res.upd_mp_pos, None)  # fmt: skip
        Store.set_kf_high(pipe, h.agent, h.kf_high)
        pipe.execute()

    def process_pose_bytes(self, key: str, payload: bytes, recv_ns: int) -> dict | None:
        agent_key = keys.agent_of(key) or "?"
        try:
            p = PoseUpdate.decode(payload)
            if p.agent != agent_key:
                raise DecodeError(f"agent {p.agent!r} sent on the key of {agent_key!r}")
        except (DecodeError, ValueError) as e:
            REJECTED.labels(SERVICE, key, _reason(e)).inc()
            log.warning("rejected pose on %s: %s", key, e, extra={"key": key})
            return None
        h = self.handlers.get(p.agent)
        if h is None:
            return None  # no keyframe yet: no map frame to place it in
        T = h.pose_of(p.kf_ref, p.T_ref_c)
        if T is None:
            return None
        doc = {
            "agent": p.agent, "map_id": h.map_id, "stamp_ns": p.stamp_ns, "T_m_c": T,
            "kf_ref": p.kf_ref, "tracking": p.tracking, "fps": p.fps, "recv_ns": recv_ns,
        }  # fmt: skip
        self.store.put_pose(p.agent, doc)
        return doc

    # --- service loop -------------------------------------------------------------------
    def start(self) -> None:
        self.load()
        self.session = open_session(self.settings.zenoh)
        self.bus = Bus(self.session, SERVICE, self.settings.inject)
        self.kf_q = self.bus.subscribe(keys.ALL_AGENT_KF)
        self.pose_q = self.bus.subscribe(keys.ALL_AGENT_POSE, maxsize=256)
        for name, fn in (("kf", self._kf_worker), ("pose", self._pose_worker)):
            t = threading.Thread(target=fn, name=f"mapper-{name}", daemon=True)
            t.start()
            self._threads.append(t)
        UP.labels(SERVICE).set(1)
        log.info("mapper running")

    def _kf_worker(self) -> None:
        while not self._stop.is_set():
            try:
                item: Received = self.kf_q.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                self.process_kf_bytes(item.key, item.payload, item.recv_ns)
            except redis.RedisError:
                # Not acked, so the agent resends once Redis is back.
                log.exception("redis write failed; batch not acknowledged")
            except Exception:
                REJECTED.labels(SERVICE, item.key, "internal").inc()
                log.exception("keyframe batch failed", extra={"key": item.key})

    def _pose_worker(self) -> None:
        while not self._stop.is_set():
            try:
                item: Received = self.pose_q.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                self.process_pose_bytes(item.key, item.payload, item.recv_ns)
            except Exception:
                log.exception("pose failed", extra={"key": item.key})

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=5)
        UP.labels(SERVICE).set(0)
        if self.bus:
            self.bus.close()
        if self.session is not None:
            self.session.close()
            self.session = None
        self.store.r.close()


def _reason(e: Exception) -> str:
    msg = str(e)
    if "not msgpack" in msg:
        return "malformed"
    if "version" in msg:
        return "version"
    if "schema" in msg:
        return "schema"
    return "invalid"
