"""Load ramp (issue 18 item 1): the full stack (mapper, place recognition, optimizer) on
this machine against 1, 8, 16, 24, 32 simulated agents, one fresh stack per step.

Per step: the mapper's p95 (received -> stored + acked, pooled over the agents), the
agents' round-trip p95 (publish -> ack), traffic per agent, CPU per service (cores, from
/proc over the flight and flush), server CPU ms per keyframe (mapper + placerec +
optimizer, per keyframe the agents made) and what that makes in agents per core at the
simulated agents' keyframe rate; plus what the mapper shed under overload. The agents
run in processes of their own session at nice 10, four agents per process (see
shared.runtime.set_priority and services/agent/sim_cli.py): they stand for robots, and
the figure is the server's. Each step says how far behind real time the agents fell
(a step whose agents fell behind offered less load than its count says), the CPU
their processes used and how long they waited for a core.

    .venv/bin/python bench/bench_ramp.py [--counts 1,8,16,24,32] [--seconds 60]

Writes bench/results/ramp.json and ramp_latency.png (latency against agents).

Overload (issue 18 item 2), one command:

    .venv/bin/python bench/bench_ramp.py --overload [--counts 8,48] [--seconds 120]

runs 8 and then 48 agents and checks: no service died; each of the first 8 agents'
traffic in the 48-agent run is at most 1.3x the same agent's (same trajectory and seed)
in the 8-agent run; the p95 latency of the keyframes the mapper accepted is at most 1 s;
and within 60 s of the end of their flights every keyframe the agents made is stored
(in Redis, or culled as redundant) and acknowledged. Writes bench/results/overload.json.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy as np  # noqa: E402
from bench_mapper import AGENT_NICE, pooled_quantile  # noqa: E402
from bench_scale import cpu_s  # noqa: E402
from common import LAT, ProcWatch, mapper_metrics, stack_settings, table, write_report  # noqa: E402
from plots import latency_vs_team  # noqa: E402

from services.launcher import Stack, _hivemap_exe  # noqa: E402
from shared.runtime import set_priority  # noqa: E402
from shared.store import Store, connect  # noqa: E402
from shared.trajectory import SEQUENCES  # noqa: E402

SERVER = ("mapper", "placerec", "optimizer")


def _mean_ms(metrics: dict[str, float], name: str, labels: str) -> float:
    n = metrics.get(f"{name}_count{{{labels}}}", 0.0)
    return 1e3 * metrics.get(f"{name}_sum{{{labels}}}", 0.0) / n if n else float("nan")


def _holds_over(metrics: dict[str, float], s: float) -> float:
    """Holds of a map's lock longer than ``s`` (a bucket bound of the histogram)."""
    name = "hivemap_map_lock_hold_seconds"
    le = metrics.get(f'{name}_bucket{{le="{s}"}}')
    return metrics.get(f"{name}_count", 0.0) - le if le is not None else float("nan")


