"""Redundant keyframe rejection (CCM-SLAM §4.6).

A keyframe is redundant when at least ``ratio`` of the map points it observes are
also observed by at least ``min_others`` other keyframes. The check starts from a
random keyframe and inspects its covisible neighbours, so connections that changed
since a keyframe arrived are seen again later (the paper's probabilistic scheme).
Keyframes the agent may still refine (its newest ones) are not candidates.
"""

from __future__ import annotations

import random

from shared.ids import agent_index_of

from .server_map import ServerMap

# The agent's local BA still moves its newest keyframes (a window of 7) and sends their
# new poses; one culled there breaks the chain the following keyframes register through,
# so they are left alone until the agent is done with them.
KEEP_NEWEST = 10


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
    keep_newest: int = KEEP_NEWEST,
) -> list[int]:
    """Redundant keyframes among a random keyframe's covisible neighbours. The
    ``keep_newest`` newest keyframes of each agent are never candidates."""
    if len(smap.kfs) < 3:
        return []
    start = rng.choice(list(smap.kfs))
    # Newest gid per agent (the agent index is the gid's high bits).
    newest: dict[int, int] = {}
    for g in smap.kfs:
        a = agent_index_of(g)
        if g > newest.get(a, -1):
            newest[a] = g
    out = []
    for g in [start, *smap.covisible(start)][:max_checks]:
        if g in protected or g in out or g > newest[agent_index_of(g)] - keep_newest:
            continue
        if is_redundant(smap, g, ratio, min_others):
            out.append(g)
    return out
