"""A map actor registers the batches queued for its map together and stores them in one
transaction (issue 18, mapper latency under many agents): the map, what Redis holds and
the acks must be exactly what registering them one at a time gives."""

from __future__ import annotations

import time
import zlib

import numpy as np
from procs import gt_part

from services.agent.comm import CommModule
from services.agent.sim_agent import SimAgent
from services.mapper import persist
from services.mapper.registration import MapperParams
from services.mapper.server_map import digest
from services.mapper.service import GROUP_MAX, MapperService
from shared.geometry import Sim3
from shared.messages import Ack
from shared.settings import Settings
from shared.store import Store, connect


def _flight(world, agent: str, seq: str, frames: tuple[int, int], seed: int) -> list:
    """(key, payload) of every batch a simulated agent sends, each acked as sent."""
    comm = CommModule(agent, rate_hz=1e9, session=zlib.crc32(agent.encode()))
    sim = SimAgent(gt_part(seq, *frames), world, seed=seed)
    out, t = [], 0.0
    while not sim.done:
        kf = sim.step()[2]
        if kf is None:
            continue
        comm.add_keyframe(kf.kf)
        comm.add_map_points(kf.new_mps)
        msg = comm.next_message(t, 0, kf.kf.id)
        out.append((f"hivemap/agent/{agent}/up/kf", msg.encode()))
        comm.on_ack(Ack(agent, "m", np.array([k.id for k in msg.new_kfs], np.int64),
                        msg.new_mps.ids.astype(np.int64), 0, 0), t)  # fmt: skip
        t += 1.0
    return out


def _interleaved(world) -> list:
    a = _flight(world, "A", "MH01", (900, 1300), 1)
    b = _flight(world, "B", "MH02", (700, 1100), 2)
    return [m for pair in zip(a, b, strict=False) for m in pair] + a[len(b) :] + b[len(a) :]


def _service(redis_url: str) -> MapperService:
    """A mapper whose agents A and B register into one map (B joined A's map). It never
    sheds: the test queues every batch before the actor takes any, and on a loaded
    machine the last ones waited past ``shed_after_s`` (64 of 77 registered, once)."""
    svc = MapperService(Settings(redis_url=redis_url, mapper={"shed_after_s": 3600.0}))
    svc.handler("A")
    svc.handler("B", map_id="map-A", S_m_l=Sim3.identity())
    return svc


def _state(svc: MapperService, redis_url: str) -> tuple[dict, dict]:
    maps, _ = persist.load_all(Store(connect(redis_url)), MapperParams())
    assert list(maps) == ["map-A"] and maps["map-A"].check_invariants() == []
    assert svc.maps["map-A"].check_invariants() == []
    return digest(svc.maps["map-A"]), digest(maps["map-A"])


def test_queued_batches_registered_together_give_the_same_map_store_and_acks(
    redis_url, world, monkeypatch
):
    from services.mapper import service

    monkeypatch.setattr(service, "GROUP_BUDGET_S", 10.0)  # groups by count, not by time
    msgs = _interleaved(world)
    assert len(msgs) > 3 * GROUP_MAX
    import redis

    # One batch at a time.
    one = _service(redis_url)
    acks_one = []
    for key, payload in msgs:
        batch = one.decode_kf(key, payload)
        acks_one.append(one.apply(one.handler(batch.agent), batch, time.time_ns()))
    want_mem, want_stored = _state(one, redis_url)
    assert want_mem["n_kf"] > 20

    r = redis.Redis.from_url(redis_url)
    r.flushall()
    r.close()

    # Everything queued first, then taken up by the actor's grouped path.
    svc = _service(redis_url)
    actor = svc.actor("map-A")  # not started: no session
    for key, payload in msgs:
        batch = svc.decode_kf(key, payload)
        h = svc.handler(batch.agent)
        pre = h.undistorted(batch) if len(actor.q.queue) % 2 else None  # either way
        actor.q.put((h, batch, time.time_ns(), key, pre))
    groups = []
    while not actor.q.empty():
        groups.append(actor._apply_queued(actor.q.get(), time.monotonic()))
    assert sum(groups) == len(msgs)
    assert max(groups) == GROUP_MAX and len(groups) == -(-len(msgs) // GROUP_MAX)
    assert _state(svc, redis_url) == (want_mem, want_stored)
    assert want_mem == want_stored

    # The acks of a group, in order, are those of the batches one at a time.
    r = redis.Redis.from_url(redis_url)
    r.flushall()
    r.close()
    svc = _service(redis_url)
    acks = []
    for i in range(0, len(msgs), 5):
        group = []
        for key, payload in msgs[i : i + 5]:
            batch = svc.decode_kf(key, payload)
            h = svc.handler(batch.agent)
            group.append((h, batch, time.time_ns(), svc.ingest(h, batch)))
        acks += svc.store_and_ack(group)
    assert len(acks) == len(acks_one)
    for a, b in zip(acks, acks_one, strict=True):
        assert (a.agent, a.map_id, a.kf_high, a.seq) == (b.agent, b.map_id, b.kf_high, b.seq)
        for f in ("kf_ids", "mp_ids", "held_kf_ids", "missing_kf_ids"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    assert _state(svc, redis_url) == (want_mem, want_stored)
