"""Lossy and jittery links (issue 18 item 6, CCM-SLAM §5.3) without transport: the
agent's communication module, a channel that drops or delays its batches, and the
server's registration. Whatever the order in which batches arrive (lost ones resent,
late ones overtaken), the server must end with the map that in-order delivery gives:
every keyframe at the agent's final local-map pose.

The agent's local BA is modelled: each keyframe starts off by a few cm and is refined
in each of the next ``W`` keyframes' steps (an update of every keyframe of the window,
relative to its predecessor, as ``runner.VOProducer`` sends them). A keyframe's last
update has no successor; before the fix, a lost one left that keyframe and every one
chained after it at the stale pose (20 % loss: 8-150 mm mean error on a 120-keyframe
flight where in-order delivery gives 0).
"""

from __future__ import annotations

import heapq
import random
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from services.agent.comm import CommModule
from services.agent.sim_agent import DriftModel, LandmarkWorld, SimAgent
from services.mapper.registration import AgentHandler, MapperParams
from services.mapper.server_map import ServerMap
from shared.geometry import se3_inv
from shared.messages import Ack, KeyframeBatch, KeyframeUpdate, MapPoints
from shared.trajectory import Trajectory, load_euroc_gt

W = 7  # keyframes in the modelled local BA window


@pytest.fixture(scope="module")
def keyframes():
    gt = load_euroc_gt("MH01")
    sim = SimAgent(Trajectory(gt.stamps_ns[900:], gt.poses[900:]), LandmarkWorld(0),
                   drift=DriftModel.zero())  # fmt: skip
    out = []
    while len(out) < 100:
        _, _, kf = sim.step()
        if kf is not None:
            out.append(kf)
    return out


def _deliver(wire: list, h, comm: CommModule, t: float, ack_lag: float) -> None:
    """The batches on ``wire`` due by ``t`` ingested by the handler ``h``, each answered
    ``ack_lag`` later with what it stored, held and misses."""
    while wire and wire[0][0] <= t:
        b = KeyframeBatch.decode(heapq.heappop(wire)[2])
        res = h.ingest(b, t)
        held, missing = h.blocked()
        comm.on_ack(Ack("A", "m", np.array(res.ack_kf_ids, np.int64),
                        np.array(res.ack_mp_ids, np.int64), h.kf_high, 0,
                        np.array(held, np.int64), np.array(missing, np.int64), b.seq),
                    t + ack_lag)  # fmt: skip


def _indexed(comm: CommModule) -> bool:
    """The communication module's by-message indexes of what is in flight name exactly
    the items in flight, each under the message that carries it."""
    points = {i: (s.seq, None) for i, s in comm.sent_mps.items()}
    for by, items in ((comm._mps_by_seq, points), (comm._upd_kf_sent, None),
                      (comm._upd_mp_sent, None)):  # fmt: skip
        items = by.items if items is None else items
        if by.items.keys() != items.keys():
            return False
        if {(q, i) for q, ids in by.seqs.items() for i in ids} != {
            (q, i) for i, (q, _) in items.items()
        } or not all(by.seqs.values()):
            return False
    return True


