"""What the live agent's asynchronous local BA and dropped frames do to the VO's ATE,
without a clock (agent issue 17, item 3). ``--realtime`` runs differ from run to run
(when each local BA comes back, which frames are dropped), so the causes are taken
apart here deterministically: the VO alone on a rendered sequence, its local BA
solved at once but its result handed back only ``K`` frames later (what the worker
process does, minus the timing), and optionally a seeded share of frames left out
(what a live camera drops while the tracker is busy). K=0 is the inline BA of the
unpaced run. Prints and writes the ATE per setting, with what the VO's work costs on
this machine: tracking per frame (median, ORB included) and mapping per keyframe
(triangulation, local BA, culling; with K=0, where the BA is inline).

    .venv/bin/python bench/bench_async_ba.py [--seq MH02] [--k 0,4] [--drop 0,0.07] [--abort 0,1]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from common import table, write_report  # noqa: E402

from services.agent.sources import open_source  # noqa: E402
from services.agent.vo.local_ba import BAResult, local_ba  # noqa: E402
from services.agent.vo.odometry import VisualOdometry  # noqa: E402
from shared.trajectory import Trajectory, ate  # noqa: E402


class HeldBA:
    """The BA worker's interface (busy / submit / result), solved in this process at
    submit and handed back after ``k`` frames."""

    def __init__(self, k: int, abortable: bool = False) -> None:
        self.k, self.res, self.age, self.abortable = k, None, 0, abortable
        self.job: dict | None = None
        self.aborted = 0

    @property
    def busy(self) -> bool:
        return self.res is not None

    def submit(self, job: dict) -> None:
        self.job, self.res, self.age = job, local_ba(**job), 0

    def abort(self) -> None:
        """The worker's abort, modelled: the iterations spread evenly over the ``k``
        frames, the one running when the keyframe came finishes, and the result is
        back at the next poll."""
        if not self.abortable or self.res is None or self.age >= self.k:
            return
        done = max(1, math.ceil(self.res.iterations * (self.age + 1) / self.k))
        if done < self.res.iterations:
            self.res = local_ba(**{**self.job, "max_iters": done})
        self.age, self.aborted = self.k, self.aborted + 1

    def tick(self) -> None:
        self.age += 1

    def result(self, wait: bool = False) -> BAResult | None:
        if self.res is None or not (wait or self.age >= self.k):
            return None
        r, self.res = self.res, None
        return r

    def close(self) -> None:
        pass


def run(seq: str, k: int, drop: float, frames: str, seed: int = 7, abort: bool = False) -> dict:
    src = open_source(f"synthetic:{seq}" + (f"?frames={frames}" if frames else ""))
    vo = VisualOdometry(src.camera)
    held = HeldBA(k, abort) if k > 0 else None
    vo.ba_worker = held
    rng = np.random.default_rng(seed)
    stamps, poses, dropped = [], [], 0
    track_s, map_s = [], []
    t0 = time.monotonic()
    for f in src:
        if drop and stamps and rng.random() < drop:
            dropped += 1
            continue
        r = vo.track(f.image, f.stamp_ns)
        track_s.append(r.track_s)
        if r.keyframe is not None:
            map_s.append(r.map_s)
        if r.T_w_c is not None:
            stamps.append(f.stamp_ns)
            poses.append(r.T_w_c)
        if held is not None:
            held.tick()
            vo.poll_mapping()
    a = ate(Trajectory(np.array(stamps), np.stack(poses)), src.ground_truth)
    return {"seq": seq, "k": k, "abort": abort, "aborted": held.aborted if held else 0,
            "drop": drop, "dropped": dropped, "frames": len(stamps),
            "keyframes": vo.next_kf, "ate_m": a.rmse, "ate_pct": a.percent_of_path,
            "track_ms_median": 1e3 * float(np.median(track_s)),
            "map_ms_per_kf": 1e3 * float(np.mean(map_s)) if map_s else float("nan"),
            "seconds": time.monotonic() - t0}  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seq", default="MH02")
    ap.add_argument("--k", default="0,4", help="frames a local BA result is held back")
    ap.add_argument("--drop", default="0", help="shares of frames left out (seeded)")
    ap.add_argument("--abort", default="0", help="0,1: model the worker's abort at a keyframe")
    ap.add_argument("--frames", default="")
    ap.add_argument("--name", default="async_ba")
    args = ap.parse_args()
    rows = [run(args.seq, int(k), float(d), args.frames, abort=bool(int(a)))
            for d in args.drop.split(",") for k in args.k.split(",")
            for a in args.abort.split(",") if int(a) == 0 or int(k) > 0]  # fmt: skip
    path = write_report(args.name, {"rows": rows})
    cols = ["seq", "k", "abort", "aborted", "drop", "dropped", "frames", "keyframes", "ate_m",
            "track_ms_median", "map_ms_per_kf"]  # fmt: skip
    print(table(rows, cols))
    print(f"written {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
