"""Global optimization: Sim(3) pose graph, global BA, snapshots, and applying a
correction to a live server map (CCM-SLAM §4.9, Fig. 4). Seeded synthetic scenes."""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
import pytest

from services.mapper.capture import request_from_map as snapshot_from_map
from services.mapper.correction import apply_correction
from services.mapper.server_map import ServerKeyframe, ServerMap, ServerMapPoint
from services.optimizer.global_ba import BAParams, bundle_adjust, optimize_map, reprojection
from services.optimizer.pose_graph import (
    correct_points,
    from_gtsam,
    optimize_pose_graph,
    pose_scale_to_sim3,
    to_gtsam,
)
from shared.camera import EUROC_FX
from shared.geometry import Sim3, exp_so3, scale_translation, se3, se3_inv, umeyama
from shared.messages import CorrectionMsg, OptimizeRequest

FX = 458.0


def MapSnapshot(map_id, version, kf_gids, T_m_kf, fixed_gids, edges, loops, S_loop, mp_gids,
                mp_pos, mp_ref, obs_kf, obs_mp, obs_xy, obs_octave,
                fx=EUROC_FX) -> OptimizeRequest:  # fmt: skip
    """The map copy the optimizer takes, in the argument order these tests write."""
    return OptimizeRequest(
        map_id=map_id, version=version, reason="test", sent_ns=0, fx=fx, kf_gids=kf_gids,
        T_m_kf=T_m_kf, fixed_gids=fixed_gids, edges=edges, loops=loops, S_loop=S_loop,
        mp_gids=mp_gids, mp_pos=mp_pos, mp_ref=mp_ref, obs_kf=obs_kf, obs_mp=obs_mp,
        obs_xy=obs_xy, obs_octave=obs_octave,
    )  # fmt: skip


def _look_at(c: np.ndarray, target: np.ndarray) -> np.ndarray:
    z = target - c
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 0.0, -1.0], z)
    if np.linalg.norm(x) < 1e-6:
        x = np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    return se3(np.column_stack([x, np.cross(z, x), z]), c)


def _ate(P: np.ndarray, G: np.ndarray) -> float:
    S = umeyama(P, G)
    return float(np.sqrt(((S.apply(P) - G) ** 2).sum(axis=1).mean()))


def _empty_obs() -> dict:
    return dict(mp_gids=np.zeros(0, np.int64), mp_pos=np.zeros((0, 3)),
                mp_ref=np.zeros(0, np.int64), obs_kf=np.zeros(0, np.int32),
                obs_mp=np.zeros(0, np.int32), obs_xy=np.zeros((0, 2)),
                obs_octave=np.zeros(0, np.uint8))  # fmt: skip


# --- Sim(3) conventions -------------------------------------------------------------------


def test_sim3_gtsam_round_trip_maps_points_alike():
    rng = np.random.default_rng(0)
    for _ in range(5):
        S = Sim3(exp_so3(rng.normal(size=3)), rng.normal(size=3), float(rng.uniform(0.3, 3)))
        g = to_gtsam(S.matrix())
        p = rng.normal(size=3)
        assert np.allclose(g.transformFrom(p), S.apply(p[None])[0], atol=1e-12)
        assert np.allclose(from_gtsam(g), S.matrix(), atol=1e-12)
        assert g.scale() == pytest.approx(S.s)


# --- pose graph ---------------------------------------------------------------------------


