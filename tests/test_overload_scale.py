"""Overload at the bench's scale without processes: 48 agents' communication modules
(services/agent/comm.py) against one map actor's queue of fixed capacity that admits
with the mapper's policy (services/mapper/overload.py) and NACKs what it sheds.

The agents offer more keyframes than the actor registers (the bench_ramp --overload
case: 48 agents, one merged map). What must hold (issue 18 item 2): the latency of what
the actor accepts stays bounded; every keyframe is acknowledged soon after the flights;
and the agents do not bury the server under resends. Without shedding the same
agents' windows alone keep a queue of several seconds standing: the test has teeth.
"""

from __future__ import annotations

import collections
import heapq

import numpy as np

from services.agent.comm import CommModule, estimate_kf_bytes
from services.mapper.overload import Overload
from shared.messages import Ack, NewKeyframe

N_KP = 600


def _kf(i: int) -> NewKeyframe:
    return NewKeyframe(
        id=i, stamp_ns=0, T_l_kf=np.eye(4), pred_id=i - 1, T_pred_kf=np.eye(4),
        parent_id=i - 1, T_par_kf=np.eye(4), keypoints=np.zeros((N_KP, 2), np.float32),
        octaves=np.zeros(N_KP, np.uint8), descriptors=np.zeros((N_KP, 32), np.uint8),
        mp_ids=np.full(N_KP, -1, np.int64),
    )  # fmt: skip


def _ack(agent: str, ids: list[int], seq: int, retry_after_s: float | None = None) -> Ack:
    return Ack(agent, "m", np.array(ids, np.int64), np.zeros(0, np.int64), 0, 0, seq=seq,
               retry_after_s=retry_after_s)  # fmt: skip


def fly(n=48, kf_rate=0.7, flight_s=120.0, per_batch_s=0.01, per_kf_s=0.028,
        shed_after_s=0.6, seed=0, dt=0.05) -> dict:  # fmt: skip
    """``n`` agents making ``kf_rate`` keyframes a second for ``flight_s``; the actor
    takes ``per_batch_s + per_kf_s * keyframes`` per batch it registers (~30 keyframes a
    second here, below the 34 offered). Time advances in steps of ``dt``; links take 3 ms."""
    rng = np.random.default_rng(seed)
    agents = [CommModule(f"a{i}") for i in range(n)]
    made = [0] * n
    t_next = [rng.uniform(0, 1 / kf_rate) for _ in range(n)]
    policy = Overload.from_shed_after(shed_after_s)
    q: collections.deque = collections.deque()  # (received, agent, batch)
    inbox: list = []  # (delivered, order, agent, ack)
    busy_until, order, shed, lat = 0.0, 0, 0, []
    nbytes = [0] * n
    t, drained = 0.0, None
    while t < flight_s + 120 and drained is None:
        while inbox and inbox[0][0] <= t:
            _, _, i, ack = heapq.heappop(inbox)
            agents[i].on_ack(ack, t)
        for i, c in enumerate(agents):
            while t < flight_s and t_next[i] <= t:
                c.add_keyframe(_kf(made[i]))
                made[i] += 1
                t_next[i] += rng.exponential(1 / kf_rate)
            c.check_timeouts(t)
            m = c.next_message(t, 0, 0)
            if m is not None:
                nbytes[i] += sum(estimate_kf_bytes(k) for k in m.new_kfs)
                q.append((t + 0.003, i, m))
        while q and busy_until < t + dt and q[0][0] <= max(busy_until, t):
            recv, i, m = q.popleft()
            start = max(busy_until, recv)
            waited = start - recv
            policy.observe(waited, start, "m")
            ids = [k.id for k in m.new_kfs]
            order += 1
            if policy.admit(f"a{i}", ids, waited, start, "m"):
                busy_until = start + per_batch_s + per_kf_s * len(ids)
                lat += [busy_until - recv] * len(ids)
                heapq.heappush(inbox, (busy_until + 0.003, order, i, _ack(f"a{i}", ids, m.seq)))
            else:
                shed += 1
                retry = policy.retry_after(start, "m")
                heapq.heappush(inbox, (start + 0.003, order, i, _ack(f"a{i}", [], m.seq, retry)))
        t += dt
        if t > flight_s and all(not c.kfs for c in agents):
            drained = t - flight_s
    total = sum(made)
    return {
        "made": total,
        "p95_s": float(np.percentile(lat, 95)),
        "drained_s": drained,
        "shed": shed,
        "resent_per_kf": sum(c.stats.kf_resent for c in agents) / total,
        "kB_per_s": float(np.mean(nbytes)) / flight_s / 1e3,
    }


def test_shedding_bounds_accepted_latency_and_the_backlog_drains():
    r = fly()
    print(r)
    assert r["shed"] > 0  # overloaded
    assert r["p95_s"] <= 1.0
    assert r["drained_s"] is not None and r["drained_s"] <= 60
    assert r["resent_per_kf"] <= 1.0


def test_without_shedding_the_agents_windows_keep_a_queue_standing():
    r = fly(shed_after_s=1e9)
    print(r)
    assert r["shed"] == 0 and r["p95_s"] > 2.0
