"""The real agent: image source -> monocular VO -> bounded local map -> the agent loop.

:class:`VOProducer` is the VO side of :class:`~services.agent.loop.AgentLoop`: it tracks
each image, turns new keyframes, map points and local-BA changes into messages for the
communication module, bounds the local map (CCM-SLAM §4.2: past N + B keyframes the
oldest go, unacknowledged ones too; the communication module keeps those until they are
acknowledged) and takes the server's map points near KF_ref
into tracking. :class:`Agent` is the loop with this producer.

What it sends, and why it is small (CCM-SLAM §4.5): a keyframe goes out once the two
after it have triangulated against it (its associations are final then), with only the
keypoints that have a map point; each new point goes with its reference keyframe; after
a local BA, the keyframes' new relative poses and the points that moved by more than
``comm.mp_update_rel`` of their depth, as updates. Live (``realtime``), local BA runs in
a process of its own (``vo/ba_worker.py``), and images are read and their ORB features
extracted on camera threads (``_Camera``) while the tracker works on the frame before.

The VO runs in its own frame ``l`` and is never moved. What the agent reports as its
pose is the VO pose mapped through the latest correction from the server
(``S_g_l``, see ``services.mapper.feedback.frame_correction``): the VO's drift
since the agent was last in a place the server's map knows, taken out by the
map's loop closures, merges and global optimization -- the map -> odometry split of
ROS navigation. Without a server (or with feedback off) the correction stays the
identity and the reported pose is the VO's. Every frame's reported pose goes to a TUM
file.
"""

from __future__ import annotations

import json
import queue
import threading
import time
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from shared.geometry import se3_inv
from shared.messages import KeyframeUpdate, MapChunk, MapPoints, NewKeyframe
from shared.orb import Features
from shared.settings import Settings
from shared.trajectory import Trajectory, format_tum

from .comm import CommModule
from .local_map_trim import KfInfo, trim
from .loop import AgentLoop, AgentStats, Frame, Step
from .sources import ImageSource
from .vo.ba_worker import BAWorker
from .vo.odometry import FrameResult, KeyFrame, VisualOdometry, VOParams, remove_keyframe


