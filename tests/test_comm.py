"""The agent communication module (CCM-SLAM §4.5) without transport."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from services.agent.comm import CommModule, estimate_kf_bytes
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
    # The keyframe times out; its points, lost with it, go again with it.
    assert c.check_timeouts(1.5) == 1
    m = c.next_message(1.5, 0, 0)
    assert [k.id for k in m.new_kfs] == [0]
    assert len(m.new_mps) == len(kfs[0].new_mps)
    assert c.resent_reasons[("kf", "timeout")] == 1
    assert c.resent_reasons[("mp", "timeout")] == len(kfs[0].new_mps)


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


def _send_all(c: CommModule, t: float) -> list[int]:
    m = c.next_message(t, 0, 0)
    return [] if m is None else [k.id for k in m.new_kfs]


def test_resends_back_off_exponentially_to_a_cap_with_jitter():
    """A server that never answers gets a keyframe again after ~2, 4, 8, 16, 30, 30 s
    (+-20 %), not every 2 s: 8 sends in 120 s instead of 60."""
    kf = _keyframes(1)[0].kf
    c = CommModule("A", rate_hz=10, resend_timeout_s=2.0, backoff_max_s=30.0, jitter=0.2)
    c.add_keyframe(kf)
    sends = []
    for i in range(1200):
        t = i * 0.1
        c.check_timeouts(t)
        if _send_all(c, t):
            sends.append(t)
    gaps = np.diff(sends)
    assert len(sends) <= 9
    nominal = [2, 4, 8, 16, 30, 30, 30][: len(gaps)]
    for g, n in zip(gaps, nominal, strict=False):
        assert 0.8 * n - 0.11 <= g <= 1.2 * n + 0.11, (gaps, nominal)
    # Jitter: two agents that lost the server at the same moment do not resend in step.
    d = CommModule("B", rate_hz=10, resend_timeout_s=2.0, backoff_max_s=30.0, jitter=0.2)
    d.add_keyframe(kf)
    other = []
    for i in range(1200):
        d.check_timeouts(i * 0.1)
        if _send_all(d, i * 0.1):
            other.append(i * 0.1)
    assert other[1:] != sends[1:]


def test_resend_timeout_follows_the_ack_latency():
    """Acks that take 3 s (a loaded server) do not make the agent resend after 2 s."""
    kfs = _keyframes(12)
    c = CommModule("A", rate_hz=100, resend_timeout_s=2.0)
    t, sent_at = 0.0, {}
    for k in kfs:
        c.add_keyframe(k.kf)
        c.add_map_points(k.new_mps)
    for step in range(600):
        t = step * 0.05
        c.check_timeouts(t)
        m = c.next_message(t, 0, 0)
        if m is not None:
            for k in m.new_kfs:
                sent_at.setdefault(k.id, t)
        due = [i for i, t0 in sent_at.items() if t - t0 >= 3.0 and i in c.kfs]
        mp = [i for i, v in c.mps.items() if v[0] in due]
        if due:
            c.on_ack(_ack(due, mp), t)
    assert not c.pending
    assert c.srtt == pytest.approx(3.0, abs=0.1)
    assert c.rto >= 3.0
    # Only the first keyframes, before any latency was measured, went out twice.
    assert c.stats.kf_resent <= 8


def test_window_shrinks_when_acks_are_late_and_grows_when_prompt():
    kfs = _keyframes(30)
    c = CommModule(
        "A", rate_hz=1000, resend_timeout_s=100, window=8, ack_target_s=0.5, window_min=1
    )
    for k in kfs:
        c.add_keyframe(k.kf)
    first = _send_all(c, 0.0)
    assert len(first) == 8 and c.in_flight == 8
    assert c.next_message(0.01, 0, 0) is None  # window full: nothing more, not even empty
    # Acks come 2 s late: the window halves (once per round trip), down to 1.
    t = 2.0
    for i in first:
        c.on_ack(_ack([i]), t)
    assert c.window < 8
    for _ in range(6):
        ids = _send_all(c, t)
        t += 2.0
        c.on_ack(_ack(ids), t)
    assert c.window == 1 and c.stats.window_cuts >= 3
    # Prompt acks: it grows again, one per ack.
    for _ in range(5):
        ids = _send_all(c, t)
        t += 0.1
        c.on_ack(_ack(ids), t)
    assert c.window >= 8


def test_a_long_link_is_no_slow_server():
    """Acks 2 s after the send, but the server held each batch 50 ms: the delay is the
    link's, and the window grows as on prompt acks (before, it halved down to its
    minimum on a 0.5-1.5 s link, and two keyframes per round trip fell behind the VO).
    The same latency held by the server is back-pressure: the window halves."""
    for held, grows in ((0.05, True), (1.9, False)):
        kfs = _keyframes(30)
        c = CommModule(
            "A", rate_hz=1000, resend_timeout_s=100, window=8, ack_target_s=0.5, window_min=1
        )
        for k in kfs:
            c.add_keyframe(k.kf)
        t = 0.0
        for _ in range(3):
            ids = _send_all(c, t)
            t += 2.0
            ack = _ack(ids)
            ack.held_s = held
            c.on_ack(ack, t)
        assert (c.window > 8) if grows else (c.window < 8), (held, c.window)
        assert c.srtt is not None and c.srtt > 1.5  # the resend timeout follows it all


def test_held_and_asked_for_keyframes_stay_outside_the_window():
    """With a window of one, a keyframe the server holds (its predecessor was lost) must
    not block the predecessor's resend, or the two would wait on each other."""
    kfs = _keyframes(3)
    c = CommModule("A", rate_hz=1000, resend_timeout_s=100, window=1, window_max=1)
    for k in kfs:
        c.add_keyframe(k.kf)
    assert _send_all(c, 0.0) == [0]
    c.on_ack(_ack([0]), 0.1)
    assert _send_all(c, 0.2) == [1]  # lost on the way
    c.on_ack(Ack("A", "m", np.zeros(0, np.int64), np.zeros(0, np.int64), 0, 0,
                 np.array([1], np.int64)), 0.3)  # fmt: skip
    assert c.in_flight == 0  # held: not counted
    assert _send_all(c, 0.4) == [2]
    # The server holds 2 and asks for 1 again: 1 goes out though 2 fills the window.
    c.on_ack(Ack("A", "m", np.zeros(0, np.int64), np.zeros(0, np.int64), 0, 0,
                 np.array([2], np.int64), np.array([1], np.int64)), 0.5)  # fmt: skip
    assert _send_all(c, 0.6) == [1]
    c.on_ack(_ack([1, 2]), 0.7)
    assert c.unacked_kf_ids == set()


