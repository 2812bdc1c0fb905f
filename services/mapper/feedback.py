"""Map data sent back to an agent (CCM-SLAM §4.5): the k keyframes most covisible with
its KF_ref and their map points, relative to KF_ref and in the agent's local scale.

Keypoints and descriptors of a keyframe go to an agent once; later chunks carry only
its pose, which keeps the down-link small.
"""

from __future__ import annotations

import numpy as np

from shared.geometry import se3_inv
from shared.messages import MapChunk

from .registration import AgentHandler

# The agent tracks against the points of its newest 10 keyframes (VOParams.local_kfs);
# a margin covers keyframes in flight.
RECENT_KFS = 15
MIN_SPREAD = 0.01  # of the scene depth: the centres' spread that fixes a scale


def map_to_agent_ref(
    h: AgentHandler, ref, lo: int, hi: int
) -> tuple[np.ndarray, np.ndarray, float]:
    """(R, t, s) with ``p_ref = s R p_m + t``: map coordinates into KF_ref's camera frame
    in the agent's local units.

    Fitted on the agent's own newest keyframes, whose poses the server holds both in the
    map (``T_m_kf``) and as the agent sent them (``T_l_kf``): rotation by chordal mean,
    scale from the spread of their centres. Around KF_ref this is the agent's frame as
    its tracking sees it; the handler's global scale (a filtered VO/map ratio) and
    KF_ref's map pose alone are each off by the map's local corrections. Without enough
    baseline among them, those are used."""
    smap = h.smap
    kfs = [smap.kfs[g] for g in range(lo, hi + 1) if g in smap.kfs]
    T_l_ref = ref.T_l_kf
    if len(kfs) >= 4:
        M = sum(k.T_l_kf[:3, :3] @ k.T_m_kf[:3, :3].T for k in kfs)
        U, _, Vt = np.linalg.svd(M)
        R_lm = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
        c_m = np.array([k.T_m_kf[:3, 3] for k in kfs])
        c_l = np.array([k.T_l_kf[:3, 3] for k in kfs])
        d_m = np.linalg.norm((c_m - c_m.mean(0)) @ R_lm.T, axis=1).sum()
        d_l = np.linalg.norm(c_l - c_l.mean(0), axis=1).sum()
        obs = ref.mp[ref.mp >= 0][:200].tolist()
        depth = np.median([np.linalg.norm(smap.mps[g].pos - ref.T_m_kf[:3, 3])
                           for g in obs if g in smap.mps] or [np.inf])  # fmt: skip
        s_lm = d_l / d_m if d_m > 1e-12 else 0.0
        # Enough baseline (mean spread >= MIN_SPREAD of the scene depth), and no more than
        # 20 % from the handler's scale (anything further is a broken fit, not drift).
        if d_m / len(kfs) >= MIN_SPREAD * depth and abs(s_lm * h.scale - 1.0) < 0.2:
            t_lm = c_l.mean(0) - s_lm * R_lm @ c_m.mean(0)
            # p_ref = T_ref_l (s R_lm p_m + t_lm)
            R_rl, t_rl = T_l_ref[:3, :3].T, -T_l_ref[:3, :3].T @ T_l_ref[:3, 3]
            return R_rl @ R_lm, R_rl @ t_lm + t_rl, float(s_lm)
    T_ref_m = se3_inv(ref.T_m_kf)
    inv_s = 1.0 / h.scale
    return T_ref_m[:3, :3], T_ref_m[:3, 3] * inv_s, inv_s


