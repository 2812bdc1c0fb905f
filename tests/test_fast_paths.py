"""The server's per-keyframe fast paths (issue 18 item 1) give what the plain numpy they
replace gives: id-set helpers against np.unique / np.isin, Hamming distances against a
bit count, guided matching by projection against comparing every neighbour."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from services.placerec.keyframe import KeyframeData
from services.placerec.verify import _BIG, _one_per_target, match_projected
from shared.ids import gid, in_sorted, present_in, unique_ids
from shared.orb import as_u64, hamming, hamming_u64


def test_id_sets_equal_numpy():
    rng = np.random.default_rng(0)
    for n, m in [(0, 5), (1, 0), (7, 3), (3000, 800), (500, 5000)]:
        a = gid(rng.integers(0, 4, n), rng.integers(0, 2000, n)).astype(np.int64)
        b = gid(rng.integers(0, 4, m), rng.integers(0, 2000, m)).astype(np.int64)
        b = np.where(rng.random(m) < 0.2, -1, b)  # "no point" entries
        u = unique_ids(a)
        assert np.array_equal(u, np.unique(a))
        assert np.array_equal(u[~present_in(u, b)], np.setdiff1d(a, b[b >= 0]))
        assert np.array_equal(present_in(u, b), np.isin(u, b))
        assert np.array_equal(in_sorted(b, u), np.isin(b, u))


def test_hamming_equals_a_bit_count():
    rng = np.random.default_rng(1)
    a = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    b[:3] = a[:3]  # distance 0
    b[3:6] = ~a[3:6]  # all 256 bits differ: the largest sum
    want = np.unpackbits(a ^ b, axis=1).sum(axis=1)
    assert np.array_equal(hamming(a, b), want)
    assert hamming(a, b).dtype == np.int32 and want[3:6].tolist() == [256] * 3
    # Broadcast (n, 1, 4) against (n, k, 4), as the matchers call it.
    got = hamming_u64(as_u64(a)[:, None, :], as_u64(b)[None, :50, :])
    assert np.array_equal(got[7], np.unpackbits(a[7] ^ b[:50], axis=1).sum(axis=1))


def _match_projected_all(P, desc, target, allowed, radius_px, max_hamming, k=10):
    """Guided matching comparing every one of the k neighbours of every point (the
    form match_projected had before it left out points out of reach)."""
    cand = np.nonzero(allowed)[0]
    z = P[:, 2]
    front = z > 1e-6
    uv = np.where(front[:, None], P[:, :2] / np.where(front, z, 1.0)[:, None], 0.0) * target.fx
    kp = target.xy[cand] * target.fx
    radius = np.full(len(P), radius_px)
    kk = min(k, len(cand))
    dist, idx = cKDTree(kp).query(uv, k=kk, distance_upper_bound=float(radius.max()))
    valid = (idx < len(cand)) & (dist <= radius[:, None]) & front[:, None]
    kidx = cand[np.where(valid, idx, 0)]
    hd = hamming_u64(as_u64(target.descriptors)[kidx], as_u64(desc)[:, None, :])
    hd = np.where(valid, hd, _BIG)
    j = hd.argmin(axis=1)
    best = hd[np.arange(len(P)), j]
    ok = np.nonzero(best <= max_hamming)[0]
    pi, ki = _one_per_target(ok, kidx[ok, j[ok]], best[ok])
    return pi, ki, best[pi]


def test_match_projected_equals_comparing_every_neighbour():
    rng = np.random.default_rng(2)
    n = 800
    xy = rng.uniform(-0.6, 0.6, (n, 2))
    desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    target = KeyframeData(1, "m", "a", xy, np.zeros(n, np.uint8), desc, np.full(n, -1),
                          np.full((n, 3), np.nan), 458.0)  # fmt: skip
    # Points: near keypoints (descriptors a few bits off), far outside the image, behind.
    m = 1500
    src = rng.integers(0, n, m)
    depth = rng.uniform(1.0, 8.0, m)
    uv = xy[src] + rng.normal(0, 2.0 / 458.0, (m, 2))
    uv[:300] += 3.0  # out of reach of every keypoint
    P = np.c_[uv * depth[:, None], depth]
    P[300:400, 2] *= -1  # behind the camera
    d = desc[src].copy()
    flip = rng.integers(0, 32, (m, 3))
    for c in range(3):
        d[np.arange(m), flip[:, c]] ^= np.uint8(1 << c)
    d[400:600] = rng.integers(0, 256, (200, 32), dtype=np.uint8)  # no good match
    allowed = rng.random(n) < 0.9
    got = match_projected(P, d, None, None, target, allowed, 4.0, 50, 1.2)
    want = _match_projected_all(P, d, target, allowed, 4.0, 50)
    assert len(want[0]) > 400
    for g, w in zip(got, want, strict=True):
        assert np.array_equal(g, w)
