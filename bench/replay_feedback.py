"""Replay the frame-correction feedback loop offline from a recorded team run.

Record a run with the mapper's and agents' inputs dumped (``shared.feedback_dump``)::

    HIVEMAP_FEEDBACK_DUMP=/tmp/dump flock /tmp/hivemap-cpu.lock \\
        .venv/bin/python bench/bench_team.py --only team3 --frames 0:1200 --name team3_dump

then, with the run's output directory (``"out"`` in its bench/results JSON, for the
ground truth)::

    .venv/bin/python bench/replay_feedback.py /tmp/dump /tmp/hivemap-team-XXXX

For each agent: its raw VO ATE, the reported pose as it flew (``recorded``), the same
corrections replayed through ``ReportedPose`` (must match ``recorded`` exactly: a check
of the replay), and the corrections ``services.mapper.feedback.frame_correction`` as it
is now computes from the recorded map states, replayed at the frames they arrived at
(every state the mapper recorded for the agent feeds its correction history, in order,
as on the server; agents record every chunk's arrival, with a correction or without,
in dumps older than the correction history only the chunks that carried one).
The agent's reported pose does not feed back into the map (it publishes its VO pose),
so a replay is what a live run with the same map would have reported.

``--estimates AGENT`` lists instead, per map estimate of that agent's correction, how far
the VO, the estimate and what was sent are from the same rule on the ground truth at
the newest keyframe, how far (m) that keyframe is from the centre of the keyframes the
estimate was fitted on, and the angle between the estimate's rotation and the rule's
on the truth.

``--oracle`` replays the rule with the ground truth in place of the map's poses,
``--final-map`` with the map's own final poses (the last state recorded): the second
is what a map already settled at the time would have given, so the gap between it and
the live run is what the map did not yet know when each correction was made.

``--maturity`` lists instead, per agent, how far each state's settled keyframes were from
where the last state put them, by rank back from the newest settled one (the ones a
correction is fitted on).

``--settle-sooner N`` counts, in every recorded state, the N keyframes after the newest
settled one as settled too (with ``--oracle``: what settling sooner would give on an
exact map; alone: the registration's poses of those keyframes taken as they are).

``--windows 10`` adds, per agent and 10 s of its flight, the error of each of these and
of the oracle (the same rule on the ground truth): where along the flight the map's
estimate, rather than the rule, put the reported pose above the VO.
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_flight import flight_metrics  # noqa: E402
from common import write_report  # noqa: E402

from services.agent.reported import ReportedPose  # noqa: E402
from services.mapper.correction_history import CorrectionHistory  # noqa: E402
from services.mapper.feedback import (  # noqa: E402
    SETTLED_SPREAD,
    estimate_from_poses,
    fit_frame,
    settled_span,
)
from services.mapper.registration import AgentHandler  # noqa: E402
from services.mapper.server_map import ServerKeyframe, ServerMap  # noqa: E402
from shared.feedback_dump import load  # noqa: E402
from shared.geometry import Sim3, log_so3, umeyama  # noqa: E402
from shared.ids import gid  # noqa: E402
from shared.settings import Settings  # noqa: E402
from shared.trajectory import Trajectory, aligned_errors, ate, read_tum  # noqa: E402


def runs(dump: str | Path) -> dict[str, dict]:
    """Per agent: its VO ("vo": stamps, T, reported) and the chunks it got, each with the
    mapper's record of the map state it was computed from (or None)."""
    recs = load(dump)
    fcs = {(r["agent"], r["sent_ns"]): r for r in recs
           if r["who"] == "mapper" and r["kind"] == "fc"}  # fmt: skip
    out = {}
    for ag in sorted({r["who"] for r in recs if r["who"] != "mapper"}):
        vo = [r for r in recs if r["who"] == ag and r["kind"] == "vo"]
        if not vo:
            continue
        chunks = [r for r in recs if r["who"] == ag and r["kind"] == "chunk"]
        out[ag] = {"vo": vo[-1], "chunks": chunks,
                   "fcs": [fcs.get((ag, c["sent_ns"])) for c in chunks],
                   "all_fcs": [r for r in fcs.values() if r["agent"] == ag]}  # fmt: skip
    return out


