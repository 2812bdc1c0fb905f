"""Load ramp (issue 18 item 1): the full stack (mapper, place recognition, optimizer) on
this machine against 1, 8, 16, 24, 32 simulated agents, one fresh stack per step.

Per step: the mapper's p95 (received -> stored + acked, pooled over the agents), the
agents' round-trip p95 (publish -> ack), traffic per agent, CPU per service (cores, from
/proc over the flight and flush), server CPU ms per keyframe (mapper + placerec +
optimizer, per keyframe the agents made) and what that makes in agents per core at the
simulated agents' keyframe rate; plus what the mapper shed under overload. The agents
run in one process of their own session at nice 10 (see shared.runtime.set_priority):
they stand for robots, and the figure is the server's.

    .venv/bin/python bench/bench_ramp.py [--counts 1,8,16,24,32] [--seconds 60]

Writes bench/results/ramp.json and ramp_latency.png (latency against agents).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy as np  # noqa: E402
from bench_mapper import AGENT_NICE, hist_quantile  # noqa: E402
from bench_scale import cpu_s  # noqa: E402
from common import mapper_metrics, stack_settings, table, write_report  # noqa: E402
from plots import latency_vs_team  # noqa: E402

from services.launcher import Stack, _hivemap_exe  # noqa: E402
from shared.runtime import set_priority  # noqa: E402
from shared.trajectory import SEQUENCES  # noqa: E402

SERVER = ("mapper", "placerec", "optimizer")
LAT = "hivemap_keyframe_latency_seconds"


def _pooled_quantile(metrics: dict[str, float], q: float) -> float:
    """Quantile of the mapper's latency histogram summed over its agents."""
    acc: dict[str, float] = {}
    for k, v in metrics.items():
        if k.startswith(f"{LAT}_bucket{{"):
            le = k.split('le="')[1].split('"')[0]
            acc[le] = acc.get(le, 0.0) + v
    pooled = {f'{LAT}_bucket{{all="1",le="{le}"}}': v for le, v in acc.items()}
    return hist_quantile(pooled, LAT, 'all="1"', q)


