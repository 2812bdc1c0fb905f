"""Server map stack algorithms (no transport): graph bookkeeping, registration with
pose refinement and scale correction, fusion and redundant-keyframe rejection."""

from __future__ import annotations

import numpy as np
from feeding import cull, feed_handler, server_traj, twice

from services.agent.sim_agent import DriftModel, SimAgent
from services.mapper import registration
from services.mapper.registration import AgentHandler, MapperParams
from services.mapper.server_map import ServerKeyframe, ServerMap, ServerMapPoint
from shared.ids import local_id_of
from shared.trajectory import Trajectory, ate, load_euroc_gt


def _kf(g: int, mp: list[int]) -> ServerKeyframe:
    n = len(mp)
    return ServerKeyframe(g, "A", g, g, np.eye(4), np.eye(4), np.zeros((n, 2), np.float32),
                          np.zeros((n, 2)), np.zeros(n, np.uint8), np.zeros((n, 32), np.uint8),
                          np.array(mp, np.int64))  # fmt: skip


def _pt(g: int) -> ServerMapPoint:
    return ServerMapPoint(g, np.zeros(3), np.zeros(32, np.uint8), 0)


def test_graph_bookkeeping_add_fuse_remove():
    m = ServerMap("m")
    for g in range(100, 160):
        m.add_map_point(_pt(g))
    m.add_keyframe(_kf(0, list(range(100, 140))))
    m.add_keyframe(_kf(1, list(range(110, 150))))  # shares 30 with kf 0
    m.add_keyframe(_kf(2, list(range(120, 160)) + [999]))  # unknown point is dropped
    assert m.covis[0][1] == 30 and m.covis[1][2] == 30 and m.covis[0][2] == 20
    assert m.kfs[1].parent == 0 and m.kfs[2].parent in (0, 1)
    assert m.kfs[2].mp[-1] == -1
    assert m.covisible(2) == [1, 0]
    assert m.check_invariants() == []
    m.fuse(105, 155)  # point 155 (seen by 2) is the same as 105 (seen by 0)
    assert 155 not in m.mps and 2 in m.mps[105].obs
    assert m.covis[0][2] == 21
    assert m.check_invariants() == []
    dead = m.remove_keyframe(1)
    assert 1 not in m.kfs and all(1 not in p.obs for p in m.mps.values())
    assert dead == [] and m.kfs[2].parent == 0
    assert m.check_invariants() == []
    assert (0, 2, "tree") in m.essential_edges()


def test_scale_correction_keeps_drifting_agent_consistent(world):
    gt = load_euroc_gt("MH01")
    gt = Trajectory(gt.stamps_ns[:2000], gt.poses[:2000])
    drift = DriftModel(scale_drift_per_s=0.02)
    out = {}
    # The simulated VO drifts while its points stay true: refined against its own
    # points, a keyframe sees the drift (a real VO's own points drift with it, so the
    # mapper refines against settled points only, the next test).
    for on in (False, True):
        params = MapperParams(scale_correction=on, refine_settled_only=False)
        h = AgentHandler("A", 1, ServerMap("m"), params=params)
        vo = feed_handler(h, SimAgent(gt, world, drift=drift, seed=2))
        out[on] = ate(server_traj(h), gt).rmse
        assert h.smap.check_invariants() == []
    assert out[True] * 3 <= out[False], out
    assert ate(vo, gt).rmse > out[True]


def test_refined_server_trajectory_no_worse_than_vo(world):
    gt = load_euroc_gt("MH02")
    gt = Trajectory(gt.stamps_ns[300:1500], gt.poses[300:1500])
    h = AgentHandler("A", 1, ServerMap("m"))
    vo = feed_handler(h, SimAgent(gt, world, drift=DriftModel(), seed=4))
    assert ate(server_traj(h), gt).rmse <= ate(vo, gt).rmse * 1.001


