"""Sim(3) pose-graph optimization over the essential graph plus loop edges.

As ORB-SLAM and CCM-SLAM do it before global BA: one Similarity3 per keyframe,
initialised from its SE(3) pose with scale 1; every essential-graph edge measures
the current relative pose (so before the loop edges pull, the graph is at rest);
loop edges carry their measured Sim(3); the gauge keyframes are held by a tight
prior. Levenberg-Marquardt spreads the loop's rotation, translation and scale
error along the graph. Points then move rigidly (with scale) with their reference
keyframe: ``p' = S'_m_ref S_m_ref^-1 p``.

Variables are camera-to-map ``S_m_kf``. GTSAM's Similarity3 (R, t, s) maps
``p -> s (R p + t)``; our matrices are ``[[s R, t], [0, 1]]`` (``p -> s R p + t``),
hence the ``t / s`` in :func:`to_gtsam`.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace

import gtsam
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from shared.geometry import loop_residual
from shared.messages import CorrectionMsg, OptimizeRequest

log = logging.getLogger(__name__)


@dataclass
class PGOParams:
    max_iters: int = 20  # ORB-SLAM's essential-graph optimization runs 20 iterations
    rel_tol: float = 1e-7
    # Unit information on every edge, as ORB-SLAM; the prior only has to dominate.
    edge_sigma: float = 1.0
    loop_sigma: float = 1.0
    prior_sigma: float = 1e-6


def _orthonormal(A: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(A)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    return R


def to_gtsam(S: np.ndarray) -> gtsam.Similarity3:
    """``[[s R, t], [0, 1]]`` -> gtsam.Similarity3 (same map of points)."""
    A = np.asarray(S, np.float64)[:3, :3]
    s = float(np.cbrt(np.linalg.det(A)))
    R = _orthonormal(A / s)
    return gtsam.Similarity3(gtsam.Rot3(R), np.asarray(S[:3, 3], np.float64) / s, s)


def from_gtsam(sim: gtsam.Similarity3) -> np.ndarray:
    """gtsam.Similarity3 -> ``[[s R, t], [0, 1]]``: its matrix ``[[R, t], [0, 1/s]]``
    normalized so the last entry is 1."""
    M = np.asarray(sim.matrix(), np.float64)
    return M / M[3, 3]


def sim3_to_pose(S: np.ndarray) -> tuple[np.ndarray, float]:
    """Camera-to-map Sim(3) -> (SE(3) camera-to-map pose, scale): rotation and camera
    centre stay, the scale is dropped (it only changes lengths seen from this camera)."""
    A = S[:3, :3]
    s = float(np.cbrt(np.linalg.det(A)))
    T = np.eye(4)
    T[:3, :3] = _orthonormal(A / s)
    T[:3, 3] = S[:3, 3]
    return T, s


def pose_scale_to_sim3(T: np.ndarray, s: np.ndarray | float) -> np.ndarray:
    """SE(3) pose(s) and scale(s) -> ``[[s R, t], [0, 1]]``; works on (..., 4, 4)."""
    S = np.array(T, np.float64, copy=True)
    S[..., :3, :3] *= np.asarray(s, np.float64)[..., None, None]
    return S


def inv_se3_batch(T: np.ndarray) -> np.ndarray:
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    Ti[..., 3, 3] = 1.0
    return Ti


def loops_pull(snap: OptimizeRequest, rot_deg: float = 0.05, trans_share: float = 0.0025) -> bool:
    """Whether any loop edge of ``snap`` is away from its keyframes' current relative
    pose by more than ``rot_deg`` or ``trans_share`` of its length: if none is, the
    pose graph is (nearly) at rest and would move nothing a BA does not (loops a global
    run distributed come at rest, see the mapper's ``Collaboration._rebase_loops``,
    unless a windowed BA or a registration moved their keyframes since)."""
    if not len(snap.loops):
        return False
    idx = snap.kf_index()
    a = np.array([idx[int(q)] for q in snap.loops[:, 0]], np.int64)
    b = np.array([idx[int(c)] for c in snap.loops[:, 1]], np.int64)
    rel = inv_se3_batch(snap.T_m_kf[a]) @ snap.T_m_kf[b]
    S = np.asarray(snap.S_loop, np.float64)
    for k in range(len(S)):
        rot, trans = loop_residual(S[k], rel[k])
        if rot > rot_deg or trans > trans_share:
            return True
    return False


def correct_points(
    pos: np.ndarray, ref_idx: np.ndarray, T_old: np.ndarray, S_new: np.ndarray
) -> np.ndarray:
    """``p' = S_new[r] T_old[r]^-1 p`` for each point with reference index r (-1: stays)."""
    out = np.array(pos, np.float64, copy=True)
    ok = ref_idx >= 0
    if not ok.any():
        return out
    r = ref_idx[ok]
    C = S_new @ inv_se3_batch(T_old)  # per keyframe correction, (K, 4, 4)
    out[ok] = np.einsum("nij,nj->ni", C[r, :3, :3], pos[ok]) + C[r, :3, 3]
    return out


def point_ref_index(snap: OptimizeRequest) -> np.ndarray:
    """Index of each point's reference keyframe in ``snap.kf_gids``; a point whose
    reference is not in the snapshot falls back to its first observing keyframe, one
    with neither gets -1 (it is left where it is)."""
    order = np.argsort(snap.kf_gids)
    sorted_g = snap.kf_gids[order]
    pos = np.searchsorted(sorted_g, snap.mp_ref)
    pos_c = np.minimum(pos, max(len(sorted_g) - 1, 0))
    found = (
        (pos < len(sorted_g)) & (sorted_g[pos_c] == snap.mp_ref)
        if len(sorted_g)
        else (np.zeros(len(snap.mp_ref), bool))
    )
    ref = np.where(found, order[pos_c] if len(order) else -1, -1).astype(np.int64)
    missing = np.nonzero(~found)[0]
    if len(missing) and len(snap.obs_mp):
        first = np.full(len(snap.mp_gids), -1, np.int64)
        # Reverse so the earliest observation of each point is written last and wins.
        first[snap.obs_mp[::-1]] = snap.obs_kf[::-1]
        ref[missing] = first[missing]
    return ref


