"""End to end: simulated agents -> real Zenoh router -> mapper -> real Redis.

Nothing is mocked: a Python Zenoh router and a private redis-server per test
session, the mapper in-process (or as a real child process for the crash test).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from procs import gt_part

from services.agent.sim_agent import DriftModel, SimAgent
from services.agent.sim_runner import SimAgentRunner
from services.mapper.service import MapperService
from shared import keys
from shared.messages import packb
from shared.metrics import sample_value
from shared.settings import InjectSettings, Settings
from shared.store import Store, connect
from shared.transport import Bus, open_session


@pytest.fixture()
def settings(settings):
    """Keyframe culling off: these tests check that every keyframe is kept."""
    return settings.model_copy(
        update={"mapper": settings.mapper.model_copy(update={"redundancy": False})}
    )


@pytest.fixture()
def mapper(request, settings):
    s = settings
    if "chain_only" in request.keywords:
        # Registration by relative poses alone (no refinement against the map), so
        # the server map must equal the agent's own chained estimate.
        s = settings.model_copy(update={"mapper": settings.mapper.model_copy(update={
            "refine_poses": False, "scale_correction": False, "fuse": False})})  # fmt: skip
    m = MapperService(s)
    m.start()
    yield m
    m.stop()


def _run_agent(settings, agent, sim, **kw):
    return SimAgentRunner(settings, agent, sim, speed=kw.pop("speed", 0), **kw).run()


def test_zero_noise_trajectory_equals_ground_truth(settings, mapper, world):
    gt = gt_part("MH01", 900, 1700)
    stats = _run_agent(settings, "A", SimAgent(gt, world, drift=DriftModel.zero()))
    assert stats.all_acked and stats.keyframes > 30
    ids, stamps, T_m = Store(connect(settings.redis_url)).trajectory("A")
    assert len(ids) == stats.keyframes
    # The agent's local map (= server map, S_m_l = identity) starts at the first camera.
    T_w_m = gt.poses[0]
    idx = np.searchsorted(gt.stamps_ns, stamps)
    np.testing.assert_array_equal(gt.stamps_ns[idx], stamps)
    err = np.linalg.norm((T_w_m @ T_m)[:, :3, 3] - gt.poses[idx][:, :3, 3], axis=1)
    assert err.max() < 1e-6


@pytest.mark.chain_only
def test_noisy_trajectory_equals_agent_chained_estimate(settings, mapper, world):
    gt = gt_part("MH02", 600, 1400)
    drift = DriftModel(rot_deg_per_sqrt_m=0.5, trans_m_per_sqrt_m=0.05, scale_drift_per_s=0.01)
    sim = SimAgent(gt, world, drift=drift, seed=3)
    runner = SimAgentRunner(settings, "N", sim, speed=0)
    est = {}
    orig = runner.comm.add_keyframe

    def spy(kf):
        est[kf.id] = kf.T_l_kf.copy()
        orig(kf)

    runner.comm.add_keyframe = spy
    stats = runner.run()
    assert stats.all_acked
    ids, stamps, T_m = Store(connect(settings.redis_url)).trajectory("N")
    assert list(ids) == sorted(est)
    E = np.stack([est[i] for i in ids])
    np.testing.assert_allclose(T_m, E, atol=1e-9)
    # and it really drifted away from the ground truth
    idx = np.searchsorted(gt.stamps_ns, stamps)
    assert (
        np.linalg.norm((gt.poses[0] @ T_m)[:, :3, 3] - gt.poses[idx][:, :3, 3], axis=1).max() > 0.05
    )


def test_twenty_percent_loss_every_keyframe_stored(settings, mapper, world):
    # 2x real time, both runs paced alike so their byte counts compare.
    gt = gt_part("MH03", 300, 700)
    clean = _run_agent(settings, "C", SimAgent(gt, world, drift=DriftModel.zero(), seed=1),
                       speed=2.0)  # fmt: skip
    lossy_settings = settings.model_copy(update={"inject": InjectSettings(drop=0.2, seed=5)})
    lossy = _run_agent(lossy_settings, "L", SimAgent(gt, world, drift=DriftModel.zero(), seed=1),
                       speed=2.0, flush_timeout_s=60)  # fmt: skip
    store = Store(connect(settings.redis_url))
    assert lossy.all_acked and lossy.kf_lost_unacked == 0
    assert store.keyframe_ids("L") == list(range(lossy.keyframes))
    assert len(store.mappoint_ids("L")) == lossy.map_points
    drops = sample_value("hivemap_injected_drops_total",
                         {"service": "agent", "key": keys.agent_kf("L")})  # fmt: skip
    assert drops > 0
    extra = lossy.bytes / clean.bytes - 1.0
    print(f"\n20% loss: {int(drops)} kf messages dropped, {lossy.kf_resent} keyframes resent, "
          f"{extra:+.0%} bytes vs lossless ({lossy.bytes} vs {clean.bytes})")  # fmt: skip
    assert lossy.kf_resent > 0 and extra > 0


GARBAGE = [b"", b"\x00\x01\x02", b"\xc1" * 50, packb({"schema": "hivemap.kf_batch/9"}),
           packb({"schema": "hivemap.pose/7", "agent": "G"}), packb([1, 2])]  # fmt: skip


def test_garbage_on_every_subscribed_key_is_counted_and_service_keeps_serving(
    settings, mapper, world
):
    def rejected(key: str) -> float:
        return sum(
            sample_value("hivemap_messages_rejected_total",
                         {"service": "mapper", "key": key, "reason": r})
            for r in ("malformed", "version", "schema", "invalid")
        )  # fmt: skip

    kf_key, pose_key = keys.agent_kf("G"), keys.agent_pose("G")
    ack_key = keys.agent_ack("G")
    before = rejected(kf_key), rejected(pose_key)
    agent_labels = {"service": "agent", "key": ack_key, "reason": "invalid"}
    agent_before = sample_value("hivemap_messages_rejected_total", agent_labels)
    good = gt_part("MH01", 1000, 1300)
    valid = SimAgentRunner(settings, "G", SimAgent(good, world, drift=DriftModel.zero()), 2.0)
    result = {}
    t = threading.Thread(target=lambda: result.setdefault("stats", valid.run()))
    t.start()
    with open_session(settings.zenoh) as session:
        bus = Bus(session, "test")
        # A well-formed batch of another agent sent on G's key is rejected too.
        sneaky = SimAgent(good, world, drift=DriftModel.zero())
        _, _, kf = sneaky.step()
        from shared.messages import KeyframeBatch

        # And G's own batches with a session that is not one (a negative, a string).
        spoofs = [KeyframeBatch("H", 0, 0, 0, [kf.kf]).encode(),
                  KeyframeBatch("G", 0, 0, 0, [kf.kf], session=-1).encode(),
                  KeyframeBatch("G", 0, 0, 0, [kf.kf], session="x").encode()]  # fmt: skip
        deadline = time.monotonic() + 10
        while not valid.comm.acked_kfs and time.monotonic() < deadline:
            time.sleep(0.05)  # G is flying and subscribed to its acks
        for g in [*GARBAGE, *spoofs]:
            bus.put(kf_key, g)
            bus.put(pose_key, g)
        # The agent's own subscription (acks) gets garbage as well.
        for g in GARBAGE:
            bus.put(ack_key, g)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and (
            rejected(kf_key) - before[0] < len(GARBAGE) + len(spoofs)
            or rejected(pose_key) - before[1] < len(GARBAGE) + len(spoofs)
        ):
            time.sleep(0.05)
        bus.close()
    t.join(60)
    assert rejected(kf_key) - before[0] == len(GARBAGE) + len(spoofs)
    assert rejected(pose_key) - before[1] == len(GARBAGE) + len(spoofs)
    agent_after = sample_value("hivemap_messages_rejected_total", agent_labels)
    assert agent_after - agent_before == len(GARBAGE)
    assert Store(connect(settings.redis_url)).keyframe_ids("H") == []
    assert Store(connect(settings.redis_url)).agents() == ["G"]  # no flight of garbage
    # Both services kept serving: the valid agent was fully stored and acked.
    stats = result["stats"]
    assert stats.all_acked and stats.keyframes > 0


def _start_mapper_proc(settings: Settings) -> subprocess.Popen:
    env = {**os.environ, "HIVEMAP_REDIS_URL": settings.redis_url,
           "HIVEMAP_ZENOH__CONNECT": json.dumps(settings.zenoh.connect),
           "HIVEMAP_ZENOH__MODE": "client", "HIVEMAP_MAPPER__REDUNDANCY": "false"}  # fmt: skip
    return subprocess.Popen([sys.executable, "-m", "services.cli", "mapper"], env=env,
                            stderr=subprocess.DEVNULL)  # fmt: skip


def test_kill_9_mapper_loses_no_acked_keyframe(settings, world):
    gt = gt_part("MH01", 900, 3000)
    s = settings.model_copy(
        update={"comm": settings.comm.model_copy(update={"resend_timeout_s": 1.0})}
    )
    proc = _start_mapper_proc(s)
    store = Store(connect(s.redis_url))
    runner = SimAgentRunner(s, "K", SimAgent(gt, world, drift=DriftModel.zero()), speed=6.0,
                            flush_timeout_s=60)  # fmt: skip
    result = {}
    t = threading.Thread(target=lambda: result.setdefault("stats", runner.run()))
    t.start()
    try:
        deadline = time.monotonic() + 30
        while len(runner.comm.acked_kfs) < 15 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert len(runner.comm.acked_kfs) >= 15, "mapper never acked"
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        acked_at_kill = set(runner.comm.acked_kfs)
        assert acked_at_kill <= set(store.keyframe_ids("K"))
        time.sleep(1.5)  # the agent keeps flying and sending into the void
        unacked_during_outage = set(runner.comm.unacked_kf_ids)
        assert unacked_during_outage, "nothing was sent while the mapper was down"
        proc = _start_mapper_proc(s)
        t.join(120)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(10)
    stats = result["stats"]
    assert stats.all_acked
    stored = set(store.keyframe_ids("K"))
    assert acked_at_kill <= stored
    assert unacked_during_outage <= stored
    assert stored == set(range(stats.keyframes))
