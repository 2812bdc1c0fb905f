"""Map data sent back to an agent (CCM-SLAM §4.5): the k keyframes most covisible with
its KF_ref and their map points, relative to KF_ref and in the agent's local scale.

Keypoints and descriptors of a keyframe go to an agent once; later chunks carry only
its pose, which keeps the down-link small.
"""

from __future__ import annotations

import numpy as np

from shared import feedback_dump
from shared.geometry import Sim3, fit_sim3_poses, se3_inv, umeyama
from shared.ids import agent_index_of, in_sorted, local_id_of
from shared.messages import MapChunk
from shared.settings import MapperSettings, default_of

from .correction_history import CorrectionHistory
from .registration import AgentHandler

# The agent tracks against the points of its newest 10 keyframes (VOParams.local_kfs);
# a margin covers keyframes in flight.
RECENT_KFS = 15
MIN_SPREAD = 0.01  # of the scene depth: the centres' spread that fixes a scale
# The agent's newest keyframes that went through a global optimization (loop closure,
# merge) say where the map puts it. A Sim(3) fitted on a long stretch of a drifting VO
# is least right at its ends, i.e. where the agent is: with the final map of a team3
# run (frames 0:1500), reported poses corrected through a 60-keyframe fit were worse
# than the raw VO for two of three agents (4.53 / 5.73 / 12.14 mm vs 4.54 / 3.72 /
# 13.51), through a 10-keyframe fit better for all three (4.00 / 3.62 / 8.64 mm). The
# default is 20 now: the setting this takes (MapperSettings.feedback_correction_kfs)
# says why.
LOCAL_FIT_KFS: int = default_of(MapperSettings, "feedback_correction_kfs")
# No correction until the agent's keyframes reach a spread (anchor_count): at least
# ANCHOR_KFS, and as many more as it takes for their centres to spread ANCHOR_SPREAD
# (RMS distance from their mean, in the VO's units: the initial median scene depth).
# A fit on a short baseline is a lever: its rotation is off by about (how far the map
# moves those keyframes) / (their spread), and that swings the reported pose by the same
# angle times its distance from them. The first 20 keyframes of a team3 agent span 2 cm
# of those units (they take off slowly): every global BA that moved them by a millimetre
# turned frame g by tenths of a degree, and the reported pose, a unit away, by 2-8 cm
# where the VO was within 4 mm (replayed from a recorded run, bench/replay_feedback.py).
ANCHOR_KFS = 20
ANCHOR_SPREAD = 0.4
MIN_FIT_KFS = 8
SETTLED_SPREAD = 0.05  # the local fit's spread (units as ANCHOR_SPREAD)
LINE_RATIO = 0.03  # centres this much narrower across than along lie on a line
# The handler's scale after a correction (settled_scale): newest 20 settled keyframes,
# reaching back until their centres spread 0.2 units.
SCALE_FIT_KFS = 20
SCALE_FIT_SPREAD = 0.2
SCALE_FIT_MAX = 400  # newest keyframes of the agent looked at
# The frame correction's settled fit's scale may differ from that of the settled stretch
# before it by at most this (estimate_from_poses). Over five runs recorded at c293d0a
# (team5 x2, team3, the seed-1 pair x2: 14 agents; the scale steps of every map state
# each agent was sent, bench/replay_feedback.py dumps) the VO's own steps were at most
# 0.72 % (p99 0.35-0.72 % per agent), and the steps above that, 1.3-3.4 % in three
# agents, were settles gone wrong: windowed BAs that put a stretch 1-3 % off in scale,
# and the correction carried that scale over every keyframe flown until the next settle
# (team5 agent5: 0.16-0.24 m off for 11 s until the next optimization put the scale
# back, ATE 81 mm against its VO's 37; agent1 of the second team5 run: 15.0 against
# 13.7). At 4 % (before) those passed; at 1.25 % the same recorded map states give
# agent1 9.7 mm and agent5 57 (replayed exactly), no agent's reported pose worse than
# before, and the steady 2.7 % per 120 keyframes scale drift of
# tests/test_frame_correction.py still corrected. A windowed
# settle adds about settle_window_kfs (8) of an agent's keyframes, fewer than a fit
# spans; a broken stretch longer than two fits would be compared with itself.
MAX_SCALE_STEP = 0.0125
# ... between stretches whose centres spread this much (RMS, units as ANCHOR_SPREAD);
# narrower ones are allowed proportionally more, up to MAX_SCALE_STEP_NARROW (the bound
# before). The steps of the settles gone wrong above came at spreads of 0.24-0.33.
SCALE_STEP_SPREAD = 0.2
MAX_SCALE_STEP_NARROW = 0.04