def handler_of(r: dict) -> AgentHandler:
    """An agent handler holding the recorded keyframes (VO and map poses, optimized)."""
    smap = ServerMap(r["map_id"])
    h = AgentHandler(r["agent"], 1, smap)
    none = np.zeros(0, np.int64)
    for i, Tl, Tm, opt, st in zip(r["ids"].tolist(), r["T_l"], r["T_m"], r["optimized"].tolist(),
                                  r["stamps"].tolist(), strict=True):  # fmt: skip
        kf = ServerKeyframe(gid(1, i), r["agent"], i, st, Tm.copy(), Tl.copy(),
                            np.zeros((0, 2), np.float32), np.zeros((0, 2)), np.zeros(0, np.uint8),
                            np.zeros((0, 32), np.uint8), none)  # fmt: skip
        kf.optimized = bool(opt)
        smap.add_keyframe(kf)
        h.local_poses[i] = Tl
    return h


def current(r: dict, history: CorrectionHistory, n_local: int | None = None) -> Sim3 | None:
    """The correction today's frame_correction computes from a recorded map state;
    ``history``: the agent's earlier ones, as its handler on the server keeps them.

    The same steps as :func:`~services.mapper.feedback.frame_correction` on the recorded
    arrays (its handler's keyframes in order, the newest last), without building a
    server map per record; the map's estimate is kept in the record, so replaying
    another history rule on the same dump costs only the rule."""
    if r["T_l"] is None:
        return None
    if "_estimate" not in r:
        r["_estimate"] = estimate_from_poses(
            r["T_l"],
            r["T_m"],
            r["optimized"],
            Settings().mapper.feedback_correction_kfs if n_local is None else n_local,
        )
    S_g_l = r["_estimate"]
    if S_g_l is None:
        return None
    p = r["T_l"][-1, :3, 3]
    history.add(S_g_l, p)
    return history.significant(S_g_l, p)


def recompute(a: dict, n_local: int | None = None) -> dict[int, Sim3 | None]:
    """Today's correction for each of the agent's recorded map states (by ``sent_ns``),
    in the order the mapper computed them, every one of them feeding the agent's
    correction history as on the server (chunks that never reached the agent too)."""
    history = CorrectionHistory()
    return {r["sent_ns"]: current(r, history, n_local) for r in a["all_fcs"]}


def truth_at(gt: Trajectory, stamps: np.ndarray) -> np.ndarray:
    """The ground-truth poses at (or just after) each of ``stamps`` (ns)."""
    return gt.poses[np.clip(np.searchsorted(gt.stamps_ns, stamps), 0, len(gt) - 1)]


def with_truth(a: dict, gt: Trajectory) -> None:
    """Put the ground truth at each keyframe's stamp in place of the map's poses in every
    recorded map state of agent ``a`` (``--oracle``): what the correction would do with
    an exact map, the same keyframes, settled at the same times. Any frame of the truth
    serves: frame g is fitted onto the map (feedback.fit_frame)."""
    for r in a["all_fcs"]:
        if r["T_l"] is not None:
            r["T_m"] = truth_at(gt, r["stamps"]).copy()
            r.pop("_estimate", None)


def _final_state(a: dict):
    """The agent's recorded map states with keyframes, the last of them, and a function
    giving keyframe ids' rows in the last (-1 for one it no longer holds); None when
    there is no state."""
    states = [r for r in a["all_fcs"] if r["T_l"] is not None]
    if not states:
        return None
    at = {int(i): k for k, i in enumerate(states[-1]["ids"])}

    def rows(ids: np.ndarray) -> np.ndarray:
        return np.array([at.get(int(i), -1) for i in ids], np.int64)

    return states, states[-1], rows


def with_final_map(a: dict) -> int:
    """Put the agent's last recorded map state's poses in place of each earlier state's
    (``--final-map``): the same keyframes, settled at the same times, but where the map
    put them in the end, after every later optimization. Against the live run this
    separates what the map knew when a correction was made from what the rule does with
    a settled map. A keyframe the map dropped before the end keeps the pose it had then;
    returns how many states held one."""
    final = _final_state(a)
    if final is None:
        return 0
    states, last, rows = final
    partial = 0
    for r in states:
        ix = rows(r["ids"])
        have = ix >= 0
        partial += int(not have.all())
        r["T_m"] = r["T_m"].copy()
        r["T_m"][have] = last["T_m"][ix[have]]
        r.pop("_estimate", None)
    return partial


