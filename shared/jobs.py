"""Optimization jobs: a Redis stream with one consumer group that every optimizer reads.

The mapper adds a job (a map copy to optimize) with :meth:`JobQueue.submit`; any number
of optimizers take jobs with :meth:`JobQueue.take`; each job is handed to one of them
(``XREADGROUP``), stays *pending* under that worker until it is done (``XACK``), and a
worker that dies mid-job leaves it pending: another worker claims it (``XAUTOCLAIM``)
once it has been idle ``claim_idle_s``. A worker alive on a long job keeps it from
looking idle by re-claiming it to itself (``XCLAIM ... JUSTID``, which counts no
delivery) every ``claim_idle_s / 4``. A job delivered ``max_deliveries`` times (a copy
that kills every worker that takes it) is dropped, logged and counted.

Why a Redis stream and not a Zenoh queryable: a query lives as long as the querier
waits and the queryable answers, so with a queryable the mapper would hold a query open
for the whole optimization (seconds to minutes), find a worker's death only by timeout
and resend -- the mapper would be the scheduler, and a mapper restart would forget the
job. A stream keeps the job in the state every service already shares: who holds it,
how often it was delivered and for how long it has not been touched are Redis's own
bookkeeping, the hand-out to exactly one consumer is atomic, and jobs outlive both
sides. The cost is that a map copy (megabytes) passes through Redis once; an entry is
deleted when it is acknowledged.

A copy larger than ``DATA_SLICE_BYTES`` does not go into the stream entry: it is
pushed to a list of its own a slice at a time and read back the same way, the entry
naming the list. Redis serves one command at a time, and a 24-agent map's copy (tens of
MB) in one XADD kept it from every other client for about half a second: the map
actors' stores waited behind it with their map's lock held (494-855 ms holds, the
actor waiting for Redis's answer while the mapper sent the copy).

A job can still *run* twice: a worker that published its correction and was killed
before acknowledging, or one paused past ``claim_idle_s`` that resumes. So the result
carries the job id and the mapper applies a job's correction once
(:meth:`JobQueue.mark_applied`, ``SET NX``).

Keys: ``hm:opt:*`` (the stream, the newest job per map, restarts, per-consumer counts,
the applied marks), laid out in ``shared/store.py``.
"""

from __future__ import annotations

import logging
import os
import socket
import time
import uuid
from dataclasses import dataclass

import redis

from shared import store

log = logging.getLogger(__name__)

K_JOBS, K_LATEST, K_RESTARTS = store.K_OPT_JOBS, store.K_OPT_LATEST, store.K_OPT_RESTARTS
K_TAKEN, K_WORKERS = store.K_OPT_TAKEN, store.K_OPT_WORKERS
GROUP = "optimizers"
APPLIED_TTL_S = 86400
# Copies larger than this are written and read in slices of this size (see above), and
# kept at most DATA_TTL_S should their job never be done (the stream entry deleted
# unread, a worker gone): a job that old has long been superseded.
DATA_SLICE_BYTES = 4 << 20
DATA_TTL_S = 900


_KEEP = """
local p = redis.call('XPENDING', KEYS[1], ARGV[1], ARGV[3], ARGV[3], 1)
if #p == 0 or p[1][2] ~= ARGV[2] then return 0 end
redis.call('XCLAIM', KEYS[1], ARGV[1], ARGV[2], 0, ARGV[3], 'JUSTID')
return 1
"""


def stream_id(job: str) -> tuple[int, int]:
    """``"ms-seq"`` -> (ms, seq), the order Redis gives its stream ids."""
    ms, _, seq = job.partition("-")
    return int(ms), int(seq or 0)


def consumer_name() -> str:
    """Unique per process and recognizable in ``XINFO CONSUMERS`` (host and pid)."""
    return f"{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:6]}"


def _s(v) -> str:
    return v.decode() if isinstance(v, bytes) else str(v)


@dataclass
class Job:
    id: str
    map_id: str
    data: bytes
    deliveries: int  # 1 for a fresh job, more for one claimed from a dead worker
    claimed: bool
    data_key: str | None = None  # where a large copy was (deleted with the job)


