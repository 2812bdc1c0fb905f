"""Motion-only pose refinement of a keyframe against map points (CSfM §III-C).

OpenCV's Levenberg-Marquardt PnP does the optimization; this module adds the outlier
rejection rounds and the test of whether the refined pose is better supported by
the observations than the pose chained from the agent's odometry.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from shared.geometry import se3, se3_inv


@dataclass
class Refined:
    T_m_c: np.ndarray
    inliers: np.ndarray  # bool mask over the input correspondences
    rms_before_px: float
    rms_after_px: float
    accepted: bool


def _residuals_px(T_c_m: np.ndarray, xy: np.ndarray, P: np.ndarray, f: float) -> np.ndarray:
    X = P @ T_c_m[:3, :3].T + T_c_m[:3, 3]
    z = X[:, 2]
    bad = z <= 1e-6
    z = np.where(bad, 1.0, z)
    r = np.linalg.norm(X[:, :2] / z[:, None] - xy, axis=1) * f
    r[bad] = 1e6
    return r


def refine_pose(
    T_m_c: np.ndarray,
    xy: np.ndarray,
    P_m: np.ndarray,
    focal: float,
    thr_px: float = 3.0,
    min_inliers: int = 20,
    min_gain_px: float = 0.5,
) -> Refined:
    """Refine camera pose T_m_c from normalized image points ``xy`` (N, 2) observing
    map points ``P_m`` (N, 3). The result is accepted only with enough inliers and a
    lower inlier reprojection error than the initial pose."""
    T_c_m = se3_inv(T_m_c)
    r0 = _residuals_px(T_c_m, xy, P_m, focal)
    inl = r0 < thr_px * 3
    rms0 = float(np.sqrt(np.mean(np.minimum(r0, thr_px * 3) ** 2))) if len(r0) else np.inf
    if inl.sum() < min_inliers:
        return Refined(T_m_c, inl, rms0, rms0, False)
    rvec, _ = cv2.Rodrigues(T_c_m[:3, :3])
    tvec = T_c_m[:3, 3].reshape(3, 1).copy()
    K = np.eye(3)
    obj = np.ascontiguousarray(P_m, dtype=np.float64)
    img = np.ascontiguousarray(xy, dtype=np.float64)
    used = None
    for _ in range(3):
        if inl.sum() < min_inliers:
            break
        if used is not None and np.array_equal(inl, used):
            # The same inliers as the last solve, which started from a pose no better
            # than the one it returned: another solve would return that pose again (a
            # third of the map actor's pose-refinement time, bench_ramp --profile).
            break
        used = inl
        ok, rvec, tvec = cv2.solvePnP(
            obj[inl], img[inl], K, None, rvec, tvec,
            useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE,
        )  # fmt: skip
        if not ok:
            return Refined(T_m_c, inl, rms0, rms0, False)
        T_c_m1 = se3(cv2.Rodrigues(rvec)[0], tvec.ravel())
        r1 = _residuals_px(T_c_m1, xy, P_m, focal)
        inl = r1 < thr_px
    if inl.sum() < min_inliers:
        return Refined(T_m_c, inl, rms0, rms0, False)
    # Same inlier set for both, so the comparison is fair.
    rms_before = float(np.sqrt(np.mean(r0[inl] ** 2)))
    rms_after = float(np.sqrt(np.mean(r1[inl] ** 2)))
    # Gains below half a pixel fit noise (single-view point depths, float32 keypoints on the
    # wire), not a pose error: such a chained pose is kept as the agent sent it.
    accepted = rms_after < 0.99 * rms_before and rms_before - rms_after > min_gain_px
    T = se3_inv(T_c_m1) if accepted else T_m_c
    return Refined(T, inl, rms_before, rms_after, accepted)