def _circle(n: int = 60, seed: int = 0):
    """A loop with rotation, translation and scale drift in the odometry, and one loop
    edge (last -> first) carrying the true relative Sim(3) in the drifting scales."""
    rng = np.random.default_rng(seed)
    th = 2 * np.pi * np.arange(n) / n
    T_true = np.array([
        _look_at(np.array([5 * np.cos(a), 5 * np.sin(a), 0.3 * np.sin(3 * a)]),
                 np.array([12 * np.cos(a), 12 * np.sin(a), 0.0]))
        for a in th])  # fmt: skip
    sig = np.exp(0.006 * np.arange(n))  # local VO scale: 43 % scale drift around the loop
    est = [T_true[0].copy()]
    for i in range(n - 1):
        D = se3_inv(T_true[i]) @ T_true[i + 1]
        Dn = D.copy()
        Dn[:3, :3] = exp_so3(rng.normal(0, 0.01, 3) + [0.0, 0.004, 0.0]) @ D[:3, :3]
        Dn[:3, 3] = D[:3, 3] * sig[i + 1] + rng.normal(0, 0.01, 3)
        est.append(est[-1] @ Dn)
    est = np.array(est)
    i, j = n - 1, 0
    D = se3_inv(T_true[i]) @ T_true[j]
    S = np.eye(4)
    S[:3, :3] = (sig[i] / sig[j]) * D[:3, :3]
    S[:3, 3] = sig[i] * D[:3, 3]
    edges = [(k, k + 1) for k in range(n - 1)] + [(k, k + 2) for k in range(n - 2)]
    return T_true, est, sig, np.array(edges, np.int64), np.array([[i, j]]), S[None]


def test_pose_graph_closes_loop_and_removes_scale_drift():
    n = 60
    T_true, est, sig, edges, loops, S_loop = _circle(n)
    # Points seen from keyframe 30, placed with that keyframe's drifted pose and scale.
    rng = np.random.default_rng(1)
    p_true = T_true[30, :3, 3] + rng.normal(0, 1.0, (20, 3)) + 4 * T_true[30, :3, 2]
    X_c = (p_true - T_true[30, :3, 3]) @ T_true[30, :3, :3]
    p_est = (sig[30] * X_c) @ est[30, :3, :3].T + est[30, :3, 3]
    snap = MapSnapshot(
        "m", 7, np.arange(n, dtype=np.int64) + 1000, est, np.array([1000]), edges + 1000,
        loops + 1000, S_loop, np.arange(20, dtype=np.int64), p_est, np.full(20, 1030, np.int64),
        np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros((0, 2)),
        np.zeros(0, np.uint8))  # fmt: skip
    assert snap.check() == []
    corr = optimize_pose_graph(snap)
    assert corr.base_version == 7
    assert corr.stats["pgo_error_final"] < corr.stats["pgo_error_initial"]
    ate0 = _ate(est[:, :3, 3], T_true[:, :3, 3])
    ate1 = _ate(corr.T_m_kf[:, :3, 3], T_true[:, :3, 3])
    assert ate1 * 5 <= ate0, (ate0, ate1)
    # Scale drift: the local scale after correction is sig_i * s_i; it was sig_i.
    drift0 = np.abs(np.log(sig)).max()
    drift1 = np.abs(np.log(sig * corr.kf_scale)).max()
    assert drift1 < 0.25 * drift0, (drift0, drift1)
    assert np.allclose(corr.T_m_kf[0], est[0], atol=1e-9)
    assert corr.kf_scale[0] == pytest.approx(1.0, abs=1e-9)
    for T in corr.T_m_kf:  # rigid poses come back
        assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
    # Points ride with their reference keyframe's Sim(3).
    S_new = pose_scale_to_sim3(corr.T_m_kf[30], corr.kf_scale[30])
    want = (S_new @ se3_inv(est[30]))[:3] @ np.c_[p_est, np.ones(20)].T
    assert np.allclose(corr.mp_pos, want.T, atol=1e-9)
    # And they got closer to the truth (in the frame where the trajectory fits best).
    A = umeyama(corr.T_m_kf[:, :3, 3], T_true[:, :3, 3])
    B = umeyama(est[:, :3, 3], T_true[:, :3, 3])
    err1 = np.linalg.norm(A.apply(corr.mp_pos) - p_true, axis=1).mean()
    err0 = np.linalg.norm(B.apply(p_est) - p_true, axis=1).mean()
    assert err1 < 0.5 * err0


def test_pose_graph_leaves_disconnected_keyframes_alone():
    T_true, est, _, edges, loops, S_loop = _circle(20)
    est = np.concatenate([est, est[:1] @ se3(np.eye(3), [0, 0, 50])[None]])
    snap = MapSnapshot("m", 1, np.arange(21, dtype=np.int64), est, np.array([0]), edges,
                       loops, S_loop, **_empty_obs())  # fmt: skip
    corr = optimize_pose_graph(snap)
    assert np.array_equal(corr.T_m_kf[20], est[20]) and corr.kf_scale[20] == 1.0
    assert not np.allclose(corr.T_m_kf[10], est[10], atol=1e-3)


