"""The mapper's collaboration path (no transport; real redis-server): a verified match
between two agents' maps fuses them into one frame, loop edges and corrections keep
the map consistent, and a restart rebuilds the merged map exactly from Redis."""

from __future__ import annotations

import time
from operator import attrgetter

import numpy as np
import pytest
from feeding import feed_mapper as _feed

from services.agent.sim_agent import DriftModel, SimAgent
from services.mapper.merge import LoopConstraint, fuse_matched, move_map
from services.mapper.metrics import LOOPS_REBASED
from services.mapper.server_map import ServerKeyframe, ServerMap, ServerMapPoint, digest
from services.mapper.service import MapperService
from services.optimizer.pose_graph import loops_pull
from services.optimizer.service import OptimizerService, Superseded
from shared import keys
from shared.geometry import Sim3, exp_so3, loop_residual, se3_inv
from shared.ids import gid, local_id_of
from shared.messages import CorrectionMsg, Match, OptimizeRequest
from shared.settings import OptimizerSettings, Settings
from shared.store import Store, connect
from shared.trajectory import Trajectory, load_euroc_gt


def _kf(g: int, mp: list[int], T: np.ndarray) -> ServerKeyframe:
    n = len(mp)
    return ServerKeyframe(g, "A", g, g, T, T, np.zeros((n, 2), np.float32), np.zeros((n, 2)),
                          np.zeros(n, np.uint8), np.zeros((n, 32), np.uint8),
                          np.array(mp, np.int64))  # fmt: skip


def test_move_map_carries_poses_points_and_graph_through_a_similarity():
    rng = np.random.default_rng(0)
    src, dst = ServerMap("b"), ServerMap("a")
    for g in range(100, 150):
        src.add_map_point(ServerMapPoint(g, rng.normal(size=3), np.zeros(32, np.uint8), 0))
    T0, T1 = np.eye(4), np.eye(4)
    T1[:3, 3] = [1.0, 0.0, 0.0]
    src.add_keyframe(_kf(0, list(range(100, 140)), T0))
    src.add_keyframe(_kf(1, list(range(110, 150)), T1))
    before = {g: p.pos.copy() for g, p in src.mps.items()}
    S = Sim3(exp_so3(np.array([0.1, -0.2, 0.3])), np.array([5.0, 1.0, -2.0]), 2.5)
    res = move_map(dst, src, S)
    assert sorted(res.moved_kfs) == [0, 1] and not src.kfs and not src.mps
    for g, p in before.items():
        np.testing.assert_allclose(dst.mps[g].pos, S.apply(p[None])[0], atol=1e-12)
    # Poses stay rigid; the baseline between them scales with the map.
    np.testing.assert_allclose(np.linalg.norm(dst.kfs[1].T_m_kf[:3, 3] - dst.kfs[0].T_m_kf[:3, 3]),
                               2.5, atol=1e-12)  # fmt: skip
    assert dst.covis[0][1] == 30 and dst.check_invariants() == []
    fres = fuse_matched(dst, np.array([100, 101]), np.array([145, 101]))
    assert len(fres.aliases) == 1 and 145 not in dst.mps or 100 not in dst.mps
    assert dst.check_invariants() == []


def test_a_window_is_tied_to_each_agents_own_settled_chain_by_its_vo_edge():
    """Agent A flies on through what agent B mapped: its two unsettled keyframes see
    only points B's settled keyframes see, its own newest settled keyframe none of them.
    The window fixes B's keyframes for the shared points and A's newest settled one
    too (capture.own_anchors), with the VO edge from it to A's first free keyframe;
    without that A's part of the window would hang on B's placement alone."""
    from services.mapper.capture import capture_window

    smap = ServerMap("m")
    # 100-139: B's points, seen by A's free keyframes; 200-219: A's own older ones.
    desc = np.zeros(32, np.uint8)
    for g in [*range(100, 140), *range(200, 220)]:
        smap.add_map_point(ServerMapPoint(g, np.array([0.01 * g, 0.0, 5.0]), desc, 0))

    def kf(gid: int, agent: str, i: int, x: float, mp: list[int], settled: bool) -> ServerKeyframe:
        T = np.eye(4)
        T[0, 3] = x
        n = len(mp)
        k = ServerKeyframe(gid, agent, i, 1_000 + gid, T, T.copy(), np.zeros((n, 2), np.float32),
                           np.zeros((n, 2)), np.zeros(n, np.uint8), np.zeros((n, 32), np.uint8),
                           np.array(mp, np.int64))  # fmt: skip
        k.optimized = settled
        return k

    for j in range(4):  # B, settled, every one seeing the points A will see
        smap.add_keyframe(kf(j, "B", j, 0.1 * j, list(range(100, 140)), True))
    smap.add_keyframe(kf(10, "A", 0, 1.0, list(range(200, 220)), True))
    smap.add_keyframe(kf(11, "A", 1, 1.1, list(range(200, 220)), True))
    smap.add_keyframe(kf(12, "A", 2, 1.2, list(range(100, 140)), False))
    smap.add_keyframe(kf(13, "A", 3, 1.3, list(range(100, 140)), False))
    cap = capture_window(smap, max_fixed=2, odometry=True)
    assert cap is not None
    assert 11 in cap.fixed and 10 not in cap.fixed
    assert sum(g < 10 for g in cap.fixed) == 2  # B's, for their shared points
    pairs = {tuple(e) for e in cap.odometry.pairs.tolist()}
    assert pairs == {(11, 12), (12, 13)}


def _traj(svc: MapperService, agent: str) -> Trajectory:
    h = svc.handlers[agent]
    kfs = sorted((k for k in h.smap.kfs.values() if k.agent == agent), key=lambda k: k.id)
    return Trajectory(np.array([k.stamp_ns for k in kfs]), np.stack([k.T_m_kf for k in kfs]))


def _match_from_truth(svc, sims, gts, qa: str, ca: str) -> Match:
    """What place recognition would publish for the closest pair of keyframes of two
    agents: the true S_q_c (in their local-map scales) and the landmarks both see."""
    tq, tc = _traj(svc, qa), _traj(svc, ca)
    gq, gc = gts[qa], gts[ca]
    Pq = gq.poses[np.searchsorted(gq.stamps_ns, tq.stamps_ns)]
    Pc = gc.poses[np.searchsorted(gc.stamps_ns, tc.stamps_ns)]
    d = np.linalg.norm(Pq[:, None, :3, 3] - Pc[None, :, :3, 3], axis=2)
    iq, ic = np.unravel_index(np.argmin(d), d.shape)
    hq, hc = svc.handlers[qa], svc.handlers[ca]
    kq = hq.smap.kfs[hq.kf_gid(_kf_id(svc, qa, iq))]
    kc = hc.smap.kfs[hc.kf_gid(_kf_id(svc, ca, ic))]
    T_q_c = se3_inv(Pq[iq]) @ Pc[ic]  # metres
    sq, sc = sims[qa].state.scale, sims[ca].state.scale
    S = Sim3(T_q_c[:3, :3], T_q_c[:3, 3] * sq, sq / sc)
    inv_q = {m: lm for lm, m in sims[qa].lm_to_mp.items()}
    inv_c = {m: lm for lm, m in sims[ca].lm_to_mp.items()}
    lm_q = {inv_q[local_id_of(int(g))]: int(g) for g in kq.mp[kq.mp >= 0]}
    lm_c = {inv_c[local_id_of(int(g))]: int(g) for g in kc.mp[kc.mp >= 0]}
    both = sorted(set(lm_q) & set(lm_c))
    assert len(both) >= 30, "the chosen keyframes should see a common place"
    return Match(hq.map_id, kq.gid, hc.map_id, kc.gid, S.matrix(),
                 np.array([lm_q[x] for x in both], np.int64),
                 np.array([lm_c[x] for x in both], np.int64), len(both), 1.0, 0)  # fmt: skip


def _kf_id(svc, agent: str, i: int) -> int:
    h = svc.handlers[agent]
    return sorted(k.id for k in h.smap.kfs.values() if k.agent == agent)[i]


