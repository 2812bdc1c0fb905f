"""The optimizer service: map copies in, corrections out (CCM-SLAM §4.9); a pool.

The contract is the two wire messages of ``shared/messages.py``: the algorithms
(``pose_graph``, ``global_ba``) take the mapper's ``OptimizeRequest`` as it is and
return the ``CorrectionMsg`` this service publishes; nothing here knows the mapper's
map objects (the mapper builds the request in ``services/mapper/capture.py``).

The mapper adds a copy of a map to the Redis job stream after a merge or a loop
(``shared/jobs.py``: why a stream and not a Zenoh queryable, and the keys). Any number
of optimizer processes read the stream as one consumer group, so each job runs on one
of them; one that dies mid-job (``kill -9``) leaves the job pending and another claims
it after ``claim_idle_s``, at most ``max_deliveries`` times. A worker runs the Sim(3)
pose graph over the essential graph plus loop edges, then global BA, and publishes the
result on ``hivemap/map/{map}/correction`` carrying the job id, which the mapper applies
once (a job may run twice: a worker killed between publishing and acknowledging).

The newest copy of a map wins: a job whose map has a newer job waiting is dropped
untaken, and a run whose map gets one is abandoned at the next stage boundary (after
PGO, after BA) -- at most ``max_restarts`` times in a row per map (counted in Redis,
whichever worker ran them), so that frequent loops (agents re-visiting each other's
places) still get corrections out.
"""

from __future__ import annotations

import logging
import threading
import time

import redis

from shared import keys
from shared.jobs import K_JOBS, Job, JobQueue
from shared.messages import CorrectionMsg, DecodeError, OptimizeRequest
from shared.metrics import PROCESSING, REJECTED, UP
from shared.settings import Settings
from shared.store import connect
from shared.transport import Bus, open_session

from .global_ba import GlobalParams, optimize_map
from .metrics import JOBS, OPTIMIZATIONS, SUPERSEDED
from .pose_graph import loops_pull

log = logging.getLogger(__name__)
SERVICE = "optimizer"


class Superseded(Exception):
    """A newer copy of the map arrived; this run's result would be stale."""


