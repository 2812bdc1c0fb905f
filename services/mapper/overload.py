"""Graceful overload: what the mapper gives up, in which order, when offered more than
it can process.

The signal is how long keyframe batches waited in the map actors' queues before
registration (received -> taken up), the part of a keyframe's latency that grows
without bound once the mapper falls behind. Its recent maximum (decaying over
``decay_s``) sets a level, and each level sheds one more kind of work, cheapest loss
first:

1. ``poses``      live poses are stored at most once a second per agent (they are
                  display only, and at 10 Hz x agents each is a Redis round trip);
2. ``feedback``   map chunks to agents at a quarter of their rate;
3. ``background`` keyframe events for place recognition and map copies for the
                  optimizer wait (merges and loop closures come later, nothing is lost:
                  events queue up and an overdue optimization request still goes out
                  once the level drops);
4. ``keyframes``  once a map actor's batches have waited past the ``background``
                  threshold for ``sustain_s`` (overload, not one long lock hold), a
                  batch of that actor that waited longer than ``shed_after_s`` is not
                  registered: the mapper answers it with a NACK (an ``Ack`` of that
                  batch with ``retry_after_s``), and the agent sends it again after that
                  long, oldest first, with nothing new before it. So the latency of
                  every keyframe the mapper accepts stays bounded, the backlog waits in
                  the agents' buffers (CCM-SLAM §4.5), and nothing acknowledged is lost.

Whether waits are sustained is judged per queue (one per map actor): with many agents
most maps are small and their batches wait a few milliseconds, while the one map most
agents merged into queues for seconds; one clock over all queues was reset by any quick
batch of a small map, so the big map's batches were hardly ever shed (48 agents at
84fb110, bench_ramp --overload: 28 batches shed, accepted p95 3.9 s). And a queue in
overload stays there until its waits stayed low for ``calm_s``: shedding drains the
queue, and a clock reset by the first quick batch after that let the next
``sustain_s`` of batches through unshed however long they had waited. Each entry into
overload lets ``sustain_s`` of batches through whatever their wait (~30 keyframes a
second at 48 agents), so it is 1 s, not 2: a merge's hold of a map's lock takes
0.2-1 s.

Shedding a keyframe batch opens a hole in that agent's stream: its later batches are
shed too (and NACKed, so the agent sends the whole run again together) until the hole's
keyframe comes back, so the map never registers an agent's keyframes out of order
because of shedding. The NACK is what makes this cheap: without it the agent learned
of a shed batch only from its backed-off resend timeout (seconds, doubling), while the
hole held back everything it sent meanwhile; at 48 agents (per-queue clock, no NACK,
e033846) 431 keyframes were not stored 60 s after the flights. A hole the agent cannot
fill (its buffer dropped the keyframe) closes after ``hole_max_s``, and the
registration's orphan rule takes over.

The retry-after is the queue's recent wait beyond the shedding threshold (at least
``retry_min_s``, at most ``retry_max_s``): about how long the backlog over the budget
takes to drain, so agents come back when the queue has room for them.

Pure bookkeeping: the service reports waits and asks; this class never sleeps or sends.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

LEVELS = ("normal", "poses", "feedback", "background", "keyframes")
POSES, FEEDBACK, BACKGROUND, KEYFRAMES = 1, 2, 3, 4
# A map actor registering batches more than this share of its time is busy: its
# feedback runs at a quarter rate and a loop's point fusion takes smaller slices.
BUSY_LOAD = 0.5


@dataclass
class _Hole:
    kf_id: int
    since: float


class Overload:
    def __init__(
        self,
        thresholds_s: tuple[float, float, float] = (0.1, 0.25, 0.4),
        shed_after_s: float = 0.5,
        decay_s: float = 2.0,
        hole_max_s: float = 10.0,
        sustain_s: float = 1.0,
        calm_s: float = 2.0,
        retry_min_s: float = 1.0,
        retry_max_s: float = 5.0,
    ) -> None:
        if not (0 < thresholds_s[0] <= thresholds_s[1] <= thresholds_s[2] <= shed_after_s):
            raise ValueError("overload thresholds must rise up to shed_after_s")
        if not 0 < retry_min_s <= retry_max_s:
            raise ValueError("retry_min_s must be positive and at most retry_max_s")
        self.thresholds_s = thresholds_s
        self.shed_after_s = shed_after_s
        self.decay_s = decay_s
        self.hole_max_s = hole_max_s
        self.sustain_s = sustain_s
        self.calm_s = calm_s
        self.retry_min_s = retry_min_s
        self.retry_max_s = retry_max_s
        # Per queue (map actor): since when its waits stay above the background threshold,
        # and, once that is sustained, since when they stay below the feedback one.
        self._over_since: dict[str, float] = {}
        self._calm_since: dict[str, float] = {}
        self._wait = 0.0
        self._t = 0.0
        self._qwait: dict[str, tuple[float, float]] = {}  # queue -> (wait, when)
        self.holes: dict[str, _Hole] = {}
        self._lock = threading.Lock()  # map actors report from their own threads

    @classmethod
    def from_shed_after(cls, shed_after_s: float) -> Overload:
        """Levels at fixed fractions of the keyframe shedding threshold."""
        f = (0.15, 0.4, 0.7)
        return cls(tuple(x * shed_after_s for x in f), shed_after_s)  # type: ignore[arg-type]

    def observe(self, waited_s: float, now: float, queue: str = "") -> None:
        """A batch taken up from ``queue`` after waiting ``waited_s`` in it."""
        with self._lock:
            self._wait = max(waited_s, self.wait(now))
            self._t = now
            self._qwait[queue] = (max(waited_s, self._queue_wait(queue, now)), now)
            since = self._over_since.get(queue)
            if waited_s > self.thresholds_s[2]:
                if since is None:
                    self._over_since[queue] = now
                self._calm_since.pop(queue, None)
            elif waited_s < self.thresholds_s[1] and since is not None:
                if not self._sustained(queue, now):
                    del self._over_since[queue]  # one long hold, not overload
                elif now - self._calm_since.setdefault(queue, now) >= self.calm_s:
                    del self._over_since[queue]
                    del self._calm_since[queue]

    def _sustained(self, queue: str, now: float) -> bool:
        since = self._over_since.get(queue)
        return since is not None and now - since >= self.sustain_s

    def shedding(self, queue: str, now: float) -> bool:
        """Whether ``queue``'s batches that waited past ``shed_after_s`` are shed now."""
        with self._lock:
            return self._sustained(queue, now)

    def _queue_wait(self, queue: str, now: float) -> float:
        w, t = self._qwait.get(queue, (0.0, now))
        return w * math.exp(-max(now - t, 0.0) / self.decay_s)

    def wait(self, now: float) -> float:
        """Recent queue wait: the largest seen, decaying with ``decay_s``."""
        return self._wait * math.exp(-max(now - self._t, 0.0) / self.decay_s)

    def retry_after(self, now: float, queue: str = "") -> float:
        """How long an agent whose batch ``queue`` shed waits before sending again."""
        with self._lock:
            w = self._queue_wait(queue, now) - self.shed_after_s
        return min(max(w, self.retry_min_s), self.retry_max_s)

    def level(self, now: float) -> int:
        with self._lock:
            # A hole whose agent went quiet must not hold the level up for ever.
            for a in [a for a, h in self.holes.items() if now - h.since >= self.hole_max_s]:
                del self.holes[a]
            if self.holes:
                return KEYFRAMES
        w = self.wait(now)
        return sum(w > t for t in self.thresholds_s)

    def admit(self, agent: str, kf_ids: list[int], waited_s: float, now: float,
              queue: str = "") -> bool:  # fmt: skip
        """Whether to register a batch carrying new keyframes ``kf_ids``, taken up from
        ``queue`` (batches with none -- updates of keyframes already stored -- are
        always cheap and admitted)."""
        if not kf_ids:
            return True
        with self._lock:
            return self._admit(agent, min(kf_ids), waited_s, now, queue)

    def _admit(self, agent: str, lo: int, waited_s: float, now: float, queue: str) -> bool:
        hole = self.holes.get(agent)
        if hole is not None:
            if lo > hole.kf_id and now - hole.since < self.hole_max_s:
                return False  # waits behind the hole
            del self.holes[agent]
        if waited_s > self.shed_after_s and self._sustained(queue, now):
            h = self.holes.get(agent)
            self.holes[agent] = _Hole(min(lo, h.kf_id) if h else lo, now)
            return False
        return True