def _joint_rigid_error(svc, gts, agents, upto_ns: dict[str, int] | None = None) -> float:
    """Largest position error of every agent's keyframes in their common map frame,
    after one similarity alignment to ground truth (with ``upto_ns``, only each agent's
    keyframes stamped up to its entry)."""
    from shared.geometry import umeyama

    P, G = [], []
    for a in agents:
        tr = _traj(svc, a)
        if upto_ns is not None:
            keep = tr.stamps_ns <= upto_ns[a]
            tr = Trajectory(tr.stamps_ns[keep], tr.poses[keep])
        P.append(tr.positions)
        G.append(gts[a].positions[np.searchsorted(gts[a].stamps_ns, tr.stamps_ns)])
    P, G = np.concatenate(P), np.concatenate(G)
    S = umeyama(P, G)
    return float(np.linalg.norm(S.apply(P) - G, axis=1).max())


def _fly_on(svc, sims, gts, agent: str, seq: str, a: int, b: int) -> None:
    """``agent``, which flew frames 0:a of ``seq``, flies on to frame b, fed to ``svc``."""
    gt = load_euroc_gt(seq)
    more = Trajectory(gt.stamps_ns[a:b], gt.poses[a:b])
    gts[agent] = Trajectory(gt.stamps_ns[0:b], gt.poses[0:b])
    sims[agent].traj = Trajectory(np.concatenate([sims[agent].traj.stamps_ns, more.stamps_ns]),
                                  np.concatenate([sims[agent].traj.poses, more.poses]))  # fmt: skip
    _feed(svc, agent, sims[agent])


def test_match_between_two_agents_merges_their_maps_into_one_frame(redis_url, world):
    settings = Settings(redis_url=redis_url)
    svc = MapperService(settings)
    gts, sims = {}, {}
    for agent, seq, (a, b), scale in (("A", "MH01", (0, 700), 1.0), ("B", "MH02", (0, 700), 2.0)):
        gt = load_euroc_gt(seq)
        gts[agent] = Trajectory(gt.stamps_ns[a:b], gt.poses[a:b])
        sims[agent] = SimAgent(gts[agent], world, drift=DriftModel.zero())
        sims[agent].state.scale = scale  # B's monocular map has twice the metric scale
        _feed(svc, agent, sims[agent])
    assert svc.handlers["A"].map_id != svc.handlers["B"].map_id
    m = _match_from_truth(svc, sims, gts, "B", "A")
    assert svc.collab.on_match(m) == "merge"
    assert svc.handlers["A"].smap is svc.handlers["B"].smap
    smap = svc.handlers["A"].smap
    assert len(svc.maps) == 1 and smap.check_invariants() == []
    assert sum(1 for _ in smap.kfs) == sum(len(_traj(svc, a)) for a in "AB")
    # Every matched pair is one point now.
    assert not any(q in smap.mps and c in smap.mps and q != c
                   for q, c in zip(m.mp_q.tolist(), m.mp_c.tolist(), strict=True))  # fmt: skip
    # Zero-noise agents: one similarity aligns both trajectories to ground truth exactly.
    assert _joint_rigid_error(svc, gts, "AB") < 1e-6
    # B's local units are half a metre: per local unit it moves half as far in the map.
    ratio = svc.handlers["B"].S_m_l.s / svc.handlers["A"].S_m_l.s
    np.testing.assert_allclose(ratio, 0.5, rtol=1e-9)
    # The same place again: already tied by fused points, nothing more to do.
    assert svc.collab.on_match(_match_from_truth(svc, sims, gts, "B", "A")) is None

    # A restart rebuilds the merged map, handlers and loop edges from Redis alone.
    again = MapperService(settings)
    again.load()
    assert list(again.maps) == [smap.map_id]
    assert digest(again.maps[smap.map_id]) == digest(smap)
    assert again.handlers["B"].map_id == smap.map_id
    again_ratio = again.handlers["B"].S_m_l.s / again.handlers["A"].S_m_l.s
    np.testing.assert_allclose(again_ratio, 0.5, rtol=1e-9)
    assert [(lc.q, lc.c) for lc in again.collab.loops[smap.map_id]] == [(m.query_gid, m.cand_gid)]
    assert m.cand_gid in again.maps[smap.map_id].kfs[m.query_gid].loop_edges
    info = Store(connect(redis_url)).map_info(smap.map_id)
    assert set(info["agents"]) == {"A", "B"} and info["n_kf"] == len(smap.kfs)
    assert Store(connect(redis_url)).maps() == [smap.map_id]

    # After the merge B keeps registering into the common map, at the common scale, on
    # the restarted mapper: the first one's lease may have lapsed meanwhile on a slow
    # machine (3 s, nothing renews it here), and then the restart took the map over
    # with a new fencing token and the first one's writes are refused (``Fenced``).
    _fly_on(again, sims, gts, "B", "MH02", 700, 900)
    assert _joint_rigid_error(again, gts, "AB") < 1e-6


def test_a_match_verified_before_a_merge_is_taken_in_the_merged_units(redis_url, world):
    """Place recognition verified a match between A's and B's maps, and the mapper
    merged them through another match before this one arrived: it now names a pair in
    one map, whose units are not B's any more (B's map was scaled by 2 or 1/2 into
    A's). Taken as it came it was a loop carrying the merge's scale."""
    svc = MapperService(Settings(redis_url=redis_url))
    c = svc.collab
    gts, sims = {}, {}
    for agent, seq, scale in (("A", "MH01", 1.0), ("B", "MH02", 2.0)):
        gt = load_euroc_gt(seq)
        gts[agent] = Trajectory(gt.stamps_ns[0:700], gt.poses[0:700])
        sims[agent] = SimAgent(gts[agent], world, drift=DriftModel.zero())
        sims[agent].state.scale = scale
        _feed(svc, agent, sims[agent])
    late = _match_from_truth(svc, sims, gts, "B", "A")  # verified now, applied later
    assert (late.query_map, late.cand_map) == (svc.handlers["B"].map_id,
                                               svc.handlers["A"].map_id)  # fmt: skip
    assert c.on_match(_match_from_truth(svc, sims, gts, "B", "A")) == "merge"
    smap = svc.handlers["A"].smap
    assert svc.handlers["B"].smap is smap
    # The pair's Sim(3) in the merged map's units: the zero-drift map's own relative pose.
    now = c._in_current_units(late, smap.map_id, smap.map_id)
    assert now is not None and now.query_map == now.cand_map == smap.map_id
    rel = se3_inv(smap.kfs[late.query_gid].T_m_kf) @ smap.kfs[late.cand_gid].T_m_kf
    S = Sim3.from_matrix(now.S_q_c)
    assert abs(S.s - 1.0) < 1e-6, S.s
    rot, trans = loop_residual(now.S_q_c, rel)
    assert rot < 1e-6 and trans < 1e-6, (rot, trans)
    # A mapper restarted on the same store knows the merge's scale too.
    again = MapperService(Settings(redis_url=redis_url))
    again.load()
    assert again.registry.merge_scale == svc.registry.merge_scale
    now2 = again.collab._in_current_units(late, smap.map_id, smap.map_id)
    assert now2 is not None and np.allclose(now2.S_q_c, now.S_q_c, atol=1e-9)
    # Where the merge's scale is not known (stored before scales were), it is dropped.
    from shared.metrics import REJECTED

    stale = REJECTED.labels("mapper", keys.MATCH, "stale_units")
    before = stale._value.get()
    svc.registry.merge_scale.clear()
    assert c.on_match(late) is None
    assert stale._value.get() == before + 1


