"""Apply a global-optimization result to the live server map (CCM-SLAM Fig. 4).

The optimizer worked on a snapshot while the map kept growing. Keyframes of the
snapshot take their corrected pose. Keyframes that arrived meanwhile were
registered relative to keyframes already in the map, so they follow the
correction of their nearest snapshot ancestor in the spanning tree: with the
anchor's correction as a Sim(3) ``C_a = S'_m_a T_m_a^-1`` (``S'_m_a`` the
optimized pose with its pose-graph scale), a new keyframe becomes
``T'_m_kf = C_a T_m_kf`` as a rigid pose, i.e. ``T'_a @ [R_a_kf, s_a t_a_kf]`` --
its pose relative to the anchor is kept, its translation scaled like the anchor's
neighbourhood. Points take their optimized position when their reference keyframe
was in the snapshot, otherwise they move with their reference keyframe's
correction. Keyframes and points removed meanwhile are skipped.

Pure function of (map, correction): no transport, no storage.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import chain, compress, islice
from operator import attrgetter, not_

import numpy as np

from shared.geometry import se3_inv
from shared.messages import CorrectionMsg

from .server_map import ServerMap

log = logging.getLogger(__name__)
_gid, _ref_kf = attrgetter("gid"), attrgetter("ref_kf")


@dataclass
class AppliedCorrection:
    kfs: set[int] = field(default_factory=set)  # keyframes whose pose was set
    mps: set[int] = field(default_factory=set)  # points whose position was set
    kfs_propagated: set[int] = field(default_factory=set)  # newer keyframes moved with an anchor
    kfs_unanchored: set[int] = field(default_factory=set)  # newer keyframes left as they were
    kfs_missing: int = 0  # snapshot keyframes no longer in the map
    mps_missing: int = 0  # snapshot points no longer in the map
    # Seconds per step and sizes of the work, for the log line of a long hold.
    phases: dict[str, float] = field(default_factory=dict)

    @property
    def changed(self) -> bool:
        return bool(self.kfs or self.mps)


def _sim(T: np.ndarray, s: float) -> np.ndarray:
    S = T.copy()
    S[:3, :3] *= s
    return S


def _rigid(S: np.ndarray) -> np.ndarray:
    """Sim(3) ``[[s R, t], [0, 1]]`` -> SE(3) ``[R, t]``."""
    T = S.copy()
    s = float(np.cbrt(np.linalg.det(S[:3, :3])))
    T[:3, :3] /= s
    return T


def _anchor(smap: ServerMap, g: int, corrected: dict, memo: dict[int, int | None]) -> int | None:
    """Nearest keyframe with a correction up ``g``'s spanning-tree parents; when the
    chain breaks, its strongest covisible keyframe that has one."""
    path = []
    cur = g
    found: int | None = None
    for _ in range(len(smap.kfs) + 1):
        if cur in memo:
            found = memo[cur]
            break
        if cur != g and cur in corrected:
            found = cur
            break
        path.append(cur)
        kf = smap.kfs.get(cur)
        if kf is None or kf.parent < 0 or kf.parent in path:
            break
        cur = kf.parent
    for p in path:
        memo[p] = found
    if found is None:
        found = next((o for o in smap.covisible(g, min_weight=1) if o in corrected), None)
    return found


@dataclass
class CorrectionPlan:
    """The part of a correction that can be worked out off the map's lock: each
    snapshot keyframe's Sim(3) correction, and the optimized position of every point
    anchored in the snapshot, from a shallow copy of the map's points. Applying it
    (:func:`apply_correction` with ``plan``) is then an assignment per point under the
    lock; what changed meanwhile is caught there (see ``apply_correction``)."""

    snap_kfs: set[int]
    kf_C: list[tuple[int, np.ndarray, np.ndarray]]  # (gid, corrected pose, C) per snapshot kf
    objs: list = field(default_factory=list)  # points taking an optimized position ...
    P: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # ... that position
    rows: list = field(default_factory=list)  # ... as row views of P (made off the lock)
    planned: set[int] = field(default_factory=set)  # their gids
    rest: list[int] = field(default_factory=list)  # points of the copy that move with a C
    index: dict[int, int] = field(default_factory=dict)  # corrected point gid -> row
    new_points: list[int] = field(default_factory=list)  # added since the copy (a journal)
    mps_missing: int = 0


PLAN_SLICE = 20_000  # points per step of a plan between pauses


def plan_correction(
    smap: ServerMap,
    corr: CorrectionMsg,
    T_m_kf_at_snapshot: dict[int, np.ndarray] | None = None,
    points: dict | None = None,
    new_points: list[int] | None = None,
    pause: Callable[[], None] | None = None,
    keep: set[int] | None = None,
) -> CorrectionPlan:
    """What ``corr`` does to ``points`` (a shallow copy of the map's points taken under
    its lock; default: the live map's, under the caller's lock). ``new_points``: the
    map's journal of points added since the copy (``ServerMap.record_new_points``),
    read when the plan is applied. ``pause`` is called between slices of points (the
    service sleeps there while keyframe batches wait). ``keep``: as for
    :func:`apply_correction`; points outside the correction anchored to those are left
    out of the plan (a windowed correction then touches only its window's points under
    the lock, not every point of the map)."""
    if corr.map_id != smap.map_id:
        raise ValueError(f"correction for map {corr.map_id!r} applied to {smap.map_id!r}")
    kf_C = []
    for g, T_new, s in zip(corr.kf_gids.tolist(), corr.T_m_kf, corr.kf_scale.tolist(),
                           strict=True):  # fmt: skip
        kf = smap.kfs.get(g)
        T_old = None if kf is None else kf.T_m_kf
        if T_m_kf_at_snapshot is not None and g in T_m_kf_at_snapshot:
            T_old = T_m_kf_at_snapshot[g]
        if T_old is not None:
            kf_C.append((g, T_new, _sim(T_new, s) @ se3_inv(T_old)))
    snap = set(corr.kf_gids.tolist())
    plan = CorrectionPlan(snap, kf_C, new_points=[] if new_points is None else new_points)
    gids = corr.mp_gids.tolist()
    index = plan.index = {g: i for i, g in enumerate(gids)}
    items = iter((smap.mps if points is None else points).items())
    idx: list[int] = []
    found = 0
    objs, rest = plan.objs, plan.rest
    while True:
        n = len(objs) + len(rest)
        for g, mp in islice(items, PLAN_SLICE):
            i = index.get(g)
            if i is None:
                if keep is None or mp.ref_kf not in keep:
                    rest.append(g)
                continue
            found += 1
            if mp.ref_kf in snap:
                objs.append(mp)
                idx.append(i)
            else:
                rest.append(g)
        if len(objs) + len(rest) - n < PLAN_SLICE:
            break
        if pause is not None:
            pause()
    pos = np.asarray(corr.mp_pos, np.float64).reshape(-1, 3)
    plan.P = pos[np.array(idx, np.int64)] if idx else np.zeros((0, 3))
    plan.rows = list(plan.P)
    plan.planned = {mp.gid for mp in objs}
    plan.mps_missing = len(gids) - found
    return plan


def apply_correction(
    smap: ServerMap,
    corr: CorrectionMsg,
    T_m_kf_at_snapshot: dict[int, np.ndarray] | None = None,
    plan: CorrectionPlan | None = None,
    keep: set[int] | None = None,
    unsettled: set[int] | None = None,
) -> AppliedCorrection:
    """Write ``corr`` into ``smap`` (see the module doc). ``T_m_kf_at_snapshot``: the
    poses the correction was computed from, when some changed since the snapshot
    (default: the map's current poses); a keyframe's correction ``C = S' T_snap^-1``
    is what moves newer keyframes and points anchored to it.

    ``plan``: the correction worked out off the lock (:func:`plan_correction`); without
    it, it is worked out here. Either way the result is the same: a planned point whose
    anchor moved out of the snapshot since the plan (its keyframe was culled), and the
    points added since (the plan's journal), follow the rules below like the rest.
    The map's lock is held for this call: a half-corrected map would register new
    keyframes against stale points.

    ``keep``: keyframes a windowed copy left out (services/mapper/capture.py
    capture_window): they, and the points anchored to them, stay as they are; only
    keyframes that arrived since the copy follow an anchor.

    ``unsettled``: keyframes of the copy moved like the rest but not marked settled
    (``ServerKeyframe.optimized``; a global copy's frontier, collab ``_frontier``)."""
    t0 = time.perf_counter()
    unsettled = unsettled or set()
    if plan is None:
        plan = plan_correction(smap, corr, T_m_kf_at_snapshot, keep=keep)
    res = AppliedCorrection(mps_missing=plan.mps_missing)
    ph = res.phases
    t_plan = time.perf_counter()
    ph["plan_s"] = t_plan - t0
    if corr.map_id != smap.map_id:
        raise ValueError(f"correction for map {corr.map_id!r} applied to {smap.map_id!r}")
    # Per snapshot keyframe still in the map: new pose and the Sim(3) correction.
    C: dict[int, np.ndarray] = {}
    new_T: dict[int, np.ndarray] = {}
    planned_C = {g for g, _, _ in plan.kf_C}
    for g, T_new, Cg in plan.kf_C:
        if g not in smap.kfs:
            continue
        C[g] = Cg
        new_T[g] = T_new
    res.kfs_missing = len(corr.kf_gids) - len(C)
    for g, T_new, s in zip(corr.kf_gids.tolist(), corr.T_m_kf, corr.kf_scale.tolist(),
                           strict=True):  # fmt: skip
        kf = smap.kfs.get(g)
        if g in planned_C or kf is None:
            continue  # a keyframe new since the plan: the default pose
        res.kfs_missing -= 1
        T_old = kf.T_m_kf
        if T_m_kf_at_snapshot is not None and g in T_m_kf_at_snapshot:
            T_old = T_m_kf_at_snapshot[g]
        C[g] = _sim(T_new, s) @ se3_inv(T_old)
        new_T[g] = T_new
    # Newer keyframes follow their anchor, computed from the current (old) poses
    # before any pose is overwritten.
    memo: dict[int, int | None] = {}
    for g, kf in smap.kfs.items():
        if g in C or (keep is not None and g in keep):
            continue
        a = _anchor(smap, g, C, memo)
        if a is None:
            res.kfs_unanchored.add(g)
            continue
        new_T[g] = _rigid(C[a] @ kf.T_m_kf)
        C[g] = C[a]
        res.kfs_propagated.add(g)
    t1 = time.perf_counter()
    ph["anchors_s"] = t1 - t_plan
    if res.kfs_unanchored:
        log.warning("map %s: %d keyframes without a corrected ancestor keep their pose",
                    smap.map_id, len(res.kfs_unanchored))  # fmt: skip

    # Points: optimized position if anchored in the snapshot, else moved with their ref.
    # This runs under the map's lock over every point of the map (300k in a big merged
    # map), so the loop does nothing but check and assign; rows are views of one array
    # (positions are replaced, never edited in place).
    # The checks and assignments go through map() at C speed, not a Python loop: at 24
    # agents a correction still held the map's lock for 657 ms, and these passes run
    # over its 330k points and the tens of thousands added since the copy.
    snap_kfs = plan.snap_kfs
    mps = smap.mps
    if len(plan.rows) != len(plan.objs):
        raise ValueError("a plan's rows and points differ in number")
    ok = list(map(snap_kfs.__contains__, map(_ref_kf, plan.objs)))
    smap.set_positions(list(compress(plan.objs, ok)), plan.P[np.array(ok, bool)],
                       list(compress(plan.rows, ok)))  # fmt: skip
    moved_off = list(map(_gid, compress(plan.objs, map(not_, ok))))
    res.mps = plan.planned  # a plan is applied once
    res.mps.difference_update(moved_off)
    t2 = time.perf_counter()
    ph["planned_s"] = t2 - t1
    # The rest move with their reference keyframe's correction, grouped by correction
    # (keyframes carried along share their anchor's) so each group is one matrix
    # product: a 3x3 product per point cost ~0.2 s of lock hold per 100k points.
    pos = np.asarray(corr.mp_pos, np.float64).reshape(-1, 3)
    groups: dict[int, tuple[np.ndarray, list]] = {}
    seen: set[int] = set()
    for m in chain(plan.rest, moved_off, plan.new_points):
        mp = mps.get(m)
        if mp is None or m in seen or m in res.mps:
            continue
        seen.add(m)
        i = plan.index.get(m)
        if i is not None and mp.ref_kf in snap_kfs:
            mp.pos = pos[i]
            res.mps.add(m)
            continue
        Cr = C.get(mp.ref_kf)
        if Cr is None and keep is not None and mp.ref_kf in keep:
            continue  # outside the window
        if Cr is None:
            # Reference gone or unanchored: any corrected observer will do.
            Cr = next((C[o] for o in mp.obs if o in C), None)
            if Cr is None:
                continue
        groups.setdefault(id(Cr), (Cr, []))[1].append(mp)
    t3 = time.perf_counter()
    ph["rest_s"] = t3 - t2
    for Cr, grp in groups.values():
        g = np.fromiter(map(_gid, grp), np.int64, len(grp))
        smap.set_positions(grp, smap.positions(g) @ Cr[:3, :3].T + Cr[:3, 3])
        res.mps.update(g.tolist())

    t4 = time.perf_counter()
    ph["groups_s"] = t4 - t3
    for g, T in new_T.items():
        smap.kfs[g].T_m_kf = T
        res.kfs.add(g)
    for g in snap_kfs:
        kf = smap.kfs.get(g)
        if kf is not None and g not in unsettled:
            kf.optimized = True
    # Culled keyframes are kept as (anchor, T_anchor_kf) for registration chains; the
    # relative translation scales with the anchor's neighbourhood.
    for g, (a, T_a_kf) in list(smap.culled.items()):
        if a in C:
            s = float(np.cbrt(np.linalg.det(C[a][:3, :3])))
            T2 = T_a_kf.copy()
            T2[:3, 3] *= s
            smap.culled[g] = (a, T2)
    smap.version += 1
    ph["kfs_s"] = time.perf_counter() - t4
    ph.update(planned=len(plan.objs), rest=len(plan.rest), new_points=len(plan.new_points),
              moved_off=len(moved_off), groups=len(groups), kfs_new=len(res.kfs_propagated),
              culled=len(smap.culled))  # fmt: skip
    log.info("map %s: correction from version %d applied: %d kfs (%d newer), %d points",
             smap.map_id, corr.base_version, len(res.kfs), len(res.kfs_propagated),
             len(res.mps))  # fmt: skip
    return res