def settle_sooner(a: dict, n: int) -> None:
    """Count the ``n`` keyframes after the newest settled one as settled in every
    recorded map state of agent ``a`` (``--settle-sooner``)."""
    for r in a["all_fcs"]:
        if r["T_l"] is None:
            continue
        settled = np.asarray(r["optimized"], bool).copy()
        idx = np.nonzero(settled)[0]
        if len(idx):
            settled[: idx[-1] + 1 + n] = True
        r["optimized"] = settled
        r.pop("_estimate", None)


def replay(a: dict, fc=None) -> np.ndarray:
    """The agent's reported poses, frame by frame: the chunks offered to ReportedPose
    before the frame they arrived ahead of; ``fc(record)`` recomputes each correction
    (None: the recorded one)."""
    rp = ReportedPose()
    at: dict[int, list] = {}
    for c, r in zip(a["chunks"], a["fcs"], strict=True):
        at.setdefault(c["frame"], []).append((c, r))
    out = []
    for i, T in enumerate(a["vo"]["T"]):
        for c, r in at.get(i, []):
            if fc is None:
                S = None if c["S_g_l"] is None else Sim3.from_matrix(c["S_g_l"])
            else:
                S = None if r is None else fc(r)
            if S is not None:
                rp.offer(S)
        out.append(rp.update(T, "ok"))
    return np.stack(out)


def windows(a: dict, b: dict, gt: Trajectory, seconds: float) -> list[tuple]:
    """Where along the flight each trajectory is off: per ``seconds`` of it, the RMS error
    (m, each trajectory aligned whole, as its ATE) of the raw VO, the reported pose as
    flown, today's rule replayed on the map states, and the same rule on the ground truth
    in place of the map (``b``: the agent's records after :func:`with_truth`). A window
    where the replay is above the VO and the oracle is not is one where the map's
    estimate, not the rule, cost the agent."""
    st = a["vo"]["stamps"]
    now, now_o = recompute(a), recompute(b)
    series = [a["vo"]["T"], a["vo"]["reported"],
              replay(a, lambda r: now.get(r["sent_ns"])),
              replay(b, lambda r: now_o.get(r["sent_ns"]))]  # fmt: skip
    per = []
    for T in series:
        ie, _, err, _ = aligned_errors(Trajectory(st, T), gt)
        per.append(((st[ie] - st[0]) * 1e-9, err))
    rows = []
    for w0 in np.arange(0.0, (st[-1] - st[0]) * 1e-9, seconds):
        rms = []
        for t, err in per:
            m = (t >= w0) & (t < w0 + seconds)
            rms.append(float(np.sqrt(np.mean(err[m] ** 2))) if m.any() else float("nan"))
        rows.append((float(w0), *rms))
    return rows


def estimates(a: dict, b: dict) -> list[tuple]:
    """Per distinct map estimate of agent ``a``'s correction (in the order the mapper
    computed them): its newest keyframe's seconds into the flight and id, its newest settled
    one, and in mm at its newest keyframe the error of the VO, of the map's estimate
    and of what was sent (the part beyond the scatter), each against the same rule on
    the ground truth (``b``: :func:`with_truth`), converted to metres by the truth's
    frame fit. Where the estimate is off by more than the VO, the map state, not the
    rule, is what would cost the agent."""
    st0 = a["vo"]["stamps"][0]
    # Every map state feeds the history, as on the server (:func:`recompute`).
    n_local = Settings().mapper.feedback_correction_kfs  # the local fit's, as in current()
    hist, hist_o = CorrectionHistory(), CorrectionHistory()
    rows, prev = [], None
    for r, ro in zip(a["all_fcs"], b["all_fcs"], strict=True):
        sent = current(r, hist)
        current(ro, hist_o)
        S, S_o = r.get("_estimate"), ro.get("_estimate")
        A_o = None if ro["T_l"] is None else fit_frame(ro["T_l"], ro["T_m"], ro["optimized"])
        if S is None or S_o is None or A_o is None:
            continue
        if prev is not None and np.abs(S.matrix() - prev).max() <= 1e-12:
            continue
        prev = S.matrix()
        p = r["T_l"][-1, :3, 3]
        truth = S_o.apply(p[None])[0]

        def off(X, p=p, truth=truth, m=A_o.s) -> float:
            return float("nan") if X is None else 1e3 * m * float(
                np.linalg.norm(X.apply(p[None])[0] - truth))  # fmt: skip

        opt = np.asarray(r["optimized"], bool)
        settled = r["ids"][opt]
        # How far the VO carries the correction past the keyframes it was fitted on (a
        # rotation error of the estimate grows with it) and that rotation error.
        span = settled_span(r["T_l"], np.nonzero(opt)[0], n_local, SETTLED_SPREAD)
        lever = (float("nan") if span is None else
                 A_o.s * float(np.linalg.norm(p - r["T_l"][span, :3, 3].mean(0))))  # fmt: skip
        rot = float(np.degrees(np.linalg.norm(log_so3(S.R @ S_o.R.T))))
        rows.append(((int(r["stamps"][-1]) - st0) * 1e-9, int(r["ids"][-1]),
                     int(settled[-1]) if len(settled) else -1,
                     off(Sim3.identity()), off(S), off(sent), lever, rot))  # fmt: skip
    return rows