def _profilers(
    pids: dict[str, int], seconds: float, out: Path, start_s: float = 0.0
) -> list[subprocess.Popen]:
    """py-spy samplers on the server's services (and, given as "agents", the simulated
    agents' processes) for ``seconds`` (collapsed stacks, one file per process; the rate
    is low so the sampler's own CPU stays small). The agents' processes are sampled with
    their idle threads too (``--idle``): where an agent waits tells why it falls behind."""
    spy = Path(sys.executable).with_name("py-spy")
    if not spy.exists():
        raise SystemExit("--profile needs py-spy in the venv: .venv/bin/pip install py-spy")
    out.mkdir(parents=True, exist_ok=True)
    # From ``start_s`` into the step on (its late part, when every agent is airborne and
    # the merged map dense, is where the latency tail is), to its end and the drain.
    delay = ["sh", "-c", f'sleep {start_s}; exec "$@"', "sh"] if start_s > 0 else []
    dur = int(seconds) if start_s <= 0 else int(seconds - start_s + 12)
    return [subprocess.Popen([*delay, str(spy), "record", "--pid", str(pids[name]), "--rate",
                              "50", "--nonblocking", "--format", "raw", "--duration",
                              str(dur), "--output", str(out / f"{name}.txt"),
                              *(["--idle", "--subprocesses"] if name == "agents" else [])],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            for name in (*SERVER, "agents") if name in pids]  # fmt: skip


# Leaf frames of a thread that waits (py-spy's idle test is unreliable with
# --nonblocking: these showed up as a third of the mapper's "busy" samples).
WAITING = ("Condition.wait ", "Event.wait ", "_PollLikeSelector.select ",
           "SocketBuffer._read_from_socket ", "MapRegistry.wait_for_batches ")  # fmt: skip


def top_of(path: Path, n: int = 25) -> str:
    """The ``n`` functions with most samples in a py-spy collapsed-stack file, by own
    samples and by samples with the function anywhere on the stack; samples of threads
    waiting (``WAITING``) are counted apart, and line numbers are dropped."""
    own: dict[str, int] = {}
    incl: dict[str, int] = {}
    total = waiting = 0
    for line in path.read_text().splitlines():
        stack, _, cnt = line.rpartition(" ")
        if not stack:
            continue
        c = int(cnt)
        frames = [re.sub(r":\d+\)$", ")", f) for f in stack.split(";")]
        if frames[-1].startswith(WAITING):
            waiting += c
            continue
        total += c
        own[frames[-1]] = own.get(frames[-1], 0) + c
        for f in set(frames):
            incl[f] = incl.get(f, 0) + c
    lines = [f"{path.stem}: {total} samples busy, {waiting} waiting"]
    for title, d in (("own", own), ("inclusive", incl)):
        lines.append(f"  by {title}:")
        for f, c in sorted(d.items(), key=lambda kv: -kv[1])[:n]:
            lines.append(f"    {100 * c / max(total, 1):5.1f} %  {f}")
    return "\n".join(lines)


class LatencyTimeline:
    """The mapper's keyframe latency histogram scraped every ``every`` seconds while a
    step runs: the p95 of each window tells whether a step's tail comes from a few
    episodes (the merges at the start, one long hold) or from the whole flight."""

    def __init__(self, stack, every: float = 5.0) -> None:
        self.stack, self.every = stack, every
        self.samples: list[tuple[float, dict[str, float]]] = []
        self._stop = threading.Event()
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.every):
            try:
                m = mapper_metrics(self.stack)
            except Exception:  # noqa: BLE001 - a missed scrape leaves a wider window
                continue
            self.samples.append((time.monotonic() - self._t0,
                                 {k: v for k, v in m.items() if k.startswith(LAT)}))  # fmt: skip

    def stop(self) -> list[dict]:
        """Per window: its end (s since the start), keyframes, p95 (ms)."""
        self._stop.set()
        self._thread.join(10)
        out, prev = [], {}
        for t, m in self.samples:
            diff = {k: v - prev.get(k, 0.0) for k, v in m.items()}
            cnt = sum(v for k, v in diff.items() if k.startswith(f"{LAT}_count"))
            if cnt > 0:
                p95 = 1e3 * pooled_quantile(diff, LAT, 0.95)
                out.append({"t_s": round(t, 1), "keyframes": int(cnt), "p95_ms": round(p95, 1)})
            prev = m
        return out