def test_correct_points_uses_reference_sim3():
    rng = np.random.default_rng(2)
    T_old = np.stack([se3(exp_so3(rng.normal(size=3)), rng.normal(size=3)) for _ in range(3)])
    S_new = np.stack([Sim3(exp_so3(rng.normal(size=3)), rng.normal(size=3), 2.0).matrix()
                      for _ in range(3)])  # fmt: skip
    p = rng.normal(size=(4, 3))
    out = correct_points(p, np.array([0, 2, -1, 1]), T_old, S_new)
    assert np.allclose(out[2], p[2])
    C = S_new[2] @ se3_inv(T_old[2])
    assert np.allclose(out[1], C[:3, :3] @ p[1] + C[:3, 3])


# --- global BA ----------------------------------------------------------------------------


def _ba_scene(seed: int = 1, n_cam: int = 30, n_pt: int = 500):
    rng = np.random.default_rng(seed)
    T = []
    for k in range(n_cam):
        a = -0.6 + 1.2 * k / (n_cam - 1)
        c = np.array([6 * np.sin(a), 6 * np.cos(a), 0.3 * np.sin(3 * a)])
        T.append(_look_at(c, np.zeros(3)))
    T = np.array(T)
    P = rng.uniform(-2, 2, (n_pt, 3))
    okf, omp, oxy, ooct = [], [], [], []
    for k in range(n_cam):
        X_c = (P - T[k, :3, 3]) @ T[k, :3, :3]
        xy = X_c[:, :2] / X_c[:, 2:]
        vis = np.nonzero((X_c[:, 2] > 0.5) & (np.abs(xy).max(1) < 0.6)
                         & (rng.random(n_pt) < 0.7))[0]  # fmt: skip
        oc = rng.integers(0, 4, len(vis))
        noise = rng.normal(0, 0.5, (len(vis), 2)) * 1.2 ** oc[:, None] / FX
        okf.append(np.full(len(vis), k))
        omp.append(vis)
        oxy.append(xy[vis] + noise)
        ooct.append(oc)
    okf, omp, oxy, ooct = map(np.concatenate, (okf, omp, oxy, ooct))
    bad = rng.random(len(okf)) < 0.05
    nb = int(bad.sum())
    oxy[bad] += rng.uniform(10, 40, (nb, 2)) * rng.choice([-1, 1], (nb, 2)) / FX
    T0 = T.copy()
    for k in range(1, n_cam):
        T0[k, :3, :3] = exp_so3(rng.normal(0, 0.01, 3)) @ T[k, :3, :3]
        T0[k, :3, 3] += rng.normal(0, 0.05, 3)
    P0 = P + rng.normal(0, 0.05, P.shape)
    snap = MapSnapshot(
        "m", 3, np.arange(n_cam, dtype=np.int64) + 100, T0, np.array([100]),
        np.zeros((0, 2), np.int64), np.zeros((0, 2), np.int64), np.zeros((0, 4, 4)),
        np.arange(n_pt, dtype=np.int64) + 5000, P0, np.full(n_pt, 100, np.int64),
        okf.astype(np.int32), omp.astype(np.int32), oxy, ooct.astype(np.uint8), FX)  # fmt: skip
    return snap, T, P, bad