def test_map_points_wait_for_their_keyframe():
    kfs = _keyframes(3)
    c = CommModule("A", rate_hz=1000, resend_timeout_s=100, window=1, window_max=1)
    for k in kfs:
        c.add_keyframe(k.kf)
        c.add_map_points(k.new_mps)
    m = c.next_message(0.0, 0, 0)
    assert [k.id for k in m.new_kfs] == [0]
    assert set(m.new_mps.ref_kf.tolist()) <= {0}


def test_a_shedding_server_loses_no_keyframe_of_a_long_flight():
    """Issue 18 item 2: a server that sheds (acks nothing) for 60 s while the agent keeps
    making 5 keyframes a second. The backlog (300+ keyframes, past the VO's N + B) stays
    in the communication module, goes out through the window with backed-off resends,
    and is all acknowledged once the server takes work again; only a buffer of
    ``buffer_bytes`` drops the oldest, and says so."""
    base = _keyframes(1)[0].kf
    c = CommModule("A", rate_hz=10, resend_timeout_s=1.0, backoff_max_s=8.0, window=4,
                   window_min=2)  # fmt: skip
    sends: dict[int, int] = {}
    n, t = 0, 0.0
    while t < 90.0:
        if t < 70.0 and round(t * 10) % 2 == 0:
            assert c.add_keyframe(replace(base, id=n)) == []
            n += 1
        c.check_timeouts(t)
        m = c.next_message(t, 0, 0)
        if m is not None:
            for k in m.new_kfs:
                sends[k.id] = sends.get(k.id, 0) + 1
            if t >= 60.0:  # the server takes work again
                c.on_ack(_ack([k.id for k in m.new_kfs]), t + 0.05)
        t = round(t + 0.1, 1)
    assert n == 350 and c.stats.kf_dropped_unacked == 0 and not c.forgotten
    assert c.acked_kfs == set(range(n)) and not c.kfs and c.buffered_bytes == 0
    # While shed, only the window's few went out again, backed off to one send per
    # ~8 s (1, 2, 4, 8, 8, ... s): no resend storm.
    assert max(sends.values()) <= 12 and sum(sends.values()) <= 1.2 * n, sends

    size = estimate_kf_bytes(base)
    small = CommModule("B", buffer_bytes=10 * size)
    dropped = [i for k in range(14) for i in small.add_keyframe(replace(base, id=k))]
    assert dropped == [0, 1, 2, 3] and small.forgotten == {0, 1, 2, 3}
    assert sorted(small.kfs) == list(range(4, 14)) and small.queued_kfs == list(range(4, 14))
    assert small.stats.kf_dropped_unacked == 4 and small.buffered_bytes == 10 * size


