"""Geometry, camera model and trajectory math on seeded synthetic data."""

from __future__ import annotations

import numpy as np
import pytest

from shared.camera import CalibrationError, PinholeRadTan
from shared.geometry import (
    Sim3,
    exp_so3,
    se3,
    se3_inv,
    sim3_in_units,
    transform_points,
    umeyama,
)
from shared.keys import ALL_AGENT_KF, agent_kf, check_id
from shared.trajectory import Trajectory, ate, format_tum, load_euroc_gt, parse_tum


def _rand_sim3(rng) -> Sim3:
    return Sim3(exp_so3(rng.normal(size=3)), rng.normal(size=3) * 3, float(rng.uniform(0.3, 3)))


def test_sim3_compose_inverse_matrix():
    rng = np.random.default_rng(0)
    a, b = _rand_sim3(rng), _rand_sim3(rng)
    np.testing.assert_allclose((a @ b).matrix(), a.matrix() @ b.matrix(), atol=1e-12)
    np.testing.assert_allclose((a @ a.inverse()).matrix(), np.eye(4), atol=1e-12)
    c = Sim3.from_matrix(a.matrix())
    assert c.s == pytest.approx(a.s)
    np.testing.assert_allclose(Sim3.from_array(a.to_array()).matrix(), a.matrix(), atol=1e-12)


def test_se3_inverse_and_transform():
    rng = np.random.default_rng(1)
    T = se3(exp_so3(rng.normal(size=3)), rng.normal(size=3))
    np.testing.assert_allclose(T @ se3_inv(T), np.eye(4), atol=1e-12)
    p = rng.normal(size=(10, 3))
    np.testing.assert_allclose(transform_points(se3_inv(T), transform_points(T, p)), p, atol=1e-12)


def test_umeyama_recovers_similarity():
    rng = np.random.default_rng(2)
    S = _rand_sim3(rng)
    src = rng.normal(size=(50, 3))
    est = umeyama(src, S.apply(src))
    np.testing.assert_allclose(est.matrix(), S.matrix(), atol=1e-9)
    rigid = Sim3(S.R, S.t, 1.0)
    est = umeyama(src, rigid.apply(src), with_scale=False)
    np.testing.assert_allclose(est.matrix(), rigid.matrix(), atol=1e-9)


def test_camera_project_undistort_round_trip():
    cam = PinholeRadTan.euroc_cam0()
    rng = np.random.default_rng(3)
    X = rng.uniform([-3, -2, 2], [3, 2, 6], (2000, 3))
    uv, ok = cam.project(X)
    assert ok.sum() > 1000
    xy = cam.undistort_points(uv[ok])
    np.testing.assert_allclose(xy, X[ok, :2] / X[ok, 2:], atol=1e-9)
    # Against OpenCV's own projection with the same model.
    import cv2

    ref, _ = cv2.projectPoints(X[ok], np.zeros(3), np.zeros(3), cam.K, cam.dist)
    np.testing.assert_allclose(uv[ok], ref.reshape(-1, 2), atol=1e-6)
    assert not cam.project(np.array([[0.0, 0.0, -1.0]]))[1][0]


def test_calibration_errors_name_the_file(tmp_path):
    good = tmp_path / "sensor.yaml"
    good.write_text(PinholeRadTan.euroc_cam0().to_euroc_yaml())
    assert PinholeRadTan.from_yaml(good) == PinholeRadTan.euroc_cam0()
    bad = tmp_path / "bad.yaml"
    bad.write_text("camera_model: pinhole\nintrinsics: [1, 2]\n")
    with pytest.raises(CalibrationError, match="bad.yaml"):
        PinholeRadTan.from_yaml(bad)
    with pytest.raises(CalibrationError, match="missing.yaml"):
        PinholeRadTan.from_yaml(tmp_path / "missing.yaml")
    (tmp_path / "fish.yaml").write_text("camera_model: omni\n")
    with pytest.raises(CalibrationError, match="omni"):
        PinholeRadTan.from_yaml(tmp_path / "fish.yaml")


def test_gt_loads_and_tum_round_trip():
    gt = load_euroc_gt("MH01")
    assert len(gt) == 3638
    assert gt.path_length() == pytest.approx(80.6, abs=0.1)
    back = parse_tum(format_tum(gt.stamps_ns[:50], gt.poses[:50]))
    np.testing.assert_array_equal(back.stamps_ns, gt.stamps_ns[:50])
    np.testing.assert_allclose(back.poses, gt.poses[:50], atol=1e-8)


def test_ate_matches_evo():
    """Our Sim(3)-aligned ATE equals evo's (the field's reference implementation)."""
    from evo.core import metrics, sync
    from evo.core.trajectory import PoseTrajectory3D

    gt = load_euroc_gt("MH02")
    gt = Trajectory(gt.stamps_ns[::10], gt.poses[::10])
    rng = np.random.default_rng(4)
    S = Sim3(exp_so3([0.1, 0.2, 0.3]), np.array([1.0, 2.0, 3.0]), 0.5)
    est_poses = np.stack([S.transform_pose(T) for T in gt.poses])
    est_poses[:, :3, 3] += rng.normal(0, 0.05, (len(gt), 3))
    est = Trajectory(gt.stamps_ns.copy(), est_poses)
    ours = ate(est, gt)

    def to_evo(t: Trajectory) -> PoseTrajectory3D:
        return PoseTrajectory3D(poses_se3=list(t.poses), timestamps=t.stamps_ns * 1e-9)

    ref, e = sync.associate_trajectories(to_evo(gt), to_evo(est))
    e.align(ref, correct_scale=True)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, e))
    assert ours.rmse == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), rel=1e-6)
    assert ours.scale == pytest.approx(2.0, rel=0.05)


def test_key_expressions():
    import zenoh

    assert zenoh.KeyExpr(ALL_AGENT_KF).includes(zenoh.KeyExpr(agent_kf("drone-1")))
    for bad in ["", "a/b", "a*", "x" * 65, "a b"]:
        with pytest.raises(ValueError):
            check_id(bad)


def test_a_matchs_sim3_follows_its_maps_units():
    """Points of the candidate's camera in units scaled by a_c, of the query's by a_q:
    the converted Sim(3) maps the one onto the other as the original did before."""
    rng = np.random.default_rng(3)
    S = Sim3(exp_so3(np.array([0.2, -0.1, 0.3])), np.array([0.5, -1.0, 2.0]), 1.7)
    p_c = rng.normal(size=(20, 3))
    p_q = S.apply(p_c)
    a_q, a_c = 0.8, 2.5
    S2 = sim3_in_units(S.matrix(), a_q, a_c)
    got = (S2[:3, :3] @ (a_c * p_c).T).T + S2[:3, 3]
    np.testing.assert_allclose(got, a_q * p_q, atol=1e-12)
