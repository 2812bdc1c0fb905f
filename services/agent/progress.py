"""What a flying agent tells its user: a progress line every few seconds, and a warning
while no router answers (or a router answers but nothing acknowledges keyframes).

An agent keeps tracking whatever the network does (CCM-SLAM §4.5): keyframes wait in
its buffer and go out once a server is there. Without these lines a user who started
``hivemap agent`` beside no server -- or the wrong one -- learns it only at the end of
the flight, from a map that does not exist.

The reporter runs on its own thread and reads a :class:`Snapshot` the agent gives it:
a blocked send or a long frame must not hold up the warning about the network.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

log = logging.getLogger(__name__)

PROGRESS_EVERY_S = 5.0
# First warning this long after the start (or the loss) of the router: under the 5 s a
# user waits before wondering, above the ~1 s a client takes to connect to a live router.
NO_ROUTER_WARN_S = 3.0
# A router without a mapper behind it: keyframes go out and nothing comes back.
NO_ACK_WARN_S = 10.0


@dataclass
class Snapshot:
    frames: int
    total: int | None  # frames in the source, None for a live camera
    state: str  # the VO's: init | ok | lost
    keyframes: int  # made by the VO
    kf_sent: int  # distinct keyframes sent at least once
    kf_acked: int
    kf_waiting: int  # made, not acknowledged (buffered or in flight)
    map_id: str | None  # the server map the agent is in, None before the first ack
    routers: int  # routers this agent's session reaches now (0: none, or not open yet)


def format_progress(agent: str, s: Snapshot, fps: float) -> str:
    done = f"{s.frames}/{s.total} ({100 * s.frames / s.total:.0f} %)" if s.total else f"{s.frames}"
    return (f"{agent}: frame {done}, {fps:.1f} fps, tracking {s.state}, keyframes "
            f"{s.keyframes} made / {s.kf_sent} sent / {s.kf_acked} acked, "
            f"server map {s.map_id or '-'}")  # fmt: skip


class ProgressReporter:
    """``check(now)`` decides what to say (a unit test drives it with its own clock);
    ``start`` runs it on a thread that logs."""

    def __init__(
        self,
        agent: str,
        endpoint: str | None,
        snapshot: Callable[[], Snapshot],
        every_s: float = PROGRESS_EVERY_S,
        warn_after_s: float = NO_ROUTER_WARN_S,
        no_ack_warn_s: float = NO_ACK_WARN_S,
    ) -> None:
        self.agent = agent
        self.endpoint = endpoint  # None: flying without a server, nothing to warn about
        self.snapshot = snapshot
        self.every_s = every_s
        self.warn_after_s = warn_after_s
        self.no_ack_warn_s = no_ack_warn_s
        self.warnings = 0
        self._t0: float | None = None
        self._last_progress: float | None = None
        self._last_frames = 0
        self._no_router_since: float | None = None
        self._last_router_warn = -1e18
        self._warned_no_router = False
        self._acked = 0
        self._acked_at: float | None = None
        self._last_ack_warn = -1e18
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def check(self, now: float) -> list[tuple[int, str]]:
        """The (level, message) lines due at ``now``."""
        s = self.snapshot()
        out: list[tuple[int, str]] = []
        if self._t0 is None:
            self._t0 = self._last_progress = self._acked_at = now
            self._no_router_since = now
        if self.endpoint is not None:
            out += self._router_lines(now, s)
        if now - self._last_progress >= self.every_s:
            fps = (s.frames - self._last_frames) / (now - self._last_progress)
            self._last_progress, self._last_frames = now, s.frames
            out.append((logging.INFO, format_progress(self.agent, s, fps)))
        return out

    def _router_lines(self, now: float, s: Snapshot) -> list[tuple[int, str]]:
        out = []
        if s.kf_acked != self._acked:
            self._acked, self._acked_at = s.kf_acked, now
        if s.routers == 0:
            if self._no_router_since is None:
                self._no_router_since = now
            gone = now - self._no_router_since
            if gone >= self.warn_after_s and now - self._last_router_warn >= self.every_s:
                self._last_router_warn = now
                self._warned_no_router = True
                self.warnings += 1
                out.append((logging.WARNING,
                            f"{self.agent}: no router answers at {self.endpoint} for "
                            f"{gone:.0f} s; still tracking, {s.kf_waiting} keyframes wait "
                            "in the buffer (is `hivemap up` running? --server names "
                            "another router)"))  # fmt: skip
            return out
        if self._no_router_since is not None:
            if self._warned_no_router:
                out.append((logging.INFO,
                            f"{self.agent}: router at {self.endpoint} answers; sending "
                            f"{s.kf_waiting} buffered keyframes"))  # fmt: skip
            self._no_router_since = None
            self._warned_no_router = False
            self._acked_at = now  # the server gets its chance from now on
        quiet = now - self._acked_at
        if (
            s.kf_waiting > 0
            and quiet >= self.no_ack_warn_s
            and (now - self._last_ack_warn >= self.every_s)
        ):
            self._last_ack_warn = now
            self.warnings += 1
            out.append((logging.WARNING,
                        f"{self.agent}: the router at {self.endpoint} answers but no "
                        f"keyframe was acknowledged for {quiet:.0f} s ({s.kf_waiting} "
                        "waiting): is a mapper running behind it?"))  # fmt: skip
        return out

    def start(self, tick_s: float = 0.5) -> None:
        def run() -> None:
            while not self._stop.wait(tick_s):
                try:
                    lines = self.check(time.monotonic())
                except Exception:  # a torn read of the agent's state: next tick
                    log.debug("progress snapshot failed", exc_info=True)
                    continue
                for level, msg in lines:
                    log.log(level, msg, extra={"agent": self.agent})

        self._thread = threading.Thread(target=run, name="agent-progress", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