def test_a_lost_update_goes_again_unless_a_newer_one_is_queued():
    """Updates are tracked per message (``Ack.seq``): the last update of a keyframe has
    no successor, so a lost one must be resent, and only while it is the newest."""
    kfs = _keyframes(3)
    c = CommModule("A", rate_hz=100, resend_timeout_s=1.0)
    for k in kfs:
        c.add_keyframe(k.kf)
    m0 = c.next_message(0.0, 0, 2)
    c.on_ack(Ack("A", "m", np.array([0, 1, 2], np.int64), np.zeros(0, np.int64), 2, 0,
                 seq=m0.seq), 0.05)  # fmt: skip

    def upd(i, x):
        T = np.eye(4)
        T[0, 3] = x
        return KeyframeUpdate(i, i - 1, T, -1, np.eye(4))

    c.update_keyframe(upd(1, 0.1))
    c.update_keyframe(upd(2, 0.2))
    m1 = c.next_message(0.1, 0, 2)  # lost
    c.update_keyframe(upd(2, 0.3))  # newer for 2
    m2 = c.next_message(0.2, 0, 2)
    assert [u.id for u in m1.kf_updates] == [1, 2] and [u.id for u in m2.kf_updates] == [2]
    assert c.has_updates  # not known to have arrived
    c.on_ack(Ack("A", "m", np.zeros(0, np.int64), np.zeros(0, np.int64), 2, 0, seq=m2.seq), 0.25)
    m3 = c.next_message(0.3, 0, 2)  # 1's update again; 2's old one is superseded
    assert [(u.id, u.T_pred_kf[0, 3]) for u in m3.kf_updates] == [(1, 0.1)]
    assert c.resent_reasons[("upd", "gap")] == 1
    assert c.check_timeouts(0.5) == 0 and c.next_message(0.5, 0, 2) is None
    c.check_timeouts(2.0)  # m3 unanswered past its timeout: 1's update goes once more
    assert [u.id for u in c.next_message(2.0, 0, 2).kf_updates] == [1]
    c.on_ack(Ack("A", "m", np.zeros(0, np.int64), np.zeros(0, np.int64), 2, 0, seq=c.seq - 1), 2.1)
    assert not c.has_updates


def test_an_update_of_an_unacked_keyframe_is_folded_into_its_resend():
    kfs = _keyframes(2)
    c = CommModule("A", rate_hz=100, resend_timeout_s=1.0)
    for k in kfs:
        c.add_keyframe(k.kf)
    c.next_message(0.0, 0, 1)  # lost
    T = np.eye(4)
    T[0, 3] = 0.5
    c.update_keyframe(KeyframeUpdate(1, 0, T, -1, np.eye(4)))
    m = c.next_message(0.1, 0, 1)  # the update goes too: the keyframe may be there
    assert [u.id for u in m.kf_updates] == [1]
    c.check_timeouts(5.0)
    again = c.next_message(5.0, 0, 1)
    assert [k.id for k in again.new_kfs] == [0, 1]
    assert again.new_kfs[1].T_pred_kf[0, 3] == 0.5  # the resend carries the newest pose


