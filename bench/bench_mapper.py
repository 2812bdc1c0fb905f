"""Server-mapping benchmark (server-mapping issue, items 2-4).

latency: the mapping stack (router, redis, mapper as `hivemap up` runs them; with
  --collab also placerec and optimizer) with 1 and then 8 simulated agents flying in
  real time (each at its own nominal keyframe rate); keyframe latency per agent,
  measured by the agent (publish -> ack, a superset of the mapper's received -> stored
  -> acked) and by the mapper. Use >= 120 s so the maps reach their full size.
scale: a simulated agent with 2 %/s scale drift on all of MH01, server trajectory
  ATE with the scale correction on and off.
redundancy: an agent that flies MH01 twice; keyframes culled and the ATE change.

    .venv/bin/python bench/bench_mapper.py [--seconds 120] [--collab]
        [--only latency|scale|redundancy]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import common  # noqa: E402
import numpy as np  # noqa: E402
from plots import TrafficSampler, latency_vs_team, traffic_over_time  # noqa: E402

from services import launcher  # noqa: E402
from services.launcher import Stack, _hivemap_exe  # noqa: E402
from shared.runtime import set_priority  # noqa: E402
from shared.trajectory import SEQUENCES, Trajectory, ate, load_euroc_gt  # noqa: E402

COLLAB = ("placerec", "optimizer")
AGENT_NICE = 10


def hist_quantile(metrics: dict[str, float], name: str, labels: str, q: float) -> float:
    """Quantile of a Prometheus histogram from its cumulative buckets (linear within the
    bucket, as PromQL's histogram_quantile)."""
    prefix = f"{name}_bucket{{{labels},le="
    b = sorted((float(k[len(prefix):].split('"')[1]), v) for k, v in metrics.items()
               if k.startswith(prefix))  # fmt: skip
    if not b or b[-1][1] == 0:
        return float("nan")
    rank = q * b[-1][1]
    lo_le, lo_n = 0.0, 0.0
    for le, n in b:
        if n >= rank:
            if le == float("inf"):
                return lo_le
            return lo_le + (le - lo_le) * (rank - lo_n) / max(n - lo_n, 1e-12)
        lo_le, lo_n = le, n
    return b[-1][0]


def pooled_quantile(metrics: dict[str, float], name: str, q: float) -> float:
    """Quantile of histogram ``name`` summed over all its label sets (every agent's
    keyframes together: the step figure issue 18's latency bar is set on)."""
    acc: dict[str, float] = {}
    for k, v in metrics.items():
        if k.startswith(f"{name}_bucket{{"):
            le = k.split('le="')[1].split('"')[0]
            acc[le] = acc.get(le, 0.0) + v
    pooled = {f'{name}_bucket{{all="1",le="{le}"}}': v for le, v in acc.items()}
    return hist_quantile(pooled, name, 'all="1"', q)


@contextlib.contextmanager
def _plan_without(names: tuple[str, ...]):
    """Start the stack without the named services (item 2 measures the mapper; place
    recognition and optimization are separate, horizontally scaled services)."""
    orig = launcher.service_plan
    launcher.service_plan = lambda s, scale=None: [x for x in orig(s, scale) if x.name not in names]
    try:
        yield
    finally:
        launcher.service_plan = orig


def _windows(series: list, w: float) -> list[float]:
    """p95 ack latency (ms) of the keyframes first sent in each w-second window."""
    if not series:
        return []
    a = np.array(series)
    idx = (a[:, 0] // w).astype(int)
    return [round(float(np.percentile(a[idx == i, 1], 95)) * 1e3, 1) if (idx == i).any()
            else float("nan") for i in range(idx.max() + 1)]  # fmt: skip


def run_latency(
    n_agents: int, seconds: float, collab: bool = False, traffic: dict | None = None
) -> list[dict]:
    settings = common.stack_settings()
    stack = Stack(settings)
    with _plan_without(() if collab else COLLAB):
        stack.start(with_api=False)
    services = [name for name, _ in stack.procs]
    load_before = os.getloadavg()
    out = Path(tempfile.mkdtemp(prefix="hivemap-bench-"))
    procs = []
    try:
        # All agents in one process (the load-test mode), as a fleet simulator runs.
        env = {**os.environ, "HIVEMAP_ZENOH__CONNECT": json.dumps([stack.zenoh_endpoint]),
               "HIVEMAP_LOG_LEVEL": "WARNING"}  # fmt: skip
        many = ["--id", f"a{n_agents}", "--count", str(n_agents), "--traj", ",".join(SEQUENCES)]
        argv = _hivemap_exe() + ["sim-agent"] + (
            many if n_agents > 1 else ["--id", "a1-0", "--traj", "MH01"]
        ) + ["--frames", f"0:{int(seconds * 20)}", "--out", str(out)]  # fmt: skip
        # The agents fly on robots in a deployment; here they share the server's 2 cores,
        # so they run at nice 10 as in bench_team.py (their own clocks still time acks).
        # (In a session of their own: see shared.runtime.set_priority.)
        p = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL, start_new_session=True,
                             preexec_fn=lambda: set_priority(AGENT_NICE))  # fmt: skip
        procs = [(f"a{n_agents}-{i}", SEQUENCES[i % 5], p) for i in range(n_agents)]
        sampler = TrafficSampler(f"http://127.0.0.1:{stack.settings.mapper_metrics_port}/metrics")
        common.wait_agents(procs, seconds, f"{n_agents} agent(s) flying")
        if traffic is not None:
            traffic[f"{n_agents} agent{'s' if n_agents > 1 else ''}"] = sampler.stop()
        else:
            sampler.stop()
        load_after = os.getloadavg()
        metrics = common.mapper_metrics(stack)
    finally:
        common.stop_agents(procs, stack)
    rows = []
    for agent, seq, _ in procs:
        st = common.agent_stats(out, agent)
        rows.append({
            "agents": n_agents, "agent": agent, "traj": seq, "keyframes": st["keyframes"],
            "all_acked": st["all_acked"], "kf_per_s": st["keyframes"] / st["flight_s"],
            "median_ms": 1e3 * st["ack_latency_median_s"],
            "p95_ms": 1e3 * st["ack_latency_p95_s"],
            "mapper_mean_ms": common.mapper_latency_mean_ms(metrics, agent),
            "mapper_median_ms": 1e3 * hist_quantile(
                metrics, common.LAT, f'agent="{agent}"', 0.5),
            "mapper_p95_ms": 1e3 * hist_quantile(
                metrics, common.LAT, f'agent="{agent}"', 0.95),
            "culled_total": sum(v for k, v in metrics.items()
                                if k.startswith("hivemap_keyframes_culled_total{")),
            "map_kfs": {k.split('"')[1]: v for k, v in metrics.items()
                        if k.startswith("hivemap_map_keyframes{") and v > 0},
            "lock_holds_over_200ms": metrics.get("hivemap_map_lock_hold_seconds_count", 0)
            - metrics.get('hivemap_map_lock_hold_seconds_bucket{le="0.2"}', 0),
            "agent_nice": AGENT_NICE,
            "p95_ms_per_10s": _windows(st.get("ack_series", []), 10.0),
            "bytes_per_s": st["bytes_per_s"], "flight_s": st["flight_s"],
            "services": services, "loadavg_1m_before_after": [load_before[0], load_after[0]],
        })  # fmt: skip
    return rows


def run_scale() -> dict:
    from feeding import feed_handler, server_traj

    from services.agent.sim_agent import DriftModel, LandmarkWorld, SimAgent
    from services.mapper.registration import AgentHandler, MapperParams
    from services.mapper.server_map import ServerMap

    gt = load_euroc_gt("MH01")
    world = LandmarkWorld(0)
    res = {}
    # As tests/test_server_map.py's scale-correction test: the simulated VO drifts while its
    # points stay true, so the scale filter is measured refining against its own points
    # (the mapper's default refines against settled points only).
    for on in (False, True):
        params = MapperParams(scale_correction=on, refine_settled_only=False)
        h = AgentHandler("A", 1, ServerMap("m"), params=params)
        vo = feed_handler(h, SimAgent(gt, world, drift=DriftModel(scale_drift_per_s=0.02), seed=2))
        res["on" if on else "off"] = ate(server_traj(h), gt).rmse
    res["vo"] = ate(vo, gt).rmse
    res["ratio_off_over_on"] = res["off"] / res["on"]
    res["pass"] = res["ratio_off_over_on"] >= 3
    return res


def run_redundancy() -> dict:
    from feeding import cull, feed_handler, server_traj, twice

    from services.agent.sim_agent import DriftModel, LandmarkWorld, SimAgent
    from services.mapper.registration import AgentHandler
    from services.mapper.server_map import ServerMap

    gt = load_euroc_gt("MH01")
    two = twice(gt, gt.stamps_ns[-1] - gt.stamps_ns[0] + 50_000_000)
    h = AgentHandler("A", 1, ServerMap("m"))
    feed_handler(h, SimAgent(two, LandmarkWorld(0), drift=DriftModel(), seed=5))
    stamps = {k.id: k.stamp_ns for k in h.smap.kfs.values()}
    before = ate(server_traj(h), two).rmse
    n0 = len(h.smap.kfs)
    cull(h, 3000)
    ids = sorted(stamps)
    full = Trajectory(np.array([stamps[i] for i in ids]), np.stack([h.kf_pose(i) for i in ids]))
    after = ate(full, two).rmse
    kept = ate(server_traj(h), two).rmse
    frac = 1 - len(h.smap.kfs) / n0
    change = abs(after - before) / before
    return {"keyframes": n0, "culled_fraction": frac, "ate_before": before, "ate_after": after,
            "ate_kept_only": kept, "ate_change": change,
            "pass": frac >= 0.10 and change <= 0.10}  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, default=120.0)
    ap.add_argument("--only", default="")
    ap.add_argument("--collab", action="store_true", help="also run placerec and optimizer")
    ap.add_argument("--counts", default="1,8", help="agent counts for the latency runs")
    args = ap.parse_args()
    report: dict = {}
    if args.only in ("", "latency"):
        counts = [int(x) for x in args.counts.split(",")]
        traffic: dict = {}
        rows = [r for n in counts for r in run_latency(n, args.seconds, args.collab, traffic)]
        report["latency"] = rows
        report["traffic"] = traffic
        report["latency_seconds"] = args.seconds
        print(common.table(rows, ["agents", "agent", "traj", "keyframes", "kf_per_s", "median_ms",
                           "p95_ms", "mapper_mean_ms", "mapper_p95_ms", "bytes_per_s",
                           "all_acked"]))  # fmt: skip
        loads = [r["loadavg_1m_before_after"] for r in rows if r["agent"].endswith("-0")]
        print("services:", rows[0]["services"], "load 1m before/after:", loads)
        one = [r for r in rows if r["agents"] == 1]
        eight = [r for r in rows if r["agents"] > 1]
        # The issue's latency is the mapper's: received -> registered, stored and acked
        # (its histogram). The agents' publish -> ack round trip is reported beside it;
        # it adds the network and, here, the simulated fleet's own process, which runs
        # at nice 10 on the server's two cores.
        report["latency_pass"] = {
            "one_agent": all(r["mapper_median_ms"] <= 30 and r["mapper_p95_ms"] <= 100
                             for r in one),
            "eight_agents_mapper_p95_max_ms": max((r["mapper_p95_ms"] for r in eight),
                                                  default=None),
            "eight_agents": all(r["mapper_p95_ms"] <= 200 for r in eight),
            "one_agent_round_trip": all(r["median_ms"] <= 30 and r["p95_ms"] <= 100
                                        for r in one),
            "eight_agents_round_trip_p95_max_ms": max((r["p95_ms"] for r in eight),
                                                      default=None),
            "eight_agents_round_trip": all(r["p95_ms"] <= 200 for r in eight),
        }  # fmt: skip
        print(report["latency_pass"])
    if args.only in ("", "scale"):
        report["scale"] = run_scale()
        print("scale drift 2%/s:", report["scale"])
    if args.only in ("", "redundancy"):
        report["redundancy"] = run_redundancy()
        print("redundancy (MH01 twice):", report["redundancy"])
    name = "mapper" + (f"_{args.only}" if args.only else "") + ("_collab" if args.collab else "")
    path = common.write_report(name, report)
    print(f"written {path}")
    if report.get("latency"):
        print("plot", latency_vs_team(report["latency"], path.with_name(f"{name}_vs_team.png"),
                                      f"Keyframe latency against team size ({name})"))  # fmt: skip
        print("plot", traffic_over_time(report["traffic"], path.with_name(f"{name}_traffic.png"),
                                        f"Mapper traffic over time ({name})"))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