def test_global_ba_converges_to_noise_and_flags_outliers():
    snap, T, P, bad = _ba_scene()
    assert snap.check() == []
    corr = bundle_adjust(snap, BAParams(max_iters=30))
    st = corr.stats
    assert st["ba_error_final"] < 0.5 * st["ba_error_initial"]
    rp = reprojection(corr.T_m_kf, corr.mp_pos, snap)
    # Noise is 0.5 px * 1.2**octave per axis: expected RMSE of the 2D error.
    expect = np.sqrt(np.mean(2 * (0.5 * 1.2 ** snap.obs_octave[~bad].astype(float)) ** 2))
    got = np.sqrt(np.mean(rp.err_px[~bad] ** 2))
    assert got < 1.1 * expect, (got, expect)
    assert reprojection(snap.T_m_kf, snap.mp_pos, snap).err_px[~bad].mean() > 5 * expect
    flagged = {(int(a), int(b)) for a, b in corr.outliers}
    is_flag = np.array([(int(snap.kf_gids[k]), int(snap.mp_gids[m])) in flagged
                        for k, m in zip(snap.obs_kf, snap.obs_mp, strict=True)])  # fmt: skip
    assert (is_flag & bad).sum() >= 0.9 * bad.sum()
    assert (is_flag & ~bad).sum() <= 0.01 * (~bad).sum()
    # Gauge: the fixed keyframe and its distance to the range partner hold.
    assert np.allclose(corr.T_m_kf[0], snap.T_m_kf[0], atol=1e-7)
    partner = snap.kf_index()[st["ba_gauge"]["range_to"]]
    d0 = np.linalg.norm(snap.T_m_kf[partner, :3, 3] - snap.T_m_kf[0, :3, 3])
    d1 = np.linalg.norm(corr.T_m_kf[partner, :3, 3] - corr.T_m_kf[0, :3, 3])
    assert d1 == pytest.approx(d0, rel=1e-4)
    # Up to the monocular gauge, the structure is the true one.
    S = umeyama(corr.mp_pos, P)
    assert np.sqrt(np.mean(np.sum((S.apply(corr.mp_pos) - P) ** 2, axis=1))) < 0.01
    assert _ate(corr.T_m_kf[:, :3, 3], T[:, :3, 3]) < 0.01


def test_global_ba_respects_iteration_and_time_bounds():
    snap, *_ = _ba_scene(seed=3)
    one = bundle_adjust(snap, BAParams(max_iters=1))
    assert one.stats["ba_iterations"] == 1 and one.stats["ba_stop"] == "max_iters"
    quick = bundle_adjust(snap, BAParams(max_iters=50, time_budget_s=0.0))
    assert quick.stats["ba_iterations"] == 1 and quick.stats["ba_stop"] == "time_budget"


def test_global_ba_skips_single_observation_points_and_unseen_keyframes():
    snap, *_ = _ba_scene(seed=4, n_cam=10, n_pt=200)
    # Keep one observation of point 0 only; the last keyframe loses all observations.
    drop = ((snap.obs_mp == 0) & (np.arange(len(snap.obs_mp)) != np.argmax(snap.obs_mp == 0))) | (
        snap.obs_kf == 9
    )
    ref = snap.mp_ref.copy()
    ref[0] = snap.kf_gids[5]
    snap = replace(snap, obs_kf=snap.obs_kf[~drop], obs_mp=snap.obs_mp[~drop],
                   obs_xy=snap.obs_xy[~drop], obs_octave=snap.obs_octave[~drop],
                   mp_ref=ref)  # fmt: skip
    corr = bundle_adjust(snap, BAParams(max_iters=3))
    # Point 0 was not optimized: it moved rigidly with its reference keyframe.
    C = corr.T_m_kf[5] @ se3_inv(snap.T_m_kf[5])
    assert not np.allclose(C, np.eye(4), atol=1e-4)
    assert np.allclose(corr.mp_pos[0], C[:3, :3] @ snap.mp_pos[0] + C[:3, 3])
    assert np.array_equal(corr.T_m_kf[9], snap.T_m_kf[9])
    assert corr.stats["ba_kfs"] == 9 and corr.stats["ba_points"] <= 199


# --- snapshots of a ServerMap and applying corrections -------------------------------------


