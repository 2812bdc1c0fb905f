"""Zenoh sessions and the publish/subscribe helpers every service uses.

Callbacks only enqueue (zenoh invokes them on its own threads); a service's worker
drains the queue. Keyframe, ack and correction traffic is published reliably with
blocking congestion control; live poses use DROP so a slow reader never stalls an
agent. Every sample sent or received is counted in bytes and messages per key
expression. The loss/delay injector (CCM-SLAM §5.3 communication controller) sits
on the sending side, configured by ``Settings.inject``.
"""

from __future__ import annotations

import contextlib
import heapq
import json
import logging
import queue
import random
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import zenoh

from shared.metrics import BYTES, INJECTED_DELAY, INJECTED_DROPS, MESSAGES, REJECTED
from shared.settings import InjectSettings, ZenohSettings

log = logging.getLogger(__name__)


def zenoh_config(zs: ZenohSettings) -> zenoh.Config:
    conf = zenoh.Config.from_file(zs.config_file) if zs.config_file else zenoh.Config()
    user, password = zs.user, zs.password.get_secret_value()
    if zs.credentials and not user:
        doc = json.loads(Path(zs.credentials).read_text())
        user, password = str(doc["user"]), str(doc["password"])
    if user:
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    if zs.mode == "router" and zs.auth_dir:
        from shared.zenoh_auth import router_config

        rc = router_config(zs.auth_dir)
        conf.insert_json5("transport/auth/usrpwd", json.dumps(rc["transport"]["auth"]["usrpwd"]))
        conf.insert_json5("access_control", json.dumps(rc["access_control"]))
    conf.insert_json5("mode", json.dumps(zs.mode))
    if zs.connect:
        conf.insert_json5("connect/endpoints", json.dumps(zs.connect))
    if zs.mode != "router":
        conf.insert_json5("connect/timeout_ms", json.dumps(zs.connect_timeout_ms))
    conf.insert_json5("listen/endpoints", json.dumps(zs.listen))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(zs.scouting))
    conf.insert_json5("scouting/gossip/enabled", json.dumps(zs.scouting))
    return conf


def open_session(zs: ZenohSettings) -> zenoh.Session:
    return zenoh.open(zenoh_config(zs))


def router_count(session: zenoh.Session | None) -> int:
    """Routers a client session reaches now: 0 before it opened and while its router is
    gone (the session stays open and reconnects by itself when the router is back)."""
    if session is None:
        return 0
    try:
        return len(list(session.info.routers_zid()))
    except Exception:  # a session closed under us (shutdown): no router either
        return 0


@dataclass
class Received:
    key: str
    payload: bytes
    recv_ns: int


class _DelayLine:
    """One thread that sends delayed samples at their due time."""

    def __init__(self) -> None:
        self._heap: list[tuple[float, int, Callable[[], None]]] = []
        self._cv = threading.Condition()
        self._n = 0
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="delay-line", daemon=True)
        self._thread.start()

    def schedule(self, due: float, fn: Callable[[], None]) -> None:
        with self._cv:
            self._n += 1
            heapq.heappush(self._heap, (due, self._n, fn))
            self._cv.notify()

    def close(self, flush: bool = True) -> None:
        with self._cv:
            self._closed = True
            pending = [fn for _, _, fn in sorted(self._heap)] if flush else []
            self._heap.clear()
            self._cv.notify()
        for fn in pending:
            fn()

    def _run(self) -> None:
        while True:
            with self._cv:
                while not self._closed and (not self._heap or self._heap[0][0] > time.monotonic()):
                    timeout = None if not self._heap else self._heap[0][0] - time.monotonic()
                    self._cv.wait(timeout)
                if self._closed:
                    return
                _, _, fn = heapq.heappop(self._heap)
            try:
                fn()
            except Exception:  # a closed session at shutdown must not kill the thread
                log.exception("delayed send failed")


