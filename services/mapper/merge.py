"""Map fusion and loop bookkeeping on server maps (CCM-SLAM §4.8-4.9), no transport.

A verified place match names a query keyframe q, a candidate keyframe c and the Sim(3)
``S_q_c`` (points in c's camera frame into q's). When q and c live in different maps
the two maps become one: the map with fewer keyframes is carried into the frame of the
other by

    S_Q_C = T_Q_q ∘ S_q_c ∘ T_C_c⁻¹

(keyframe poses stay rigid, translations and points scale), its keyframes, points,
covisibility and culled anchors move over, and the matched point pairs are fused.
When q and c are in one map the match is a loop: the pair becomes a loop edge of the
essential graph with its measured Sim(3) and the matched points are fused; the pose
graph optimization then spreads the correction.

Every match, merge or loop, is kept as a loop constraint (gid_q, gid_c, S_q_c): after
a merge it is what ties the two former maps together in the pose graph.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from shared.geometry import Sim3, se3_inv

from .server_map import ServerMap


@dataclass
class LoopConstraint:
    q: int
    c: int
    S_q_c: np.ndarray  # (4, 4) [[sR, t], [0, 1]]
    # A global run's correction distributed it: ``S_q_c`` is then the relative pose its
    # keyframes had after that correction, no longer the detection-time Sim(3)
    # (Collaboration ``_rebase_loops``).
    distributed: bool = False


@dataclass
class FusionResult:
    moved_kfs: list[int] = field(default_factory=list)
    moved_mps: list[int] = field(default_factory=list)
    aliases: dict[int, int] = field(default_factory=dict)  # dropped point -> kept
    changed_kfs: set[int] = field(default_factory=set)


def sim3_of_pose(T: np.ndarray) -> Sim3:
    return Sim3(T[:3, :3].copy(), T[:3, 3].copy(), 1.0)


def map_to_map(T_Q_q: np.ndarray, S_q_c: np.ndarray, T_C_c: np.ndarray) -> Sim3:
    """S_Q_C from the two keyframe poses and the match's Sim(3)."""
    return sim3_of_pose(T_Q_q) @ Sim3.from_matrix(S_q_c) @ sim3_of_pose(se3_inv(T_C_c))


def relative_sim3(T_m_a: np.ndarray, T_m_b: np.ndarray) -> np.ndarray:
    """S_a_b of two poses in one map (scale 1), as a 4x4 matrix."""
    return se3_inv(T_m_a) @ T_m_b


def move_map(target: ServerMap, source: ServerMap, S_t_s: Sim3) -> FusionResult:
    """Carry every keyframe and point of ``source`` into ``target`` through S_t_s.
    ``source`` is left empty. Gids are unique across agents, so nothing collides."""
    res = FusionResult()
    for g, kf in source.kfs.items():
        kf.T_m_kf = S_t_s.transform_pose(kf.T_m_kf)
        target.kfs[g] = kf
        target.covis[g] = source.covis.get(g, Counter())
        res.moved_kfs.append(g)
    # Points in one matrix product (this runs under both maps' locks; one Sim(3) per
    # point cost ~5 us each, a quarter second for a map of 50k points). Rows are views of
    # one array: positions are replaced, never edited in place.
    pts = list(source.mps.values())
    if pts:
        source.set_positions(pts, S_t_s.apply(source.positions(list(source.mps))))
    target.absorb_points(source.mps)
    res.moved_mps.extend(source.mps)
    for g, (anchor, T_a_kf) in source.culled.items():
        T = T_a_kf.copy()
        T[:3, 3] *= S_t_s.s  # relative poses are in map units
        target.culled[g] = (anchor, T)
    target.agents |= source.agents
    source.kfs, source.mps, source.covis, source.culled = {}, {}, {}, {}
    source.agents = set()
    target.version += 1
    source.version += 1
    return res


def fuse_matched(
    smap: ServerMap, keep: np.ndarray, drop: np.ndarray, earlier: dict[int, int] | None = None
) -> FusionResult:
    """Fuse matched point pairs (one landmark seen from both sides of a match).
    Pairs whose points are gone, identical, or already fused are skipped; ``earlier``:
    aliases from previous slices of the same match, to follow fused points."""
    res = FusionResult()
    if earlier:
        res.aliases.update(earlier)
    for k, d in zip(keep.tolist(), drop.tolist(), strict=True):
        k, d = _resolve(res.aliases, k), _resolve(res.aliases, d)
        if k == d or k not in smap.mps or d not in smap.mps:
            continue
        # Keep the point with more observations (its position is better constrained).
        if len(smap.mps[d].obs) > len(smap.mps[k].obs):
            k, d = d, k
        res.changed_kfs |= set(smap.mps[d].obs)
        smap.fuse(k, d)
        res.aliases[d] = k
    if earlier:
        for d in earlier:
            res.aliases.pop(d, None)
    return res


def _resolve(aliases: dict[int, int], g: int) -> int:
    while g in aliases:
        g = aliases[g]
    return g


def add_loop_edge(smap: ServerMap, q: int, c: int) -> bool:
    if q not in smap.kfs or c not in smap.kfs or q == c:
        return False
    smap.kfs[q].loop_edges.add(c)
    smap.kfs[c].loop_edges.add(q)
    smap.version += 1
    return True


def points_in_camera(smap: ServerMap, kf_gid: int) -> np.ndarray:
    """(N, 3) position of each keypoint's map point in the keyframe's camera frame,
    NaN where the keypoint has none."""
    kf = smap.kfs[kf_gid]
    out = np.full((len(kf.mp), 3), np.nan)
    has = np.nonzero(kf.mp >= 0)[0]
    if len(has):
        P = smap.positions(kf.mp[has])
        T = se3_inv(kf.T_m_kf)
        out[has] = P @ T[:3, :3].T + T[:3, 3]
    return out
