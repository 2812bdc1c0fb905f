"""An agent id flown again (services/mapper/sessions.py): every flight is stored, as an
agent of its own, while resends within a flight are still deduplicated, and a mapper
restart does not start a new flight.

Before sessions, the second flight of an agent id against the same Redis (``hivemap up``
keeps its data by default) sent keyframe ids 0, 1, ... again, and the mapper acked them
as duplicates of the first flight's and dropped them."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from fastapi.testclient import TestClient
from procs import ServiceProcess, gt_part, wait_until

from services.agent.comm import CommModule
from services.agent.sim_agent import DriftModel, SimAgent
from services.agent.sim_runner import SimAgentRunner
from services.api.main import create_app
from services.mapper.feedback import label
from services.mapper.service import MapperService
from shared import keys
from shared.messages import Ack, KeyframeBatch, PoseUpdate, peek_session
from shared.metrics import sample_value
from shared.settings import Settings
from shared.store import Store, connect


def _batches(world, seq: str, frames: slice, session: int | None, n: int) -> list[KeyframeBatch]:
    """The first ``n`` batches of agent A flying ``frames`` of ``seq`` (one keyframe
    each, ids from 0), in session ``session`` (None: an agent without sessions)."""
    sim = SimAgent(gt_part(seq, frames.start, frames.stop), world, drift=DriftModel.zero())
    comm = CommModule("A", rate_hz=1e9)
    out, t = [], 0.0
    while len(out) < n and not sim.done:
        _, _, kf = sim.step()
        if kf is None:
            continue
        comm.add_keyframe(kf.kf)
        comm.add_map_points(kf.new_mps)
        msg = comm.next_message(t, int(t * 1e9), kf.kf.id)
        msg.session = session
        out.append(msg)
        acked = KeyframeBatch.decode(msg.encode())  # as the mapper reads it
        comm.on_ack(Ack("A", "m", np.array([k.id for k in acked.new_kfs], np.int64),
                        acked.new_mps.ids, -1, 0, seq=msg.seq), t)  # fmt: skip
        t += 1.0
    return out


def _put(svc: MapperService, b: KeyframeBatch):
    return svc.process_kf_bytes(keys.agent_kf(b.agent), b.encode(compact=True), time.time_ns())


def _stored_keyframes() -> float:
    return sample_value("hivemap_stored_total", {"service": "mapper", "kind": "keyframe"})


def _duplicates() -> float:
    return sample_value("hivemap_registration_events_total", {"what": "duplicate"})


def test_resends_within_a_flight_are_deduplicated_and_a_second_flight_is_stored(redis_url, world):
    s = Settings(redis_url=redis_url)
    svc = MapperService(s)
    store = svc.store
    first = _batches(world, "MH01", slice(900, 1300), session=11, n=6)
    for b in first:
        t0 = time.time_ns()
        ack = _put(svc, b)
        assert ack.map_id == "map-A" and list(ack.kf_ids) == [k.id for k in b.new_kfs]
        # How long the mapper held the batch (the agent's window answers that part of
        # the ack latency only): from its arrival to the ack, no more.
        assert ack.held_s is not None and 0 < ack.held_s <= (time.time_ns() - t0) * 1e-9
    assert store.keyframe_ids("A") == list(range(6))
    # Resends within the flight: acknowledged, stored once.
    before, dup = _stored_keyframes(), _duplicates()
    for b in (first[2], first[5], first[0]):
        ack = _put(svc, b)
        assert list(ack.kf_ids) == [k.id for k in b.new_kfs] and ack.map_id == "map-A"
    assert _stored_keyframes() == before and _duplicates() == dup + 3
    assert store.agents() == ["A"] and store.keyframe_ids("A") == list(range(6))
    # A mapper restarted from Redis takes the flight's resends as resends too.
    svc.store.close()
    svc = MapperService(s)
    svc.load()
    ack = _put(svc, first[5])
    assert list(ack.kf_ids) == [first[5].new_kfs[0].id] and ack.map_id == "map-A"
    assert _stored_keyframes() == before and svc.store.agents() == ["A"]
    assert _duplicates() == dup + 4
    # A second flight of A (a new process: a new session), elsewhere, ids from 0 again:
    # stored in full, as an agent of its own with a map of its own.
    second = _batches(world, "MH03", slice(300, 700), session=12, n=5)
    assert [b.new_kfs[0].id for b in second] == list(range(5))
    for b in second:
        ack = _put(svc, b)
        assert ack.agent == "A" and ack.map_id == "map-A.s2"
        assert list(ack.kf_ids) == [k.id for k in b.new_kfs]
    assert _stored_keyframes() == before + 5 and _duplicates() == dup + 4  # none dropped
    store = svc.store
    assert store.agents() == ["A", "A.s2"]
    assert store.keyframe_ids("A") == list(range(6)) and store.keyframe_ids("A.s2") == list(
        range(5)
    )
    # Nothing of the first flight was overwritten by the second.
    for k in store.keyframes("A"):
        assert k.stamp_ns == first[k.id].new_kfs[0].stamp_ns
    for k in store.keyframes("A.s2"):
        assert k.stamp_ns == second[k.id].new_kfs[0].stamp_ns
    assert store.agent_info("A")["flight"] == 1 and store.agent_info("A.s2")["flight"] == 2
    assert store.agent_info("A.s2")["name"] == "A"
    # The second flight's live pose lands in its own map.
    T = second[-1].new_kfs[0].T_l_kf
    p = PoseUpdate("A", 5, T, 4, np.eye(4), session=12)
    pose = svc.process_pose_bytes(keys.agent_pose("A"), p.encode(), 0)
    assert pose.agent == "A.s2" and pose.map_id == "map-A.s2"
    np.testing.assert_allclose(pose.T_m_c, svc.handlers["A.s2"].kf_pose(4), atol=1e-9)
    # The REST API lists both flights, each with its trajectory.
    with TestClient(create_app(s)) as c:
        agents = {a["agent"]: a for a in c.get("/agents").json()}
        assert set(agents) == {"A", "A.s2"}
        assert (agents["A"]["name"], agents["A"]["flight"], agents["A"]["n_kf"]) == ("A", 1, 6)
        a2 = agents["A.s2"]
        assert (a2["name"], a2["flight"], a2["n_kf"], a2["map_id"]) == ("A", 2, 5, "map-A.s2")
        assert a2["last_pose"]["agent"] == "A.s2"
        tj = c.get("/agents/A.s2/trajectory").json()
        assert (tj["name"], tj["flight"], len(tj["keyframes"])) == ("A", 2, 5)
    svc.store.close()


def test_flights_of_data_from_before_sessions_and_of_taken_names(redis_url, world):
    s = Settings(redis_url=redis_url)
    svc = MapperService(s)
    # Stored by an agent without sessions (the first wire version): its flight 1.
    for b in _batches(world, "MH01", slice(900, 1100), session=None, n=3):
        assert b.encode().find(b"session") < 0
        _put(svc, b)
    assert svc.store.agent_info("A")["flight"] == 1 and svc.store.agent_info("A")["name"] == "A"
    for b in _batches(world, "MH02", slice(900, 1100), session=99, n=2):
        assert _put(svc, b).map_id == "map-A.s2"
    assert svc.store.keyframe_ids("A") == [0, 1, 2] and svc.store.keyframe_ids("A.s2") == [0, 1]
    store = svc.store
    # Names another flight holds are skipped; a flight's name is given once.
    assert store.flight("X", 1) == "X" and store.flight("X.s2", 1) == "X.s2"
    assert store.flight("X", 2) == "X.s3" and store.flight("X", 1) == "X"
    assert store.flight("X.s2", 2) == "X.s2.s2"
    # An agent registered ahead of its flight, without keyframes (as a test or bench
    # puts agents into one map): its first flight is it.
    svc.handler("P", "map-shared")
    assert store.flight("P", 5) == "P" and store.flight("P", 6) == "P.s2"
    long = "L" * 64
    name = store.flight(long, 1), store.flight(long, 2)
    assert name[0] == long and len(name[1]) <= 60 and name[1].endswith(".s2")
    keys.check_id(f"map-{name[1]}", "map")
    store.close()


def test_bad_sessions_are_counted_as_rejected(redis_url, world):
    svc = MapperService(Settings(redis_url=redis_url))
    b = _batches(world, "MH01", slice(900, 1100), session=3, n=1)[0]
    key = keys.agent_kf("A")

    def rejected() -> float:
        return sample_value("hivemap_messages_rejected_total",
                            {"service": "mapper", "key": key, "reason": "invalid"})  # fmt: skip

    before = rejected()
    for bad in (-1, "3", 2.5, True):
        b.session = bad
        data = b.encode()
        assert peek_session(data) is None
        assert svc.process_kf_bytes(key, data, 0) is None
    assert rejected() == before + 4
    assert svc.store.agents() == []
    b.session = 3
    assert peek_session(b.encode(compact=True)) == 3
    assert KeyframeBatch.decode(b.encode()).session == 3
    p = PoseUpdate("A", 1, np.eye(4), 0, np.eye(4), session=2**63 - 1)
    assert PoseUpdate.decode(p.encode()).session == 2**63 - 1
    for garbage in (b"", b"\x81\xa7session", b"\xc1" * 9, b"\x93\x01\x02\x03"):
        assert peek_session(garbage) is None
    svc.store.close()


def test_map_chunks_name_an_earlier_flight_as_another_agent():
    class H:
        agent, name = "A.s2", "A"

    assert label(H, "A.s2") == "A"  # its own keyframes: under the id it flies as
    assert label(H, "A") == "A#"  # its first flight's: another agent to it
    assert label(H, "B") == "B"
    H.agent = "A"
    assert label(H, "A") == "A" and label(H, "A.s2") == "A.s2"


@pytest.fixture()
def stack(settings):
    s = settings.model_copy(update={
        "mapper": settings.mapper.model_copy(update={"redundancy": False}),
        "comm": settings.comm.model_copy(update={"resend_timeout_s": 1.0}),
    })  # fmt: skip
    return s


def test_two_flights_of_agent_a_through_router_and_mapper_all_stored(stack, world, tmp_path):
    """Real router, redis and mapper process; agent A flies, lands, and flies again
    elsewhere; the mapper is killed (-9) and restarted during the second flight."""
    s = stack
    env = {"HIVEMAP_MAPPER__REDUNDANCY": "false"}
    mapper = ServiceProcess("mapper", s, tmp_path, "mapper", env)
    store = Store(connect(s.redis_url))
    try:
        first = SimAgentRunner(s, "A", SimAgent(gt_part("MH01", 900, 1250), world,
                                                drift=DriftModel.zero()),
                               speed=0, flush_timeout_s=30).run()  # fmt: skip
        assert first.all_acked and first.keyframes >= 10
        runner = SimAgentRunner(s, "A", SimAgent(gt_part("MH03", 300, 700), world,
                                                 drift=DriftModel.zero(), seed=2),
                                speed=5.0, flush_timeout_s=40)  # fmt: skip
        out: dict = {}
        t = threading.Thread(target=lambda: out.setdefault("stats", runner.run()))
        t.start()
        assert wait_until(lambda: len(runner.comm.acked_kfs) >= 5, 20), mapper.log.read_text()
        mapper.proc.kill()
        mapper.proc.wait()
        acked_at_kill = set(runner.comm.acked_kfs)
        mapper.close()
        mapper = ServiceProcess("mapper", s, tmp_path, "mapper2", env)
        t.join(60)
        second = out["stats"]
    finally:
        mapper.close()
    assert second.all_acked and second.keyframes >= 10
    # Every keyframe of both flights stored, none taken for a duplicate; the restart
    # did not start a third flight.
    assert store.agents() == ["A", "A.s2"]
    assert store.keyframe_ids("A") == list(range(first.keyframes))
    assert store.keyframe_ids("A.s2") == list(range(second.keyframes))
    assert acked_at_kill <= set(store.keyframe_ids("A.s2"))
    assert len(store.r.hgetall("hm:agent:A:sessions")) == 2
    info = store.agent_info("A.s2")
    assert (info["name"], info["flight"], info["map_id"]) == ("A", 2, "map-A.s2")
    assert "new flight" in (tmp_path / "mapper.log").read_text()
    print(f"\nflight 1: {first.keyframes} keyframes, flight 2: {second.keyframes} "
          f"({len(acked_at_kill)} acked before kill -9 of the mapper); all stored")  # fmt: skip
    store.close()