class VOProducer:
    """The monocular VO on an image source, as a producer of the agent loop."""

    uses_map = True

    def __init__(self, source: ImageSource, agent_id: str, n_local: int = 50,
                 n_buffer: int = 50, vo_params: VOParams | None = None,
                 live: bool = False, mp_update_rel: float = 0.01) -> None:  # fmt: skip
        self.source = source
        self.camera = source.camera
        self.agent = agent_id
        self.n_local, self.n_buffer = n_local, n_buffer
        self.vo = VisualOdometry(source.camera, vo_params)
        # Live: local BA in its own process, so tracking keeps up with the camera.
        # Offline the inline BA keeps runs repeatable (the same poses every time).
        self.live = live
        if live:
            self.vo.ba_worker = BAWorker()
        self.kf_poses: list[tuple[int, np.ndarray]] = []  # each keyframe as first sent
        self._kf_seen = 0  # VO keyframe ids below this are in kf_poses (ids count up)
        self._sent_kfs: set[int] = set()
        self._newest_sent = -1
        self._kp_sel: dict[int, np.ndarray] = {}  # keyframe -> the keypoints sent
        self._mp_sent: dict[int, tuple[int, np.ndarray]] = {}  # point -> ref kf, p_ref sent
        self.mp_update_rel = mp_update_rel

    def bind(self, comm: CommModule, stats: AgentStats) -> None:
        self.comm, self.stats = comm, stats

    def frames(self) -> Iterable[Frame]:
        if not self.live:
            return (Frame(f.stamp_ns, f.image) for f in self.source)
        return _Camera(self.source, self.vo.extract)

    def step(self, frame: Frame) -> Step:
        if isinstance(frame.data, Features):  # extracted by the camera thread
            r = self.vo.track(None, frame.stamp_ns, features=frame.data)
        else:
            r = self.vo.track(frame.data, frame.stamp_ns)
        s = Step(r.stamp_ns, r.T_w_c, r.state, T_pred=r.T_pred, track_s=r.track_s,
                 map_s=r.map_s)  # fmt: skip
        if r.keyframe is not None:
            # Every keyframe made since the last one seen: initialization makes two.
            kfs = self.vo.kfs
            made = [kfs[k] for k in range(self._kf_seen, self.vo.next_kf) if k in kfs]
            for k in made:
                self.kf_poses.append((k.stamp_ns, k.T_w_c.copy()))
            self._kf_seen = self.vo.next_kf
            s.keyframes = len(made)
            self._on_keyframe(r)
        self._after_ba()
        # KF_ref: the newest keyframe the server can have (the newer ones wait to
        # settle), so it can place the live pose and send map data around it.
        ref = self.vo.kfs.get(self._newest_sent)
        if ref is not None:
            s.kf_ref, s.T_l_ref = ref.id, ref.T_w_c
        return s

    def poll(self) -> None:
        if self.vo.poll_mapping():
            self._after_ba()

    def finish(self) -> None:
        while self.vo.poll_mapping(wait=True):
            self._after_ba()
        # The last keyframes will not settle any more.
        self._send_keyframes([k for k in sorted(self.vo.kfs) if k not in self._sent_kfs])

    def close(self) -> None:
        if self.vo.ba_worker is not None:
            self.vo.ba_worker.close()
            self.vo.ba_worker = None

    def on_chunk(self, c: MapChunk) -> None:
        """Server map data near KF_ref augments the local map."""
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

    # --- local map -> messages ------------------------------------------------------------
    def _own_ids(self, mp: np.ndarray) -> np.ndarray:
        """Associations to the server's points stay on board (the server made them)."""
        out = mp.copy()
        if self.vo.foreign:
            out[np.isin(out, np.fromiter(self.vo.foreign, np.int64))] = -1
        return out

    def _parents(self, kids: list[int]) -> dict[int, int]:
        """Each keyframe's parent: the other keyframe that observes most of its map
        points; among equals the one met first going through its keypoints in order
        (and, at one point, the older). -1 if no other keyframe sees any of them.

        One sorted index of every keyframe's point ids serves all ``kids``: a local BA
        updates its whole window, and going through each point's observations in Python
        cost ~4 ms per keyframe, 30-40 ms per BA on the tracking path (profiled, MH02)."""
        vo = self.vo
        ids = np.array(sorted(vo.kfs), np.int64)
        mps = [vo.kfs[k].mp for k in ids.tolist()]
        owner = np.repeat(np.arange(len(ids)), [len(m) for m in mps])
        allmp = np.concatenate(mps) if mps else np.zeros(0, np.int64)
        has = allmp >= 0
        owner, allmp = owner[has], allmp[has]
        order = np.argsort(allmp, kind="stable")
        sid, sown = allmp[order], owner[order]
        out = {}
        for kid in kids:
            mp = vo.kfs[kid].mp
            j = np.nonzero(mp >= 0)[0]
            lo = np.searchsorted(sid, mp[j], "left")
            n = np.searchsorted(sid, mp[j], "right") - lo
            # Every (keypoint, observing keyframe) pair, keypoints in order.
            start = np.repeat(lo - (np.cumsum(n) - n), n)
            kf_i = sown[start + np.arange(int(n.sum()))]
            kp_j = np.repeat(j, n)
            other = kf_i != np.searchsorted(ids, kid)
            kf_i, kp_j = kf_i[other], kp_j[other]
            if not len(kf_i):
                out[kid] = -1
                continue
            counts = np.bincount(kf_i, minlength=len(ids))
            best = np.nonzero(counts == counts.max())[0]
            if len(best) > 1:
                first = np.full(len(ids), np.iinfo(np.int64).max)
                np.minimum.at(first, kf_i, kp_j)
                best = best[np.argsort(first[best], kind="stable")]
            out[kid] = int(ids[best[0]])
        return out

    def _rel(self, kf: KeyFrame, other: int) -> np.ndarray:
        o = self.vo.kfs.get(other)
        return np.eye(4) if o is None else se3_inv(o.T_w_c) @ kf.T_w_c

    def _on_keyframe(self, r: FrameResult) -> None:
        vo = self.vo
        kf = r.keyframe
        # A keyframe goes out once it is settled: the VO triangulates each new keyframe
        # against the ``tri_kfs`` before it, so until that many came after it its free
        # keypoints may still gain map points. Then only the keypoints with a map
        # point are sent (the others will never have one on board), and no association
        # update follows (8 bytes a keypoint each time).
        ids = sorted(vo.kfs)
        settled = ids[: max(0, len(ids) - vo.p.tri_kfs)]
        self._send_keyframes([k for k in settled if k not in self._sent_kfs])
        self._trim(kf.id)

    def _send_keyframes(self, new: list[int]) -> None:
        vo = self.vo
        dropped: list[int] = []  # by the communication module's bound (normally none)
        parents = self._parents(new)
        for kid in new:
            k = vo.kfs[kid]
            pred = max((i for i in vo.kfs if i < kid), default=-1)
            par = parents[kid]
            sel = np.nonzero(k.mp >= 0)[0]
            self._kp_sel[kid] = sel
            dropped += self.comm.add_keyframe(NewKeyframe(
                id=kid, stamp_ns=k.stamp_ns, T_l_kf=k.T_w_c.copy(), pred_id=pred,
                T_pred_kf=self._rel(k, pred), parent_id=par, T_par_kf=self._rel(k, par),
                keypoints=k.f.kp[sel], octaves=k.f.octave[sel], descriptors=k.f.desc[sel],
                mp_ids=self._own_ids(k.mp[sel]), calib=self.camera.to_array(),
            ))  # fmt: skip
            self._sent_kfs.add(kid)
            self._newest_sent = max(self._newest_sent, kid)
        if dropped:
            self._reanchor_points(set(dropped))
        if not new:
            return
        # The new points whose reference keyframe (the oldest that sees them) the server
        # now has or is getting; positions as the last local BA left them.
        sent = self._sent_kfs
        pts = [p for i, p in vo.mps.items()
               if i not in vo.foreign and i not in self._mp_sent and p.obs
               and min(p.obs) in sent]  # fmt: skip
        if not pts:
            return
        refs = [min(p.obs) for p in pts]
        T_inv = {k: se3_inv(vo.kfs[k].T_w_c) for k in set(refs)}
        p_ref = np.array([T_inv[k][:3, :3] @ p.pos + T_inv[k][:3, 3]
                          for p, k in zip(pts, refs, strict=True)]).reshape(-1, 3)  # fmt: skip
        for p, k, x in zip(pts, refs, p_ref, strict=True):
            self._mp_sent[p.id] = (k, x)
        self.stats.map_points += len(pts)
        self.comm.add_map_points(MapPoints(
            np.array([p.id for p in pts], np.int64), np.array(refs, np.int64), p_ref,
            np.array([p.desc for p in pts], np.uint8).reshape(-1, 32),
        ))  # fmt: skip

    def _update_kf(self, kid: int, par: int) -> None:
        k = self.vo.kfs[kid]
        pred = max((i for i in self.vo.kfs if i < kid), default=-1)
        self.comm.update_keyframe(KeyframeUpdate(kid, pred, self._rel(k, pred), par,
                                                 self._rel(k, par), None))  # fmt: skip

    def _after_ba(self) -> None:
        """Local BA moved the window: send its keyframes' new relative poses and the
        new positions of its points (CCM-SLAM §4.5 "updates"), each relative to the
        point's reference keyframe, for the points that moved by more than
        ``mp_update_rel`` of their distance from it."""
        vo = self.vo
        for moved_kfs, moved_mps in vo.ba_applied:
            if moved_kfs:
                win = [k for k in sorted(vo.kfs)[-vo.p.window :] if k in self._sent_kfs]
                parents = self._parents(win)
                for kid in win:
                    self._update_kf(kid, parents[kid])
            # The moved points this agent sent whose reference keyframe it still holds,
            # transformed into their reference keyframes all at once.
            sel = [(i, s[0], s[1], mp.pos) for i in moved_mps
                   if (s := self._mp_sent.get(i)) is not None
                   and (mp := vo.mps.get(i)) is not None and s[0] in vo.kfs]  # fmt: skip
            if not sel:
                continue
            ids, refs, x0, pos = zip(*sel, strict=True)
            uref, inv = np.unique(np.array(refs, np.int64), return_inverse=True)
            T = np.stack([se3_inv(vo.kfs[k].T_w_c) for k in uref.tolist()])[inv]
            x0 = np.array(x0)
            x = (T[:, :3, :3] @ np.array(pos)[:, :, None])[:, :, 0] + T[:, :3, 3]
            far = np.linalg.norm(x - x0, axis=1) > self.mp_update_rel * np.linalg.norm(x0, axis=1)
            for n in np.nonzero(far)[0].tolist():
                i, ref, xi = ids[n], refs[n], x[n].copy()
                self._mp_sent[i] = (ref, xi)
                self.comm.update_map_point(i, ref, xi)
                self.stats.mp_updates += 1
        vo.ba_applied.clear()

    def _trim(self, kf_ref: int) -> None:
        # An unacknowledged keyframe trimmed here is not lost: the communication module
        # keeps its message (and the points anchored to it) until the server acks it.
        unacked = self.comm.unacked_kf_ids
        infos = [KfInfo(k, True, k not in unacked) for k in self.vo.kfs]
        for k in trim(infos, kf_ref, self.n_local, self.n_buffer):
            remove_keyframe(self.vo, k)
            self.stats.kf_trimmed += 1

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