class OptimizerService:
    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        o = settings.optimizer
        self.queue = JobQueue(connect(settings.redis_url), claim_idle_s=o.claim_idle_s,
                              max_deliveries=o.max_deliveries)  # fmt: skip
        self._stop = threading.Event()
        self.session = None
        self.bus: Bus | None = None
        self._thread = threading.Thread(target=self._run, name="optimizer", daemon=True)
        self._keeper = threading.Thread(target=self._keep, name="optimizer-keep", daemon=True)
        self._current: Job | None = None
        self.done: list[CorrectionMsg] = []  # results, newest last (tests read them)

    # --- transport-free core -------------------------------------------------------------
    def decode(self, job: Job) -> OptimizeRequest | None:
        try:
            req = OptimizeRequest.decode(job.data)
            if job.map_id != req.map_id:
                raise DecodeError(f"map {req.map_id!r} in a job of {job.map_id!r}")
            errs = req.check()
            if errs:
                raise DecodeError("inconsistent map copy: " + "; ".join(errs[:3]))
        except (DecodeError, ValueError) as e:
            REJECTED.labels(SERVICE, K_JOBS, "invalid").inc()
            log.warning("rejected optimization job %s: %s", job.id, e)
            return None
        return req

    def _newer(self, job: Job | None) -> bool:
        if job is None:
            return False
        if self.queue.restarts(job.map_id) >= self.settings.optimizer.max_restarts:
            return False  # finish this one; the newest copy is next
        return self.queue.newer(job)

    def optimize(self, req: OptimizeRequest, job: Job | None = None) -> CorrectionMsg:
        """PGO then BA on one map copy; raises Superseded at a stage boundary when a
        newer job for the same map is waiting."""
        o = self.settings.optimizer
        t0 = time.perf_counter()
        started_ns = time.time_ns()

        def between_stages() -> None:
            if self._newer(job):
                raise Superseded

        # No loop edge that pulls (none, or all distributed by an earlier run): nothing
        # for the pose graph to distribute.
        params = GlobalParams.from_settings(o, run_pgo=loops_pull(req))
        if req.reason == "local":
            # A windowed BA (the mapper's capture_window): its own, shorter budget.
            params.ba.time_budget_s = o.local_ba_time_budget_s
        corr = optimize_map(req, params, between_stages)
        corr.stats["seconds"] = time.perf_counter() - t0
        corr.stats["reason"] = req.reason
        corr.stats["started_ns"] = started_ns
        corr.stats["worker"] = self.queue.consumer
        if job is not None:
            corr.job = job.id
        return corr

    def handle(self, job: Job) -> CorrectionMsg | None:
        """Runs one job taken from the queue and acknowledges it; the correction, or
        None when the job was invalid, stale or failed."""
        JOBS.labels("claimed" if job.claimed else "taken").inc()
        req = self.decode(job)
        if req is None:
            JOBS.labels("invalid").inc()
            self.queue.done(job)
            return None
        if self.queue.newer(job):
            # A newer copy of this map is queued: it runs instead (no restart counted,
            # as a copy replaced before it ran cost nothing).
            SUPERSEDED.inc()
            JOBS.labels("superseded").inc()
            self.queue.done(job)
            return None
        self._current = job
        t0 = time.perf_counter()
        try:
            corr = self.optimize(req, job)
        except Superseded:
            self.queue.restarted(job.map_id)
            SUPERSEDED.inc()
            JOBS.labels("superseded").inc()
            log.info("optimization of %s restarted: a newer copy arrived", job.map_id)
            self.queue.done(job)
            return None
        except Exception:
            REJECTED.labels(SERVICE, K_JOBS, "internal").inc()
            JOBS.labels("failed").inc()
            log.exception("optimization of %s failed", job.map_id)
            self.queue.done(job)
            return None
        finally:
            self._current = None
        PROCESSING.labels(SERVICE, "optimize").observe(time.perf_counter() - t0)
        OPTIMIZATIONS.labels(req.reason).inc()
        self.done.append(corr)
        if self.bus is not None:
            corr.sent_ns = time.time_ns()
            self.bus.put(keys.map_correction(job.map_id), corr.encode())
        # Acknowledged after publishing: a worker killed in between leaves the job to
        # another, and the mapper applies the second correction of the job as a no-op.
        if not self.queue.done(job, finished=True):
            log.warning("job %s had been taken over by another worker meanwhile", job.id)
        JOBS.labels("done").inc()
        log.info("optimized %s (job %s): %d keyframes, %d points in %.2f s", job.map_id,
                 job.id, len(corr.kf_gids), len(corr.mp_gids), corr.stats["seconds"])  # fmt: skip
        return corr

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                job = self.queue.take(block_s=0.5)
                if job is not None:
                    self.handle(job)
            except redis.RedisError as e:
                log.warning("job queue unreachable (%s); retrying", e)
                self._stop.wait(1.0)

    def _keep(self) -> None:
        """Keeps the job in hand from looking abandoned while it runs."""
        period = self.settings.optimizer.claim_idle_s / 4
        while not self._stop.wait(period):
            job = self._current
            try:
                self.queue.alive()
                if job is not None and not self.queue.keep(job):
                    log.warning("job %s was claimed by another worker meanwhile", job.id)
            except redis.RedisError as e:
                log.warning("could not renew job %s: %s", job and job.id, e)

    # --- service loop --------------------------------------------------------------------
    def start(self) -> None:
        self.session = open_session(self.settings.zenoh)
        self.bus = Bus(self.session, SERVICE, self.settings.inject)
        self.queue.ensure_group()
        self.queue.alive()
        self._thread.start()
        self._keeper.start()
        # The histogram exists before the first run: rate() over it then counts that run.
        PROCESSING.labels(SERVICE, "optimize")
        UP.labels(SERVICE).set(1)
        log.info("optimizer %s taking jobs", self.queue.consumer)

    def stop(self) -> None:
        self._stop.set()
        for t in (self._thread, self._keeper):
            if t.is_alive():
                t.join(timeout=30)
        UP.labels(SERVICE).set(0)
        if self.bus:
            self.bus.close()
        if self.session is not None:
            self.session.close()
            self.session = None
        self.queue.r.close()
