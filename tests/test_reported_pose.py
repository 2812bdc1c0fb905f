"""The reported pose: the server's correction is gated against the VO and paid out
smoothly; a recovery from a loss does not jump."""

from __future__ import annotations

import numpy as np

from services.agent.reported import ReportedPose
from shared.geometry import Sim3, exp_so3


def _walk(n: int, step: float = 0.01) -> list[np.ndarray]:
    """A VO flying along x, turning slowly."""
    out = []
    for i in range(n):
        T = np.eye(4)
        T[:3, :3] = exp_so3(np.array([0.0, 0.002 * i, 0.0]))
        T[:3, 3] = [step * i, 0.0, 0.0]
        out.append(T)
    return out


def _shift(t) -> Sim3:
    return Sim3(np.eye(3), np.asarray(t, float), 1.0)


def test_correction_within_drift_is_taken_and_paid_out_without_a_jump():
    rp = ReportedPose()
    poses = _walk(300)
    rep = [rp.update(T, "ok") for T in poses[:200]]
    # 2 units flown: a 3 cm correction is drift the VO can have.
    assert rp.offer(_shift([0.0, 0.03, 0.0]))
    rep += [rp.update(T, "ok") for T in poses[200:]]
    steps = np.linalg.norm(np.diff([T[:3, 3] for T in rep], axis=0), axis=1)
    assert steps.max() < 0.01 * 1.25 + 1e-9  # never much more than the VO's own step
    # ... and it arrives: the reported pose ends up where the correction puts it.
    assert np.allclose(rep[-1][:3, 3], poses[-1][:3, 3] + [0.0, 0.03, 0.0], atol=1e-6)
    assert rp.offset < 1e-9


def test_an_offset_is_paid_out_at_a_capped_rate_in_fast_flight():
    """A fast camera (a fifth of its step is more than an offset) still gets the offset
    over several frames, never more than ``step_cap`` in one."""
    rp = ReportedPose()
    poses = _walk(300, step=0.08)
    rep = [rp.update(T, "ok") for T in poses[:200]]
    assert rp.offer(_shift([0.0, 0.01, 0.0]))
    rep += [rp.update(T, "ok") for T in poses[200:]]
    off = [R[:3, 3] - T[:3, 3] for R, T in zip(rep, poses, strict=True)]
    extra = np.linalg.norm(np.diff(off, axis=0), axis=1)
    assert extra.max() <= rp.p.step_cap + 1e-9
    assert (extra > 1e-6).sum() >= 3  # 0.01 over at least four frames, not in one
    assert rp.offset < 1e-9


def test_gate_rejects_a_correction_that_contradicts_the_vo():
    rp = ReportedPose()
    poses = _walk(100)
    for T in poses[:50]:
        rp.update(T, "ok")
    before = rp.update(poses[50], "ok")
    # Half a unit of flight cannot have drifted by 1 unit, nor changed scale by 20 %.
    assert not rp.offer(_shift([0.0, 1.0, 0.0]))
    assert not rp.offer(Sim3(np.eye(3), np.zeros(3), 1.2))
    assert rp.rejected == 2
    after = rp.update(poses[51], "ok")
    assert np.allclose(after[:3, 3] - before[:3, 3], poses[51][:3, 3] - poses[50][:3, 3])


def test_a_correction_the_server_repeats_is_taken_after_all():
    """A merge or loop closure really moves the map: the same correction chunk after
    chunk passes the gate, and is then paid out smoothly."""
    rp = ReportedPose()
    poses = _walk(400)
    for T in poses[:50]:
        rp.update(T, "ok")
    S = _shift([0.0, 0.5, 0.0])
    taken = [rp.offer(S) for _ in range(3)]
    assert taken == [False, False, True]
    rep = [rp.update(T, "ok") for T in poses[50:]]
    steps = np.linalg.norm(np.diff([T[:3, 3] for T in rep], axis=0), axis=1)
    assert steps.max() < 0.02
    assert np.allclose(rep[-1][:3, 3], S.transform_pose(poses[-1])[:3, 3], atol=1e-6)


def test_recovery_from_a_loss_follows_the_prediction():
    rp = ReportedPose()
    poses = _walk(200)
    out = [rp.update(T, "ok") for T in poses[:100]]
    # Lost for 10 frames: the VO's prediction stops short; found again 5 cm further on.
    pred = poses[99].copy()
    for _ in range(10):
        out.append(rp.update(pred, "lost", pred))
    found = poses[110]
    out.append(rp.update(found, "ok", pred, was_lost=True))
    assert np.linalg.norm(out[-1][:3, 3] - out[-2][:3, 3]) < 0.01
    out += [rp.update(T, "ok") for T in poses[111:]]
    steps = np.linalg.norm(np.diff([T[:3, 3] for T in out], axis=0), axis=1)
    assert steps.max() < 0.02
    assert np.allclose(out[-1][:3, 3], poses[-1][:3, 3], atol=1e-6)


def test_skipping_the_turn_while_no_orientation_offset_changes_nothing(monkeypatch):
    """The turn of each frame (two scipy calls) is computed only while an orientation
    offset is being paid out; the reported poses are the same bits as computing it
    always, through a rotated correction taken, paid out and done."""
    poses = _walk(400)
    S = Sim3(exp_so3(np.array([0.0, 0.0, 0.05])), np.array([0.0, 0.02, 0.0]), 1.0)

    def fly(rp: ReportedPose) -> list[np.ndarray]:
        out = [rp.update(T, "ok") for T in poses[:100]]
        assert any([rp.offer(S) for _ in range(3)])  # repeated: taken after all
        out += [rp.update(T, "ok") for T in poses[100:]]
        return out

    fast = ReportedPose()
    got = fly(fast)
    assert fast._no_turn_offset()  # paid out to the identity exactly
    monkeypatch.setattr(ReportedPose, "_no_turn_offset", lambda self: False)
    want = fly(ReportedPose())
    assert all(np.array_equal(a, b) for a, b in zip(got, want, strict=True))