def _server_map(n_kf: int = 6, n_pt: int = 120, seed: int = 0):
    """A small map: keyframes along a line looking at a wall of points, with their
    true projections as observations."""
    rng = np.random.default_rng(seed)
    P = np.c_[rng.uniform(-3, 3 + 0.3 * n_kf, n_pt), rng.uniform(-1, 1, n_pt),
              rng.uniform(4, 6, n_pt)]  # fmt: skip
    m = ServerMap("m")
    for j in range(n_pt):
        m.add_map_point(ServerMapPoint(10_000 + j, P[j].copy(), np.zeros(32, np.uint8), 0))
    Ts = []
    for k in range(n_kf):
        T = se3(exp_so3([0, 0.02 * k, 0]), [0.3 * k, 0, 0])
        Ts.append(T)
        X_c = (P - T[:3, 3]) @ T[:3, :3]
        xy = X_c[:, :2] / X_c[:, 2:]
        vis = np.nonzero(np.abs(xy[:, 0]) < 0.9)[0]
        N = len(vis) + 3  # three keypoints without a point
        mp = np.full(N, -1, np.int64)
        mp[: len(vis)] = 10_000 + vis
        kxy = np.zeros((N, 2))
        kxy[: len(vis)] = xy[vis]
        octv = rng.integers(0, 8, N).astype(np.uint8)
        kf = ServerKeyframe(k, "A", k, 1000 * k, T.copy(), T.copy(), np.zeros((N, 2), np.float32),
                            kxy, octv, np.zeros((N, 32), np.uint8), mp)  # fmt: skip
        m.add_keyframe(kf)
    for j in range(n_pt):
        p = m.mps[10_000 + j]
        p.ref_kf = min(p.obs) if p.obs else 0
    return m, np.array(Ts), P


def test_snapshot_from_map_indices_are_consistent():
    m, _, _ = _server_map()
    S = Sim3(exp_so3([0.1, 0, 0]), np.ones(3), 1.1).matrix()
    snap = snapshot_from_map(m, [(5, 0, S), (5, 99, S)])
    assert snap.check() == []
    assert snap.version == m.version and snap.map_id == "m"
    assert snap.fixed_gids.tolist() == [0]  # the oldest keyframe
    assert snap.loops.tolist() == [[5, 0]] and np.allclose(snap.S_loop[0], S)
    want = {(a, b) for a, b, kind in m.essential_edges() if kind != "loop"}
    assert {tuple(e) for e in snap.edges.tolist()} == want
    n_obs = sum(len(p.obs) for p in m.mps.values())
    assert len(snap.obs_kf) == n_obs
    for o in range(0, n_obs, 7):
        kf = m.kfs[int(snap.kf_gids[snap.obs_kf[o]])]
        g = int(snap.mp_gids[snap.obs_mp[o]])
        j = m.mps[g].obs[kf.gid]
        assert np.array_equal(snap.obs_xy[o], kf.xy[j])
        assert snap.obs_octave[o] == kf.octaves[j]
    i = snap.kf_index()
    for k, g in enumerate(snap.mp_gids.tolist()):
        assert np.array_equal(snap.mp_pos[k], m.mps[g].pos) and snap.mp_ref[k] == m.mps[g].ref_kf
    assert np.array_equal(snap.T_m_kf[i[3]], m.kfs[3].T_m_kf)
    # And the snapshot is something BA can run on: true observations -> no outliers.
    corr = bundle_adjust(snap, BAParams(max_iters=2))
    assert len(corr.outliers) == 0


def _sim_correction(
    snap: OptimizeRequest, G: Sim3, bump: dict[int, Sim3] | None = None
) -> CorrectionMsg:
    """Correction that moves every keyframe by G (per-keyframe override in ``bump``),
    with points riding along with their reference keyframe."""
    idx = snap.kf_index()
    S_new = np.empty_like(snap.T_m_kf)
    for g, i in idx.items():
        S_new[i] = (bump or {}).get(g, G).matrix() @ snap.T_m_kf[i]
    scale = np.cbrt(np.linalg.det(S_new[:, :3, :3]))
    T_new = S_new.copy()
    T_new[:, :3, :3] /= scale[:, None, None]
    ref = np.array([idx[int(r)] for r in snap.mp_ref])
    pos = correct_points(snap.mp_pos, ref, snap.T_m_kf, S_new)
    return CorrectionMsg.of(snap, T_new, scale, pos)


