"""Rigid and similarity transforms as plain numpy arrays.

Poses are 4x4 homogeneous matrices named for the frames they relate:
``T_w_c`` maps points from camera frame ``c`` into world frame ``w``.
A Sim(3) ``S_a_b`` is stored as the 4x4 matrix ``[[s R, t], [0, 1]]`` so that it
composes with ``@`` exactly like an SE(3) matrix; :class:`Sim3` wraps (R, t, s)
for the cases where the parts are needed.

scipy's Rotation handles quaternions; Umeyama is written here because neither
numpy, scipy nor OpenCV exposes a 3D similarity fit with scale for N points
(cv2.estimateAffine3D fits a full affine, evo's version lives behind its
trajectory classes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation


def se3(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def se3_inv(T: np.ndarray) -> np.ndarray:
    R = T[:3, :3]
    t = T[:3, 3]
    Ti = np.eye(4)
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ t
    return Ti


def relative(T_w_a: np.ndarray, T_w_b: np.ndarray) -> np.ndarray:
    """T_a_b: pose of b expressed in a."""
    return se3_inv(T_w_a) @ T_w_b


def transform_points(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a 4x4 (SE(3) or Sim(3)) matrix to an (N, 3) array."""
    pts = np.asarray(pts, dtype=float)
    return pts @ T[:3, :3].T + T[:3, 3]


def quat_xyzw_to_R(q: np.ndarray) -> np.ndarray:
    return Rotation.from_quat(np.asarray(q, dtype=float)).as_matrix()