def test_a_dropped_maps_agents_leave_no_settle_state_behind(redis_url):
    """A map another mapper took over takes its agents' handlers with it
    (``MapRegistry.drop``), and what a correction had settled of them here goes too,
    with what was pending for the map."""
    from types import SimpleNamespace

    svc = MapperService(Settings(redis_url=redis_url))
    reg, c = svc.registry, svc.collab
    for agent, map_id in (("A", "map-a"), ("B", "map-b")):
        reg.ensure_map(map_id)
        reg.add_handler(SimpleNamespace(agent=agent, map_id=map_id))
        c._settled[agent] = 7
        c.mark_dirty(map_id, "loop")
        c._inflight[map_id] = (0.0, "loop", 3)
        c._spacing(map_id, "local").run_s = 1.0
    svc.drop_map("map-a", "lease lost")
    assert reg.handler("A") is None and "A" not in c._settled
    assert c._settled == {"B": 7}
    assert list(c._dirty) == ["map-b"] and list(c._inflight) == ["map-b"]
    assert [k[0] for k in c._spacings] == ["map-b"]


def _two_noisy_agents(svc, world) -> tuple[dict, dict]:
    """Agents A (MH01) and B (MH02), 700 frames each with drift, fed to ``svc``:
    (ground truths, simulated agents) by agent."""
    gts, sims = {}, {}
    for i, (agent, seq) in enumerate((("A", "MH01"), ("B", "MH02"))):
        gt = load_euroc_gt(seq)
        gts[agent] = Trajectory(gt.stamps_ns[0:700], gt.poses[0:700])
        sims[agent] = SimAgent(gts[agent], world, drift=DriftModel(), seed=10 + i)
        _feed(svc, agent, sims[agent])
    return gts, sims


def _merged_with_optimizer(redis_url, world, optimizer: OptimizerSettings | None = None):
    """A and B (``_two_noisy_agents``) merged by a true match, requests unspaced, and an
    optimizer on the same Redis: (settings, mapper, ground truths, simulated agents,
    the merged map, optimizer).

    Global BA gets a budget it never reaches here (~1-3 s of work): a run stopped on its
    budget asks to continue (``Collaboration._continue``), and that pending request
    would hold back the settle marks these tests check on a slow machine."""
    optimizer = optimizer or OptimizerSettings(ba_time_budget_s=60.0)
    settings = Settings(redis_url=redis_url, optimizer=optimizer)
    svc = MapperService(settings)
    c = svc.collab
    c.min_interval = 0.0
    gts, sims = _two_noisy_agents(svc, world)
    assert c.on_match(_match_from_truth(svc, sims, gts, "B", "A")) == "merge"
    opt = OptimizerService(settings)
    opt.queue.ensure_group()
    return settings, svc, gts, sims, svc.handlers["A"].map_id, opt


def test_optimization_round_trip_keeps_a_consistent_map(redis_url, world):
    """Merge two noisy agents, ask for an optimization, run it, apply the correction:
    invariants hold, Redis follows, and the joint error does not grow."""
    settings = Settings(redis_url=redis_url)
    svc = MapperService(settings)
    gts, sims = _two_noisy_agents(svc, world)
    assert svc.collab.on_match(_match_from_truth(svc, sims, gts, "B", "A")) == "merge"
    map_id = svc.handlers["A"].map_id
    before = _joint_rigid_error(svc, gts, "AB")
    sent = svc.collab.request(map_id, "merge")
    assert isinstance(sent, OptimizeRequest) and len(sent.loops) == 1
    opt = OptimizerService(settings)
    opt.queue.ensure_group()
    job = opt.queue.take(block_s=0.1)  # the request went to the job stream
    assert job is not None and job.map_id == map_id
    req = opt.decode(job)  # what travels through Redis
    assert req is not None and req.version == sent.version and len(req.loops) == 1
    # A newer copy of the same map waiting: the run stops at a stage boundary...
    svc.collab.jobs.submit(map_id, job.data)
    with pytest.raises(Superseded):
        opt.optimize(req, job)
    # ...but not forever: after max_restarts in a row it finishes.
    for _ in range(settings.optimizer.max_restarts):
        opt.queue.restarted(map_id)
    corr = opt.optimize(req, job)
    assert corr.job == job.id
    corr = CorrectionMsg.decode(corr.encode())
    # A keyframe that arrived during the optimization is carried along (CCM-SLAM Fig. 4).
    optimized_upto = {a: int(gts[a].stamps_ns[-1]) for a in "AB"}
    _fly_on(svc, sims, gts, "A", "MH01", 700, 760)
    svc.collab.drop_slice = 5  # the BA's outlier observations dropped over several holds
    assert svc.collab.on_correction(corr) is True
    # The same job's correction again (a second worker ran it): applied once.
    assert svc.collab.on_correction(corr) is False
    smap = svc.maps[map_id]
    assert smap.check_invariants() == []
    kept = [(kg, mg) for kg, mg in zip(corr.outlier_kf.tolist(), corr.outlier_mp.tolist(),
                                       strict=True)
            if mg in smap.mps and kg in smap.mps[mg].obs and len(smap.mps[mg].obs) > 2]  # fmt: skip
    assert kept == []  # each dropped, but where it was one of its point's last two
    # Judged on the keyframes the optimization covered: the ones flown meanwhile only
    # moved with their neighbours and keep the VO's error of their 3 s (with one noise
    # draw those three were the map's largest errors, 30 mm against 23 before, while
    # the covered keyframes' largest fell to 11 mm).
    after = _joint_rigid_error(svc, gts, "AB", upto_ns=optimized_upto)
    assert after <= before * 1.05, (before, after)
    again = MapperService(settings)
    again.load()
    assert digest(again.maps[map_id]) == digest(smap)


def test_a_correction_of_a_copy_taken_before_a_merge_is_not_applied(redis_url, world):
    """Both maps' optimizations are out when they merge. The merged-away map's correction
    is stale (its map is gone); so is the one of the map that stayed put: its copy holds
    none of the keyframes the merge brought in, and applied it would move each of them
    by its strongest covisible keyframe's correction, every point with it, in one hold
    of the map's lock (1.8 s at 24 agents). It changes nothing; the merged map's own
    run, which the merge asked for, is applied."""
    from shared.metrics import REJECTED

    settings = Settings(redis_url=redis_url, optimizer=OptimizerSettings(ba_time_budget_s=60.0))
    svc = MapperService(settings)
    c = svc.collab
    c.min_interval = 0.0
    gts, sims = _two_noisy_agents(svc, world)
    maps = {a: svc.handlers[a].map_id for a in "AB"}
    opt = OptimizerService(settings)
    opt.queue.ensure_group()
    reqs = {}
    for a in "AB":
        assert c.request(maps[a], "loop") is not None
        reqs[a] = opt.decode(opt.queue.take(block_s=0.1))
        assert reqs[a].map_id == maps[a]
    assert c.on_match(_match_from_truth(svc, sims, gts, "B", "A")) == "merge"
    smap = svc.handlers["A"].smap
    target = smap.map_id
    stayed = next(a for a in "AB" if maps[a] == target)
    before = digest(smap)
    stale = REJECTED.labels("mapper", keys.map_correction(target), "stale")
    n0 = stale._value.get()
    for a in "AB":
        corr = CorrectionMsg.decode(opt.optimize(reqs[a]).encode())
        assert c.on_correction(corr) is False
    assert stale._value.get() == n0 + 1  # the map that stayed; the other one is gone
    assert digest(smap) == before
    assert target not in c._inflight  # not out any more: settling may ask again
    assert c.due(time.monotonic() + 1e3) == [(target, "merge")]
    sent = c.request(target, "merge")
    assert sent is not None and set(reqs[stayed].kf_gids.tolist()) < set(sent.kf_gids.tolist())
    corr = opt.handle(opt.queue.take(block_s=0.1))
    assert corr is not None and c.on_correction(CorrectionMsg.decode(corr.encode())) is True
    assert digest(smap) != before and smap.check_invariants() == []


