"""The agent's local map: CCM-SLAM §4.2 trimming rules, keyframe removal, covisibility."""

from __future__ import annotations

import numpy as np
import pytest

from services.agent.local_map_trim import KfInfo, trim
from services.agent.vo.covisibility import EDGE_MIN, build_covisibility
from services.agent.vo.odometry import KeyFrame, MapPoint, VisualOdometry, remove_keyframe
from shared.camera import PinholeRadTan
from shared.orb import Features


def _own(i: int, acked: bool = False) -> KfInfo:
    return KfInfo(i, True, acked)


def _apply(kfs: list[KfInfo], gone: list[int]) -> list[KfInfo]:
    return [k for k in kfs if k.id not in gone]


# --- trimming ----------------------------------------------------------------------------


def test_trim_nothing_while_within_n():
    kfs = [_own(i) for i in range(5)]
    assert trim(kfs, kf_ref=4, n=5, b=5) == []


def test_trim_keeps_old_kf_ref_even_when_acked():
    kfs = [_own(i, acked=True) for i in range(10)]
    gone = trim(kfs, kf_ref=0, n=4, b=4)
    assert 0 not in gone
    # KF_ref plus the N-1 newest stay.
    assert sorted(k.id for k in _apply(kfs, gone)) == [0, 7, 8, 9]


def test_trim_holds_n_keyframes_when_kf_ref_is_newest():
    kfs = [_own(i, acked=True) for i in range(10)]
    gone = trim(kfs, kf_ref=9, n=4, b=4)
    assert len(_apply(kfs, gone)) == 4


def test_trim_buffer_empties_once_acks_arrive():
    # Server gone: 5 old unacknowledged keyframes wait in the buffer (B = 6).
    kfs = [_own(i) for i in range(9)]
    assert trim(kfs, kf_ref=8, n=4, b=6) == []
    # Acks for 0..2 arrive: exactly those leave, 3 and 4 (still unacked) stay buffered.
    kfs = [_own(i, acked=i < 3) for i in range(9)]
    assert trim(kfs, kf_ref=8, n=4, b=6) == [0, 1, 2]


def test_trim_unacked_are_dropped_only_when_buffer_full_oldest_first():
    kfs = [_own(i) for i in range(12)]
    n, b = 4, 5
    gone = trim(kfs, kf_ref=11, n=n, b=b)
    left = _apply(kfs, gone)
    assert len(left) <= n + b
    # What goes is the oldest unacknowledged ones, nothing newer.
    assert gone == list(range(len(gone)))
    assert {8, 9, 10, 11} <= {k.id for k in left}


def test_trim_foreign_before_own_unacked_then_oldest_own():
    # Own 0..5 unacked, foreign (from the server, acked) 6, 7, own 8..11 unacked.
    kfs = [_own(i) for i in range(6)] + [KfInfo(6, False, True), KfInfo(7, False, True)]
    kfs += [_own(i) for i in range(8, 12)]
    # Within N + B = 12: only acked old ones may go; foreign 6, 7 are old and acked.
    assert trim(kfs, kf_ref=11, n=4, b=8) == [6, 7]
    # N + B = 8 with 12 stored: both foreign go first, then own 0 and 1 (oldest).
    assert trim(kfs, kf_ref=11, n=4, b=4) == [0, 1, 6, 7]
    # Recent foreign keyframes go before any own unacked one as well.
    kfs2 = [_own(i) for i in range(8)] + [KfInfo(8, False, True), KfInfo(9, False, True)]
    assert trim(kfs2, kf_ref=9, n=4, b=5) == [8]


def test_trim_bounds_hold_on_random_histories():
    """Any sequence of inserts, acks and trims keeps the map within N + B keyframes,
    KF_ref and the newest always survive, and once over N no acked keyframe older
    than the N-1 newest stays."""
    rng = np.random.default_rng(7)
    n, b = 6, 4
    kfs: list[KfInfo] = []
    for i in range(200):
        kfs.append(KfInfo(i, bool(rng.random() > 0.2), False))
        # Foreign keyframes come from the server: always acked. Own ones get acked
        # with some delay, sometimes not at all (link down).
        kfs = [KfInfo(k.id, k.own, (not k.own) or k.acked or bool(rng.random() < 0.3)) for k in kfs]
        ref = i if rng.random() > 0.1 else int(rng.choice([k.id for k in kfs]))
        gone = trim(kfs, kf_ref=ref, n=n, b=b)
        kfs = _apply(kfs, gone)
        ids = [k.id for k in kfs]
        assert len(kfs) <= n + b
        assert ref in ids and i in ids
        newest = set(sorted(set(ids) - {ref})[-(n - 1) :])
        # Beyond N keyframes, everything old is waiting for an ack.
        assert len(kfs) <= n or all(not k.acked for k in kfs if k.id not in newest and k.id != ref)


