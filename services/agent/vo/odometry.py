"""Keyframe-based monocular visual odometry (CCM-SLAM §4.1, the ORB-SLAM front end).

Tracking per frame: constant-velocity prediction, projection search of the local
map points, robust pose refinement (two passes), keyframe decision. Mapping per
keyframe: triangulation of new points against the previous keyframes, point
culling, local bundle adjustment (GTSAM). Relocalization against recent keyframes
when tracking is lost. Pure algorithm: images in, poses and keyframes out.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from shared.camera import PinholeRadTan
from shared.geometry import exp_so3, log_so3, se3_inv
from shared.orb import Extractor, Features, hamming
from shared.settings import VOSettings as VOParams

from .ba_worker import BAWorker
from .features import match_by_projection, match_descriptors
from .geometry import solve_pnp, triangulate, two_view_init
from .local_ba import BAResult, local_ba

FOREIGN_ID0 = 1 << 50  # first local id of a point the server sent


@dataclass
class KeyFrame:
    id: int
    stamp_ns: int
    T_w_c: np.ndarray
    f: Features
    mp: np.ndarray  # (N,) int64 map point per keypoint, -1 none


@dataclass
class MapPoint:
    id: int
    pos: np.ndarray
    desc: np.ndarray
    obs: dict[int, int] = field(default_factory=dict)  # kf id -> keypoint
    visible: int = 1
    found: int = 1
    first_kf: int = 0


@dataclass
class FrameResult:
    stamp_ns: int
    T_w_c: np.ndarray | None
    state: str  # init | ok | lost
    inliers: int = 0
    keyframe: KeyFrame | None = None
    new_points: list[int] = field(default_factory=list)
    track_s: float = 0.0
    map_s: float = 0.0
    T_pred: np.ndarray | None = None  # the motion model's pose for this frame
    how: str = ""  # which path found the pose (diagnostics: predict, wide, reloc, ...)


class VisualOdometry:
    def __init__(self, camera: PinholeRadTan, params: VOParams | None = None) -> None:
        self.cam = camera
        self.p = params or VOParams()
        self._strong = self.p.strong_factor * self.p.min_inliers
        self.extract = Extractor(camera, self.p.n_features)
        self.kfs: dict[int, KeyFrame] = {}
        self.mps: dict[int, MapPoint] = {}
        self.next_kf = 0
        self.next_mp = 0
        # The server's points get ids of their own range, so the agent's own point ids
        # (what it sends) do not depend on what the server sent when.
        self.next_foreign_mp = FOREIGN_ID0
        self.state = "init"
        self.init_ref: tuple[int, Features] | None = None
        self.init_age = 0
        self.T_last: np.ndarray | None = None
        self.velocity = np.eye(4)
        # The interval ``velocity`` was measured over, and this frame's (seconds): a live
        # camera drops frames, so the next frame may come one or more periods later
        # than the one the motion was measured on (or sooner, after such a gap).
        self.vel_dt_s: float | None = None
        self.dt_s: float | None = None
        self.last_stamp: int | None = None
        self.dt_ratio = 1.0  # this frame's interval / the nominal one
        self.depth = 1.0  # median depth of the points tracked last (VO units)
        self.rejected_jumps = 0  # PnP poses refused as implausible
        self.relocalized = 0
        self.frames_since_kf = 0
        self.kf_inliers = 0
        self.lost_frames = 0
        self.foreign: OrderedDict[int, tuple[str, int]] = OrderedDict()  # local id -> key
        self.foreign_by_key: dict[tuple[str, int], int] = {}
        # Local BA off the tracking path (see _local_ba); None: inline, deterministic.
        self.ba_worker: BAWorker | None = None
        self._ba_wanted = False
        self.ba_aborted = 0  # local BAs asked to end early for a newer keyframe
        # (keyframes, map points) each applied local BA moved, for the agent to send.
        self.ba_applied: list[tuple[list[int], list[int]]] = []

    # --- public -----------------------------------------------------------------------------
    def track(self, img: np.ndarray | None, stamp_ns: int,
              features: Features | None = None) -> FrameResult:  # fmt: skip
        """Track one image, or its ``features`` when they were extracted already (the
        live agent extracts on its camera thread, while the previous frame is tracked)."""
        t0 = time.perf_counter()
        self.dt_s = None
        if self.last_stamp is not None and stamp_ns > self.last_stamp:
            dt = self.dt_s = (stamp_ns - self.last_stamp) * 1e-9
            self.dt_ratio = float(np.clip(dt / self.p.nominal_dt_s, self.p.dt_ratio_min,
                                          self.p.dt_ratio_max))  # fmt: skip
        self.last_stamp = stamp_ns
        f = self.extract(img) if features is None else features
        step = self._initialize if self.state == "init" else self._track
        res = step(f, stamp_ns)
        res.track_s = time.perf_counter() - t0 - res.map_s
        return res

    @property
    def last_kf(self) -> KeyFrame:
        return self.kfs[max(self.kfs)]

    # --- initialization ---------------------------------------------------------------------
    def _initialize(self, f: Features, stamp: int) -> FrameResult:
        p = self.p
        if (self.init_ref is None or self.init_age > p.init_max_age_frames
                or len(self.init_ref[1]) < p.init_min_features):  # fmt: skip
            self.init_ref = (stamp, f)
            self.init_age = 0
            return FrameResult(stamp, None, "init")
        self.init_age += 1
        s0, f0 = self.init_ref
        a, b = match_descriptors(f0.desc, f.desc, ratio=p.init_match_ratio,
                                max_dist=p.init_match_max_dist)  # fmt: skip
        if len(a) < p.init_min_matches:
            return FrameResult(stamp, None, "init")
        tv = two_view_init(f0.xy[a], f.xy[b], self.cam.fx, min_inliers=p.init_min_inliers,
                           min_parallax_deg=p.init_min_parallax_deg)  # fmt: skip
        if not tv.ok:
            return FrameResult(stamp, None, "init")
        g = tv.good
        depth = np.median(tv.points[g, 2])
        s = 1.0 / depth  # median scene depth 1, as ORB-SLAM
        T1 = tv.T_c1_c2.copy()
        T1[:3, 3] *= s
        kf0 = self._new_kf(s0, np.eye(4), f0)
        kf1 = self._new_kf(stamp, T1, f)
        new = []
        for i in np.nonzero(g)[0]:
            mp = self._new_mp(tv.points[i] * s, f.desc[b[i]], kf0.id)
            self._observe(kf0, int(a[i]), mp)
            self._observe(kf1, int(b[i]), mp)
            new.append(mp.id)
        t = time.perf_counter()
        if self.p.ba:
            self._local_ba(kf1, inline=True)
        self.state = "ok"
        self.T_last = kf1.T_w_c
        self.velocity = se3_inv(kf0.T_w_c) @ kf1.T_w_c
        self.kf_inliers = len(new)
        self.frames_since_kf = 0
        r = FrameResult(stamp, kf1.T_w_c.copy(), "ok", len(new), kf1, new)
        r.map_s = time.perf_counter() - t
        self.init_kf0 = kf0
        return r

    # --- tracking ---------------------------------------------------------------------------
    def _local_points(self, with_foreign: bool = False) -> np.ndarray:
        """Points of the newest ``local_kfs`` keyframes (and the server's, if asked)."""
        ids = sorted(self.kfs)[-self.p.local_kfs :]
        pts = set(self.foreign) if with_foreign else set()
        for k in ids:
            m = self.kfs[k].mp
            pts.update(m[m >= 0].tolist())
        return np.array(sorted(p for p in pts if p in self.mps), np.int64)

    def add_foreign_points(self, keys: list[tuple[str, int]], pos: np.ndarray,
                           desc: np.ndarray, max_points: int | None = None) -> int:  # fmt: skip
        """Map points the server sent (CCM-SLAM §4.5): searched while tracking like
        the agent's own, never sent back, the oldest forgotten past ``max_points``."""
        max_points = self.p.foreign_max_points if max_points is None else max_points
        n = 0
        for key, p, d in zip(keys, pos, desc, strict=True):
            local = self.foreign_by_key.get(key)
            if local is not None and local in self.mps:
                self.mps[local].pos = np.asarray(p, float)  # the server's latest estimate
                self.foreign.move_to_end(local)
                continue
            mp = self._new_mp(p, d, max(self.kfs, default=0), foreign=True)
            self.foreign[mp.id] = key
            self.foreign_by_key[key] = mp.id
            n += 1
        while len(self.foreign) > max_points:
            old, key = self.foreign.popitem(last=False)
            self.foreign_by_key.pop(key, None)
            if old in self.mps:
                self._remove_mp(old)
        return n

    def _points(self, pids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions and descriptors of ``pids``, gathered once per frame."""
        mps = self.mps
        P = np.array([mps[i].pos for i in pids.tolist()]).reshape(-1, 3)
        D = np.array([mps[i].desc for i in pids.tolist()], np.uint8).reshape(-1, 32)
        return P, D

    def _search(self, f: Features, T: np.ndarray, P: np.ndarray, D: np.ndarray, radius: float):
        Xc = (P - T[:3, 3]) @ T[:3, :3]
        uv, ok = self.cam.project(Xc, min_depth=self.p.min_depth)
        if not ok.any():
            return np.zeros(0, int), np.zeros(0, int), ok
        sel = np.nonzero(ok)[0]
        pi, kp = match_by_projection(f, uv[sel], D[sel], radius)
        return sel[pi], kp, ok

    def _predict(self, f: Features, T_pred: np.ndarray, P: np.ndarray, D: np.ndarray):
        """First pose from the motion model: projection search, widened once.

        The window grows with the frame interval (a 10 Hz camera moves twice as far
        between frames). In the wide window the guess is too far off for the guided
        solver, whose first outlier cut (16 px) is narrower than the window: there
        RANSAC decides, and the result must then agree with the motion model."""
        r0 = self.p.search_radius * max(1.0, self.dt_ratio)
        pi, kp, _ = self._search(f, T_pred, P, D, r0)
        if len(pi) >= self.p.min_inliers:
            r = solve_pnp(P[pi], f.xy[kp], self.cam.fx, T_guess=T_pred)
            if r.ok and r.inliers.sum() >= self.p.min_inliers:
                return r, pi, kp
        # Wide: around the prediction, then around the last pose (a sudden stop).
        for T0, how in ((T_pred, "wide"), (self.T_last, "still")):
            pi, kp, _ = self._search(f, T0, P, D, self.p.search_widen * r0)
            if len(pi) < self.p.min_inliers:
                continue
            r = solve_pnp(P[pi], f.xy[kp], self.cam.fx)
            if r.ok and r.inliers.sum() >= self.p.min_inliers and self._plausible(r, T_pred):
                r2 = solve_pnp(P[pi], f.xy[kp], self.cam.fx, T_guess=r.T_w_c)
                if r2.ok and r2.inliers.sum() >= r.inliers.sum() * self.p.refine_keep_ratio:
                    r = r2
                r.how = how
                return r, pi, kp
        return None, None, None

    def _motion(self) -> np.ndarray:
        """The constant-velocity step to this frame: the last measured motion, scaled to
        this frame's interval when that differs from the one it was measured over by
        a frame or more (a frame the camera dropped; a regular rate's jitter is left
        alone, so a camera that drops nothing predicts exactly as before). Unscaled, the
        frame after a dropped one was predicted a whole period of motion off, and the
        frame after that a period short."""
        if self.vel_dt_s is None or self.dt_s is None:
            return self.velocity
        a = self.dt_s / self.vel_dt_s
        if self.p.dt_jitter_max_ratio**-1 < a < self.p.dt_jitter_max_ratio:
            return self.velocity
        return _damp(self.velocity, a)

    def _plausible(self, r, T_pred: np.ndarray) -> bool:
        """Could the camera be there? A drone does not teleport: the pose must lie near
        the motion model's prediction, the more loosely the longer tracking was lost,
        unless so many points support it that it cannot be a wrong solution."""
        if int(r.inliers.sum()) >= self.p.strong_inliers:
            return True
        grow = 1.0 + self.lost_frames
        v = float(np.linalg.norm(self.velocity[:3, 3]))
        dt = float(np.linalg.norm(r.T_w_c[:3, 3] - T_pred[:3, 3]))
        bound = (self.p.jump_depth_share * self.depth + self.p.jump_motion_factor * v) * grow
        ang = np.rad2deg(np.linalg.norm(log_so3(T_pred[:3, :3].T @ r.T_w_c[:3, :3])))
        ok = dt <= bound and ang <= self.p.jump_rot_deg * grow
        if not ok:
            self.rejected_jumps += 1
        return ok

    def _track(self, f: Features, stamp: int) -> FrameResult:
        # The agent's own points first. The server's sit in this frame through a fitted
        # similarity and are less accurate locally than the VO's own map (measured: the
        # server map's newest keyframes carry 6-8 mm of local error where the VO has
        # 4 mm), so they join only where the agent's own map is thin: another agent's
        # place, or after the agent lost track. Where its own points suffice, tracking
        # is what it would be without a server; the server helps there by correcting the
        # drift of the reported pose (S_g_l in the runner).
        pids = self._local_points()
        P, D = self._points(pids)
        T_pred = self.T_last @ self._motion()
        res, pi, kp = self._predict(f, T_pred, P, D)
        # Few own inliers in the first pass need not mean a thin map: the prediction may
        # just have been poor (a sudden turn at 10 Hz), so the wide search's RANSAC found
        # only some of the points. Refined, the own points may be plenty, and then the
        # server's do not join (their coherent offset would pull the pose: seen on MH05
        # at every=3, a 0.17 m spike on the one frame where 41 own inliers let them in).
        seen = None
        if self.foreign and res is not None and res.inliers.sum() < self._strong:
            res, pi, kp, seen = self._refine(f, res, pi, kp, P, D)
        weak = res is None or res.inliers.sum() < self._strong
        if weak and self.foreign:
            ids = self._local_points(with_foreign=True)
            P2, D2 = self._points(ids)
            r2, pi2, kp2 = self._predict(f, T_pred, P2, D2)
            # The server's points never move the pose where the motion model says the
            # camera cannot be (a badly placed chunk must not destabilize tracking).
            if (r2 is not None and (res is None or r2.inliers.sum() > res.inliers.sum())
                    and self._plausible(r2, T_pred if res is None else res.T_w_c)):  # fmt: skip
                res, pi, kp, pids, P, D = r2, pi2, kp2, ids, P2, D2
                seen = None
        was_lost = self.state == "lost"
        if res is None:
            res, pi, kp, P = self._relocalize(f, pids, T_pred)
            if res is None:
                self.lost_frames += 1
                self.state = "lost"
                # Keep predicting so the reported pose continues: a drone keeps its
                # velocity for a while (inertia), but a constant-velocity guess held
                # for seconds flies off (it was reported, and searched around, metres
                # from the camera), so past ``coast_s`` the velocity dies away.
                if self.lost_frames * self.dt_ratio * self.p.nominal_dt_s > self.p.coast_s:
                    self.velocity = _damp(self.velocity, self.p.coast_damping)
                self.T_last = T_pred
                return FrameResult(stamp, T_pred.copy(), "lost", T_pred=T_pred.copy(),
                                   how="lost")  # fmt: skip
            self.relocalized += 1
            seen = None
        if seen is None:  # not refined yet
            res, pi, kp, seen = self._refine(f, res, pi, kp, P, D)
        res, pi, kp = self._gate_foreign(f, res, pids, pi, kp, P)
        for i in pids[seen].tolist():
            self.mps[i].visible += 1
        inl = res.inliers
        for i in pids[pi[inl]].tolist():
            self.mps[i].found += 1
        self.state = "ok"
        T = res.T_w_c
        # After a loss the last pose is a prediction: no velocity from it.
        self.velocity = np.eye(4) if was_lost else se3_inv(self.T_last) @ T
        self.vel_dt_s = None if was_lost else self.dt_s
        self.lost_frames = 0
        self.T_last = T
        self.frames_since_kf += 1
        n_in = int(inl.sum())
        Xc = (P[pi[inl]] - T[:3, 3]) @ T[:3, :3]
        if len(Xc):
            self.depth = float(np.median(Xc[:, 2]))
        out = FrameResult(stamp, T.copy(), "ok", n_in, T_pred=T_pred.copy(),
                          how=getattr(res, "how", "predict"))  # fmt: skip
        if self._need_kf(n_in):
            t = time.perf_counter()
            kf = self._new_kf(stamp, T, f)
            for i, k in zip(pids[pi[inl]].tolist(), kp[inl].tolist(), strict=True):
                if k not in kf.f_taken:
                    self._observe(kf, k, self.mps[i])
            out.new_points = self._triangulate(kf)
            if self.p.ba:
                self._local_ba(kf)
            self._cull_points(kf)
            self.T_last = kf.T_w_c
            out.T_w_c = kf.T_w_c.copy()
            out.keyframe = kf
            self.kf_inliers = n_in
            self.frames_since_kf = 0
            out.map_s = time.perf_counter() - t
        return out

    def _refine(self, f: Features, res, pi, kp, P: np.ndarray, D: np.ndarray):
        """Second pass: with the refined pose, a tighter search finds more points."""
        pi2, kp2, seen = self._search(f, res.T_w_c, P, D, self.p.refine_radius)
        if len(pi2) >= self.p.min_inliers:
            r2 = solve_pnp(P[pi2], f.xy[kp2], self.cam.fx, T_guess=res.T_w_c)
            if r2.ok and r2.inliers.sum() >= res.inliers.sum() * self.p.refine_keep_ratio:
                return r2, pi2, kp2, seen
        return res, pi, kp, seen

    def _gate_foreign(self, f: Features, res, pids, pi, kp, P):
        """Server points count only where they agree with the agent's own. They sit in
        the agent's frame through KF_ref and a fitted similarity, so where the two maps
        still differ (before a correction reaches both, or past the fit's reach) they are
        off coherently, and RANSAC would keep them as inliers of a compromise pose. With
        enough own matches the pose comes from those, and a server point stays only if it
        reprojects within ``foreign_gate_px`` there; with few own matches (a place only
        another agent mapped) all are used, which is where the server's map helps."""
        if not self.foreign or not len(pi):
            return res, pi, kp
        fr = np.fromiter((i in self.foreign for i in pids[pi].tolist()), bool, count=len(pi))
        own = ~fr
        if not fr.any() or own.sum() < self._strong:
            return res, pi, kp
        r_own = solve_pnp(P[pi[own]], f.xy[kp[own]], self.cam.fx, T_guess=res.T_w_c)
        if not r_own.ok or r_own.inliers.sum() < self._strong:
            return res, pi, kp
        T = r_own.T_w_c
        Xc = (P[pi[fr]] - T[:3, 3]) @ T[:3, :3]
        z = np.maximum(Xc[:, 2], 1e-6)
        err = np.linalg.norm(Xc[:, :2] / z[:, None] - f.xy[kp[fr]], axis=1) * self.cam.fx
        keep = own.copy()
        keep[np.nonzero(fr)[0][err < self.p.foreign_gate_px]] = True
        if keep.all():
            return res, pi, kp
        pi, kp = pi[keep], kp[keep]
        r = solve_pnp(P[pi], f.xy[kp], self.cam.fx, T_guess=T)
        if r.ok and r.inliers.sum() >= self.p.min_inliers:
            return r, pi, kp
        return r_own, pi[own[keep]], kp[own[keep]]

    def _need_kf(self, n_in: int) -> bool:
        # Counted in nominal frames: at 10 Hz a frame is two of them, so the map keeps
        # the same keyframes per second of flight.
        n = self.frames_since_kf * self.dt_ratio
        # Few points tracked: the camera is leaving the map (fast flight into new
        # space), so a keyframe now, while there are still enough to place it.
        if n_in < self.p.min_inliers * self.p.kf_thin_factor:
            return True
        if n < self.p.kf_min_frames:
            return False
        return n >= self.p.kf_max_frames or n_in < self.p.kf_inlier_ratio * self.kf_inliers

    def _relocalize(self, f: Features, pids: np.ndarray, T_pred: np.ndarray):
        """Brute-force matching against keyframes of the local map (nearest the last
        pose first), PnP with RANSAC, then the motion-model check."""
        c = self.T_last[:3, 3]
        near = sorted(self.kfs, key=lambda k: (np.linalg.norm(self.kfs[k].T_w_c[:3, 3] - c), -k))
        for k in near[: self.p.reloc_kfs]:
            kf = self.kfs[k]
            has = np.nonzero(kf.mp >= 0)[0]
            if len(has) < self.p.reloc_min_matches:
                continue
            a, b = match_descriptors(kf.f.desc[has], f.desc, ratio=self.p.reloc_match_ratio)
            if len(a) < self.p.reloc_min_matches:
                continue
            mp_ids = kf.mp[has[a]]
            P = np.array([self.mps[i].pos for i in mp_ids.tolist()])
            r = solve_pnp(P, f.xy[b], self.cam.fx)
            if r.ok and r.inliers.sum() >= self.p.min_inliers and self._plausible(r, T_pred):
                r.how = "reloc"
                idx = np.searchsorted(pids, mp_ids)
                idx = np.clip(idx, 0, max(len(pids) - 1, 0))
                Pall = np.array([self.mps[i].pos for i in pids.tolist()]).reshape(-1, 3)
                keep = (
                    (len(pids) > 0) & (pids[idx] == mp_ids)
                    if len(pids)
                    else np.zeros(len(mp_ids), bool)
                )
                r2 = solve_pnp(P, f.xy[b], self.cam.fx, T_guess=r.T_w_c)
                if r2.ok:
                    r2.how = "reloc"
                    r = r2
                r.inliers = r.inliers & keep
                return r, idx, b, Pall
        return None, None, None, None

    # --- mapping ----------------------------------------------------------------------------
    def _new_kf(self, stamp: int, T: np.ndarray, f: Features) -> KeyFrame:
        kf = KeyFrame(self.next_kf, stamp, T.copy(), f, np.full(len(f), -1, np.int64))
        kf.f_taken = set()
        self.kfs[kf.id] = kf
        self.next_kf += 1
        return kf

    def _new_mp(self, pos: np.ndarray, desc: np.ndarray, kf_id: int,
                foreign: bool = False) -> MapPoint:  # fmt: skip
        i = self.next_foreign_mp if foreign else self.next_mp
        mp = MapPoint(i, np.asarray(pos, float), desc.copy(), first_kf=kf_id)
        self.mps[mp.id] = mp
        if foreign:
            self.next_foreign_mp += 1
        else:
            self.next_mp += 1
        return mp

    def _observe(self, kf: KeyFrame, k: int, mp: MapPoint) -> None:
        kf.mp[k] = mp.id
        kf.f_taken.add(k)
        mp.obs[kf.id] = k

    def _triangulate(self, kf: KeyFrame) -> list[int]:
        p = self.p
        new = []
        free_new = np.nonzero(kf.mp < 0)[0]
        for k in sorted(self.kfs, reverse=True)[1 : 1 + p.tri_kfs]:
            old = self.kfs[k]
            free_old = np.nonzero(old.mp < 0)[0]
            if len(free_old) < p.tri_min_free or len(free_new) < p.tri_min_free:
                continue
            a, b = match_descriptors(old.f.desc[free_old], kf.f.desc[free_new],
                                     ratio=p.tri_match_ratio,
                                     max_dist=p.tri_match_max_dist)  # fmt: skip
            if len(a) < p.tri_min_matches:
                continue
            ia, ib = free_old[a], free_new[b]
            tri = triangulate(old.T_w_c, kf.T_w_c, old.f.xy[ia], kf.f.xy[ib], self.cam.fx,
                              max_err_px=p.tri_max_err_px,
                              min_parallax_deg=p.tri_min_parallax_deg)  # fmt: skip
            for j in np.nonzero(tri.good)[0].tolist():
                if kf.mp[ib[j]] >= 0 or old.mp[ia[j]] >= 0:
                    continue
                mp = self._new_mp(tri.points[j], kf.f.desc[ib[j]], kf.id)
                self._observe(old, int(ia[j]), mp)
                self._observe(kf, int(ib[j]), mp)
                new.append(mp.id)
            free_new = np.nonzero(kf.mp < 0)[0]
        return new

    def _cull_points(self, kf: KeyFrame) -> None:
        for i in list(self.mps):
            if i in self.foreign:
                continue  # the server's points are judged by the server
            mp = self.mps[i]
            age = kf.id - mp.first_kf
            rarely = mp.found / max(mp.visible, 1) < self.p.cull_min_found_ratio
            if age >= self.p.cull_min_age_kfs and (rarely or len(mp.obs) < 2):
                self._remove_mp(i)

    def _remove_mp(self, i: int) -> None:
        mp = self.mps.pop(i)
        for k, j in mp.obs.items():
            kf = self.kfs.get(k)
            if kf is not None and kf.mp[j] == i:
                kf.mp[j] = -1

    def _local_ba(self, kf: KeyFrame, inline: bool = False) -> None:
        """Local BA of the newest window, in this thread or, with a ``ba_worker``, in
        its process (the tracking path goes on meanwhile; :meth:`poll_mapping` applies
        the result). A keyframe that comes while a BA runs asks for one more run."""
        if self.ba_worker is None or inline:
            job = self._ba_job()
            if job is not None:
                self._apply_ba(local_ba(**job))
            return
        if self.ba_worker.busy:
            # The running BA ends after its current iteration and the new keyframe's
            # starts at once (ORB-SLAM aborts local BA when tracking inserts a
            # keyframe): where a BA takes longer than keyframes come, the newest
            # keyframe's points would otherwise wait a whole BA more to be refined.
            if not self._ba_wanted:
                self.ba_aborted += 1
            self._ba_wanted = True
            self.ba_worker.abort()
            return
        job = self._ba_job()
        if job is not None:
            self.ba_worker.submit(job)

    def poll_mapping(self, wait: bool = False) -> bool:
        """Apply a local BA the worker finished (waiting for it with ``wait``); start
        the one a keyframe asked for meanwhile. True if a result was applied."""
        if self.ba_worker is None:
            return False
        r = self.ba_worker.result(wait)
        if r is None:
            return False
        self._apply_ba(r)
        if self._ba_wanted and self.kfs:
            self._ba_wanted = False
            self._local_ba(self.last_kf)
        return True

    def _ba_job(self) -> dict | None:
        win = sorted(self.kfs)[-self.p.window :]
        pts = set()
        for k in win:
            m = self.kfs[k].mp
            pts.update(m[m >= 0].tolist())
        pts = {i for i in pts if i in self.mps}
        obs = []
        fixed = set(win[:2]) if len(win) > 2 else {win[0]}
        kf_ids = set(win)
        for i in pts:
            mp = self.mps[i]
            for k, j in mp.obs.items():
                if k in self.kfs:
                    obs.append((k, i, self.kfs[k].f.xy[j]))
                    if k not in kf_ids:
                        kf_ids.add(k)
                        fixed.add(k)
        if len(pts) < self.p.ba_min_points:
            return None
        return {
            "poses": {k: self.kfs[k].T_w_c.copy() for k in kf_ids}, "fixed": fixed,
            "points": {i: self.mps[i].pos.copy() for i in pts}, "obs": obs,
            "focal": self.cam.fx, "max_iters": self.p.ba_max_iters,
        }  # fmt: skip

    def _apply_ba(self, r: BAResult) -> None:
        """A BA run in the background may come back after trimming or culling removed
        some of its keyframes and points: those are skipped.

        Tracking went on while it ran, against the window as it was. So what came since
        it was handed the window -- the last tracked pose, keyframes made meanwhile and
        the points they added -- moves rigidly with the window's newest keyframe
        (ORB-SLAM's UpdateLastFrame): left where they were, the next frame would be
        predicted from a pose the moved map no longer agrees with (the difference
        taken for motion: a velocity spike), and the points of a keyframe made
        meanwhile would sit apart from the moved ones they are tracked with."""
        moved_kfs = [k for k in r.poses if k in self.kfs]
        if moved_kfs:
            newest = max(moved_kfs)
            delta = r.poses[newest] @ se3_inv(self.kfs[newest].T_w_c)
            self._move_since(newest, delta, set(r.points))
        for k in moved_kfs:
            self.kfs[k].T_w_c = r.poses[k]
        moved_mps = [i for i in r.points if i in self.mps]
        for i in moved_mps:
            self.mps[i].pos = r.points[i]
        for k, i in r.outliers:
            mp = self.mps.get(i)
            if mp is not None and k in mp.obs:
                j = mp.obs.pop(k)
                kf = self.kfs.get(k)
                if kf is not None and kf.mp[j] == i:
                    kf.mp[j] = -1
        self.ba_applied.append((moved_kfs, moved_mps))

    def _move_since(self, newest: int, delta: np.ndarray, in_ba: set[int]) -> None:
        """Apply ``delta`` (world -> world) to the last tracked pose and to keyframes
        newer than ``newest`` with the points they added (not the ones BA placed). Moved
        rigidly with ``newest``, they keep their poses relative to it, so the agent's
        update of the window (``ba_applied``) tells the server all there is."""
        if self.T_last is not None:
            self.T_last = delta @ self.T_last
        later = [k for k in self.kfs if k > newest]
        for k in later:
            self.kfs[k].T_w_c = delta @ self.kfs[k].T_w_c
        if not later:
            return
        R, t = delta[:3, :3], delta[:3, 3]
        for i, mp in self.mps.items():
            if mp.first_kf > newest and i not in in_ba and i not in self.foreign:
                mp.pos = R @ mp.pos + t


def _damp(T: np.ndarray, a: float) -> np.ndarray:
    """The motion ``T`` scaled by ``a`` (rotation angle and translation): a share of it
    (damping), or a longer step (``a`` > 1)."""
    out = np.eye(4)
    out[:3, :3] = exp_so3(a * log_so3(T[:3, :3]))
    out[:3, 3] = a * T[:3, 3]
    return out


def remove_keyframe(vo: VisualOdometry, kf_id: int) -> list[int]:
    """Drop a keyframe from the local map (trimming); returns map points left with no
    observation, which are removed too."""
    kf = vo.kfs.pop(kf_id, None)
    if kf is None:
        return []
    dead = []
    for j in np.nonzero(kf.mp >= 0)[0].tolist():
        mp = vo.mps.get(int(kf.mp[j]))
        if mp is None:
            continue
        mp.obs.pop(kf_id, None)
        if not mp.obs:
            del vo.mps[mp.id]
            dead.append(mp.id)
    return dead


def keyframe_observed(kf: KeyFrame) -> int:
    return int((kf.mp >= 0).sum())


__all__ = ["VisualOdometry", "VOParams", "FrameResult", "KeyFrame", "MapPoint", "hamming",
           "keyframe_observed", "remove_keyframe"]  # fmt: skip
