"""Global optimization bench: Sim(3) pose-graph optimization then global BA on a
synthetic 1000-keyframe monocular map along a EuRoC Machine Hall trajectory.

The map is what a drifting monocular VO plus loop detection would hand the
server: keyframe poses composed from noisy relative motions with a scale random
walk, points placed from their first keyframe's drifted pose and depth, about 300
observations per keyframe (pixel noise by octave, a few gross outliers), point
tracks that break when a landmark is out of view for a while (VO does not
re-identify it), and a few loop edges whose matched points were fused (as loop
closure does) with the loop's measured Sim(3). The essential graph comes from
covisibility before the loop fusion.

    OMP_NUM_THREADS=1 .venv/bin/python bench/bench_optimizer.py [--full]
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common import table, write_report  # noqa: E402

from services.mapper.capture import request_from_map  # noqa: E402
from services.mapper.correction import apply_correction  # noqa: E402
from services.mapper.server_map import ServerKeyframe, ServerMap, ServerMapPoint  # noqa: E402
from services.optimizer.global_ba import (  # noqa: E402
    BAParams,
    _select,
    bundle_adjust,
    reprojection,
)
from services.optimizer.pose_graph import apply_to_snapshot, optimize_pose_graph  # noqa: E402
from shared.geometry import exp_so3, se3_inv, umeyama  # noqa: E402
from shared.messages import OptimizeRequest  # noqa: E402
from shared.synthetic.world import World  # noqa: E402
from shared.trajectory import load_euroc_gt  # noqa: E402

log = logging.getLogger(__name__)

FX = 458.654
HALF_W, HALF_H = 376.0 / FX, 240.0 / FX  # EuRoC cam0 field of view in normalized units


@dataclass
class Scene:
    snap: OptimizeRequest
    T_true: np.ndarray  # (K, 4, 4) true camera-to-world
    p_true: np.ndarray  # (M, 3) true positions of the map points
    outlier: np.ndarray  # (O,) bool, gross outliers injected
    sigma: np.ndarray  # (K,) local VO scale at each keyframe


def make_scene(
    seq: str = "MH01",
    n_kf: int = 1000,
    obs_per_kf: int = 300,
    n_landmarks: int = 150_000,
    pixel_sigma: float = 0.7,
    outlier_rate: float = 0.02,
    rot_deg_per_sqrt_m: float = 0.15,
    trans_rel: float = 0.01,
    scale_rw_per_sqrt_m: float = 0.01,
    track_gap: int = 5,
    survival: float = 0.85,
    n_loops: int = 8,
    loop_min_gap: int = 150,
    seed: int = 0,
) -> Scene:
    rng = np.random.default_rng(seed)
    gt = load_euroc_gt(seq)
    # Keyframes where a VO would take them: evenly spaced in motion (path length plus
    # rotation), not in time -- hovering at the start makes no keyframes.
    step = np.linalg.norm(np.diff(gt.positions, axis=0), axis=1)
    R = gt.poses[:, :3, :3]
    ang = np.arccos(np.clip((np.einsum("nij,nij->n", R[1:], R[:-1]) - 1) / 2, -1, 1))
    motion = np.concatenate([[0.0], np.cumsum(step + 0.5 * ang)])
    pick = np.searchsorted(motion, np.linspace(0, motion[-1], n_kf))
    T_true = gt.poses[pick]
    L, _ = World(seed=0).landmarks(n_landmarks, seed=seed)
    rank = rng.permutation(n_landmarks)  # consistent feature choice -> long tracks

    # --- observations, tracked like a VO does: each keyframe keeps a point of the
    # previous one with probability `survival` while it stays in view, and fills up to
    # obs_per_kf with new points on the best-ranked visible landmarks that were not seen
    # in the last `track_gap` keyframes (a consistent choice, so revisits see the same
    # landmarks again; but as new points, VO does not re-identify them).
    kf_l, lm_l, xc_l, seg_l = [], [], [], []
    last_seen = np.full(n_landmarks, -(10**9), np.int64)
    seg_of = np.full(n_landmarks, -1, np.int64)
    n_seg = 0
    prev = np.zeros(0, np.int64)
    for k in range(n_kf):
        R, t = T_true[k, :3, :3], T_true[k, :3, 3]
        X = (L - t) @ R
        z = X[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = X[:, 0] / z, X[:, 1] / z
        in_view = (z > 0.3) & (z < 12.0) & (np.abs(x) < HALF_W) & (np.abs(y) < HALF_H)
        keep = prev[in_view[prev] & (rng.random(len(prev)) < survival)]
        cand = np.nonzero(in_view & (k - last_seen > track_gap))[0]
        cand = cand[np.argsort(rank[cand])[: max(obs_per_kf - len(keep), 0)]]
        seg_of[cand] = n_seg + np.arange(len(cand))
        n_seg += len(cand)
        vis = np.concatenate([keep, cand])
        last_seen[vis] = k
        kf_l.append(np.full(len(vis), k))
        lm_l.append(vis)
        xc_l.append(X[vis])
        seg_l.append(seg_of[vis])
        prev = vis
    okf = np.concatenate(kf_l)
    olm = np.concatenate(lm_l)
    X_c = np.concatenate(xc_l)
    seg = np.concatenate(seg_l)
    O = len(okf)
    octv = rng.choice(8, size=O, p=(w := 1.2 ** (-2.0 * np.arange(8))) / w.sum()).astype(np.uint8)
    xy = X_c[:, :2] / X_c[:, 2:3]
    xy += rng.normal(0.0, pixel_sigma, (O, 2)) * (1.2 ** octv[:, None]) / FX
    outlier = rng.random(O) < outlier_rate
    n_out = int(outlier.sum())
    xy[outlier] += rng.uniform(8.0, 40.0, (n_out, 2)) * rng.choice([-1, 1], (n_out, 2)) / FX

    # --- drifting VO poses
    sigma = np.ones(n_kf)
    T_est = np.empty_like(T_true)
    T_est[0] = T_true[0]
    for k in range(n_kf - 1):
        D = se3_inv(T_true[k]) @ T_true[k + 1]
        step = float(np.linalg.norm(D[:3, 3]))
        sigma[k + 1] = sigma[k] * np.exp(rng.normal(0.0, scale_rw_per_sqrt_m * np.sqrt(step)))
        Dn = D.copy()
        w = np.deg2rad(rng.normal(0, rot_deg_per_sqrt_m * np.sqrt(step), 3))
        Dn[:3, :3] = exp_so3(w) @ D[:3, :3]
        Dn[:3, 3] = sigma[k + 1] * (D[:3, 3] + rng.normal(0, trans_rel * step, 3))
        T_est[k + 1] = T_est[k] @ Dn

    # --- covisibility before loop fusion: spanning tree + strong edges
    from scipy.sparse import coo_matrix

    A = coo_matrix((np.ones(O), (okf, seg)), shape=(n_kf, n_seg)).tocsr()
    C = (A @ A.T).toarray().astype(np.int64)
    np.fill_diagonal(C, 0)
    edges = set()
    for k in range(1, n_kf):
        p = int(np.argmax(C[k, :k]))
        edges.add((p, k))
    a_idx, b_idx = np.nonzero(np.triu(C >= 100, 1))
    edges |= set(zip(a_idx.tolist(), b_idx.tolist(), strict=True))
    edges_arr = np.array(sorted(edges), np.int64)

    # --- loops: far apart in time, many landmarks in common; one per stretch of trajectory
    A_lm = coo_matrix((np.ones(O), (okf, olm)), shape=(n_kf, n_landmarks)).tocsr()
    Cl = (A_lm @ A_lm.T).toarray()
    cand = []
    for i in range(loop_min_gap, n_kf):
        j = int(np.argmax(Cl[i, : i - loop_min_gap + 1]))
        if Cl[i, j] >= 100:
            cand.append((Cl[i, j], i, j))
    loops = []
    for _, i, j in sorted(cand, reverse=True):
        if all(abs(i - a) > n_kf // (2 * n_loops) for a, _ in loops):
            loops.append((i, j))
        if len(loops) == n_loops:
            break
    S_loop = []
    parent = np.arange(n_seg)

    def find(s: int) -> int:
        while parent[s] != s:
            parent[s] = parent[parent[s]]
            s = parent[s]
        return s

    for i, j in loops:
        D = se3_inv(T_true[i]) @ T_true[j]
        S = np.eye(4)
        # Measured Sim(3) from the matched points: small noise, as a RANSAC fit would give.
        S[:3, :3] = (sigma[i] / sigma[j]) * exp_so3(rng.normal(0, 1e-3, 3)) @ D[:3, :3]
        S[:3, 3] = sigma[i] * (D[:3, 3] + rng.normal(0, 0.005, 3))
        S_loop.append(S)
        # Loop fusion: the points both ends see become one (union of their tracks).
        si = dict(zip(olm[okf == i].tolist(), seg[okf == i].tolist(), strict=True))
        for lm_, s_ in zip(olm[okf == j].tolist(), seg[okf == j].tolist(), strict=True):
            if lm_ in si:
                parent[find(s_)] = find(si[lm_])
    roots = np.array([find(s) for s in range(n_seg)])
    _, mp_of_obs = np.unique(roots[seg], return_inverse=True)
    M = int(mp_of_obs.max()) + 1
    # A fused point can now have two observations in one keyframe (never here: the
    # tracks of one landmark never share a keyframe), so no dedup is needed.

    # --- initial point positions from each point's first keyframe (VO triangulation)
    first = np.full(M, n_kf, np.int64)
    np.minimum.at(first, mp_of_obs, okf)
    ref_obs = np.full(M, -1, np.int64)
    is_first = okf == first[mp_of_obs]
    ref_obs[mp_of_obs[is_first]] = np.nonzero(is_first)[0]
    r = first
    X_ref = X_c[ref_obs] * sigma[r][:, None] * (1.0 + rng.normal(0, 0.01, (M, 1)))
    mp_pos = np.einsum("nij,nj->ni", T_est[r, :3, :3], X_ref) + T_est[r, :3, 3]
    p_true = L[olm[ref_obs]]

    snap = OptimizeRequest(
        map_id=f"bench-{seq}",
        version=1,
        reason="bench",
        sent_ns=0,
        kf_gids=np.arange(n_kf, dtype=np.int64),
        T_m_kf=T_est,
        fixed_gids=np.array([0], np.int64),
        edges=edges_arr,
        loops=np.array(loops, np.int64).reshape(-1, 2),
        S_loop=np.array(S_loop).reshape(-1, 4, 4),
        mp_gids=np.arange(M, dtype=np.int64),
        mp_pos=mp_pos,
        mp_ref=r.astype(np.int64),
        obs_kf=okf.astype(np.int32),
        obs_mp=mp_of_obs.astype(np.int32),
        obs_xy=xy,
        obs_octave=octv,
        fx=FX,
    )
    return Scene(snap, T_true, p_true, outlier, sigma)


def to_server_map(snap: OptimizeRequest) -> ServerMap:
    """The scene as a live ServerMap (to time the copy-out and the write-back)."""
    m = ServerMap(snap.map_id)
    for g, p, r in zip(snap.mp_gids.tolist(), snap.mp_pos, snap.mp_ref.tolist(), strict=True):
        m.add_map_point(ServerMapPoint(g, p.copy(), np.zeros(32, np.uint8), r))
    order = np.argsort(snap.obs_kf, kind="stable")
    bounds = np.searchsorted(snap.obs_kf[order], np.arange(snap.n_kf + 1))
    for i, g in enumerate(snap.kf_gids.tolist()):
        o = order[bounds[i] : bounds[i + 1]]
        n = len(o)
        m.add_keyframe(ServerKeyframe(
            g, "A", g, g, snap.T_m_kf[i].copy(), snap.T_m_kf[i].copy(),
            np.zeros((n, 2), np.float32), snap.obs_xy[o].copy(), snap.obs_octave[o].copy(),
            np.zeros((n, 32), np.uint8), snap.mp_gids[snap.obs_mp[o]].copy()))  # fmt: skip
    return m


def ate_rmse(T: np.ndarray, T_true: np.ndarray) -> float:
    P, G = T[:, :3, 3], T_true[:, :3, 3]
    S = umeyama(P, G)
    return float(np.sqrt(((S.apply(P) - G) ** 2).sum(axis=1).mean()))


def point_rmse(pos: np.ndarray, T: np.ndarray, sc: Scene) -> float:
    """Point error after the trajectory's Sim(3) alignment to the truth."""
    S = umeyama(T[:, :3, 3], sc.T_true[:, :3, 3])
    e = np.linalg.norm(S.apply(pos) - sc.p_true, axis=1)
    return float(np.sqrt(np.median(e**2)))  # median: fused outlier-heavy points skew the mean


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seq", default="MH01")
    ap.add_argument("--kfs", type=int, default=1000)
    ap.add_argument("--obs", type=int, default=300)
    ap.add_argument("--budget", type=float, default=None, help="BA time budget, seconds")
    ap.add_argument("--ordering", default="colamd")
    ap.add_argument("--full", action="store_true", help="also run BA to convergence")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    threads = os.environ.get("OMP_NUM_THREADS")

    t0 = time.perf_counter()
    sc = make_scene(args.seq, args.kfs, args.obs)
    t_scene = time.perf_counter() - t0
    snap = sc.snap
    assert not snap.check(), snap.check()
    print(f"scene: {snap.n_kf} kfs, {len(snap.mp_gids)} points, {len(snap.obs_kf)} obs, "
          f"{len(snap.edges)} edges, {len(snap.loops)} loops ({t_scene:.1f} s)")  # fmt: skip

    t0 = time.perf_counter()
    pgo = optimize_pose_graph(snap)
    t_pgo = time.perf_counter() - t0
    after_pgo = apply_to_snapshot(snap, pgo)
    pgo_total = t_pgo
    # The 10 s target covers PGO and BA; keep a little for BA's own setup and readout.
    budget = args.budget if args.budget is not None else max(0.5, 9.5 - pgo_total)
    t0 = time.perf_counter()
    ba = bundle_adjust(after_pgo, BAParams(max_iters=20, time_budget_s=budget,
                                           ordering=args.ordering))  # fmt: skip
    t_ba = time.perf_counter() - t0

    rp_vo = reprojection(snap.T_m_kf, snap.mp_pos, snap)
    rp_pgo = reprojection(after_pgo.T_m_kf, after_pgo.mp_pos, snap)
    rp_ba = reprojection(ba.T_m_kf, ba.mp_pos, snap)
    inl = ~sc.outlier

    def rmse_px(rp) -> float:
        e = rp.err_px[inl & np.isfinite(rp.err_px)]
        return float(np.sqrt(np.mean(np.minimum(e, 1e3) ** 2)))

    used = _select(after_pgo, BAParams())[0]
    flagged = np.zeros(len(snap.obs_kf), bool)
    if len(ba.outliers):
        key = ba.outliers[:, 0] * (1 << 32) + ba.outliers[:, 1]
        flagged = np.isin(snap.obs_kf.astype(np.int64) * (1 << 32) + snap.obs_mp, key)
    rows = [
        {"stage": "VO (input)", "seconds": 0.0, "iterations": 0,
         "ate_m": ate_rmse(snap.T_m_kf, sc.T_true), "rmse_px": rmse_px(rp_vo),
         "pt_err_m": point_rmse(snap.mp_pos, snap.T_m_kf, sc)},
        {"stage": "PGO", "seconds": t_pgo, "iterations": pgo.stats["pgo_iterations"],
         "ate_m": ate_rmse(pgo.T_m_kf, sc.T_true), "rmse_px": rmse_px(rp_pgo),
         "pt_err_m": point_rmse(pgo.mp_pos, pgo.T_m_kf, sc)},
        {"stage": "PGO+BA", "seconds": t_pgo + t_ba, "iterations": ba.stats["ba_iterations"],
         "ate_m": ate_rmse(ba.T_m_kf, sc.T_true), "rmse_px": rmse_px(rp_ba),
         "pt_err_m": point_rmse(ba.mp_pos, ba.T_m_kf, sc)},
    ]  # fmt: skip
    report = {
        "sequence": args.seq,
        "omp_num_threads": threads,
        # The 2 cores are shared with other work: load average at the end of the run.
        "load_avg_1m": os.getloadavg()[0],
        "n_kf": int(snap.n_kf),
        "n_points": int(len(snap.mp_gids)),
        "n_observations": int(len(snap.obs_kf)),
        "n_edges": int(len(snap.edges)),
        "n_loops": int(len(snap.loops)),
        "path_m": float(np.linalg.norm(np.diff(sc.T_true[:, :3, 3], axis=0), axis=1).sum()),
        "pgo": {**pgo.stats, "seconds": t_pgo},
        "ba": {**ba.stats, "seconds": t_ba, "time_budget_s": budget, "ordering": args.ordering},
        "total_seconds": t_pgo + t_ba,
        "outliers_injected": int(sc.outlier.sum()),
        "outliers_flagged": int(flagged.sum()),
        "outliers_recall": float((flagged & sc.outlier).sum() / max(sc.outlier.sum(), 1)),
        "inliers_flagged": int((flagged & ~sc.outlier).sum()),
        # Outliers on observations BA weighed (points with enough parallax).
        "outliers_recall_in_ba": float(
            (flagged & sc.outlier & used).sum() / max((sc.outlier & used).sum(), 1)
        ),
        "stages": rows,
    }
    # Copy-out and write-back on a live ServerMap of the same size.
    smap = to_server_map(snap)
    loops = [(int(a), int(b), S) for (a, b), S in zip(snap.loops, snap.S_loop, strict=True)]
    t0 = time.perf_counter()
    snap_copy = request_from_map(smap, loops)
    t_snap = time.perf_counter() - t0
    t0 = time.perf_counter()
    applied = apply_correction(smap, ba)
    t_apply = time.perf_counter() - t0
    report["server_map"] = {
        "snapshot_seconds": t_snap, "apply_seconds": t_apply,
        "snapshot_observations": int(len(snap_copy.obs_kf)),
        "applied_kfs": len(applied.kfs), "applied_points": len(applied.mps),
    }  # fmt: skip
    if args.full:
        t0 = time.perf_counter()
        p_full = BAParams(time_budget_s=1e9, max_iters=100, ordering=args.ordering)
        full = bundle_adjust(after_pgo, p_full)
        t_full = time.perf_counter() - t0
        report["ba_to_convergence"] = {
            "seconds": t_full, "iterations": full.stats["ba_iterations"],
            "stop": full.stats["ba_stop"], "error_final": full.stats["ba_error_final"],
            "ate_m": ate_rmse(full.T_m_kf, sc.T_true),
            "rmse_px": rmse_px(reprojection(full.T_m_kf, full.mp_pos, snap)),
        }  # fmt: skip
    path = write_report("optimizer", report)
    print(table(rows, ["stage", "seconds", "iterations", "ate_m", "rmse_px", "pt_err_m"]))
    b = ba.stats
    print(f"BA: build {b['ba_build_seconds']:.2f} s, iterate {b['ba_iterate_seconds']:.2f} s, "
          f"{b['ba_iterations']} it ({b['ba_stop']}), error {b['ba_error_initial']:.4g} -> "
          f"{b['ba_error_final']:.4g}; outliers flagged {report['outliers_flagged']} "
          f"(recall {report['outliers_recall']:.3f}, "
          f"in BA {report['outliers_recall_in_ba']:.3f}, "
          f"inliers flagged {report['inliers_flagged']})")  # fmt: skip
    print("ServerMap copy-out / write-back:", report["server_map"])
    if args.full:
        print("BA to convergence:", report["ba_to_convergence"])
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
