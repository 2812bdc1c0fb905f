"""Overload at small scale: a mapper throttled to a sixth of the wall clock (stopped
and continued by signals, as cpulimit does) with simulated agents that keep flying.

What must hold (issue 18 item 2): no crash; the latency of what the mapper accepts stays
bounded, because the agents' windows keep the backlog in their own buffers; the agents
do not bury the server under resends; and once they stop, every keyframe they made is
stored and acknowledged.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import pytest
from prometheus_client.parser import text_string_to_metric_families

from shared.redis_server import free_port
from shared.runtime import set_priority
from shared.store import Store, connect

HIVEMAP = str(Path(sys.executable).with_name("hivemap"))
# Eight agents at a sixth: with six at a fifth, a CI run on a fast machine kept up
# (accepted p95 0.73 s, no batch shed) and the overload under test never happened.
AGENTS = 8
RUN_S, STOP_S = 0.025, 0.125  # the mapper gets 1/6 of the wall clock


def _quantile(buckets: list[tuple[float, float]], q: float) -> float:
    """Upper bound of the bucket holding the q-quantile of a cumulative histogram."""
    total = buckets[-1][1]
    return next(le for le, n in buckets if n >= q * total)


def _shed(text: str) -> dict[str, float]:
    return {s.labels["what"]: s.value for fam in text_string_to_metric_families(text)
            if fam.name == "hivemap_mapper_shed" for s in fam.samples
            if s.name.endswith("_total")}  # fmt: skip


def _latency_buckets(text: str) -> list[tuple[float, float]]:
    acc: dict[float, float] = {}
    for fam in text_string_to_metric_families(text):
        if fam.name != "hivemap_keyframe_latency_seconds":
            continue
        for s in fam.samples:
            if s.name.endswith("_bucket"):
                le = float(s.labels["le"])
                acc[le] = acc.get(le, 0.0) + s.value
    return sorted(acc.items())


class Throttle:
    """SIGSTOP/SIGCONT duty cycle on a process."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            os.kill(self.pid, signal.SIGSTOP)
            time.sleep(STOP_S)
            os.kill(self.pid, signal.SIGCONT)
            time.sleep(RUN_S)

    def __enter__(self):
        self._t.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._t.join()
        os.kill(self.pid, signal.SIGCONT)


@pytest.mark.slow
def test_throttled_mapper_bounds_accepted_latency_and_agents_back_off(
    redis_url, zenoh_router, tmp_path
):
    port = free_port()
    env = {**os.environ, "HIVEMAP_REDIS_URL": redis_url, "HIVEMAP_ZENOH__MODE": "client",
           "HIVEMAP_ZENOH__CONNECT": json.dumps([zenoh_router]), "HIVEMAP_LOG_LEVEL": "WARNING",
           # Every keyframe must stay stored to be counted: no culling here.
           "HIVEMAP_MAPPER__REDUNDANCY": "false",
           # Eight agents: a smaller overload than the bench's 48, so batches are shed
           # sooner (the default is 0.5 s), or the agents' windows alone would bound the
           # queue here and the shedding (NACK, resend, the hole rule) would go untested.
           "HIVEMAP_MAPPER__SHED_AFTER_S": "0.3"}  # fmt: skip
    mapper = subprocess.Popen([HIVEMAP, "mapper"], env={**env, "HIVEMAP_METRICS_PORT": str(port)})
    agents = None
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=1).read()
                break
            except OSError:
                time.sleep(0.2)
        t0 = time.monotonic()
        with Throttle(mapper.pid):
            # The agents in their own session at lower priority, as in the load benches:
            # what is measured is the server's overload, not theirs.
            agents = subprocess.Popen(
                [HIVEMAP, "sim-agent", "--id", "ov", "--count", str(AGENTS),
                 "--traj", "MH01,MH02,MH03", "--frames", "800:1200", "--speed", "2",
                 "--flush-timeout", "120", "--out", str(tmp_path)],
                env=env, stdout=subprocess.DEVNULL, start_new_session=True,
                preexec_fn=lambda: set_priority(10),
            )  # fmt: skip
            agents.wait(300)
            elapsed = time.monotonic() - t0
        assert mapper.poll() is None, "the mapper died"
        text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read()
    finally:
        if agents is not None and agents.poll() is None:
            agents.kill()
        mapper.send_signal(signal.SIGCONT)
        mapper.terminate()
        mapper.wait(30)
    store = Store(connect(redis_url))
    stats = [json.loads((tmp_path / f"ov-{i}_stats.json").read_text()) for i in range(AGENTS)]
    made = sum(s["keyframes"] for s in stats)
    resent = sum(s["kf_resent"] for s in stats)
    lost = sum(s["kf_lost_unacked"] for s in stats)
    buckets = _latency_buckets(text.decode())
    p95 = _quantile(buckets, 0.95)
    flights = [s["flight_s"] for s in stats]
    kbps = [s["bytes"] / s["duration_s"] / 1e3 for s in stats]
    after = elapsed - max(flights)  # from the end of the last flight to the agents' exit
    print(f"\n{AGENTS} agents, {made} keyframes, mapper at {RUN_S / (RUN_S + STOP_S):.0%}: "
          f"accepted latency p95 <= {p95:.2f} s, {resent} keyframes resent "
          f"({resent / made:.1%}), {lost} lost unacked, {min(kbps):.0f}-{max(kbps):.0f} "
          f"kB/s per agent, flights {min(flights):.0f}-{max(flights):.0f} s, agents done "
          f"{after:.0f} s after the flights; shed {_shed(text.decode())}; latency "
          f"histogram {[(le, int(n)) for le, n in buckets if le >= 0.1]}")  # fmt: skip
    # Nothing is lost: every keyframe made is stored and acknowledged within 60 s of the
    # end of the flights (the agents' buffers hold the backlog however long it lasts).
    for s in stats:
        assert s["kf_lost_unacked"] == 0, s["agent"]
        assert s["all_acked"], s["agent"]
        assert len(store.keyframe_ids(s["agent"])) == s["keyframes"], s["agent"]
    assert after <= 60
    # The server was overloaded: acknowledgements lagged production (the backlog sat in
    # the agents, which is what bounds the latency below), and it shed keyframe batches.
    assert max(s["ack_latency_p95_s"] for s in stats) > 1.0
    assert _shed(text.decode()).get("keyframe_batch", 0) > 0
    # What the mapper accepts waited at most shed_after_s (0.3 s here) in its queue; the
    # rest of its latency is the registration and store of its group, and with the mapper
    # stopped 5/6 of the time those alone take up to a second or more, so the bound here
    # is the bucket above the 1 s bar (bench_ramp --overload checks 1 s at 48 agents on
    # an unthrottled mapper). Without shedding and the agents' windows the queue grew
    # with the flight (>= 10 s at 32 agents, issue 18).
    # At a65d6e0: 82 % within 1 s, 99 % within 2 s (main at 85a443d: also <= 2 s).
    assert p95 <= 2.0
    # No resend storm: each agent's traffic over its whole run (flight and flush) is at
    # most 1.3x what sending each of its keyframes once over the flight takes (the
    # issue's bar against a run without overload), and on average a keyframe goes out
    # at most twice (a storm was 3-7x the data).
    for s in stats:
        once = s["bytes"] / (1 + s["kf_resent"] / max(s["keyframes"], 1))
        assert s["bytes"] / s["duration_s"] <= 1.3 * once / s["flight_s"], s["agent"]
    assert resent <= made