def test_a_map_too_large_for_one_job_is_not_sent_and_not_copied_again(redis_url, world):
    """A global copy over what one job can carry (the optimizer could not decode it) is
    not written to the job stream; it is counted, and the map is not copied again at that
    size (each copy held the map's lock for seconds at 48 agents)."""
    from services.mapper.metrics import OPT_SKIPPED

    settings = Settings(redis_url=redis_url)
    svc = MapperService(settings)
    gts, sims = _two_noisy_agents(svc, world)
    assert svc.collab.on_match(_match_from_truth(svc, sims, gts, "B", "A")) == "merge"
    map_id = svc.handlers["A"].map_id
    svc.collab.max_job_bytes = 1000  # any copy of this map is larger
    skipped = OPT_SKIPPED.labels("too_large")._value.get()
    opt = OptimizerService(settings)
    opt.queue.ensure_group()
    assert svc.collab.request(map_id, "merge") is None
    assert OPT_SKIPPED.labels("too_large")._value.get() == skipped + 1
    assert opt.queue.take(block_s=0.1) is None  # nothing went to the job stream
    assert map_id not in svc.collab._inflight
    # Asked again at the same size: refused before any copy is taken.
    svc.collab.max_job_bytes = 1 << 40
    assert svc.collab.request(map_id, "merge") is None
    assert OPT_SKIPPED.labels("too_large")._value.get() == skipped + 2
    assert opt.queue.take(block_s=0.1) is None


def _settled_then_restarted(redis_url, world, forget_flags: bool = False):
    """The merged pair optimized once (settled), then a second mapper loaded from the
    same Redis; ``forget_flags``: the stored settled flags removed first, as in a store
    written before they were. (first mapper, restarted mapper, sims, gts, map, opt)."""
    settings, svc, gts, sims, map_id, opt = _merged_with_optimizer(redis_url, world)
    c = svc.collab
    assert c.due(time.monotonic()) == [(map_id, "merge")]
    c.request(map_id, "merge")
    job = opt.queue.take(block_s=0.1)
    assert c.on_correction(CorrectionMsg.decode(opt.handle(job).encode()))
    assert _n_settled(svc, map_id) > 0 and set(c._settled) == {"A", "B"}
    assert c.due(time.monotonic() + 100.0) == []  # nothing more to do before the restart
    if forget_flags:
        r = connect(redis_url)
        for key in r.scan_iter("hm:kf:*"):
            r.hdel(key, "opt")
    again = MapperService(settings)
    again.load()
    again.collab.min_interval = 0.0
    return svc, again, sims, gts, map_id, opt


def _n_settled(mapper, map_id: str) -> int:
    return sum(k.optimized for k in mapper.maps[map_id].kfs.values())


def test_a_restarted_mapper_knows_which_keyframes_were_settled(redis_url, world):
    """Which keyframes an optimization settled is stored with them: a restarted mapper
    holds the same flags (its agents' corrections are fitted on them) and settles the
    agents on as before, without optimizing the whole map again first."""
    svc, again, sims, gts, map_id, _ = _settled_then_restarted(redis_url, world)
    ca = again.collab
    assert _n_settled(again, map_id) == _n_settled(svc, map_id)
    assert ca._settled == svc.collab._settled
    for agent in ("A", "B"):
        mine = [g for g, k in svc.maps[map_id].kfs.items() if k.agent == agent]
        assert [again.maps[map_id].kfs[g].optimized for g in mine] == [
            svc.maps[map_id].kfs[g].optimized for g in mine
        ]
    now = time.monotonic()
    # What the mapper before the restart would do next, the restarted one does: a
    # windowed BA for each agent's frontier the global run moved but left unsettled
    # (collab ``_frontier``), not a whole "resume" run.
    assert ca.mark_unsettled(now) == svc.collab.mark_unsettled(now)
    assert ca.due(now) == svc.collab.due(now) == [(map_id, "local")]
    _fly_on(again, sims, gts, "A", "MH01", 700, 900)
    assert ca.mark_unsettled(now) == [map_id]
    assert ca.due(now) == [(map_id, "local")]  # settling, not a whole "resume" run


def test_a_restarted_mapper_without_settled_flags_optimizes_a_merged_map_once(redis_url, world):
    """A store without the settled flags (written before they were): after a restart
    nothing is settled, so no frame correction can be fitted and settling never starts.
    The restarted mapper asks once for the map ("resume") when an agent flies on; its
    correction settles the agents again."""
    _, again, sims, gts, map_id, opt = _settled_then_restarted(redis_url, world, True)
    ca = again.collab
    assert _n_settled(again, map_id) == 0 and ca._settled == {}
    now = time.monotonic()
    # Nobody flies on: the map stays as it was stored (a restart alone changes nothing).
    assert ca.mark_unsettled(now) == [] and ca.due(now) == []
    _fly_on(again, sims, gts, "A", "MH01", 700, 760)
    assert ca.mark_unsettled(now) == [map_id]
    assert ca.mark_unsettled(now) == []  # once
    assert ca.due(now) == [(map_id, "resume")]
    ca.request(map_id, "resume")
    job = opt.queue.take(block_s=0.1)
    assert job is not None and job.map_id == map_id
    assert ca.on_correction(CorrectionMsg.decode(opt.handle(job).encode()))
    assert _n_settled(again, map_id) > 0 and set(ca._settled) == {"A", "B"}
    assert again.maps[map_id].check_invariants() == []


def test_unknown_keyframes_in_a_match_are_rejected(redis_url):
    svc = MapperService(Settings(redis_url=redis_url))
    m = Match("m1", gid(1, 5), "m2", gid(2, 7), np.eye(4), np.zeros(0, np.int64),
              np.zeros(0, np.int64), 0, 0.0, 0)  # fmt: skip
    assert svc.collab.on_match(m) is None
    assert svc.collab.on_match_bytes("hivemap/match", b"\x93garbage") is None


def test_feedback_after_a_merge_carries_what_the_agent_lacks(redis_url, world):
    """After two maps merge, B's chunk holds A's points near B's KF_ref and none that
    B's own newest keyframes observe (B tracks those already; a second copy at the
    server's position would compete for the same keypoints)."""
    from services.mapper.feedback import RECENT_KFS, build_chunk

    svc = MapperService(Settings(redis_url=redis_url))
    gts, sims = {}, {}
    for i, (agent, seq, n) in enumerate((("A", "MH01", 700), ("B", "MH02", 160))):
        gt = load_euroc_gt(seq)
        gts[agent] = Trajectory(gt.stamps_ns[0:n], gt.poses[0:n])
        sims[agent] = SimAgent(gts[agent], world, drift=DriftModel(), seed=20 + i)
        _feed(svc, agent, sims[agent])
    hb = svc.handlers["B"]
    hb.kf_ref = hb.latest_kf
    alone = build_chunk(hb, 5, set(), 0, svc.names)
    assert alone is None or set(alone.mp_agents) <= {"B"}
    m = _match_from_truth(svc, sims, gts, "B", "A")
    assert svc.collab.on_match(m) == "merge"
    # B flies on where A has been (the match was near its newest keyframe).
    hb.kf_ref = hb.latest_kf
    chunk = build_chunk(hb, 5, set(), 0, svc.names)
    assert chunk is not None and len(chunk.mp_ids) > 0
    smap = hb.smap
    lo, hi = hb.kf_gid(max(hb.latest_kf - RECENT_KFS, 0)), hb.kf_gid(hb.latest_kf)
    gids = [gid(svc.handlers[a].index, int(i)) for a, i in
            zip(chunk.mp_agents, chunk.mp_ids.tolist(), strict=True)]  # fmt: skip
    assert all(not any(lo <= o <= hi for o in smap.mps[g].obs) for g in gids)
    assert "A" in chunk.kf_agents and "A" in chunk.mp_agents
    # Map -> KF_ref (agent units) fitted on B's newest keyframes agrees with B's Sim(3)
    # from its local map into the merged one (no drift here, so both are right).
    from services.mapper.feedback import map_to_agent_ref

    ref = smap.kfs[hb.kf_gid(hb.kf_ref)]
    R, t, s = map_to_agent_ref(hb, ref, lo, hi)
    T_ref_m = se3_inv(ref.T_m_kf)
    assert abs(s * hb.scale - 1) < 0.02
    assert np.linalg.norm(R - T_ref_m[:3, :3]) < 0.02
    assert s != 1.0 / hb.scale  # the fit, not the fallback
    p_m = smap.mps[gids[0]].pos
    expect = (T_ref_m[:3, :3] @ p_m + T_ref_m[:3, 3]) / hb.scale
    tol = 0.02 * np.linalg.norm(p_m - ref.T_m_kf[:3, 3]) / hb.scale
    np.testing.assert_allclose(s * R @ p_m + t, expect, atol=tol)