class JobQueue:
    def __init__(
        self,
        r: redis.Redis,
        consumer: str | None = None,
        claim_idle_s: float = 30.0,
        max_deliveries: int = 3,
    ) -> None:
        self.r = r
        self.consumer = consumer or consumer_name()
        self.claim_idle_ms = max(int(claim_idle_s * 1000), 1)
        self.max_deliveries = max_deliveries
        self.dropped = 0
        self.data_slice = DATA_SLICE_BYTES
        self._keep = r.register_script(_KEEP)

    # --- mapper side -------------------------------------------------------------------
    def submit(self, map_id: str, data: bytes | bytearray, pause=None) -> str:
        """Adds a job; returns its id. It becomes the map's newest job, so a worker
        holding an older copy of the map may abandon it. A copy over
        ``DATA_SLICE_BYTES`` is written a slice at a time, ``pause`` called between
        slices (see the module's docstring)."""
        if len(data) <= self.data_slice:
            fields = {"map": map_id, "data": data}
        else:
            key = store.k_opt_data(uuid.uuid4().hex)
            view = memoryview(data)
            for i in range(0, len(view), self.data_slice):
                if i and pause is not None:
                    pause()
                p = self.r.pipeline(transaction=False)
                p.rpush(key, view[i : i + self.data_slice])
                p.expire(key, DATA_TTL_S)
                p.execute()
            fields = {"map": map_id, "data_key": key, "data_len": len(data)}
        job = _s(self.r.xadd(K_JOBS, fields))
        # Two mappers never submit for one map (one owner), so this is not a race:
        # it only has to follow the XADD.
        self.r.hset(K_LATEST, map_id, job)
        return job

    def mark_applied(self, job: str) -> bool:
        """True the first time ``job``'s correction is applied, False after."""
        return bool(self.r.set(store.k_opt_applied(job), b"1", nx=True, ex=APPLIED_TTL_S))

    # --- worker side -------------------------------------------------------------------
    def ensure_group(self) -> None:
        try:
            self.r.xgroup_create(K_JOBS, GROUP, id="0", mkstream=True)
        except redis.ResponseError as e:
            if "BUSYGROUP" not in str(e):
                raise

    def take(self, block_s: float = 1.0) -> Job | None:
        """A job this worker now holds: first one a dead worker left, else a new one
        (waiting up to ``block_s``); None when there is none."""
        job = self._claim_abandoned()
        if job is not None:
            return job
        got = self.r.xreadgroup(
            GROUP, self.consumer, {K_JOBS: ">"}, count=1, block=max(int(block_s * 1000), 1)
        )
        for _stream, entries in got or []:
            for eid, fields in entries:
                return self._job(eid, fields, deliveries=1, claimed=False)
        return None

    def _claim_abandoned(self) -> Job | None:
        while True:
            res = self.r.xautoclaim(
                K_JOBS, GROUP, self.consumer, min_idle_time=self.claim_idle_ms, count=1
            )
            entries = res[1] if len(res) > 1 else []
            # Entries deleted while pending come back as None (nothing to run).
            live = [(eid, f) for eid, f in entries if f]
            for eid, _ in [(eid, f) for eid, f in entries if not f]:
                self.r.xack(K_JOBS, GROUP, eid)
            if not live:
                return None
            eid, fields = live[0]
            info = self.r.xpending_range(K_JOBS, GROUP, min=eid, max=eid, count=1)
            n = int(info[0]["times_delivered"]) if info else 1
            job = self._job(eid, fields, deliveries=n, claimed=True)
            if n <= self.max_deliveries:
                log.warning("claimed job %s (map %s) from a worker that stopped; "
                            "delivery %d", job.id, job.map_id, n)  # fmt: skip
                return job
            log.error("job %s (map %s) dropped after %d deliveries", job.id, job.map_id, n)
            self.dropped += 1
            self.done(job)

    def _job(self, eid, fields: dict, deliveries: int, claimed: bool) -> Job:
        f = {_s(k): v for k, v in fields.items()}
        key = _s(f["data_key"]) if "data_key" in f else None
        data = bytes(f.get("data", b"")) if key is None else self._read(key)
        if key is not None and len(data) != int(f.get("data_len", -1)):
            data = b""  # gone (expired) or cut short: rejected as undecodable
        job = Job(id=_s(eid), map_id=_s(f.get("map", b"")), data=data,
                  deliveries=deliveries, claimed=claimed, data_key=key)  # fmt: skip
        self.r.hincrby(K_TAKEN, self.consumer, 1)
        return job

    def _read(self, key: str) -> bytes:
        """A copy written in slices, read a slice at a time (empty when it is gone:
        the job then fails to decode and is rejected)."""
        n = self.r.llen(key)
        return b"".join(self.r.lindex(key, i) or b"" for i in range(n))

    def keep(self, job: Job) -> bool:
        """Marks ``job`` as alive under this worker; False when it is no longer pending
        here (another worker claimed it, or it was acknowledged)."""
        # Only while this worker still holds it: a plain XCLAIM would take the job back
        # from a worker that claimed it while this one was paused.
        return bool(self._keep(keys=[K_JOBS], args=[GROUP, self.consumer, job.id]))

    def newer(self, job: Job) -> bool:
        """A newer job for the same map was submitted."""
        latest = self.r.hget(K_LATEST, job.map_id)
        return latest is not None and stream_id(_s(latest)) > stream_id(job.id)

    def restarts(self, map_id: str) -> int:
        return int(self.r.hget(K_RESTARTS, map_id) or 0)

    def restarted(self, map_id: str) -> None:
        self.r.hincrby(K_RESTARTS, map_id, 1)

    def done(self, job: Job, finished: bool = False) -> bool:
        """Acknowledges and deletes ``job``; ``finished``: it ran to the end, so its
        map's count of abandoned runs starts again. False when it was no longer pending
        (another worker claimed it while this one was paused, and finished it)."""
        p = self.r.pipeline(transaction=True)
        p.xack(K_JOBS, GROUP, job.id)
        p.xdel(K_JOBS, job.id)
        if job.data_key is not None:
            p.delete(job.data_key)
        if finished:
            p.hdel(K_RESTARTS, job.map_id)
        return bool(p.execute()[0])

    def alive(self) -> None:
        self.r.hset(K_WORKERS, self.consumer, int(time.time() * 1000))

    def workers(self, within_s: float) -> list[str]:
        """Consumers that said they were alive within ``within_s``."""
        now = time.time() * 1000
        return [_s(k) for k, v in self.r.hgetall(K_WORKERS).items()
                if now - int(v) <= within_s * 1000]  # fmt: skip

    def taken(self) -> dict[str, int]:
        """Jobs taken per consumer (every worker that ever took one)."""
        return {_s(k): int(v) for k, v in self.r.hgetall(K_TAKEN).items()}

    def pending(self) -> list[tuple[str, str]]:
        """(job id, consumer) of every job taken and not yet done."""
        rows = self.r.xpending_range(K_JOBS, GROUP, min="-", max="+", count=1000)
        return [(_s(x["message_id"]), _s(x["consumer"])) for x in rows]