def anchor_count(
    c_l: np.ndarray, min_kfs: int = ANCHOR_KFS, spread: float = ANCHOR_SPREAD
) -> int | None:
    """How many of the first keyframe centres ``c_l`` (N, 3) the anchor takes: the fewest,
    at least ``min_kfs``, whose RMS spread about their mean reaches ``spread``; None when
    the flight so far has not spread that far (no correction yet: the VO has not
    drifted either)."""
    if len(c_l) < min_kfs:
        return None
    n = np.arange(1, len(c_l) + 1, dtype=float)
    mean = np.cumsum(c_l, axis=0) / n[:, None]
    ms = np.cumsum((c_l * c_l).sum(1)) / n
    rms = np.sqrt(np.maximum(ms - (mean * mean).sum(1), 0.0))
    ok = np.nonzero((rms >= spread) & (n >= min_kfs))[0]
    return int(ok[0]) + 1 if len(ok) else None


def fit_settled(
    T_l: np.ndarray,
    T_m: np.ndarray,
    optimized: np.ndarray,
    n: int = LOCAL_FIT_KFS,
    spread: float = SETTLED_SPREAD,
    max_step: float | None = None,
) -> Sim3 | None:
    """S_m_l fitted on the newest of an agent's keyframes that a global optimization
    has settled (``optimized``), VO poses ``T_l`` against map poses ``T_m`` ((N, 4, 4),
    in keyframe order): the newest ``n`` of them, and as many older ones as it takes
    for their centres to spread ``spread`` (:func:`anchor_count`); None with fewer than
    ``min(n, MIN_FIT_KFS)`` settled keyframes or no such spread.

    The keyframes no optimization has touched yet are left out altogether. They sit
    where registration chained and refined them against the map's points, and that
    frontier is worse than the VO it came from: replayed from a recorded team5 run
    (bench/replay_feedback.py), a fit that included them put agent3's reported pose
    6 % off in scale over its last 20 s (55 keyframes since the last optimization) and
    its ATE at 65 mm against its VO's 17; the same fit on settled keyframes only, 14 mm.
    Past them the VO carries the pose on, which is the best the agent has there. The
    spread is the anchor's lever again: the first global BA of agent5's map settled
    its first 15 keyframes, taken off slowly within 0.01 units, and ten of them gave a
    scale of 0.966 that moved its reported pose by 37 cm (ATE 37 vs 20 mm).

    ``max_step``: None too when the fit's scale differs from that of the settled
    keyframes just before them (fitted the same way) by more than this
    (:func:`estimate_from_poses` asks so)."""
    idx = np.nonzero(np.asarray(optimized, bool))[0]
    span = settled_span(T_l, idx, n, spread)
    if span is None:
        return None
    S = fit_sim3_poses(T_l[span], T_m[span])
    if S is None or max_step is None:
        return S
    # The stretch before is looked for only when asked: settled_scale fits once per
    # correction and agent under the map's lock, the frame correction per chunk.
    before = settled_span(T_l, idx[: len(idx) - len(span)], n, spread)
    if before is not None:
        S0 = fit_sim3_poses(T_l[before], T_m[before])
        if S0 is not None and abs(S.s / S0.s - 1.0) > _step_bound(T_l, span, before, max_step):
            return None
    return S


