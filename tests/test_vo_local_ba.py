"""Local bundle adjustment, projection-guided matching and spread ORB on seeded scenes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.agent.vo.ba_worker import BAWorker
from services.agent.vo.features import match_by_projection
from services.agent.vo.local_ba import local_ba
from shared.camera import PinholeRadTan
from shared.geometry import exp_so3, rotation_angle, se3
from shared.orb import Extractor, Features

F = 458.0


def _observe(T_w_c: np.ndarray, P: np.ndarray) -> np.ndarray:
    Xc = (P - T_w_c[:3, 3]) @ T_w_c[:3, :3]
    return Xc[:, :2] / Xc[:, 2:3]


def _scene(seed: int = 5):
    """Six keyframes over 250 points, three gross outliers, keyframes 0 and 1 fixed,
    the rest and the points perturbed: (truth, P, obs, fixed, bad, start, pts0)."""
    rng = np.random.default_rng(seed)
    n_kf, n_pts = 6, 250
    P = rng.uniform([-4, -3, 4], [4, 3, 10], (n_pts, 3))
    truth = {
        k: se3(exp_so3([0.0, 0.02 * k, 0.01 * k]), [0.2 * k, 0.02 * k, 0.0]) for k in range(n_kf)
    }
    obs = []
    for k, T in truth.items():
        xy = _observe(T, P) + rng.normal(0, 0.5 / F, (n_pts, 2))
        obs += [(k, j, xy[j]) for j in range(n_pts)]
    # Gross outliers on a few observations of window keyframes.
    bad = {(3, 7), (4, 11), (5, 19)}
    obs = [(k, j, xy + (0.05 if (k, j) in bad else 0.0)) for k, j, xy in obs]
    # Keyframes 0 and 1 are fixed (they fix the gauge and scale), the rest perturbed.
    fixed = {0, 1}
    start = {
        k: T if k in fixed else T @ se3(exp_so3(rng.normal(0, 0.01, 3)), rng.normal(0, 0.03, 3))
        for k, T in truth.items()
    }
    pts0 = {j: P[j] + rng.normal(0, 0.1, 3) for j in range(n_pts)}
    return truth, P, obs, fixed, bad, start, pts0


def test_local_ba_converges_to_ground_truth_from_perturbed_start():
    truth, P, obs, fixed, bad, start, pts0 = _scene()
    n_pts = len(P)
    r = local_ba(start, fixed, pts0, obs, F, max_iters=10)
    assert set(r.poses) == set(truth) - fixed
    assert r.error_after < 0.05 * r.error_before
    # Converged: the same optimum as when started at the truth (the noise floor) ...
    ref = local_ba(truth, fixed, dict(enumerate(P)), obs, F, max_iters=10)
    for k, T in r.poses.items():
        assert np.linalg.norm(T[:3, 3] - ref.poses[k][:3, 3]) < 2e-4, k
        assert np.degrees(rotation_angle(T[:3, :3].T @ ref.poses[k][:3, :3])) < 2e-3, k
        # ... and that optimum is near the truth (0.5 px noise, 4-10 m depth).
        assert np.linalg.norm(T[:3, 3] - truth[k][:3, 3]) < 0.015, k
        assert np.degrees(rotation_angle(T[:3, :3].T @ truth[k][:3, :3])) < 0.1, k
    got = np.array([r.points[j] for j in range(n_pts)])
    want = np.array([ref.points[j] for j in range(n_pts)])
    assert np.percentile(np.linalg.norm(got - want, axis=1), 95) < 2e-3
    # Depth noise grows as z^2: compare relative to distance (about 0.5 % here).
    rel = np.linalg.norm(got - P, axis=1) / np.linalg.norm(P, axis=1)
    assert np.median(rel) < 0.01
    # The corrupted observations (~23 px) come back as outliers, and few others do.
    assert bad <= set(r.outliers) and len(r.outliers) <= len(bad) + 3


def _features(uv: np.ndarray, desc: np.ndarray) -> Features:
    n = len(uv)
    return Features(uv.astype(np.float32), np.zeros(n, np.uint8), desc, np.zeros((n, 2)))


def test_local_ba_stopped_after_an_iteration_and_unstopped_one_step_at_a_time():
    _, _, obs, fixed, _, start, pts0 = _scene()
    whole = local_ba(start, fixed, pts0, obs, F, max_iters=10)
    assert whole.iterations > 2
    # Stepped by hand with nobody stopping it: GTSAM's own loop, the same bits.
    stepped = local_ba(start, fixed, pts0, obs, F, max_iters=10, should_stop=lambda: False)
    assert stepped.iterations == whole.iterations
    for k in whole.poses:
        assert np.array_equal(stepped.poses[k], whole.poses[k])
    assert stepped.outliers == whole.outliers
    # Stopped: one iteration, already downhill, and its outlier check still made.
    once = local_ba(start, fixed, pts0, obs, F, max_iters=10, should_stop=lambda: True)
    assert once.iterations == 1
    assert whole.error_after < once.error_after < once.error_before


def test_ba_worker_abort_ends_the_running_solve_and_hands_back_what_it_got():
    _, _, obs, fixed, _, start, pts0 = _scene()
    job = {"poses": start, "fixed": fixed, "points": pts0, "obs": obs, "focal": F,
           "max_iters": 10}  # fmt: skip
    w = BAWorker()
    try:
        w.submit(job)
        whole = w.result(wait=True)
        w.abort()  # nothing running: no effect on the next job
        w.submit(job)
        assert w.busy
        w.abort()
        cut = w.result(wait=True)
        assert not w.busy
        # The same job again, not aborted: the flag was cleared at submit.
        w.submit(job)
        again = w.result(wait=True)
    finally:
        w.close()
    assert whole.iterations > 2 and again.iterations == whole.iterations
    # Set before or during the worker's first iteration: it stops after that one.
    assert cut.iterations == 1 and cut.error_after > whole.error_after
    assert set(cut.poses) == set(whole.poses)


def test_match_by_projection_finds_true_keypoint_within_radius():
    rng = np.random.default_rng(9)
    n_kp = 1000
    kp = rng.uniform([0, 0], [752, 480], (n_kp, 2))
    desc = rng.integers(0, 256, (n_kp, 32), dtype=np.uint8)
    feats = _features(kp, desc)
    truth = rng.choice(n_kp, 300, replace=False)
    # Map points predicted 0-4 px from their keypoint, descriptors a few bits off.
    uv = kp[truth] + rng.uniform(-3, 3, (300, 2))
    mdesc = desc[truth].copy()
    flip = rng.integers(0, 32, (300, 3))
    np.bitwise_xor.at(mdesc, (np.arange(300)[:, None], flip), np.uint8(1))
    pi, ki = match_by_projection(feats, uv, mdesc, radius=8.0)
    assert len(pi) >= 290
    assert np.array_equal(ki, truth[pi])
    assert len(np.unique(ki)) == len(ki)
    # Predictions far from their keypoint (beyond the radius) must not match it.
    pi2, ki2 = match_by_projection(feats, kp[truth] + 30.0, mdesc, radius=8.0)
    assert not np.any(ki2 == truth[pi2])


def _texture(rng: np.random.Generator, contrast: float, h: int = 480, w: int = 752) -> np.ndarray:
    # Full texture in the left quarter, ``contrast`` of it elsewhere: plain ORB clusters left.
    img = cv2.GaussianBlur(rng.integers(0, 256, (h, w), dtype=np.uint8), (5, 5), 1.5)
    img = img.astype(np.float32)
    img[:, w // 4 :] = 128 + contrast * (img[:, w // 4 :] - 128)
    return np.clip(img, 0, 255).astype(np.uint8)


def test_extractor_spreads_keypoints_and_undistorts():
    rng = np.random.default_rng(2)
    cam = PinholeRadTan.euroc_cam0()
    img = _texture(rng, 0.8, cam.height, cam.width)
    f = Extractor(cam, n_features=500)(img)
    assert len(f) == 500
    assert f.kp.dtype == np.float32 and f.desc.shape == (len(f), 32) and f.octave.dtype == np.uint8
    # Keypoints reach every column band of the 8x6 grid, not only the textured quarter.
    cols = np.minimum(f.kp[:, 0] * 8 // cam.width, 7).astype(int)
    counts = np.bincount(cols, minlength=8)
    assert (counts > 0).all(), counts
    plain = cv2.ORB_create(500, 1.2, 8, 19, 0, 2, cv2.ORB_HARRIS_SCORE, 31, 12).detect(img, None)
    plain_left = np.mean([p.pt[0] < cam.width / 4 for p in plain])
    assert counts[:2].sum() / len(f) < 0.7 * plain_left
    # Normalized coordinates re-project onto the distorted keypoints.
    uv, valid = cam.project(np.column_stack([f.xy, np.ones(len(f))]))
    assert valid.all()
    np.testing.assert_allclose(uv, f.kp, atol=0.05)


@pytest.mark.xfail(
    strict=True,
    reason="no per-cell FAST threshold fallback (ORB-SLAM's minThFAST): the candidate pool "
    "is ORB's global top 2n, so weakly textured cells get no keypoints at all",
)
def test_extractor_reaches_weakly_textured_cells():
    rng = np.random.default_rng(2)
    cam = PinholeRadTan.euroc_cam0()
    f = Extractor(cam, n_features=500)(_texture(rng, 0.5, cam.height, cam.width))
    cols = np.minimum(f.kp[:, 0] * 8 // cam.width, 7).astype(int)
    assert (np.bincount(cols, minlength=8) >= 10).all()


def test_late_local_ba_moves_what_was_tracked_meanwhile_with_its_keyframe():
    """A local BA that comes back from its worker after tracking went on: the window
    takes the BA's poses, and the last tracked pose, a keyframe made meanwhile and the
    points that keyframe added move rigidly with the window's newest keyframe (so the
    motion model keeps predicting from where the moved map says the camera is). Points
    the BA placed keep the BA's positions; the server's points stay."""
    from services.agent.vo.local_ba import BAResult
    from services.agent.vo.odometry import KeyFrame, MapPoint, VisualOdometry

    vo = VisualOdometry(PinholeRadTan(752, 480, F, F, 376.0, 240.0))
    feats = _features(np.zeros((4, 2)), np.zeros((4, 32), np.uint8))
    for k in range(4):  # 0, 1 fixed; 2 in the BA window; 3 made while the BA ran
        vo.kfs[k] = KeyFrame(k, k, se3(np.eye(3), [0.1 * k, 0, 0]), feats, np.full(4, -1))
    d0 = np.zeros(32, np.uint8)
    vo.mps = {i: MapPoint(i, np.array([float(i), 0, 5]), d0, first_kf=kf)
              for i, kf in ((0, 0), (1, 3), (2, 3))}  # fmt: skip
    vo.foreign[2] = ("other", 7)
    vo.T_last = se3(np.eye(3), [0.35, 0, 0])
    vo.velocity = se3(np.eye(3), [0.05, 0, 0])
    delta = se3(exp_so3([0.0, 0.01, 0.0]), [0.0, 0.02, 0.0])
    moved = delta @ vo.kfs[2].T_w_c
    kf2, kf3, T_last = vo.kfs[2].T_w_c.copy(), vo.kfs[3].T_w_c.copy(), vo.T_last.copy()
    vo._apply_ba(BAResult({2: moved}, {0: np.array([0.0, 0.01, 5])}, [], 3, 1.0, 0.5))
    assert np.allclose(vo.kfs[2].T_w_c, moved)
    assert np.allclose(vo.kfs[3].T_w_c, delta @ kf3)
    assert np.allclose(vo.T_last, delta @ T_last)
    # Relative to the moved keyframe, the last pose and the prediction are unchanged.
    assert np.allclose(np.linalg.inv(vo.kfs[2].T_w_c) @ vo.T_last, np.linalg.inv(kf2) @ T_last)
    assert np.allclose(vo.mps[0].pos, [0.0, 0.01, 5])  # the BA's own
    assert np.allclose(vo.mps[1].pos, delta[:3, :3] @ [1.0, 0, 5] + delta[:3, 3])
    assert np.allclose(vo.mps[2].pos, [2.0, 0, 5])  # the server's
    assert vo.ba_applied == [([2], [0])]
