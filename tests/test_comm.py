"""The agent communication module (CCM-SLAM §4.5) without transport."""

from __future__ import annotations

import numpy as np

from services.agent.comm import CommModule
from services.agent.sim_agent import DriftModel, LandmarkWorld, SimAgent
from shared.messages import Ack, KeyframeBatch, KeyframeUpdate
from shared.trajectory import Trajectory, load_euroc_gt


def _keyframes(n: int):
    gt = load_euroc_gt("MH01")
    sim = SimAgent(Trajectory(gt.stamps_ns[900:], gt.poses[900:]), LandmarkWorld(0),
                   drift=DriftModel.zero())  # fmt: skip
    out = []
    while len(out) < n:
        _, _, kf = sim.step()
        if kf is not None:
            out.append(kf)
    return out


def _ack(kf_ids, mp_ids=()):
    return Ack("A", "m", np.array(kf_ids, np.int64), np.array(mp_ids, np.int64), 0, 0)


def test_rate_limit_and_size_cap():
    kfs = _keyframes(6)
    c = CommModule("A", rate_hz=2.0, max_msg_bytes=120_000, resend_timeout_s=100)
    for k in kfs:
        c.add_keyframe(k.kf)
        c.add_map_points(k.new_mps)
    m1 = c.next_message(0.0, 0, 5)
    assert m1 is not None
    assert len(m1.encode()) <= 120_000 * 1.05
    assert 1 <= len(m1.new_kfs) < 6
    assert [k.id for k in m1.new_kfs] == sorted(k.id for k in m1.new_kfs)
    assert c.next_message(0.2, 0, 5) is None  # 2 Hz: nothing before 0.5 s
    sent = list(m1.new_kfs)
    t = 0.5
    while c.queued_kfs or c.queued_mps:
        m = c.next_message(t, 0, 5)
        sent += m.new_kfs
        t += 0.5
    assert [k.id for k in sent] == [k.kf.id for k in kfs]  # each sent once, in order


def test_new_data_once_then_updates_only():
    kfs = _keyframes(2)
    c = CommModule("A", rate_hz=100, resend_timeout_s=100)
    c.add_keyframe(kfs[0].kf)
    m = c.next_message(0, 0, 0)
    c.on_ack(_ack([0], m.new_mps.ids), 0.01)
    c.update_keyframe(KeyframeUpdate(0, -1, np.eye(4), -1, np.eye(4)))
    m2 = c.next_message(1, 0, 0)
    assert m2.new_kfs == [] and len(m2.kf_updates) == 1
    assert len(m2.encode()) < 1500  # an update is small; the keypoints are not resent


def test_gap_in_acks_triggers_resend():
    kfs = _keyframes(3)
    c = CommModule("A", rate_hz=100, resend_timeout_s=100)
    msgs = []
    for i, k in enumerate(kfs):
        c.add_keyframe(k.kf)
        msgs.append(c.next_message(i * 0.1, 0, k.kf.id))
    # The message with keyframe 0 was lost; keyframes 1 and 2 arrived.
    c.on_ack(_ack([1, 2]), 0.5)
    assert c.queued_kfs == [0]
    again = c.next_message(1.0, 0, 2)
    assert [k.id for k in again.new_kfs] == [0]
    assert again.new_kfs[0].keypoints.shape == kfs[0].kf.keypoints.shape  # full data again
    c.on_ack(_ack([0]), 1.1)
    assert not c.pending or c.mps  # keyframes all acknowledged
    assert c.unacked_kf_ids == set()


def test_timeout_resend_when_last_message_lost():
    kfs = _keyframes(1)
    c = CommModule("A", rate_hz=100, resend_timeout_s=1.0)
    c.add_keyframe(kfs[0].kf)
    c.add_map_points(kfs[0].new_mps)
    assert c.next_message(0, 0, 0) is not None
    assert c.check_timeouts(0.5) == 0
    assert c.check_timeouts(1.5) == 1 + len(kfs[0].new_mps)
    m = c.next_message(1.5, 0, 0)
    assert [k.id for k in m.new_kfs] == [0]
    assert len(m.new_mps) == len(kfs[0].new_mps)
    assert c.resent_reasons[("kf", "timeout")] == 1


def test_round_trip_through_encoding_keeps_all_data():
    kfs = _keyframes(2)
    c = CommModule("A", rate_hz=100)
    for k in kfs:
        c.add_keyframe(k.kf)
        c.add_map_points(k.new_mps)
    d = KeyframeBatch.decode(c.next_message(0, 123, 1).encode())
    assert [k.id for k in d.new_kfs] == [0, 1]
    assert len(d.new_mps) == sum(len(k.new_mps) for k in kfs)
    np.testing.assert_array_equal(d.new_kfs[1].mp_ids, kfs[1].kf.mp_ids)
