"""Global bundle adjustment with GTSAM, and the full global optimization (PGO + BA).

Graph: one Pose3 (camera to map) per keyframe, one Point3 per map point with at
least two observations, one GenericProjectionFactorCal3_S2 per observation on
undistorted normalized coordinates (unit calibration), noise ``SCALE_FACTOR**octave / fx``
(``shared.orb``: ORB's pyramid sigma in pixels, expressed in normalized units) under a Huber
kernel with ``k = sqrt(5.991)`` standard deviations (ORB-SLAM's 2-DoF 95 % chi2).

Gauge (7 DoF for monocular): a tight prior on the fixed keyframe's pose (6 DoF)
plus a tight ``RangeFactorPose3`` holding its distance to one reference keyframe
(the one sharing most points with it) -- one scalar for the scale. That is the
minimal gauge: fixing a second full pose as well would remove 5 more DoF that are
not gauge and bend the map near those two keyframes towards their pre-BA relative
pose. When the caller names several fixed keyframes (a windowed BA) they stay exactly
where they are, no range factor is added, and they are known cameras rather than
variables: each of their observations is a ``TriangulationFactorCal3_S2`` on the point
alone (:func:`_known_cameras`).

Graph building is where Python costs: factors are inserted per (keyframe, octave)
group through ``gtsam.utilities.insertProjectionFactors`` (one C++ loop per group)
and keys are plain integers (cameras ``0..K-1``, points after them) so they pass
as a float vector. Reprojection errors and outliers are computed with numpy.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import gtsam
import numpy as np

from services.optimizer.pose_graph import (
    PGOParams,
    apply_to_snapshot,
    correct_points,
    optimize_pose_graph,
    point_ref_index,
)
from shared.messages import CorrectionMsg, OptimizeRequest
from shared.orb import SCALE_FACTOR
from shared.settings import OptimizerSettings, default_of

log = logging.getLogger(__name__)

CHI2_2DOF_95 = 5.991
CHI2_6DOF_95 = 12.592


@dataclass
class BAParams:
    """The settings-backed fields default to and are built from ``OptimizerSettings``."""

    max_iters: int = default_of(OptimizerSettings, "ba_max_iterations")
    # Seconds from the call: no iteration starts that would end later than this
    # (one iteration always runs).
    time_budget_s: float = default_of(OptimizerSettings, "ba_time_budget_s")
    rel_tol: float = 1e-4  # stop when an iteration lowers the error by less than this fraction
    huber_k: float = float(np.sqrt(CHI2_2DOF_95))
    chi2_outlier: float = CHI2_2DOF_95
    min_obs_per_point: int = 2
    min_obs_per_kf: int = 5  # fewer observations do not pin a 6-DoF pose
    prior_sigma: float = 1e-6
    range_sigma_rel: float = 1e-6
    min_parallax_deg: float = 1.0  # ORB-SLAM triangulates only above about 1 degree
    min_depth: float = 1e-3  # observations of points this close or behind are outliers
    # "colamd" (GTSAM's default), "metis", or "points_first" (Schur-like: points
    # eliminated first, the reduced camera system last). Measured on the 1000-keyframe
    # bench: COLAMD 2.2 s per LM iteration, METIS similar plus 1.3 s to order,
    # points_first slowest.
    ordering: str = "colamd"
    diagonal_damping: bool = True  # LM damping scaled by the Hessian's diagonal (as g2o)
    lambda_initial: float = 1e-5
    linear_solver: str = "MULTIFRONTAL_CHOLESKY"  # GTSAM's name; no CHOLMOD in the wheel
    # A windowed BA's fixed keyframes as known cameras rather than variables under
    # tight priors (:func:`_known_cameras`); False: as variables (the same result,
    # slower; tests compare the two).
    known_cameras: bool = True

    @classmethod
    def from_settings(cls, o: OptimizerSettings) -> BAParams:
        return cls(max_iters=o.ba_max_iterations, time_budget_s=o.ba_time_budget_s)


@dataclass
class ReprojStats:
    chi2: np.ndarray  # (O,) squared error in units of the observation's sigma
    err_px: np.ndarray  # (O,) pixel error (inf for points behind the camera)


def reprojection(snap_T: np.ndarray, pos: np.ndarray, snap: OptimizeRequest) -> ReprojStats:
    """Per-observation pixel error and chi2 of poses ``snap_T`` and points ``pos``."""
    T = snap_T[snap.obs_kf]
    d = pos[snap.obs_mp] - T[:, :3, 3]
    X_c = np.einsum("nji,nj->ni", T[:, :3, :3], d)  # R^T (p - t)
    z = X_c[:, 2]
    front = z > 1e-9
    proj = X_c[:, :2] / np.where(front, z, 1.0)[:, None]
    err = np.linalg.norm(proj - snap.obs_xy, axis=1) * snap.fx
    err = np.where(front, err, np.inf)
    sig = SCALE_FACTOR ** snap.obs_octave.astype(np.float64)
    return ReprojStats((err / sig) ** 2, err)


def _gauge_partner(snap: OptimizeRequest, fixed: int, kf_ok: np.ndarray, obs_ok: np.ndarray) -> int:
    """The keyframe sharing most (used) points with ``fixed`` at a nonzero distance;
    the nearest other keyframe in index order when none shares any."""
    ok = obs_ok.copy()
    pts = np.unique(snap.obs_mp[ok & (snap.obs_kf == fixed)])
    sel = ok & np.isin(snap.obs_mp, pts) & (snap.obs_kf != fixed)
    cnt = np.bincount(snap.obs_kf[sel], minlength=snap.n_kf).astype(np.float64)
    dist = np.linalg.norm(snap.T_m_kf[:, :3, 3] - snap.T_m_kf[fixed, :3, 3], axis=1)
    scale = max(float(np.median(dist[kf_ok])) if kf_ok.any() else 1.0, 1e-9)
    cnt[(dist < 1e-6 * scale) | ~kf_ok] = 0
    if cnt.max() > 0:
        return int(np.argmax(cnt))
    cand = np.nonzero(kf_ok & (dist >= 1e-6 * scale))[0]
    return int(cand[0]) if len(cand) else -1


def _select(snap: OptimizeRequest, p: BAParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(observation mask, keyframe mask, point mask) of what enters the graph: points
    with enough observations in front of their cameras, keyframes with enough of
    those, repeated once so the two rules agree."""
    rp = reprojection(snap.T_m_kf, snap.mp_pos, snap)
    obs_ok = np.isfinite(rp.err_px)
    # Depth check again with the configured margin (err_px is inf only behind).
    T = snap.T_m_kf[snap.obs_kf]
    z = np.einsum("ni,ni->n", T[:, :3, 2], snap.mp_pos[snap.obs_mp] - T[:, :3, 3])
    obs_ok &= z > p.min_depth
    # Points seen under too small an angle have an unobservable depth: they would make
    # the system (nearly) singular; they keep their input position.
    if p.min_parallax_deg > 0 and len(snap.obs_kf):
        ray = snap.mp_pos[snap.obs_mp] - snap.T_m_kf[snap.obs_kf, :3, 3]
        ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
        mean = np.zeros((len(snap.mp_gids), 3))
        np.add.at(mean, snap.obs_mp, np.where(obs_ok[:, None], ray, 0.0))
        mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)
        cos = np.einsum("ni,ni->n", ray, mean[snap.obs_mp])
        half = np.zeros(len(snap.mp_gids))
        np.maximum.at(half, snap.obs_mp[obs_ok], np.arccos(np.clip(cos[obs_ok], -1, 1)))
        obs_ok &= (2 * half >= np.deg2rad(p.min_parallax_deg))[snap.obs_mp]
    fixed = snap.kf_index()
    fixed_idx = [fixed[int(g)] for g in snap.fixed_gids]
    kf_ok = np.ones(snap.n_kf, bool)
    mp_ok = np.ones(len(snap.mp_gids), bool)
    for _ in range(2):
        cur = obs_ok & kf_ok[snap.obs_kf] & mp_ok[snap.obs_mp]
        mp_ok = np.bincount(snap.obs_mp[cur], minlength=len(mp_ok)) >= p.min_obs_per_point
        cur &= mp_ok[snap.obs_mp]
        kf_ok = np.bincount(snap.obs_kf[cur], minlength=snap.n_kf) >= p.min_obs_per_kf
        kf_ok[fixed_idx] = True
    cur = obs_ok & kf_ok[snap.obs_kf] & mp_ok[snap.obs_mp]
    mp_ok = np.bincount(snap.obs_mp[cur], minlength=len(mp_ok)) >= p.min_obs_per_point
    cur &= mp_ok[snap.obs_mp]
    return cur, kf_ok, mp_ok


