"""Geometric verification of a place-recognition candidate with a Sim(3).

Query q and candidate c may live in maps of different scale, so the transform
between their camera frames is a similarity ``S_q_c`` (p_q = s R p_c + t). The
steps are ORB-SLAM's ``LoopClosing::ComputeSim3``:

1. match descriptors of keypoints that have map points, only under the same
   vocabulary node (``SearchByBoW``: Hamming <= 50, ratio 0.75);
2. Sim(3) RANSAC on the 3D-3D pairs: minimal sets of 3 solved in closed form
   (Umeyama, ``shared.geometry``), all hypotheses at once as batched SVDs; a pair
   is an inlier when it reprojects within chi2(2 dof, 99 %) = 9.21 px^2 x sigma^2
   in both images, sigma = 1.2^octave;
3. guided matching keyframe to keyframe through the Sim(3) in both directions,
   keeping mutual matches (``SearchBySim3``);
4. nonlinear refinement of the 7 parameters on the reprojection errors in both
   images with a Huber loss, outliers dropped and refined again (``OptimizeSim3``),
   plus a weak term on point distances that ORB-SLAM lacks: without it the scale
   drifts freely when both cameras sit at the same spot (11-18 % scale error on
   hovering pairs of the benchmark);
5. the candidate's neighbourhood map points projected into q with the refined
   Sim(3) and matched by descriptor within a radius (``SearchByProjection``).

Accepted when step 4 keeps >= 20 inliers and steps 4+5 give >= 40 matches.

The refinement uses scipy's ``least_squares`` rather than GTSAM: the problem has
7 unknowns and a few hundred residuals with no graph structure, GTSAM's Python
wheel has no Sim(3)-projection factor (a Python ``CustomFactor`` would call back
per residual), and a vectorized residual with a 2-point Jacobian converges in a
few milliseconds.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from shared.geometry import Sim3, umeyama
from shared.orb import SCALE_FACTOR
from shared.settings import PlacerecSettings, default_of

from .database import ranges
from .keyframe import KeyframeData, MapPoints
from .vocabulary import as_u64, hamming_u64

log = logging.getLogger(__name__)

_BIG = 1 << 20
_EPS_2POINT = float(np.finfo(np.float64).eps ** 0.5)  # scipy's relative step for '2-point'


@dataclass(frozen=True)
class VerifyParams:
    bow_max_hamming: int = 50  # ORB-SLAM TH_LOW
    bow_ratio: float = 0.75
    min_bow_matches: int = 20
    ransac_iterations: int = 300
    ransac_min_inliers: int = 20
    chi2: float = 9.21  # 2 dof, 99 %, in px^2 at sigma 1
    scale_factor: float = SCALE_FACTOR  # ORB pyramid: sigma = scale_factor ** octave
    guided_radius_px: float = 7.5  # SearchBySim3, times the predicted level's scale
    guided_max_hamming: int = 100  # ORB-SLAM TH_HIGH
    opt_chi2: float = 10.0  # OptimizeSim3 outlier threshold (and Huber width sqrt)
    # Relative 1-sigma of a map point's distance from its camera, for the weak 3D term
    # that keeps the scale observable when the two cameras share a centre.
    distance_sigma_rel: float = 0.1
    min_inliers: int = default_of(PlacerecSettings, "min_inliers")  # after the refinement
    neighbourhood_radius_px: float = 10.0  # SearchByProjection into q
    neighbourhood_max_hamming: int = 50
    # refined inliers + neighbourhood matches
    min_total_matches: int = default_of(PlacerecSettings, "min_matches")
    seed: int = 0

    @classmethod
    def from_settings(cls, p: PlacerecSettings) -> VerifyParams:
        return cls(min_inliers=p.min_inliers, min_total_matches=p.min_matches)


@dataclass
class VerifyResult:
    accepted: bool
    reason: str  # why it was rejected, or "ok"
    S_q_c: np.ndarray | None = None  # 4x4 [[sR, t], [0, 1]]: p_q = s R p_c + t
    scale: float = float("nan")
    kp_q: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    kp_c: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # -1: not in c
    mp_q: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # -1: no point
    mp_c: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    n_inliers: int = 0  # len(kp_q): refined inliers + neighbourhood matches
    stats: dict = field(default_factory=dict)

    @property
    def sim3(self) -> Sim3 | None:
        return None if self.S_q_c is None else Sim3.from_matrix(self.S_q_c)


# -- step 1: BoW-restricted descriptor matching ----------------------------------------
def match_by_bow(q: KeyframeData, c: KeyframeData, p: VerifyParams) -> tuple[np.ndarray, ...]:
    """(index in q, index in c) of keypoints with map points, one c keypoint per match."""
    if q.fv is None or c.fv is None:
        raise ValueError("keyframes need a feature vector: call compute_bow(voc) first")
    dq, dc = as_u64(q.descriptors), as_u64(c.descriptors)
    _, a, b = np.intersect1d(q.fv.nodes, c.fv.nodes, assume_unique=True, return_indices=True)
    # All shared nodes at once (a Python loop over ~100 nodes per candidate before): every
    # q keypoint with a point is a row, paired with each c keypoint with a point under
    # its node; rows come in node order, then keypoint order, as the loop made them.
    kq, q_off = _with_points(q)
    kc, c_off = _with_points(c)
    nq, nc = q_off[a + 1] - q_off[a], c_off[b + 1] - c_off[b]
    both = (nq > 0) & (nc > 0)
    a, b, nq, nc = a[both], b[both], nq[both], nc[both]
    if len(a) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    rows = kq[ranges(q_off[a], nq)]  # q keypoint of each row
    row_nc = np.repeat(nc, nq)  # its node's number of c keypoints
    row_c0 = np.repeat(c_off[b], nq)  # where they start in kc
    start = np.cumsum(row_nc) - row_nc  # each row's first pair
    col = np.arange(int(row_nc.sum())) - np.repeat(start, row_nc)
    pair_c = kc[np.repeat(row_c0, row_nc) + col]
    d = hamming_u64(dq[np.repeat(rows, row_nc)], dc[pair_c])
    best = np.minimum.reduceat(d, start)
    # The first pair at the row's minimum is the argmin; the second smallest is the
    # minimum of the rest (_BIG for a row of one pair, as before).
    row_of = np.repeat(np.arange(len(rows)), row_nc)
    at_best = np.flatnonzero(d == best[row_of])
    r = row_of[at_best]
    first = at_best[np.r_[True, r[1:] != r[:-1]]]
    rest = d.astype(np.int64)
    rest[first] = _BIG
    second = np.minimum.reduceat(rest, start)
    ok = (best <= p.bow_max_hamming) & (best < p.bow_ratio * second)
    return _one_per_target(rows[ok], pair_c[first[ok]], best[ok])


def _with_points(k: KeyframeData) -> tuple[np.ndarray, np.ndarray]:
    """The feature vector's keypoint order without keypoints lacking a point, and each
    node's offsets into it."""
    fv = k.fv
    assert fv is not None
    keep = k.has_point[fv.order]
    kept_before = np.r_[0, np.cumsum(keep)]
    return fv.order[keep], kept_before[fv.offsets]


