"""What an agent reports about itself in each pose message (agents are never scraped:
the mapper exports what they report, see ``shared.messages.PoseUpdate``)."""

from __future__ import annotations

from collections import deque

import numpy as np

from .comm import CommModule

# Frames per second over this many seconds; ack latency over this many recent acks.
FPS_WINDOW_S = 2.0
ACK_WINDOW = 50


class HealthMeter:
    """Frame rate and frames dropped, plus the comm module's traffic and ack counts."""

    def __init__(self, frame_period_s: float | None = None) -> None:
        self.frame_period_s = frame_period_s
        self.frames: deque[float] = deque()
        self.frames_dropped = 0
        self.pose_bytes = 0
        # The ack-latency percentiles of the last ``fields`` call, by how many latencies
        # there were: poses go out at 10 Hz, acks come at the keyframe rate.
        self._ack_pct: tuple[int, float, float] | None = None

    def frame(self, now: float, due: float | None = None, period: float | None = None) -> None:
        """One frame tracked at ``now``; ``due`` is when the camera took it (monotonic
        clock). More than a frame period late, a live camera with a one-frame buffer
        would have replaced it: it counts as dropped."""
        self.frames.append(now)
        while self.frames and self.frames[0] < now - FPS_WINDOW_S:
            self.frames.popleft()
        period = period or self.frame_period_s
        if due is not None and period and now - due > period:
            self.frames_dropped += 1

    def fps(self) -> float:
        if len(self.frames) < 2:
            return 0.0
        span = self.frames[-1] - self.frames[0]
        return (len(self.frames) - 1) / span if span > 0 else 0.0

    def fields(self, comm: CommModule) -> dict:
        """The health fields of a PoseUpdate."""
        s = comm.stats
        lat = s.ack_latencies[-ACK_WINDOW:]
        out = {
            "fps": round(self.fps(), 2),
            "frames_dropped": self.frames_dropped,
            "kf_lost": s.kf_dropped_unacked,
            "bytes_sent": s.bytes + self.pose_bytes,
            "resent": sum(comm.resent_reasons.values()),
        }
        if lat:
            n = len(s.ack_latencies)
            if self._ack_pct is None or self._ack_pct[0] != n:
                p50, p95 = np.percentile(lat, [50, 95])
                self._ack_pct = (n, round(float(p50), 5), round(float(p95), 5))
            out["ack_p50_s"], out["ack_p95_s"] = self._ack_pct[1], self._ack_pct[2]
        return out