def _ordering(graph: gtsam.NonlinearFactorGraph, cam_keys: list[int], kind: str):
    if kind == "colamd":
        return None
    if kind == "metis":
        return gtsam.Ordering.MetisNonlinearFactorGraph(graph)
    if kind == "points_first":
        return gtsam.Ordering.ColamdConstrainedLastNonlinearFactorGraph(graph, cam_keys)
    raise ValueError(f"unknown ordering {kind!r}")


def _optimizer(graph, values, ordering, p: BAParams) -> gtsam.LevenbergMarquardtOptimizer:
    # Levenberg-Marquardt only: Gauss-Newton and Dogleg stop with an indeterminate
    # system on real maps (weakly seen points, the tight gauge) where damping copes.
    prm = gtsam.LevenbergMarquardtParams()
    prm.setDiagonalDamping(p.diagonal_damping)
    prm.setlambdaInitial(p.lambda_initial)
    prm.setMaxIterations(p.max_iters)
    prm.setRelativeErrorTol(p.rel_tol)
    prm.setLinearSolverType(p.linear_solver)
    if ordering is not None:
        prm.setOrdering(ordering)
    return gtsam.LevenbergMarquardtOptimizer(graph, values, prm)


def _known_cameras(snap: OptimizeRequest, idx: dict[int, int], kf_ok: np.ndarray,
                   fixed: list[int], use: bool = True) -> np.ndarray:  # fmt: skip
    """Per keyframe: held fixed as a known camera, no variable at all (its observations
    are TriangulationFactors on the points). Only where the caller fixes several
    keyframes (a windowed BA: the settled ones around the window); a lone gauge
    keyframe keeps its prior and range factor. A fixed keyframe tied to a free one by
    a VO edge stays a variable under its prior, so the edge is kept as it is.

    As variables under tight priors the fixed keyframes went through every elimination:
    in a windowed BA they are most of the cameras (e.g. 60 of 84), and the reduced
    camera system grows with them (the agent's local BA, services/agent/vo/local_ba.py,
    went from 111 to 67 ms per job the same way)."""
    known = np.zeros(snap.n_kf, bool)
    if len(fixed) <= 1 or not use:
        return known
    known[fixed] = True  # _select keeps every fixed keyframe in the graph
    free = kf_ok & ~known
    if snap.odo is not None and len(snap.odo):
        for a, b in snap.odo.tolist():
            ia, ib = idx.get(int(a)), idx.get(int(b))
            if ia is None or ib is None:
                continue
            if free[ia] or free[ib]:
                known[ia] = known[ib] = False
    return known