def test_keyframes_after_a_correction_continue_at_the_map_scale(redis_url, world):
    """A global optimization that shrinks the map where the agent flies (as global BA
    does: the correction's per-keyframe scale stays 1), applied after the agent's newest
    keyframe arrived (carried along, as in every live run): the keyframes that follow
    are chained at the map's new scale, not at the one the handler had. Chained at the
    old one, each is a few per cent too far from the one before, pose refinement cannot
    see it, and the error grows until the next optimization (MH01 in team5 at 85a443d:
    a 2.4 % mismatch, 55.7 mm server ATE)."""
    settings = Settings(redis_url=redis_url)
    svc = MapperService(settings)
    gt = load_euroc_gt("MH01")
    gts = {"A": Trajectory(gt.stamps_ns[0:700], gt.poses[0:700])}
    sims = {"A": SimAgent(gts["A"], world, drift=DriftModel.zero())}
    _feed(svc, "A", sims["A"])
    map_id = svc.handlers["A"].map_id
    req = svc.collab.request(map_id, "loop")
    assert isinstance(req, OptimizeRequest)
    # The optimizer's answer: the map 0.95 times as large about its first keyframe.
    s = 0.95
    o = req.T_m_kf[0, :3, 3].copy()
    T = req.T_m_kf.copy()
    T[:, :3, 3] = o + s * (T[:, :3, 3] - o)
    corr = CorrectionMsg(map_id, req.version, time.time_ns(), req.kf_gids, T,
                         np.ones(len(T)), req.mp_gids, o + s * (req.mp_pos - o),
                         np.zeros(0, np.int64), np.zeros(0, np.int64), {})  # fmt: skip
    newest = svc.handlers["A"].latest_kf
    _fly_on(svc, sims, gts, "A", "MH01", 700, 760)  # arrived during the optimization
    assert svc.handlers["A"].latest_kf > newest
    assert svc.collab.on_correction(corr) is True
    # The keyframes carried along moved rigidly with their anchors (per-keyframe scale 1):
    # a few tens of micrometres here.
    assert _joint_rigid_error(svc, gts, "A") < 1e-4
    _fly_on(svc, sims, gts, "A", "MH01", 760, 1200)
    np.testing.assert_allclose(svc.handlers["A"].scale, s, rtol=1e-6)
    # At the handler's old scale: 5.2 mm (0.96, part of it learned back by refinement).
    assert _joint_rigid_error(svc, gts, "A") < 1e-4


def test_an_agent_far_past_its_settled_keyframes_gets_its_map_optimized_again(redis_url, world):
    """Optimizations come from loops and merges; once a team has flown its common places
    over, new loops are ones the map holds already and none comes. An agent that flew
    settle_after_kfs keyframes past its newest settled one gets its map optimized
    ("settle"), never while an optimization of the map is still out, and the run
    settles its newest keyframes, which its frame correction is fitted on."""
    from services.mapper.feedback import estimate_correction

    # The budget of _merged_with_optimizer: the merge's BA (~7 s here with one noise
    # draw) stopped on the default one asks to continue, and that pending run holds
    # the settle back.
    settings = Settings(redis_url=redis_url, optimizer=OptimizerSettings(ba_time_budget_s=60.0))
    svc = MapperService(settings)
    c = svc.collab
    c.min_interval = 0.0
    c.settle_window_kfs = 0  # settling by global runs (windowed BA: the next test)
    gts, sims = _two_noisy_agents(svc, world)
    assert c.on_match(_match_from_truth(svc, sims, gts, "B", "A")) == "merge"
    map_id = svc.handlers["A"].map_id
    ha = svc.handlers["A"]
    now = time.monotonic()
    assert c.due(now) == [(map_id, "merge")]
    # Nothing has been settled yet: no settling either, however far the agents fly.
    assert c.mark_unsettled(now) == []
    opt = OptimizerService(settings)
    opt.queue.ensure_group()

    def run_one() -> None:
        job = opt.queue.take(block_s=0.1)
        assert job is not None and job.map_id == map_id
        corr = opt.handle(job)
        assert corr is not None and c.on_correction(CorrectionMsg.decode(corr.encode()))

    c.request(map_id, "merge")
    settled = ha.latest_kf
    _fly_on(svc, sims, gts, "A", "MH01", 700, 1150)  # flown during the optimization
    flown = ha.latest_kf - settled
    assert flown >= c.settle_kfs, flown
    # Out (requested, not yet applied): a settle request would abandon it.
    assert c.mark_unsettled(now) == [] and c.due(time.monotonic() + 100.0) == []
    run_one()
    assert not ha.smap.kfs[ha.kf_gid(ha.latest_kf)].optimized
    before = estimate_correction(ha)
    # Applied: A is `flown` keyframes past its newest settled one; B has not moved.
    c.settle_kfs = 0  # off: only loops and merges optimize
    assert c.mark_unsettled(now) == []
    c.settle_kfs = settings.mapper.settle_after_kfs
    assert c.mark_unsettled(now) == [map_id]
    assert c.mark_unsettled(now) == []  # marked once
    assert c.due(time.monotonic() + 100.0) == [(map_id, "settle")]
    c.request(map_id, "settle")
    run_one()
    assert ha.smap.kfs[ha.kf_gid(ha.latest_kf)].optimized
    after = estimate_correction(ha)
    assert before is not None and after is not None
    assert np.abs(after.matrix() - before.matrix()).max() > 1e-6  # fitted on newer keyframes
    assert c.mark_unsettled(now) == []
    assert ha.smap.check_invariants() == []


def test_a_windowed_settle_runs_in_the_gap_of_a_spaced_global_request(redis_url, world):
    """A global request waiting out its spacing (a loop on a big map: 4x its run time)
    does not hold settling back: the window goes out in the gap and the global request
    stays pending; due together, the global run alone goes (it settles too)."""
    settings, svc, gts, sims, map_id, opt = _merged_with_optimizer(redis_url, world)
    c = svc.collab
    ha = svc.handlers["A"]

    def run_one(reason: str) -> None:
        job = opt.queue.take(block_s=0.1)
        assert job is not None and job.map_id == map_id
        corr = opt.handle(job)
        assert corr is not None and corr.stats["reason"] == reason
        assert c.on_correction(CorrectionMsg.decode(corr.encode()))

    assert c.due(time.monotonic()) == [(map_id, "merge")]
    c.request(map_id, "merge")
    _fly_on(svc, sims, gts, "A", "MH01", 700, 1150)  # flown during the optimization
    run_one("merge")
    assert not ha.smap.kfs[ha.kf_gid(ha.latest_kf)].optimized
    now = time.monotonic()
    g = c._spacing(map_id, "loop")
    g.sent, g.run_s = now, 20.0  # the next global run waits 20 / optimizer_share
    c.mark_dirty(map_id, "loop")
    assert c.due(now + 1.0) == []
    assert c.mark_unsettled(now) == [map_id]
    assert c.mark_unsettled(now) == []  # once
    assert c.due(now + 1.0) == [(map_id, "local")]
    assert c._dirty == {map_id: "loop"}  # still pending
    assert c.request(map_id, "local") is not None
    assert c.mark_unsettled(now) == []  # out
    run_one("local")
    assert ha.smap.kfs[ha.kf_gid(ha.latest_kf)].optimized
    assert c.due(now + 1.0) == []
    assert c.due(now + 20.0 / c.optimizer_share + 0.1) == [(map_id, "loop")]
    # Both due at once: the global run alone.
    _fly_on(svc, sims, gts, "A", "MH01", 1150, 1400)
    c.mark_dirty(map_id, "loop")
    assert c.mark_unsettled(time.monotonic()) == [map_id]
    assert c.due(time.monotonic() + 1e3) == [(map_id, "loop")]
    assert c._windows == set()