def R_to_quat_xyzw(R: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(R).as_quat()


def pose_from_tq(t: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    return se3(quat_xyzw_to_R(q_xyzw), t)


def pose_to_tq(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return T[:3, 3].copy(), R_to_quat_xyzw(T[:3, :3])


def exp_so3(w: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(np.asarray(w, dtype=float)).as_matrix()


def log_so3(R: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(R).as_rotvec()


def rotation_angle(R: np.ndarray) -> float:
    """Angle of a rotation matrix in radians."""
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def sim3_in_units(S_q_c: np.ndarray, a_q: float, a_c: float) -> np.ndarray:
    """A place match's Sim(3) ``S_q_c`` (candidate camera -> query camera, ``p_q = s R
    p_c + t``) after the query's map units were scaled by ``a_q`` and the candidate's by
    ``a_c`` (a merge moved one of them): ``p_q' = (a_q s / a_c) R p_c' + a_q t``."""
    out = np.array(S_q_c, np.float64, copy=True)
    out[:3, :3] *= a_q / a_c
    out[:3, 3] *= a_q
    return out


def loop_residual(S_meas: np.ndarray, T_rest: np.ndarray) -> tuple[float, float]:
    """How far two keyframes' relative pose ``T_rest`` (SE(3)) is from a loop's
    constraint ``S_meas`` (Sim(3)): the rotation between them in degrees, and the
    distance between the translations as a share of the constraint's length (map units
    carry no metric scale; a floor of 1e-3 keeps a zero-length loop from dividing by
    zero)."""
    sR = S_meas[:3, :3]
    s = float(np.cbrt(np.linalg.det(sR)))
    R = sR / s if s > 0 else sR
    rot = float(np.degrees(rotation_angle(R.T @ T_rest[:3, :3])))
    t_meas = S_meas[:3, 3]
    trans = float(np.linalg.norm(T_rest[:3, 3] - t_meas) / max(np.linalg.norm(t_meas), 1e-3))
    return rot, trans


@dataclass(frozen=True)
class Sim3:
    """x_a = s * R @ x_b + t  for S_a_b."""

    R: np.ndarray
    t: np.ndarray
    s: float = 1.0

    @staticmethod
    def identity() -> Sim3:
        return Sim3(np.eye(3), np.zeros(3), 1.0)

    @staticmethod
    def from_matrix(S: np.ndarray) -> Sim3:
        A = S[:3, :3]
        s = float(np.cbrt(np.linalg.det(A)))
        return Sim3(A / s, S[:3, 3].copy(), s)

    def matrix(self) -> np.ndarray:
        S = np.eye(4)
        S[:3, :3] = self.s * self.R
        S[:3, 3] = self.t
        return S

    def inverse(self) -> Sim3:
        Ri = self.R.T
        return Sim3(Ri, -(Ri @ self.t) / self.s, 1.0 / self.s)

    def __matmul__(self, other: Sim3) -> Sim3:
        return Sim3(self.R @ other.R, self.s * (self.R @ other.t) + self.t, self.s * other.s)

    def apply(self, pts: np.ndarray) -> np.ndarray:
        return self.s * (np.asarray(pts, dtype=float) @ self.R.T) + self.t

    def transform_pose(self, T_b_c: np.ndarray) -> np.ndarray:
        """Map an SE(3) pose of frame c in b into a (rigid) pose in a: scale moves the
        translation only, the rotation stays a rotation."""
        T = np.eye(4)
        T[:3, :3] = self.R @ T_b_c[:3, :3]
        T[:3, 3] = self.s * (self.R @ T_b_c[:3, 3]) + self.t
        return T

    def to_array(self) -> np.ndarray:
        """8 floats: t (3), quaternion xyzw (4), s."""
        return np.concatenate([self.t, R_to_quat_xyzw(self.R), [self.s]])

    @staticmethod
    def from_array(a: np.ndarray) -> Sim3:
        a = np.asarray(a, dtype=float)
        return Sim3(quat_xyzw_to_R(a[3:7]), a[:3].copy(), float(a[7]))


def scale_translation(T_a_b: np.ndarray, s: float) -> np.ndarray:
    """A relative pose whose translation is measured in a map with scale factor s."""
    T = T_a_b.copy()
    T[:3, 3] *= s
    return T


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> Sim3:
    """Least-squares S such that dst ≈ S.apply(src) (Umeyama 1991)."""
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError("umeyama needs two (N>=3, 3) arrays of equal shape")
    mu_s = src.mean(axis=0)
    mu_d = dst.mean(axis=0)
    xs = src - mu_s
    xd = dst - mu_d
    n = len(src)
    cov = xd.T @ xs / n
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    if with_scale:
        var_s = (xs**2).sum() / n
        s = float(np.trace(np.diag(D) @ S) / var_s)
    else:
        s = 1.0
    t = mu_d - s * R @ mu_s
    return Sim3(R, t, s)


def fit_sim3_poses(T_a: np.ndarray, T_b: np.ndarray) -> Sim3 | None:
    """S_b_a with ``T_b ≈ S_b_a T_a`` for the same cameras posed in two frames ((N, 4, 4)
    rigid poses each): rotation as the chordal mean of ``R_b R_a^T``, scale from the
    spread of the camera centres about their mean, translation from the means.

    Unlike :func:`umeyama` on the centres, the rotation is fixed by the orientations,
    so it holds for a short, nearly straight stretch of flight. None when the centres
    have no spread to measure a scale from."""
    T_a = np.asarray(T_a, dtype=float)
    T_b = np.asarray(T_b, dtype=float)
    if T_a.shape != T_b.shape or T_a.ndim != 3 or len(T_a) < 2:
        raise ValueError("fit_sim3_poses needs two (N>=2, 4, 4) arrays of equal shape")
    M = np.einsum("nij,nkj->ik", T_b[:, :3, :3], T_a[:, :3, :3])
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    c_a, c_b = T_a[:, :3, 3], T_b[:, :3, 3]
    d_a = np.linalg.norm(c_a - c_a.mean(0), axis=1).sum()
    d_b = np.linalg.norm(c_b - c_b.mean(0), axis=1).sum()
    if d_a <= 1e-12 or d_b <= 1e-12:
        return None
    s = float(d_b / d_a)
    return Sim3(R, c_b.mean(0) - s * R @ c_a.mean(0), s)