def _step_bound(T_l: np.ndarray, span: np.ndarray, before: np.ndarray, max_step: float) -> float:
    """The scale step allowed between two settled stretches: ``max_step`` where both
    spread SCALE_STEP_SPREAD or more, more for narrower ones (in proportion, up to
    MAX_SCALE_STEP_NARROW): a fit's scale is a lever on its centres' spread. An agent
    hovering for 25 keyframes (tests/test_collab.py, the settle test) fitted stretches
    1.5 % apart at a spread of ~0.06, with no scale change at all."""

    def rms(ix: np.ndarray) -> float:
        c = T_l[ix, :3, 3]
        return float(np.sqrt(((c - c.mean(0)) ** 2).sum(1).mean()))

    narrow = max(min(rms(span), rms(before)), 1e-9)
    return min(MAX_SCALE_STEP_NARROW, max(max_step, max_step * SCALE_STEP_SPREAD / narrow))


def settled_span(T_l: np.ndarray, idx: np.ndarray, n: int, spread: float) -> np.ndarray | None:
    """Of settled keyframes ``idx`` (in keyframe order), the newest ones
    :func:`fit_settled` fits on; None when there are too few or they do not spread."""
    if n <= 0 or len(idx) < max(min(n, MIN_FIT_KFS), 2):
        return None
    # Newest first, so the count runs back from the newest settled keyframe.
    m = anchor_count(T_l[idx[::-1], :3, 3], min_kfs=min(n, len(idx)), spread=spread)
    return None if m is None else idx[-m:]


def fit_frame(T_l: np.ndarray, T_m: np.ndarray, settled: np.ndarray) -> Sim3 | None:
    """A_m_l: the agent's VO frame onto the map, fitted on the centres of all its
    settled keyframes (least squares, :func:`~shared.geometry.umeyama`); frame g, in
    which the agent reports, is the map seen through it. None with fewer than
    MIN_FIT_KFS settled keyframes.

    It changes only when an optimization lands, like the local fit. Anchored on the
    agent's first keyframes instead (d0cbe27), g turned whenever an optimization moved
    those against the rest, and with 10 settled keyframes in the local fit each
    correction then moved the pose by 4-15 mm more or less than the one before.
    Replayed (bench/replay_feedback.py), first keyframes vs this fit: team5 13.9 / 8.2 /
    13.8 / 22.9 / 19.8 vs 12.6 / 8.5 / 14.4 / 22.1 / 18.6 mm (VO 13.7 / 18.8 / 17.3 /
    44.1 / 37.2); the two-agent seed-1 run 14.6 / 12.9 vs 8.3 / 13.3 (VO 7.5 / 15.2).
    On a synthetic flight with steady drift and an exact map it is the worse choice
    (tests/test_frame_correction.py: 0.44 vs 0.02 of the VO's error left), there g
    follows the drift as the flight grows. Fixed once at the agent's first estimate
    instead (and moved with its map at a merge) it leaves 0.05 of that VO's error there,
    but replayed on the seed-1 pair it was far worse: 25.2 / 18.1 vs 6.8 / 12.5 mm at
    f1a4bbd, 11.0 / 13.4 vs 7.1 / 10.3 at 525e4a3, and with the oracle map 7.4 / 23.7 vs
    7.4 / 11.2 (VO 7.5 / 15.2): the reported pose then goes wherever the short local fit
    (fit_settled) puts it, while refitted g keeps it near the VO. Centres on a line
    leave the roll about it open: then the orientations fix the rotation
    (:func:`~shared.geometry.fit_sim3_poses`)."""
    idx = np.nonzero(np.asarray(settled, bool))[0]
    if len(idx) < MIN_FIT_KFS:
        return None
    c = T_l[idx, :3, 3]
    sv = np.linalg.svd(c - c.mean(0), compute_uv=False)
    if sv[0] <= 1e-12:
        return None
    if sv[1] < LINE_RATIO * sv[0]:
        return fit_sim3_poses(T_l[idx], T_m[idx])
    return umeyama(c, T_m[idx, :3, 3], with_scale=True)


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
        T_m = np.stack([k.T_m_kf for k in kfs])
        S_l_m = fit_sim3_poses(T_m, np.stack([k.T_l_kf for k in kfs]))
        c_m = T_m[:, :3, 3]
        d_m = np.linalg.norm(c_m - c_m.mean(0), axis=1).sum()
        # A keyframe's points are all in the map (its ``mp`` names only points the map
        # holds), read from the point table.
        P = smap.positions(ref.mp[ref.mp >= 0][:200])
        depth = (float(np.median(np.linalg.norm(P - ref.T_m_kf[:3, 3], axis=1)))
                 if len(P) else np.inf)  # fmt: skip
        # Enough baseline (mean spread >= MIN_SPREAD of the scene depth), and no more than
        # 20 % from the handler's scale (anything further is a broken fit, not drift).
        if (
            S_l_m is not None
            and d_m / len(kfs) >= MIN_SPREAD * depth
            and abs(S_l_m.s * h.scale - 1.0) < 0.2
        ):
            # p_ref = T_ref_l (s R_lm p_m + t_lm)
            R_rl, t_rl = T_l_ref[:3, :3].T, -T_l_ref[:3, :3].T @ T_l_ref[:3, 3]
            return R_rl @ S_l_m.R, R_rl @ S_l_m.t + t_rl, float(S_l_m.s)
    T_ref_m = se3_inv(ref.T_m_kf)
    inv_s = 1.0 / h.scale
    return T_ref_m[:3, :3], T_ref_m[:3, 3] * inv_s, inv_s


