"""Agent health: what agents put in their pose messages, and what the mapper exports."""

from __future__ import annotations

import numpy as np
from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.parser import text_string_to_metric_families

from services.agent.comm import CommModule
from services.agent.health import HealthMeter
from services.mapper.agent_health import DISCONNECTED_AFTER_S, MAX_AGENTS, AgentHealth
from shared.messages import Ack, PoseUpdate


def _pose(agent: str, tracking: str = "ok", **health) -> PoseUpdate:
    return PoseUpdate(agent, 1, np.eye(4), 0, np.eye(4), tracking, **health)


def _samples(h: AgentHealth) -> dict[tuple[str, tuple], float]:
    reg = CollectorRegistry()
    reg.register(h)
    out = {}
    for fam in text_string_to_metric_families(generate_latest(reg).decode()):
        for s in fam.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


def test_meter_reports_rate_drops_traffic_and_acks():
    comm = CommModule("A", rate_hz=100.0)
    m = HealthMeter(frame_period_s=0.05)
    for i in range(21):  # 20 fps, frame 10 tracked 0.2 s after the camera took it
        t = i * 0.05
        m.frame(t + (0.2 if i == 10 else 0.0), due=t)
    comm.record_sent(1000)
    comm.resent_reasons[("kf", "timeout")] = 3
    comm.stats.ack_latencies.extend([0.01] * 9 + [0.1])
    f = m.fields(comm)
    assert 19 < f["fps"] < 21
    assert f["frames_dropped"] == 1
    assert f["bytes_sent"] == 1000 and f["resent"] == 3 and f["kf_lost"] == 0
    assert f["ack_p50_s"] == 0.01 and 0.05 < f["ack_p95_s"] < 0.1
    # They fit a PoseUpdate and survive the wire.
    d = PoseUpdate.decode(_pose("A", **f).encode())
    assert d.resent == 3 and d.ack_p95_s == f["ack_p95_s"]
    # New acks move the percentiles (they are computed again only when acks came).
    comm.stats.ack_latencies.extend([0.5] * 20)
    f2 = m.fields(comm)
    assert f2["ack_p50_s"] == 0.5 and f2["ack_p95_s"] == 0.5
    assert m.fields(comm) == f2


def test_no_acks_yet_no_latency_fields():
    f = HealthMeter().fields(CommModule("A"))
    assert "ack_p50_s" not in f and f["fps"] == 0.0
    c = CommModule("A")
    c.on_ack(Ack("A", "m", np.zeros(0, np.int64), np.zeros(0, np.int64), -1, 0), 0.0)
    assert "ack_p95_s" not in HealthMeter().fields(c)


def test_mapper_exports_each_agent_state_and_counters():
    h = AgentHealth()
    t0 = 100.0
    h.report(_pose("a-0", "ok", fps=20.0, frames_dropped=2, kf_lost=1, bytes_sent=5000,
                   resent=4, ack_p50_s=0.02, ack_p95_s=0.05), now=t0)  # fmt: skip
    h.report(_pose("a-1", "lost", fps=19.0), now=t0)
    h.report(_pose("a-2", "init"), now=t0 - DISCONNECTED_AFTER_S - 1)
    assert [h.state(a, t0) for a in ("a-0", "a-1", "a-2", "nobody")] == [
        "ok", "lost", "disconnected", "disconnected"]  # fmt: skip
    s = _samples(h)
    assert s[("hivemap_agent_fps", (("agent", "a-0"),))] == 20.0
    assert s[("hivemap_agent_resends_total", (("agent", "a-0"),))] == 4
    assert s[("hivemap_agent_sent_bytes_total", (("agent", "a-0"),))] == 5000
    assert s[("hivemap_agent_frames_dropped_total", (("agent", "a-0"),))] == 2
    assert s[("hivemap_agent_keyframes_lost_total", (("agent", "a-0"),))] == 1
    q95 = ("hivemap_agent_ack_latency_recent_seconds", (("agent", "a-0"), ("quantile", "0.95")))
    assert s[q95] == 0.05
    # An agent that sent no counters (a first-version agent) gets no counter series.
    assert ("hivemap_agent_resends_total", (("agent", "a-1"),)) not in s
    assert s[("hivemap_agent_state", (("agent", "a-2"),))] == 3  # disconnected


def test_cardinality_for_64_agents():
    h = AgentHealth()
    for i in range(64):
        h.report(_pose(f"agent-{i}", fps=20.0, frames_dropped=0, kf_lost=0, bytes_sent=1,
                       resent=0, ack_p50_s=0.01, ack_p95_s=0.02))  # fmt: skip
    s = _samples(h)
    series = [k for k in s if not k[0].endswith("_created")]
    assert len(series) == 64 * 9
    # Made-up ids off the wire stop growing the table at MAX_AGENTS.
    for i in range(MAX_AGENTS):
        h.report(_pose(f"x-{i}"))
    assert len(h.reports) == MAX_AGENTS and not h.report(_pose("one-more"))
    assert h.report(_pose("agent-0"))  # known agents still report
