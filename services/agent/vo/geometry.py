"""Multi-view geometry of the on-board VO, on undistorted normalized coordinates.

OpenCV does the estimation (USAC_MAGSAC essential matrix and homography, SQPNP /
iterative PnP); this module adds what ORB-SLAM adds around them: model selection
between E and H, cheirality and parallax checks, and a vectorized DLT
triangulation that reports per-point quality.

Conventions: ``T_w_c`` maps camera to world; ``xy`` are normalized image
coordinates (x/z, y/z) from ``PinholeRadTan.undistort_points``; thresholds in
pixels are divided by the focal length.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from shared.geometry import se3, se3_inv


@dataclass
class Triangulated:
    points: np.ndarray  # (N, 3) world
    good: np.ndarray  # (N,) bool: in front of both cameras, small error, enough parallax
    parallax_deg: np.ndarray  # (N,)
    err_px: np.ndarray  # (N,) max reprojection error of the two views


def triangulate(
    T_w_c1: np.ndarray,
    T_w_c2: np.ndarray,
    xy1: np.ndarray,
    xy2: np.ndarray,
    focal: float = 458.0,
    max_err_px: float = 2.0,
    min_parallax_deg: float = 1.0,
) -> Triangulated:
    """Linear (DLT) triangulation of N correspondences, vectorized with one batched SVD."""
    P1 = se3_inv(T_w_c1)[:3]
    P2 = se3_inv(T_w_c2)[:3]
    n = len(xy1)
    A = np.empty((n, 4, 4))
    A[:, 0] = xy1[:, :1] * P1[2] - P1[0]
    A[:, 1] = xy1[:, 1:2] * P1[2] - P1[1]
    A[:, 2] = xy2[:, :1] * P2[2] - P2[0]
    A[:, 3] = xy2[:, 1:2] * P2[2] - P2[1]
    _, _, Vt = np.linalg.svd(A)
    Xh = Vt[:, -1]
    w = Xh[:, 3:4]
    w = np.where(np.abs(w) < 1e-12, 1e-12, w)
    X = Xh[:, :3] / w
    X1 = X @ P1[:, :3].T + P1[:, 3]
    X2 = X @ P2[:, :3].T + P2[:, 3]
    front = (X1[:, 2] > 0) & (X2[:, 2] > 0)
    z1 = np.where(front, X1[:, 2], 1.0)
    z2 = np.where(front, X2[:, 2], 1.0)
    e1 = np.linalg.norm(X1[:, :2] / z1[:, None] - xy1, axis=1)
    e2 = np.linalg.norm(X2[:, :2] / z2[:, None] - xy2, axis=1)
    err = np.maximum(e1, e2) * focal
    r1 = X - T_w_c1[:3, 3]
    r2 = X - T_w_c2[:3, 3]
    cosp = np.einsum("ij,ij->i", r1, r2) / (
        np.linalg.norm(r1, axis=1) * np.linalg.norm(r2, axis=1) + 1e-12
    )
    par = np.degrees(np.arccos(np.clip(cosp, -1, 1)))
    good = front & (err < max_err_px) & (par >= min_parallax_deg) & np.isfinite(X).all(axis=1)
    return Triangulated(X, good, par, err)


@dataclass
class TwoView:
    ok: bool
    reason: str
    model: str = ""  # "essential" or "homography"
    T_c1_c2: np.ndarray | None = None  # pose of camera 2 in camera 1, |t| = 1
    points: np.ndarray | None = None  # (N, 3) in camera 1, for inlier & good matches
    good: np.ndarray | None = None  # (N,) bool over the input correspondences
    median_parallax_deg: float = 0.0


def _pose_candidates_score(R: np.ndarray, t: np.ndarray, xy1, xy2, focal, thr_px):
    T_c1_c2 = se3(R.T, -R.T @ t.ravel())  # recoverPose gives x2 = R x1 + t
    tri = triangulate(np.eye(4), T_c1_c2, xy1, xy2, focal, thr_px * 2, 0.0)
    return tri.good.sum(), T_c1_c2, tri


def two_view_init(
    xy1: np.ndarray,
    xy2: np.ndarray,
    focal: float,
    thr_px: float = 1.0,
    min_inliers: int = 80,
    min_parallax_deg: float = 1.0,
    seed: int = 0,
) -> TwoView:
    """Relative pose and structure from two views (ORB-SLAM's initializer, on OpenCV).

    Both an essential matrix and a homography are fitted with MAGSAC; the
    homography wins when R_H = S_H / (S_H + S_E) > 0.45 (planar or low-parallax
    scene). The pose is the decomposition with most points in front of both
    cameras; initialization fails without enough parallax or inliers."""
    if len(xy1) < min_inliers:
        return TwoView(False, f"only {len(xy1)} matches")
    cv2.setRNGSeed(seed)
    # MAGSAC in pixel units: on normalized coordinates (thresholds ~1e-3) it keeps too
    # few inliers when a fifth of the matches are wrong (tests/test_vo_init_outliers.py).
    Kf = np.diag([focal, focal, 1.0])
    p1, p2 = xy1 * focal, xy2 * focal
    E, me = cv2.findEssentialMat(p1, p2, Kf, cv2.USAC_MAGSAC, 0.999, thr_px)
    H, mh = cv2.findHomography(p1, p2, cv2.USAC_MAGSAC, thr_px * 2, maxIters=2000,
                               confidence=0.999)  # fmt: skip
    if H is not None:
        H = np.linalg.inv(Kf) @ H @ Kf
    se = 0 if me is None else int(me.sum())
    sh = 0 if mh is None else int(mh.sum())
    if E is None and H is None:
        return TwoView(False, "no model")
    use_h = H is not None and (E is None or sh / max(sh + se, 1) > 0.45)
    best = None
    if use_h:
        inl = mh.ravel().astype(bool)
        n, Rs, ts, _ = cv2.decomposeHomographyMat(H, np.eye(3))
        for R, t in zip(Rs, ts, strict=True):
            if np.linalg.norm(t) < 1e-9:
                continue
            cand = _pose_candidates_score(
                R, t / np.linalg.norm(t), xy1[inl], xy2[inl], focal, thr_px
            )
            if best is None or cand[0] > best[0]:
                best = cand
        model = "homography"
    else:
        E = E[:3]
        inl = me.ravel().astype(bool)
        _, R, t, _ = cv2.recoverPose(E, xy1[inl], xy2[inl], np.eye(3))
        best = _pose_candidates_score(R, t / np.linalg.norm(t), xy1[inl], xy2[inl], focal, thr_px)
        model = "essential"
    if best is None:
        return TwoView(False, "no valid decomposition", model)
    n_good, T_c1_c2, tri = best
    good = np.zeros(len(xy1), bool)
    idx = np.nonzero(inl)[0]
    good[idx[tri.good]] = True
    par = float(np.median(tri.parallax_deg[tri.good])) if n_good else 0.0
    if n_good < min_inliers:
        return TwoView(False, f"{n_good} triangulated points < {min_inliers}", model)
    if par < min_parallax_deg:
        return TwoView(False, f"median parallax {par:.2f} deg < {min_parallax_deg}", model)
    pts = np.full((len(xy1), 3), np.nan)
    pts[idx] = tri.points
    return TwoView(True, "ok", model, T_c1_c2, pts, good, par)


@dataclass
class PnPResult:
    ok: bool
    T_w_c: np.ndarray
    inliers: np.ndarray  # (N,) bool
    rms_px: float


def solve_pnp(
    P_w: np.ndarray,
    xy: np.ndarray,
    focal: float,
    T_guess: np.ndarray | None = None,
    thr_px: float = 2.0,
    min_inliers: int = 15,
) -> PnPResult:
    """Camera pose from 3D points and their normalized observations: MAGSAC-style
    RANSAC (cv2.solvePnPRansac, SQPNP minimal solver) unless a motion-model guess is
    given, then iterative LM on the inliers with a second outlier pass."""
    P = np.ascontiguousarray(P_w, np.float64)
    x = np.ascontiguousarray(xy, np.float64)
    K = np.eye(3)
    thr = thr_px / focal
    if T_guess is None:
        if len(P) < 6:
            return PnPResult(False, np.eye(4), np.zeros(len(P), bool), np.inf)
        ok, rvec, tvec, inl = cv2.solvePnPRansac(P, x, K, None, reprojectionError=thr,
                                                 iterationsCount=200, confidence=0.999,
                                                 flags=cv2.SOLVEPNP_SQPNP)  # fmt: skip
        if not ok or inl is None:
            return PnPResult(False, np.eye(4), np.zeros(len(P), bool), np.inf)
        mask = np.zeros(len(P), bool)
        mask[inl.ravel()] = True
    else:
        T_c_w = se3_inv(T_guess)
        rvec, _ = cv2.Rodrigues(T_c_w[:3, :3])
        tvec = T_c_w[:3, 3].reshape(3, 1).copy()
        # Gross outliers are cut at the guess already; LM is not robust.
        mask = _errors(P, x, cv2.Rodrigues(rvec)[0], tvec, focal) < max(8 * thr_px, 10.0)
    for _ in range(3):
        if mask.sum() < min_inliers:
            return PnPResult(False, np.eye(4), mask, np.inf)
        ok, rvec, tvec = cv2.solvePnP(
            P[mask], x[mask], K, None, rvec, tvec,
            useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE,
        )  # fmt: skip
        R = cv2.Rodrigues(rvec)[0]
        err = _errors(P, x, R, tvec, focal)
        mask = err < thr_px
    rms = float(np.sqrt(np.mean(err[mask] ** 2))) if mask.any() else np.inf
    T_w_c = se3_inv(se3(R, tvec.ravel()))
    return PnPResult(bool(mask.sum() >= min_inliers), T_w_c, mask, rms)


def _errors(P: np.ndarray, x: np.ndarray, R: np.ndarray, tvec: np.ndarray, focal: float):
    """Reprojection errors in pixels; points behind the camera get +inf."""
    Xc = P @ R.T + tvec.ravel()
    z = np.where(Xc[:, 2] > 1e-6, Xc[:, 2], np.nan)
    err = np.linalg.norm(Xc[:, :2] / z[:, None] - x, axis=1) * focal
    return np.nan_to_num(err, nan=np.inf)
