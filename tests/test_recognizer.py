"""PlaceRecognizer's check of a verified Sim(3) in the query's covisible keyframes:
the true similarity predicts where the candidate's points appear in a neighbour of the
query; one a few degrees off does not (ORB-SLAM3's common-region check)."""

from __future__ import annotations

import numpy as np
import pytest

from services.placerec.keyframe import KeyframeData
from services.placerec.recognizer import PlaceRecognizer, _Kf
from services.placerec.vocabulary import Vocabulary
from shared.geometry import Sim3, exp_so3, se3, se3_inv


@pytest.fixture(scope="module")
def voc() -> Vocabulary:
    return Vocabulary.load()


def _view(g: int, T_w_c: np.ndarray, P_w: np.ndarray, desc: np.ndarray, scale: float,
          map_id: str) -> KeyframeData:  # fmt: skip
    """A keyframe seeing every world point in front of it; positions in map units of
    ``scale`` metres."""
    T = se3_inv(T_w_c)
    P_c = P_w @ T[:3, :3].T + T[:3, 3]
    front = P_c[:, 2] > 0.5
    xy = P_c[front, :2] / P_c[front, 2:]
    n = int(front.sum())
    return KeyframeData(g, map_id, "a", xy, np.zeros(n, np.uint8), desc[front],
                        np.nonzero(front)[0].astype(np.int64) + 1000 * g, P_c[front] / scale,
                        458.654)  # fmt: skip


def test_sim3_is_confirmed_in_query_neighbours_only_when_right(voc):
    rng = np.random.default_rng(3)
    P_w = np.c_[rng.uniform(-4, 4, 600), rng.uniform(-3, 3, 600), rng.uniform(4, 9, 600)]
    desc = rng.integers(0, 256, (600, 32), dtype=np.uint8)
    T_q = np.eye(4)
    T_n = se3(exp_so3(np.array([0.0, 0.05, 0.0])), np.array([0.3, 0.0, 0.1]))
    T_c = se3(exp_so3(np.array([0.02, -0.15, 0.03])), np.array([-0.8, 0.1, -0.3]))
    k = 2.0  # the candidate's map is in units of 2 m
    rec = PlaceRecognizer(voc)
    rec.kfs[1] = _Kf(_view(1, T_q, P_w, desc, 1.0, "A"), T_q, "A", 1, 1)
    rec.kfs[2] = _Kf(_view(2, T_n, P_w, desc, 1.0, "A"), T_n, "A", 2, 2)
    rec.kfs[3] = _Kf(_view(3, T_c, P_w, desc, k, "B"), se3(np.eye(3), np.zeros(3)), "B", 3, 3)
    rec.covis = {1: [2], 2: [1], 3: []}
    T_q_c = se3_inv(T_q) @ T_c
    S_true = Sim3(T_q_c[:3, :3], T_q_c[:3, 3], k)
    assert rec.confirm_in_neighbours(1, S_true.matrix(), 3) == (1, 1)
    tilted = Sim3(exp_so3(np.array([0.0, np.deg2rad(5.0), 0.0])) @ S_true.R, S_true.t, k)
    assert rec.confirm_in_neighbours(1, tilted.matrix(), 3) == (1, 0)
    # Without a neighbour of the query there is nothing to check (the caller decides).
    rec.covis[1] = []
    assert rec.confirm_in_neighbours(1, S_true.matrix(), 3) == (0, 0)
