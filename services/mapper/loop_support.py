"""Which relative pose a loop's matched points support: the loop's Sim(3) or the map's.

A loop within one map comes with a measurement, the Sim(3) ``S_q_c`` place recognition
verified. The map has its own answer already: the two keyframes' relative pose as they
are. Where the map has drifted, the matched points reproject into the query only through
the loop's Sim(3); where the map already holds the place together, they reproject
through the map's pose as well, and a measurement that differs from it is then no
evidence that the map is wrong -- the matches do not tell the two apart. In the seed-1
pair, wide-baseline matches (2.8-5.4 m) came with a scale 2-5 % off and were 5.6-24 % of
their length off the map, which held the pair within 0.09 deg and 17 mm of the truth;
kept at their measurement until a second global run overruled them (``_rebase_loops``),
they bent the map meanwhile. With this check (bench/results/b2_loopsupport.json) the
map's pose reprojected 127 of such a loop's pairs where its Sim(3) reprojected 46, and
135 where it reprojected 104; the map held those pairs within 0.04 deg and 15 mm of the
truth, the loops were 1.0 / 1.4 deg and 3.3 / 8.7 % (0.20 / 0.32 m) off it. Where the
map had drifted (team3, t3_loopsupport.json) the map's pose reprojected 58 pairs, the
loop's 197: kept, and the next global run satisfied it within 1.3 %.

Plain function of (map, match): no transport.
"""

from __future__ import annotations

import numpy as np

from shared.geometry import se3_inv
from shared.orb import SCALE_FACTOR

from .server_map import ServerMap

CHI2_2DOF = 5.991  # 95 %: a point reprojected this close (x sigma^2) supports a pose


def _reprojects(S: np.ndarray, P: np.ndarray, xy: np.ndarray, tol2: np.ndarray) -> np.ndarray:
    """Whether points ``P`` (N, 3), moved by ``S`` (4x4), land within ``tol2`` (squared,
    normalized units) of ``xy`` (N, 2) in front of the camera."""
    X = P @ S[:3, :3].T + S[:3, 3]
    z = X[:, 2]
    front = z > 1e-6
    e2 = np.full(len(P), np.inf)
    e2[front] = ((X[front, :2] / z[front, None] - xy[front]) ** 2).sum(1)
    return e2 <= tol2


def loop_support(smap: ServerMap, q: int, c: int, mp_q: np.ndarray, mp_c: np.ndarray,
                 S_q_c: np.ndarray, fx_q: float, fx_c: float) -> tuple[int, int]:  # fmt: skip
    """(pairs the map's relative pose supports, pairs the loop's ``S_q_c`` supports)
    among the matched point pairs ``mp_q`` / ``mp_c`` (gids, pairwise).

    A pair supports a pose when the candidate side's point, moved into the query's
    camera by it, reprojects onto the query's keypoint of its partner, and, where the
    candidate observes its point, the query side's point reprojects onto that keypoint
    through the inverse, each within chi2(2 dof, 95 %) x (1.2^octave / fx)^2."""
    kq, kc = smap.kfs[q], smap.kfs[c]
    mps = smap.mps
    rows = []
    for a, b in zip(mp_q.tolist(), mp_c.tolist(), strict=True):
        pa, pb = mps.get(a), mps.get(b)
        if pa is None or pb is None:
            continue
        jq = pa.obs.get(q)
        if jq is None:
            continue
        rows.append((a, b, jq, pb.obs.get(c, -1)))
    if not rows:
        return 0, 0
    a, b, jq, jc = (np.array(col, np.int64) for col in zip(*rows, strict=True))
    Xq, Xc = smap.positions(a), smap.positions(b)
    T_q_m, T_c_m = se3_inv(kq.T_m_kf), se3_inv(kc.T_m_kf)
    in_q = Xq @ T_q_m[:3, :3].T + T_q_m[:3, 3]  # the query's point in its own camera
    in_c = Xc @ T_c_m[:3, :3].T + T_c_m[:3, 3]
    tol_q = CHI2_2DOF * (SCALE_FACTOR ** kq.octaves[jq].astype(float) / fx_q) ** 2
    seen = jc >= 0
    jcs = jc[seen]
    tol_c = CHI2_2DOF * (SCALE_FACTOR ** kc.octaves[jcs].astype(float) / fx_c) ** 2
    counts = []
    for S in (T_q_m @ kc.T_m_kf, S_q_c):
        ok = _reprojects(S, in_c, kq.xy[jq], tol_q)
        ok[seen] &= _reprojects(np.linalg.inv(S), in_q[seen], kc.xy[jcs], tol_c)
        counts.append(int(ok.sum()))
    return counts[0], counts[1]