def frame_correction(
    h: AgentHandler, n_local: int = LOCAL_FIT_KFS, history: CorrectionHistory | None = None
) -> Sim3 | None:
    """The correction sent to ``h``'s agent: of the map's estimate
    (:func:`estimate_correction`), the part that stands out of the scatter of its
    successive estimates (``history``, default the handler's; see
    services/mapper/correction_history.py), taken about the agent's newest keyframe.
    None while there is no estimate, or too few to judge its scatter by: the agent
    keeps its last correction, at first none (its VO)."""
    S_g_l = estimate_correction(h, n_local)
    if S_g_l is None:
        return None
    hist = h.correction_history if history is None else history
    newest = max(i for i in h.local_poses if h.kf_gid(i) in h.smap.kfs)
    p = h.smap.kfs[h.kf_gid(newest)].T_l_kf[:3, 3]
    hist.add(S_g_l, p)
    return hist.significant(S_g_l, p)


def estimate_correction(h: AgentHandler, n_local: int = LOCAL_FIT_KFS) -> Sim3 | None:
    """The map's estimate of S_g_l: the agent's VO frame ``l`` onto its server-corrected
    frame ``g``.

    The server holds each of the agent's keyframes twice: as the VO sent it (``T_l_kf``)
    and in the map after registration, loop closures, merges and global optimization
    (``T_m_kf``). Two similarities relate them: ``S_m_l`` fitted on the newest
    ``n_local`` keyframes that went through a global optimization (:func:`fit_settled`)
    and ``A_m_l`` fitted on the centres of all its settled keyframes (:func:`fit_frame`:
    how the agent's frame sits on the map). ``S_g_l = A_m_l^-1 S_m_l`` moves a VO pose to
    where the map puts it, expressed in frame ``g``: the agent's own frame as the map
    sees it, which stays put while the map's frame changes (a merge moves the whole map
    into another agent's frame; a loop closure re-scales it about the map's first
    keyframe). Past the settled keyframes the agent is carried on by its VO's own
    relative motion (a similarity keeps it), so S_g_l changes only when an optimization
    lands, and the reported pose never follows the unsettled frontier. None (the agent
    keeps its last correction, at first none: its VO) until a global optimization has
    settled enough of its keyframes and its keyframes spread widely enough
    (:func:`anchor_count`), or when a fit is degenerate."""
    smap = h.smap
    kfs = [k for k in (smap.kfs.get(h.kf_gid(i)) for i in sorted(h.local_poses)) if k is not None]
    if len(kfs) < MIN_FIT_KFS:
        return None
    settled = np.array([kf.optimized for kf in kfs], bool)
    if settled.sum() < MIN_FIT_KFS:
        # fit_frame has nothing to fit on, so the estimate is None: known before the
        # poses of every keyframe of the flight are stacked (each chunk, until an
        # optimization has settled some).
        return None
    T_l = np.stack([k.T_l_kf for k in kfs])
    T_m = np.stack([k.T_m_kf for k in kfs])
    return estimate_from_poses(T_l, T_m, settled, n_local)