def _one_per_target(src: np.ndarray, tgt: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, ...]:
    """Several sources on one target: the smallest descriptor distance keeps it."""
    order = np.argsort(dist, kind="stable")
    _, first = np.unique(tgt[order], return_index=True)
    sel = np.sort(order[first])
    return src[sel].astype(np.int64), tgt[sel].astype(np.int64)


# -- step 2: Sim(3) RANSAC ---------------------------------------------------------------
def _umeyama_batch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, ...]:
    """Closed-form similarities for (H, m, 3) point sets: (R (H,3,3), t (H,3), s (H,))."""
    mu_s, mu_d = src.mean(axis=1), dst.mean(axis=1)
    xs, xd = src - mu_s[:, None], dst - mu_d[:, None]
    cov = np.einsum("hni,hnj->hij", xd, xs) / src.shape[1]
    U, D, Vt = np.linalg.svd(cov)
    sgn = np.where(np.linalg.det(U) * np.linalg.det(Vt) < 0, -1.0, 1.0)
    Sd = np.ones((len(src), 3))
    Sd[:, 2] = sgn
    R = U @ (Sd[:, :, None] * Vt)
    var_s = (xs**2).sum(axis=(1, 2)) / src.shape[1]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (D * Sd).sum(axis=1) / var_s
    t = mu_d - s[:, None] * np.einsum("hij,hj->hi", R, mu_s)
    return R, t, s