def _fly(keyframes, drop=0.0, delay=0.0, jitter=0.0, seed=0):
    """Returns the handler, the agent's final poses and its communication module."""
    rng, nrng = random.Random(seed), np.random.default_rng(1)
    final = {k.kf.id: k.kf.T_l_kf for k in keyframes}
    off = {i: (nrng.normal(0, 0.02, 3), nrng.normal(0, 0.02, 3)) for i in final}
    off[0] = (np.zeros(3), np.zeros(3))  # the VO's origin does not move

    def estimate(i: int, age: int) -> np.ndarray:
        f = max(W - 1 - age, 0) / (W - 1)
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(off[i][0] * f).as_matrix()
        T[:3, 3] = off[i][1] * f
        return final[i] @ T

    def rel(a: int, b: int) -> np.ndarray:
        return se3_inv(est[a]) @ est[b] if a >= 0 else np.eye(4)

    comm = CommModule("A", rate_hz=5, resend_timeout_s=1.0, backoff_max_s=8.0)
    exact = MapperParams(refine_poses=False, scale_correction=False, fuse=False)
    h = AgentHandler("A", 0, ServerMap("m"), params=exact)
    est: dict[int, np.ndarray] = {}
    ids: list[int] = []
    wire: list[tuple[float, int, bytes]] = []  # (arrival, order, batch)
    t, n, order = 0.0, 0, 0
    while n < len(keyframes) or comm.pending or comm.has_updates or wire:
        assert t < 600, "not everything arrived"
        if round(t * 20) % 4 == 0 and n < len(keyframes):  # 5 keyframes a second
            kf = keyframes[n].kf
            ids.append(kf.id)
            for age, i in enumerate(reversed(ids)):
                est[i] = estimate(i, age)
            for j in range(max(len(ids) - W, 0), len(ids) - 1):  # the window moved
                p = ids[j - 1] if j > 0 else -1
                comm.update_keyframe(KeyframeUpdate(ids[j], p, rel(p, ids[j]), -1, np.eye(4)))
            pred = ids[-2] if len(ids) > 1 else -1
            comm.add_keyframe(replace(kf, T_l_kf=est[kf.id], pred_id=pred,
                                      T_pred_kf=rel(pred, kf.id), parent_id=-1))  # fmt: skip
            comm.add_map_points(keyframes[n].new_mps)
            n += 1
        comm.check_timeouts(t)
        assert _indexed(comm)
        m = comm.next_message(t, int(t * 1e9), ids[-1])
        if m is not None and rng.random() >= drop:
            lag = max(delay + rng.uniform(-jitter, jitter), 0.0)
            heapq.heappush(wire, (t + lag, order, m.encode()))
            order += 1
        _deliver(wire, h, comm, t, ack_lag=0.01)
        t = round(t + 0.05, 2)
    return h, est, comm


@pytest.mark.parametrize("link", [dict(drop=0.2), dict(drop=0.2, seed=1), dict(drop=0.5),
                                  dict(delay=1.0, jitter=0.5)],
                         ids=["loss20", "loss20b", "loss50", "delay1_jitter"])  # fmt: skip
def test_lost_and_overtaken_batches_end_in_the_in_order_map(keyframes, link):
    h, est, comm = _fly(keyframes, **link)
    assert comm.stats.kf_resent > 0 or link.get("delay")
    assert sorted(h.local_poses) == sorted(est) and not h.pending_kfs
    err = [np.abs(h.kf_pose(i) - T).max() for i, T in est.items()]
    assert max(err) < 1e-9, (np.argmax(err), max(err))
    assert len(h.smap.mps) == sum(len(k.new_mps) for k in keyframes)


def test_in_order_reference(keyframes):
    h, est, _ = _fly(keyframes)
    assert max(np.abs(h.kf_pose(i) - T).max() for i, T in est.items()) < 1e-9


def test_the_first_keyframe_is_placed_though_its_parent_comes_later(keyframes):
    """An agent's first keyframe has no predecessor, and its covisibility parent is a
    later keyframe. Registration placed it only once that parent was in the map, which
    the parent itself waited for: each agent's first batch sat out the orphan rule's
    5 s unacknowledged (the first ~9 keyframes of every team3 agent, ack p95 ~3 s)."""
    k0, k1 = keyframes[0], keyframes[1]
    first = replace(
        k0.kf, pred_id=-1, parent_id=k1.kf.id, T_par_kf=se3_inv(k1.kf.T_l_kf) @ k0.kf.T_l_kf
    )
    h = AgentHandler("A", 0, ServerMap("m"), params=MapperParams(refine_poses=False))
    res = h.ingest(
        KeyframeBatch("A", 0, 0, 0, [first, k1.kf], [], k0.new_mps, MapPoints.empty()), now=0.0
    )
    assert sorted(res.ack_kf_ids) == [k0.kf.id, k1.kf.id] and not h.pending_kfs
    assert res.orphans_anchored == 0


