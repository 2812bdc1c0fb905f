"""ORB features as every service uses them: extraction, pyramid constants, Hamming distance.

The agent extracts; the mapper, place recognition and the optimizer reason about what
it extracted (a keypoint on pyramid level ``o`` is measured with a standard deviation
of ``SCALE_FACTOR ** o`` pixels, ORB-SLAM's rule), so the pyramid is defined here once.

OpenCV's ORB clusters keypoints on strong texture; like ORB-SLAM the extractor detects
more candidates than needed and keeps the strongest per grid cell, so every part of the
image contributes (which PnP and triangulation need).

Hamming distances of 256-bit descriptors are four 64-bit popcounts (``np.bitwise_count``
on a ``uint64`` view: 5x faster than a byte table). ``hamming`` takes ``(..., 32)``
uint8 descriptors; code that compares the same descriptors many times keeps the
``uint64`` view (``as_u64``) and calls ``hamming_u64``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from shared.camera import PinholeRadTan

SCALE_FACTOR = 1.2  # pyramid: level o is the image scaled by 1 / SCALE_FACTOR**o
N_LEVELS = 8
EDGE_THRESHOLD = 19  # px border without keypoints (ORB's patch needs it)
FAST_THRESHOLD = 12
DESCRIPTOR_BYTES = 32


def level_sigma(octave: np.ndarray | int) -> np.ndarray | float:
    """Standard deviation in pixels of a keypoint found on pyramid level ``octave``."""
    return SCALE_FACTOR ** np.asarray(octave, np.float64)


def as_u64(desc: np.ndarray) -> np.ndarray:
    """(N, 32) uint8 ORB descriptors -> (N, 4) uint64 view (copied if not contiguous)."""
    d = np.ascontiguousarray(desc, dtype=np.uint8)
    if d.ndim != 2 or d.shape[1] != DESCRIPTOR_BYTES:
        raise ValueError(f"expected (N, 32) uint8 descriptors, got {d.shape}")
    return d.view(np.uint64)


def hamming_u64(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distance between broadcastable (..., 4) uint64 descriptor arrays."""
    c = np.bitwise_count(np.bitwise_xor(a, b))  # (..., 4) uint8, each at most 64
    # The four words added by hand: a reduction over an axis of length 4 cost 2.5x as
    # much as the popcounts (place recognition's vocabulary descent, point fusion).
    # Pairs first in uint8 (at most 128 each), then the two pairs in int32 (256 fits).
    return np.add(c[..., 0] + c[..., 1], c[..., 2] + c[..., 3], dtype=np.int32)


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distance between broadcastable (..., 32) uint8 descriptor arrays."""
    a = np.ascontiguousarray(a, dtype=np.uint8)
    b = np.ascontiguousarray(b, dtype=np.uint8)
    return hamming_u64(a.view(np.uint64), b.view(np.uint64))


@dataclass
class Features:
    kp: np.ndarray  # (N, 2) float32 distorted pixels
    octave: np.ndarray  # (N,) uint8 pyramid level
    desc: np.ndarray  # (N, 32) uint8
    xy: np.ndarray  # (N, 2) float64 undistorted normalized coordinates
    _tree: cKDTree | None = None

    def __len__(self) -> int:
        return len(self.kp)

    @property
    def tree(self) -> cKDTree:
        """k-d tree over the keypoints' pixels, for searches by projection."""
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
        self.orb = cv2.ORB_create(nfeatures=int(n_features * oversample), scaleFactor=SCALE_FACTOR,
                                  nlevels=N_LEVELS, edgeThreshold=EDGE_THRESHOLD,
                                  fastThreshold=FAST_THRESHOLD)  # fmt: skip

    def __call__(self, img: np.ndarray) -> Features:
        kps = self.orb.detect(img, None)
        if len(kps) > self.n:
            kps = self._spread(kps, img.shape)
        kps, desc = self.orb.compute(img, kps)
        if desc is None or not kps:
            z = np.zeros((0, 2))
            return Features(z.astype(np.float32), np.zeros(0, np.uint8),
                            np.zeros((0, DESCRIPTOR_BYTES), np.uint8), z)  # fmt: skip
        kp = cv2.KeyPoint_convert(kps).reshape(-1, 2)  # float32, as k.pt (~1 ms less)
        octv = np.array([k.octave for k in kps], np.uint8)
        return Features(kp, octv, desc, self.cam.undistort_points(kp))

    def _spread(self, kps, shape) -> list:
        gx, gy = self.grid
        h, w = shape
        pts = cv2.KeyPoint_convert(kps).reshape(-1, 2).astype(np.float64)
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