def test_redundant_keyframes_culled_on_second_lap(world):
    """An agent flying its path twice: the second lap's keyframes see nothing new."""
    gt = load_euroc_gt("MH01")
    a, b = 400, 1600
    two = twice(Trajectory(gt.stamps_ns[a:b], gt.poses[a:b]),
                gt.stamps_ns[b] - gt.stamps_ns[a] + 50_000_000)  # fmt: skip
    h = AgentHandler("A", 1, ServerMap("m"))
    feed_handler(h, SimAgent(two, world, drift=DriftModel(), seed=5))
    _stamps = [k.stamp_ns for k in sorted(h.smap.kfs.values(), key=lambda k: k.id)]
    before = ate(server_traj(h), two).rmse
    n0 = len(h.smap.kfs)
    cull(h, 400)
    kept = ate(server_traj(h), two).rmse
    # The trajectory a user gets keeps culled keyframes through their anchors (as
    # ORB-SLAM keeps culled keyframes relative to their parents).
    full = server_traj(h)
    culled = sorted(h.removed)
    T_c = np.stack([h.kf_pose(i) for i in culled])
    stamps = {k: s for k, s in zip(range(len(_stamps)), _stamps, strict=True)}
    full = Trajectory(np.concatenate([full.stamps_ns, [stamps[i] for i in culled]]),
                      np.concatenate([full.poses, T_c]))  # fmt: skip
    order = np.argsort(full.stamps_ns)
    after = ate(Trajectory(full.stamps_ns[order], full.poses[order]), two).rmse
    removed = 1 - len(h.smap.kfs) / n0
    print(f"\nculled {removed:.0%} of {n0} keyframes; ATE {before:.4f} -> {after:.4f} m "
          f"(kept keyframes only: {kept:.4f} m)")  # fmt: skip
    assert removed >= 0.10, removed
    assert abs(after - before) <= 0.10 * before, (before, after)
    assert h.smap.check_invariants() == []


def test_redundancy_never_offers_an_agents_newest_keyframes():
    """Every keyframe here is redundant (all see the same points); the candidates are
    exactly those that are not among their agent's ``keep_newest`` newest (the newest
    per agent comes from the gids' agent bits, computed over the whole map)."""
    import random

    from services.mapper.redundancy import find_redundant
    from shared.ids import gid

    m = ServerMap("m")
    for g in range(100, 140):
        m.add_map_point(_pt(g))
    gids = [gid(a, i) for a, n in ((1, 15), (2, 12), (3, 4)) for i in range(n)]
    for g in gids:
        m.add_keyframe(_kf(g, list(range(100, 140))))
    for seed in range(5):
        got = find_redundant(m, random.Random(seed), {gid(1, 0)}, max_checks=100,
                             keep_newest=10)  # fmt: skip
        assert sorted(got) == [gid(1, i) for i in range(1, 5)] + [gid(2, i) for i in range(2)]


def test_fusing_points_keeps_covisibility_equal_to_a_recount():
    """Fusion counts only what changes in the covisibility graph (observers of one point
    but not of the other); a recount from the observations is the reference, over
    random maps where the two points' observers overlap in every way."""
    rng = np.random.default_rng(7)
    for trial in range(30):
        m = ServerMap("m")
        n_pts, n_kfs = 40, 25
        for g in range(1000, 1000 + n_pts):
            m.add_map_point(_pt(g))
        for k in range(n_kfs):
            # Each keyframe sees a random subset; some see a point on two keypoints'
            # worth of ids (duplicates are dropped by add_keyframe).
            seen = rng.choice(np.arange(1000, 1000 + n_pts), size=rng.integers(5, 30))
            m.add_keyframe(_kf(k, seen.tolist()))
        assert m.check_invariants() == []
        for _ in range(8):
            alive = sorted(m.mps)
            keep, drop = (int(x) for x in rng.choice(alive, 2, replace=False))
            obs_k, obs_d = dict(m.mps[keep].obs), dict(m.mps[drop].obs)
            m.fuse(keep, drop)
            assert drop not in m.mps
            assert m.check_invariants() == [], trial
            # Every former observer of ``drop`` observes ``keep`` now, through its own
            # keypoint if it had none of ``keep``; the others' keypoints are freed.
            for g, j in obs_d.items():
                assert m.mps[keep].obs[g] == obs_k.get(g, j)
                if g in obs_k:
                    assert m.kfs[g].mp[j] == -1
            assert set(m.mps[keep].obs) == set(obs_k) | set(obs_d)


def _fly_with(world, params: MapperParams, at: int, disturb) -> tuple[AgentHandler, dict]:
    """An agent (zero drift: its VO is the truth) into a fresh handler; after its keyframe
    ``at`` is registered, ``disturb(handler)`` changes the map. Returns the handler and
    the VO poses by keyframe id."""
    gt = load_euroc_gt("MH01")
    gt = Trajectory(gt.stamps_ns[:1400], gt.poses[:1400])
    h = AgentHandler("A", 1, ServerMap("m"), params=params)
    vo = feed_handler(h, SimAgent(gt, world, drift=DriftModel.zero(), seed=3),
                      after=lambda i: disturb(h) if i == at else None)  # fmt: skip
    return h, dict(enumerate(vo.poses))


def _off_chain(h: AgentHandler, vo: dict, after: int, until: float = np.inf) -> float:
    """How far (map units) the keyframes registered after ``after`` (up to ``until``) sit
    from where the VO's relative motion since ``after`` puts them."""
    T0, L0 = h.kf_pose(after), vo[after]
    return max(
        float(np.linalg.norm((T0 @ np.linalg.inv(L0) @ vo[i])[:3, 3] - h.kf_pose(i)[:3, 3]))
        for i in vo
        if after < i <= until and h.kf_pose(i) is not None
    )


