"""Local bundle adjustment over a window of keyframes with GTSAM.

Poses are gtsam.Pose3 (camera to world), points Point3, measurements the
keypoints' undistorted coordinates scaled by the focal length (a Cal3_S2 with the
principal point at 0), with a Huber kernel. The two oldest window keyframes, and
every keyframe outside the window that sees a window point, are held fixed: they fix
the gauge, scale included. A fixed keyframe is no variable at all: its observations
are GTSAM's TriangulationFactor (a projection from a known camera onto the point).
As variables held by tight priors (before), the ~26 fixed keyframes of a job went
through every elimination: on 58 jobs of MH03 (~8,900 observations each) a BA took
111 ms that way and 67 ms this way, poses equal to 1e-8 (same iterations).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X


@dataclass
class BAResult:
    poses: dict[int, np.ndarray]  # kf id -> T_w_c
    points: dict[int, np.ndarray]  # mp id -> position
    outliers: list[tuple[int, int]]  # (kf id, mp id) observations to drop
    iterations: int
    error_before: float
    error_after: float


def local_ba(
    poses: dict[int, np.ndarray],
    fixed: set[int],
    points: dict[int, np.ndarray],
    obs: list[tuple[int, int, np.ndarray]],
    focal: float,
    sigma_px: float = 1.0,
    max_iters: int = 10,
    outlier_px: float = 4.0,
    should_stop: Callable[[], bool] | None = None,
) -> BAResult:
    """poses: kf id -> T_w_c (window and fixed ones); obs: (kf id, mp id, xy normalized).

    ``should_stop``: asked after each iteration; True ends the solve there (ORB-SLAM's
    abort of local BA when tracking inserts a keyframe), with the outlier check run on
    what the iterations so far gave."""
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    cal = gtsam.Cal3_S2(focal, focal, 0.0, 0.0, 0.0)
    huber = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(1.345),
        gtsam.noiseModel.Isotropic.Sigma(2, sigma_px),
    )
    cams = {}
    for k, T in poses.items():
        if k in fixed:
            cams[k] = gtsam.PinholeCameraCal3_S2(gtsam.Pose3(T), cal)
        else:
            values.insert(X(k), gtsam.Pose3(T))
    for j, p in points.items():
        values.insert(L(j), gtsam.Point3(*p))
    # The observations as arrays once: the factors take rows of the pixel array (an
    # Eigen vector each, no Point2 per factor) and the outlier check below is one
    # vectorized pass. Per observation in Python the two cost ~12 ms of a keyframe's
    # mapping on MH03 (163 ms then, 69 ms since fixed keyframes are known cameras;
    # bench/bench_async_ba.py; cProfile, which taxes each Python call, had made them
    # look like half); GTSAM's solve is most of the rest.
    ks, js, xys = zip(*obs, strict=True) if obs else ((), (), ())
    kf_of, mp_of = np.array(ks, np.int64), np.array(js, np.int64)
    xy_all = np.array(xys, np.float64).reshape(-1, 2)
    uv = focal * xy_all
    for i, (k, j) in enumerate(zip(kf_of.tolist(), mp_of.tolist(), strict=True)):
        cam = cams.get(k)
        if cam is None:
            graph.add(gtsam.GenericProjectionFactorCal3_S2(uv[i], huber, X(k), L(j), cal))
        else:
            graph.add(gtsam.TriangulationFactorCal3_S2(cam, uv[i], huber, L(j)))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iters)
    params.setRelativeErrorTol(1e-4)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    e0 = graph.error(values)
    result = _optimize(opt, params, max_iters, should_stop)
    out_poses = {k: result.atPose3(X(k)).matrix() for k in poses if k not in fixed}
    out_pts = {j: np.asarray(result.atPoint3(L(j))) for j in points}
    outliers = []
    if len(obs):
        kf_ids = list(poses)
        T_all = np.stack([out_poses.get(k, poses[k]) for k in kf_ids])
        row = {k: r for r, k in enumerate(kf_ids)}
        T = T_all[np.fromiter((row[k] for k in kf_of.tolist()), np.int64, count=len(obs))]
        P = np.stack([out_pts[j] for j in mp_of.tolist()])
        # Xc = R^T (p - t), per observation
        Xc = np.einsum("nji,nj->ni", T[:, :3, :3], P - T[:, :3, 3])
        z = Xc[:, 2]
        safe = np.where(z > 0, z, 1.0)
        err = np.linalg.norm(Xc[:, :2] / safe[:, None] - xy_all, axis=1) * focal
        bad = np.nonzero((z <= 0) | (err > outlier_px))[0]
        outliers = list(zip(kf_of[bad].tolist(), mp_of[bad].tolist(), strict=True))
    return BAResult(out_poses, out_pts, outliers, opt.iterations(), e0, graph.error(result))


def _optimize(
    opt: gtsam.LevenbergMarquardtOptimizer,
    params: gtsam.LevenbergMarquardtParams,
    max_iters: int,
    should_stop: Callable[[], bool] | None,
) -> gtsam.Values:
    """``opt.optimize()``, one iteration at a time when it may be stopped. The loop is
    GTSAM's own (NonlinearOptimizer::defaultOptimize: the same convergence test after
    each iteration), so a solve nobody stops gives the same values to the bit."""
    if should_stop is None:
        return opt.optimize()
    new = opt.error()
    if new <= params.getErrorTol():
        return opt.values()
    while True:
        cur = new
        opt.iterate()
        new = opt.error()
        if (opt.iterations() >= max_iters or not np.isfinite(cur)
                or gtsam.checkConvergence(params, cur, new) or should_stop()):  # fmt: skip
            return opt.values()
