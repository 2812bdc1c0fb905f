"""Redundant keyframe rejection (CCM-SLAM §4.6).

A keyframe is redundant when at least ``ratio`` of the map points it observes are
also observed by at least ``min_others`` other keyframes. The check starts from a
random keyframe and inspects its covisible neighbours, so connections that changed
since a keyframe arrived are seen again later (the paper's probabilistic scheme).
Keyframes the agent may still refine (its newest ones) are not candidates.
"""

from __future__ import annotations

import random

import numpy as np

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
    gids = np.fromiter(smap.kfs, np.int64, len(smap.kfs))
    start = int(gids[rng.randrange(len(gids))])
    # Newest gid per agent (the agent index is the gid's high bits), with numpy: a
    # Python loop over every keyframe of the map ran in each rejection round, and
    # rounds run between batches of a map several agents share.
    ai = agent_index_of(gids)
    order = np.lexsort((gids, ai))
    last = np.r_[ai[order][1:] != ai[order][:-1], True]
    newest = dict(zip(ai[order][last].tolist(), gids[order][last].tolist(), strict=True))
    out = []
    for g in [start, *smap.covisible(start)][:max_checks]:
        if g in protected or g in out or g > newest[agent_index_of(g)] - keep_newest:
            continue
        if is_redundant(smap, g, ratio, min_others):
            out.append(g)
    return out