class Agent(AgentLoop):
    """The real agent: the agent loop with the VO producer. ``realtime`` flies as a
    live camera delivers: frames at their timestamps, dropped when the agent is behind."""

    def __init__(self, settings: Settings, agent_id: str, source: ImageSource,
                 use_server: bool = True, realtime: bool = False, n_local: int = 50,
                 n_buffer: int = 50, vo_params: VOParams | None = None) -> None:  # fmt: skip
        self.source = source
        self.realtime = realtime
        producer = VOProducer(source, agent_id, n_local, n_buffer, vo_params or settings.vo,
                              live=realtime,
                              mp_update_rel=settings.comm.mp_update_rel)  # fmt: skip
        super().__init__(settings, agent_id, producer, use_server=use_server,
                         speed=1.0 if realtime else 0.0, drop_when_behind=realtime,
                         progress=True, total_frames=_len(source))  # fmt: skip

    @property
    def vo(self) -> VisualOdometry:
        return self.producer.vo

    @property
    def kf_poses(self) -> list[tuple[int, np.ndarray]]:
        return self.producer.kf_poses

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
        if self.kf_poses:
            st = np.array([s for s, _ in self.kf_poses], np.int64)
            T = np.stack([T for _, T in self.kf_poses])
            (out / f"{self.agent}_keyframes.tum").write_text(format_tum(st, T))
        vo = {"relocalized": self.vo.relocalized, "rejected_jumps": self.vo.rejected_jumps,
              "local_ba_aborted": self.vo.ba_aborted}  # fmt: skip
        doc = {**self.stats.to_dict(), "vo": vo}
        (out / f"{self.agent}_stats.json").write_text(json.dumps(doc, indent=2))


