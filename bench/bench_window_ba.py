"""A windowed BA with its fixed keyframes as known cameras against the same BA with them
as pose variables under tight priors (``BAParams.known_cameras``).

Windows are cut from bench_optimizer's scene (MH01's path, noisy VO, ~230 observations
per keyframe): the first KFS keyframes, the first FIXED of them held (the settled
keyframes around a window, services/mapper/capture.py), the rest free. Both graphs run
the same number of LM iterations, alternately, REPS times each; the report holds the
best time of each, the largest difference between their poses and points, and the free
keyframes' error against the truth::

    .venv/bin/python bench/bench_window_ba.py --windows 84:60,60:30 --name window_ba
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_optimizer import make_scene  # noqa: E402
from common import write_report  # noqa: E402

from services.optimizer.global_ba import BAParams, bundle_adjust  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--windows", default="84:60,60:30", help="KFS:FIXED,...")
    ap.add_argument("--obs", type=int, default=230, help="observations per keyframe")
    ap.add_argument("--iters", type=int, default=5)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--name", default="window_ba")
    args = ap.parse_args()
    rows = []
    for spec in args.windows.split(","):
        n_kf, n_fixed = (int(x) for x in spec.split(":"))
        sc = make_scene("MH01", n_kf=n_kf, obs_per_kf=args.obs, n_loops=0)
        win = replace(sc.snap, fixed_gids=sc.snap.kf_gids[:n_fixed].copy())
        best: dict[bool, dict] = {}
        for _ in range(args.reps):
            for known in (False, True):
                prm = BAParams(max_iters=args.iters, known_cameras=known, time_budget_s=600)
                t = time.perf_counter()
                c = bundle_adjust(win, prm)
                dt = time.perf_counter() - t
                if known not in best or dt < best[known]["seconds"]:
                    free = c.T_m_kf[n_fixed:, :3, 3] - sc.T_true[n_fixed:, :3, 3]
                    best[known] = {"seconds": dt, "build_s": c.stats["ba_build_seconds"],
                                   "iterate_s": c.stats["ba_iterate_seconds"],
                                   "iterations": c.stats["ba_iterations"],
                                   "known_cameras": c.stats["ba_known_cameras"],
                                   "observations": c.stats["ba_observations"],
                                   "free_err_m": float(np.sqrt((free**2).sum(1).mean())),
                                   "T": c.T_m_kf, "P": c.mp_pos}  # fmt: skip
        a, b = best[False], best[True]
        rows.append({
            "kfs": n_kf, "fixed": n_fixed, "observations": b["observations"],
            "variables_s": a["seconds"], "known_s": b["seconds"],
            "speedup": a["seconds"] / b["seconds"],
            "variables": {k: v for k, v in a.items() if k not in ("T", "P")},
            "known": {k: v for k, v in b.items() if k not in ("T", "P")},
            "max_pose_diff": float(np.abs(a["T"] - b["T"]).max()),
            "max_point_diff": float(np.abs(a["P"] - b["P"]).max()),
        })  # fmt: skip
    print(f"{'kfs':>4} {'fixed':>5} {'obs':>6} {'variables_s':>11} {'known_s':>8} "
          f"{'speedup':>7} {'max_pose_diff':>13}")  # fmt: skip
    for r in rows:
        print(f"{r['kfs']:4d} {r['fixed']:5d} {r['observations']:6d} {r['variables_s']:11.3f} "
              f"{r['known_s']:8.3f} {r['speedup']:7.2f} {r['max_pose_diff']:13.1e}")  # fmt: skip
    path = write_report(args.name, {"iters": args.iters, "reps": args.reps,
                                    "load_avg_1m": os.getloadavg()[0], "rows": rows})  # fmt: skip
    print(f"written {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
