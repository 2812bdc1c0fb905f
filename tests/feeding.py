"""Driving a simulated agent straight into a mapper, or into one agent's handler of a
server map, without transport (tests, and bench/bench_mapper.py)."""

from __future__ import annotations

import random
import zlib
from collections.abc import Callable

import numpy as np

from services.agent.comm import CommModule
from services.agent.sim_agent import SimAgent
from services.mapper.redundancy import find_redundant
from services.mapper.registration import AgentHandler
from services.mapper.service import MapperService
from shared.messages import Ack
from shared.trajectory import Trajectory


def feed(agent: str, sim: SimAgent, apply: Callable) -> None:
    """Every keyframe of ``sim`` as one batch: ``apply(message, t, step)`` (``step``
    what ``sim.step()`` returned, ``t`` the agent's clock, one second a keyframe)
    returns the ack the agent gets back. Calls for one agent id are one flight (one
    session, see services/mapper/sessions.py): a test may fly an agent on in steps."""
    comm = CommModule(agent, rate_hz=1e9, session=zlib.crc32(agent.encode()))
    t = 0.0
    while not sim.done:
        step = sim.step()
        kf = step[2]
        if kf is None:
            continue
        comm.add_keyframe(kf.kf)
        comm.add_map_points(kf.new_mps)
        comm.on_ack(apply(comm.next_message(t, 0, kf.kf.id), t, step), t)
        t += 1.0


def feed_mapper(svc: MapperService, agent: str, sim: SimAgent) -> None:
    """Every keyframe of ``sim`` as one batch, applied synchronously, and acked."""

    def apply(msg, t, step):
        ack = svc.process_kf_bytes(f"hivemap/agent/{agent}/up/kf", msg.encode(), 0)
        return Ack(agent, ack.map_id, ack.kf_ids, ack.mp_ids, 0, 0)

    feed(agent, sim, apply)


def feed_handler(
    handler: AgentHandler, sim: SimAgent, after: Callable[[int], None] | None = None
) -> Trajectory:
    """Every keyframe of ``sim`` into ``handler`` (then fused); returns the agent's own
    (VO) keyframe trajectory, in keyframe id order (ids count from 0). ``after(kf_id)``
    is called once each keyframe is in, before the next one comes."""
    est = {}

    def apply(msg, t, step):
        kf = step[2]
        est[kf.kf.id] = (kf.kf.stamp_ns, kf.kf.T_l_kf)
        res = handler.ingest(msg, t)
        handler.fuse_new()
        if after is not None:
            after(kf.kf.id)
        return Ack(handler.agent, "m", np.array(res.ack_kf_ids, np.int64),
                   np.array(res.ack_mp_ids, np.int64), 0, 0)  # fmt: skip

    feed(handler.agent, sim, apply)
    return Trajectory(np.array([est[i][0] for i in sorted(est)]),
                      np.stack([est[i][1] for i in sorted(est)]))  # fmt: skip


def server_traj(h: AgentHandler) -> Trajectory:
    """The server's poses of the agent's keyframes still in the map, in id order."""
    kfs = sorted((k for k in h.smap.kfs.values() if k.agent == h.agent), key=lambda k: k.id)
    return Trajectory(np.array([k.stamp_ns for k in kfs]), np.stack([k.T_m_kf for k in kfs]))


def twice(lap: Trajectory, dt_ns: int) -> Trajectory:
    """``lap`` flown twice, the second time ``dt_ns`` later."""
    return Trajectory(np.concatenate([lap.stamps_ns, lap.stamps_ns + dt_ns]),
                      np.concatenate([lap.poses, lap.poses]))  # fmt: skip


def cull(h: AgentHandler, rounds: int) -> None:
    """``rounds`` rounds of redundant-keyframe culling (seeded), keeping the newest."""
    rng = random.Random(0)
    for _ in range(rounds):
        for g in find_redundant(h.smap, rng, {h.kf_gid(h.latest_kf)}):
            h.on_removed(h.smap.kfs[g])
            h.smap.remove_keyframe(g)
