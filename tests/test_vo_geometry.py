"""On-board VO geometry on seeded synthetic correspondences, and local-map trimming."""

from __future__ import annotations

import numpy as np
import pytest

from services.agent.local_map_trim import KfInfo, trim
from services.agent.vo.geometry import solve_pnp, triangulate, two_view_init
from shared.geometry import exp_so3, rotation_angle, se3, se3_inv

F = 458.0


def _scene(rng, n=400, planar=False):
    if planar:
        P = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-2, 2, n), np.full(n, 5.0)])
    else:
        P = rng.uniform([-3, -2, 3], [3, 2, 9], (n, 3))
    return P


def _observe(T_w_c, P, rng, sigma_px=0.0):
    Xc = (P - T_w_c[:3, 3]) @ T_w_c[:3, :3]
    xy = Xc[:, :2] / Xc[:, 2:3]
    return xy + rng.normal(0, sigma_px / F, xy.shape)


@pytest.mark.parametrize("planar", [False, True])
def test_two_view_init_recovers_relative_pose_up_to_scale(planar):
    rng = np.random.default_rng(1)
    P = _scene(rng, planar=planar)
    T1 = np.eye(4)
    T2 = se3(exp_so3([0.02, -0.05, 0.01]), [0.6, 0.1, 0.05])
    xy1, xy2 = _observe(T1, P, rng, 0.5), _observe(T2, P, rng, 0.5)
    r = two_view_init(xy1, xy2, F)
    assert r.ok, r.reason
    assert r.model == ("homography" if planar else "essential")
    R_err = np.degrees(rotation_angle(r.T_c1_c2[:3, :3].T @ T2[:3, :3]))
    t_true = T2[:3, 3] / np.linalg.norm(T2[:3, 3])
    t_err = np.degrees(np.arccos(np.clip(r.T_c1_c2[:3, 3] @ t_true, -1, 1)))
    assert R_err < 0.3 and t_err < 2.0, (R_err, t_err)
    # Structure matches the truth up to the scale of the baseline.
    s = np.linalg.norm(T2[:3, 3])
    g = r.good
    assert g.sum() > 200
    err = np.linalg.norm(r.points[g] * s - P[g], axis=1) / np.linalg.norm(P[g], axis=1)
    assert np.median(err) < 0.02


def test_two_view_init_refuses_pure_rotation():
    rng = np.random.default_rng(2)
    P = _scene(rng)
    T2 = se3(exp_so3([0.0, 0.08, 0.0]), [0.0, 0.0, 0.0])
    r = two_view_init(_observe(np.eye(4), P, rng, 0.3), _observe(T2, P, rng, 0.3), F)
    assert not r.ok


def test_triangulation_recovers_known_points():
    rng = np.random.default_rng(3)
    P = _scene(rng, 300)
    T1 = se3(exp_so3([0.1, 0.2, -0.1]), [1.0, 2.0, -3.0])
    T2 = T1 @ se3(exp_so3([0.0, -0.03, 0.0]), [0.5, 0.0, 0.0])
    Pw = (P @ T1[:3, :3].T) + T1[:3, 3]
    tri = triangulate(T1, T2, _observe(T1, Pw, rng), _observe(T2, Pw, rng), F)
    assert tri.good.all()
    np.testing.assert_allclose(tri.points, Pw, atol=1e-6)
    # Points behind a camera and zero parallax are flagged.
    far = triangulate(T1, T1 @ se3(np.eye(3), [1e-6, 0, 0]), _observe(T1, Pw, rng),
                      _observe(T1, Pw, rng), F)  # fmt: skip
    assert not far.good.any()


def test_pnp_recovers_known_pose_with_outliers():
    rng = np.random.default_rng(4)
    P = _scene(rng, 300)
    T = se3(exp_so3([0.05, -0.1, 0.02]), [0.3, -0.2, 0.4])
    xy = _observe(T, P, rng, 0.5)
    bad = rng.choice(300, 60, replace=False)
    xy[bad] += rng.uniform(-0.2, 0.2, (60, 2))
    r = solve_pnp(P, xy, F)
    assert r.ok
    assert np.linalg.norm(r.T_w_c[:3, 3] - T[:3, 3]) < 0.01
    assert np.degrees(rotation_angle(r.T_w_c[:3, :3].T @ T[:3, :3])) < 0.1
    assert not r.inliers[bad].any() and r.inliers.sum() >= 230
    # From a motion-model guess (no RANSAC), the same answer.
    guess = T @ se3(exp_so3([0.01, 0, 0]), [0.05, 0, 0])
    r2 = solve_pnp(P, xy, F, T_guess=guess)
    assert r2.ok and np.linalg.norm(r2.T_w_c[:3, 3] - r.T_w_c[:3, 3]) < 1e-3
    assert np.allclose(se3_inv(r2.T_w_c) @ r.T_w_c, np.eye(4), atol=1e-3)


def _own(i, acked=False):
    return KfInfo(i, True, acked)


def test_trim_keeps_newest_and_ref_drops_acked():
    kfs = [_own(i, acked=i < 8) for i in range(12)]
    # N = 5: keep 8..11 and KF_ref 2; acked old ones (0, 1, 3..7) go; nothing unacked old.
    assert trim(kfs, kf_ref=2, n=5, b=5) == [0, 1, 3, 4, 5, 6, 7]


def test_trim_buffers_unacked_up_to_b():
    kfs = [_own(i) for i in range(12)]  # nothing acknowledged (server gone)
    assert trim(kfs, kf_ref=11, n=5, b=10) == []  # 12 <= N + B
    # N + B = 8: the 4 oldest unacknowledged keyframes are lost.
    assert trim(kfs, kf_ref=11, n=5, b=3) == [0, 1, 2, 3]


def test_trim_drops_foreign_keyframes_first():
    kfs = [_own(i) for i in range(8)] + [KfInfo(8, False, True), KfInfo(9, False, True)]
    kfs += [_own(10), _own(11)]
    # 12 > N + B = 9: foreign 8, 9 go first (even though they are recent), then own 0.
    assert trim(kfs, kf_ref=11, n=5, b=4) == [0, 8, 9]
    # KF_ref is never removed, even when it is a foreign keyframe.
    assert 9 not in trim(kfs, kf_ref=9, n=5, b=4)