def test_apply_correction_propagates_to_newer_keyframes_and_points():
    m, Ts, P = _server_map()
    snap = snapshot_from_map(m, [])
    G = Sim3(exp_so3([0.05, -0.1, 0.2]), np.array([1.0, -2.0, 0.5]), 1.3)
    bump = {5: Sim3(exp_so3([0, 0.03, 0]), np.array([0.2, 0, 0]), 0.8)}
    corr = _sim_correction(snap, G, bump)
    T5_snap = m.kfs[5].T_m_kf.copy()

    # Meanwhile: keyframes 6 (child of 5) and 7 (child of 6) arrive with new points
    # anchored on 7; keyframe 2 and one point are removed.
    old_pts = [10_000 + j for j in range(len(P)) if 10_000 + j in m.mps]
    for k in (6, 7):
        T = se3(exp_so3([0, 0.02 * k, 0]), [0.3 * k, 0.05, 0])
        mp = np.array(old_pts[:30] + [20_000 + k], np.int64)
        pos = np.array([0.3 * k, 0.0, 5.0])
        m.add_map_point(ServerMapPoint(20_000 + k, pos, np.zeros(32, np.uint8), k))
        N = len(mp)
        m.add_keyframe(ServerKeyframe(k, "A", k, 1000 * k, T, T, np.zeros((N, 2), np.float32),
                                      np.zeros((N, 2)), np.zeros(N, np.uint8),
                                      np.zeros((N, 32), np.uint8), mp))  # fmt: skip
        # Spanning tree as registration through the predecessor would have it.
        kf = m.kfs[k]
        m.kfs[kf.parent].children.discard(k)
        kf.parent = k - 1
        m.kfs[k - 1].children.add(k)
    gone_pt = old_pts[-1]
    m.fuse(old_pts[0], gone_pt)  # a duplicate found meanwhile: one point fewer
    dead = m.remove_keyframe(2)
    assert m.check_invariants() == []
    T6, T7 = m.kfs[6].T_m_kf.copy(), m.kfs[7].T_m_kf.copy()
    p7 = m.mps[20_007].pos.copy()
    v0 = m.version

    res = apply_correction(m, corr)
    assert m.check_invariants() == [] and m.version == v0 + 1
    assert res.kfs_missing == 1 and res.mps_missing == 1 + len(dead)
    assert res.kfs_propagated == {6, 7} and not res.kfs_unanchored
    # Snapshot keyframes take their corrected pose.
    i = snap.kf_index()
    assert np.allclose(m.kfs[3].T_m_kf, corr.T_m_kf[i[3]])
    # Newer keyframes keep their pose relative to the anchor, scaled by its scale.
    s5 = corr.kf_scale[i[5]]
    assert s5 == pytest.approx(0.8)  # kf 5's own correction, not G's
    rel6 = se3_inv(m.kfs[5].T_m_kf) @ m.kfs[6].T_m_kf
    assert np.allclose(rel6, scale_translation(se3_inv(T5_snap) @ T6, s5), atol=1e-12)
    rel67 = se3_inv(m.kfs[6].T_m_kf) @ m.kfs[7].T_m_kf
    assert np.allclose(rel67, scale_translation(se3_inv(T6) @ T7, s5), atol=1e-12)
    # A point added after the snapshot rides with its reference keyframe (7).
    C7 = pose_scale_to_sim3(m.kfs[7].T_m_kf, s5) @ se3_inv(T7)
    assert np.allclose(m.mps[20_007].pos, C7[:3, :3] @ p7 + C7[:3, 3], atol=1e-12)
    # A snapshot point anchored in the snapshot takes its corrected position.
    k = int(np.nonzero(snap.mp_gids == 10_000)[0][0])
    if 10_000 in m.mps:
        assert np.allclose(m.mps[10_000].pos, corr.mp_pos[k])
    # With a pure Sim(3) G applied to the whole snapshot, the map is G of the old one.
    assert np.allclose(m.kfs[0].T_m_kf, G.transform_pose(snap.T_m_kf[i[0]]), atol=1e-12)