@pytest.fixture(scope="module")
def flight():
    gt = load_euroc_gt("MH03")
    sim = SimAgent(Trajectory(gt.stamps_ns, gt.poses), LandmarkWorld(0), drift=DriftModel.zero())
    out = []
    while len(out) < 227:  # team3's agent3 (MH03)
        _, _, kf = sim.step()
        if kf is not None:
            out.append(kf)
    return out


def _fly_prompt_server(keyframes, drop: float, seed: int, flush_s: float = 30.0):
    """The agent's communication module with its default settings (as
    ``CommSettings``) against a server that answers every batch that arrives within
    50 ms and never sheds; a keyframe every 0.55 s, and the updates of the local BA
    window with each. Returns the module and the time after the last keyframe when
    everything was acknowledged (None: not within ``flush_s``, the agent's flush)."""
    rng = random.Random(seed)
    comm = CommModule("A")
    exact = MapperParams(refine_poses=False, scale_correction=False, fuse=False)
    h = AgentHandler("A", 0, ServerMap("m"), params=exact)
    T = {k.kf.id: k.kf.T_l_kf for k in keyframes}

    def rel(a: int, b: int) -> np.ndarray:
        return se3_inv(T[a]) @ T[b] if a >= 0 else np.eye(4)

    ids: list[int] = []
    wire: list[tuple[float, int, bytes]] = []
    t, n, order, t_last = 0.0, 0, 0, None
    while t_last is None or t <= t_last + flush_s:
        if n < len(keyframes) and t >= 0.55 * n:
            kf = keyframes[n].kf
            ids.append(kf.id)
            for j in range(max(len(ids) - W, 0), len(ids) - 1):
                p = ids[j - 1] if j > 0 else -1
                comm.update_keyframe(KeyframeUpdate(ids[j], p, rel(p, ids[j]), -1, np.eye(4)))
            pred = ids[-2] if len(ids) > 1 else -1
            comm.add_keyframe(replace(kf, pred_id=pred, T_pred_kf=rel(pred, kf.id), parent_id=-1))
            comm.add_map_points(keyframes[n].new_mps)
            n += 1
            t_last = t if n == len(keyframes) else None
        elif t_last is not None and not (comm.pending or comm.has_updates):
            return comm, t - t_last
        comm.check_timeouts(t)
        m = comm.next_message(t, int(t * 1e9), ids[-1])
        if m is not None and rng.random() >= drop:
            heapq.heappush(wire, (t + 0.05, order, m.encode()))
            order += 1
        _deliver(wire, h, comm, t, ack_lag=0.05)
        t = round(t + 0.01, 2)
    return comm, None


@pytest.mark.parametrize("seed", [1, 4, 5])
def test_half_the_batches_lost_with_a_prompt_server_everything_is_acked_in_the_flush(flight, seed):
    """Issue 18 item 6: 50 % of the agent's batches lost, the server answering the rest
    at once and never shedding. Loss is no congestion: a keyframe whose batch got no
    answer while a later one did was lost, and is sent again at the same timeout,
    without backing off or halving the window. Before, each such timeout doubled the
    resend timeout (carried to first sends too) and halved the window down to 2, whose
    keyframes, both lost, then stalled the agent for timeout after timeout while the
    server answered its update batches (team3 at 50 % loss: 13-21 stalls of >4 s without
    an ack per agent, 109-164 s of 204-277 s; in this simulation, seeds 1 and 5 left
    17 and 6 keyframes unacknowledged after the 30 s flush, ack p95 10.5-13.3 s)."""
    comm, after = _fly_prompt_server(flight, drop=0.5, seed=seed)
    assert after is not None and after < 20.0, (len(comm.kfs), len(comm.mps))
    assert comm.acked_kfs == {k.kf.id for k in flight}
    assert np.percentile(comm.stats.ack_latencies, 95) < 8.0
    assert comm.stats.window_cuts <= 10
    assert comm.stats.kf_resent < 1.3 * len(flight)  # about one resend a keyframe at 50 %
