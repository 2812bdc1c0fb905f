"""Mapper, placerec and optimizer as services on a real Zenoh router and a real
redis-server: two simulated agents that start in one place end in one map, found by
place recognition (not told), optimized, corrected; garbage on every new key is
counted and nothing stops serving."""

from __future__ import annotations

import time

import numpy as np
import pytest
from procs import fly_two_agents, wait_until

from services.mapper.service import MapperService
from services.optimizer.service import OptimizerService
from services.placerec.service import PlacerecService
from shared import keys
from shared.evaluation import evaluate_team
from shared.jobs import K_JOBS, JobQueue
from shared.messages import packb
from shared.metrics import sample_value
from shared.store import Store, connect
from shared.trajectory import Trajectory
from shared.transport import Bus, open_session

GARBAGE = [b"", b"\x00\x01", b"\xc1" * 40, packb({"schema": "hivemap.match/9"}), packb([1])]


@pytest.fixture()
def services(settings):
    mapper, placerec, optimizer = (MapperService(settings), PlacerecService(settings),
                                   OptimizerService(settings))  # fmt: skip
    for s in (mapper, placerec, optimizer):
        s.start()
    yield mapper, placerec, optimizer
    for s in (optimizer, placerec, mapper):
        s.stop()


def _rejected(service: str, key: str) -> float:
    return sum(sample_value("hivemap_messages_rejected_total",
                            {"service": service, "key": key, "reason": r})
               for r in ("invalid", "malformed", "version", "schema"))  # fmt: skip


def test_two_agents_meet_merge_and_get_optimized(settings, services, world):
    mapper, placerec, optimizer = services
    targets = [
        ("mapper", keys.MATCH), ("mapper", keys.map_correction("map-X")),
        ("placerec", keys.map_kf("map-X")), ("placerec", keys.map_merged("map-X")),
        ("optimizer", K_JOBS),
    ]  # fmt: skip
    before = {t: _rejected(*t) for t in targets}
    with open_session(settings.zenoh) as session:
        bus = Bus(session, "test")
        time.sleep(0.5)  # subscribers of the services are declared; routes settle
        jobs = JobQueue(connect(settings.redis_url))
        for _, key in targets:
            for g in GARBAGE:
                if key == K_JOBS:  # optimization jobs come through Redis
                    jobs.submit("map-X", g)
                else:
                    bus.put(key, g)
        assert wait_until(lambda: all(_rejected(*t) - before[t] >= len(GARBAGE)
                                      for t in targets), 15), \
            {t: _rejected(*t) - before[t] for t in targets}  # fmt: skip
        bus.close()
    for t in targets:
        assert _rejected(*t) - before[t] == len(GARBAGE), t

    results, gts = fly_two_agents(settings, world)
    assert all(results[a].all_acked for a in "AB")
    merged = wait_until(lambda: len(mapper.maps) == 1, 30)
    assert merged, "place recognition never merged the two maps"
    corrected = wait_until(lambda: sample_value("hivemap_corrections_applied_total", {}) >= 1, 60)
    assert corrected, "no optimization came back"
    smap = next(iter(mapper.maps.values()))
    with mapper.actor(smap.map_id).lock:
        assert smap.check_invariants() == []
    store = Store(connect(settings.redis_url))
    assert store.maps() == [smap.map_id]
    trajs = {}
    for a in "AB":
        assert store.agent_info(a)["map_id"] == smap.map_id
        _, stamps, poses = store.trajectory(a)
        trajs[a] = (smap.map_id, Trajectory(stamps, poses))
    (ev,) = evaluate_team(trajs, gts)
    # One frame for both: the joint error stays at the level of the simulated VO drift.
    assert ev.joint_ate_m < 0.15, ev
    assert placerec.rec.db.maps() == [smap.map_id]
    assert sample_value("hivemap_placerec_matches_total", {"kind": "merge"}) >= 1
    assert np.isfinite(ev.joint_ate_m)
