"""The simulated agent's observation model, checked against brute force: its culls
(float32 cone, image box) only save work, they never drop a landmark that projects."""

from __future__ import annotations

import numpy as np

from services.agent.sim_agent import DriftModel, SimAgent, _bit_flips
from shared.trajectory import load_euroc_gt


def _brute_force(sim: SimAgent, T_w_c: np.ndarray) -> np.ndarray:
    """Ids of every landmark that projects into the image within range, in float64."""
    c, R = T_w_c[:3, 3], T_w_c[:3, :3]
    D = sim.world.points - c
    X_c = D @ R
    ok = (X_c[:, 2] > 0.2) & (X_c[:, 2] < sim.max_range) & (np.abs(D) < sim.max_range).all(1)
    _, valid = sim.cam.project(X_c, min_depth=0.2)
    return np.nonzero(ok & valid)[0]


def test_observe_sees_every_landmark_that_projects(world):
    gt = load_euroc_gt("MH04")
    sim = SimAgent(gt, world, drift=DriftModel.zero(), max_features=10**9)
    seen = 0
    for k in range(0, len(gt), 97):
        ids, X_c, uv = sim.observe(gt.poses[k])
        np.testing.assert_array_equal(ids, _brute_force(sim, gt.poses[k]))
        uv_ref, _ = sim.cam.project(X_c, min_depth=0.2)
        np.testing.assert_allclose(uv, uv_ref)  # no pixel noise in the zero model
        seen += len(ids)
    assert seen > 10_000  # the poses see the hall, not an empty corner


def test_bit_flips_are_independent_bits_at_the_rate_asked():
    rng = np.random.default_rng(5)
    assert not _bit_flips(rng, 10, 0.0).any()
    assert (_bit_flips(rng, 10, 1.0) == 0xFF).all()  # every gap is 1: every bit set
    bits = np.unpackbits(_bit_flips(rng, 4000, 0.03), axis=1)  # (4000, 256)
    assert bits.shape == (4000, 256)
    sd = np.sqrt(0.03 * 0.97 / bits.size)
    assert abs(bits.mean() - 0.03) < 5 * sd
    # No bit position favoured (every bit of every byte reached) ...
    per_pos = bits.mean(axis=0)
    assert np.abs(per_pos - 0.03).max() < 5 * np.sqrt(0.03 * 0.97 / 4000)
    # ... and flips per descriptor spread as a binomial's do.
    per_row = bits.sum(axis=1)
    assert abs(per_row.var() / (256 * 0.03 * 0.97) - 1) < 0.15
