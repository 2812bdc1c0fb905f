"""Registration of an agent's keyframes and map points into its server map.

Pure bookkeeping and geometry, no transport or storage: the service feeds
decoded batches in and writes out what :meth:`AgentHandler.ingest` returns.

A keyframe is placed by chaining its pose relative to its predecessor, or to its
covisibility parent when the predecessor is not on the server (CCM-SLAM §4.5).
Relative translations are in the agent's local-map units, so they are scaled by
the handler's Sim(3) S_m_l. A keyframe whose predecessor and parent are both
missing waits until one of them arrives (it is not acknowledged meanwhile, so the
agent resends it). When both were lost for good (the agent's buffer overflowed,
CCM-SLAM §4.2), waiting would orphan every later keyframe too; after
``orphan_after_s`` the keyframe is anchored instead to the registered keyframe
nearest in id, through the agent's own local-map poses.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from shared.geometry import Sim3, scale_translation, transform_points
from shared.messages import KeyframeBatch, KeyframeUpdate, MapPoints, NewKeyframe
from shared.store import StoredKeyframe


@dataclass
class IngestResult:
    keyframes: list[StoredKeyframe] = field(default_factory=list)
    pose_updates: list[tuple[int, np.ndarray, KeyframeUpdate]] = field(default_factory=list)
    mp_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    mp_ref: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    mp_p_ref: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    mp_pos: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    mp_desc: np.ndarray = field(default_factory=lambda: np.zeros((0, 32), np.uint8))
    upd_mp_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    upd_mp_ref: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    upd_mp_p_ref: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    upd_mp_pos: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    ack_kf_ids: list[int] = field(default_factory=list)
    ack_mp_ids: list[int] = field(default_factory=list)
    duplicates: int = 0
    pending_kfs: int = 0
    orphans_anchored: int = 0

    @property
    def changed(self) -> bool:
        return bool(self.keyframes or self.pose_updates or len(self.mp_ids) or len(self.upd_mp_ids))


class AgentHandler:
    """One agent's view of its server map: T_m_kf of each keyframe and S_m_l."""

    def __init__(
        self, agent: str, map_id: str, S_m_l: Sim3 | None = None, orphan_after_s: float = 5.0
    ) -> None:
        self.agent = agent
        self.orphan_after_s = orphan_after_s
        self.local_poses: dict[int, np.ndarray] = {}  # kf id -> T_l_kf as the agent sent it
        self.pending_since: dict[int, float] = {}
        self.map_id = map_id
        self.S_m_l = S_m_l or Sim3.identity()
        self.poses: dict[int, np.ndarray] = {}  # kf id -> T_m_kf
        self.mp_ids: set[int] = set()
        self.pending_kfs: dict[int, NewKeyframe] = {}
        self.pending_mps: dict[int, tuple[int, np.ndarray, np.ndarray]] = {}
        self.kf_ref = -1

    @property
    def kf_high(self) -> int:
        return max(self.poses, default=-1)

    def _place(self, kf_id: int, pred_id: int, T_pred: np.ndarray, par_id: int, T_par: np.ndarray,
               T_l_kf: np.ndarray | None) -> np.ndarray | None:  # fmt: skip
        s = self.S_m_l.s
        if pred_id in self.poses:
            return self.poses[pred_id] @ scale_translation(T_pred, s)
        if par_id in self.poses:
            return self.poses[par_id] @ scale_translation(T_par, s)
        if pred_id < 0 and par_id < 0 and T_l_kf is not None and not self.poses:
            # The agent's first keyframe seeds the map through S_m_l.
            return self.S_m_l.transform_pose(T_l_kf)
        return None

    def ingest(self, batch: KeyframeBatch, now: float = 0.0) -> IngestResult:
        res = IngestResult()
        for kf in sorted(batch.new_kfs, key=lambda k: k.id):
            if kf.id in self.poses:
                res.duplicates += 1
                res.ack_kf_ids.append(kf.id)
            else:
                self.pending_kfs[kf.id] = kf
                self.pending_since.setdefault(kf.id, now)
        self._drain_pending_kfs(res, now)
        for upd in batch.kf_updates:
            if upd.id in self.poses:
                T = self._place(
                    upd.id, upd.pred_id, upd.T_pred_kf, upd.parent_id, upd.T_par_kf, None
                )
                if T is not None:
                    self.poses[upd.id] = T
                    res.pose_updates.append((upd.id, T, upd))
            elif upd.id in self.pending_kfs:
                kf = self.pending_kfs[upd.id]
                kf.pred_id, kf.T_pred_kf = upd.pred_id, upd.T_pred_kf
                kf.parent_id, kf.T_par_kf = upd.parent_id, upd.T_par_kf
                if upd.mp_ids is not None:
                    kf.mp_ids = upd.mp_ids
        self._ingest_mps(batch.new_mps, res)
        self._update_mps(batch.mp_updates, res)
        if batch.kf_ref in self.poses:
            self.kf_ref = batch.kf_ref
        res.pending_kfs = len(self.pending_kfs)
        return res

    def _anchor(self, kf: NewKeyframe) -> np.ndarray | None:
        if not self.local_poses:
            return None
        ids = np.fromiter(self.local_poses, dtype=np.int64)
        a = int(ids[np.argmin(np.abs(ids - kf.id))])
        T_a_kf = np.linalg.inv(self.local_poses[a]) @ kf.T_l_kf
        return self.poses[a] @ scale_translation(T_a_kf, self.S_m_l.s)

    def _drain_pending_kfs(self, res: IngestResult, now: float) -> None:
        progress = True
        while progress and self.pending_kfs:
            progress = False
            for kid in sorted(self.pending_kfs):
                kf = self.pending_kfs[kid]
                T = self._place(kid, kf.pred_id, kf.T_pred_kf, kf.parent_id, kf.T_par_kf, kf.T_l_kf)
                if T is None and now - self.pending_since.get(kid, now) > self.orphan_after_s:
                    T = self._anchor(kf)
                    res.orphans_anchored += T is not None
                if T is None:
                    continue
                del self.pending_kfs[kid]
                self.pending_since.pop(kid, None)
                self.poses[kid] = T
                self.local_poses[kid] = kf.T_l_kf
                res.keyframes.append(
                    StoredKeyframe(
                        self.agent, kid, self.map_id, kf.stamp_ns, T, kf.pred_id, kf.parent_id,
                        kf.T_pred_kf, kf.T_par_kf, kf.keypoints, kf.octaves, kf.descriptors,
                        kf.mp_ids, kf.T_l_kf,
                    )
                )  # fmt: skip
                res.ack_kf_ids.append(kid)
                progress = True

    def _mp_positions(self, ref: np.ndarray, p_ref: np.ndarray) -> np.ndarray:
        out = np.empty((len(ref), 3))
        s = self.S_m_l.s
        for r in np.unique(ref):
            sel = ref == r
            out[sel] = transform_points(self.poses[int(r)], s * p_ref[sel])
        return out

    def _ingest_mps(self, mps: MapPoints, res: IngestResult) -> None:
        for j, i in enumerate(mps.ids.tolist()):
            if i in self.mp_ids:
                res.ack_mp_ids.append(i)
            else:
                self.pending_mps[i] = (int(mps.ref_kf[j]), mps.p_ref[j], mps.descriptors[j])
        ready = [i for i, (r, _, _) in self.pending_mps.items() if r in self.poses]
        if not ready:
            return
        ready.sort()
        ref = np.array([self.pending_mps[i][0] for i in ready], np.int64)
        p_ref = np.array([self.pending_mps[i][1] for i in ready], np.float64).reshape(-1, 3)
        desc = np.array([self.pending_mps[i][2] for i in ready], np.uint8).reshape(-1, 32)
        for i in ready:
            del self.pending_mps[i]
        self.mp_ids.update(ready)
        res.mp_ids = np.array(ready, np.int64)
        res.mp_ref, res.mp_p_ref, res.mp_desc = ref, p_ref, desc
        res.mp_pos = self._mp_positions(ref, p_ref)
        res.ack_mp_ids.extend(ready)

    def _update_mps(self, mps: MapPoints, res: IngestResult) -> None:
        if not len(mps):
            return
        known = [
            i in self.mp_ids and r in self.poses
            for i, r in zip(mps.ids.tolist(), mps.ref_kf.tolist(), strict=True)
        ]
        sel = np.array(known, dtype=bool)
        if not sel.any():
            return
        res.upd_mp_ids = mps.ids[sel]
        res.upd_mp_ref = mps.ref_kf[sel]
        res.upd_mp_p_ref = mps.p_ref[sel]
        res.upd_mp_pos = self._mp_positions(res.upd_mp_ref, res.upd_mp_p_ref)

    def pose_of(self, kf_ref: int, T_ref_c: np.ndarray) -> np.ndarray | None:
        """A live camera pose, given relative to one of the agent's keyframes."""
        T = self.poses.get(kf_ref)
        return None if T is None else T @ scale_translation(T_ref_c, self.S_m_l.s)
