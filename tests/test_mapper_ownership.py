"""Three mappers own the maps through leases (services/mapper/ownership.py): new agents
spread over them; ``kill -9`` of one hands its map to another within about twice the
lease time, rebuilt from Redis, and its agent keeps being acked with nothing acked lost;
a mapper paused (SIGSTOP) past its lease and resumed writes nothing to the map another
took, and drops it."""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

from procs import ServiceProcess, fly, sim_agent, wait_until

from services.agent.sim_agent import LandmarkWorld
from services.agent.sim_runner import SimAgentRunner
from shared.leases import Leases
from shared.store import K_MAPPERS, Store, connect

LEASE_S = 1.0


def _mapper(settings, tmp: Path, name: str) -> ServiceProcess:
    return ServiceProcess("mapper", settings, tmp, name, env={
        "HIVEMAP_MAPPER__INSTANCE": name,
        "HIVEMAP_MAPPER__LEASE_S": str(LEASE_S),
        # Culled keyframes leave the stored set; here every acked one must stay.
        "HIVEMAP_MAPPER__REDUNDANCY": "false",
    })  # fmt: skip


def test_three_mappers_share_agents_fail_over_and_fence(settings, tmp_path):
    mappers = {n: _mapper(settings, tmp_path, n) for n in ("m1", "m2", "m3")}
    r = connect(settings.redis_url)
    store = Store(r)
    leases = Leases(r, "observer")
    world = LandmarkWorld(0)
    threads, results = [], {}
    stop = threading.Event()
    try:
        assert wait_until(lambda: r.hlen(K_MAPPERS) == 3, 60), \
            {n: m.log.read_text()[-800:] for n, m in mappers.items()}  # fmt: skip
        # Three agents on three stretches of MH01, far enough apart not to need a merge
        # (no placerec runs here), started one by one so each goes to the least loaded.
        for i, agent in enumerate("ABC"):
            sim = sim_agent(world, "MH01", slice(300 * i, 300 * i + 1500), seed=40 + i)
            threads.append(fly(SimAgentRunner(settings, agent, sim, speed=2.0, stop=stop),
                               results))  # fmt: skip
            assert wait_until(lambda agent=agent: leases.owner_of(f"map-{agent}"), 30), agent
            time.sleep(3 * LEASE_S)  # its load is in the next heartbeats
        owners = {m: leases.owner_of(m)[0] for m in ("map-A", "map-B", "map-C")}
        print("map owners:", owners)
        assert sorted(owners.values()) == ["m1", "m2", "m3"], owners

        # kill -9 of map-B's owner mid-flight.
        victim = mappers[owners["map-B"]]
        n_before = len(store.keyframe_ids("B"))
        os.kill(victim.proc.pid, signal.SIGKILL)
        t_kill = time.monotonic()
        victim.proc.wait(10)
        new_owner = wait_until(lambda: (o := leases.owner_of("map-B")) and o[0] != victim.name
                          and o[0], 10 * LEASE_S, step=0.02)  # fmt: skip
        takeover_s = time.monotonic() - t_kill
        print(f"map-B taken by {new_owner} {takeover_s:.2f} s after kill -9 (lease {LEASE_S} s)")
        assert new_owner in ("m1", "m2", "m3") and new_owner != victim.name
        assert takeover_s <= 2 * LEASE_S + 0.5, takeover_s
        # B keeps being acked by the new owner.
        assert wait_until(lambda: len(store.keyframe_ids("B")) > n_before + 3, 30), \
            mappers[new_owner].log.read_text()[-2000:]  # fmt: skip

        # SIGSTOP of map-C's owner past its lease, then SIGCONT: it must not write.
        paused = mappers[owners["map-C"]]
        if paused is victim or paused.name == new_owner:
            paused = mappers[owners["map-A"]]
        held = next(m for m, o in owners.items() if o == paused.name)
        os.kill(paused.proc.pid, signal.SIGSTOP)
        taker = wait_until(lambda: (o := leases.owner_of(held)) and o[0] != paused.name and o[0],
                      10 * LEASE_S)  # fmt: skip
        assert taker, f"nobody took {held} from the paused {paused.name}"
        time.sleep(1.0)  # the taker serves the agent for a while
        os.kill(paused.proc.pid, signal.SIGCONT)
        assert wait_until(lambda: f"dropped map {held}" in paused.log.read_text(), 10), \
            paused.log.read_text()[-2000:]  # fmt: skip
        assert leases.owner_of(held)[0] == taker

        for t in threads:
            t.join(240)
        for agent in "ABC":
            res = results[agent]
            stored = store.keyframe_ids(agent)
            print(agent, "sent", res.keyframes, "acked", res.acked_keyframes, "stored",
                  len(stored))  # fmt: skip
            assert res.all_acked, agent
            # Nothing acked is lost, nothing stored twice.
            assert len(stored) == len(set(stored)) == res.acked_keyframes, agent
        text = paused.log.read_text()
        print(
            "paused mapper after resuming:",
            [ln[-120:] for ln in text.splitlines() if "not stored" in ln or "dropped" in ln],
        )
    finally:
        stop.set()
        for t in threads:
            t.join(30)
        for m in mappers.values():
            m.close()
        r.close()


def test_a_match_across_two_owners_hands_one_map_over_and_merges(settings, tmp_path):
    """Two agents over the same place on two mappers: place recognition matches their
    maps, one owner hands its map to the other, the merge runs, nothing acked is lost."""
    from services.placerec.service import PlacerecService

    mappers = {n: _mapper(settings, tmp_path, n) for n in ("m1", "m2")}
    placerec = PlacerecService(settings)
    placerec.start()
    r = connect(settings.redis_url)
    store = Store(r)
    leases = Leases(r, "observer")
    world = LandmarkWorld(0)
    threads, results = [], {}
    stop = threading.Event()
    try:
        assert wait_until(lambda: r.hlen(K_MAPPERS) == 2, 60)
        for i, (agent, seq) in enumerate((("A", "MH01"), ("B", "MH02"))):
            sim = sim_agent(world, seq, slice(900), seed=20 + i)
            threads.append(fly(SimAgentRunner(settings, agent, sim, speed=2.0, stop=stop),
                               results))  # fmt: skip
            assert wait_until(lambda agent=agent: leases.owner_of(f"map-{agent}"), 30), agent
            if i == 0:
                time.sleep(3 * LEASE_S)  # A's load is in the heartbeats: B goes elsewhere
        owners = {m: leases.owner_of(m)[0] for m in ("map-A", "map-B")}
        print("map owners before the merge:", owners)
        assert sorted(owners.values()) == ["m1", "m2"], owners
        assert wait_until(lambda: len(store.maps()) == 1, 120), \
            {n: m.log.read_text()[-1500:] for n, m in mappers.items()}  # fmt: skip
        for t in threads:
            t.join(240)
        (merged,) = store.maps()
        for agent in "AB":
            res = results[agent]
            stored = store.keyframe_ids(agent)
            assert res.all_acked, agent
            assert len(stored) == len(set(stored)) == res.acked_keyframes, agent
            assert store.agent_state(agent).map_id == merged
        logs = {n: m.log.read_text() for n, m in mappers.items()}
        assert any("handed over to" in x for x in logs.values()), logs
        print("merged into", merged, "owned by", leases.owner_of(merged))
    finally:
        stop.set()
        for t in threads:
            t.join(30)
        placerec.stop()
        for m in mappers.values():
            m.close()
        r.close()