def run_step(n: int, seconds: float) -> dict:
    stack = Stack(stack_settings(log_level="WARNING"), env={"HIVEMAP_LOG_LEVEL": "WARNING"})
    stack.start(with_api=False)
    out = Path(tempfile.mkdtemp(prefix="hivemap-ramp-"))
    try:
        time.sleep(3)  # start-up (imports, vocabulary) is not per keyframe
        pids = {c.name: c.proc.pid for c in stack.children}
        pids["redis"] = stack.redis.proc.pid
        cpu0 = {k: cpu_s(p) for k, p in pids.items()}
        load0 = os.getloadavg()[0]
        env = {**os.environ, "HIVEMAP_ZENOH__CONNECT": json.dumps([stack.zenoh_endpoint]),
               "HIVEMAP_LOG_LEVEL": "WARNING"}  # fmt: skip
        trajs = ",".join(SEQUENCES) if n > 1 else SEQUENCES[0]  # one agent: one sequence
        argv = _hivemap_exe() + ["sim-agent", "--id", f"r{n}", "--count", str(n), "--traj",
                                 trajs, "--frames", f"0:{int(seconds * 20)}",
                                 "--flush-timeout", "60", "--out", str(out)]  # fmt: skip
        t0 = time.monotonic()
        p = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL, start_new_session=True,
                             preexec_fn=lambda: set_priority(AGENT_NICE))  # fmt: skip
        p.wait(seconds * 4 + 300)
        wall = time.monotonic() - t0
        cpu = {k: cpu_s(pid) - cpu0[k] for k, pid in pids.items()}
        load1 = os.getloadavg()[0]
        metrics = mapper_metrics(stack)
    finally:
        stack.stop()
    stats = [json.loads(f.read_text()) for f in sorted(out.glob("*_stats.json"))]
    if len(stats) != n:
        raise RuntimeError(f"{n} agents: {len(stats)} stats files in {out} (agents failed?)")
    kfs = sum(s["keyframes"] for s in stats)
    lats = np.array([x[1] for s in stats for x in s.get("ack_series", [])] or [np.nan])
    server_cpu = sum(cpu.get(k, 0.0) for k in SERVER)
    flight = float(np.mean([s["flight_s"] for s in stats]))
    kf_rate = kfs / max(flight, 1e-9) / max(n, 1)  # keyframes per second per agent
    ms_per_kf = 1e3 * server_cpu / max(kfs, 1)
    return {
        "agents": n,
        "keyframes": kfs,
        "kf_per_s_per_agent": kf_rate,
        "all_acked": sum(bool(s["all_acked"]) for s in stats),
        "kf_lost": sum(s.get("kf_lost_unacked", 0) for s in stats),
        "mapper_p95_ms": 1e3 * _pooled_quantile(metrics, 0.95),
        "mapper_median_ms": 1e3 * _pooled_quantile(metrics, 0.5),
        "p95_ms": float(np.nanpercentile(lats, 95) * 1e3),
        "rt_median_ms": float(np.nanmedian(lats) * 1e3),
        "kB_per_s_per_agent": float(np.mean([s["bytes_per_s"] for s in stats]) / 1e3),
        "kB_per_s_per_agent_max": float(max(s["bytes_per_s"] for s in stats) / 1e3),
        "kf_resent": sum(s["kf_resent"] for s in stats),
        "cpu_cores": {k: round(v / wall, 3) for k, v in cpu.items()},
        "server_cpu_ms_per_kf": ms_per_kf,
        # At these agents' keyframe rate, one core of server CPU serves this many agents.
        "agents_per_core": 1e3 / (ms_per_kf * kf_rate) if kf_rate > 0 else float("nan"),
        "shed": {
            k.split('"')[1]: v
            for k, v in metrics.items()
            if k.startswith("hivemap_mapper_shed_total{")
        },  # fmt: skip
        "wall_s": wall,
        "flight_s": flight,
        "loadavg_1m_before_after": [load0, load1],
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--counts", default="1,8,16,24,32")
    ap.add_argument("--seconds", type=float, default=60.0, help="flight per agent")
    ap.add_argument("--name", default="ramp")
    args = ap.parse_args()
    rows = []
    for n in (int(x) for x in args.counts.split(",")):
        print(f"{n} agent(s) ...", flush=True)
        rows.append(run_step(n, args.seconds))
        r = rows[-1]
        print(f"  mapper p95 {r['mapper_p95_ms']:.0f} ms, round trip p95 {r['p95_ms']:.0f} ms, "
              f"{r['kB_per_s_per_agent']:.0f} kB/s/agent, {r['server_cpu_ms_per_kf']:.1f} "
              f"server CPU ms/kf, cores {r['cpu_cores']}", flush=True)  # fmt: skip
    print(
        table(
            rows,
            [
                "agents",
                "keyframes",
                "mapper_p95_ms",
                "p95_ms",
                "kB_per_s_per_agent",
                "server_cpu_ms_per_kf",
                "agents_per_core",
                "all_acked",
                "kf_lost",
            ],
        )
    )
    report = {
        "ramp": rows,
        "seconds": args.seconds,
        "bar": {"mapper_p95_ms_at_24": next((r["mapper_p95_ms"] for r in rows
                                             if r["agents"] == 24), None),
                "pass_24": all(r["mapper_p95_ms"] <= 200 for r in rows if r["agents"] <= 24),
                "pass_32": all(r["mapper_p95_ms"] <= 200 for r in rows if r["agents"] <= 32)},
    }  # fmt: skip
    path = write_report(args.name, report)
    print(f"written {path}")
    print(
        "plot",
        latency_vs_team(
            rows,
            path.with_name(f"{args.name}_latency.png"),
            "Keyframe latency against agents (placerec + optimizer on)",
        ),
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
