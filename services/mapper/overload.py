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
4. ``keyframes``  once batches have waited past the ``background`` threshold for
                  ``sustain_s`` (overload, not one long lock hold), a batch that
                  waited longer than ``shed_after_s`` is not registered
                  and not acknowledged: the agent keeps it and resends it after its
                  backed-off timeout. So the latency of every keyframe the mapper
                  accepts stays bounded, and nothing acknowledged is lost.

Shedding a keyframe batch opens a hole in that agent's stream: its later batches are
shed too until the hole's keyframe comes back (agents resend oldest first), so the map
never registers an agent's keyframes out of order because of shedding. A hole the agent
cannot fill (its buffer dropped the keyframe) closes after ``hole_max_s``, and the
registration's orphan rule takes over.

Pure bookkeeping: the service reports waits and asks; this class never sleeps or sends.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

LEVELS = ("normal", "poses", "feedback", "background", "keyframes")
POSES, FEEDBACK, BACKGROUND, KEYFRAMES = 1, 2, 3, 4


@dataclass
class _Hole:
    kf_id: int
    since: float


class Overload:
    def __init__(
        self,
        thresholds_s: tuple[float, float, float] = (0.1, 0.25, 0.4),
        shed_after_s: float = 0.6,
        decay_s: float = 2.0,
        hole_max_s: float = 10.0,
        sustain_s: float = 2.0,
    ) -> None:
        if not (0 < thresholds_s[0] <= thresholds_s[1] <= thresholds_s[2] <= shed_after_s):
            raise ValueError("overload thresholds must rise up to shed_after_s")
        self.thresholds_s = thresholds_s
        self.shed_after_s = shed_after_s
        self.decay_s = decay_s
        self.hole_max_s = hole_max_s
        self.sustain_s = sustain_s
        self._over_since: float | None = None  # waits above the background threshold
        self._wait = 0.0
        self._t = 0.0
        self.holes: dict[str, _Hole] = {}
        self._lock = threading.Lock()  # map actors report from their own threads

    @classmethod
    def from_shed_after(cls, shed_after_s: float) -> Overload:
        """Levels at fixed fractions of the keyframe shedding threshold."""
        f = (0.15, 0.4, 0.7)
        return cls(tuple(x * shed_after_s for x in f), shed_after_s)  # type: ignore[arg-type]

    def observe(self, waited_s: float, now: float) -> None:
        """A batch taken up after waiting ``waited_s`` in the queue."""
        with self._lock:
            self._wait = max(waited_s, self.wait(now))
            self._t = now
            if waited_s > self.thresholds_s[2]:
                if self._over_since is None:
                    self._over_since = now
            elif waited_s < self.thresholds_s[1]:
                self._over_since = None

    def wait(self, now: float) -> float:
        """Recent queue wait: the largest seen, decaying with ``decay_s``."""
        return self._wait * math.exp(-max(now - self._t, 0.0) / self.decay_s)

    def level(self, now: float) -> int:
        with self._lock:
            # A hole whose agent went quiet must not hold the level up for ever.
            for a in [a for a, h in self.holes.items() if now - h.since >= self.hole_max_s]:
                del self.holes[a]
            if self.holes:
                return KEYFRAMES
        w = self.wait(now)
        return sum(w > t for t in self.thresholds_s)

    def admit(self, agent: str, kf_ids: list[int], waited_s: float, now: float) -> bool:
        """Whether to register a batch carrying new keyframes ``kf_ids`` (batches with
        none -- updates of keyframes already stored -- are always cheap and admitted)."""
        if not kf_ids:
            return True
        with self._lock:
            return self._admit(agent, min(kf_ids), waited_s, now)

    def _admit(self, agent: str, lo: int, waited_s: float, now: float) -> bool:
        hole = self.holes.get(agent)
        if hole is not None:
            if lo > hole.kf_id and now - hole.since < self.hole_max_s:
                return False  # waits behind the hole
            del self.holes[agent]
        sustained = self._over_since is not None and now - self._over_since >= self.sustain_s
        if waited_s > self.shed_after_s and sustained:
            h = self.holes.get(agent)
            self.holes[agent] = _Hole(min(lo, h.kf_id) if h else lo, now)
            return False
        return True
