"""A loop's matched points tell whether the map already holds the place (its relative
pose reprojects them as well as the loop's Sim(3)) or has drifted (only the loop's
Sim(3) reprojects them): ``loop_support``."""

from __future__ import annotations

import numpy as np

from services.mapper.loop_support import loop_support
from services.mapper.server_map import ServerKeyframe, ServerMap, ServerMapPoint
from shared.geometry import exp_so3, se3, se3_inv

FX = 450.0


def _scene(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points 3-6 m in front of a query camera at the origin, and a candidate camera
    3 m to its side turned towards them (a wide-baseline loop)."""
    rng = np.random.default_rng(seed)
    P = np.c_[rng.uniform(-1.5, 1.5, 80), rng.uniform(-1.0, 1.0, 80), rng.uniform(3, 6, 80)]
    T_w_q = np.eye(4)
    T_w_c = se3(exp_so3(np.array([0.0, -0.6, 0.0])), [3.0, 0.2, 0.5])
    return P, T_w_q, T_w_c


def _observed(T_w_kf: np.ndarray, P: np.ndarray, rng) -> np.ndarray:
    T = se3_inv(T_w_kf)
    X = P @ T[:3, :3].T + T[:3, 3]
    return X[:, :2] / X[:, 2:] + rng.normal(0.0, 0.5 / FX, (len(P), 2))


def _map(P: np.ndarray, T_w_q: np.ndarray, T_w_c: np.ndarray, drift: np.ndarray) -> ServerMap:
    """Query keyframe 1 with points 1000+i, candidate keyframe 2 with its own copies
    2000+i of the same points; the candidate side (keyframe and points) sits in the map
    moved by ``drift``, as a map that drifted between the two visits holds it. The
    keypoints are where the cameras really see the points."""
    rng = np.random.default_rng(1)
    m = ServerMap("map-A")
    n = len(P)
    for gid, T, base, move in ((1, T_w_q, 1000, np.eye(4)), (2, T_w_c, 2000, drift)):
        Pm = P @ move[:3, :3].T + move[:3, 3]
        for i in range(n):
            m.add_map_point(ServerMapPoint(base + i, Pm[i], np.zeros(32, np.uint8), gid))
        xy = _observed(T, P, rng)
        T_m = move @ T
        m.add_keyframe(ServerKeyframe(gid, "A", gid, gid, T_m, T_m, (xy * FX).astype(np.float32),
                                      xy, np.zeros(n, np.uint8), np.zeros((n, 32), np.uint8),
                                      np.arange(base, base + n, dtype=np.int64)))  # fmt: skip
    return m


def _support(m: ServerMap, S: np.ndarray, n: int) -> tuple[int, int]:
    mp_q, mp_c = np.arange(1000, 1000 + n), np.arange(2000, 2000 + n)
    return loop_support(m, 1, 2, mp_q, mp_c, S, FX, FX)


def test_a_map_that_holds_the_place_supports_its_own_pose_not_a_rescaled_loop():
    """The seed-1 pair's wrong loops: the map right, the measurement 5 % off in scale
    over a 3 m baseline. The map's relative pose reprojects every pair; the loop's far
    fewer."""
    P, T_w_q, T_w_c = _scene()
    m = _map(P, T_w_q, T_w_c, np.eye(4))
    true = se3_inv(T_w_q) @ T_w_c
    wrong = true.copy()
    wrong[:3, :3] *= 0.95
    n_map, n_loop = _support(m, wrong, len(P))
    assert n_map >= 0.95 * len(P), n_map
    assert n_loop < 0.5 * n_map, (n_map, n_loop)
    # A right measurement is supported as well as the map's pose: the loop adds nothing.
    n_map, n_loop = _support(m, true, len(P))
    assert n_loop == n_map >= 0.95 * len(P)


def test_a_drifted_map_supports_only_the_loop():
    """Drift between the two visits (2 degrees, 10 cm): the map's relative pose puts the
    candidate's points off the query's keypoints, the true loop puts them on."""
    P, T_w_q, T_w_c = _scene(3)
    drift = se3(exp_so3(np.array([0.0, 0.0, np.radians(2.0)])), [0.1, 0.0, 0.03])
    m = _map(P, T_w_q, T_w_c, drift)
    true = se3_inv(T_w_q) @ T_w_c
    n_map, n_loop = _support(m, true, len(P))
    assert n_loop >= 0.95 * len(P), n_loop
    assert n_map < 0.2 * n_loop, (n_map, n_loop)


def test_pairs_the_map_no_longer_holds_are_skipped():
    """Points fused or culled since the match (gone from the map), and a query point the
    query keyframe does not observe, count for neither pose."""
    P, T_w_q, T_w_c = _scene()
    m = _map(P, T_w_q, T_w_c, np.eye(4))
    true = se3_inv(T_w_q) @ T_w_c
    for g in (1000, 1001, 2002):
        p = m.mps.pop(g)
        for kf in p.obs:
            m.kfs[kf].mp[p.obs[kf]] = -1
    m.mps[1003].obs.pop(1)
    assert _support(m, true, len(P)) == (len(P) - 4, len(P) - 4)
    assert _support(m, true, 0) == (0, 0)