def estimate_from_poses(
    T_l: np.ndarray, T_m: np.ndarray, settled: np.ndarray, n_local: int = LOCAL_FIT_KFS
) -> Sim3 | None:
    """:func:`estimate_correction` on an agent's keyframes in keyframe order: VO poses
    ``T_l``, map poses ``T_m`` ((N, 4, 4)) and which of them an optimization settled
    (also what bench/replay_feedback.py calls on recorded map states)."""
    if len(T_l) < MIN_FIT_KFS:
        return None
    # Frame g waits for the agent's first keyframes to spread (anchor_count): before,
    # any fit is a lever. Then it is where the settled map puts the agent's flight so
    # far, as a whole (fit_frame).
    if anchor_count(T_l[:, :3, 3]) is None:
        return None
    A_m_l = fit_frame(T_l, T_m, settled)
    # A settled stretch whose scale steps away from the one before it is a settle gone
    # wrong, not drift (a VO's scale drifts slowly): the agent keeps its last correction
    # until an optimization places those keyframes again. In a team5 run a windowed BA
    # settled agent4's newest keyframes (in the dark stretch of MH04, where registration
    # had put them 0.3-0.6 m off) 0.5 m off the truth, at a scale 12 % above the stretch
    # before; the correction fitted on them moved agent4's reported pose by 0.7 m, its
    # ATE 141 mm against its VO's 44 (36.6 mm replayed with this check). Only here: in
    # settled_scale, whose fit sets the scale registration chains new keyframes at, the
    # same check left the handler at a stale scale after each such step, the next
    # keyframes were registered off it, and the seed-1 pair's agent1 went from 7 to
    # 24 and 70 mm in two runs (01442d0).
    S_m_l = fit_settled(T_l, T_m, settled, n_local, max_step=MAX_SCALE_STEP)
    if A_m_l is None or S_m_l is None:
        return None
    S_g_l = A_m_l.inverse() @ S_m_l
    if not (0.8 < S_g_l.s < 1.25 and np.isfinite(S_g_l.matrix()).all()):
        return None  # a broken fit, not drift: the agent keeps its last correction
    return S_g_l