class Injector:
    """Drops and delays outgoing samples with the configured probabilities."""

    def __init__(self, cfg: InjectSettings, service: str) -> None:
        self.cfg = cfg
        self.active = (cfg.drop > 0 or cfg.delay_s > 0 or cfg.jitter_s > 0) and (
            not cfg.service or cfg.service == service
        )
        self._rng = random.Random(f"{cfg.seed}:{service}")
        self._lock = threading.Lock()
        self._line: _DelayLine | None = None

    def applies(self, key: str) -> bool:
        return self.active and key.startswith(self.cfg.key_prefix)

    def decide(self) -> tuple[bool, float]:
        with self._lock:
            drop = self._rng.random() < self.cfg.drop
            delay = self.cfg.delay_s + (self._rng.random() * self.cfg.jitter_s)
        return drop, delay

    def later(self, delay: float, fn: Callable[[], None]) -> None:
        if self._line is None:
            with self._lock:
                if self._line is None:
                    self._line = _DelayLine()
        self._line.schedule(time.monotonic() + delay, fn)

    def close(self) -> None:
        if self._line is not None:
            self._line.close(flush=False)


class Bus:
    """A service's view of Zenoh: counted publishers and queue-backed subscribers."""

    def __init__(
        self, session: zenoh.Session, service: str, inject: InjectSettings | None = None
    ) -> None:
        self.session = session
        self.service = service
        self.injector = Injector(inject or InjectSettings(), service)
        self._pubs: dict[tuple[str, bool], zenoh.Publisher] = {}
        self._subs: list[zenoh.Subscriber] = []
        self._lock = threading.Lock()

    def _publisher(self, key: str, reliable: bool) -> zenoh.Publisher:
        k = (key, reliable)
        pub = self._pubs.get(k)
        if pub is None:
            with self._lock:
                pub = self._pubs.get(k)
                if pub is None:
                    cc = zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP
                    pub = self.session.declare_publisher(key, congestion_control=cc)
                    self._pubs[k] = pub
        return pub

    def put(self, key: str, payload: bytes, reliable: bool = True) -> bool:
        """Publish; returns False when the injector dropped the sample."""
        MESSAGES.labels(self.service, "out", key).inc()
        BYTES.labels(self.service, "out", key).inc(len(payload))
        pub = self._publisher(key, reliable)
        if self.injector.applies(key):
            drop, delay = self.injector.decide()
            if drop:
                INJECTED_DROPS.labels(self.service, key).inc()
                return False
            if delay > 0:
                INJECTED_DELAY.labels(self.service).observe(delay)
                self.injector.later(delay, lambda: pub.put(payload))
                return True
        pub.put(payload)
        return True

    def subscribe(
        self, key_expr: str, q: queue.Queue | None = None, maxsize: int = 0
    ) -> queue.Queue:
        """Every sample on key_expr lands in the returned queue as :class:`Received`.

        maxsize > 0 makes a ring: when full the oldest sample is dropped (for live
        poses); 0 is an unbounded FIFO (for keyframes, which must not be lost).
        """
        out: queue.Queue = q if q is not None else queue.Queue(maxsize=maxsize)
        service = self.service

        def on_sample(sample: zenoh.Sample) -> None:
            payload = sample.payload.to_bytes()
            key = str(sample.key_expr)
            MESSAGES.labels(service, "in", key).inc()
            BYTES.labels(service, "in", key).inc(len(payload))
            item = Received(key, payload, time.time_ns())
            while True:
                try:
                    out.put_nowait(item)
                    return
                except queue.Full:
                    with contextlib.suppress(queue.Empty):
                        out.get_nowait()

        self._subs.append(self.session.declare_subscriber(key_expr, on_sample))
        return out

    def close(self) -> None:
        self.injector.close()
        for s in self._subs:
            with contextlib.suppress(Exception):
                s.undeclare()
        for p in self._pubs.values():
            with contextlib.suppress(Exception):
                p.undeclare()
        self._subs.clear()
        self._pubs.clear()


def get_all(q: queue.Queue) -> list:
    """Everything queued right now, oldest first, without waiting."""
    out = []
    with contextlib.suppress(queue.Empty):
        while True:
            out.append(q.get_nowait())
    return out


def drain(
    q: queue.Queue,
    stop: threading.Event,
    handle: Callable[[Received], object],
    service: str,
    what: str,
    timeout: float = 0.2,
) -> None:
    """A worker thread's loop over a subscription queue (Zenoh callbacks only enqueue):
    ``handle`` each item until ``stop`` is set. An exception is counted as rejected
    ("internal") and logged, and the loop goes on with the next item."""
    while not stop.is_set():
        try:
            item = q.get(timeout=timeout)
        except queue.Empty:
            continue
        try:
            handle(item)
        except Exception:
            REJECTED.labels(service, item.key, "internal").inc()
            log.exception("%s failed", what, extra={"key": item.key})
