"""The simulated agents of the load tests keep real time: split over processes, no
busy waiting between frames, and how far behind real time they ran is reported."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import zenoh

from services.agent.sim_agent import SimAgent
from services.agent.sim_cli import child_argv, partition
from services.agent.sim_runner import SimAgentRunner
from services.cli import build_parser
from shared import keys
from shared.messages import Ack, KeyframeBatch
from shared.settings import Settings, ZenohSettings
from shared.trajectory import Trajectory, load_euroc_gt
from shared.transport import zenoh_config

ROOT = Path(__file__).resolve().parents[1]


def test_partition_covers_every_agent_once():
    for first, count, k in [(0, 24, 4), (0, 3, 2), (5, 7, 3), (0, 4, 4), (2, 1, 8)]:
        parts = partition(first, count, k)
        ids = [i for a, n in parts for i in range(a, a + n)]
        assert ids == list(range(first, first + count))
        assert all(0 < n <= k for _, n in parts)


def test_child_command_is_the_same_flight_for_a_slice_of_the_agents():
    p = build_parser()
    args = p.parse_args(["sim-agent", "--id", "r8", "--count", "8", "--traj", "MH01,MH03",
                         "--frames", "0:1200", "--seed", "3", "--speed", "0.5",
                         "--flush-timeout", "60", "--out", "/tmp/x", "--zero-noise"])  # fmt: skip
    child = p.parse_args(child_argv(args, 4, 3))
    for name in ("id", "traj", "frames", "seed", "speed", "flush_timeout", "out", "zero_noise",
                 "world_seed", "scale_drift", "credentials"):  # fmt: skip
        assert getattr(child, name) == getattr(args, name), name
    assert (child.first, child.count, child.per_process) == (4, 3, 0)


class _Bus:
    def put(self, key, payload, reliable=True):
        return True

    def subscribe(self, key, q=None, maxsize=0):
        return q


def test_agent_loop_does_not_wake_every_few_ms_while_nothing_can_be_sent(world):
    gt = load_euroc_gt("MH01")
    sim = SimAgent(Trajectory(gt.stamps_ns[:40], gt.poses[:40]), world, seed=0)
    runner = SimAgentRunner(Settings(), "spin", sim, speed=1.0)
    runner._attach(_Bus())
    wakes = 0
    check = runner.comm.check_timeouts

    def counted(now):
        nonlocal wakes
        wakes += 1
        return check(now)

    runner.comm.check_timeouts = counted
    # Nothing queued (the last send long ago): waiting for the next frame 0.2 s away.
    t_end = time.monotonic() + 0.2
    while (now := time.monotonic()) < t_end:
        runner._service(t_end - now)
    assert wakes <= 15, wakes  # every 20 ms at most (it was every 2 ms: ~100)
    # A keyframe waits for the rate limit only: the loop wakes when it may go out.
    runner.comm.add_keyframe(sim.step()[2].kf)
    runner.comm.last_send = time.monotonic()
    assert runner._wait_for(1.0) > 0.015
    runner.comm.last_send = time.monotonic() - runner.comm.min_interval + 0.005
    assert 0.002 <= runner._wait_for(1.0) <= 0.006


def _acker(session: zenoh.Session) -> list:
    """Acknowledges every keyframe batch at once (a mapper with no work)."""
    stored: dict[str, set[int]] = {}

    def on_batch(sample: zenoh.Sample) -> None:
        b = KeyframeBatch.decode(sample.payload.to_bytes())
        st = stored.setdefault(b.agent, set())
        ids = [k.id for k in b.new_kfs]
        st.update(ids)
        high = 0
        while high in st:
            high += 1
        ack = Ack(b.agent, "m0", np.array(ids, np.int64), np.asarray(b.new_mps.ids, np.int64),
                  high, time.time_ns(), seq=b.seq)  # fmt: skip
        session.put(keys.agent_ack(b.agent), ack.encode(),
                    congestion_control=zenoh.CongestionControl.BLOCK)  # fmt: skip

    return [session.declare_subscriber("hivemap/agent/*/up/kf", on_batch)]


def test_agents_split_over_processes_fly_in_real_time_and_say_so(zenoh_router, tmp_path):
    client = ZenohSettings(mode="client", connect=[zenoh_router])
    with zenoh.open(zenoh_config(client)) as session:
        subs = _acker(session)
        env = {**os.environ, "PYTHONPATH": str(ROOT), "HIVEMAP_LOG_LEVEL": "WARNING",
               "HIVEMAP_ZENOH__CONNECT": json.dumps([zenoh_router])}  # fmt: skip
        rc = subprocess.run(
            [sys.executable, "-m", "services.cli", "sim-agent", "--id", "lg", "--count", "3",
             "--per-process", "2", "--traj", "MH01,MH02", "--frames", "0:60",
             "--flush-timeout", "10", "--out", str(tmp_path)],
            env=env, cwd=ROOT, stdout=subprocess.DEVNULL, timeout=120,
        ).returncode  # fmt: skip
        for s in subs:
            s.undeclare()
    assert rc == 0
    stats = {f.name: json.loads(f.read_text()) for f in tmp_path.glob("*_stats.json")}
    assert sorted(stats) == [f"lg-{i}_stats.json" for i in range(3)]
    for st in stats.values():
        assert st["all_acked"] and st["keyframes"] > 0
        assert abs(st["nominal_flight_s"] - 59 / 20) < 0.01  # 60 frames at 20 Hz
        assert st["flight_s"] - st["nominal_flight_s"] < 0.5  # kept real time
