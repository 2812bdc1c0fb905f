"""The copy of a server map that a global optimization works on: the
:class:`~shared.messages.OptimizeRequest` the mapper sends to the optimizer.

Two steps, so keyframe ingestion is not held up by a large copy: :func:`capture_map`
takes what is needed in a few milliseconds under the map's lock, and
:func:`build_request` turns it into the message off-lock. The message's docstring
gives the conventions; the optimizer never touches live map objects.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from dataclasses import dataclass
from operator import attrgetter

import numpy as np

from shared.camera import EUROC_FX
from shared.geometry import se3_inv
from shared.messages import OptimizeRequest
from shared.settings import MapperSettings, default_of

from .server_map import STRONG, ServerMap, stack_rows

log = logging.getLogger(__name__)
_pos = attrgetter("pos")
_ref_kf = attrgetter("ref_kf")
# Points per step of build_request's point arrays (a pause between steps).
POINT_SLICE = 50_000


def oldest_keyframe(smap: ServerMap) -> int:
    """The gauge keyframe: earliest stamp, lowest gid among equals."""
    return min(smap.kfs.values(), key=lambda k: (k.stamp_ns, k.gid)).gid


@dataclass
class MapCapture:
    """What a snapshot needs from a live map, taken in a few milliseconds under the map's
    lock: poses and observation index arrays copied, immutable arrays referenced. The
    expensive part (essential graph, observation tables) is built from it off-lock by
    :func:`build_request`, so keyframe ingestion is not held up by a large copy."""

    map_id: str
    version: int
    gids: list[int]
    T: np.ndarray  # (K, 4, 4) copies
    kf_mp: list[np.ndarray]  # copies (fusion rewrites them in place)
    kf_xy: list[np.ndarray]  # never rewritten after a keyframe is made
    kf_oct: list[np.ndarray]
    parents: list[int]
    covis: list[dict[int, int]]  # copies
    loop_edges: list[set[int]]
    points: dict  # gid -> ServerMapPoint (shallow copy; a position is replaced, not edited)
    loops: list[tuple[int, int, np.ndarray]]
    fixed: list[int]
    odometry: Odometry | None = None


@dataclass
class Odometry:
    """Relative-pose factors from the agents' own VO for a windowed BA: edge ``i``
    says keyframe ``pairs[i, 1]`` sits at ``T_rel[i]`` (SE(3), its camera in
    ``pairs[i, 0]``'s, translation in map units) with standard deviations
    ``sigma[i] = (rotation rad, translation map units)``."""

    pairs: np.ndarray  # (E, 2) gids
    T_rel: np.ndarray  # (E, 4, 4)
    sigma: np.ndarray  # (E, 2)


# The VO's relative motion between an agent's neighbouring keyframes, as a windowed BA's
# prior: rotation to this (rad), translation to a share of the step (MapperSettings
# window_odometry_trans_share, which says why it is weak) plus a floor in map units. The
# step is taken to map units at the agent's own map/VO ratio over the window's
# neighbouring pairs (median), which registration chained it at.
ODO_ROT_SIGMA = np.deg2rad(0.3)
ODO_TRANS_SHARE = default_of(MapperSettings, "window_odometry_trans_share")
ODO_TRANS_FLOOR = 0.002
ODO_MIN_STEP = 1e-6
# Only keyframes this close in the agent's own sequence are linked (a longer stretch of
# VO has drifted in rotation too; the rotation's sigma grows with the square root).
ODO_MAX_GAP = 10


def window_odometry(
    smap: ServerMap, gids: list[int], free: set[int], trans_share: float = ODO_TRANS_SHARE
) -> Odometry | None:
    """VO relative-pose edges between each free keyframe of ``gids`` and the same
    agent's previous keyframe among ``gids`` (free or fixed).

    A windowed BA places the newest keyframes from points that mostly only they see;
    where those are few or badly spread it can settle them off the VO's own shape, and
    the frame correction is fitted on what it settled (services/mapper/feedback.py).
    The VO's relative motion over a few keyframes is the best the system knows of it,
    so the window is held to it, softly (the BA's kernel is robust). Recorded seed-1
    pair runs (HIVEMAP_FEEDBACK_DUMP, bench/registration_errors.py), mean over 10 s
    windows of the median error of new keyframes: 10.5 / 9.8 mm without the edges,
    7.3 / 8.8 with them; agent1's reported pose 10.30 and 7.32 mm against its VO's 7.45
    in those two runs, 8.87 in a second run with the edges (one run each: the spread
    between runs is as large as the gain)."""
    by_agent: dict[str, list] = {}
    for g in gids:
        k = smap.kfs[g]
        by_agent.setdefault(k.agent, []).append(k)
    pairs, rels, sig = [], [], []
    for kfs in by_agent.values():
        if len(kfs) < 2:
            continue
        kfs.sort(key=lambda k: (k.stamp_ns, k.id))
        Tl = np.stack([k.T_l_kf for k in kfs])
        Tm = np.stack([k.T_m_kf for k in kfs])
        dl = np.linalg.norm(np.diff(Tl[:, :3, 3], axis=0), axis=1)
        dm = np.linalg.norm(np.diff(Tm[:, :3, 3], axis=0), axis=1)
        ok = dl > ODO_MIN_STEP
        if not ok.any():
            continue
        s = float(np.median(dm[ok] / dl[ok]))
        if not np.isfinite(s) or s <= 0:
            continue
        for i in range(1, len(kfs)):
            gap = kfs[i].id - kfs[i - 1].id  # the agent's keyframes in between
            if kfs[i].gid not in free or not 0 < gap <= ODO_MAX_GAP:
                continue
            T = se3_inv(Tl[i - 1]) @ Tl[i]
            T[:3, 3] *= s
            pairs.append((kfs[i - 1].gid, kfs[i].gid))
            rels.append(T)
            sig.append((ODO_ROT_SIGMA * np.sqrt(gap),
                        trans_share * s * dl[i - 1] + ODO_TRANS_FLOOR))  # fmt: skip
    if not pairs:
        return None
    return Odometry(np.array(pairs, np.int64), np.array(rels, np.float64),
                    np.array(sig, np.float64))  # fmt: skip


def capture_map(
    smap: ServerMap,
    loops: list[tuple[int, int, np.ndarray]],
    fixed: list[int] | None = None,
    covis: bool = True,
) -> MapCapture:
    """``covis=False``: the keyframes' covisibility is left out, for
    :func:`copy_covisibility` to copy off the map's lock."""
    gids = sorted(smap.kfs)
    if fixed is None:
        fixed = [oldest_keyframe(smap)] if gids else []
    return _capture(smap, gids, dict(smap.mps), list(loops), list(fixed), covis)


# Keyframes whose covisibility copy_covisibility copies per step (a pause between).
COVIS_SLICE = 200


def copy_covisibility(
    smap: ServerMap, gids: list[int], pause=None, slice_kfs: int = COVIS_SLICE
) -> list[dict[int, int]]:
    """The covisibility of keyframes ``gids`` (a global capture's, ``MapCapture.covis``),
    copied off the map's lock, ``pause`` called between slices.

    In a dense merged map a keyframe shares points with over a thousand others: at 24
    agents (2700 keyframes, 330k points) copying every keyframe's counts took 330 ms
    of CPU, 440 ms of the capture's 500 ms hold of the lock, while every batch of the
    map waited. Only the strong edges they make (``_essential_edges``) go to the
    optimizer, with the captured poses as their measurements: each ``dict()`` is one C
    call (no other thread changes a keyframe's counts midway), a keyframe removed since
    the capture keeps the counts it had, a keyframe added since is not one of ``gids``
    (edges name captured keyframes only), and counts that moved since (fusion, an
    agent's new observations) can tip a pair at the threshold, as a capture taken a
    batch later would have."""
    pause = pause or (lambda: None)
    covis = smap.covis
    out: list[dict[int, int]] = []
    for i in range(0, len(gids), slice_kfs):
        if i:
            pause()
        out.extend(dict(covis.get(g, {})) for g in gids[i : i + slice_kfs])
    return out


def _capture(smap: ServerMap, gids: list[int], points: dict,
             loops: list[tuple[int, int, np.ndarray]], fixed: list[int],
             covis: bool = True) -> MapCapture:  # fmt: skip
    """The keyframes ``gids`` of ``smap`` copied (poses, observations, graph edges;
    ``covis=False``: covisibility left for :func:`copy_covisibility`)."""
    kfs = [smap.kfs[g] for g in gids]
    return MapCapture(
        map_id=smap.map_id, version=smap.version, gids=gids,
        T=np.array([k.T_m_kf for k in kfs], np.float64).reshape(-1, 4, 4),
        kf_mp=[k.mp.copy() for k in kfs], kf_xy=[k.xy for k in kfs],
        kf_oct=[k.octaves for k in kfs], parents=[k.parent for k in kfs],
        covis=copy_covisibility(smap, gids) if covis else [],
        loop_edges=[set(k.loop_edges) for k in kfs], points=points,
        loops=loops, fixed=fixed,
    )  # fmt: skip


def _essential_edges(cap: MapCapture) -> np.ndarray:
    """Spanning tree + strong covisibility (ServerMap.essential_edges without its 'loop'
    edges, which come with their measurements through ``loops``)."""
    known = set(cap.gids)
    edges = []
    for g, parent, covis in zip(cap.gids, cap.parents, cap.covis, strict=True):
        if parent in known and parent != g:
            edges.append((min(g, parent), max(g, parent)))
        edges.extend((g, o) for o, n in covis.items() if n >= STRONG and g < o and o in known)
    # Tree and strong edges can name the same pair; one measurement per pair is enough.
    return np.unique(np.array(edges, np.int64).reshape(-1, 2), axis=0)


def build_request(
    cap: MapCapture, reason: str = "", fx: float = EUROC_FX, pause=None
) -> OptimizeRequest:
    """``pause``: called between the steps (each ~0.1 s for a 1500-keyframe map) so the
    mapper can give its actors the GIL meanwhile."""
    pause = pause or (lambda: None)
    gids = np.array(cap.gids, dtype=np.int64)
    K = len(gids)
    idx = {g: i for i, g in enumerate(cap.gids)}
    edges_arr = _essential_edges(cap)
    pause()
    loops = cap.loops
    lp = [(int(a), int(b), S) for a, b, S in loops if a in idx and b in idx and a != b]
    if len(lp) < len(loops):
        log.info("snapshot %s: %d loop edges name missing keyframes", cap.map_id,
                 len(loops) - len(lp))  # fmt: skip
    loops_arr = np.array([(a, b) for a, b, _ in lp], np.int64).reshape(-1, 2)
    S_loop = np.array([np.asarray(S, np.float64) for _, _, S in lp]).reshape(-1, 4, 4)

    mp_gids = np.sort(np.fromiter(cap.points, np.int64, len(cap.points)))
    M = len(mp_gids)
    pts = [cap.points[g] for g in mp_gids.tolist()]
    pause()
    # Positions a slice at a time (stack_rows: the bytes joined, the same values as
    # np.array of the rows): np.array over the 330k rows of a 24-agent map was one C
    # call that held the GIL for ~0.1 s while keyframe batches waited for it.
    pos_parts, ref_parts = [], []
    for i in range(0, M, POINT_SLICE):
        part = pts[i : i + POINT_SLICE]
        pos_parts.append(stack_rows(list(map(_pos, part)), np.float64, 3))
        ref_parts.append(np.fromiter(map(_ref_kf, part), np.int64, len(part)))
        pause()
    mp_pos = np.concatenate(pos_parts) if M else np.zeros((0, 3))
    mp_ref = np.concatenate(ref_parts) if M else np.zeros(0, np.int64)

    # Observations straight from the keyframes' keypoint arrays, all keyframes at once:
    # one searchsorted maps point gids to indices.
    counts = np.array([len(m) for m in cap.kf_mp], np.int64)
    okf = np.repeat(np.arange(K, dtype=np.int32), counts) if K else np.zeros(0, np.int32)
    cat = np.concatenate
    allmp = cat(cap.kf_mp).astype(np.int64) if K else np.zeros(0, np.int64)
    oxy = cat([np.asarray(x, np.float64) for x in cap.kf_xy]) if K else np.zeros((0, 2))
    ooct = cat([np.asarray(o) for o in cap.kf_oct]).astype(np.uint8) if K else np.zeros(0)
    pause()
    pos = np.searchsorted(mp_gids, allmp)
    ok = (allmp >= 0) & (pos < M)
    ok[ok] &= mp_gids[pos[ok]] == allmp[ok]
    return OptimizeRequest(
        map_id=cap.map_id,
        version=cap.version,
        reason=reason,
        sent_ns=time.time_ns(),
        fx=float(fx),
        kf_gids=gids,
        T_m_kf=cap.T,
        fixed_gids=np.array([g for g in cap.fixed if g in idx], np.int64),
        edges=edges_arr,
        loops=loops_arr,
        S_loop=S_loop,
        mp_gids=mp_gids,
        mp_pos=mp_pos,
        mp_ref=mp_ref,
        obs_kf=okf[ok].astype(np.int32),
        obs_mp=pos[ok].astype(np.int32),
        obs_xy=oxy[ok].reshape(-1, 2),
        obs_octave=ooct[ok].astype(np.uint8),
        **_odometry_fields(cap.odometry),
    )


def _odometry_fields(odo: Odometry | None) -> dict:
    if odo is None:
        return {}
    return {"odo": odo.pairs, "T_odo": odo.T_rel, "odo_sigma": odo.sigma}


def request_from_map(
    smap: ServerMap,
    loops: list[tuple[int, int, np.ndarray]],
    fixed: list[int] | None = None,
    fx: float = EUROC_FX,
    reason: str = "",
) -> OptimizeRequest:
    """Copy ``smap`` into an :class:`OptimizeRequest` in one go (tests, benches).

    ``loops``: (a, b, S_a_b) loop edges with their measured Sim(3); the map's own
    'loop' essential edges carry no measurement, so they come only through here
    (edges naming keyframes that are no longer in the map are dropped).
    ``fixed``: gauge keyframes, the oldest keyframe when None.
    """
    return build_request(capture_map(smap, loops, fixed), reason, fx)


# A windowed copy frees at most this many keyframes (the newest unsettled ones).
WINDOW_MAX_FREE = 60
# ... and holds fixed at most this many of the settled keyframes that see the window's
# points, those sharing most of them (in a room flown over and over, every keyframe of
# the map sees some).
WINDOW_MAX_FIXED = 60


def own_anchors(smap: ServerMap, free: list) -> set[int]:
    """Per agent with keyframes in ``free``: its newest settled keyframe before the first
    of them, fixed in the window so that the VO edge from it (:func:`window_odometry`)
    ties the agent's part of the window to its own settled chain.

    The keyframes fixed for the points they share with the window are, where an agent
    flies through a part of the map another agent made, largely the other agent's, and
    its own predecessor is among them only if it shares enough points: without it the
    window hangs on the other agent's placement of that part, and the VO edges hold only
    the window's shape. In the seed-1 pair (bench_team.py --only team2_seed1) agent1's
    keyframes of its last 30 s sat 10-15 mm off the truth in the live map against its
    VO's 5-6 (the final map put them at 5-8), its frame corrections followed them, and
    its reported pose was above its VO in four runs of four (7.56 / 7.89 / 7.56 / 7.88
    mm against 7.45); with the anchor below in four of four (7.37 / 6.82 / 6.76 / 7.02),
    the map's joint ATE 4.6-5.5 mm against 5.1-5.7."""
    first: dict[str, int] = {}
    for k in free:
        first[k.agent] = min(first.get(k.agent, k.stamp_ns), k.stamp_ns)
    best: dict[str, tuple[int, int]] = {}
    for k in smap.kfs.values():
        t0 = first.get(k.agent)
        if (t0 is not None and k.optimized and k.stamp_ns < t0
                and k.stamp_ns > best.get(k.agent, (-1, 0))[0]):  # fmt: skip
            best[k.agent] = (k.stamp_ns, k.gid)
    return {g for _, g in best.values()}


def capture_window(
    smap: ServerMap,
    max_free: int = WINDOW_MAX_FREE,
    max_fixed: int = WINDOW_MAX_FIXED,
    odometry: bool = False,
    odometry_trans_share: float = ODO_TRANS_SHARE,
) -> MapCapture | None:
    """A copy of the part of ``smap`` its unsettled keyframes (``optimized`` False) touch,
    for a windowed BA (ORB-SLAM's local BA): the newest ``max_free`` of them free, the
    ``max_fixed`` other keyframes that observe most of their points fixed, and those
    points (observations by keyframes outside the copy are left out). Under the map's
    lock, like :func:`capture_map`, but it copies only the window (tens of keyframes, a
    few thousand points). None when nothing is unsettled or fewer than two other
    keyframes see the window (no gauge: the global optimization's business).

    The fixed keyframes are (almost always) settled ones, placed by a global optimization
    or an earlier window, so the BA places the free ones and their points consistently
    with the settled map, which is what settling means to the frame correction
    (services/mapper/feedback.py) -- at the cost of a window instead of the whole map.
    In tests/test_collab.py it cut the unsettled keyframes' error from 9.1 to 2.0
    (thousandths of the VO's unit) in 1.6 s."""
    free = sorted((k for k in smap.kfs.values() if not k.optimized),
                  key=lambda k: (k.stamp_ns, k.gid))[-max_free:]  # fmt: skip
    if not free:
        return None
    free_g = {k.gid for k in free}
    mps = smap.mps
    pts: dict = {}
    for k in free:
        for m in k.mp[k.mp >= 0].tolist():
            p = mps.get(m)
            if p is not None:
                pts[m] = p
    shared: Counter = Counter()
    for p in pts.values():
        shared.update(o for o in p.obs if o not in free_g and o in smap.kfs)
    fixed = {g for g, _ in shared.most_common(max_fixed)}
    if len(fixed) < 2:
        return None
    if odometry:
        fixed |= own_anchors(smap, free)
    gids = sorted(free_g | fixed)
    cap = _capture(smap, gids, pts, [], sorted(fixed))
    if odometry:
        cap.odometry = window_odometry(smap, gids, free_g, odometry_trans_share)
    return cap