def test_pgo_then_ba_on_a_server_map_and_back():
    """The whole path: ServerMap -> snapshot -> PGO + BA -> apply_correction."""
    m, Ts, P = _server_map(n_kf=8, n_pt=200, seed=5)
    rng = np.random.default_rng(6)
    for g in range(1, 8):  # odometry-like pose noise on every keyframe but the first
        kf = m.kfs[g]
        kf.T_m_kf = kf.T_m_kf @ se3(exp_so3(rng.normal(0, 0.005, 3)), rng.normal(0, 0.02, 3))
    snap = snapshot_from_map(m, [])
    e0 = reprojection(snap.T_m_kf, snap.mp_pos, snap).err_px
    corr = optimize_map(snap)
    res = apply_correction(m, corr)
    snap2 = snapshot_from_map(m, [])
    e1 = reprojection(snap2.T_m_kf, snap2.mp_pos, snap2).err_px
    assert np.sqrt(np.mean(e1**2)) < 0.1 * np.sqrt(np.mean(e0**2))
    assert res.kfs == set(m.kfs) and m.check_invariants() == []
    assert np.allclose(m.kfs[0].T_m_kf, Ts[0], atol=1e-7)


def test_gtsam_similarity3_convention_is_as_documented():
    # The one fact the conversions rest on: matrix() is [[R, t], [0, 1/s]], p -> s(Rp + t).
    g = gtsam.Similarity3(gtsam.Rot3.Rz(0.3), np.array([1.0, 2.0, 3.0]), 2.0)
    M = g.matrix()
    assert M[3, 3] == pytest.approx(0.5)
    p = np.array([0.5, -1.0, 2.0])
    assert np.allclose(g.transformFrom(p), 2.0 * (M[:3, :3] @ p + M[:3, 3]))


# --- VO relative motion in a windowed BA -------------------------------------------------


def test_window_odometry_edges_follow_the_vo_at_the_agents_map_scale():
    """capture.window_odometry: one edge per free keyframe to the same agent's previous
    keyframe in the window, the VO's relative pose with its translation taken to map
    units at the agent's map/VO ratio."""
    from services.mapper.capture import window_odometry

    m, Ts, _ = _server_map(n_kf=6)
    for k in m.kfs.values():
        k.T_l_kf = scale_translation(k.T_m_kf, 0.5)  # the VO's unit is twice the map's
    odo = window_odometry(m, sorted(m.kfs), free={3, 4, 5})
    assert odo is not None
    assert odo.pairs.tolist() == [[2, 3], [3, 4], [4, 5]]
    for (a, b), T in zip(odo.pairs.tolist(), odo.T_rel, strict=True):
        np.testing.assert_allclose(T, se3_inv(Ts[a]) @ Ts[b], atol=1e-12)
    assert (odo.sigma > 0).all()
    # Another agent's keyframes are never linked to A's.
    m.kfs[4].agent = "B"
    assert window_odometry(m, sorted(m.kfs), free={3, 4, 5}).pairs.tolist() == [[2, 3], [3, 5]]