def test_a_windowed_ba_settles_an_agents_newest_keyframes_and_leaves_the_rest(redis_url, world):
    """Settling without a global optimization (reason "local"): an agent
    settle_window_kfs keyframes past its newest settled one gets a windowed BA -- the
    map's unsettled keyframes free, the settled ones that see their points fixed. The
    copy is a small part of the map, keyframes outside it and their points do not move,
    the window's keyframes come out settled (its newest is what the frame correction is
    fitted on) and no further from the truth than registration had put them; it is
    spaced by its own run time, not the global BA's."""
    settings, svc, gts, sims, map_id, opt = _merged_with_optimizer(redis_url, world)
    c = svc.collab
    ha = svc.handlers["A"]

    def run_one():
        job = opt.queue.take(block_s=0.1)
        assert job is not None and job.map_id == map_id
        corr = opt.handle(job)
        assert corr is not None and c.on_correction(CorrectionMsg.decode(corr.encode()))
        return corr

    assert c.due(time.monotonic()) == [(map_id, "merge")]
    c.request(map_id, "merge")
    _fly_on(svc, sims, gts, "A", "MH01", 700, 1150)  # flown during the optimization
    glob = run_one()
    smap = ha.smap
    unsettled = {g for g, k in smap.kfs.items() if not k.optimized}
    assert unsettled and ha.kf_gid(ha.latest_kf) in unsettled
    outside = {g: k.T_m_kf.copy() for g, k in smap.kfs.items()}
    pts = {g: p.pos.copy() for g, p in smap.mps.items()}

    def err_of(gids) -> float:
        """RMS position error of A's keyframes ``gids`` after a similarity alignment of
        all of A's keyframes to the truth."""
        from shared.geometry import umeyama

        tr = _traj(svc, "A")
        G = gts["A"].positions[np.searchsorted(gts["A"].stamps_ns, tr.stamps_ns)]
        S = umeyama(tr.positions, G)
        ids = {smap.kfs[g].stamp_ns for g in gids if smap.kfs[g].agent == "A"}
        sel = np.array([s in ids for s in tr.stamps_ns])
        return float(np.sqrt((np.linalg.norm(S.apply(tr.positions) - G, axis=1)[sel] ** 2).mean()))

    before = err_of(unsettled)
    now = time.monotonic()
    assert c.mark_unsettled(now) == [map_id]
    assert c.due(time.monotonic() + 100.0) == [(map_id, "local")]
    req = c.request(map_id, "local")
    assert req is not None and not len(req.loops)
    # The free keyframes held to the VO's relative motion (capture.window_odometry).
    assert req.odo is not None and set(req.odo[:, 1].tolist()) <= unsettled
    window = set(req.kf_gids.tolist())
    free = window - set(req.fixed_gids.tolist())
    assert free == unsettled or (len(free) == 60 and free <= unsettled), (len(free), len(unsettled))
    # 60 for their shared points, and each agent's own newest settled keyframe before
    # its part of the window (capture.own_anchors), tied to it by a VO edge.
    assert 2 <= len(req.fixed_gids) <= 62 and len(window) < len(smap.kfs), (
        len(window),
        len(smap.kfs),
    )
    first = min((smap.kfs[g] for g in free if smap.kfs[g].agent == "A"), key=attrgetter("stamp_ns"))
    anchor = max((k for k in smap.kfs.values()
                  if k.agent == "A" and k.optimized and k.stamp_ns < first.stamp_ns),
                 key=attrgetter("stamp_ns"))  # fmt: skip
    assert anchor.gid in set(req.fixed_gids.tolist())
    assert (anchor.gid, first.gid) in {tuple(e) for e in req.odo.tolist()}
    # Out: no second copy, local or global settle.
    assert c.mark_unsettled(now) == []
    corr = run_one()
    assert corr.stats["reason"] == "local"
    assert corr.stats["ba_odometry_edges"] > 0
    assert corr.stats["seconds"] < glob.stats["seconds"], (corr.stats, glob.stats)
    # Outside the window nothing moved, nor the points anchored there.
    for g, T in outside.items():
        if g not in window:
            np.testing.assert_array_equal(smap.kfs[g].T_m_kf, T)
    for g, p in smap.mps.items():
        if g in pts and p.ref_kf not in window:
            np.testing.assert_array_equal(p.pos, pts[g])
    assert smap.kfs[ha.kf_gid(ha.latest_kf)].optimized
    assert all(smap.kfs[g].optimized for g in free)
    after = err_of(unsettled)
    assert after < 0.5 * before, (before, after)  # 9.1 -> 2.0 (units of the VO)
    assert c._settled["A"] == ha.latest_kf
    assert smap.check_invariants() == []
    # Spaced by its own run time (far shorter than the global BA's).
    assert c._spacing(map_id, "local").run_s == corr.stats["seconds"]
    assert c._spacing(map_id, "global").run_s == glob.stats["seconds"]
    print(
        f"window {len(window)} of {len(smap.kfs)} kfs, free {len(free)}, "
        f"{corr.stats['seconds']:.2f} s vs global {glob.stats['seconds']:.2f} s; "
        f"unsettled error {1e3 * before:.3f} -> {1e3 * after:.3f} milli-units"
    )


def test_a_lost_windowed_ba_holds_settling_back_for_its_own_run_time_only(redis_url, world):
    """A windowed BA whose correction never comes (its job failed, the correction was
    dropped on the way) is given up after a few of its own runs (plus the map's global
    run it may have queued behind), not after the minute a global request gets: the next
    settle mark comes within seconds. A lost global request still holds it back for
    ``inflight_timeout_s``."""
    settings, svc, gts, sims, map_id, opt = _merged_with_optimizer(redis_url, world)
    c = svc.collab
    assert c.due(time.monotonic()) == [(map_id, "merge")]
    c.request(map_id, "merge")
    _fly_on(svc, sims, gts, "A", "MH01", 700, 1150)  # flown during the optimization
    job = opt.queue.take(block_s=0.1)
    glob = opt.handle(job)
    assert glob is not None and c.on_correction(CorrectionMsg.decode(glob.encode()))
    global_s = glob.stats["seconds"]
    local_budget_s = settings.optimizer.local_ba_time_budget_s
    bound = global_s + 3.0 * local_budget_s  # no windowed BA has run yet
    assert bound + 1.0 < c.inflight_timeout_s, (global_s, local_budget_s)

    def lose(reason: str) -> float:
        """Requests an optimization of the map whose job the optimizer takes and drops."""
        assert c.due(time.monotonic() + 1e3) == [(map_id, reason)]
        assert c.request(map_id, reason) is not None
        sent = time.monotonic()
        lost = opt.queue.take(block_s=0.1)
        assert lost is not None and lost.map_id == map_id
        opt.queue.done(lost)
        return sent

    now = time.monotonic()
    assert c.mark_unsettled(now) == [map_id]
    sent = lose("local")
    assert c.mark_unsettled(sent + 1.0) == []  # out
    assert c.mark_unsettled(sent + bound - 1.0) == []  # may be queued behind a global run
    assert c.mark_unsettled(sent + bound + 1.0) == [map_id]  # lost: asked again
    # A global request lost: as before, a minute (or three of the map's global runs).
    c.mark_dirty(map_id, "loop")  # in place of the settle just marked
    sent = lose("loop")
    timeout = max(c.inflight_timeout_s, 3.0 * global_s)
    assert c.mark_unsettled(sent + timeout - 1.0) == []
    assert c.mark_unsettled(sent + timeout + 1.0) == [map_id]