def run_step(
    n: int,
    seconds: float,
    profile: Path | None = None,
    profile_agents: bool = False,
    profile_from: float = 0.0,
) -> dict:
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
        timeline = LatencyTimeline(stack)
        p = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL, start_new_session=True,
                             preexec_fn=lambda: set_priority(AGENT_NICE))  # fmt: skip
        watch = ProcWatch(p.pid)
        server_watch = {k: ProcWatch(pids[k], 1.0, children=False) for k in SERVER if k in pids}
        prof = {**pids, "agents": p.pid} if profile_agents else pids
        spies = _profilers(prof, seconds, profile / f"{n}", profile_from) if profile else []
        p.wait(seconds * 4 + 300)
        agents_proc = watch.stop()
        server_proc = {k: w.stop() for k, w in server_watch.items()}
        for spy in spies:
            spy.wait(60)
        wall = time.monotonic() - t0
        cpu = {k: cpu_s(pid) - cpu0[k] for k, pid in pids.items()}
        load1 = os.getloadavg()[0]
        metrics = mapper_metrics(stack)
        windows = timeline.stop()
        # Services that exited during the run (nothing restarts them here).
        died = [c.name for c in stack.children if c.proc.poll() is not None]
        stats = [json.loads(f.read_text()) for f in sorted(out.glob("*_stats.json"))]
        if len(stats) != n:
            raise RuntimeError(f"{n} agents: {len(stats)} stats files in {out} (agents failed?)")
        # Every keyframe an agent made is in Redis: stored, or culled as redundant.
        store = Store(connect(stack.redis.url))
        not_stored = {s["agent"]: s["keyframes"] - len(set(store.keyframe_ids(s["agent"]))
                                                       | set(store.removed(s["agent"])))
                      for s in stats}  # fmt: skip
        store.close()
    finally:
        stack.stop()
    kfs = sum(s["keyframes"] for s in stats)
    lats = np.array([x[1] for s in stats for x in s.get("ack_series", [])] or [np.nan])
    server_cpu = sum(cpu.get(k, 0.0) for k in SERVER)
    flight = float(np.mean([s["flight_s"] for s in stats]))
    kf_rate = kfs / max(flight, 1e-9) / max(n, 1)  # keyframes per second per agent
    ms_per_kf = 1e3 * server_cpu / max(kfs, 1)

    def index(s: dict) -> int:
        return int(s["agent"].rpartition("-")[2]) if "-" in s["agent"] else 0

    return {
        "agents": n,
        "died": died,
        "keyframes_not_stored": sum(max(v, 0) for v in not_stored.values()),
        # From the end of each agent's flight to its exit (all acknowledged, or the
        # 60 s flush timeout): the longest over the agents.
        "after_flights_s": max(s["duration_s"] - s["flight_s"] for s in stats),
        "per_agent": [
            {
                "i": index(s),
                "traj": SEQUENCES[index(s) % len(SEQUENCES)],
                "keyframes": s["keyframes"],
                "kB_per_s": s["bytes_per_s"] / 1e3,
                "bytes_per_kf": s["bytes"] / max(s["keyframes"], 1),
                "all_acked": s["all_acked"],
                "kf_resent": s["kf_resent"],
            }
            for s in sorted(stats, key=index)
        ],  # fmt: skip
        "keyframes": kfs,
        "kf_per_s_per_agent": kf_rate,
        "all_acked": sum(bool(s["all_acked"]) for s in stats),
        "kf_lost": sum(s.get("kf_lost_unacked", 0) for s in stats),
        "mapper_p95_ms": 1e3 * pooled_quantile(metrics, LAT, 0.95),
        "mapper_p95_ms_by_window": windows,
        "mapper_median_ms": 1e3 * pooled_quantile(metrics, LAT, 0.5),
        "p95_ms": float(np.nanpercentile(lats, 95) * 1e3),
        "rt_median_ms": float(np.nanmedian(lats) * 1e3),
        "kB_per_s_per_agent": float(np.mean([s["bytes_per_s"] for s in stats]) / 1e3),
        "kB_per_s_per_agent_max": float(max(s["bytes_per_s"] for s in stats) / 1e3),
        "kf_resent": sum(s["kf_resent"] for s in stats),
        "cpu_cores": {k: round(v / wall, 3) for k, v in cpu.items()},
        "server_cpu_ms_per_kf": ms_per_kf,
        # At these agents' keyframe rate, one core of server CPU serves this many agents.
        "agents_per_core": 1e3 / (ms_per_kf * kf_rate) if kf_rate > 0 else float("nan"),
        # What a batch cost the map actor (registration and its share of the store), and
        # how often a map's lock was held longer than 200 ms (merges, corrections): the
        # rest of the mapper's latency is queueing (behind other batches, background work
        # and the GIL).
        "mapper_batch_ms_mean": _mean_ms(
            metrics, "hivemap_processing_seconds", 'kind="kf_batch",service="mapper"'
        ),
        "lock_holds_over_200ms": _holds_over(metrics, 0.2),
        # Full collections of the mapper's garbage collector (every thread stops).
        "mapper_gc_full": {
            "count": metrics.get('hivemap_gc_pause_seconds_count{generation="2"}', 0.0),
            "seconds": metrics.get('hivemap_gc_pause_seconds_sum{generation="2"}', 0.0),
        },
        # The maps at the end (merged ones report nothing): how many, and their size.
        "maps_at_end": sum(
            1 for k, v in metrics.items() if k.startswith("hivemap_map_keyframes{") and v > 0
        ),
        "map_keyframes_at_end": sum(
            v for k, v in metrics.items() if k.startswith("hivemap_map_keyframes{")
        ),
        "map_points_at_end": sum(
            v for k, v in metrics.items() if k.startswith("hivemap_map_points{")
        ),
        "shed": {
            k.split('"')[1]: v
            for k, v in metrics.items()
            if k.startswith("hivemap_mapper_shed_total{")
        },  # fmt: skip
        # Merges and loops applied (and loops found already tied): what the place
        # recognition brought to the mapper in this step.
        "matches": {
            k.split('"')[1]: v
            for k, v in metrics.items()
            if k.startswith("hivemap_matches_applied_total{")
        },  # fmt: skip
        "wall_s": wall,
        "flight_s": flight,
        # How far behind real time the simulated agents fell (a run that fell behind
        # offered less load than its agent count says): flight beyond its nominal
        # length (the trajectory's duration), worst agent, and the p95 of how late a
        # frame was stepped (worst agent).
        "behind_s_max": max(
            s["flight_s"] - s.get("nominal_flight_s", s["flight_s"]) for s in stats
        ),
        "frame_late_p95_ms_max": 1e3 * max(s.get("latency_s_p95", 0.0) for s in stats),
        # The agents' process: CPU it used (cores over the run) and how long its
        # threads were ready but waited for a core (seconds per second of run).
        "agents_process": {
            "cores": round(agents_proc["cpu_s"] / wall, 3),
            "runqueue_wait_per_s": round(agents_proc["runqueue_wait_s"] / wall, 3),
            "threads": agents_proc["threads"],
            "processes": agents_proc["processes"],
        },
        # The same run-queue wait for the server's services: CPU they were denied.
        "server_runqueue_wait_per_s": {
            k: round(v["runqueue_wait_s"] / wall, 3) for k, v in server_proc.items()
        },
        "loadavg_1m_before_after": [load0, load1],
    }