def _pose_in(R: np.ndarray, t: np.ndarray, s: float, T_m_kf: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R @ T_m_kf[:3, :3]
    T[:3, 3] = s * R @ T_m_kf[:3, 3] + t
    return T


def build_chunk(
    h: AgentHandler, k: int, sent: set[int], now_ns: int, names: dict[int, str]
) -> MapChunk | None:
    smap = h.smap
    ref_g = h.kf_gid(h.kf_ref) if h.kf_ref >= 0 else -1
    ref = smap.kfs.get(ref_g)
    if ref is None:
        return None
    # The agent's own newest keyframes are always the most covisible with its KF_ref,
    # and it holds them: the k sent are the most covisible of the others (another
    # agent's keyframes here, or its own from an earlier pass).
    lo, hi = h.kf_gid(max(h.latest_kf - RECENT_KFS, 0)), h.kf_gid(max(h.latest_kf, 0))
    neigh = [g for g in smap.covisible(ref_g, min_weight=1) if not lo <= g <= hi][:k]
    if not neigh:
        return None
    R_a, t_a, s_a = map_to_agent_ref(h, ref, lo, hi)
    kfs = [smap.kfs[g] for g in neigh]
    # Points in order of first appearance over the keyframes, found with numpy (this
    # runs at 2 Hz per agent on the map actor; per-keypoint Python loops cost ~10 ms).
    allmp = np.concatenate([kf.mp for kf in kfs])
    allmp = allmp[allmp >= 0]
    # Points the agent's own newest keyframes observe are in its tracking map already
    # (its own, or another agent's it associated): a second copy at the server's slightly
    # different position would compete with the first for the same keypoints. The rest
    # (other agents' points, places it saw long ago) is what the agent lacks.
    mine = [smap.kfs[g].mp for g in range(lo, hi + 1) if g in smap.kfs]
    if mine:
        allmp = allmp[~np.isin(allmp, np.concatenate(mine))]
    uniq, first = np.unique(allmp, return_index=True)
    order = np.argsort(first, kind="stable")
    mp_gids = uniq[order]
    rank = np.empty(len(uniq), np.int64)
    rank[order] = np.arange(len(uniq))
    pts = [smap.mps[g] for g in mp_gids.tolist()]
    pos = np.concatenate([p.pos for p in pts]).reshape(-1, 3) if pts else np.zeros((0, 3))
    p_ref = s_a * pos @ R_a.T + t_a
    kp, desc, idx = [], [], []
    for kf in kfs:
        if kf.gid in sent:
            kp.append(np.zeros((0, 2), np.float32))
            desc.append(np.zeros((0, 32), np.uint8))
            idx.append(np.zeros(0, np.int64))
        else:
            kp.append(kf.keypoints.astype(np.float32))
            desc.append(kf.descriptors.astype(np.uint8))
            i = np.full(len(kf.mp), -1, np.int64)
            pos = np.searchsorted(uniq, kf.mp)
            has = (kf.mp >= 0) & (pos < len(uniq))
            has[has] &= uniq[pos[has]] == kf.mp[has]
            i[has] = rank[pos[has]]
            idx.append(i)
            sent.add(kf.gid)
    # Agent of each point from its gid's high bits, looked up once per agent.
    ai, inv = np.unique(mp_gids >> 40, return_inverse=True)
    lut = np.array([names.get(int(a), "") for a in ai.tolist()], dtype=object)
    mp_agents = lut[inv].tolist() if len(mp_gids) else []
    return MapChunk(
        agent=h.agent, map_id=smap.map_id, kf_ref=h.kf_ref,
        kf_agents=[kf.agent for kf in kfs],
        kf_ids=np.array([kf.id for kf in kfs], np.int64),
        T_ref_kf=np.stack([_pose_in(R_a, t_a, s_a, kf.T_m_kf) for kf in kfs]),
        kf_keypoints=kp, kf_descriptors=desc, kf_mp_index=idx,
        # Point ids are agent-local: the agent index (high bits) names their agent.
        mp_agents=mp_agents,
        mp_ids=mp_gids & ((1 << 40) - 1),
        p_ref=p_ref.astype(np.float64),
        mp_descriptors=(np.concatenate([p.descriptor for p in pts]) if pts
                        else np.zeros(0, np.uint8)).astype(np.uint8).reshape(-1, 32),
        sent_ns=now_ns,
    )  # fmt: skip
