"""Robust motion-only pose refinement on seeded synthetic 2D-3D matches."""

from __future__ import annotations

import numpy as np

from services.agent.vo.pose import refine_pose
from shared.geometry import exp_so3, rotation_angle, se3

F = 458.0


def _scene(seed: int, n: int = 300, n_bad: int = 60):
    rng = np.random.default_rng(seed)
    P = rng.uniform([-3, -2, 3], [3, 2, 9], (n, 3))
    T = se3(exp_so3([0.05, -0.1, 0.02]), [0.3, -0.2, 0.4])
    Xc = (P - T[:3, 3]) @ T[:3, :3]
    xy = Xc[:, :2] / Xc[:, 2:3] + rng.normal(0, 0.5 / F, (n, 2))
    bad = rng.choice(n, n_bad, replace=False)
    # Wrong matches from the projection search: 5-30 px off.
    off = rng.uniform(5, 30, n_bad) / F
    ang = rng.uniform(0, 2 * np.pi, n_bad)
    xy[bad] += np.column_stack([np.cos(ang), np.sin(ang)]) * off[:, None]
    return P, xy, T, bad


def test_refine_pose_recovers_known_pose_and_rejects_outliers():
    P, xy, T, bad = _scene(4)
    # A constant-velocity guess a few cm and ~1 degree off.
    guess = T @ se3(exp_so3([0.01, -0.015, 0.005]), [0.04, -0.03, 0.05])
    r = refine_pose(guess, P, xy, F)
    assert np.linalg.norm(r.T_w_c[:3, 3] - T[:3, 3]) < 5e-3
    assert np.degrees(rotation_angle(r.T_w_c[:3, :3].T @ T[:3, :3])) < 0.05
    assert not r.inliers[bad].any()
    good = np.setdiff1d(np.arange(len(P)), bad)
    assert r.inliers[good].mean() > 0.93
    assert r.rms_px < 1.0


def test_refine_pose_per_point_sigma_and_too_few_points():
    P, xy, T, bad = _scene(5, n=200, n_bad=0)
    sigma = np.full(len(P), 1.0)
    sigma[::2] = 1.2**3  # high pyramid octave: less weight, wider gate
    r = refine_pose(T @ se3(np.eye(3), [0.02, 0, 0]), P, xy, F, sigma_px=sigma)
    assert np.linalg.norm(r.T_w_c[:3, 3] - T[:3, 3]) < 5e-3
    assert r.inliers.mean() > 0.95
    # Points behind the camera are never inliers.
    Pb = P.copy()
    Pb[:5, 2] = -Pb[:5, 2] + 2 * T[2, 3]
    r2 = refine_pose(T, Pb, xy, F)
    assert not r2.inliers[:5].any()
    # With fewer points than min_inliers the guess comes back untouched.
    r3 = refine_pose(T, P[:5], xy[:5], F)
    np.testing.assert_allclose(r3.T_w_c, T, atol=1e-12)