def test_a_keyframe_is_refined_against_settled_points_not_its_own_frontier(world):
    """Registration refines a new keyframe against map points that carry information its
    VO does not have: points of keyframes an optimization settled and of other agents.
    Its own unsettled points were placed from the VO's own frontier; refined against them
    a keyframe follows whatever is wrong with that frontier (in a recorded team5 run
    53-100 % of such refinements per agent moved the keyframe further from the truth,
    the median 1-52 mm, new keyframes went up to 0.42 m off in dark stretches, and the
    scale filter lam learned 0.79-1.38 from them; bench/results/team5_dump_e09623c.json
    against t5_rso_c1.json)."""
    # Past the slow take-off: six keyframes back is then far enough for a 6 cm
    # correction to pass registration's gate (a move within 10 % of the chain).
    at = 70

    def bias_own_points(h):  # a frontier gone 8 cm off: its points with it
        for p in h.smap.mps.values():
            p.pos = p.pos + np.array([0.08, 0.0, 0.0])

    old = MapperParams(refine_settled_only=False)
    h, vo = _fly_with(world, old, at, bias_own_points)
    assert _off_chain(h, vo, at) > 0.03  # the old rule follows the biased points
    h, vo = _fly_with(world, MapperParams(), at, bias_own_points)
    assert _off_chain(h, vo, at) < 1e-9  # nothing settled: the VO's chain, exactly

    def settle_and_shift_chain(h):  # settled up to 6 keyframes back, the frontier 6 cm off
        for i, kf in h.smap.kfs.items():
            if local_id_of(i) <= at - 6:
                kf.optimized = True
            else:
                kf.T_m_kf[:3, 3] += np.array([0.06, 0.0, 0.0])

    h, vo = _fly_with(world, MapperParams(), at, settle_and_shift_chain)
    nxt = min(i for i in vo if i > at)
    err = np.linalg.norm(h.kf_pose(nxt)[:3, 3] - vo[nxt][:3, 3])
    assert err < 0.01, err  # refined back onto the settled points


def test_a_scale_ratio_over_a_short_step_moves_lam_little(world, monkeypatch):
    """Refined against settled points only, a keyframe is refined now and then, and the
    ratio of its refined step from its predecessor to the VO's (CSfM eq. 3) is off by the
    refined pose's error over that step: over the 20-45 cm steps of a seed-1 pair run (p1x_b0a0b9f,
    bench/registration_errors.py), 1-2 cm read as scale errors of 4-6 %, and two of them
    set lam, the scale every later keyframe is chained at, to 0.988 and then 1.006
    within 4 s (the agent's VO scale was within 0.3 % of the map's). Here a frontier
    3 cm off (the VO exact) is refined back onto settled points: the ratio it gives
    moves lam in proportion to the step's length, and a short step moves it little."""
    gt = load_euroc_gt("MH01")
    gt = Trajectory(gt.stamps_ns[:1400], gt.poses[:1400])
    at = 70

    def lam_after_refinement(full: float) -> float:
        monkeypatch.setattr(registration, "SCALE_STEP_FULL", full)
        lams: dict[int, float] = {}
        h = AgentHandler("A", 1, ServerMap("m"))

        def after(i: int) -> None:
            lams[i] = h.lam
            if i != at:
                return
            # An optimization settled the flight up to 6 keyframes back; the frontier
            # since went 3 cm off.
            for g, kf in h.smap.kfs.items():
                if local_id_of(g) <= at - 6:
                    kf.optimized = True
                else:
                    kf.T_m_kf[:3, 3] += np.array([0.0, 0.03, 0.0])

        feed_handler(h, SimAgent(gt, world, drift=DriftModel.zero(), seed=3), after=after)
        return lams[min(i for i in lams if i > at)]

    whole = lam_after_refinement(1e-9)  # every ratio at kappa's full weight
    # Full weight from 2 units (metres here: the simulated VO is the truth), 7-8 times
    # this flight's 0.25-0.29 m keyframe steps, as SCALE_STEP_FULL (0.3 units) is 4-10
    # times a real run's.
    weighted = lam_after_refinement(2.0)
    assert abs(whole - 1.0) > 0.01, whole
    assert abs(weighted - 1.0) < 0.5 * abs(whole - 1.0), (weighted, whole)


