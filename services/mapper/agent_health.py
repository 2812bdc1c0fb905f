"""Agent health, as the agents report it, exported to Prometheus by the mapper.

Agents are robots in the field and are never scraped; each pose message carries the
agent's tracking state, frame rate and cumulative counters (``PoseUpdate``). The mapper
keeps each agent's newest report and a collector turns them into series at scrape time,
so a report costs a dict assignment, and an agent whose reports stop is shown as
disconnected without any timer thread.

Cardinality: one series per agent for each metric (two for the ack latency quantiles),
nine per agent: 576 series for a team of 64. Counters are the agent's own cumulative
counts, exported as counters; an agent that restarts starts again from 0, which
Prometheus's ``rate()`` treats as a counter reset.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.registry import REGISTRY, Collector

from shared.messages import PoseUpdate

# No report for this long: the agent is disconnected (agents report at 10-20 Hz).
DISCONNECTED_AFTER_S = 3.0
# At most this many agents get series: ids come off the wire, and a flood of made-up ones
# must not grow the scrape without bound (4x the 64-agent team this is sized for).
MAX_AGENTS = 256
# hivemap_agent_state's values, and the tracking states agents send.
STATES = {"ok": 0, "init": 1, "lost": 2, "disconnected": 3}


@dataclass
class Report:
    pose: PoseUpdate
    t: float  # monotonic, when received


class AgentHealth(Collector):
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.reports: dict[str, Report] = {}

    def report(self, p: PoseUpdate, now: float | None = None) -> bool:
        """Keep ``p`` as its agent's newest report; False when the table is full."""
        with self._lock:
            if p.agent not in self.reports and len(self.reports) >= MAX_AGENTS:
                return False
            self.reports[p.agent] = Report(p, time.monotonic() if now is None else now)
            return True

    def state(self, agent: str, now: float | None = None) -> str:
        r = self.reports.get(agent)
        now = time.monotonic() if now is None else now
        if r is None or now - r.t > DISCONNECTED_AFTER_S:
            return "disconnected"
        return r.pose.tracking if r.pose.tracking in STATES else "lost"

    def collect(self):
        now = time.monotonic()
        with self._lock:
            reports = dict(self.reports)
        state = GaugeMetricFamily(
            "hivemap_agent_state",
            "Agent state as reported: 0 tracking, 1 initializing, 2 lost, 3 disconnected "
            f"(no report for {DISCONNECTED_AFTER_S:g} s)", labels=["agent"],
        )  # fmt: skip
        age = GaugeMetricFamily(
            "hivemap_agent_report_age_seconds",
            "Seconds since the agent's last report",
            labels=["agent"],
        )
        fps = GaugeMetricFamily("hivemap_agent_fps", "Frames per second the agent tracks",
                                labels=["agent"])  # fmt: skip
        ack = GaugeMetricFamily(
            "hivemap_agent_ack_latency_recent_seconds",
            "Keyframe publish -> ack latency over the agent's most recent acks",
            labels=["agent", "quantile"],
        )
        counters = {
            "frames_dropped": CounterMetricFamily(
                "hivemap_agent_frames_dropped", "Frames not tracked in time (a live camera "
                "would have dropped them)", labels=["agent"]),
            "kf_lost": CounterMetricFamily(
                "hivemap_agent_keyframes_lost", "Keyframes dropped unacknowledged (agent "
                "buffer full)", labels=["agent"]),
            "bytes_sent": CounterMetricFamily(
                "hivemap_agent_sent_bytes", "Payload bytes the agent sent", labels=["agent"]),
            "resent": CounterMetricFamily(
                "hivemap_agent_resends", "Keyframes and map points the agent sent again",
                labels=["agent"]),
        }  # fmt: skip
        for agent, r in sorted(reports.items()):
            p = r.pose
            state.add_metric([agent], STATES[self.state(agent, now)])
            age.add_metric([agent], now - r.t)
            fps.add_metric([agent], p.fps)
            for name, fam in counters.items():
                v = getattr(p, name)
                if v is not None:
                    fam.add_metric([agent], v)
            if p.ack_p50_s is not None and p.ack_p95_s is not None:
                ack.add_metric([agent, "0.5"], p.ack_p50_s)
                ack.add_metric([agent, "0.95"], p.ack_p95_s)
        yield from (state, age, fps, ack, *counters.values())

    def describe(self):
        return []  # collected at scrape time only: the agents are not known up front


# One per process, like every other metric of the default registry.
HEALTH = AgentHealth()
REGISTRY.register(HEALTH)