def test_an_older_requests_correction_does_not_let_settling_overtake_a_newer_request(
    redis_url, world
):
    """Two requests of a map out, the older one's run finishes (the optimizer lets it
    when the map's restarts are spent) and is applied: the newer one is still out, so no
    settle request may go out yet (the map's newest job wins, and a windowed BA would
    replace the global run with its loops). Its own correction ends it."""
    settings, svc, gts, sims, map_id, opt = _merged_with_optimizer(redis_url, world)
    c = svc.collab
    assert c.due(time.monotonic()) == [(map_id, "merge")]
    assert c.request(map_id, "merge") is not None
    older = opt.decode(opt.queue.take(block_s=0.1))
    _fly_on(svc, sims, gts, "A", "MH01", 700, 1150)  # unsettled by the older copy
    c.mark_dirty(map_id, "loop")
    assert c.due(time.monotonic() + 1e3) == [(map_id, "loop")]
    assert c.request(map_id, "loop") is not None
    newer_job = opt.queue.take(block_s=0.1)
    corr = opt.optimize(older)  # run to the end, as with its restarts spent
    assert c.on_correction(CorrectionMsg.decode(corr.encode()))
    assert c.mark_unsettled(time.monotonic()) == []  # the newer request is out
    newer = opt.handle(newer_job)
    assert newer is not None and c.on_correction(CorrectionMsg.decode(newer.encode()))
    _fly_on(svc, sims, gts, "A", "MH01", 1150, 1400)
    assert c.mark_unsettled(time.monotonic()) == [map_id]


def test_a_second_global_run_starts_where_the_first_ended(redis_url, world):
    """A global run distributes the map's loop constraints (pose graph, then BA); once
    its correction is applied they measure the corrected map, so the next global run
    (a "continue" of a BA its budget cut short) starts where the first ended instead
    of being pulled back towards the detection-time measurements. Kept as measured,
    every settle of team3 at f7923c3 began its BA at the same error (6.93e4, ending
    at 5.23e4): the map never converged."""
    # One BA iteration per run: the first leaves the map short of its optimum.
    one = OptimizerSettings(ba_time_budget_s=60.0, ba_max_iterations=1)
    settings, svc, _, _, map_id, opt = _merged_with_optimizer(redis_url, world, one)
    c = svc.collab

    def run(reason: str):
        sent = c.request(map_id, reason)
        assert isinstance(sent, OptimizeRequest) and len(sent.loops) == 1
        job = opt.queue.take(block_s=0.1)
        corr = opt.optimize(opt.decode(job), job)
        assert c.on_correction(CorrectionMsg.decode(corr.encode())) is True
        return sent, corr.stats

    first_req, first = run("merge")
    smap = svc.maps[map_id]
    (lc,) = c.loops[map_id]
    # The constraint now measures the corrected map's relative pose...
    rel = np.linalg.inv(smap.kfs[lc.q].T_m_kf) @ smap.kfs[lc.c].T_m_kf
    assert np.allclose(lc.S_q_c, rel, atol=1e-9)
    assert not np.allclose(lc.S_q_c, first_req.S_loop[0], atol=1e-6)
    assert lc.distributed
    second_req, second = run("continue")
    assert np.allclose(second_req.S_loop[0], rel, atol=1e-9)
    # ...so the second run has no pose graph to run and its BA goes on from the first's end.
    assert "pgo_error_initial" not in second, second
    assert second["ba_error_initial"] <= first["ba_error_final"] * 1.01, (first, second)
    assert second["ba_error_final"] < first["ba_error_final"]
    # Something moves a loop keyframe between global runs (a windowed BA, say): the next
    # run gets the loop where the last run left it, not where its keyframes are now, and
    # its pose graph pulls them back (taken from the map at each request, 01a2bdd's rule,
    # whatever moved the keyframes became the loop's measurement).
    held = c.loops[map_id][0].S_q_c.copy()
    nudge = np.eye(4)
    nudge[:3, :3], nudge[:3, 3] = exp_so3(np.array([0.0, 0.0, 0.02])), [0.0, 0.0, 0.05]
    smap.kfs[lc.q].T_m_kf = smap.kfs[lc.q].T_m_kf @ nudge
    moved = loop_residual(held, np.linalg.inv(smap.kfs[lc.q].T_m_kf) @ smap.kfs[lc.c].T_m_kf)
    third_req, third = run("settle")
    assert np.allclose(third_req.S_loop[0], held, atol=1e-12)
    assert loops_pull(third_req) and "pgo_error_initial" in third, third
    back = loop_residual(held, np.linalg.inv(smap.kfs[lc.q].T_m_kf) @ smap.kfs[lc.c].T_m_kf)
    assert back[0] < 0.25 * moved[0] and back[1] < 0.25 * moved[1], (moved, back)
    # The rebased constraint is what a restarted mapper loads.
    again = MapperService(settings)
    again.load()
    (lc2,) = again.collab.loops[map_id]
    assert np.allclose(lc2.S_q_c, c.loops[map_id][0].S_q_c, atol=1e-12)


def test_a_merge_carries_the_moved_maps_loops_in_the_new_units(redis_url, world):
    """The map a merge moves into the other's frame is scaled (the two agents' VO units
    differ), and so are the relative poses of its keyframes: its loop constraints must
    follow, as its culled keyframes' relative poses do (``move_map``). Carried over
    unscaled, each one pulled its keyframes, at every later global run, towards a
    length off by the merge's scale (B's is half of A's here)."""
    svc = MapperService(Settings(redis_url=redis_url))
    c = svc.collab
    gts, sims = _two_noisy_agents(svc, world)

    def rel(smap, q, k):
        return np.linalg.inv(smap.kfs[q].T_m_kf) @ smap.kfs[k].T_m_kf

    for agent in "AB":
        smap = svc.maps[svc.handlers[agent].map_id]
        q, k = sorted(smap.kfs)[5], sorted(smap.kfs)[40]
        c.loops[smap.map_id] = [LoopConstraint(q, k, rel(smap, q, k), distributed=True)]
    assert c.on_match(_match_from_truth(svc, sims, gts, "B", "A")) == "merge"
    smap = svc.maps[svc.handlers["A"].map_id]
    assert svc.handlers["B"].map_id == smap.map_id
    carried = [lc for lc in c.loops[smap.map_id] if lc.distributed]
    assert len(carried) == 2
    for lc in carried:
        rot, trans = loop_residual(lc.S_q_c, rel(smap, lc.q, lc.c))
        assert rot < 1e-6 and trans < 1e-9, (lc.q, lc.c, rot, trans)


def _merged_loop(redis_url, world):
    """The merged map of ``_merged_with_optimizer`` and its one loop (the merge's): the
    collaboration, the map, its id, the loop, its keyframes' relative pose in the map,
    and a function giving a measurement of it off by (degrees, share of its length)."""
    _, svc, _, _, map_id, _ = _merged_with_optimizer(redis_url, world)
    c = svc.collab
    smap = svc.maps[map_id]
    (lc,) = c.loops[map_id]
    rest = np.linalg.inv(smap.kfs[lc.q].T_m_kf) @ smap.kfs[lc.c].T_m_kf
    length = np.linalg.norm(rest[:3, 3])

    def measured(deg: float, share: float) -> np.ndarray:
        off = np.eye(4)
        off[:3, :3] = exp_so3(np.array([0.0, np.radians(deg), 0.0]))
        off[:3, 3] = [share * length, 0.0, 0.0]
        return rest @ off

    return c, smap, map_id, lc, rest, measured