def settled_scale(
    h: AgentHandler, n: int = SCALE_FIT_KFS, spread: float = SCALE_FIT_SPREAD
) -> float | None:
    """Map units per VO unit where the agent flies now: the scale of :func:`fit_settled`
    on its newest ``n`` keyframes a global optimization settled (VO poses as sent
    against map poses), reaching back until their centres spread ``spread``. None
    without enough settled keyframes or spread, or for a degenerate fit.

    Registration chains every new keyframe from its predecessor at the handler's scale,
    and pose refinement cannot see a scale error: each keyframe is a few centimetres from
    the one before and its new points are placed at the same scale. So the scale a global
    optimization gives the map where the agent flies must reach the handler, or every
    keyframe until the next optimization is placed at the old one. The per-keyframe
    scale of the correction says only what the pose graph did (global BA, which runs
    after it, moves the scale too) and only for keyframes in the optimizer's copy, which
    an agent's newest one almost never is (it arrived during the optimization). In a
    team5 run at 85a443d, MH01's map ended 2.4 % smaller per VO unit than agent1 flew
    it (0.976), the handler stayed at ~1.0, and the 88 keyframes after the last applied
    correction were placed 2 % too far apart: per-agent ATE 55.7 mm (its settled
    keyframes alone 5.8 mm; the tail re-placed at the fitted scale 17.9 mm).

    A scale wants a longer lever than the frame correction's local fit: with two noisy
    simulated agents merged and optimized once in-process (three seeds; one BA changed
    the agent's scale by 1-3 % with per-keyframe scale 1), the local fit's 10 keyframes
    / 0.05 units put the agent's next 59 keyframes at 5.5 / 14.5 / 9.2 mm RMSE, 20 /
    0.2 at 7.0 / 7.0 / 8.1, the old rule at 7.4 / 5.9 / 9.1. On the team5 run both
    fits give 0.972-0.976 after each correction from 321 s on."""
    smap = h.smap
    # Under the map's lock, once per correction and agent: the newest SCALE_FIT_MAX of
    # its keyframes are plenty (None if they never spread; the old rule then applies).
    newest = sorted(h.local_poses)[-SCALE_FIT_MAX:]
    kfs = [k for k in (smap.kfs.get(h.kf_gid(i)) for i in newest) if k is not None]
    if len(kfs) < MIN_FIT_KFS:
        return None
    T_l = np.stack([k.T_l_kf for k in kfs])
    T_m = np.stack([k.T_m_kf for k in kfs])
    settled = np.array([kf.optimized for kf in kfs], bool)
    S = fit_settled(T_l, T_m, settled, n, spread)
    if S is None or not (np.isfinite(S.s) and S.s > 0):
        return None
    return float(S.s)


