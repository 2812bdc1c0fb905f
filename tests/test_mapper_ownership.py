"""Three mappers own the maps through leases (services/mapper/ownership.py): new agents
spread over them; ``kill -9`` of one hands its map to another within about twice the
lease time, rebuilt from Redis, and its agent keeps being acked with nothing acked lost;
a mapper paused (SIGSTOP) past its lease and resumed writes nothing to the map another
took, and drops it."""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from pathlib import Path

from procs import ServiceProcess, fly, sim_agent, wait_until

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


class Mappers:
    """``n`` mapper processes, what the test sees of Redis, and the simulated agents it
    flies (each in a thread)."""

    def __init__(self, settings, tmp: Path, n: int) -> None:
        self.settings = settings
        self.mappers = {f"m{i + 1}": _mapper(settings, tmp, f"m{i + 1}") for i in range(n)}
        self.r = connect(settings.redis_url)
        self.store = Store(self.r)
        self.leases = Leases(self.r, "observer")
        self.stop = threading.Event()
        self.threads: list[threading.Thread] = []
        self.results: dict = {}

    def logs(self, tail: int | None = None) -> dict[str, str]:
        """Each mapper's log, or its last ``tail`` characters."""
        return {n: m.log.read_text()[-(tail or 0) :] for n, m in self.mappers.items()}

    def fly(self, agent: str, sim) -> None:
        runner = SimAgentRunner(self.settings, agent, sim, speed=2.0, stop=self.stop)
        self.threads.append(fly(runner, self.results))

    def join(self, timeout: float) -> None:
        for t in self.threads:
            t.join(timeout)

    def assert_all_acked_stored_once(self, agent: str) -> None:
        """Nothing acked is lost, nothing stored twice."""
        res, stored = self.results[agent], self.store.keyframe_ids(agent)
        print(agent, "sent", res.keyframes, "acked", res.acked_keyframes, "stored",
              len(stored))  # fmt: skip
        assert res.all_acked, agent
        assert len(stored) == len(set(stored)) == res.acked_keyframes, agent


@contextlib.contextmanager
def _mappers(settings, tmp: Path, n: int):
    """``Mappers`` once all ``n`` said they live; stopped, agents and all, at the end."""
    c = Mappers(settings, tmp, n)
    try:
        assert wait_until(lambda: c.r.hlen(K_MAPPERS) == n, 60), c.logs(800)
        yield c
    finally:
        c.stop.set()
        c.join(30)
        for m in c.mappers.values():
            m.close()
        c.r.close()


def test_three_mappers_share_agents_fail_over_and_fence(settings, tmp_path, world):
    with _mappers(settings, tmp_path, 3) as c:
        mappers, leases = c.mappers, c.leases
        # Three agents on three stretches of MH01, far enough apart not to need a merge
        # (no placerec runs here), started one by one so each goes to the least loaded.
        for i, agent in enumerate("ABC"):
            c.fly(agent, sim_agent(world, "MH01", slice(300 * i, 300 * i + 1000), seed=40 + i))
            assert wait_until(lambda agent=agent: leases.owner_of(f"map-{agent}"), 30), agent
            time.sleep(3 * LEASE_S)  # its load is in the next heartbeats
        owners = {m: leases.owner_of(m)[0] for m in ("map-A", "map-B", "map-C")}
        print("map owners:", owners)
        assert sorted(owners.values()) == ["m1", "m2", "m3"], owners

        # kill -9 of map-B's owner mid-flight.
        victim = mappers[owners["map-B"]]
        n_before = len(c.store.keyframe_ids("B"))
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
        assert wait_until(lambda: len(c.store.keyframe_ids("B")) > n_before + 3, 30), \
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

        c.join(240)
        for agent in "ABC":
            c.assert_all_acked_stored_once(agent)
        text = paused.log.read_text()
        print(
            "paused mapper after resuming:",
            [ln[-120:] for ln in text.splitlines() if "not stored" in ln or "dropped" in ln],
        )


def test_a_match_across_two_owners_hands_one_map_over_and_merges(settings, tmp_path, world):
    """Two agents over the same place on two mappers: place recognition matches their
    maps, one owner hands its map to the other, the merge runs, nothing acked is lost."""
    from services.placerec.service import PlacerecService

    placerec = PlacerecService(settings)
    placerec.start()
    try:
        with _mappers(settings, tmp_path, 2) as c:
            store, leases = c.store, c.leases
            for i, (agent, seq) in enumerate((("A", "MH01"), ("B", "MH02"))):
                c.fly(agent, sim_agent(world, seq, slice(900), seed=20 + i))
                assert wait_until(lambda agent=agent: leases.owner_of(f"map-{agent}"), 30), agent
                if i == 0:
                    time.sleep(3 * LEASE_S)  # A's load is in the heartbeats: B goes elsewhere
            owners = {m: leases.owner_of(m)[0] for m in ("map-A", "map-B")}
            print("map owners before the merge:", owners)
            assert sorted(owners.values()) == ["m1", "m2"], owners
            assert wait_until(lambda: len(store.maps()) == 1, 120), c.logs(1500)
            c.join(240)
            (merged,) = store.maps()
            for agent in "AB":
                c.assert_all_acked_stored_once(agent)
                assert store.agent_state(agent).map_id == merged
            logs = c.logs()
            # Handed over once: the old owner does not take the released map back.
            assert sum(x.count("handed over to") for x in logs.values()) == 1, logs
            print("merged into", merged, "owned by", leases.owner_of(merged))
    finally:
        placerec.stop()