# Ranks counted back from an agent's newest settled keyframe (--maturity).
RANKS = (0, 5, 10, 20, 40, 80, 160)


def maturity(a: dict, gt: Trajectory, every: int = 3) -> list[tuple[str, float, int]]:
    """How far the settled keyframes of each recorded map state were from where the last
    state put them, by rank back from the newest settled one (RANKS): per bucket the RMS
    in metres (each state aligned onto the last by a similarity over the keyframes both
    hold; map units to metres by the last state's fit onto the truth), and how many.
    Every ``every``-th state is looked at. The newest settled keyframes are what each
    correction is fitted on (feedback.fit_settled)."""
    final = _final_state(a)
    if final is None:
        return []
    states, last, rows = final
    Q_all = last["T_m"][:, :3, 3]
    to_m = umeyama(Q_all, truth_at(gt, last["stamps"])[:, :3, 3]).s
    edges = (*RANKS, np.inf)
    sq: list[list[float]] = [[] for _ in RANKS]
    for r in states[:-1:every]:
        sett = np.asarray(r["optimized"], bool)
        ix = rows(r["ids"][sett])
        have = ix >= 0
        if have.sum() < 8:
            continue
        P = r["T_m"][sett][have, :3, 3]
        Q = Q_all[ix[have]]
        d = np.linalg.norm(umeyama(P, Q).apply(P) - Q, axis=1) * to_m
        rank = np.arange(int(sett.sum()))[::-1][have]
        for b in range(len(RANKS)):
            sq[b].extend((d[(rank >= edges[b]) & (rank < edges[b + 1])] ** 2).tolist())
    return [(f"{edges[b]:g}-{edges[b + 1]:g}", float(np.sqrt(np.mean(x))) if x else float("nan"),
             len(x)) for b, x in enumerate(sq)]  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dump")
    ap.add_argument("out", help="the run's output directory (agentN_gt.tum)")
    ap.add_argument("--name", default="", help="also write bench/results/NAME.json")
    poses = ap.add_mutually_exclusive_group()
    poses.add_argument("--oracle", action="store_true",
                       help="ground truth in place of the map's keyframe poses")  # fmt: skip
    poses.add_argument("--final-map", action="store_true",
                       help="the last recorded map state's poses in place of every earlier "
                       "state's (what a settled map would have given)")  # fmt: skip
    ap.add_argument("--settle-sooner", type=int, default=0, metavar="N",
                    help="count the N keyframes after each state's newest settled one as "
                    "settled too")  # fmt: skip
    ap.add_argument("--maturity", action="store_true",
                    help="only list, per agent, how far each state's settled keyframes were "
                    "from their final poses, by rank back from the newest settled one")  # fmt: skip
    ap.add_argument("--windows", type=float, default=0.0, metavar="S",
                    help="also per S seconds of each flight: VO, recorded, replayed and "
                    "oracle error (where the map's estimate cost the agent)")  # fmt: skip
    ap.add_argument("--estimates", default="", metavar="AGENT",
                    help="only list, per map estimate of AGENT's correction, the error "
                    "at its newest keyframe of the VO, the estimate and what was sent")  # fmt: skip
    args = ap.parse_args()
    if args.maturity:
        print(f"{'agent':8} " + " ".join(f"{f'rank {lo}+ mm':>13}" for lo in RANKS))
        for ag, a in runs(args.dump).items():
            rows = maturity(a, read_tum(Path(args.out) / f"{ag}_gt.tum"))
            print(f"{ag:8} " + " ".join(f"{1e3 * e:13.2f}" for _, e, _ in rows))
        return 0
    if args.estimates:
        a = runs(args.dump)[args.estimates]
        b = copy.deepcopy(a)
        with_truth(b, read_tum(Path(args.out) / f"{args.estimates}_gt.tum"))
        print(f"{'t_s':>7} {'kf':>5} {'settled':>7} {'vo_mm':>7} {'estimate_mm':>11} "
              f"{'sent_mm':>8} {'lever_m':>7} {'rot_off_deg':>11}")  # fmt: skip
        for t, kf, sk, e_vo, e_est, e_sent, lever, rot in estimates(a, b):
            print(f"{t:7.1f} {kf:5d} {sk:7d} {e_vo:7.2f} {e_est:11.2f} {e_sent:8.2f} "
                  f"{lever:7.2f} {rot:11.3f}")  # fmt: skip
        return 0
    rows, sums, report = [], np.zeros(3), []
    recorded = runs(args.dump)
    # --windows replays on the map's states and on the truth: a second copy for the
    # truth (with_truth rewrites the records), copied rather than read from disk again.
    truth_copy = copy.deepcopy(recorded) if args.windows > 0 else {}
    for ag, a in recorded.items():
        gt = read_tum(Path(args.out) / f"{ag}_gt.tum")
        st = a["vo"]["stamps"]
        if args.windows > 0:
            b = truth_copy[ag]
            with_truth(b, gt)
            print(f"{ag}: per {args.windows:g} s, RMS mm (each trajectory aligned whole)")
            print(f"{'t_s':>6} {'vo':>7} {'recorded':>9} {'current':>8} {'oracle':>7}")
            for w0, *rms in windows(a, b, gt, args.windows):
                print(f"{w0:6.0f} " + " ".join(f"{1e3 * x:{w}.2f}" for x, w in
                                                zip(rms, (7, 9, 8, 7), strict=True)))  # fmt: skip
        if args.oracle:
            with_truth(a, gt)
        elif args.final_map:
            n = with_final_map(a)
            print(f"{ag}: {n} map states held keyframes the final one had dropped")
        if args.settle_sooner > 0:
            settle_sooner(a, args.settle_sooner)

        def err(T, st=st, gt=gt) -> float:
            return ate(Trajectory(st, T), gt).rmse

        rec = a["vo"]["reported"]
        again = replay(a)
        now = recompute(a)
        cur = replay(a, lambda r, now=now: now.get(r["sent_ns"]))
        e = np.array([err(a["vo"]["T"]), err(rec), err(cur)])
        sums += e
        fl = flight_metrics(Trajectory(st, cur), Trajectory(st, a["vo"]["T"]), gt)
        rows.append((ag, *e, fl["max_own_jump_5cm_m"], float(np.abs(again - rec).max())))
        report.append({"agent": ag, "vo_ate_m": e[0], "recorded_ate_m": e[1], "current_ate_m": e[2],
                       "max_own_jump_5cm_m": fl["max_own_jump_5cm_m"], "jumps_5cm": fl["jumps_5cm"],
                       "replay_check": rows[-1][-1]})  # fmt: skip
    print(f"{'agent':8} {'vo_mm':>7} {'recorded_mm':>12} {'current_mm':>11} "
          f"{'own_jump>5cm_m':>15} {'replay_check':>13}")  # fmt: skip
    for ag, v, r, c, j, d in rows:
        print(f"{ag:8} {1e3 * v:7.2f} {1e3 * r:12.2f} {1e3 * c:11.2f} {j:15.3f} {d:13.1e}")
    print(f"{'sum':8} {1e3 * sums[0]:7.2f} {1e3 * sums[1]:12.2f} {1e3 * sums[2]:11.2f}")
    if args.name:
        # "current": this checkout's frame correction replayed on the recorded map states.
        data = {
            "dump": str(args.dump),
            "oracle": args.oracle,
            "final_map": args.final_map,
            "settle_sooner": args.settle_sooner,
            "run_out": str(args.out),
            "agents": report,
            "vo_sum_m": sums[0],
            "recorded_sum_m": sums[1],
            "current_sum_m": sums[2],
        }
        path = write_report(args.name, data)
        print(f"written {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
