"""Local bundle adjustment over a window of keyframes with GTSAM.

Poses are gtsam.Pose3 (camera to world), points Point3, measurements the
keypoints' undistorted coordinates scaled by the focal length (a Cal3_S2 with the
principal point at 0), with a Huber kernel. The two oldest window keyframes, and
every keyframe outside the window that sees a window point, are held by tight
priors: they fix the gauge, scale included.
"""

from __future__ import annotations

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
) -> BAResult:
    """poses: kf id -> T_w_c (window and fixed ones); obs: (kf id, mp id, xy normalized)."""
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    cal = gtsam.Cal3_S2(focal, focal, 0.0, 0.0, 0.0)
    huber = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(1.345),
        gtsam.noiseModel.Isotropic.Sigma(2, sigma_px),
    )
    tight = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
    for k, T in poses.items():
        values.insert(X(k), gtsam.Pose3(T))
        if k in fixed:
            graph.add(gtsam.PriorFactorPose3(X(k), gtsam.Pose3(T), tight))
    for j, p in points.items():
        values.insert(L(j), gtsam.Point3(*p))
    for k, j, xy in obs:
        graph.add(gtsam.GenericProjectionFactorCal3_S2(
            gtsam.Point2(focal * xy[0], focal * xy[1]), huber, X(k), L(j), cal))  # fmt: skip
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iters)
    params.setRelativeErrorTol(1e-4)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    e0 = graph.error(values)
    result = opt.optimize()
    out_poses = {k: result.atPose3(X(k)).matrix() for k in poses if k not in fixed}
    out_pts = {j: np.asarray(result.atPoint3(L(j))) for j in points}
    outliers = []
    for k, j, xy in obs:
        T = result.atPose3(X(k)).matrix() if k not in fixed else poses[k]
        Xc = T[:3, :3].T @ (out_pts[j] - T[:3, 3])
        if Xc[2] <= 0 or np.linalg.norm(Xc[:2] / Xc[2] - xy) * focal > outlier_px:
            outliers.append((k, j))
    return BAResult(out_poses, out_pts, outliers, opt.iterations(), e0, graph.error(result))
