"""Optimizers as a pool (shared/jobs.py): two ``hivemap optimizer`` processes share the
job stream; one killed with ``kill -9`` mid-job leaves the job to the other, one paused
past its claim and resumed runs it a second time, and either way the mapper applies the
job's correction once."""

from __future__ import annotations

import os
import signal
import time
from functools import partial
from pathlib import Path

import pytest
from feeding import feed_mapper as _feed
from procs import ServiceProcess, sim_agent, wait_until

from services.agent.sim_agent import LandmarkWorld
from services.mapper.service import MapperService
from shared.jobs import K_JOBS, JobQueue
from shared.metrics import sample_value
from shared.settings import Settings
from shared.store import connect

CLAIM_IDLE_S = 2.0
_wait = partial(wait_until, step=0.02)


def _worker(settings: Settings, tmp: Path, name: str) -> ServiceProcess:
    return ServiceProcess("optimizer", settings, tmp, name, env={
        "HIVEMAP_OPTIMIZER__CLAIM_IDLE_S": str(CLAIM_IDLE_S),
        # Long enough a run that the test catches it mid-job.
        "HIVEMAP_OPTIMIZER__BA_MAX_ITERATIONS": "200",
        "HIVEMAP_OPTIMIZER__BA_TIME_BUDGET_S": "3",
        "HIVEMAP_OPTIMIZER__NICE": "0",
    })  # fmt: skip


def _consumers(r) -> dict[int, str]:
    """pid -> consumer name of every live worker (names are host-pid-random)."""
    return {int(n.split("-")[-2]): n for n in JobQueue(r).workers(within_s=CLAIM_IDLE_S / 2)}


def _applied() -> float:
    return sample_value("hivemap_corrections_applied_total", {})


def _duplicates(map_id: str) -> float:
    return sample_value("hivemap_messages_rejected_total",
                        {"service": "mapper", "key": f"hivemap/map/{map_id}/correction",
                         "reason": "duplicate"})  # fmt: skip


@pytest.fixture()
def stack(settings, tmp_path):
    """A map of one simulated agent stored in Redis, a mapper serving it, two workers."""
    _feed(MapperService(settings), "A", sim_agent(LandmarkWorld(0), "MH01", slice(600), seed=3))
    mapper = MapperService(settings)
    # One job per request: a BA stopped by its time budget (on a loaded machine) would
    # ask for a continuation, a newer copy of the map, and a worker resumed from a pause
    # then drops its stale run instead of finishing it, which is what the tests watch.
    # Nor settling: a global run leaves the agent's frontier to a windowed BA (collab
    # ``_frontier``), which would be such a newer copy too.
    mapper.collab.max_continues = 0
    mapper.collab.settle_kfs = mapper.collab.settle_window_kfs = 0
    mapper.start()  # rebuilds the map from Redis, takes corrections over Zenoh
    workers = [_worker(settings, tmp_path, f"opt{i}") for i in range(2)]
    r = connect(settings.redis_url)
    try:
        assert _wait(lambda: len(_consumers(r)) == 2, 60), \
            [w.log.read_text()[-1500:] for w in workers]  # fmt: skip
        yield mapper, workers, r, tmp_path
    finally:
        for w in workers:
            w.close()
        mapper.stop()
        r.close()


def _holder(r, workers: list[ServiceProcess], taken_before: int) -> ServiceProcess:
    """The worker that holds the one pending job and has started on it."""
    q = JobQueue(r)
    pend = _wait(lambda: sum(q.taken().values()) > taken_before and q.pending(), 30)
    assert pend, "no worker took the job"
    ((_, consumer),) = pend
    pid = next(p for p, n in _consumers(r).items() if n == consumer)
    return next(w for w in workers if w.proc.pid == pid)


def test_a_killed_worker_leaves_its_job_to_another_and_it_is_applied_once(settings, stack):
    mapper, workers, r, tmp = stack
    (map_id,) = mapper.maps
    q = JobQueue(r)
    applied0, dup0 = _applied(), _duplicates(map_id)

    # 1. kill -9 mid-job: the other worker claims it once it has been idle CLAIM_IDLE_S.
    assert mapper.collab.request(map_id, "loop") is not None
    victim = _holder(r, workers, 0)
    (survivor,) = [w for w in workers if w is not victim]
    os.kill(victim.proc.pid, signal.SIGKILL)
    t_kill = time.monotonic()
    victim.proc.wait(10)
    assert _applied() == applied0, "the killed worker had finished already"
    names = _consumers(r)
    assert _wait(lambda: q.taken().get(names[survivor.proc.pid], 0) >= 1, 4 * CLAIM_IDLE_S)
    takeover_s = time.monotonic() - t_kill
    assert takeover_s < 2 * CLAIM_IDLE_S + 1.0, takeover_s
    assert _wait(lambda: _applied() == applied0 + 1, 60), survivor.log.read_text()[-2000:]
    assert _wait(lambda: not q.pending() and r.xlen(K_JOBS) == 0, 10)
    assert "from a worker that stopped; delivery 2" in survivor.log.read_text()
    print(f"takeover after kill -9: {takeover_s:.2f} s (claim idle {CLAIM_IDLE_S} s)")

    # 2. A worker paused past its claim and resumed runs the job a second time; the
    # mapper applies the job's correction once.
    workers.append(_worker(settings, tmp, "opt2"))
    assert _wait(lambda: len(_consumers(r)) == 2 and victim.proc.pid not in _consumers(r), 60)
    assert mapper.collab.request(map_id, "loop") is not None
    paused = _holder(r, [w for w in workers if w.proc.poll() is None], 2)
    os.kill(paused.proc.pid, signal.SIGSTOP)
    assert _wait(lambda: _applied() == applied0 + 2, 60), "no other worker ran the job"
    os.kill(paused.proc.pid, signal.SIGCONT)
    assert _wait(lambda: _duplicates(map_id) == dup0 + 1, 60), paused.log.read_text()[-2000:]
    time.sleep(1.0)
    assert _applied() == applied0 + 2
    assert "taken over by another worker meanwhile" in paused.log.read_text()
    taken = q.taken()
    print("jobs taken per worker:", taken)
    assert sum(taken.values()) == 4  # two jobs, each taken twice


def test_a_large_copy_goes_through_redis_in_slices_and_is_deleted_with_its_job(redis_url):
    """A copy over the slice size is pushed to a key of its own a slice at a time (one
    XADD of tens of MB kept Redis from every other client for about half a second); a
    worker reads it back whole, and the key goes when the job is done."""
    r = connect(redis_url)
    try:
        q = JobQueue(r, consumer="w")
        q.data_slice = 1000
        q.ensure_group()
        data = bytes(range(256)) * 16 + b"end"  # 4099 bytes: 5 slices
        pauses = []
        jid = q.submit("map-A", bytearray(data), pause=lambda: pauses.append(1))
        small = q.submit("map-B", b"small")
        assert len(pauses) == 4
        job = q.take(block_s=0.1)
        assert (job.id, job.map_id, job.data) == (jid, "map-A", data)
        assert job.data_key is not None and r.exists(job.data_key)
        q.done(job, finished=True)
        assert not r.exists(job.data_key)
        job = q.take(block_s=0.1)
        assert (job.id, job.data, job.data_key) == (small, b"small", None)
        # A copy gone before it was read (expired) decodes as nothing: rejected.
        jid = q.submit("map-A", data)
        r.delete(*r.keys("*opt:data*"))
        assert q.take(block_s=0.1).data == b""
    finally:
        r.close()
