"""Runs :class:`SimAgent` against a real server over Zenoh: the load-test agent.

The loop is paced by the trajectory's timestamps divided by ``speed`` (0 = as fast
as possible) and waits for acks between frames instead of sleeping. At the end it
keeps resending until everything is acknowledged or ``flush_timeout_s`` passes.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from shared import keys
from shared.geometry import se3_inv
from shared.messages import Ack, DecodeError, PoseUpdate
from shared.metrics import AGENT_ACK_LATENCY, REJECTED, RESENT
from shared.settings import Settings
from shared.trajectory import Trajectory
from shared.transport import Bus, open_session

from .comm import CommModule
from .health import HealthMeter
from .sim_agent import SimAgent

log = logging.getLogger(__name__)


@dataclass
class RunStats:
    agent: str
    frames: int = 0
    keyframes: int = 0
    map_points: int = 0
    acked_keyframes: int = 0
    messages: int = 0
    bytes: int = 0
    kf_resent: int = 0
    kf_lost_buffer_full: int = 0
    resent: dict = field(default_factory=dict)
    duration_s: float = 0.0
    flight_s: float = 0.0
    ack_latency_median_s: float = float("nan")
    ack_latency_p95_s: float = float("nan")
    bytes_per_s: float = 0.0
    all_acked: bool = False
    # (seconds since the start of the flight, ack latency) per keyframe, for plots of
    # latency over a run.
    ack_series: list = field(default_factory=list)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["resent"] = {f"{k[0]}_{k[1]}": v for k, v in self.resent.items()}
        return d


class SimAgentRunner:
    def __init__(
        self,
        settings: Settings,
        agent_id: str,
        sim: SimAgent,
        speed: float = 1.0,
        buffer_kfs: int = 100,
        flush_timeout_s: float = 30.0,
        stop: threading.Event | None = None,
    ) -> None:
        keys.check_id(agent_id, "agent")
        self.settings = settings
        self.agent = agent_id
        self.sim = sim
        self.speed = speed
        self.buffer_kfs = buffer_kfs
        self.flush_timeout_s = flush_timeout_s
        self.stop_event = stop or threading.Event()
        c = settings.comm
        self.comm = CommModule.from_settings(agent_id, c)
        self.stats = RunStats(agent_id)
        self.estimates: list[tuple[int, np.ndarray]] = []
        self.kf_ref = -1
        self.T_l_ref = np.eye(4)
        st = sim.traj.stamps_ns
        period = float(np.median(np.diff(st))) * 1e-9 / speed if len(st) > 1 and speed > 0 else None
        self.health = HealthMeter(period)

    def run(self, bus: Bus | None = None) -> RunStats:
        if bus is not None:
            return self._run(bus)
        with open_session(self.settings.zenoh) as session:
            b = Bus(session, "agent", self.settings.inject)
            try:
                return self._run(b)
            finally:
                b.close()

    def _run(self, bus: Bus) -> RunStats:
        ack_q = bus.subscribe(keys.agent_ack(self.agent))
        kf_key, pose_key = keys.agent_kf(self.agent), keys.agent_pose(self.agent)
        traj: Trajectory = self.sim.traj
        t_start = time.monotonic()
        stamp0 = int(traj.stamps_ns[0])
        pose_interval = 1.0 / self.settings.comm.pose_rate_hz
        last_pose = -1e18
        while not self.sim.done and not self.stop_event.is_set():
            due = None
            if self.speed > 0:
                due = (
                    t_start
                    + (int(traj.stamps_ns[self.sim.state.frame]) - stamp0) * 1e-9 / self.speed
                )
                self._service(bus, ack_q, kf_key, until=due)
            stamp, T_l_c, kf = self.sim.step()
            self.stats.frames += 1
            self.health.frame(time.monotonic(), due)
            self.estimates.append((stamp, T_l_c))
            if kf is not None:
                self.comm.add_keyframe(kf.kf)
                self.comm.add_map_points(kf.new_mps)
                self.stats.keyframes += 1
                self.stats.map_points += len(kf.new_mps)
                self.kf_ref, self.T_l_ref = kf.kf.id, kf.kf.T_l_kf
                self._trim()
            now = time.monotonic()
            if now - last_pose >= pose_interval and self.kf_ref >= 0:
                last_pose = now
                msg = PoseUpdate(
                    self.agent,
                    stamp,
                    T_l_c,
                    self.kf_ref,
                    se3_inv(self.T_l_ref) @ T_l_c,
                    "ok",
                    **self.health.fields(self.comm),
                )
                data = msg.encode()
                bus.put(pose_key, data, reliable=False)
                self.health.pose_bytes += len(data)
            self._service(bus, ack_q, kf_key, until=None)
        self.stats.flight_s = time.monotonic() - t_start
        deadline = time.monotonic() + self.flush_timeout_s
        while self.comm.pending and time.monotonic() < deadline and not self.stop_event.is_set():
            self._service(bus, ack_q, kf_key, until=min(deadline, time.monotonic() + 0.05))
        return self._finish(t_start)

    def _trim(self) -> None:
        # CCM-SLAM §4.2: past N + B keyframes the oldest unacknowledged ones are lost.
        while len(self.comm.kfs) > self.buffer_kfs:
            oldest = min(self.comm.kfs)
            self.comm.forget_keyframe(oldest)
            self.stats.kf_lost_buffer_full += 1

    def _service(self, bus: Bus, ack_q: queue.Queue, kf_key: str, until: float | None) -> None:
        """Send what is due and handle acks; with ``until``, keep at it until then."""
        while True:
            now = time.monotonic()
            self.comm.check_timeouts(now)
            msg = self.comm.next_message(now, time.time_ns(), self.kf_ref)
            if msg is not None:
                data = msg.encode()
                bus.put(kf_key, data)
                self.comm.record_sent(len(data))
            while True:
                try:
                    item = ack_q.get_nowait()
                    self._on_ack(item.payload, item.key)
                except queue.Empty:
                    break
            if until is None:
                return
            remaining = until - time.monotonic()
            if remaining <= 0:
                return
            next_send = self.comm.last_send + self.comm.min_interval - time.monotonic()
            wait = min(remaining, max(next_send, 0.002), 0.05)
            with contextlib.suppress(queue.Empty):
                item = ack_q.get(timeout=wait)
                self._on_ack(item.payload, item.key)

    def _on_ack(self, payload: bytes, key: str) -> None:
        try:
            ack = Ack.decode(payload)
        except DecodeError as e:
            REJECTED.labels("agent", key, "invalid").inc()
            log.warning("bad ack: %s", e)
            return
        for lat in self.comm.on_ack(ack, time.monotonic()):
            AGENT_ACK_LATENCY.labels(self.agent).observe(lat)

    def _finish(self, t_start: float) -> RunStats:
        s, c = self.stats, self.comm
        s.duration_s = time.monotonic() - t_start
        s.messages, s.bytes = c.stats.messages, c.stats.bytes
        s.kf_resent = c.stats.kf_resent
        s.resent = dict(c.resent_reasons)
        for (kind, reason), n in c.resent_reasons.items():
            RESENT.labels(self.agent, kind, reason).inc(n)
        s.acked_keyframes = len(c.acked_kfs)
        lat = np.array(c.stats.ack_latencies)
        if len(lat):
            s.ack_latency_median_s = float(np.median(lat))
            s.ack_latency_p95_s = float(np.percentile(lat, 95))
        s.bytes_per_s = s.bytes / s.flight_s if s.flight_s > 0 else 0.0
        s.all_acked = not c.pending
        pairs = zip(c.stats.ack_sent_at, c.stats.ack_latencies, strict=True)
        s.ack_series = [[round(t - t_start, 3), round(x, 4)] for t, x in pairs]
        return s
