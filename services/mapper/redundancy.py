"""Redundant keyframe rejection (CCM-SLAM §4.6).

A keyframe is redundant when at least ``ratio`` of the map points it observes are
also observed by at least ``min_others`` other keyframes. The check starts from a
random keyframe and inspects its covisible neighbours, so connections that changed
since a keyframe arrived are seen again later (the paper's probabilistic scheme).
"""

from __future__ import annotations

import random

from .server_map import ServerMap


def is_redundant(smap: ServerMap, kf_gid: int, ratio: float = 0.98, min_others: int = 3) -> bool:
    kf = smap.kfs[kf_gid]
    # A keyframe observes a point through one keypoint at most (the map keeps that
    # invariant), so its point list needs no np.unique.
    pts = kf.mp[kf.mp >= 0].tolist()
    if len(pts) < 20:
        return False
    # Most keyframes fail within their first few dozen points: stop as soon as more
    # than (1 - ratio) of them are seen by too few others, instead of counting all.
    allowed = len(pts) - ratio * len(pts)
    bad = 0
    mps = smap.mps
    for g in pts:
        if len(mps[g].obs) <= min_others:
            bad += 1
            if bad > allowed:
                return False
    return True


def find_redundant(
    smap: ServerMap,
    rng: random.Random,
    protected: set[int],
    ratio: float = 0.98,
    min_others: int = 3,
    max_checks: int = 10,
) -> list[int]:
    """Redundant keyframes among a random keyframe's covisible neighbours."""
    if len(smap.kfs) < 3:
        return []
    start = rng.choice(list(smap.kfs))
    out = []
    for g in [start, *smap.covisible(start)][:max_checks]:
        if g in protected or g in out:
            continue
        if is_redundant(smap, g, ratio, min_others):
            out.append(g)
    return out
