"""The optimizer service: map copies in, corrections out (CCM-SLAM §4.9).

The mapper sends a copy of a map on ``hivemap/map/{map}/optimize`` after a merge or a
loop; this service runs the Sim(3) pose graph over the essential graph plus loop
edges, then global BA, and publishes the result on ``hivemap/map/{map}/correction``.
Requests only enqueue (Zenoh callback); one worker thread optimizes. The newest
request per map wins: one that arrives while its map is being optimized makes the
worker drop the run at the next stage boundary (after PGO, after BA) and restart from
the new copy, which carries the new constraint -- at most ``max_restarts`` times in a
row, so that frequent loops (agents re-visiting each other's places) still get
corrections out.
"""

from __future__ import annotations

import logging
import threading
import time

from shared import keys
from shared.messages import CorrectionMsg, DecodeError, OptimizeRequest
from shared.metrics import PROCESSING, REJECTED, UP
from shared.settings import Settings
from shared.transport import Bus, drain, open_session

from .global_ba import BAParams, GlobalParams, optimize_map
from .metrics import OPTIMIZATIONS, SUPERSEDED

log = logging.getLogger(__name__)
SERVICE = "optimizer"


class Superseded(Exception):
    """A newer copy of the map arrived; this run's result would be stale."""


class OptimizerService:
    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self._pending: dict[str, OptimizeRequest] = {}
        self._cv = threading.Condition()
        self._stop = threading.Event()
        self.session = None
        self.bus: Bus | None = None
        self._thread = threading.Thread(target=self._run, name="optimizer", daemon=True)
        self.done: list[CorrectionMsg] = []  # results, newest last (tests read them)
        self._restarts: dict[str, int] = {}

    # --- transport-free core -------------------------------------------------------------
    def submit(self, key: str, payload: bytes) -> OptimizeRequest | None:
        try:
            req = OptimizeRequest.decode(payload)
            if keys.map_of(key) not in (None, req.map_id):
                raise DecodeError(f"map {req.map_id!r} sent on the key of {keys.map_of(key)!r}")
            errs = req.check()
            if errs:
                raise DecodeError("inconsistent map copy: " + "; ".join(errs[:3]))
        except (DecodeError, ValueError) as e:
            REJECTED.labels(SERVICE, key, "invalid").inc()
            log.warning("rejected optimization request on %s: %s", key, e)
            return None
        with self._cv:
            if req.map_id in self._pending:
                SUPERSEDED.inc()
            self._pending[req.map_id] = req
            self._cv.notify()
        return req

    def _newer(self, map_id: str) -> bool:
        if self._restarts.get(map_id, 0) >= self.settings.optimizer.max_restarts:
            return False  # finish this one; the newest copy is next
        with self._cv:
            return map_id in self._pending

    def optimize(self, req: OptimizeRequest) -> CorrectionMsg:
        """PGO then BA on one map copy; raises Superseded at a stage boundary when a
        newer copy of the same map is waiting."""
        o = self.settings.optimizer
        t0 = time.perf_counter()

        def between_stages() -> None:
            if self._newer(req.map_id):
                raise Superseded

        params = GlobalParams(
            ba=BAParams(max_iters=o.ba_max_iterations, time_budget_s=o.ba_time_budget_s),
            run_pgo=len(req.loops) > 0,  # nothing to distribute without a loop edge
            run_ba=o.ba and o.ba_max_iterations > 0,
        )
        corr = optimize_map(req, params, between_stages)
        corr.stats["seconds"] = time.perf_counter() - t0
        corr.stats["reason"] = req.reason
        return corr

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._cv:
                while not self._pending and not self._stop.is_set():
                    self._cv.wait(0.5)
                if self._stop.is_set():
                    return
                map_id = next(iter(self._pending))
                req = self._pending.pop(map_id)
            t0 = time.perf_counter()
            try:
                corr = self.optimize(req)
            except Superseded:
                self._restarts[map_id] = self._restarts.get(map_id, 0) + 1
                SUPERSEDED.inc()
                log.info("optimization of %s restarted: a newer copy arrived", map_id)
                continue
            except Exception:
                REJECTED.labels(SERVICE, keys.map_optimize(map_id), "internal").inc()
                log.exception("optimization of %s failed", map_id)
                continue
            self._restarts[map_id] = 0
            PROCESSING.labels(SERVICE, "optimize").observe(time.perf_counter() - t0)
            OPTIMIZATIONS.labels(req.reason).inc()
            self.done.append(corr)
            if self.bus is not None:
                corr.sent_ns = time.time_ns()
                self.bus.put(keys.map_correction(map_id), corr.encode())
            log.info("optimized %s: %d keyframes, %d points in %.2f s", map_id,
                     len(corr.kf_gids), len(corr.mp_gids), corr.stats["seconds"])  # fmt: skip

    # --- service loop --------------------------------------------------------------------
    def start(self) -> None:
        self.session = open_session(self.settings.zenoh)
        self.bus = Bus(self.session, SERVICE, self.settings.inject)
        q = self.bus.subscribe(keys.ALL_MAP_OPTIMIZE)
        self._rx = threading.Thread(
            target=drain, args=(q, self._stop, lambda it: self.submit(it.key, it.payload),
                                SERVICE, "optimization request"),
            name="optimizer-rx", daemon=True,
        )  # fmt: skip
        self._rx.start()
        self._thread.start()
        # The histogram exists before the first run: rate() over it then counts that run.
        PROCESSING.labels(SERVICE, "optimize")
        UP.labels(SERVICE).set(1)
        log.info("optimizer running")

    def stop(self) -> None:
        self._stop.set()
        with self._cv:
            self._cv.notify_all()
        for t in (getattr(self, "_rx", None), self._thread):
            if t is not None and t.is_alive():
                t.join(timeout=30)
        UP.labels(SERVICE).set(0)
        if self.bus:
            self.bus.close()
        if self.session is not None:
            self.session.close()
            self.session = None