def test_a_loop_the_correction_left_unsatisfied_keeps_its_measurement(redis_url, world):
    """Only a loop the corrected map satisfies becomes a rest edge. One the map is still
    away from (the run could not tie its keyframes, or they arrived late and were
    carried along) keeps its measurement, so the next global run pulls again: making
    every carried loop a rest edge (9b35735) left team5 with 1 s delayed messages with
    one agent's keyframes 157 mm off."""
    c, smap, map_id, lc, rest, measured = _merged_loop(redis_url, world)
    for deg, share, at_rest in [(0.3, 0.01, True), (3.0, 0.0, False), (0.0, 0.2, False)]:
        S = measured(deg, share)
        c.loops[map_id] = [LoopConstraint(lc.q, lc.c, S)]
        stored = c._rebase_loops(smap, {(lc.q, lc.c)})
        (now,) = c.loops[map_id]
        assert now.distributed is at_rest, (deg, share)
        if at_rest:
            assert np.allclose(now.S_q_c, rest, atol=1e-12) and len(stored) == 1
        else:
            assert now.S_q_c is S and not stored
            sent = c.request(map_id, "settle")
            assert np.allclose(sent.S_loop[0], S, atol=1e-12)
    # A loop already at rest that the map no longer satisfies is held where it was.
    for deg, share, follows in [(0.3, 0.01, True), (3.0, 0.0, False), (0.0, 0.2, False)]:
        S = measured(deg, share)
        c.loops[map_id] = [LoopConstraint(lc.q, lc.c, S, distributed=True)]
        stored = c._rebase_loops(smap, {(lc.q, lc.c)})
        (now,) = c.loops[map_id]
        assert now.distributed and (now.S_q_c is not S) is follows, (deg, share)
        assert len(stored) == int(follows)
        assert np.allclose(now.S_q_c, rest if follows else S, atol=1e-12)


def test_loop_residual_measures_rotation_and_translation_share():
    S = np.eye(4)
    S[:3, :3] = 1.1 * exp_so3(np.array([0.0, 0.0, np.radians(2.0)]))
    S[:3, 3] = [1.0, 0.0, 0.0]
    T = np.eye(4)
    T[:3, 3] = [1.0, 0.05, 0.0]
    rot, trans = loop_residual(S, T)
    assert abs(rot - 2.0) < 1e-9 and abs(trans - 0.05) < 1e-12


def test_a_loop_fuses_fewer_matched_points_while_the_maps_actor_is_busy(redis_url, world):
    """A loop's matched points are fused ``loop_fuse_max`` pairs at most; while the map's
    actor spends over half its time on batches, ``loop_fuse_busy`` (the loop edge
    carries the constraint; the fusion is background work and counted as shed)."""
    from types import SimpleNamespace

    from services.mapper.metrics import SHED

    svc = MapperService(Settings(redis_url=redis_url))
    c = svc.collab
    _two_noisy_agents(svc, world)
    smap = svc.maps[svc.handlers["A"].map_id]
    actor = svc.registry.actor(smap.map_id)
    pts = sorted(smap.mps)
    assert len(pts) >= 4 * c.loop_fuse_max
    half = len(pts) // 2
    m = SimpleNamespace(mp_q=np.array(pts[:half]), mp_c=np.array(pts[half : 2 * half]))

    def shed() -> float:
        return SHED.labels("loop_fusion")._value.get()

    n0, s0 = len(smap.mps), shed()
    actor.load = lambda: 0.2
    c._fuse_in_slices(smap.map_id, m)
    assert n0 - len(smap.mps) == c.loop_fuse_max and shed() == s0
    n1 = len(smap.mps)
    live = sorted(smap.mps)  # distinct points each, so every pair fuses
    half = len(live) // 2
    m = SimpleNamespace(mp_q=np.array(live[:half]), mp_c=np.array(live[half : 2 * half]))
    actor.load = lambda: 0.8
    c._fuse_in_slices(smap.map_id, m)
    assert n1 - len(smap.mps) == c.loop_fuse_busy and shed() == s0 + 1
    assert not smap.check_invariants()


def test_a_global_run_moves_each_agents_frontier_but_leaves_it_to_a_window(redis_url, world):
    """A global correction settles the keyframes of its copy except each agent's
    ``settle_window_kfs`` newest unsettled ones (collab ``_frontier``: a global BA has no
    VO relative-motion edges, and a frontier keyframe few observations): those are moved
    with the rest, and the next windowed BA settles them."""
    _, svc, _, _, map_id, opt = _merged_with_optimizer(redis_url, world)
    c = svc.collab
    n = c.settle_window_kfs
    smap = svc.maps[map_id]
    before = {g: k.T_m_kf.copy() for g, k in smap.kfs.items()}
    c.request(map_id, "merge")
    job = opt.queue.take(block_s=0.1)
    assert c.on_correction(CorrectionMsg.decode(opt.handle(job).encode()))
    for agent in "AB":
        mine = sorted(g for g, k in smap.kfs.items() if k.agent == agent)
        assert [smap.kfs[g].optimized for g in mine[-n:]] == [False] * n
        assert all(smap.kfs[g].optimized for g in mine[:-n])
        # Moved with the rest all the same.
        assert any(not np.allclose(smap.kfs[g].T_m_kf, before[g]) for g in mine[-n:])
        assert c._settled[agent] == local_id_of(mine[-n - 1])
    assert c.mark_unsettled(time.monotonic()) == [map_id]
    assert c.due(time.monotonic()) == [(map_id, "local")]


def test_a_loop_the_map_keeps_rejecting_is_overruled(redis_url, world):
    """A loop left unsatisfied by ``loop_overrule_runs`` (2) global runs in a row, the map not
    moving towards it, is a wrong measurement: it becomes a rest edge where the map
    holds it, so later pose graphs stop pulling the map by it (in the seed-1 pair such a
    loop, 2.8 degrees and 13 % off, restarted every global BA at 1.7 px RMS instead of
    0.96). One whose residual falls from run to run is being satisfied and is kept."""
    c, smap, map_id, lc, rest, off = _merged_loop(redis_url, world)
    assert c.loop_overrule_runs == 2
    # The map does not move towards it: kept once, overruled at the second run.
    wrong = off(2.8, 0.13)
    c.loops[map_id] = [LoopConstraint(lc.q, lc.c, wrong)]
    for run in range(2):
        stored = c._rebase_loops(smap, {(lc.q, lc.c)})
        (now,) = c.loops[map_id]
        assert now.distributed is (run == 1), run
    assert np.allclose(now.S_q_c, rest, atol=1e-12) and len(stored) == 1
    # A loop the runs pull closer each time (its residual down 30 % a run, still
    # unsatisfied at the fourth): kept.
    for run in range(4):
        c.loops[map_id] = [LoopConstraint(lc.q, lc.c, off(4.0 * 0.7**run, 0.2 * 0.7**run))]
        c._rebase_loops(smap, {(lc.q, lc.c)})
        (now,) = c.loops[map_id]
        assert not now.distributed, run
    # Never, with the rule off.
    c.loop_overrule_runs = 0
    c.loops[map_id] = [LoopConstraint(lc.q, lc.c, wrong)]
    for _ in range(5):
        c._rebase_loops(smap, {(lc.q, lc.c)})
    assert not c.loops[map_id][0].distributed


def test_a_new_loop_the_map_already_holds_is_at_rest_from_detection(redis_url, world):
    """A loop whose matched points the map's relative pose reprojects as well as its
    Sim(3) is a rest edge from detection (``loop_support``): in the seed-1 pair such
    loops came 3-41 % of their length off a map that held the pair within 0.05 deg and
    15 mm of the truth, and kept at their measurement they bent it until two runs
    overruled them.
    With the rule off the measurement is kept."""
    c, smap, map_id, lc, rest, off = _merged_loop(redis_url, world)
    shared = np.intersect1d(smap.kfs[lc.q].observed(), smap.kfs[lc.c].observed())
    assert len(shared) >= 20
    before = LOOPS_REBASED.labels("held")._value.get()
    for S in (rest, off(2.8, 0.13)):
        m = Match(map_id, lc.q, map_id, lc.c, S, shared, shared, len(shared), 1.0, 0)
        new = c._new_loop(smap, m)
        assert new.distributed and np.allclose(new.S_q_c, rest, atol=1e-12)
    assert LOOPS_REBASED.labels("held")._value.get() == before + 2
    # Asked for more support than the loop's own (no map can give it): kept.
    c.loop_map_support = 1.5
    right = Match(map_id, lc.q, map_id, lc.c, rest, shared, shared, len(shared), 1.0, 0)
    new = c._new_loop(smap, right)
    assert not new.distributed and np.array_equal(new.S_q_c, right.S_q_c)
    c.loop_map_support = 0
    new = c._new_loop(smap, m)
    assert not new.distributed and np.array_equal(new.S_q_c, m.S_q_c)