def _pose_in(R: np.ndarray, t: np.ndarray, s: float, T_m_kf: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R @ T_m_kf[:3, :3]
    T[:3, 3] = s * R @ T_m_kf[:3, 3] + t
    return T


def build_chunk(
    h: AgentHandler,
    k: int,
    sent: set[int],
    now_ns: int,
    names: dict[int, str],
    correction_kfs: int = LOCAL_FIT_KFS,
) -> MapChunk | None:
    """The chunk due to ``h``'s agent: its frame correction (unless ``correction_kfs``
    is 0) and the k keyframes most covisible with its KF_ref that it lacks; None when
    there is neither."""
    smap = h.smap
    S = frame_correction(h, correction_kfs) if correction_kfs > 0 else None
    S_g_l = None if S is None else S.matrix()
    if feedback_dump.enabled():
        _dump(h, now_ns, S_g_l)
    ref_g = h.kf_gid(h.kf_ref) if h.kf_ref >= 0 else -1
    ref = smap.kfs.get(ref_g)
    # The agent's own newest keyframes are always the most covisible with its KF_ref,
    # and it holds them: the k sent are the most covisible of the others (another
    # agent's keyframes here, or its own from an earlier pass).
    lo, hi = h.kf_gid(max(h.latest_kf - RECENT_KFS, 0)), h.kf_gid(max(h.latest_kf, 0))
    neigh = [] if ref is None else [
        g for g in smap.covisible(ref_g, min_weight=1) if not lo <= g <= hi][:k]  # fmt: skip
    if not neigh:
        return None if S_g_l is None else _correction_only(h, now_ns, S_g_l)
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
    uniq, first = np.unique(allmp, return_index=True)
    mine = [smap.kfs[g].mp for g in range(lo, hi + 1) if g in smap.kfs]
    if mine:
        # Sorted first: ~5k sorted ids searched in ~16k sorted ones cost an eighth of
        # the ~16k unsorted ids' binary searches into them (present_in).
        keep = ~in_sorted(uniq, np.sort(np.concatenate(mine)))
        uniq, first = uniq[keep], first[keep]
    order = np.argsort(first, kind="stable")
    mp_gids = uniq[order]
    rank = np.empty(len(uniq), np.int64)
    rank[order] = np.arange(len(uniq))
    pos = smap.positions(mp_gids)
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
    ai, inv = np.unique(agent_index_of(mp_gids), return_inverse=True)
    lut = np.array([label(h, names.get(int(a), "")) for a in ai.tolist()], dtype=object)
    mp_agents = lut[inv].tolist() if len(mp_gids) else []
    return MapChunk(
        agent=h.name, map_id=smap.map_id, kf_ref=h.kf_ref,
        kf_agents=[label(h, kf.agent) for kf in kfs],
        kf_ids=np.array([kf.id for kf in kfs], np.int64),
        T_ref_kf=np.stack([_pose_in(R_a, t_a, s_a, kf.T_m_kf) for kf in kfs]),
        kf_keypoints=kp, kf_descriptors=desc, kf_mp_index=idx,
        # Point ids are agent-local: the agent index (high bits) names their agent.
        mp_agents=mp_agents,
        mp_ids=local_id_of(mp_gids),
        p_ref=p_ref.astype(np.float64),
        mp_descriptors=smap.descriptors(mp_gids),
        sent_ns=now_ns, S_g_l=S_g_l,
    )  # fmt: skip


def label(h: AgentHandler, agent: str) -> str:
    """How a chunk for ``h``'s agent names the keyframes and points of stored agent
    ``agent``: the agent knows its own (this flight's) under the id it flies as; an
    earlier flight stored under that same id is another agent to it, so it gets a name
    no agent id can have (ids never contain ``#``; see ``sessions``)."""
    if agent == h.agent:
        return h.name
    return f"{agent}#" if agent == h.name else agent


def _correction_only(h: AgentHandler, now_ns: int, S_g_l: np.ndarray) -> MapChunk:
    none = np.zeros(0, np.int64)
    return MapChunk(
        agent=h.name, map_id=h.smap.map_id, kf_ref=h.kf_ref, kf_agents=[], kf_ids=none,
        T_ref_kf=np.zeros((0, 4, 4)), kf_keypoints=[], kf_descriptors=[], kf_mp_index=[],
        mp_agents=[], mp_ids=none, p_ref=np.zeros((0, 3)),
        mp_descriptors=np.zeros((0, 32), np.uint8), sent_ns=now_ns, S_g_l=S_g_l,
    )  # fmt: skip


def _dump(h: AgentHandler, now_ns: int, S_g_l: np.ndarray | None) -> None:
    """The inputs of this frame correction (HIVEMAP_FEEDBACK_DUMP): the agent's
    keyframes as the VO sent them and as the map holds them."""
    smap = h.smap
    ids = [i for i in sorted(h.local_poses) if h.kf_gid(i) in smap.kfs]
    kfs = [smap.kfs[h.kf_gid(i)] for i in ids]
    feedback_dump.record(
        "mapper", "fc", agent=h.agent, map_id=smap.map_id, sent_ns=now_ns,
        n_kfs=len(h.local_poses), ids=np.array(ids), kf_ref=h.kf_ref, latest=h.latest_kf,
        T_l=np.stack([k.T_l_kf for k in kfs]) if kfs else None,
        T_m=np.stack([k.T_m_kf for k in kfs]) if kfs else None,
        optimized=np.array([k.optimized for k in kfs], bool), S_g_l=S_g_l,
        stamps=np.array([k.stamp_ns for k in kfs], np.int64), version=smap.version,
        ties=np.array([_ties(smap, k) for k in kfs], np.int64).reshape(-1, 3),
    )  # fmt: skip


# Own keyframes more than this many ids apart count as a tie beyond the VO chain (a loop).
TIE_GAP = 20


def _ties(smap, kf) -> tuple[int, int, int]:
    """Covisibility weights (points shared, summed over keyframes) of a keyframe with
    other agents' keyframes, with the agent's own more than TIE_GAP ids away, and in
    all: what ties it to more than its VO chain, for the replay (a settle of keyframes
    tied by neither only re-optimizes the chain)."""
    cross = far = 0
    c = smap.covis.get(kf.gid, {})
    for o, n in c.items():
        ok = smap.kfs.get(o)
        if ok is None:
            continue
        if ok.agent != kf.agent:
            cross += n
        elif abs(ok.id - kf.id) > TIE_GAP:
            far += n
    return cross, far, sum(c.values())