def _components_with_gauge(
    snap: OptimizeRequest, pairs: np.ndarray, fixed: np.ndarray
) -> np.ndarray:
    """Mask of keyframes connected (through ``pairs``) to a gauge keyframe."""
    K = snap.n_kf
    if len(pairs):
        g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(K, K))
        _, lab = connected_components(g, directed=False)
    else:
        lab = np.arange(K)
    return np.isin(lab, lab[fixed])


def optimize_pose_graph(snap: OptimizeRequest, params: PGOParams | None = None) -> CorrectionMsg:
    """Sim(3) pose-graph optimization of ``snap``; returns corrected poses, per-keyframe
    scales and points moved with their reference keyframes."""
    p = params or PGOParams()
    t0 = time.perf_counter()
    K = snap.n_kf
    idx = snap.kf_index()
    T = snap.T_m_kf
    fixed = np.array([idx[int(g)] for g in snap.fixed_gids], np.int64)
    if not len(fixed) and K:
        fixed = np.array([0], np.int64)

    def to_idx(arr: np.ndarray) -> np.ndarray:
        return np.array([[idx[int(a)], idx[int(b)]] for a, b in arr], np.int64).reshape(-1, 2)

    loops = to_idx(snap.loops)
    edges = to_idx(snap.edges)
    edges = edges[edges[:, 0] != edges[:, 1]]
    # A loop pair also present as an odometry/covisibility edge keeps only the loop
    # measurement: the drifted relative pose would fight it (ORB-SLAM skips those too).
    loop_keys = {(min(a, b), max(a, b)) for a, b in loops.tolist()}
    edges = np.array([e for e in edges.tolist() if (min(e), max(e)) not in loop_keys],
                     np.int64).reshape(-1, 2)  # fmt: skip
    active = _components_with_gauge(snap, np.concatenate([edges, loops]), fixed)
    if (~active).any():
        log.warning("pose graph %s: %d keyframes not connected to the gauge stay put",
                    snap.map_id, int((~active).sum()))  # fmt: skip

    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for i in np.nonzero(active)[0].tolist():
        values.insert(i, to_gtsam(T[i]))
    prior = gtsam.noiseModel.Isotropic.Sigma(7, p.prior_sigma)
    for i in fixed.tolist():
        graph.add(gtsam.PriorFactorSimilarity3(i, to_gtsam(T[i]), prior))
    n_edge = gtsam.noiseModel.Isotropic.Sigma(7, p.edge_sigma)
    n_loop = gtsam.noiseModel.Isotropic.Sigma(7, p.loop_sigma)
    if len(edges):
        T_a_b = inv_se3_batch(T[edges[:, 0]]) @ T[edges[:, 1]]
        for (a, b), M in zip(edges.tolist(), T_a_b, strict=True):
            if active[a]:
                graph.add(gtsam.BetweenFactorSimilarity3(a, b, to_gtsam(M), n_edge))
    for (a, b), S in zip(loops.tolist(), snap.S_loop, strict=True):
        if active[a]:
            graph.add(gtsam.BetweenFactorSimilarity3(a, b, to_gtsam(S), n_loop))

    lm = gtsam.LevenbergMarquardtParams()
    lm.setMaxIterations(p.max_iters)
    lm.setRelativeErrorTol(p.rel_tol)
    e0 = graph.error(values)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, lm)
    result = opt.optimize()
    e1 = graph.error(result)

    S_new = pose_scale_to_sim3(T, np.ones(K))
    for i in np.nonzero(active)[0].tolist():
        S_new[i] = from_gtsam(result.atSimilarity3(i))
    T_new = np.empty_like(T)
    scale = np.ones(K)
    for i in range(K):
        T_new[i], scale[i] = sim3_to_pose(S_new[i])
    mp_pos = correct_points(snap.mp_pos, point_ref_index(snap), T, S_new)
    dt = time.perf_counter() - t0
    log.info("pose graph %s: %d kfs, %d edges, %d loops, error %.4g -> %.4g in %d it, %.3f s",
             snap.map_id, K, len(edges), len(loops), e0, e1, opt.iterations(), dt)  # fmt: skip
    return CorrectionMsg.of(
        snap,
        T_new,
        scale,
        mp_pos,
        stats={
            "pgo_iterations": int(opt.iterations()),
            "pgo_error_initial": float(e0),
            "pgo_error_final": float(e1),
            "pgo_seconds": dt,
            "pgo_edges": int(len(edges)),
            "pgo_loops": int(len(loops)),
        },
    )


def apply_to_snapshot(snap: OptimizeRequest, corr: CorrectionMsg) -> OptimizeRequest:
    """The map copy with the correction's poses and points (same gids, same order)."""
    if not (np.array_equal(snap.kf_gids, corr.kf_gids)
            and np.array_equal(snap.mp_gids, corr.mp_gids)):  # fmt: skip
        raise ValueError("correction does not match the snapshot's keyframes and points")
    return replace(snap, T_m_kf=corr.T_m_kf.copy(), mp_pos=corr.mp_pos.copy())


__all__ = [
    "PGOParams",
    "apply_to_snapshot",
    "correct_points",
    "from_gtsam",
    "optimize_pose_graph",
    "pose_scale_to_sim3",
    "sim3_to_pose",
    "to_gtsam",
]