def test_an_overtaken_batch_is_late_not_lost():
    """Delay with jitter reorders batches. One overtaken within the reordering window (4x
    the ack latency's mean deviation) is not sent again; one sent before it is lost. A
    held keyframe's batch is evidence too, and a keyframe the server asks for that
    already went out again after the answered batch does not go a third time."""
    base = _keyframes(1)[0].kf
    c = CommModule("A", rate_hz=1000, resend_timeout_s=100)
    seqs, t = {}, 0.0

    def ack(seq, kf_ids=(), held=(), missing=()):
        c.on_ack(Ack("A", "m", np.array(kf_ids, np.int64), np.zeros(0, np.int64), 0, 0,
                     np.array(held, np.int64), np.array(missing, np.int64), seq), t)  # fmt: skip

    # Ack latencies spread 0.5-1.5 s: the window grows to about a second.
    for i in range(40):
        c.add_keyframe(replace(base, id=i))
        seqs[i] = c.next_message(t, 0, i).seq
        t += 0.5 + (i % 3) * 0.5
        ack(seqs[i], [i])
    assert 0.5 < c.reorder_s < 2.0 and not c.resent_reasons
    t0 = t
    for i in (200, 201, 202):
        c.add_keyframe(replace(base, id=i))
        seqs[i] = c.next_message(t, 0, i).seq
        t += 0.2
    # 202 (sent 0.4 s after 200) overtook 200 and 201: they are late, not lost.
    ack(seqs[202], [202])
    assert c.queued_kfs == [] and not c.resent_reasons
    # Sent 2.5 s after 200, 203 is held (its predecessor 201 is missing): 200 was lost.
    t = t0 + 2.5
    c.add_keyframe(replace(base, id=203))
    seqs[203] = c.next_message(t, 0, 203).seq
    ack(seqs[203], held=[203], missing=[201])
    assert c.queued_kfs == [200, 201] and c.resent_reasons == {("kf", "gap"): 1, ("kf", "nack"): 1}
    m = c.next_message(t + 0.1, 0, 203)
    assert [k.id for k in m.new_kfs] == [200, 201]
    # A late answer to an earlier batch still names 201 missing: it is on its way.
    ack(seqs[202], missing=[201])
    assert c.queued_kfs == []


def test_an_answered_update_batch_is_no_evidence_of_a_lost_keyframe():
    """An overloaded mapper sheds keyframe batches unanswered but answers update-only
    ones: what it shed waits for its backed-off timeout, not for the next update's ack."""
    kfs = _keyframes(2)
    c = CommModule("A", rate_hz=1000, resend_timeout_s=2.0)
    c.add_keyframe(kfs[0].kf)
    m0 = c.next_message(0.0, 0, 0)
    c.on_ack(Ack("A", "m", np.array([0], np.int64), np.zeros(0, np.int64), 0, 0, seq=m0.seq), 0.01)
    c.add_keyframe(kfs[1].kf)
    assert [k.id for k in c.next_message(0.1, 0, 1).new_kfs] == [1]  # shed
    c.update_keyframe(KeyframeUpdate(0, -1, np.eye(4), -1, np.eye(4)))
    m2 = c.next_message(0.2, 0, 1)
    assert m2.new_kfs == [] and len(m2.kf_updates) == 1
    c.on_ack(Ack("A", "m", np.zeros(0, np.int64), np.zeros(0, np.int64), 0, 0, seq=m2.seq), 0.21)
    assert c.queued_kfs == [] and not c.resent_reasons
    assert c.check_timeouts(2.5) == 1 and c.queued_kfs == [1]


def _nack(seq: int, retry_after_s: float) -> Ack:
    return Ack("A", "m", np.zeros(0, np.int64), np.zeros(0, np.int64), 0, 0, seq=seq,
               retry_after_s=retry_after_s)  # fmt: skip


