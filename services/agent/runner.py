"""The real agent: image source -> VO -> bounded local map -> communication module.

The VO never waits for the network: the Zenoh session is opened in the background
(a client retries until a router is reachable), and until then keyframes and map
points wait in the communication module, bounded by the local map's buffer rules
(CCM-SLAM §4.2). Every frame's online pose goes to a TUM file.

The VO runs in its own frame ``l`` and is never moved. What the agent reports as its
pose is the VO pose mapped through the latest correction from the server
(``S_g_l``, see ``services.mapper.feedback.frame_correction``): the VO's drift
since the agent was last in a place the server's map knows, taken out by the
map's loop closures, merges and global optimization -- the map -> odometry split of
ROS navigation. Without a server (or with feedback off) the correction stays the
identity and the reported pose is the VO's.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from shared import keys
from shared.geometry import Sim3, se3_inv
from shared.messages import (
    Ack,
    DecodeError,
    KeyframeUpdate,
    MapChunk,
    MapPoints,
    NewKeyframe,
    PoseUpdate,
)
from shared.metrics import AGENT_ACK_LATENCY, REJECTED
from shared.settings import Settings
from shared.trajectory import Trajectory, format_tum

from .comm import CommModule
from .health import HealthMeter
from .local_map_trim import KfInfo, trim
from .progress import ProgressReporter, Snapshot
from .reported import ReportedPose
from .sources import ImageSource
from .vo.odometry import FrameResult, KeyFrame, VisualOdometry, VOParams, remove_keyframe

log = logging.getLogger(__name__)


@dataclass
class AgentStats:
    frames: int = 0
    keyframes: int = 0
    lost_frames: int = 0
    longest_lost_s: float = 0.0
    track_ms: list[float] = field(default_factory=list)
    map_ms: list[float] = field(default_factory=list)
    kf_trimmed: int = 0
    kf_lost_unacked: int = 0
    foreign_points: int = 0  # server points taken into the local map
    chunks: int = 0  # server map chunks received for a keyframe still held
    corrections: int = 0  # frame corrections taken from the server
    corrections_held: int = 0  # ... and held back by the gate (they contradicted the VO)
    server_maps: list[str] = field(default_factory=list)  # the server maps it was in, in order

    def summary(self) -> dict:
        t = np.array(self.track_ms) if self.track_ms else np.zeros(1)
        m = np.array(self.map_ms) if self.map_ms else np.zeros(1)
        return {
            "frames": self.frames, "keyframes": self.keyframes, "lost_frames": self.lost_frames,
            "longest_lost_s": self.longest_lost_s,
            "track_ms_median": float(np.median(t)), "track_ms_p95": float(np.percentile(t, 95)),
            "map_ms_per_kf_median": float(np.median(m)),
            "map_ms_per_kf_p95": float(np.percentile(m, 95)),
            "kf_trimmed": self.kf_trimmed, "kf_lost_unacked": self.kf_lost_unacked,
            "foreign_points": self.foreign_points, "chunks": self.chunks,
            "corrections": self.corrections, "corrections_held": self.corrections_held,
            "server_maps": self.server_maps,
        }  # fmt: skip


class Agent:
    def __init__(self, settings: Settings, agent_id: str, source: ImageSource,
                 use_server: bool = True, realtime: bool = False, n_local: int = 50,
                 n_buffer: int = 50, vo_params: VOParams | None = None) -> None:  # fmt: skip
        keys.check_id(agent_id, "agent")
        self.settings = settings
        self.agent = agent_id
        self.source = source
        self.use_server = use_server
        self.realtime = realtime
        self.n_local, self.n_buffer = n_local, n_buffer
        self.vo = VisualOdometry(source.camera, vo_params)
        c = settings.comm
        self.comm = CommModule.from_settings(agent_id, c)
        self.stats = AgentStats()
        self.health = HealthMeter()
        self.poses: list[tuple[int, np.ndarray]] = []  # online: VO pose through S_g_l
        self.vo_poses: list[tuple[int, np.ndarray]] = []  # the VO's own
        self.S_g_l = Sim3.identity()  # VO frame -> frame corrected by the server's map
        self.reported = ReportedPose()  # gates S_g_l and keeps the reported pose smooth
        self.kf_poses: list[tuple[int, np.ndarray]] = []  # each keyframe as first sent
        self.bus = None
        self._session = None
        self._ack_q: queue.Queue = queue.Queue()
        self._sent_kfs: set[int] = set()
        self._stop = threading.Event()
        ep = settings.zenoh.connect[0] if use_server and settings.zenoh.connect else None
        self._reporter = ProgressReporter(agent_id, ep, self._progress)

    # --- network (background) -----------------------------------------------------------
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
        bus = Bus(session, "agent", self.settings.inject)
        bus.subscribe(keys.agent_ack(self.agent), self._ack_q)
        bus.subscribe(keys.agent_map(self.agent), self._ack_q, maxsize=4)
        self.bus = bus
        log.info("connected to the server", extra={"agent": self.agent})

    # --- main loop ------------------------------------------------------------------------
    def run(self) -> AgentStats:
        if self.use_server:
            threading.Thread(target=self._connect, name="agent-connect", daemon=True).start()
        self._reporter.start()
        t_start = time.monotonic()
        stamp0 = prev_stamp = None
        lost_since = None
        for fr in self.source:
            if self._stop.is_set():
                break
            due = period = None
            if self.realtime:
                stamp0 = fr.stamp_ns if stamp0 is None else stamp0
                due = t_start + (fr.stamp_ns - stamp0) * 1e-9
                if prev_stamp is not None:
                    period = (fr.stamp_ns - prev_stamp) * 1e-9
                prev_stamp = fr.stamp_ns
                while time.monotonic() < due:
                    self._service(min(due - time.monotonic(), 0.02))
            r = self.vo.track(fr.image, fr.stamp_ns)
            self.stats.frames += 1
            self.health.frame(time.monotonic(), due, period)
            self.stats.track_ms.append(r.track_s * 1e3)
            if r.T_w_c is not None:
                self.vo_poses.append((fr.stamp_ns, r.T_w_c))
                was_lost = lost_since is not None
                self.poses.append((fr.stamp_ns, self.reported.update(r.T_w_c, r.state, r.T_pred,
                                                                     was_lost)))  # fmt: skip
            if r.state == "lost":
                self.stats.lost_frames += 1
                lost_since = fr.stamp_ns if lost_since is None else lost_since
                self.stats.longest_lost_s = max(self.stats.longest_lost_s,
                                                (fr.stamp_ns - lost_since) * 1e-9)  # fmt: skip
            else:
                lost_since = None
            if r.keyframe is not None:
                self.kf_poses.append((r.keyframe.stamp_ns, r.keyframe.T_w_c.copy()))
                self.stats.keyframes += 1
                self.stats.map_ms.append(r.map_s * 1e3)
                self._on_keyframe(r)
            self._publish_pose(r)
            self._service(0.0)
        deadline = time.monotonic() + 30
        while self._flushing() and time.monotonic() < deadline:
            self._service(0.05)
        self.stats.kf_lost_unacked = self.comm.stats.kf_dropped_unacked
        self._reporter.stop()
        return self.stats

    def _progress(self) -> Snapshot:
        """Counters only (read from the reporter's thread: no iteration over live maps)."""
        from shared.transport import router_count

        c, maps = self.comm, self.stats.server_maps
        total = len(self.source) if hasattr(self.source, "__len__") else None
        return Snapshot(self.stats.frames, total, self.vo.state, self.stats.keyframes,
                        len(c.acked_kfs) + len(c.first_sent_at), len(c.acked_kfs), len(c.kfs),
                        maps[-1] if maps else None, router_count(self._session))  # fmt: skip

    def _flushing(self) -> bool:
        """After the last frame: keep going while a server may still take our data."""
        return self.use_server and (self.bus is None or self.comm.pending)

    def close(self) -> None:
        self._stop.set()
        self._reporter.stop()
        if self.bus is not None:
            self.bus.close()
        if self._session is not None:
            self._session.close()

    def _service(self, wait: float) -> None:
        try:
            item = self._ack_q.get(timeout=wait) if wait > 0 else self._ack_q.get_nowait()
            self._on_ack(item.payload, item.key)
            while True:
                item = self._ack_q.get_nowait()
                self._on_ack(item.payload, item.key)
        except queue.Empty:
            pass
        if self.bus is None:
            return
        now = time.monotonic()
        self.comm.check_timeouts(now)
        msg = self.comm.next_message(now, time.time_ns(), max(self.vo.kfs, default=-1))
        if msg is not None:
            data = msg.encode()
            self.bus.put(keys.agent_kf(self.agent), data)
            self.comm.record_sent(len(data))

    def _on_ack(self, payload: bytes, key: str) -> None:
        if key.endswith("/down/map"):
            self._on_chunk(payload, key)
            return
        try:
            ack = Ack.decode(payload)
        except DecodeError as e:
            REJECTED.labels("agent", key, "invalid").inc()
            log.warning("bad ack: %s", e)
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

    def _on_chunk(self, payload: bytes, key: str) -> None:
        """Server map data near KF_ref augments the local map."""
        try:
            c = MapChunk.decode(payload)
        except DecodeError as e:
            REJECTED.labels("agent", key, "invalid").inc()
            log.warning("bad map chunk: %s", e)
            return
        if c.S_g_l is not None:
            S = Sim3.from_matrix(c.S_g_l)
            if self.reported.offer(S):
                self.S_g_l = S
                self.stats.corrections += 1
            else:
                self.stats.corrections_held += 1
        ref = self.vo.kfs.get(c.kf_ref)
        if ref is None:
            return
        # Counted even when empty: the server leaves out what this agent tracks already,
        # so a lone agent's chunks often carry nothing new.
        self.stats.chunks += 1
        if len(c.mp_ids) == 0:
            return
        own = {i for i in self.vo.mps if i not in self.vo.foreign}
        sel = [j for j, (a, i) in enumerate(zip(c.mp_agents, c.mp_ids.tolist(), strict=True))
               if not (a == self.agent and i in own)]  # fmt: skip
        if not sel:
            return
        pos = c.p_ref[sel] @ ref.T_w_c[:3, :3].T + ref.T_w_c[:3, 3]
        keys_ = [(c.mp_agents[j], int(c.mp_ids[j])) for j in sel]
        self.stats.foreign_points += self.vo.add_foreign_points(keys_, pos, c.mp_descriptors[sel])

    def _publish_pose(self, r: FrameResult) -> None:
        # Lost, the agent still reports (its last pose, marked lost): the server tells a
        # lost agent from a disconnected one by whether messages keep coming.
        T = r.T_w_c if r.T_w_c is not None else (self.vo_poses[-1][1] if self.vo_poses else None)
        if self.bus is None or T is None or not self.vo.kfs:
            return
        ref = self.vo.kfs[max(self.vo.kfs)]
        msg = PoseUpdate(self.agent, r.stamp_ns, T, ref.id, se3_inv(ref.T_w_c) @ T,
                         r.state, **self.health.fields(self.comm))  # fmt: skip
        data = msg.encode()
        self.bus.put(keys.agent_pose(self.agent), data, reliable=False)
        self.health.pose_bytes += len(data)

    # --- local map -> messages ------------------------------------------------------------
    def _own_ids(self, mp: np.ndarray) -> np.ndarray:
        """Associations to the server's points stay on board (the server made them)."""
        out = mp.copy()
        if self.vo.foreign:
            out[np.isin(out, np.fromiter(self.vo.foreign, np.int64))] = -1
        return out

    def _parent(self, kf: KeyFrame) -> int:
        counts: dict[int, int] = {}
        for i in kf.mp[kf.mp >= 0].tolist():
            mp = self.vo.mps.get(i)
            if mp is None:
                continue
            for k in mp.obs:
                if k != kf.id:
                    counts[k] = counts.get(k, 0) + 1
        return max(counts, key=counts.get) if counts else -1

    def _rel(self, kf: KeyFrame, other: int) -> np.ndarray:
        o = self.vo.kfs.get(other)
        return np.eye(4) if o is None else se3_inv(o.T_w_c) @ kf.T_w_c

    def _on_keyframe(self, r: FrameResult) -> None:
        vo = self.vo
        kf = r.keyframe
        ids = sorted(vo.kfs)
        # The first two keyframes come from initialization together.
        new = [k for k in ids if k not in self._sent_kfs]
        for kid in new:
            k = vo.kfs[kid]
            pred = max((i for i in ids if i < kid), default=-1)
            par = self._parent(k)
            self.comm.add_keyframe(NewKeyframe(
                id=kid, stamp_ns=k.stamp_ns, T_l_kf=k.T_w_c.copy(), pred_id=pred,
                T_pred_kf=self._rel(k, pred), parent_id=par, T_par_kf=self._rel(k, par),
                keypoints=k.f.kp, octaves=k.f.octave, descriptors=k.f.desc,
                mp_ids=self._own_ids(k.mp), calib=self.source.camera.to_array(),
            ))  # fmt: skip
            self._sent_kfs.add(kid)
        if r.new_points:
            pts = [vo.mps[i] for i in r.new_points if i in vo.mps]
            refs = [min(p.obs) for p in pts]
            T_inv = {k: se3_inv(vo.kfs[k].T_w_c) for k in set(refs)}
            self.comm.add_map_points(MapPoints(
                np.array([p.id for p in pts], np.int64), np.array(refs, np.int64),
                np.array([T_inv[k][:3, :3] @ p.pos + T_inv[k][:3, 3] for p, k in
                          zip(pts, refs, strict=True)]).reshape(-1, 3),
                np.array([p.desc for p in pts], np.uint8).reshape(-1, 32),
            ))  # fmt: skip
        # Local BA moved the window: send its keyframes' new relative poses and the
        # older keyframes that gained observations of the new points.
        gained = {k for i in r.new_points if i in vo.mps for k in vo.mps[i].obs}
        for kid in ids[-self.vo.p.window :]:
            if kid in new:
                continue
            k = vo.kfs[kid]
            pred = max((i for i in ids if i < kid), default=-1)
            par = self._parent(k)
            # Associations (8 bytes a keypoint) only where triangulation added some.
            mp = self._own_ids(k.mp) if kid in gained else None
            self.comm.update_keyframe(KeyframeUpdate(kid, pred, self._rel(k, pred), par,
                                                     self._rel(k, par), mp))  # fmt: skip
        self._trim(kf.id)

    def _trim(self, kf_ref: int) -> None:
        unacked = self.comm.unacked_kf_ids
        infos = [KfInfo(k, True, k not in unacked) for k in self.vo.kfs]
        gone = trim(infos, kf_ref, self.n_local, self.n_buffer)
        for k in gone:
            remove_keyframe(self.vo, k)
            self.stats.kf_trimmed += 1
            if k in unacked:
                self.comm.forget_keyframe(k)
        lost = set(gone) & unacked
        if lost:
            self._reanchor_points(lost)

    def _reanchor_points(self, lost_kfs: set[int]) -> None:
        """Unsent points anchored to a keyframe the server will never get move to a
        keyframe that still exists and sees them; points nobody sees any more go."""
        for i, (ref, _, desc) in list(self.comm.mps.items()):
            if ref not in lost_kfs:
                continue
            mp = self.vo.mps.get(i)
            alive = [k for k in (mp.obs if mp else ()) if k in self.vo.kfs]
            if not alive:
                self.comm.forget_map_point(i)
                continue
            k = min(alive)
            T = se3_inv(self.vo.kfs[k].T_w_c)
            self.comm.mps[i] = (k, T[:3, :3] @ mp.pos + T[:3, 3], desc)

    def write_outputs(self, out: Path) -> None:
        out.mkdir(parents=True, exist_ok=True)
        for name, poses in (("online", self.poses), ("vo", self.vo_poses)):
            if poses:
                st = np.array([s for s, _ in poses], np.int64)
                T = np.stack([T for _, T in poses])
                (out / f"{self.agent}_{name}.tum").write_text(format_tum(st, T))
        gt = self.source.ground_truth
        if gt is not None:
            (out / f"{self.agent}_gt.tum").write_text(format_tum(gt.stamps_ns, gt.poses))
        import json

        if self.kf_poses:
            st = np.array([s for s, _ in self.kf_poses], np.int64)
            T = np.stack([T for _, T in self.kf_poses])
            (out / f"{self.agent}_keyframes.tum").write_text(format_tum(st, T))
        lat = np.array(self.comm.stats.ack_latencies) if self.comm.stats.ack_latencies else None
        comm = {
            "bytes": self.comm.stats.bytes, "messages": self.comm.stats.messages,
            "kf_resent": self.comm.stats.kf_resent,
            "ack_latency_median_ms": None if lat is None else float(np.median(lat) * 1e3),
            "ack_latency_p95_ms": None if lat is None else float(np.percentile(lat, 95) * 1e3),
        }  # fmt: skip
        vo = {"relocalized": self.vo.relocalized, "rejected_jumps": self.vo.rejected_jumps}
        doc = {**self.stats.summary(), "comm": comm, "vo": vo}
        (out / f"{self.agent}_stats.json").write_text(json.dumps(doc, indent=2))


def online_trajectory(agent: Agent) -> Trajectory:
    st = np.array([s for s, _ in agent.poses], np.int64)
    return Trajectory(st, np.stack([T for _, T in agent.poses]))