def test_vo_edges_hold_a_windows_poorly_seen_keyframes_to_the_vo():
    """A window whose free keyframes see few of their points, through 3 px of noise:
    the BA alone places them where that noise puts them; with the VO's relative motion as
    edges (here the true one) they come out closer to the truth, and the request with
    its edges survives the wire."""
    snap, T, P, _ = _ba_scene(seed=5)
    rng = np.random.default_rng(7)
    n_fixed = 10
    T0 = snap.T_m_kf.copy()
    T0[:n_fixed] = T[:n_fixed]
    free_obs = snap.obs_kf >= n_fixed
    xy = snap.obs_xy.copy()
    xy[free_obs] += rng.normal(0, 3.0, (int(free_obs.sum()), 2)) / FX
    keep = ~free_obs | (rng.random(len(xy)) < 0.15)  # and few of them
    win = replace(snap, T_m_kf=T0, obs_xy=xy[keep], obs_kf=snap.obs_kf[keep],
                  obs_mp=snap.obs_mp[keep], obs_octave=snap.obs_octave[keep],
                  fixed_gids=snap.kf_gids[:n_fixed].copy())  # fmt: skip
    ks = np.arange(n_fixed, len(T))
    pairs = np.column_stack([snap.kf_gids[ks - 1], snap.kf_gids[ks]])
    rel = np.array([se3_inv(T[k - 1]) @ T[k] for k in ks])
    step = np.linalg.norm(rel[:, :3, 3], axis=1)
    sig = np.column_stack([np.full(len(ks), np.deg2rad(0.3)), 0.05 * step + 0.002])
    with_odo = OptimizeRequest.decode(replace(win, odo=pairs, T_odo=rel, odo_sigma=sig).encode())
    assert with_odo.check() == [] and with_odo.odo.tolist() == pairs.tolist()
    assert OptimizeRequest.decode(win.encode()).odo is None
    bad = replace(with_odo, odo=pairs + 10_000)
    assert "odo names unknown keyframes" in bad.check()

    def err(corr) -> float:
        d = corr.T_m_kf[n_fixed:, :3, 3] - T[n_fixed:, :3, 3]
        return float(np.sqrt((d**2).sum(1).mean()))

    plain = bundle_adjust(win, BAParams(max_iters=30))
    held = bundle_adjust(with_odo, BAParams(max_iters=30))
    assert plain.stats["ba_odometry_edges"] == 0
    assert held.stats["ba_odometry_edges"] == len(ks)
    assert err(held) < 0.7 * err(plain), (err(plain), err(held))
    print(f"free keyframes' error {1e3 * err(plain):.2f} -> {1e3 * err(held):.2f} mm-units")


def test_windowed_ba_holds_its_fixed_keyframes_as_known_cameras():
    """A windowed BA (several fixed keyframes, VO edges from the last fixed one into the
    window): its fixed keyframes enter as known cameras, not variables under priors --
    except the one a VO edge ties to a free keyframe -- and the free keyframes and points
    come out where the slower graph with every fixed keyframe a variable puts them."""
    snap, T, P, _ = _ba_scene(seed=3)
    n_fixed = 12
    T0 = snap.T_m_kf.copy()
    T0[:n_fixed] = T[:n_fixed]
    ks = np.arange(n_fixed, len(T))
    pairs = np.column_stack([snap.kf_gids[ks - 1], snap.kf_gids[ks]])
    rel = np.array([se3_inv(T[k - 1]) @ T[k] for k in ks])
    sig = np.column_stack([np.full(len(ks), np.deg2rad(0.3)),
                           0.05 * np.linalg.norm(rel[:, :3, 3], axis=1) + 0.002])  # fmt: skip
    win = replace(snap, T_m_kf=T0, fixed_gids=snap.kf_gids[:n_fixed].copy(),
                  odo=pairs, T_odo=rel, odo_sigma=sig)  # fmt: skip
    known = bundle_adjust(win, BAParams(max_iters=30))
    held = bundle_adjust(win, BAParams(max_iters=30, known_cameras=False))
    assert known.stats["ba_known_cameras"] == n_fixed - 1  # the last is tied to the window
    assert held.stats["ba_known_cameras"] == 0
    assert known.stats["ba_odometry_edges"] == held.stats["ba_odometry_edges"] == len(ks)
    assert np.array_equal(known.T_m_kf[: n_fixed - 1], T0[: n_fixed - 1])
    assert np.abs(known.T_m_kf - held.T_m_kf).max() < 1e-5
    assert np.abs(known.mp_pos - held.mp_pos).max() < 1e-5
    # It did move the free keyframes towards the truth (the test is not of two no-ops).
    d0 = np.linalg.norm(T0[n_fixed:, :3, 3] - T[n_fixed:, :3, 3], axis=1).mean()
    d1 = np.linalg.norm(known.T_m_kf[n_fixed:, :3, 3] - T[n_fixed:, :3, 3], axis=1).mean()
    assert d1 < 0.3 * d0, (d0, d1)
    # A lone fixed keyframe (a global BA's gauge) keeps its prior and range factor.
    one = bundle_adjust(replace(win, fixed_gids=snap.kf_gids[:1].copy(), odo=None,
                                T_odo=None, odo_sigma=None), BAParams(max_iters=2))  # fmt: skip
    assert one.stats["ba_known_cameras"] == 0 and one.stats["ba_gauge"]["range_to"] is not None
