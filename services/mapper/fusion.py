"""Duplicate map points: project covisible points into a new keyframe and fuse.

ORB-SLAM's search-by-projection and fuse, vectorized: a k-d tree over the keyframe's
keypoints (scipy) finds the keypoints near each projected point, ``shared.orb.hamming``
gives Hamming distances, and the best match under ``max_hamming`` either adds an
observation (the keypoint had no point) or merges two points that are the same
landmark (typically the agent re-triangulated a place it had trimmed from its
local map, or two agents mapped it).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from shared.camera import PinholeRadTan
from shared.ids import present_in, unique_ids
from shared.orb import hamming

from .server_map import ServerKeyframe, ServerMap


def fuse_by_projection(
    smap: ServerMap,
    kf: ServerKeyframe,
    cam: PinholeRadTan,
    n_neighbours: int = 6,
    radius_px: float = 4.0,
    max_hamming: int = 50,
) -> tuple[int, set[int], set[int], dict[int, int]]:
    """Returns (number of fused or added associations, keyframes whose observations
    changed, removed point gids, aliases dropped -> kept)."""
    changed: set[int] = set()
    removed: set[int] = set()
    aliases: dict[int, int] = {}
    neigh = smap.covisible(kf.gid, n_neighbours, min_weight=1)
    if not neigh or len(kf.keypoints) == 0:
        return 0, changed, removed, aliases
    # Candidates: the neighbours' points this keyframe does not observe yet (sorted),
    # gathered with numpy; this runs for every keyframe, so Python loops stay per point.
    nb = np.concatenate([smap.kfs[n].mp for n in neigh])
    cand = unique_ids(nb[nb >= 0])
    cand = cand[~present_in(cand, kf.mp)]  # sorted, as np.setdiff1d gives them
    if len(cand) == 0:
        return 0, changed, removed, aliases
    P = smap.positions(cand)
    R, t = kf.T_m_kf[:3, :3], kf.T_m_kf[:3, 3]
    X_c = (P - t) @ R
    uv, ok = cam.project(X_c, min_depth=0.1)
    if not ok.any():
        return 0, changed, removed, aliases
    ok_idx = np.nonzero(ok)[0]
    kp = kf.keypoints.astype(np.float64)
    # Only points that may have a keypoint in reach are queried (about half): the
    # others' queries find nothing, and each query is answered on its own, so the
    # points that do have one get the same neighbours.
    close = _maybe_near(kp, uv[ok_idx], radius_px)
    ok_idx = ok_idx[close]
    if len(ok_idx) == 0:
        return 0, changed, removed, aliases
    cand, uv = cand[ok_idx], uv[ok_idx]
    tree = cKDTree(kp)
    dist, idx = tree.query(uv, k=3, distance_upper_bound=radius_px)
    n_kp = len(kf.keypoints)
    valid = idx < n_kp
    # Descriptors only of points with a keypoint in reach (most have none).
    reach = np.nonzero(valid.any(axis=1))[0]
    if len(reach) == 0:
        return 0, changed, removed, aliases
    cand, idx, valid = cand[reach], idx[reach], valid[reach]
    idx_safe = np.where(valid, idx, 0)
    desc_c = smap.descriptors(cand)
    hd = hamming(kf.descriptors[idx_safe], desc_c[:, None, :])
    hd = np.where(valid, hd, 1 << 20)
    best = hd.argmin(axis=1)
    best_d = hd[np.arange(len(cand)), best]
    best_kp = idx_safe[np.arange(len(cand)), best]
    good = best_d <= max_hamming
    # One point per keypoint: the closest descriptor wins.
    order = np.argsort(best_d[good], kind="stable")
    taken: set[int] = set()
    n = 0
    for c_i in np.nonzero(good)[0][order].tolist():
        j = int(best_kp[c_i])
        if j in taken:
            continue
        taken.add(j)
        p = int(cand[c_i])
        if p not in smap.mps:
            continue  # fused away earlier in this loop
        cur = int(kf.mp[j])
        if cur < 0:
            if smap.add_observation(kf.gid, j, p):
                changed.add(kf.gid)
                n += 1
        elif cur != p and cur in smap.mps:
            a, b = smap.mps[cur], smap.mps[p]
            keep, drop = (a, b) if len(a.obs) >= len(b.obs) else (b, a)
            # Only the dropped point's observers rewrite their point ids; the kept
            # point's observers keep theirs (persisting those rewrote dozens of
            # keyframes per fused point).
            changed.update(drop.obs)
            smap.fuse(keep.gid, drop.gid)
            removed.add(drop.gid)
            aliases[drop.gid] = keep.gid
            n += 1
    return n, changed, removed, aliases


def _maybe_near(kp: np.ndarray, uv: np.ndarray, radius: float) -> np.ndarray:
    """Mask of the points ``uv`` (N, 2) that may have a keypoint of ``kp`` (M, 2) within
    ``radius``: a superset of those that do. On a grid of cells a little wider than
    ``radius`` such a keypoint lies in the point's cell or one of its 8 neighbours."""
    if len(kp) == 0 or not 0 < radius < np.inf:
        return np.ones(len(uv), bool)
    cell = 1.01 * radius  # the margin covers the divisions' rounding at a cell border
    ck = np.floor(kp / cell).astype(np.int64)
    cu = np.floor(uv / cell).astype(np.int64)
    lo = np.minimum(ck.min(0), cu.min(0, initial=ck.min())) - 1
    ck -= lo
    cu -= lo
    shape = np.maximum(ck.max(0), cu.max(0, initial=0)) + 2
    kp_cells = np.zeros(shape, bool)
    kp_cells[ck[:, 0], ck[:, 1]] = True
    # Dilated by whole-grid slices (the grid is small; 9 scatters of every keypoint
    # cost more).
    occ = np.zeros(shape, bool)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            occ[1:-1, 1:-1] |= kp_cells[1 + dx : shape[0] - 1 + dx, 1 + dy : shape[1] - 1 + dy]
    return occ[cu[:, 0], cu[:, 1]]