def _add_odometry(graph, snap: OptimizeRequest, idx: dict[int, int],
                  cam_key: np.ndarray) -> int:  # fmt: skip
    """The request's VO relative-pose edges (a windowed BA's, see
    services/mapper/capture.py ``window_odometry``) between keyframes both in the graph
    as variables, under a Huber kernel at the 6-DoF 95 % chi2; how many were added. An
    edge with a known camera (:func:`_known_cameras`) ties two fixed keyframes: a
    constant."""
    if snap.odo is None or not len(snap.odo):
        return 0
    huber = gtsam.noiseModel.mEstimator.Huber.Create(float(np.sqrt(CHI2_6DOF_95)))
    n = 0
    for (a, b), T, (sr, st) in zip(snap.odo.tolist(), snap.T_odo, snap.odo_sigma.tolist(),
                                   strict=True):  # fmt: skip
        ia, ib = idx.get(int(a)), idx.get(int(b))
        # Not a variable: left out of the graph, or a known camera.
        if ia is None or ib is None or cam_key[ia] < 0 or cam_key[ib] < 0:
            continue
        noise = gtsam.noiseModel.Robust.Create(
            huber, gtsam.noiseModel.Diagonal.Sigmas(np.array([sr, sr, sr, st, st, st]))
        )
        graph.add(gtsam.BetweenFactorPose3(int(cam_key[ia]), int(cam_key[ib]),
                                           gtsam.Pose3(T), noise))  # fmt: skip
        n += 1
    return n


