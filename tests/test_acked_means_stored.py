"""An acknowledgement means "stored", also after a store or a registration that failed."""

from __future__ import annotations

import pytest


def _first_batch() -> bytes:
    """Agent A's first keyframe batch, as it goes on the wire."""
    from services.agent.comm import CommModule
    from services.agent.sim_agent import DriftModel, LandmarkWorld, SimAgent
    from shared.trajectory import Trajectory, load_euroc_gt

    gt = load_euroc_gt("MH01")
    sim = SimAgent(Trajectory(gt.stamps_ns[900:], gt.poses[900:]), LandmarkWorld(0),
                   drift=DriftModel.zero())  # fmt: skip
    comm = CommModule("A", rate_hz=1e9)
    while not comm.kfs:
        kf = sim.step()[2]
        if kf is not None:
            comm.add_keyframe(kf.kf)
            comm.add_map_points(kf.new_mps)
    return comm.next_message(0.0, 0, 0).encode()


def test_a_keyframe_whose_store_failed_is_not_acked_as_a_duplicate_later(redis_url, monkeypatch):
    """A batch registered in memory whose store failed is not acknowledged; its resend is
    a duplicate for the map in memory, and its ack must still mean "stored": what the
    failed store missed is written first."""
    import redis

    from services.mapper import persist
    from services.mapper.service import MapperService
    from shared.settings import Settings

    msg = _first_batch()
    svc = MapperService(Settings(redis_url=redis_url))
    key = "hivemap/agent/A/up/kf"
    write = persist.write_result
    calls = []

    def broken(*a, **kw):
        calls.append(1)
        if len(calls) == 1:
            raise redis.ConnectionError("redis went away")
        return write(*a, **kw)

    monkeypatch.setattr(persist, "write_result", broken)
    with pytest.raises(redis.ConnectionError):
        svc.process_kf_bytes(key, msg, 0)  # registered in memory, not stored: no ack
    (h,) = svc.handlers.values()
    assert h.has_kf(0) and svc.store.keyframe_ids(h.agent) == []
    ack = svc.process_kf_bytes(key, msg, 0)  # the agent's resend: a duplicate
    assert ack.kf_ids.tolist() == [0]
    assert 0 in svc.store.keyframe_ids(h.agent)  # acknowledged means stored
    assert not svc._unstored
    svc.store.close()


def test_a_registration_that_fails_part_way_is_stored_before_the_resend_is_acked(
    redis_url, monkeypatch
):
    """Registration raises after the keyframe entered the map in memory (a bug, an
    unexpected input): the batch is not acknowledged, and its resend, a duplicate for
    the map in memory, is acknowledged only with the keyframe stored."""
    from services.mapper.registration import AgentHandler, IngestFailed
    from services.mapper.service import MapperService
    from shared.settings import Settings

    msg = _first_batch()
    svc = MapperService(Settings(redis_url=redis_url))
    key = "hivemap/agent/A/up/kf"
    attach = AgentHandler._attach_ready_mps
    calls = []

    def broken(self, res):
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("injected fault after the keyframe's insertion")
        return attach(self, res)

    monkeypatch.setattr(AgentHandler, "_attach_ready_mps", broken)
    with pytest.raises(IngestFailed):
        svc.process_kf_bytes(key, msg, 0)
    (h,) = svc.handlers.values()
    assert h.has_kf(0) and svc.store.keyframe_ids(h.agent) == []
    ack = svc.process_kf_bytes(key, msg, 0)
    assert ack.kf_ids.tolist() == [0]
    assert 0 in svc.store.keyframe_ids(h.agent)
    assert not svc._unstored
    svc.store.close()
