"""The one agent loop: frames in, keyframes and poses out over Zenoh, acks back.

What produces the keyframes is behind :class:`Producer`: the real monocular VO on an
image source (``producer_vo.VOProducer``) or the feature-level simulated agent
(``sim_runner.SimProducer``). Everything else is the loop's and the same for both:

- pacing by the frames' timestamps (``speed``: 1 = real time, 0 = as fast as possible)
  and, for a live camera (``drop_when_behind``), dropping the frames that arrived while
  the previous one was being tracked -- what a camera driver does: the tracker always
  takes the newest frame there is, so a frame is dropped only when a newer one is both
  due and delivered (a camera that delivers late is not a reason to drop the frame it
  has) -- counted in ``dropped_frames`` and ``hivemap_agent_frames_dropped_total``;
- the communication module (CCM-SLAM §4.5) built from ``settings.comm`` (rate, message
  size cap, resend timeout) and live poses at ``comm.pose_rate_hz``;
- acks and the server's map chunks, handled in one place (``_on_message``): a chunk's
  frame correction ``S_g_l``, gated and paid out smoothly (``reported.ReportedPose``),
  maps the producer's VO pose to the reported pose;
- a progress line every few seconds and warnings while no router answers (optional);
- one :class:`AgentStats` (durations in seconds).

The Zenoh session is opened in the background (a client retries until a router is
reachable) unless ``wait_for_server``; until then the producer's data waits in the
communication module, bounded by the producer's own buffer rule (CCM-SLAM §4.2).
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from typing import Any, Protocol

import numpy as np

from shared import feedback_dump, keys
from shared.geometry import Sim3, se3_inv
from shared.messages import Ack, DecodeError, MapChunk, PoseUpdate
from shared.metrics import AGENT_ACK_LATENCY, AGENT_FRAMES_DROPPED, REJECTED, RESENT
from shared.settings import Settings

from .comm import CommModule
from .health import HealthMeter
from .progress import ProgressReporter, Snapshot
from .reported import ReportedPose

log = logging.getLogger(__name__)

# A server map chunk is only useful while its KF_ref is recent: a backlog is dropped
# oldest first instead of being worked through late.
MAP_CHUNK_QUEUE = 4


@dataclass
class Step:
    """What the producer made of one frame."""

    stamp_ns: int
    T_l_c: np.ndarray | None  # the VO's pose in its own frame l; None before init
    state: str = "ok"  # init | ok | lost
    kf_ref: int = -1  # newest keyframe (the reference of the live pose), -1 none
    T_l_ref: np.ndarray | None = None
    T_pred: np.ndarray | None = None  # the motion model's pose for this frame
    # Keyframes this frame made: two on the frame that initializes the VO (its first
    # keyframe is made with the second), else 0 or 1. Counted as a bool, stats said one
    # keyframe fewer than the agent sent and the server acknowledged.
    keyframes: int = 0
    track_s: float = 0.0
    map_s: float = 0.0  # mapping time run inline on this frame (0 when off the path)


@dataclass
class Frame:
    stamp_ns: int
    data: Any = None  # the image (real VO) or nothing (the simulation keeps its own)
    # A live camera that paces and drops frames itself (see runner._Camera): when this
    # frame was due, the frames it dropped since the last one it delivered, and the
    # seconds it spent on the frame for the agent (feature extraction).
    due: float | None = None
    dropped: int = 0
    work_s: float = 0.0


class Producer(Protocol):
    uses_map: bool  # subscribe to the server's map chunks

    def bind(self, comm: CommModule, stats: AgentStats) -> None: ...

    def frames(self) -> Iterable[Frame]:
        """The frames in order. A live camera's iterator may have ``ready()``: whether
        its next frame is delivered already (taken from it without waiting); without
        it, the next frame is always there."""

    def step(self, frame: Frame) -> Step: ...

    def poll(self) -> None:
        """Take in work finished off the tracking path (local mapping)."""

    def finish(self) -> None:
        """The last frame was tracked: complete outstanding work."""

    def on_chunk(self, chunk: MapChunk) -> None: ...

    def close(self) -> None: ...


@dataclass
class AgentStats:
    """One stats type for every agent; every duration in seconds."""

    agent: str
    frames: int = 0  # frames tracked
    dropped_frames: int = 0  # frames a live camera delivered while the agent was busy
    keyframes: int = 0
    map_points: int = 0  # new map points handed to the communication module
    mp_updates: int = 0  # map point positions sent again after a local BA moved them
    lost_frames: int = 0
    longest_lost_s: float = 0.0
    track_s: list[float] = field(default_factory=list)
    map_s: list[float] = field(default_factory=list)  # per keyframe
    latency_s: list[float] = field(default_factory=list)  # frame time -> reported pose
    kf_trimmed: int = 0
    kf_lost_unacked: int = 0  # dropped by the buffer rule before any ack
    foreign_points: int = 0  # server points taken into the local map
    chunks: int = 0  # server map chunks received for a keyframe still held
    corrections: int = 0  # frame corrections taken from the server
    corrections_held: int = 0  # ... and held back by the gate (they contradicted the VO)
    server_maps: list[str] = field(default_factory=list)  # the server maps it was in
    acked_keyframes: int = 0
    messages: int = 0
    bytes: int = 0  # keyframe batches (resends included)
    pose_bytes: int = 0  # live pose messages (``comm.pose_rate_hz``)
    kf_resent: int = 0
    resent: dict = field(default_factory=dict)
    duration_s: float = 0.0
    flight_s: float = 0.0
    # What the flight takes in real time (first to last frame's stamp, over ``speed``;
    # 0 unpaced): flight_s beyond it is how far behind real time the agent fell.
    nominal_flight_s: float = 0.0
    ack_latency_median_s: float = float("nan")
    ack_latency_p95_s: float = float("nan")
    bytes_per_s: float = 0.0
    all_acked: bool = False
    # (seconds since the start of the flight, ack latency) per keyframe.
    ack_series: list = field(default_factory=list)
    # Diagnostics: sends per acked keyframe, and the communication module's trace
    # (``CommStats.trace``, times since the start of the flight).
    ack_attempts: list = field(default_factory=list)
    comm_trace: list = field(default_factory=list)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["resent"] = {f"{k[0]}_{k[1]}": v for k, v in self.resent.items()}
        for name in ("track_s", "map_s", "latency_s"):
            a = np.array(d.pop(name) or [0.0])
            d[f"{name}_median"] = float(np.median(a))
            d[f"{name}_p95"] = float(np.percentile(a, 95))
        return d

    summary = to_dict


class AgentLoop:
    def __init__(
        self,
        settings: Settings,
        agent_id: str,
        producer: Producer,
        *,
        use_server: bool = True,
        speed: float = 0.0,
        drop_when_behind: bool = False,
        wait_for_server: bool = False,
        flush_timeout_s: float = 30.0,
        stop: threading.Event | None = None,
        progress: bool = False,
        total_frames: int | None = None,
    ) -> None:
        keys.check_id(agent_id, "agent")
        self.settings = settings
        self.agent = agent_id
        self.producer = producer
        self.use_server = use_server
        self.speed = speed
        self.drop_when_behind = drop_when_behind
        self.wait_for_server = wait_for_server
        self.flush_timeout_s = flush_timeout_s
        c = settings.comm
        self.comm = CommModule.from_settings(agent_id, c)
        self.pose_interval = 1.0 / c.pose_rate_hz
        self.stats = AgentStats(agent_id)
        self.health = HealthMeter()  # what the pose messages say about this agent
        producer.bind(self.comm, self.stats)
        self.poses: list[tuple[int, np.ndarray]] = []  # reported: VO pose through S_g_l
        self.vo_poses: list[tuple[int, np.ndarray]] = []  # the VO's own
        self.S_g_l = Sim3.identity()  # VO frame -> frame corrected by the server's map
        self.reported = ReportedPose()  # gates S_g_l and keeps the reported pose smooth
        self._state = "init"
        self._total = total_frames
        ep = settings.zenoh.connect[0] if use_server and settings.zenoh.connect else None
        self._reporter = ProgressReporter(agent_id, ep, self._progress) if progress else None
        self.kf_ref, self.T_l_ref = -1, np.eye(4)
        self.bus = None
        self._session = None
        self._own_bus = True
        self._ack_q: queue.Queue = queue.Queue()
        self._map_q: queue.Queue = queue.Queue(maxsize=MAP_CHUNK_QUEUE)
        self._stop = stop or threading.Event()
        self._last_pose = -1e18

    # --- network ----------------------------------------------------------------------
    def _connect(self) -> None:
        from shared.transport import Bus, open_session

        zs = self.settings.zenoh.model_copy(update={"connect_timeout_ms": -1})
        try:
            session = open_session(zs)
        except Exception:
            log.exception("zenoh session failed; flying without a server")
            return
        if self._stop.is_set():
            session.close()
            return
        self._session = session
        self._attach(Bus(session, "agent", self.settings.inject))

    def _attach(self, bus) -> None:
        bus.subscribe(keys.agent_ack(self.agent), self._ack_q)
        if self.producer.uses_map:
            bus.subscribe(keys.agent_map(self.agent), self._map_q)
        self.bus = bus
        log.info("connected to the server", extra={"agent": self.agent})

    def _progress(self) -> Snapshot:
        """Counters only (read from the reporter's thread: no iteration over live maps)."""
        from shared.transport import router_count

        c, st = self.comm, self.stats
        maps = st.server_maps
        return Snapshot(st.frames, self._total, self._state, st.keyframes,
                        len(c.acked_kfs) + len(c.first_sent_at), len(c.acked_kfs), len(c.kfs),
                        maps[-1] if maps else None, router_count(self._session))  # fmt: skip

    def close(self) -> None:
        self._stop.set()
        if self._reporter is not None:
            self._reporter.stop()
        self.producer.close()
        if self._own_bus and self.bus is not None:
            self.bus.close()
        if self._session is not None:
            self._session.close()
            self._session = None

    # --- main loop --------------------------------------------------------------------
    def run(self, bus=None) -> AgentStats:
        """Fly every frame, then keep sending until the server has everything (or
        ``flush_timeout_s``). ``bus``: an open bus to share (many agents, one session)."""
        if bus is not None:
            self._own_bus = False
            self._attach(bus)
        elif self.use_server and self.wait_for_server:
            self._connect()
        elif self.use_server:
            threading.Thread(target=self._connect, name="agent-connect", daemon=True).start()
        if self._reporter is not None:
            self._reporter.start()
        t_start = time.monotonic()
        clock = _Clock(self.speed)
        lost_since = None
        st = self.stats
        frames = _Lookahead(self.producer.frames())
        for fr in frames:
            if self._stop.is_set():
                break
            due = clock.due(fr.stamp_ns)
            if fr.due is not None:
                due = fr.due
            if fr.dropped:
                self._dropped(fr.dropped)
            if due is not None:
                nxt = frames.peek() if self.drop_when_behind else None
                nxt_due = None if nxt is None else nxt.due or clock.at(nxt.stamp_ns)
                if nxt_due is not None and nxt_due <= time.monotonic():
                    # A newer frame has arrived meanwhile: a camera driver keeps only the
                    # newest, so this one is gone.
                    self._dropped(1)
                    continue
                while (now := time.monotonic()) < due:
                    self._service(due - now)
            s = self.producer.step(fr)
            st.frames += 1
            # Without dropping, a frame more than a period late counts as one a live
            # camera would have dropped; with it, the drops above are the real ones.
            late = None if self.drop_when_behind else due
            self.health.frame(time.monotonic(), late, clock.period or None)
            st.track_s.append(s.track_s + fr.work_s)
            self._state = s.state
            if s.T_l_c is not None:
                self.vo_poses.append((s.stamp_ns, s.T_l_c))
                T = self.reported.update(s.T_l_c, s.state, s.T_pred, lost_since is not None)
                self.poses.append((s.stamp_ns, T))
                if due is not None:
                    st.latency_s.append(time.monotonic() - due)
            if s.state == "lost":
                st.lost_frames += 1
                lost_since = s.stamp_ns if lost_since is None else lost_since
                st.longest_lost_s = max(st.longest_lost_s, (s.stamp_ns - lost_since) * 1e-9)
            else:
                lost_since = None
            if s.keyframes:
                st.keyframes += s.keyframes
                if s.map_s > 0:
                    st.map_s.append(s.map_s)
            if s.kf_ref >= 0:
                self.kf_ref, self.T_l_ref = s.kf_ref, s.T_l_ref
            self._publish_pose(s)
            self._service(0.0)
        frames.close()
        st.flight_s = time.monotonic() - t_start
        if clock.stamp0 is not None and clock.last is not None and self.speed > 0:
            st.nominal_flight_s = (clock.last - clock.stamp0) * 1e-9 / self.speed
        if feedback_dump.enabled() and self.vo_poses:
            feedback_dump.record(self.agent, "vo", stamps=np.array([t for t, _ in self.vo_poses]),
                                 T=np.stack([T for _, T in self.vo_poses]),
                                 reported=np.stack([T for _, T in self.poses]))  # fmt: skip
        self.producer.finish()
        deadline = time.monotonic() + self.flush_timeout_s
        while self._flushing() and time.monotonic() < deadline and not self._stop.is_set():
            self._service(0.05)
        if self._reporter is not None:
            self._reporter.stop()
        return self._finish(t_start)

    def _dropped(self, n: int) -> None:
        self.stats.dropped_frames += n
        self.health.frames_dropped += n
        AGENT_FRAMES_DROPPED.labels(self.agent).inc(n)

    def _flushing(self) -> bool:
        """After the last frame: keep going while a server may still take our data."""
        c = self.comm
        return self.use_server and (self.bus is None or c.pending or c.has_updates)

    def _publish_pose(self, s: Step) -> None:
        now = time.monotonic()
        # Lost, the agent still reports (its last pose, marked lost): the server tells a
        # lost agent from a disconnected one by whether messages keep coming.
        T = s.T_l_c if s.T_l_c is not None else (self.vo_poses[-1][1] if self.vo_poses else None)
        if self.bus is None or T is None or self.kf_ref < 0:
            return
        if now - self._last_pose < self.pose_interval:
            return
        self._last_pose = now
        msg = PoseUpdate(self.agent, s.stamp_ns, T, self.kf_ref, se3_inv(self.T_l_ref) @ T,
                         s.state, session=self.comm.session,
                         **self.health.fields(self.comm))  # fmt: skip
        data = msg.encode()
        self.bus.put(keys.agent_pose(self.agent), data, reliable=False)
        self.health.pose_bytes += len(data)

    def _service(self, wait: float) -> None:
        """Take in acks, chunks and finished mapping; send what is due. With ``wait``,
        block up to that long for a message (or until the next send is due)."""
        self._drain()
        self.producer.poll()
        if self.bus is not None:
            now = time.monotonic()
            self.comm.check_timeouts(now)
            msg = self.comm.next_message(now, time.time_ns(), self.kf_ref)
            if msg is not None:
                data = msg.encode(compact=True)
                self.bus.put(keys.agent_kf(self.agent), data)
                self.comm.record_sent(len(data))
        if wait > 0:
            with contextlib.suppress(queue.Empty):
                item = self._ack_q.get(timeout=self._wait_for(wait))
                self._on_message(item.payload, item.key)

    def _wait_for(self, wait: float) -> float:
        """How long :meth:`_service` may block for a message: ``wait``, at most 20 ms
        (timeouts and map chunks are looked at that often), and no longer than until the
        next batch may go out when one waits only for the rate limit. Nothing waiting, or
        what waits held back by the window (an ack frees it, and an ack ends the wait),
        is no reason to wake sooner: waking every 2 ms there cost the simulated agents
        most of their CPU between frames."""
        c = self.comm
        w = min(wait, 0.02)
        if c.queued_kfs or c.queued_mps or c.kf_updates or c.mp_updates:
            gap = c.last_send + c.min_interval - time.monotonic()
            if gap > 0:  # else next_message just said no: the window holds it back
                w = min(w, max(gap, 0.002))
        return w

    def _drain(self) -> None:
        for q in (self._ack_q, self._map_q):
            while True:
                try:
                    item = q.get_nowait()
                except queue.Empty:
                    break
                self._on_message(item.payload, item.key)

    def _on_message(self, payload: bytes, key: str) -> None:
        if key.endswith("/down/map"):
            self._on_chunk(payload, key)
            return
        ack = self._decoded(Ack, payload, key, "ack")
        if ack is None:
            return
        maps = self.stats.server_maps
        if not maps or maps[-1] != ack.map_id:
            # The server merged our map with another agent's: we fly in a shared frame now.
            if maps:
                log.info("server map %s merged into %s", maps[-1], ack.map_id,
                         extra={"agent": self.agent})  # fmt: skip
            maps.append(ack.map_id)
        for lat in self.comm.on_ack(ack, time.monotonic()):
            AGENT_ACK_LATENCY.labels(self.agent).observe(lat)

    def _decoded(self, cls, payload: bytes, key: str, what: str):
        """``payload`` as a ``cls`` message, or None (counted, logged) when it is not one."""
        try:
            return cls.decode(payload)
        except DecodeError as e:
            REJECTED.labels("agent", key, "invalid").inc()
            log.warning("bad %s: %s", what, e)
            return None

    def _on_chunk(self, payload: bytes, key: str) -> None:
        c = self._decoded(MapChunk, payload, key, "map chunk")
        if c is None:
            return
        ok = False
        if c.S_g_l is not None:
            S = Sim3.from_matrix(c.S_g_l)
            ok = self.reported.offer(S)
            if ok:
                self.S_g_l = S
                self.stats.corrections += 1
            else:
                self.stats.corrections_held += 1
        # Every chunk, with a correction or not: a replay with another correction rule
        # (bench/replay_feedback.py) needs to know when each arrived.
        feedback_dump.record(self.agent, "chunk", frame=len(self.vo_poses), sent_ns=c.sent_ns,
                             map_id=c.map_id, S_g_l=c.S_g_l, accepted=ok)  # fmt: skip
        self.producer.on_chunk(c)

    def _finish(self, t_start: float) -> AgentStats:
        s, c = self.stats, self.comm
        s.duration_s = time.monotonic() - t_start
        s.messages, s.bytes = c.stats.messages, c.stats.bytes
        s.pose_bytes = self.health.pose_bytes
        s.kf_resent = c.stats.kf_resent
        s.kf_lost_unacked = c.stats.kf_dropped_unacked
        s.resent = dict(c.resent_reasons)
        for (kind, reason), n in c.resent_reasons.items():
            RESENT.labels(self.agent, kind, reason).inc(n)
        s.acked_keyframes = len(c.acked_kfs)
        lat = np.array(c.stats.ack_latencies)
        if len(lat):
            s.ack_latency_median_s = float(np.median(lat))
            s.ack_latency_p95_s = float(np.percentile(lat, 95))
        s.bytes_per_s = s.bytes / s.flight_s if s.flight_s > 0 else 0.0
        s.all_acked = not c.pending
        pairs = zip(c.stats.ack_sent_at, c.stats.ack_latencies, strict=True)
        s.ack_series = [[round(t - t_start, 3), round(x, 4)] for t, x in pairs]
        s.ack_attempts = list(c.stats.ack_attempts)
        s.comm_trace = [[e[0], round(e[1] - t_start, 3), *e[2:]] for e in c.stats.trace]
        return s


class _Clock:
    """When each frame is due: its timestamp since the first, divided by ``speed``."""

    def __init__(self, speed: float) -> None:
        self.speed = speed
        self.t0 = time.monotonic()
        self.stamp0: int | None = None
        self.last: int | None = None
        self.period = 0.0

    def due(self, stamp_ns: int) -> float | None:
        if self.speed <= 0:
            return None
        if self.stamp0 is None:
            self.stamp0 = stamp_ns
            self.t0 = time.monotonic()
        if self.last is not None and stamp_ns > self.last:
            self.period = (stamp_ns - self.last) * 1e-9 / self.speed
        self.last = stamp_ns
        return self.at(stamp_ns)

    def at(self, stamp_ns: int) -> float:
        """When a frame with this stamp is due (after the first frame set the clock)."""
        return self.t0 + (stamp_ns - self.stamp0) * 1e-9 / self.speed


class _Lookahead:
    """Frames with a look at the next one, if it is there without waiting for it."""

    def __init__(self, frames: Iterable[Frame]) -> None:
        self._it = iter(frames)
        self._ready = getattr(frames, "ready", None)
        self._next: list[Frame] = []  # the frame taken by peek()
        self._done = False

    def __iter__(self) -> _Lookahead:
        return self

    def __next__(self) -> Frame:
        if self._next:
            return self._next.pop()
        return next(self._it)

    def close(self) -> None:
        close = getattr(self._it, "close", None)
        if close is not None:
            close()

    def peek(self) -> Frame | None:
        if self._next:
            return self._next[0]
        if self._done or (self._ready is not None and not self._ready()):
            return None
        try:
            self._next.append(next(self._it))
        except StopIteration:
            self._done = True
            return None
        return self._next[0]