def bundle_adjust(snap: OptimizeRequest, params: BAParams | None = None) -> CorrectionMsg:
    """Global BA over ``snap``; returns refined poses and points (keyframes left out of
    the graph keep their pose, points left out move rigidly with their reference
    keyframe), the observations that are still outliers, and stats (iterations, GTSAM
    error and inlier pixel RMSE before/after)."""
    p = params or BAParams()
    t0 = time.perf_counter()
    K, M = snap.n_kf, len(snap.mp_gids)
    obs_ok, kf_ok, mp_ok = _select(snap, p)
    idx = snap.kf_index()
    fixed = [idx[int(g)] for g in snap.fixed_gids] or ([0] if K else [])
    cam = np.nonzero(kf_ok)[0]
    pts = np.nonzero(mp_ok)[0]
    known = _known_cameras(snap, idx, kf_ok, fixed, p.known_cameras)
    var = cam[~known[cam]]
    # Keys: variable cameras 0..Kv-1, points Kv.. (small integers survive the float
    # vector); a known camera has no key.
    cam_key = np.full(K, -1, np.int64)
    cam_key[var] = np.arange(len(var))
    pt_key = np.full(M, -1, np.int64)
    pt_key[pts] = len(var) + np.arange(len(pts))

    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for i in var.tolist():
        values.insert(int(cam_key[i]), gtsam.Pose3(snap.T_m_kf[i]))
    for j, P in zip(pts.tolist(), snap.mp_pos[pts], strict=True):
        values.insert(int(pt_key[j]), P)

    cal = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)
    huber = gtsam.noiseModel.mEstimator.Huber.Create(p.huber_k)
    oct_all = snap.obs_octave.astype(np.int64)
    models = {
        int(o): gtsam.noiseModel.Robust.Create(
            huber, gtsam.noiseModel.Isotropic.Sigma(2, SCALE_FACTOR**o / snap.fx)
        )
        for o in np.unique(oct_all[obs_ok])
    }
    sel = np.nonzero(obs_ok)[0]
    group = snap.obs_kf[sel].astype(np.int64) * 256 + oct_all[sel]
    order = np.argsort(group, kind="stable")
    sel, group = sel[order], group[order]
    bounds = np.flatnonzero(np.diff(group)) + 1
    starts = np.concatenate([[0], bounds]) if len(sel) else np.zeros(0, np.int64)
    ends = np.concatenate([bounds, [len(sel)]]) if len(sel) else np.zeros(0, np.int64)
    J_all = pt_key[snap.obs_mp[sel]].astype(np.float64)
    Z_all = np.ascontiguousarray(snap.obs_xy[sel].T)
    insert = gtsam.utilities.insertProjectionFactors
    for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
        o = sel[a]
        k = int(snap.obs_kf[o])
        model = models[int(oct_all[o])]
        if not known[k]:
            insert(graph, int(cam_key[k]), J_all[a:b], Z_all[:, a:b], model, cal)
            continue
        # No insert utility for these: one factor per observation from Python.
        camera = gtsam.PinholeCameraCal3_S2(gtsam.Pose3(snap.T_m_kf[k]), cal)
        zs = Z_all[:, a:b].T
        for j, z in zip(J_all[a:b].astype(np.int64).tolist(), zs, strict=True):
            graph.add(gtsam.TriangulationFactorCal3_S2(camera, z, model, j))

    prior = gtsam.noiseModel.Isotropic.Sigma(6, p.prior_sigma)
    for i in fixed:
        if not known[i]:
            graph.add(gtsam.PriorFactorPose3(int(cam_key[i]), gtsam.Pose3(snap.T_m_kf[i]), prior))
    partner = _gauge_partner(snap, fixed[0], kf_ok, obs_ok) if len(fixed) == 1 else -1
    if partner >= 0:
        d0 = float(np.linalg.norm(snap.T_m_kf[partner, :3, 3] - snap.T_m_kf[fixed[0], :3, 3]))
        if d0 > 0:
            graph.add(gtsam.RangeFactorPose3(
                int(cam_key[fixed[0]]), int(cam_key[partner]), d0,
                gtsam.noiseModel.Isotropic.Sigma(1, p.range_sigma_rel * d0)))  # fmt: skip
        else:
            partner = -1
    n_odo = _add_odometry(graph, snap, idx, cam_key)
    t_build = time.perf_counter() - t0

    rp0 = reprojection(snap.T_m_kf, snap.mp_pos, snap)
    ordering = _ordering(graph, cam_key[var].tolist(), p.ordering)
    opt = _optimizer(graph, values, ordering, p)
    e0 = opt.error()
    t_opt = time.perf_counter()
    it = 0
    e_prev = e0
    stop = "max_iters"
    errors = [e0]
    slowest = 0.0
    t_last = t_opt
    # One LM iteration at a time, so the time budget holds between iterations.
    while it < p.max_iters:
        opt.iterate()
        it += 1
        e = opt.error()
        errors.append(e)
        if log.isEnabledFor(logging.DEBUG):
            lam = opt.lambda_() if hasattr(opt, "lambda_") else float("nan")
            log.debug("BA it %d: error %.6g lambda %.3g %.2f s", it, e, lam,
                      time.perf_counter() - t_opt)  # fmt: skip
        if e_prev - e <= p.rel_tol * e_prev:
            stop = "converged"
            break
        e_prev = e
        # Do not start an iteration that would end past the budget (iterations cost
        # about the same; the slowest so far is the estimate).
        now = time.perf_counter()
        slowest = max(slowest, now - t_last)
        t_last = now
        if now - t0 + slowest > p.time_budget_s:
            stop = "time_budget"
            break
    t_iter = time.perf_counter() - t_opt
    result = opt.values()
    e1 = opt.error()

    T_new = snap.T_m_kf.copy()
    pos_new = snap.mp_pos.copy()
    if len(var):
        P = gtsam.utilities.extractPose3(result)  # rows in key order: R row-major, t
        T_new[var, :3, :3] = P[:, :9].reshape(-1, 3, 3)
        T_new[var, :3, 3] = P[:, 9:]
    if len(pts):
        pos_new[pts] = gtsam.utilities.extractPoint3(result)
    # Points left out (too little parallax, one observation) ride rigidly with their
    # reference keyframe, or they would no longer project where they were seen.
    rest = ~mp_ok
    if rest.any():
        ref = np.where(rest, point_ref_index(snap), -1)
        pos_new[rest] = correct_points(snap.mp_pos, ref, snap.T_m_kf, T_new)[rest]
    rp1 = reprojection(T_new, pos_new, snap)
    # Only observations the BA weighed are judged: the others' points never moved.
    out = ~(rp1.chi2 <= p.chi2_outlier) & kf_ok[snap.obs_kf] & mp_ok[snap.obs_mp]
    outliers = np.column_stack(
        [snap.kf_gids[snap.obs_kf[out]], snap.mp_gids[snap.obs_mp[out]]]
    ).astype(np.int64)
    inl = ~out & obs_ok

    def rmse(err: np.ndarray, m: np.ndarray) -> float:
        return float(np.sqrt(np.mean(err[m] ** 2))) if m.any() else float("nan")

    dt = time.perf_counter() - t0
    stats = {
        "ba_seconds": dt,
        "ba_build_seconds": t_build,
        "ba_iterate_seconds": t_iter,
        "ba_iterations": it,
        "ba_stop": stop,
        "ba_error_initial": float(e0),
        "ba_error_final": float(e1),
        "ba_errors": [float(x) for x in errors],
        "ba_rmse_px_initial": rmse(rp0.err_px, inl & np.isfinite(rp0.err_px)),
        "ba_rmse_px_final": rmse(rp1.err_px, inl),
        "ba_kfs": int(len(cam)),
        "ba_known_cameras": int(len(cam) - len(var)),
        "ba_points": int(len(pts)),
        "ba_observations": int(obs_ok.sum()),
        "ba_outliers": int(out.sum()),
        "ba_odometry_edges": n_odo,
        "ba_gauge": {"fixed": [int(snap.kf_gids[i]) for i in fixed],
                     "range_to": int(snap.kf_gids[partner]) if partner >= 0 else None},
    }  # fmt: skip
    log.info("global BA %s: %d kfs, %d pts, %d obs; error %.4g -> %.4g in %d it (%s), "
             "rmse %.3f -> %.3f px, %d outliers, %.2f s", snap.map_id, len(cam), len(pts),
             int(obs_ok.sum()), e0, e1, it, stop, stats["ba_rmse_px_initial"],
             stats["ba_rmse_px_final"], int(out.sum()), dt)  # fmt: skip
    return CorrectionMsg.of(snap, T_new, np.ones(K), pos_new, stats, outliers)