def _reproj_sq(P: np.ndarray, xy: np.ndarray, fx: float) -> np.ndarray:
    """Squared pixel error of camera-frame points P (..., 3) against normalized xy."""
    z = P[..., 2]
    front = z > 1e-9
    zs = np.where(front, z, 1e-9)
    # x and y apart: the same operations on the same values as summing e**2 over a
    # last axis of 2, without numpy's slow reduction over that short axis (3x faster
    # on the RANSAC's (300, n) batches).
    ex = P[..., 0] / zs - xy[..., 0]
    ey = P[..., 1] / zs - xy[..., 1]
    err = (fx * fx) * (ex * ex + ey * ey)
    return np.where(front, err, np.inf)


class _Pairs:
    """3D-3D pairs with their observations, errors measured in both images."""

    def __init__(self, q: KeyframeData, c: KeyframeData, iq: np.ndarray, ic: np.ndarray,
                 p: VerifyParams) -> None:  # fmt: skip
        self.q, self.c, self.iq, self.ic = q, c, iq, ic
        self.Pq, self.Pc = q.p_c[iq], c.p_c[ic]
        self.xq, self.xc = q.xy[iq], c.xy[ic]
        self.sig2_q = p.scale_factor ** (2.0 * q.octaves[iq].astype(np.float64))
        self.sig2_c = p.scale_factor ** (2.0 * c.octaves[ic].astype(np.float64))

    def __len__(self) -> int:
        return len(self.iq)

    def chi2(self, R: np.ndarray, t: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Whitened squared errors (..., n) in q and in c for (batched) similarities."""
        Rt = np.swapaxes(R, -1, -2)
        Pq_hat = s[..., None, None] * (self.Pc @ Rt) + t[..., None, :]
        Pc_hat = ((self.Pq - t[..., None, :]) @ R) / s[..., None, None]
        e_q = _reproj_sq(Pq_hat, self.xq, self.q.fx) / self.sig2_q
        e_c = _reproj_sq(Pc_hat, self.xc, self.c.fx) / self.sig2_c
        return e_q, e_c


def ransac_sim3(
    P_c: np.ndarray,
    P_q: np.ndarray,
    inlier_fn,
    iterations: int,
    rng: np.random.Generator,
) -> tuple[Sim3 | None, np.ndarray]:
    """Best S (P_q ~ S P_c) over ``iterations`` random minimal sets, judged by
    ``inlier_fn(R (H,3,3), t (H,3), s (H,)) -> (H, n) bool``; refit on its inliers."""
    n = len(P_c)
    if n < 3:
        return None, np.zeros(n, bool)
    sets = np.argpartition(rng.random((iterations, n)), 2, axis=1)[:, :3]
    R, t, s = _umeyama_batch(P_c[sets], P_q[sets])
    good = np.isfinite(s) & (s > 1e-9) & np.isfinite(t).all(axis=1)
    if not good.any():
        return None, np.zeros(n, bool)
    R, t, s = R[good], t[good], s[good]
    inl = inlier_fn(R, t, s)
    h = int(inl.sum(axis=1).argmax())
    best = Sim3(R[h], t[h], float(s[h]))
    best_in = inl[h]
    if best_in.sum() >= 3:
        refit = umeyama(P_c[best_in], P_q[best_in])
        r_in = inlier_fn(refit.R[None], refit.t[None], np.array([refit.s]))[0]
        if r_in.sum() >= best_in.sum():
            best, best_in = refit, r_in
    return best, best_in


# -- step 3 and 5: matching by projection ------------------------------------------------
def match_projected(
    P: np.ndarray,
    desc: np.ndarray,
    octave_src: np.ndarray | None,
    depth_src: np.ndarray | None,
    target: KeyframeData,
    allowed: np.ndarray,
    radius_px: float,
    max_hamming: int,
    scale_factor: float,
    k: int = 10,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Match points P (m, 3) in ``target``'s camera frame to its keypoints within a
    radius (scaled by the predicted pyramid level when the source level is known).
    Returns (point index, keypoint index, distance), one point per keypoint."""
    e = np.zeros(0, np.int64)
    cand = np.nonzero(allowed)[0]
    if len(P) == 0 or len(cand) == 0:
        return e, e, e
    z = P[:, 2]
    front = z > 1e-6
    uv = np.where(front[:, None], P[:, :2] / np.where(front, z, 1.0)[:, None], 0.0) * target.fx
    kp = target.xy[cand] * target.fx
    radius = np.full(len(P), radius_px)
    if octave_src is not None and depth_src is not None:
        # The same patch at depth z instead of depth_src shows up depth_src/z times bigger.
        lvl = octave_src + np.log(np.maximum(depth_src, 1e-9) / np.maximum(z, 1e-9)) / np.log(
            scale_factor
        )
        radius = radius_px * scale_factor ** np.clip(np.round(lvl), 0, 7)
    rmax = float(radius.max())
    # Only points in front whose projection falls within reach of some keypoint (the
    # keypoints' bounding box grown by the largest radius) can match: the rest are left
    # out of the k-d tree query and, of the k neighbours found, descriptors are compared
    # only where a keypoint is within the point's radius (most slots have none). The
    # result is the same as comparing all of them (bench_ramp --profile: this function
    # was a quarter of place recognition's CPU).
    lo, hi = kp.min(axis=0) - rmax, kp.max(axis=0) + rmax
    near = np.nonzero(front & (uv[:, 0] >= lo[0]) & (uv[:, 0] <= hi[0])
                      & (uv[:, 1] >= lo[1]) & (uv[:, 1] <= hi[1]))[0]  # fmt: skip
    if len(near) == 0:
        return e, e, e
    kk = min(k, len(cand))
    # Every keypoint allowed: the keyframe's own tree (the same points, the same tree).
    tree = target.pixel_tree if len(cand) == len(target) else cKDTree(kp)
    dist, idx = tree.query(uv[near], k=kk, distance_upper_bound=rmax)
    if kk == 1:
        dist, idx = dist[:, None], idx[:, None]
    valid = (idx < len(cand)) & (dist <= radius[near, None])
    vi, vj = np.nonzero(valid)
    hd = np.full(valid.shape, _BIG, np.int64)
    hd[vi, vj] = hamming_u64(as_u64(target.descriptors)[cand[idx[vi, vj]]],
                             as_u64(desc)[near[vi]])  # fmt: skip
    j = hd.argmin(axis=1)
    best = hd[np.arange(len(near)), j]
    ok = np.nonzero(best <= max_hamming)[0]
    pi, ki = _one_per_target(near[ok], cand[idx[ok, j[ok]]], best[ok])
    best_of = np.full(len(P), _BIG, np.int64)
    best_of[near] = best
    return pi, ki, best_of[pi]


def count_projected(
    P: np.ndarray,
    desc: np.ndarray,
    target: KeyframeData,
    radius_px: float,
    max_hamming: int,
    scale_factor: float,
    at_least: int,
    chunk: int = 256,
) -> int:
    """``len(match_projected(P, desc, None, None, target, all keypoints, ...)[0])`` when
    it is below ``at_least``, else some count >= ``at_least``.

    A point's match does not depend on the other points and the count is the number of
    distinct keypoints matched, which only grows with more points; so the points go
    in chunks and the count stops once it reaches ``at_least`` (a confirmation needs
    20 matches and usually has them in the first chunk of thousands of points)."""
    allowed = np.ones(len(target), bool)
    hit: set[int] = set()
    for a in range(0, len(P), chunk):
        _, ki, _ = match_projected(P[a : a + chunk], desc[a : a + chunk], None, None, target,
                                   allowed, radius_px, max_hamming, scale_factor)  # fmt: skip
        hit.update(ki.tolist())
        if len(hit) >= at_least:
            break
    return len(hit)


def _guided_kf_matches(
    pairs_q: np.ndarray, pairs_c: np.ndarray, S: Sim3, q: KeyframeData, c: KeyframeData,
    p: VerifyParams,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """More q<->c keypoint pairs through S, mutual in both directions (SearchBySim3)."""
    hq, hc = q.has_point.copy(), c.has_point.copy()
    hq[pairs_q] = False
    hc[pairs_c] = False
    src_c = np.nonzero(hc)[0]
    src_q = np.nonzero(hq)[0]
    S_inv = S.inverse()
    Pc_in_q = S.apply(c.p_c[src_c])
    Pq_in_c = S_inv.apply(q.p_c[src_q])
    a_c, a_q, _ = match_projected(
        Pc_in_q, c.descriptors[src_c], c.octaves[src_c].astype(float), S.s * c.p_c[src_c, 2],
        q, hq, p.guided_radius_px, p.guided_max_hamming, p.scale_factor,
    )  # fmt: skip
    b_q, b_c, _ = match_projected(
        Pq_in_c, q.descriptors[src_q], q.octaves[src_q].astype(float), q.p_c[src_q, 2] / S.s,
        c, hc, p.guided_radius_px, p.guided_max_hamming, p.scale_factor,
    )  # fmt: skip
    c_to_q = dict(zip(src_c[a_c].tolist(), a_q.tolist(), strict=True))
    q_to_c = dict(zip(src_q[b_q].tolist(), b_c.tolist(), strict=True))
    mutual = [(iq, ic) for ic, iq in c_to_q.items() if q_to_c.get(iq) == ic]
    if not mutual:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    m = np.array(mutual, np.int64)
    return m[:, 0], m[:, 1]


# -- step 4: refinement ----------------------------------------------------------------
def refine_sim3(pairs: _Pairs, S0: Sim3, huber: float, distance_sigma_rel: float = 0.1) -> Sim3:
    """Least squares over (rotation vector, t, log s) on whitened reprojection errors
    in both images, Huber-robust with width ``huber`` (in sigmas).

    Reprojection alone cannot see the scale when the cameras share a centre (t = 0:
    every p_c can be scaled without moving its projection; a hovering drone does
    this). A weak term on each point's log distance from q's camera anchors it
    there and is outweighed by the image terms whenever they constrain the scale.
    """
    R0 = S0.R
    d_q = np.linalg.norm(pairs.Pq, axis=1)

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        return R0 @ Rotation.from_rotvec(x[:3]).as_matrix(), x[3:6], float(np.exp(x[6]))

    wq = pairs.q.fx / np.sqrt(pairs.sig2_q)
    wc = pairs.c.fx / np.sqrt(pairs.sig2_c)

    def residuals(x: np.ndarray) -> np.ndarray:
        R, t, s = unpack(x)
        Pq_hat = s * pairs.Pc @ R.T + t
        Pc_hat = (pairs.Pq - t) @ R / s
        zq = np.maximum(Pq_hat[:, 2], 1e-6)
        zc = np.maximum(Pc_hat[:, 2], 1e-6)
        rq = (Pq_hat[:, :2] / zq[:, None] - pairs.xq) * wq[:, None]
        rc = (Pc_hat[:, :2] / zc[:, None] - pairs.xc) * wc[:, None]
        rd = np.log(np.linalg.norm(Pq_hat, axis=1) / d_q) / distance_sigma_rel
        return np.concatenate([rq.ravel(), rc.ravel(), rd])

    def residuals_each(X: np.ndarray) -> np.ndarray:
        """``residuals`` of each row of X (k, 7), computed together: (k, m)."""
        Rb = Rotation.from_rotvec(X[:, :3]).as_matrix()
        R = np.stack([R0 @ Rb[i] for i in range(len(X))])
        s = np.array([float(np.exp(X[i, 6])) for i in range(len(X))])[:, None, None]
        t = X[:, None, 3:6]
        Pq_hat = s * pairs.Pc @ np.swapaxes(R, 1, 2) + t
        Pc_hat = (pairs.Pq - t) @ R / s
        zq = np.maximum(Pq_hat[..., 2], 1e-6)
        zc = np.maximum(Pc_hat[..., 2], 1e-6)
        rq = (Pq_hat[..., :2] / zq[..., None] - pairs.xq) * wq[:, None]
        rc = (Pc_hat[..., :2] / zc[..., None] - pairs.xc) * wc[:, None]
        rd = np.log(np.linalg.norm(Pq_hat, axis=-1) / d_q) / distance_sigma_rel
        k = len(X)
        return np.concatenate([rq.reshape(k, -1), rc.reshape(k, -1), rd], axis=1)

    last: list[np.ndarray] = []  # [x, residuals(x)] of the latest evaluation

    def residuals_kept(x: np.ndarray) -> np.ndarray:
        f = residuals(x)
        last[:] = [x.copy(), f]
        return f

    def jac(x: np.ndarray) -> np.ndarray:
        """scipy's '2-point' Jacobian (``approx_derivative`` without bounds: the same
        steps, the same differences and quotients, J transposed the same way) with the
        7 shifted residual vectors computed in one batch instead of 7 calls."""
        f0 = last[1] if last and np.array_equal(last[0], x) else residuals(x)
        sign = (x >= 0).astype(float) * 2 - 1
        h = _EPS_2POINT * sign * np.maximum(1.0, np.abs(x))
        X = np.repeat(x[None], len(x), axis=0)
        idx = np.arange(len(x))
        X[idx, idx] = x + h
        dx = (x + h) - x
        return ((residuals_each(X) - f0) / dx[:, None]).T

    x0 = np.r_[np.zeros(3), S0.t, np.log(S0.s)]
    sol = least_squares(residuals_kept, x0, jac=jac, loss="huber", f_scale=huber, method="trf",
                        x_scale="jac", max_nfev=50)  # fmt: skip
    R, t, s = unpack(sol.x)
    return Sim3(R, t, s)


def estimate_sim3(
    q: KeyframeData,
    c: KeyframeData,
    iq: np.ndarray,
    ic: np.ndarray,
    params: VerifyParams | None = None,
    rng: np.random.Generator | None = None,
) -> tuple[Sim3 | None, np.ndarray]:
    """Sim(3) RANSAC on matched keypoints (q.p_c[iq] ~ S q.p_c[ic]), inliers judged by
    reprojection in both images. Returns (S_q_c or None, inlier mask over the pairs)."""
    p = params or VerifyParams()
    rng = rng if rng is not None else np.random.default_rng(p.seed)
    pairs = _Pairs(q, c, np.asarray(iq, np.int64), np.asarray(ic, np.int64), p)

    def inliers(R, t, s):
        e_q, e_c = pairs.chi2(R, t, s)
        return (e_q < p.chi2) & (e_c < p.chi2)

    return ransac_sim3(pairs.Pc, pairs.Pq, inliers, p.ransac_iterations, rng)


# -- the whole check -------------------------------------------------------------------
def verify(
    q: KeyframeData,
    c: KeyframeData,
    neighbourhood: MapPoints | None = None,
    params: VerifyParams | None = None,
) -> VerifyResult:
    """Verify candidate c for query q. ``neighbourhood``: map points of c's covisible
    keyframes (c's own included) in c's camera frame; defaults to c's own points."""
    p = params or VerifyParams()
    rng = np.random.default_rng([p.seed, int(q.gid) & 0xFFFFFFFF, int(c.gid) & 0xFFFFFFFF])
    stats: dict = {}
    iq, ic = match_by_bow(q, c, p)
    stats["bow_matches"] = len(iq)
    if len(iq) < p.min_bow_matches:
        return VerifyResult(False, f"{len(iq)} BoW matches < {p.min_bow_matches}", stats=stats)

    S, inl = estimate_sim3(q, c, iq, ic, p, rng)
    n_ransac = int(inl.sum())
    stats["ransac_inliers"] = n_ransac
    if S is None or n_ransac < p.ransac_min_inliers:
        return VerifyResult(False, f"Sim(3) RANSAC: {n_ransac} inliers < {p.ransac_min_inliers}",
                            stats=stats)  # fmt: skip

    gq, gc = _guided_kf_matches(iq[inl], ic[inl], S, q, c, p)
    stats["guided_matches"] = len(gq)
    pairs = _Pairs(q, c, np.r_[iq[inl], gq], np.r_[ic[inl], gc], p)
    huber = float(np.sqrt(p.opt_chi2))
    S = refine_sim3(pairs, S, huber, p.distance_sigma_rel)
    keep = _inlier_mask(pairs, S, p.opt_chi2)
    if keep.sum() >= 3:
        pairs = _Pairs(q, c, pairs.iq[keep], pairs.ic[keep], p)
        S = refine_sim3(pairs, S, huber, p.distance_sigma_rel)
        keep = _inlier_mask(pairs, S, p.opt_chi2)
    n_opt = int(keep.sum())
    stats["optimized_inliers"] = n_opt
    stats["scale"] = S.s
    if n_opt < p.min_inliers:
        return VerifyResult(False, f"Sim(3) refinement: {n_opt} inliers < {p.min_inliers}",
                            S.matrix(), S.s, stats=stats)  # fmt: skip
    kq, kc = pairs.iq[keep], pairs.ic[keep]

    # Step 5: the candidate's neighbourhood seen from q.
    nb = neighbourhood if neighbourhood is not None else MapPoints.of_keyframe(c)
    fresh = ~np.isin(nb.mp, c.mp[kc]) & np.isfinite(nb.p_c).all(axis=1)
    allowed = np.ones(len(q), bool)
    allowed[kq] = False
    src = np.nonzero(fresh)[0]
    pi, ki, _ = match_projected(
        S.apply(nb.p_c[src]), nb.descriptors[src], None, None, q, allowed,
        p.neighbourhood_radius_px, p.neighbourhood_max_hamming, p.scale_factor,
    )  # fmt: skip
    n_total = n_opt + len(pi)
    stats["neighbourhood_matches"] = len(pi)
    kp_c_of_mp = {int(m): i for i, m in enumerate(c.mp.tolist()) if m >= 0}
    nb_mp = nb.mp[src[pi]]
    nb_kc = np.array([kp_c_of_mp.get(int(m), -1) for m in nb_mp.tolist()], np.int64)
    res = VerifyResult(
        accepted=n_total >= p.min_total_matches,
        reason="ok" if n_total >= p.min_total_matches
        else f"{n_total} matches after guided search < {p.min_total_matches}",
        S_q_c=S.matrix(),
        scale=S.s,
        kp_q=np.r_[kq, ki].astype(np.int64),
        kp_c=np.r_[kc, nb_kc].astype(np.int64),
        mp_q=np.r_[q.mp[kq], q.mp[ki]].astype(np.int64),
        mp_c=np.r_[c.mp[kc], nb_mp].astype(np.int64),
        n_inliers=n_total,
        stats=stats,
    )  # fmt: skip
    log.debug("verify q=%d c=%d: %s %s", q.gid, c.gid, res.reason, stats)
    return res


def _inlier_mask(pairs: _Pairs, S: Sim3, chi2: float) -> np.ndarray:
    e_q, e_c = pairs.chi2(S.R, S.t, np.float64(S.s))
    return (e_q < chi2) & (e_c < chi2)