# --- keyframe removal cleans observations -----------------------------------------------


def _kf(kf_id: int, mp: list[int]) -> KeyFrame:
    n = len(mp)
    f = Features(
        np.zeros((n, 2), np.float32),
        np.zeros(n, np.uint8),
        np.zeros((n, 32), np.uint8),
        np.zeros((n, 2)),
    )
    return KeyFrame(kf_id, 0, np.eye(4), f, np.array(mp, np.int64))


def test_remove_keyframe_cleans_observations_and_orphan_points():
    vo = VisualOdometry(PinholeRadTan.euroc_cam0())
    # KF 0 sees points 0, 1, 2; KF 1 sees 1, 2; point 0 is seen only by KF 0.
    vo.kfs = {0: _kf(0, [0, 1, -1, 2]), 1: _kf(1, [-1, 1, 2])}
    vo.mps = {
        0: MapPoint(0, np.zeros(3), np.zeros(32, np.uint8), {0: 0}),
        1: MapPoint(1, np.zeros(3), np.zeros(32, np.uint8), {0: 1, 1: 1}),
        2: MapPoint(2, np.zeros(3), np.zeros(32, np.uint8), {0: 3, 1: 2}),
    }
    dead = remove_keyframe(vo, 0)
    assert dead == [0]
    assert set(vo.kfs) == {1} and set(vo.mps) == {1, 2}
    assert vo.mps[1].obs == {1: 1} and vo.mps[2].obs == {1: 2}
    assert remove_keyframe(vo, 0) == []  # already gone: a no-op


# --- covisibility ------------------------------------------------------------------------


def _kf_mp(rng: np.random.Generator, seen: np.ndarray, n_kp: int = 300) -> np.ndarray:
    """Keypoint -> map point array holding the points ``seen`` among unmatched keypoints."""
    mp = np.full(n_kp, -1, np.int64)
    mp[rng.choice(n_kp, len(seen), replace=False)] = seen
    return mp


def test_covisibility_weights_threshold_and_parent():
    rng = np.random.default_rng(3)
    # KF 0: points 0..99; KF 1: 80..179 (20 shared with 0); KF 2: 170..269 (10 with 1);
    # KF 3: 0..29 and 90..119 (40 with 0, 30 with 1, none with 2).
    kf_mp = {
        0: _kf_mp(rng, np.arange(0, 100)),
        1: _kf_mp(rng, np.arange(80, 180)),
        2: _kf_mp(rng, np.arange(170, 270)),
        3: _kf_mp(rng, np.r_[np.arange(0, 30), np.arange(90, 120)]),
    }
    cov = build_covisibility(kf_mp)
    assert cov.weight(0, 1) == cov.weight(1, 0) == 20
    assert cov.weight(1, 2) == 10 and cov.weight(0, 2) == 0
    assert cov.weight(0, 3) == 40 and cov.weight(1, 3) == 30 and cov.weight(2, 3) == 0
    assert cov.weight(2, 2) == 0
    # Edges need EDGE_MIN = 15 shared points: 1-2 (10) is no edge.
    assert EDGE_MIN == 15
    assert cov.neighbours(1) == [(3, 30), (0, 20)]
    assert cov.neighbours(3) == [(0, 40), (1, 30)]
    assert cov.neighbours(2) == []
    assert cov.neighbours(2, min_weight=1) == [(1, 10)]
    # Parent: strongest older covisible keyframe, even below the edge threshold.
    assert cov.parent(0) == -1
    assert cov.parent(1) == 0
    assert cov.parent(2) == 1
    assert cov.parent(3) == 0
    with pytest.raises(KeyError):
        cov.weight(0, 9)


def test_covisibility_matches_brute_force_count():
    rng = np.random.default_rng(11)
    kf_mp = {k: _kf_mp(rng, rng.choice(400, 120, replace=False)) for k in range(0, 40, 2)}
    cov = build_covisibility(kf_mp)
    sets = {k: set(m[m >= 0].tolist()) for k, m in kf_mp.items()}
    for a in sets:
        for b in sets:
            want = 0 if a == b else len(sets[a] & sets[b])
            assert cov.weight(a, b) == want
    assert build_covisibility({}).weights.shape == (0, 0)