@dataclass
class GlobalParams:
    pgo: PGOParams = field(default_factory=PGOParams)
    ba: BAParams = field(default_factory=BAParams)
    run_pgo: bool = True  # skip when there is no loop edge (nothing to distribute)
    run_ba: bool = True

    @classmethod
    def from_settings(cls, o: OptimizerSettings, run_pgo: bool = True) -> GlobalParams:
        return cls(ba=BAParams.from_settings(o), run_pgo=run_pgo,
                   run_ba=o.ba and o.ba_max_iterations > 0)  # fmt: skip


def optimize_map(
    snap: OptimizeRequest,
    params: GlobalParams | None = None,
    between_stages: Callable[[], None] | None = None,
) -> CorrectionMsg:
    """CCM-SLAM §4.9: Sim(3) pose-graph optimization on the essential graph, then
    global BA from its result. The returned correction holds BA's poses and points and
    PGO's per-keyframe scales (what keyframes that arrive meanwhile need).
    ``between_stages`` runs after each stage; it may raise to abandon the run (the
    service does when a newer copy of the map arrived)."""
    p = params or GlobalParams()
    check = between_stages or (lambda: None)
    stats: dict = {}
    corr: CorrectionMsg | None = None
    if p.run_pgo:
        corr = optimize_pose_graph(snap, p.pgo)
        stats.update(corr.stats)
        snap = apply_to_snapshot(snap, corr)
        check()
    if p.run_ba:
        ba = bundle_adjust(snap, p.ba)
        stats.update(ba.stats)
        if corr is not None:
            ba.kf_scale = corr.kf_scale
        corr = ba
        check()
    if corr is None:
        K = snap.n_kf
        corr = CorrectionMsg.of(snap, snap.T_m_kf.copy(), np.ones(K), snap.mp_pos.copy())
    corr.stats = stats
    return corr