def test_a_shed_batch_goes_out_again_after_the_retry_after_with_its_successors():
    """An overloaded server sheds a batch (and the agent's later ones, waiting behind
    it) with a NACK: all of them go back to the queue at once, nothing goes out before
    the retry-after, and then they go again together, oldest first -- not one by one
    after backed-off resend timeouts (seconds, doubling)."""
    kfs = _keyframes(4)
    c = CommModule("A", rate_hz=1000, resend_timeout_s=100, jitter=0.0, window=8)
    c.add_keyframe(kfs[0].kf)
    c.add_map_points(kfs[0].new_mps)
    m0 = c.next_message(0.0, 0, 0)
    c.on_ack(_ack([0], m0.new_mps.ids), 0.05)
    c.update_keyframe(KeyframeUpdate(0, -1, np.eye(4), -1, np.eye(4)))
    for k in kfs[1:3]:
        c.add_keyframe(k.kf)
        c.add_map_points(k.new_mps)
    m1 = c.next_message(0.1, 0, 0)  # keyframes 1 and 2, their points, 0's update
    assert [k.id for k in m1.new_kfs] == [1, 2] and len(m1.kf_updates) == 1
    c.add_keyframe(kfs[3].kf)
    c.add_map_points(kfs[3].new_mps)
    m2 = c.next_message(0.2, 0, 0)
    assert [k.id for k in m2.new_kfs] == [3]
    window = c.window
    c.on_ack(_nack(m1.seq, 1.0), 0.8)
    c.on_ack(_nack(m2.seq, 1.0), 0.85)
    assert c.queued_kfs == [1, 2, 3] and c.stats.batches_shed == 2
    assert c.window < window  # a congestion signal, as a late ack
    assert 0 in c.kf_updates  # the shed batch's update goes again too
    for t in (0.9, 1.3, 1.7):
        m = c.next_message(t, 0, 0)
        assert m is None or not m.new_kfs  # held back: no keyframe before 1.8 s
    m = c.next_message(1.9, 0, 0)
    assert [k.id for k in m.new_kfs] == [1, 2, 3]  # one run, as the server shed it
    assert set(m.new_mps.ref_kf.tolist()) == {1, 2, 3}  # with their points
    c.on_ack(_ack([1, 2, 3], m.new_mps.ids), 2.0)
    assert c.unacked_kf_ids == set() and not c.mps
    assert c.resent_reasons[("kf", "shed")] == 3
    # No timeout resend of what the NACK requeued: it was sent again, and acked.
    assert c.check_timeouts(500.0) == 0


def test_a_nack_of_a_batch_already_sent_again_does_not_requeue_it():
    """Only what a shed batch carried and has not gone out since goes back."""
    kfs = _keyframes(2)
    c = CommModule("A", rate_hz=1000, resend_timeout_s=100, jitter=0.0)
    c.add_keyframe(kfs[0].kf)
    m0 = c.next_message(0.0, 0, 0)
    c._requeue_kf(0, "test")  # sent again (e.g. the server asked for it)
    m1 = c.next_message(0.1, 0, 0)
    assert [k.id for k in m1.new_kfs] == [0]
    c.on_ack(_nack(m0.seq, 0.5), 0.2)
    assert c.queued_kfs == [] and 0 in c.sent_kfs


def test_nacks_in_a_row_double_the_hold_up_to_a_cap_until_keyframes_are_taken():
    """A server far over its capacity NACKs what comes back after a hold too: each such
    NACK doubles the next hold (1, 2, 4, 8, 8 s), and an ack that takes keyframes ends
    it. NACKs of one shed run (the agent's later batches, shed behind the first) do not
    count twice."""
    kfs = _keyframes(3)
    c = CommModule("A", rate_hz=1000, resend_timeout_s=100, jitter=0.0,
                   shed_backoff_max_s=8.0)  # fmt: skip
    for k in kfs[:2]:
        c.add_keyframe(k.kf)
    t, holds = 0.0, []
    m = c.next_message(t, 0, 0)
    for _ in range(5):
        c.on_ack(_nack(m.seq, 1.0), t + 0.1)
        c.on_ack(_nack(m.seq, 1.0), t + 0.2)  # the same run: no extra doubling
        start = t = t + 0.2  # the hold counts from the last NACK
        m = None
        while m is None:
            t = round(t + 0.05, 2)
            m = c.next_message(t, 0, 0)
        holds.append(round(t - start, 1))
    assert holds == [1.0, 2.0, 4.0, 8.0, 8.0]
    c.on_ack(_ack([k.id for k in m.new_kfs]), t + 0.1)  # taken: the streak ends
    c.add_keyframe(kfs[2].kf)
    m = c.next_message(t + 0.2, 0, 0)
    c.on_ack(_nack(m.seq, 1.0), t + 0.3)
    assert c._hold_until == pytest.approx(t + 1.3)
