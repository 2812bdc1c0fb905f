"""Deterministic sample messages for the golden-bytes tests."""

from __future__ import annotations

import numpy as np

from shared.geometry import se3
from shared.messages import Ack, KeyframeBatch, MapPoints, NewKeyframe, PoseUpdate


def sample_batch() -> KeyframeBatch:
    rng = np.random.default_rng(7)
    n = 5
    kf = NewKeyframe(
        id=3,
        stamp_ns=1403636580863555584,
        T_l_kf=se3(np.eye(3), [1.0, 2.0, 3.0]),
        pred_id=2,
        T_pred_kf=se3(np.eye(3), [0.1, 0.0, 0.0]),
        parent_id=1,
        T_par_kf=se3(np.eye(3), [0.3, 0.0, 0.0]),
        keypoints=rng.uniform(0, 700, (n, 2)).astype(np.float32),
        octaves=np.arange(n, dtype=np.uint8),
        descriptors=rng.integers(0, 256, (n, 32), dtype=np.uint8),
        mp_ids=np.array([10, -1, 11, 12, -1], np.int64),
    )
    mps = MapPoints(
        np.array([10, 11, 12], np.int64),
        np.array([3, 3, 3], np.int64),
        rng.normal(size=(3, 3)),
        rng.integers(0, 256, (3, 32), dtype=np.uint8),
    )
    return KeyframeBatch("A", 4, 1403636580900000000, 3, [kf], [], mps)


def sample_ack() -> Ack:
    return Ack("A", "map-A", np.array([1, 2, 3], np.int64), np.array([10, 11], np.int64), 3, 42)


def sample_pose() -> PoseUpdate:
    return PoseUpdate("A", 1403636580863555584, np.eye(4), 3, np.eye(4), "ok", 20.0)
