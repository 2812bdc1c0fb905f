"""Live-camera timing (agent issue 17, item 3): the agent as a camera drives it.

For each sequence, ``hivemap agent --no-server --realtime`` limited to two cores
(``taskset -c CPUS``): frames arrive at their timestamps and the agent drops the ones
that came while it was busy. Reported: share of frames dropped, latency from a frame's
time to its reported pose (median, p95), reported-pose ATE, and the same sequence
unpaced (every frame tracked, no clock) for the ATE it should stay within 20 % of. The
machine is shared: the 1-minute load before and after each run is recorded.

Rendering is the simulated camera's work, not the agent's: a frame rendered on the fly
costs ~65-130 ms, more than a frame period, on the same two cores. So every frame is
rendered into the render cache before the paced run (``render_warm_s``: what that took;
~0 once cached), and the paced run's camera only reads them, as a live camera delivers
decoded images.

    .venv/bin/python bench/bench_realtime.py [--seqs MH01,MH02,MH03] [--cpus 0,1] [--repeat N]
        [--seed S] [--starts 0,1,2]

``--starts``: fly each sequence from each of these first frames, paced and unpaced. The
unpaced run is deterministic but not a fixed point: MH02 started 0-5 frames in gives
10.4-16.6 mm (README), so one start compares a paced run with one draw of that spread.
Over several starts the report also gives, per sequence, the mean paced ATE over the
mean unpaced one (``ate_vs_unpaced_mean``): what pacing itself costs.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from common import run_agent, synthetic_spec, table, write_report  # noqa: E402

from services.launcher import _hivemap_exe  # noqa: E402
from shared.trajectory import ate, read_tum  # noqa: E402


def warm(src: str) -> float:
    """Render every frame of ``src`` into the render cache (seconds it took)."""
    from services.agent.sources import open_source

    t = time.monotonic()
    s = open_source(src)
    if getattr(s, "cache", None) is None:
        raise SystemExit("the render cache is off (HIVEMAP_RENDER_CACHE=''): a paced run "
                         "would render on the agent's cores")  # fmt: skip
    for _ in s:
        pass
    return time.monotonic() - t


def fly(seq: str, frames: str, realtime: bool, cpus: str, seed: int = 0) -> dict:
    out = Path(tempfile.mkdtemp(prefix=f"hivemap-rt-{seq}-"))
    agent = f"rt-{seq}"
    src = synthetic_spec(seq, frames, seed)
    argv = _hivemap_exe() + ["agent", "--id", agent, "--source", src, "--no-server",
                             "--out", str(out)] + (["--realtime"] if realtime else [])  # fmt: skip
    if cpus:
        argv = ["taskset", "-c", cpus] + argv
    warm_s = warm(src)
    load0 = os.getloadavg()[0]
    st, gt = run_agent(argv, out, agent)
    a = ate(read_tum(out / f"{agent}_online.tum"), gt)
    n = st["frames"] + st["dropped_frames"]
    return {
        "seq": seq, "seed": seed, "realtime": realtime, "frames": st["frames"],
        "dropped": st["dropped_frames"], "dropped_pct": 100.0 * st["dropped_frames"] / n,
        "latency_ms_median": 1e3 * st["latency_s_median"],
        "latency_ms_p95": 1e3 * st["latency_s_p95"],
        "track_ms_median": 1e3 * st["track_s_median"], "keyframes": st["keyframes"],
        "longest_lost_s": st["longest_lost_s"],
        "local_ba_aborted": st["vo"].get("local_ba_aborted", 0),
        "ate_m": a.rmse, "ate_pct": a.percent_of_path,
        "load_before": load0, "load_after": os.getloadavg()[0], "render_warm_s": warm_s,
    }  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seqs", default="MH01,MH02,MH03")
    ap.add_argument("--frames", default="")
    ap.add_argument("--seed", type=int, default=0, help="the synthetic world's seed")
    ap.add_argument("--cpus", default="0,1", help="taskset CPU list ('' = no limit)")
    ap.add_argument("--name", default="realtime")
    ap.add_argument("--repeat", type=int, default=1, help="paced runs per sequence")
    ap.add_argument("--starts", default="", help="first frames to fly from (with no --frames)")
    args = ap.parse_args()
    if args.starts and args.frames:
        ap.error("--starts and --frames exclude each other")
    starts = [int(k) for k in args.starts.split(",")] if args.starts else [None]
    rows, means = [], []
    for seq in args.seqs.split(","):
        for k in starts:
            frames = args.frames if k is None else f"{k}:"
            # Paced runs differ (what is dropped, when each local BA comes back); the
            # unpaced run is deterministic (local BA inline), so it runs once.
            paced = [fly(seq, frames, True, args.cpus, args.seed) for _ in range(args.repeat)]
            unpaced = fly(seq, frames, False, args.cpus, args.seed)
            for r in paced + [unpaced]:
                r["start"] = k or 0
            for p in paced:
                p["ate_unpaced_m"] = unpaced["ate_m"]
                p["ate_vs_unpaced"] = p["ate_m"] / unpaced["ate_m"]
                print(json.dumps(p), file=sys.stderr, flush=True)
            rows += paced + [unpaced]
        mine = [r for r in rows if r["seq"] == seq]
        paced_m = float(np.mean([r["ate_m"] for r in mine if r["realtime"]]))
        unpaced_m = float(np.mean([r["ate_m"] for r in mine if not r["realtime"]]))
        means.append({"seq": seq, "starts": len(starts), "ate_paced_mean_m": paced_m,
                      "ate_unpaced_mean_m": unpaced_m,
                      "ate_vs_unpaced_mean": paced_m / unpaced_m})  # fmt: skip
    path = write_report(args.name, {"cpus": args.cpus, "rows": rows, "means": means})
    print(table([r for r in rows if r["realtime"]],
                ["seq", "start", "frames", "dropped", "dropped_pct", "latency_ms_median",
                 "latency_ms_p95", "local_ba_aborted", "ate_m", "ate_unpaced_m", "ate_vs_unpaced",
                 "load_before", "load_after"]))  # fmt: skip
    if len(starts) > 1:
        print(table(means, list(means[0])))
    print(f"written {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