class _Camera:
    """A live camera's frames. It delivers decoded images: reading and decoding them (a
    few ms a frame, more when the synthetic world renders one) is the camera's work,
    done on a thread of its own (OpenCV releases the GIL) a few frames ahead.

    With ``extract`` the agent's feature extraction runs here too, on a second thread,
    while the tracker works on the previous frame (half the tracking path's time was
    ORB extraction: profiled on MH02, ~15 of ~27 ms a frame). That thread never looks
    ahead of the clock: it takes each frame at its timestamp (paced from the first
    frame), skips a frame whose successor is due already, and hands the tracker the
    newest extracted frame; one the tracker did not take before a newer one was ready
    is dropped. Each frame then says when it was due and how many were dropped before
    it. ``ready()``: a frame is delivered and waiting."""

    def __init__(self, source: ImageSource, extract=None, ahead: int = 4) -> None:
        self._raw: queue.Queue = queue.Queue(maxsize=ahead)
        self._stop = threading.Event()
        self._done = object()
        self._source = source
        self._extract = extract
        self._box: list = []  # the extracted frame waiting for the tracker; then the end
        self._cv = threading.Condition()
        threading.Thread(target=self._read, name="camera", daemon=True).start()
        if extract is not None:
            threading.Thread(target=self._front, name="camera-features", daemon=True).start()

    def _read(self) -> None:
        try:
            for f in self._source:
                while not self._stop.is_set():
                    try:
                        self._raw.put((f.stamp_ns, f.image), timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if self._stop.is_set():
                    return
            self._raw.put(self._done)
        except BaseException as e:  # the source's error reaches the agent's thread
            self._raw.put(e)

    def _deliver(self, item) -> None:
        with self._cv:
            if isinstance(item, Frame) and self._box and isinstance(self._box[-1], Frame):
                old = self._box.pop()  # not taken in time: a newer frame replaces it
                item.dropped += 1 + old.dropped
            self._box.append(item)
            self._cv.notify()

    def _take(self):
        """The next decoded frame; the end once the camera is closed."""
        while not self._stop.is_set():
            try:
                return self._raw.get(timeout=0.1)
            except queue.Empty:
                continue
        return self._done

    def _front(self) -> None:
        t0 = stamp0 = None
        dropped = 0
        item = self._take()
        while not self._stop.is_set():
            if item is self._done or isinstance(item, BaseException):
                self._deliver(item)
                return
            stamp, img = item
            if t0 is None:
                t0, stamp0 = time.monotonic(), stamp
            due = t0 + (stamp - stamp0) * 1e-9
            while (wait := due - time.monotonic()) > 0 and not self._stop.is_set():
                time.sleep(min(wait, 0.1))
            try:
                nxt = self._raw.get_nowait()
            except queue.Empty:
                nxt = None
            if isinstance(nxt, tuple) and t0 + (nxt[0] - stamp0) * 1e-9 <= time.monotonic():
                dropped += 1  # its successor is due already
                item = nxt
                continue
            t = time.perf_counter()
            feats = self._extract(img)
            fr = Frame(stamp, feats, due, dropped, time.perf_counter() - t)
            dropped = 0
            self._deliver(fr)
            item = self._take() if nxt is None else nxt

    def ready(self) -> bool:
        if self._extract is None:
            return not self._raw.empty()
        with self._cv:
            return bool(self._box)

    def __iter__(self) -> _Camera:
        return self

    def __next__(self) -> Frame:
        if self._extract is None:
            item = self._raw.get()
        else:
            with self._cv:
                while not self._box:
                    self._cv.wait()
                item = self._box.pop(0)
        if item is self._done:  # the end stays the end
            if self._extract is None:
                self._raw.put(item)
            else:
                self._deliver(item)
            raise StopIteration
        if isinstance(item, BaseException):
            self.close()
            raise item
        return item if isinstance(item, Frame) else Frame(*item)

    def close(self) -> None:
        self._stop.set()


def _len(source: ImageSource) -> int | None:
    try:
        return len(source)
    except (TypeError, NotImplementedError):
        return None  # a live camera


def online_trajectory(agent: Agent) -> Trajectory:
    st = np.array([s for s, _ in agent.poses], np.int64)
    return Trajectory(st, np.stack([T for _, T in agent.poses]))
