"""Where an agent's server keyframes went wrong, from a recorded team run.

Reads a feedback dump (``HIVEMAP_FEEDBACK_DUMP=DIR``, ``shared/feedback_dump.py``: the
mapper records every agent's keyframes, VO and map poses, at each feedback round, and
every optimization request and applied correction) and the run's output directory
(``"out"`` in its bench/results JSON, for the ground truth)::

    .venv/bin/python bench/server_scale.py DUMP OUT [--agent agent1] [--name NAME]

For the agent: after each applied correction, the map's scale per VO unit fitted on
its newest settled keyframes (``feedback.settled_scale``, what the handler takes since
d72408f) against the scale registration actually chained its next keyframes at
(their map step over their VO step); the agent's Sim(3)-aligned ATE just before each
correction; and of the last recorded state, the ATE of all its keyframes, of those an
optimization settled, and per-segment scales (a segment's own Sim(3) scale over the
whole trajectory's: a tail chained at a wrong scale shows as a step). Team5 at 85a443d
(agent1): fitted 0.972-0.976 from 321 s on, chained at 0.996-1.001; last state 55.7
mm, settled keyframes 5.8 mm; segments 1.008 -> 0.988.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import write_report  # noqa: E402
from replay_feedback import handler_of  # noqa: E402

from services.mapper.feedback import settled_scale  # noqa: E402
from shared.feedback_dump import load  # noqa: E402
from shared.geometry import umeyama  # noqa: E402
from shared.trajectory import Trajectory, associate, read_tum  # noqa: E402


def _aligned(P: np.ndarray, st: np.ndarray, gt: Trajectory) -> tuple[np.ndarray, np.ndarray, float]:
    """(errors, ground-truth positions, scale) of positions ``P`` at stamps ``st``."""
    tr = Trajectory(st, np.tile(np.eye(4), (len(P), 1, 1)))
    tr.poses[:, :3, 3] = P
    ie, ir = associate(tr, gt)
    S = umeyama(P[ie], gt.positions[ir])
    return np.linalg.norm(S.apply(P[ie]) - gt.positions[ir], axis=1), gt.positions[ir], S.s


def _rmse(e: np.ndarray) -> float:
    return float(np.sqrt((e**2).mean())) if len(e) else float("nan")


def analyse(recs: list[dict], agent: str, gt: Trajectory) -> dict:
    fc = [r for r in recs if r["who"] == "mapper" and r["kind"] == "fc"
          and r["agent"] == agent and r["T_m"] is not None]  # fmt: skip
    opts = [r for r in recs if r["who"] == "mapper" and r["kind"] == "opt"]
    if not fc:
        raise SystemExit(f"no feedback records of {agent}")
    t0 = fc[0]["wall_ns"]
    rows = []
    for k, o in enumerate(opts):
        after = [r for r in fc if r["wall_ns"] > o["wall_ns"]]
        # The state before the correction went in (records of the round that applied
        # it come before the "opt" record; they already show its settled keyframes).
        n_set = int(after[0]["optimized"].sum()) if after else 0
        before = [r for r in fc if r["wall_ns"] < o["wall_ns"] and r["optimized"].sum() < n_set]
        if not after or after[0]["map_id"] != o["map_id"]:
            continue
        a = after[0]
        end = opts[k + 1]["wall_ns"] if k + 1 < len(opts) else 1 << 62
        known = set(a["ids"].tolist())
        steps = []  # map step / VO step of keyframes registered after this correction
        for r in (r for r in after if r["wall_ns"] < end):
            i = len(r["ids"]) - 1
            if i < 1 or r["ids"][i] in known or r["ids"][i] != r["ids"][i - 1] + 1:
                continue
            known.add(int(r["ids"][i]))
            dl = np.linalg.norm(r["T_l"][i, :3, 3] - r["T_l"][i - 1, :3, 3])
            if dl > 1e-3:
                steps.append(np.linalg.norm(r["T_m"][i, :3, 3] - r["T_m"][i - 1, :3, 3]) / dl)
        prev = opts[k - 1]["wall_ns"] if k else 0
        b = before[-1] if before and before[-1]["wall_ns"] > prev else None
        rows.append({
            "t_s": (o["wall_ns"] - t0) / 1e9, "reason": o["stats"].get("reason"),
            "settled": int(a["optimized"].sum()), "fitted_scale": settled_scale(handler_of(a)),
            "chained_scale": float(np.median(steps)) if steps else None, "new_kfs": len(steps),
            "ate_before_m": _rmse(_aligned(b["T_m"][:, :3, 3], b["stamps"], gt)[0]) if b else None,
        })  # fmt: skip
    last = fc[-1]
    P, st, opt = last["T_m"][:, :3, 3], last["stamps"], last["optimized"]
    e, G, s_all = _aligned(P, st, gt)
    segs = []
    for sl in np.array_split(np.arange(len(e)), 8):
        if len(sl) >= 3:
            segs.append({"rmse_m": _rmse(e[sl]),
                         "scale": float(umeyama(P[sl], G[sl]).s / s_all)})  # fmt: skip
    return {
        "agent": agent, "corrections": rows,
        "last": {"kfs": len(P), "settled": int(opt.sum()), "ate_m": _rmse(e),
                 "ate_settled_m": _rmse(_aligned(P[opt], st[opt], gt)[0]) if opt.sum() >= 3
                 else None, "segments": segs},
    }  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dump")
    ap.add_argument("out", help="the run's output directory (agentN_gt.tum)")
    ap.add_argument("--agent", default="agent1")
    ap.add_argument("--name", default="", help="also write bench/results/NAME.json")
    args = ap.parse_args()
    gt = read_tum(Path(args.out) / f"{args.agent}_gt.tum")
    doc = analyse(load(args.dump), args.agent, gt)

    def f(x, fmt):
        return "-" if x is None else fmt % x

    print(f"{'t s':>7} {'reason':>8} {'settled':>7} {'fitted':>7} {'chained':>7} {'new':>4} "
          f"{'ATE before mm':>13}")  # fmt: skip
    for r in doc["corrections"]:
        print(
            f"{r['t_s']:7.1f} {r['reason']!s:>8} {r['settled']:7d} "
            f"{f(r['fitted_scale'], '%.4f'):>7} {f(r['chained_scale'], '%.4f'):>7} "
            f"{r['new_kfs']:4d} {f(r['ate_before_m'] and 1e3 * r['ate_before_m'], '%.1f'):>13}"
        )
    la = doc["last"]
    settled = f(la["ate_settled_m"] and 1e3 * la["ate_settled_m"], "%.1f")
    print(f"last state: {la['kfs']} keyframes ({la['settled']} settled), ATE "
          f"{1e3 * la['ate_m']:.1f} mm, settled ones {settled} mm")  # fmt: skip
    print(
        "segments (own scale / whole's, rmse mm): "
        + "  ".join(f"{s['scale']:.3f}/{1e3 * s['rmse_m']:.1f}" for s in la["segments"])
    )
    if args.name:
        print(f"written {write_report(args.name, doc)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
