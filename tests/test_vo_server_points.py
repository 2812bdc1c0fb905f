"""Server points in the agent's tracking: used where its own map is thin, left out where
its own points suffice (then tracking is exactly what it is without a server)."""

from __future__ import annotations

import numpy as np
import pytest

from services.agent.sources import open_source
from services.agent.vo.odometry import VisualOdometry
from shared.geometry import exp_so3, se3

SRC = "synthetic:MH01?frames=1200:1250"
SWITCH = 20  # frame after which the server's points arrive


@pytest.fixture(scope="module")
def frames():
    src = open_source(SRC)
    return src.camera, [(f.image, f.stamp_ns) for f in src]


def _fly(camera, frames, server=None) -> tuple[list[np.ndarray], VisualOdometry]:
    vo = VisualOdometry(camera)
    poses = []
    for i, (img, stamp) in enumerate(frames):
        if i == SWITCH and server is not None:
            server(vo)
        r = vo.track(img, stamp)
        assert r.state != "lost", i
        poses.append(np.full((4, 4), np.nan) if r.T_w_c is None else r.T_w_c)
    return poses, vo


def _server_copy(vo: VisualOdometry, scale: float = 1.0,
                 shift: tuple = (0, 0, 0)) -> tuple[list, np.ndarray, np.ndarray]:  # fmt: skip
    """The agent's current points as the server would send them back (under other
    agents' names), optionally off by a scale about the newest keyframe's camera and
    by a ``shift`` (map units)."""
    own = [m for m in vo.mps.values() if m.id not in vo.foreign]
    c = vo.last_kf.T_w_c[:3, 3]
    pos = np.array([c + scale * (m.pos - c) for m in own]) + np.asarray(shift)
    return [("other", m.id) for m in own], pos, np.array([m.desc for m in own])


def test_server_points_do_not_touch_tracking_where_own_points_suffice(frames):
    cam, fr = frames
    plain, _ = _fly(cam, fr)

    def send(vo: VisualOdometry) -> None:
        # A coherent 4 % offset: the kind of disagreement between the server's map and
        # the VO that made server points pull the pose when they were always used.
        assert vo.add_foreign_points(*_server_copy(vo, 1.04)) > 100

    with_server, vo = _fly(cam, fr, send)
    np.testing.assert_array_equal(np.stack(with_server), np.stack(plain))
    assert not any(k.mp[k.mp >= 0].max(initial=-1) >= 1 << 50 for k in vo.kfs.values())


def test_server_points_carry_tracking_where_own_map_is_gone(frames):
    """The agent's own points vanish (as if it had flown into a place only another
    agent mapped): the server's points keep it tracking, close to its own poses."""
    cam, fr = frames
    plain, _ = _fly(cam, fr)

    def swap(vo: VisualOdometry) -> None:
        sent = _server_copy(vo)
        for i in [i for i in vo.mps if i not in vo.foreign]:
            vo._remove_mp(i)
        vo.add_foreign_points(*sent)

    with_server, vo = _fly(cam, fr, swap)
    err = np.linalg.norm(np.stack(with_server)[:, :3, 3] - np.stack(plain)[:, :3, 3], axis=1)
    # Map units (median scene depth 1 at initialization): well under a percent of it.
    assert np.isfinite(err[SWITCH:]).all() and err[SWITCH:].max() < 0.01, err[SWITCH:]
    used = sum(int((k.mp >= 1 << 50).sum()) for k in vo.kfs.values())
    assert used > 50


def _jolt(vo: VisualOdometry) -> None:
    """The motion model expects a turn (2 deg) and a sidestep the camera does not make:
    the first pass then finds only ~50 own inliers, in the wide window, though the
    refined pose has ~200 of them (a poor prediction, not a thin map)."""
    step = se3(exp_so3(np.deg2rad(2.0) * np.array([0.0, 1.0, 0.0])), np.array([0.05, 0, 0]))
    vo.velocity = vo.velocity @ step


@pytest.mark.parametrize("scale, shift", [(1.04, (0, 0, 0)), (1.0, (0.04, -0.03, 0.03))])
def test_server_points_stay_out_when_a_poor_prediction_weakened_the_first_pass(
        frames, scale, shift):  # fmt: skip
    """MH05 at every=3 with a server: on the one frame whose first pass found 41 own
    inliers (wide window) the server's points joined, and the pose (a keyframe) was
    0.17 m off while its neighbours were right. Where the agent's own points suffice once
    the pose is refined, tracking must be exactly what it is without a server."""
    cam, fr = frames
    plain, _ = _fly(cam, fr, _jolt)
    first = []

    def send(vo: VisualOdometry) -> None:
        assert vo.add_foreign_points(*_server_copy(vo, scale, shift)) > 100
        _jolt(vo)
        predict = vo._predict

        def spy(f, T_pred, P, D):
            out = predict(f, T_pred, P, D)
            first.append(-1 if out[0] is None else int(out[0].inliers.sum()))
            return out

        vo._predict = spy

    with_server, vo = _fly(cam, fr, send)
    # The case happened: an own first pass above min_inliers but weak.
    assert vo.p.min_inliers <= first[0] < vo._strong, first[:3]
    err = np.linalg.norm(np.stack(with_server)[:, :3, 3] - np.stack(plain)[:, :3, 3], axis=1)
    assert np.nanmax(err) < 1e-9, (np.nanargmax(err), np.nanmax(err))
    np.testing.assert_array_equal(np.stack(with_server), np.stack(plain))
    assert not any(k.mp[k.mp >= 0].max(initial=-1) >= 1 << 50 for k in vo.kfs.values())
