"""The copy of a server map that a global optimization works on, and its result.

Both are plain dataclasses of numpy arrays (plus a few scalars), so the optimizer
never touches live map objects and a service can put them on the wire as they are.

Conventions (every 4x4 is a numpy float64 array):
- ``T_m_kf``: SE(3), camera to map (``p_m = R p_kf + t``).
- ``S_loop[i]`` for loop edge ``loops[i] = (a, b)``: Sim(3) ``S_a_b`` as
  ``[[s R, t], [0, 1]]``, mapping points in keyframe b's camera frame into keyframe
  a's camera frame (``p_a = s R p_b + t``).
- ``kf_scale``: the scale ``s`` of each keyframe's optimized camera-to-map Sim(3)
  ``S_m_kf = [[s R, t], [0, 1]]``; the corrected SE(3) pose is ``[R, t]``. A length
  measured in the keyframe's camera frame before the correction is ``s`` times as
  long in the corrected map (ORB-SLAM keeps world-to-camera ``S_cw`` and writes
  ``[R, t/s]``; that is the same pose seen from the other side).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from services.mapper.server_map import ServerMap

log = logging.getLogger(__name__)

EUROC_FX = 458.654  # EuRoC cam0, the default camera of the project


@dataclass
class MapSnapshot:
    map_id: str
    version: int
    kf_gids: np.ndarray  # (K,) int64
    T_m_kf: np.ndarray  # (K, 4, 4) float64, camera to map
    fixed_gids: np.ndarray  # (F,) int64, gauge keyframes
    edges: np.ndarray  # (E, 2) int64 gids: spanning tree + strong covisibility
    loops: np.ndarray  # (Lp, 2) int64 gids (a, b)
    S_loop: np.ndarray  # (Lp, 4, 4) float64, S_a_b measured
    mp_gids: np.ndarray  # (M,) int64
    mp_pos: np.ndarray  # (M, 3) float64, map frame
    mp_ref: np.ndarray  # (M,) int64 gid of each point's reference keyframe
    obs_kf: np.ndarray  # (O,) int32 index into kf_gids
    obs_mp: np.ndarray  # (O,) int32 index into mp_gids
    obs_xy: np.ndarray  # (O, 2) float64 undistorted normalized image coordinates
    obs_octave: np.ndarray  # (O,) uint8
    fx: float = EUROC_FX  # focal length in pixels: observation noise is 1.2**octave / fx

    @property
    def n_kf(self) -> int:
        return len(self.kf_gids)

    def kf_index(self) -> dict[int, int]:
        return {int(g): i for i, g in enumerate(self.kf_gids.tolist())}

    def check(self) -> list[str]:
        """Shape and index consistency; returns the problems (empty when consistent)."""
        errs = []
        K, M, O = len(self.kf_gids), len(self.mp_gids), len(self.obs_kf)
        if self.T_m_kf.shape != (K, 4, 4):
            errs.append(f"T_m_kf shape {self.T_m_kf.shape}, expected {(K, 4, 4)}")
        if self.mp_pos.shape != (M, 3) or self.mp_ref.shape != (M,):
            errs.append("mp_pos / mp_ref shape")
        if (
            self.obs_mp.shape != (O,)
            or self.obs_xy.shape != (O, 2)
            or self.obs_octave.shape != (O,)
        ):
            errs.append("observation arrays differ in length")
        if O and (self.obs_kf.min() < 0 or self.obs_kf.max() >= K):
            errs.append("obs_kf out of range")
        if O and (self.obs_mp.min() < 0 or self.obs_mp.max() >= M):
            errs.append("obs_mp out of range")
        known = set(self.kf_gids.tolist())
        for name, arr in (("edges", self.edges), ("loops", self.loops)):
            if arr.size and not set(arr.ravel().tolist()) <= known:
                errs.append(f"{name} name unknown keyframes")
        if not set(self.fixed_gids.tolist()) <= known:
            errs.append("fixed_gids name unknown keyframes")
        if self.S_loop.shape != (len(self.loops), 4, 4):
            errs.append("S_loop shape")
        if len(np.unique(self.kf_gids)) != K or len(np.unique(self.mp_gids)) != M:
            errs.append("duplicate gids")
        return errs


@dataclass
class Correction:
    map_id: str
    base_version: int  # the snapshot's map version
    kf_gids: np.ndarray  # (K,) int64
    T_m_kf: np.ndarray  # (K, 4, 4) corrected SE(3) camera-to-map poses
    kf_scale: np.ndarray  # (K,) float64 scale of each keyframe's Sim(3) (1.0 if none)
    mp_gids: np.ndarray  # (M,) int64
    mp_pos: np.ndarray  # (M, 3) corrected positions in the map frame
    stats: dict = field(default_factory=dict)
    # Observations still outliers after BA, (kf gid, mp gid) pairs the caller may drop.
    outliers: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))


def oldest_keyframe(smap: ServerMap) -> int:
    """The gauge keyframe: earliest stamp, lowest gid among equals."""
    return min(smap.kfs.values(), key=lambda k: (k.stamp_ns, k.gid)).gid


def snapshot_from_map(
    smap: ServerMap,
    loops: list[tuple[int, int, np.ndarray]],
    fixed: list[int] | None = None,
    fx: float = EUROC_FX,
) -> MapSnapshot:
    """Copy ``smap`` into a :class:`MapSnapshot`.

    ``loops``: (a, b, S_a_b) loop edges with their measured Sim(3); the map's own
    'loop' essential edges carry no measurement, so they come only through here
    (edges naming keyframes that are no longer in the map are dropped).
    ``fixed``: gauge keyframes, the oldest keyframe when None.
    """
    gids = np.array(sorted(smap.kfs), dtype=np.int64)
    K = len(gids)
    idx = {int(g): i for i, g in enumerate(gids.tolist())}
    T = np.stack([smap.kfs[int(g)].T_m_kf for g in gids]) if K else np.zeros((0, 4, 4))
    edges = [(a, b) for a, b, kind in smap.essential_edges() if kind != "loop"]
    # Tree and strong edges can name the same pair; one measurement per pair is enough.
    edges_arr = np.unique(np.array(edges, np.int64).reshape(-1, 2), axis=0)
    lp = [(int(a), int(b), S) for a, b, S in loops if a in idx and b in idx and a != b]
    if len(lp) < len(loops):
        log.info("snapshot %s: %d loop edges name missing keyframes", smap.map_id,
                 len(loops) - len(lp))  # fmt: skip
    loops_arr = np.array([(a, b) for a, b, _ in lp], np.int64).reshape(-1, 2)
    S_loop = np.array([np.asarray(S, np.float64) for _, _, S in lp]).reshape(-1, 4, 4)

    mp_gids = np.array(sorted(smap.mps), dtype=np.int64)
    M = len(mp_gids)
    mp_pos = np.array([smap.mps[int(g)].pos for g in mp_gids], np.float64).reshape(M, 3)
    mp_ref = np.array([smap.mps[int(g)].ref_kf for g in mp_gids], np.int64)

    # Observations straight from the keyframes' keypoint arrays: searchsorted maps
    # point gids to indices without a Python loop over keypoints.
    okf, omp, oxy, ooct = [], [], [], []
    for i, g in enumerate(gids.tolist()):
        kf = smap.kfs[g]
        j = np.nonzero(kf.mp >= 0)[0]
        if not len(j):
            continue
        m = kf.mp[j].astype(np.int64)
        pos = np.searchsorted(mp_gids, m)
        ok = (pos < M) & (mp_gids[np.minimum(pos, M - 1)] == m) if M else np.zeros(len(m), bool)
        j, pos = j[ok], pos[ok]
        okf.append(np.full(len(j), i, np.int32))
        omp.append(pos.astype(np.int32))
        oxy.append(np.asarray(kf.xy, np.float64)[j])
        ooct.append(np.asarray(kf.octaves)[j].astype(np.uint8))
    cat = np.concatenate
    if fixed is None:
        fixed = [oldest_keyframe(smap)] if K else []
    return MapSnapshot(
        map_id=smap.map_id,
        version=smap.version,
        kf_gids=gids,
        T_m_kf=T.astype(np.float64),
        fixed_gids=np.array([g for g in fixed if g in idx], np.int64),
        edges=edges_arr,
        loops=loops_arr,
        S_loop=S_loop,
        mp_gids=mp_gids,
        mp_pos=mp_pos,
        mp_ref=mp_ref,
        obs_kf=cat(okf) if okf else np.zeros(0, np.int32),
        obs_mp=cat(omp) if omp else np.zeros(0, np.int32),
        obs_xy=cat(oxy) if oxy else np.zeros((0, 2)),
        obs_octave=cat(ooct) if ooct else np.zeros(0, np.uint8),
        fx=float(fx),
    )
