"""Driving a simulated agent straight into a mapper, without transport (tests only)."""

from __future__ import annotations

from services.agent.comm import CommModule
from services.agent.sim_agent import SimAgent
from services.mapper.service import MapperService
from shared.messages import Ack


def feed_mapper(svc: MapperService, agent: str, sim: SimAgent) -> None:
    """Every keyframe of ``sim`` as one batch, applied synchronously, and acked."""
    comm = CommModule(agent, rate_hz=1e9)
    t = 0.0
    while not sim.done:
        _, _, kf = sim.step()
        if kf is None:
            continue
        comm.add_keyframe(kf.kf)
        comm.add_map_points(kf.new_mps)
        data = comm.next_message(t, 0, kf.kf.id).encode()
        ack = svc.process_kf_bytes(f"hivemap/agent/{agent}/up/kf", data, 0)
        comm.on_ack(Ack(agent, ack.map_id, ack.kf_ids, ack.mp_ids, 0, 0), t)
        t += 1.0
