"""Server points in tracking: they count only where they agree with the agent's own."""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

from services.agent.vo.geometry import solve_pnp
from services.agent.vo.odometry import VisualOdometry
from shared.camera import PinholeRadTan
from shared.geometry import exp_so3, rotation_angle, se3, se3_inv
from shared.orb import Features


def _scene(rng, n: int, T_w_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """n points 2-8 m in front of the camera and their exact normalized observations."""
    Xc = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-2, 2, n), rng.uniform(2, 8, n)])
    P_w = Xc @ T_w_c[:3, :3].T + T_w_c[:3, 3]
    return P_w, Xc[:, :2] / Xc[:, 2:]


def test_foreign_points_off_by_a_scale_are_dropped_and_do_not_bias_the_pose():
    rng = np.random.default_rng(3)
    T = se3(exp_so3(np.array([0.05, -0.1, 0.02])), np.array([0.3, -0.2, 1.0]))
    P_own, xy_own = _scene(rng, 120, T)
    P_for, xy_for = _scene(rng, 300, T)
    # The server's points came through a similarity 4 % off in scale about KF_ref (0.5 m
    # behind the camera): coherent, so a joint RANSAC keeps many of them.
    c = T[:3, 3] - 0.5 * T[:3, 2]
    P_for = c + 1.04 * (P_for - c)
    xy_own = xy_own + rng.normal(0, 0.3 / 458.0, xy_own.shape)
    P = np.vstack([P_own, P_for])
    xy = np.vstack([xy_own, xy_for])
    vo = VisualOdometry(PinholeRadTan.euroc_cam0())
    n_own = len(P_own)
    vo.foreign = OrderedDict((i, ("other", i)) for i in range(n_own, len(P)))
    pids = np.arange(len(P))
    pi, kp = np.arange(len(P)), np.arange(len(P))
    f = Features(np.zeros((len(P), 2), np.float32), np.zeros(len(P), np.uint8),
                 np.zeros((len(P), 32), np.uint8), xy)  # fmt: skip
    joint = solve_pnp(P, xy, vo.cam.fx, T_guess=T)
    res, pi2, kp2 = vo._gate_foreign(f, joint, pids, pi, kp, P)

    def err(T_est):
        d = se3_inv(T) @ T_est
        return np.linalg.norm(d[:3, 3]), np.rad2deg(rotation_angle(d[:3, :3]))

    assert err(res.T_w_c)[0] < 0.5 * err(joint.T_w_c)[0]
    assert err(res.T_w_c)[0] < 0.01
    # Those kept reproject within the gate at the agent's pose; the worst are gone.
    kept = pi2[np.isin(pi2, list(vo.foreign))]
    Xc = (P[kept] - res.T_w_c[:3, 3]) @ res.T_w_c[:3, :3]
    px = np.linalg.norm(Xc[:, :2] / Xc[:, 2:] - xy[kept], axis=1) * vo.cam.fx
    assert len(kept) < len(P_for) and px.max() < 2.0
    # Consistent server points stay.
    vo.foreign = OrderedDict((i, ("other", i)) for i in range(n_own, len(P)))
    P_ok = np.vstack([P_own, _scene(np.random.default_rng(4), 300, T)[0]])
    xy_ok = np.vstack([xy_own, _scene(np.random.default_rng(4), 300, T)[1]])
    f_ok = Features(f.kp, f.octave, f.desc, xy_ok)
    r = solve_pnp(P_ok, xy_ok, vo.cam.fx, T_guess=T)
    _, pi3, _ = vo._gate_foreign(f_ok, r, pids, pi, kp, P_ok)
    assert np.isin(pi3, list(vo.foreign)).sum() >= 0.95 * 300
