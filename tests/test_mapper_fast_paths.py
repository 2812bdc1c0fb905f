"""The mapper's per-keyframe fast paths (issue 18 item 1) give what the plain code they
replace gives: point rows joined as bytes against np.concatenate, the keypoint grid of
point fusion against a k-d tree's answer."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from services.mapper.fusion import _maybe_near
from services.mapper.server_map import stack_rows


def test_stack_rows_equals_concatenate():
    rng = np.random.default_rng(0)
    pos = [rng.normal(size=3) for _ in range(50)]
    desc = [rng.integers(0, 256, 32).astype(np.uint8) for _ in range(50)]
    got = stack_rows(pos, np.float64, 3)
    assert got.dtype == np.float64 and np.array_equal(got, np.concatenate(pos).reshape(-1, 3))
    got[0, 0] = 1.0  # writable, as concatenate's result
    assert np.array_equal(stack_rows(desc, np.uint8, 32), np.stack(desc))
    # Rows of another dtype or not contiguous take the concatenate path: same values.
    mixed = pos[:3] + [pos[3].astype(np.float32)]
    assert np.array_equal(stack_rows(mixed, np.float64, 3),
                          np.concatenate(mixed).astype(np.float64).reshape(-1, 3))  # fmt: skip
    grid = rng.normal(size=(4, 6))
    cols = [grid[:, 0], grid[:, 2], grid[:, 4]]  # strided views
    assert np.array_equal(stack_rows(cols, np.float64, 4), np.stack(cols))
    assert stack_rows([], np.float64, 3).shape == (0, 3)


def test_keypoint_grid_keeps_every_point_with_a_keypoint_in_reach():
    rng = np.random.default_rng(1)
    for n_kp, n_uv, r in [(1000, 3000, 4.0), (50, 500, 4.0), (300, 2000, 2.5), (1, 10, 4.0)]:
        kp = rng.uniform(0, 200, (n_kp, 2)).astype(np.float32).astype(np.float64)
        near = kp[: n_uv // 4] + rng.uniform(-r, r, (min(n_kp, n_uv // 4), 2))
        uv = np.concatenate([rng.uniform(0, 200, (n_uv, 2)), near])
        uv = np.clip(uv, 0, 200)
        _, idx = cKDTree(kp).query(uv, k=1, distance_upper_bound=r)
        reach = idx < n_kp
        mask = _maybe_near(kp, uv, r)
        assert not (reach & ~mask).any()
        assert mask.sum() < len(uv)  # and it does leave points out
