"""Descriptor matching of the on-board VO: by projection and brute force.

Extraction, the pyramid and the Hamming distance are ``shared.orb`` (the server reasons
about the same features). Matching by projection uses the keypoints' k-d tree
(``Features.tree``) and takes the best descriptor within a radius.
"""

from __future__ import annotations

import cv2
import numpy as np

from shared.orb import Features, hamming


def match_by_projection(
    feats: Features,
    uv: np.ndarray,
    desc: np.ndarray,
    radius: float,
    max_dist: int = 64,
    ratio: float = 0.9,
    k: int = 8,
) -> tuple[np.ndarray, np.ndarray]:
    """Match projected points (uv, desc) to keypoints within ``radius`` px.
    Returns (point index, keypoint index) pairs, one point per keypoint."""
    if len(uv) == 0 or len(feats) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    k = min(k, len(feats))
    dist, idx = feats.tree.query(uv, k=k, distance_upper_bound=radius)
    if k == 1:
        idx = idx[:, None]
    valid = idx < len(feats)
    idx0 = np.where(valid, idx, 0)
    hd = hamming(feats.desc[idx0], desc[:, None, :])
    hd = np.where(valid, hd, 1 << 20)
    o = np.argsort(hd, axis=1)
    best = hd[np.arange(len(uv)), o[:, 0]]
    second = hd[np.arange(len(uv)), o[:, 1]] if k > 1 else np.full(len(uv), 1 << 20)
    kp = idx0[np.arange(len(uv)), o[:, 0]]
    good = (best <= max_dist) & ((second >= (1 << 20)) | (best < ratio * second))
    pi = np.nonzero(good)[0]
    kp = kp[pi]
    # One point per keypoint: the best descriptor distance wins.
    order = np.argsort(best[pi], kind="stable")
    _, first = np.unique(kp[order], return_index=True)
    sel = order[first]
    return pi[sel], kp[sel]


def match_descriptors(d1: np.ndarray, d2: np.ndarray, ratio: float = 0.8,
                      max_dist: int = 64) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Brute-force Hamming matches with the ratio test and mutual consistency."""
    if len(d1) < 2 or len(d2) < 2:
        return np.zeros(0, int), np.zeros(0, int)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    knn = bf.knnMatch(d1, d2, k=2)
    a, b = [], []
    for m in knn:
        if len(m) == 2 and m[0].distance < ratio * m[1].distance and m[0].distance <= max_dist:
            a.append(m[0].queryIdx)
            b.append(m[0].trainIdx)
    a, b = np.array(a, int), np.array(b, int)
    # Mutual: keep the best match per train keypoint.
    if len(b):
        _, first = np.unique(b, return_index=True)
        a, b = a[first], b[first]
    return a, b