def overload_check(base: dict, big: dict) -> dict:
    """Issue 18 item 2 on a base run (8 agents) and an overloaded one (48)."""
    by_i = {a["i"]: a for a in base["per_agent"]}
    ratio = [{"i": a["i"], "kB_per_s": a["kB_per_s"] / by_i[a["i"]]["kB_per_s"],
              "bytes_per_kf": a["bytes_per_kf"] / by_i[a["i"]]["bytes_per_kf"]}
             for a in big["per_agent"]
             if a["i"] in by_i and by_i[a["i"]]["kB_per_s"] > 0]  # fmt: skip
    out = {
        "no_crash": not big["died"],
        "traffic_ratio_max": max((r["kB_per_s"] for r in ratio), default=float("nan")),
        "bytes_per_kf_ratio_max": max((r["bytes_per_kf"] for r in ratio), default=float("nan")),
        "traffic_ratio": ratio,
        "accepted_p95_ms": big["mapper_p95_ms"],
        "after_flights_s": big["after_flights_s"],
        "all_acked": big["all_acked"] == big["agents"],
        "keyframes_not_stored": big["keyframes_not_stored"],
    }
    out["pass"] = {
        "no_crash": out["no_crash"],
        "traffic": out["traffic_ratio_max"] <= 1.3,
        "accepted_p95": out["accepted_p95_ms"] <= 1000,
        "stored_and_acked_within_60s": out["all_acked"]
        and out["keyframes_not_stored"] == 0
        and out["after_flights_s"] <= 60,
    }
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--counts", default=None, help="1,8,16,24,32 (--overload: 8,48)")
    ap.add_argument("--seconds", type=float, default=None,
                    help="flight per agent (60; --overload: 120)")  # fmt: skip
    ap.add_argument("--name", default=None, help="ramp (--overload: overload)")
    ap.add_argument("--overload", action="store_true",
                    help="issue 18 item 2: the last count against the first")  # fmt: skip
    ap.add_argument("--profile", type=Path, default=None,
                    help="py-spy each server service over the flight; collapsed stacks "
                         "under DIR/<agents>/<service>.txt and a summary printed")  # fmt: skip
    ap.add_argument("--profile-agents", action="store_true",
                    help="with --profile, the simulated agents' processes too (idle threads "
                         "included; py-spy on tens of threads takes CPU the agents need: "
                         "at 16 agents they fell 120 s behind real time)")  # fmt: skip
    ap.add_argument("--profile-from", type=float, default=0.0,
                    help="with --profile, start sampling this many seconds into each step "
                         "(its dense, airborne end: --seconds 60 --profile-from 40)")  # fmt: skip
    args = ap.parse_args()
    ov = args.overload
    args.counts = args.counts or ("8,48" if ov else "1,8,16,24,32")
    args.seconds = args.seconds or (120.0 if ov else 60.0)
    args.name = args.name or ("overload" if ov else "ramp")
    rows = []
    for n in (int(x) for x in args.counts.split(",")):
        print(f"{n} agent(s) ...", flush=True)
        rows.append(run_step(n, args.seconds, args.profile, args.profile_agents, args.profile_from))
        if args.profile:
            for f in sorted((args.profile / str(n)).glob("*.txt")):
                print(top_of(f), flush=True)
        r = rows[-1]
        print(f"  mapper p95 {r['mapper_p95_ms']:.0f} ms, round trip p95 {r['p95_ms']:.0f} ms, "
              f"{r['kB_per_s_per_agent']:.0f} kB/s/agent, {r['server_cpu_ms_per_kf']:.1f} "
              f"server CPU ms/kf, cores {r['cpu_cores']}; agents behind real time by "
              f"{r['behind_s_max']:.1f} s (frames late p95 {r['frame_late_p95_ms_max']:.0f} "
              f"ms), agents' process {r['agents_process']}", flush=True)  # fmt: skip
        wins = r["mapper_p95_ms_by_window"]
        print("  mapper p95 by window: " + ", ".join(
            f"{w['t_s']:.0f}s {w['p95_ms']:.0f}" for w in wins))  # fmt: skip
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
    over = overload_check(rows[0], rows[-1]) if ov and len(rows) > 1 else None
    if over is not None:
        print("overload:", json.dumps({k: v for k, v in over.items() if k != "traffic_ratio"}))
    report = {
        "ramp": rows,
        "seconds": args.seconds,
        **({"overload": over} if over is not None else {}),
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
