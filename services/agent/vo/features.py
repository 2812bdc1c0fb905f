"""ORB features spread over the image, and descriptor matching.

OpenCV's ORB clusters keypoints on strong texture; like ORB-SLAM we detect more
candidates than needed and keep the strongest per grid cell, so every part of the
image contributes (which PnP and triangulation need). Matching by projection uses
a k-d tree over keypoints (scipy) and a popcount table for Hamming distances.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from shared.camera import PinholeRadTan

POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return POPCOUNT[np.bitwise_xor(a, b)].sum(axis=-1, dtype=np.int32)


@dataclass
class Features:
    kp: np.ndarray  # (N, 2) float32 distorted pixels
    octave: np.ndarray  # (N,) uint8
    desc: np.ndarray  # (N, 32) uint8
    xy: np.ndarray  # (N, 2) float64 undistorted normalized coordinates
    _tree: cKDTree | None = None

    def __len__(self) -> int:
        return len(self.kp)

    @property
    def tree(self) -> cKDTree:
        if self._tree is None:
            self._tree = cKDTree(self.kp.astype(np.float64))
        return self._tree


class Extractor:
    def __init__(
        self,
        camera: PinholeRadTan,
        n_features: int = 1000,
        grid: tuple[int, int] = (8, 6),
        oversample: float = 2.0,
    ) -> None:
        self.cam = camera
        self.n = n_features
        self.grid = grid
        self.orb = cv2.ORB_create(nfeatures=int(n_features * oversample), scaleFactor=1.2,
                                  nlevels=8, edgeThreshold=19, fastThreshold=12)  # fmt: skip

    def __call__(self, img: np.ndarray) -> Features:
        kps = self.orb.detect(img, None)
        if len(kps) > self.n:
            kps = self._spread(kps, img.shape)
        kps, desc = self.orb.compute(img, kps)
        if desc is None or not kps:
            z = np.zeros((0, 2))
            return Features(z.astype(np.float32), np.zeros(0, np.uint8),
                            np.zeros((0, 32), np.uint8), z)  # fmt: skip
        kp = np.array([k.pt for k in kps], np.float32)
        octv = np.array([k.octave for k in kps], np.uint8)
        return Features(kp, octv, desc, self.cam.undistort_points(kp))

    def _spread(self, kps, shape) -> list:
        gx, gy = self.grid
        h, w = shape
        pts = np.array([k.pt for k in kps])
        resp = np.array([k.response for k in kps])
        cell = (np.minimum(pts[:, 1] * gy // h, gy - 1) * gx
                + np.minimum(pts[:, 0] * gx // w, gx - 1)).astype(int)  # fmt: skip
        order = np.lexsort((-resp, cell))
        # Rank inside each cell; take ranks round-robin until n are chosen.
        sc = cell[order]
        start = np.r_[0, np.nonzero(np.diff(sc))[0] + 1]
        rank = np.arange(len(sc)) - np.repeat(start, np.diff(np.r_[start, len(sc)]))
        pick = order[np.lexsort((-resp[order], rank))][: self.n]
        return [kps[i] for i in pick]


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
