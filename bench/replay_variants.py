"""Frame-correction rules tried offline on recorded runs, against today's rule.

Each variant recomputes every agent's corrections from the map states a run recorded
(``HIVEMAP_FEEDBACK_DUMP``, see bench/replay_feedback.py) and replays them through the
agent's ``ReportedPose``; the map does not depend on the correction (the agent publishes
its VO), so a replay is what a live run with the same map would have reported. States a
run recorded as held back (``held``: a rule that made no estimate for them) are
estimated like any other, so every variant starts from the same map states.

Variants (``--variant``):

- ``hold-loops``: no new estimate for an agent while a loop joining one of its
  keyframes waits for the global optimization that closes it; the loops and the
  applied corrections are read from the run's mapper log (``--log``, JSON lines at
  INFO level), a loop counted open for at most ``--cap`` seconds.
- ``lag-scatter``: the scatter of an estimate measured from the changes between
  estimates ``--lag`` apart instead of successive ones (successive estimates share most
  of their settled keyframes, so their changes understate the scatter).
- ``track-frame``: frame g moved with the map (by the similarity that takes the
  previous state's settled keyframes to where the new state puts them) instead of
  refitted on all settled keyframes at each state.
- ``fit-kfs``: the local fit on ``--kfs`` settled keyframes instead of the setting's.
- ``hold-unconverged``: no new estimate for any agent while the newest global run
  applied (not a windowed BA) stopped on its time budget, until one that converged is
  applied (read from ``--log`` like ``hold-loops``).

``--oracle`` puts the ground truth in place of the map's keyframe poses first.

    .venv/bin/python bench/replay_variants.py DUMP OUT --variant hold-loops --log RUN.log
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Callable
from datetime import datetime
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import replay_feedback as rf  # noqa: E402
from common import write_report  # noqa: E402

from services.mapper import feedback as fb  # noqa: E402
from services.mapper.correction_history import SAME, CorrectionHistory, local_params  # noqa: E402
from shared.geometry import Sim3, umeyama  # noqa: E402
from shared.ids import agent_index_of  # noqa: E402
from shared.settings import Settings  # noqa: E402
from shared.trajectory import Trajectory, ate, read_tum  # noqa: E402

N_LOCAL = Settings().mapper.feedback_correction_kfs


def _ns(ts: str) -> int:
    return int(datetime.fromisoformat(ts.replace("Z", "+00:00")).timestamp() * 1e9)


def read_log(
    path: str | Path,
) -> tuple[list[tuple[int, int, int]], list[tuple[int, str, int, str]]]:
    """From a mapper log: the loops it added, (ns, agent index of q, of c), and the
    corrections it applied, (ns, reason, ns the optimizer started the run, why its BA
    stopped)."""
    loops, applied = [], []
    for line in Path(path).read_text().splitlines():
        if not line.startswith("{"):
            continue
        try:
            r = json.loads(line)
        except ValueError:
            continue
        msg = r.get("msg")
        if not isinstance(msg, str) or "ts" not in r:
            continue
        m = re.match(r"loop closed in \S+: (\d+) <-> (\d+)", msg)
        if m:
            loops.append((_ns(r["ts"]), agent_index_of(int(m[1])), agent_index_of(int(m[2]))))
        elif msg.startswith("applied correction"):
            reason = re.search(r"'reason': '(\w+)'", msg)
            started = re.search(r"'started_ns': (\d+)", msg)
            stop = re.search(r"'ba_stop': '(\w+)'", msg)
            if reason and started:
                applied.append((_ns(r["ts"]), reason[1], int(started[1]),
                                stop[1] if stop else ""))  # fmt: skip
    return loops, applied


def loop_open(loops, applied, agent_index: int, t: int, cap_s: float) -> bool:
    """A loop joining a keyframe of the agent was added before ``t`` (at most ``cap_s``
    ago) and no global run started after it had been applied by ``t``."""
    for tl, a, b in loops:
        if tl > t or t - tl > cap_s * 1e9 or agent_index not in (a, b):
            continue
        if not any(ta <= t and st > tl and reason != "local" for ta, reason, st, _ in applied):
            return True
    return False


def unconverged(applied, t: int) -> bool:
    """The newest global run applied by ``t`` stopped on its time budget."""
    last = [stop for ta, reason, _, stop in applied if ta <= t and reason != "local"]
    return bool(last) and last[-1] == "time_budget"


class LagHistory(CorrectionHistory):
    """The scatter from changes between estimates ``lag`` apart (``lag-scatter``)."""

    def __init__(self, lag: int) -> None:
        super().__init__()
        self.lag = lag
        self.past: list[Sim3] = []

    def add(self, S: Sim3, p: np.ndarray) -> None:
        if self.last is not None:
            if np.abs(local_params(S, p) - local_params(self.last, p)).max() <= SAME:
                return
            ref = self.past[-self.lag] if len(self.past) >= self.lag else self.past[0]
            self.changes.append(local_params(S, p) - local_params(ref, p))
        self.last = S
        self.past.append(S)


class TrackedFrame:
    """Frame g moved with the map between states (``track-frame``)."""

    def __init__(self) -> None:
        self.A: Sim3 | None = None
        self.prev: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def estimate(self, r: dict) -> Sim3 | None:
        T_l, T_m = r["T_l"], r["T_m"]
        settled = np.asarray(r["optimized"], bool)
        if len(T_l) < fb.MIN_FIT_KFS or settled.sum() < fb.MIN_FIT_KFS:
            return None
        if fb.anchor_count(T_l[:, :3, 3]) is None:
            return None
        A = None
        if self.A is not None and self.prev is not None:
            ids, T_prev, set_prev = self.prev
            at = {int(i): k for k, i in enumerate(ids)}
            pairs = [(at[int(i)], k) for k, i in enumerate(r["ids"])
                     if int(i) in at and set_prev[at[int(i)]]]  # fmt: skip
            if len(pairs) >= fb.MIN_FIT_KFS:
                a, b = np.array(pairs).T
                P, Q = T_prev[a, :3, 3], T_m[b, :3, 3]
                A = self.A if np.abs(P - Q).max() == 0 else umeyama(P, Q) @ self.A
        if A is None:
            A = fb.fit_frame(T_l, T_m, settled)
        self.prev = (r["ids"], T_m, settled)
        if A is None:
            return None
        self.A = A
        S_m_l = fb.fit_settled(T_l, T_m, settled, N_LOCAL, max_step=fb.MAX_SCALE_STEP)
        if S_m_l is None:
            return None
        S = A.inverse() @ S_m_l
        return S if 0.8 < S.s < 1.25 and np.isfinite(S.matrix()).all() else None


def corrections(a: dict, variant: str, args, agent_index: int, log) -> dict[int, Sim3 | None]:
    """The variant's correction for each of the agent's recorded states (by sent_ns)."""
    out: dict[int, Sim3 | None] = {}
    if variant == "track-frame":
        tracker, hist = TrackedFrame(), CorrectionHistory()
        for r in a["all_fcs"]:
            S = None if r["T_l"] is None else tracker.estimate(r)
            if S is None:
                out[r["sent_ns"]] = None
                continue
            p = r["T_l"][-1, :3, 3]
            hist.add(S, p)
            out[r["sent_ns"]] = hist.significant(S, p)
        return out
    hist = LagHistory(args.lag) if variant == "lag-scatter" else CorrectionHistory()
    for r in a["all_fcs"]:
        if (variant == "hold-loops" and loop_open(*log, agent_index, r["sent_ns"], args.cap)) or (
            variant == "hold-unconverged" and unconverged(log[1], r["sent_ns"])
        ):
            out[r["sent_ns"]] = None
        else:
            out[r["sent_ns"]] = rf.current(r, hist)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dump")
    ap.add_argument("out", help="the run's output directory (agentN_gt.tum)")
    ap.add_argument("--variant", required=True,
                    choices=["hold-loops", "lag-scatter", "track-frame", "fit-kfs",
                             "hold-unconverged"])  # fmt: skip
    ap.add_argument("--log", default="", help="the run's mapper log (hold-loops)")
    ap.add_argument("--cap", type=float, default=60.0, help="seconds a loop holds at most")
    ap.add_argument("--lag", type=int, default=3, help="estimates apart (lag-scatter)")
    ap.add_argument("--kfs", type=int, default=N_LOCAL, help="local fit (fit-kfs)")
    ap.add_argument("--oracle", action="store_true")
    ap.add_argument("--name", default="", help="also write bench/results/NAME.json")
    args = ap.parse_args()
    if args.variant in ("hold-loops", "hold-unconverged") and not args.log:
        ap.error(f"{args.variant} needs --log")
    log = read_log(args.log) if args.log else ([], [])
    rows, sums = [], np.zeros(3)
    for ag, a in rf.runs(args.dump).items():
        gt = read_tum(Path(args.out) / f"{ag}_gt.tum")
        for r in a["all_fcs"]:
            r.pop("held", None)
        if args.oracle:
            rf.with_truth(a, gt)
        st = a["vo"]["stamps"]
        today = rf.recompute(a)
        if args.variant == "fit-kfs":
            for r in a["all_fcs"]:
                r.pop("_estimate", None)  # today's, cached by the recompute above
            new = rf.recompute(a, n_local=args.kfs)
        else:
            new = corrections(a, args.variant, args, int(ag.removeprefix("agent")), log)

        def err(fc: Callable | None = None, st=st, gt=gt, a=a) -> float:
            T = a["vo"]["T"] if fc is None else rf.replay(a, fc)
            return ate(Trajectory(st, T), gt).rmse

        e = np.array([err(), err(lambda r, c=today: c.get(r["sent_ns"])),
                      err(lambda r, c=new: c.get(r["sent_ns"]))])  # fmt: skip
        sums += e
        rows.append({"agent": ag, "vo_ate_m": e[0], "today_ate_m": e[1], "variant_ate_m": e[2]})
    print(f"{'agent':8} {'vo_mm':>7} {'today_mm':>9} {'variant_mm':>11}")
    for x in rows:
        print(f"{x['agent']:8} {1e3 * x['vo_ate_m']:7.2f} {1e3 * x['today_ate_m']:9.2f} "
              f"{1e3 * x['variant_ate_m']:11.2f}")  # fmt: skip
    pct = 100 * (sums / sums[0] - 1)
    print(f"{'sum':8} {1e3 * sums[0]:7.2f} {1e3 * sums[1]:9.2f} {1e3 * sums[2]:11.2f}   "
          f"({pct[1]:+.1f} % / {pct[2]:+.1f} % against the VO)")  # fmt: skip
    if args.name:
        opts = {k: v for k, v in vars(args).items() if k not in ("dump", "out", "name")}
        write_report(args.name, {"dump": args.dump, "run_out": args.out, **opts, "agents": rows,
                                 "vo_sum_m": sums[0], "today_sum_m": sums[1],
                                 "variant_sum_m": sums[2]})  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