def test_a_refinement_that_contradicts_the_vo_chain_is_refused(world, monkeypatch):
    """A refinement may move a keyframe by at most REFINE_MAX_MOVE (10 %) of the chain's
    length since the newest trusted keyframe: over that chord the VO's relative motion is
    good to a few percent. Recorded over six runs, accepted refinements that moved their
    keyframe by more than 20 % of it were closer to the truth in 22 % of cases (median
    42 mm further). Here the settled points around the flight went 8 cm off after a
    settle (the VO exact): refined against them, the next keyframe would follow them
    over its 25 cm step; gated, it stays on its chain."""
    at = 70

    def settle_then_points_off(h):
        for kf in h.smap.kfs.values():
            kf.optimized = True
        for p in h.smap.mps.values():
            p.pos = p.pos + np.array([0.08, 0.0, 0.0])

    def off_chain_next(h: AgentHandler, vo: dict) -> float:
        return _off_chain(h, vo, at, until=min(i for i in vo if i > at))

    h, vo = _fly_with(world, MapperParams(), at, settle_then_points_off)
    assert off_chain_next(h, vo) < 1e-9  # on the VO's chain
    # (Further on, once the chain since the settled keyframes is ten times as long as
    # the points are off, a refinement onto them is accepted: the gate holds a keyframe
    # to its VO only over chords where the VO is good to better than that.)
    monkeypatch.setattr(registration, "REFINE_MAX_MOVE", np.inf)
    h, vo = _fly_with(world, MapperParams(), at, settle_then_points_off)
    assert off_chain_next(h, vo) > 0.05  # ungated, it follows the points


def test_point_table_mirrors_every_change_of_the_points():
    """Fusion, feedback and keyframe events read positions and descriptors from the
    map's point table: whatever changes a point (insertion one by one or in bulk, a
    position assigned one at a time or many at once, fusion, removal with its last
    observer, a move into another map, a copy) leaves the table equal to the points,
    and a gid it does not hold is read from the point objects."""
    from copy import deepcopy

    from services.mapper.merge import move_map
    from shared.geometry import Sim3
    from shared.ids import gid

    rng = np.random.default_rng(3)

    def pt(g):
        return ServerMapPoint(g, rng.normal(size=3), rng.integers(0, 255, 32, np.uint8), 0)

    m = ServerMap("m")
    a, b = [gid(1, i) for i in range(40)], [gid(2, i) for i in range(3000, 3040)]
    m.add_map_points([pt(g) for g in a])  # bulk
    for g in b:
        m.add_map_point(pt(g))  # one by one
    m.mps[gid(3, 7)] = pt(gid(3, 7))  # straight into the dict
    m.add_keyframe(_kf(gid(1, 0), a[:30] + b[:10]))
    m.add_keyframe(_kf(gid(1, 1), a[10:40] + b[10:40]))
    assert m.check_invariants() == []
    both = np.array(a[5:15] + b[:3], np.int64)
    want = np.stack([m.mps[g].pos for g in both.tolist()])
    np.testing.assert_array_equal(m.positions(both), want)
    np.testing.assert_array_equal(
        m.descriptors(both), np.stack([m.mps[g].descriptor for g in both.tolist()])
    )
    m.mps[a[3]].pos = np.array([1.0, 2.0, 3.0])  # one position
    m.set_positions([m.mps[g] for g in a[:3]], np.ones((3, 3)))  # many at once
    np.testing.assert_array_equal(m.positions(np.array(a[:4])),
                                  [[1, 1, 1], [1, 1, 1], [1, 1, 1], [1, 2, 3]])  # fmt: skip
    m.fuse(a[12], b[12])  # b[12] dropped
    dead = m.remove_keyframe(gid(1, 0))  # points only it observed go
    assert dead and all(g not in m.mps for g in dead)
    assert m.check_invariants() == []
    try:
        m.positions(np.array([b[12]]))
        raise AssertionError("a fused-away point was still read")
    except KeyError:
        pass
    # A local id past what the table mirrors is read from the object.
    far = gid(4, (1 << 22) + 5)
    m.add_map_point(pt(far))
    np.testing.assert_array_equal(m.positions(np.array([far, a[20]])),
                                  np.stack([m.mps[far].pos, m.mps[a[20]].pos]))  # fmt: skip
    assert m.check_invariants() == []
    c = deepcopy(m)
    c.mps[a[20]].pos = np.zeros(3)
    assert c.check_invariants() == [] and m.check_invariants() == []
    assert m.positions(np.array([a[20]]))[0].any()
    dst = ServerMap("d")
    dst.add_map_point(pt(gid(9, 0)))
    moved = list(m.mps)
    S = Sim3(np.eye(3), np.array([1.0, 0.0, 0.0]), 2.0)
    before = m.positions(np.array(moved))
    move_map(dst, m, S)
    np.testing.assert_allclose(dst.positions(np.array(moved)), S.apply(before))
    assert not m.mps and dst.check_invariants() == []
    dst.mps[moved[0]].pos = np.full(3, 7.0)  # it reports to its new map's table
    np.testing.assert_array_equal(dst.positions(np.array(moved[:1])), [[7.0, 7.0, 7.0]])
