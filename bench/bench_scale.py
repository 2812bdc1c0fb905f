"""Scale-out (issue 20 item 7, for the pools): per-instance CPU per keyframe with one
placerec and one optimizer, then with two of each, for the same simulated team, so the
ratio shows how far the work splits. Each instance's CPU is read from /proc (user +
system seconds of its process) from when the agents start to the end of the run;
keyframes are those the place recognizers took in.

    .venv/bin/python bench/bench_scale.py [--agents 6] [--frames 900:1500] [--speed 2]

Mappers (issue 20 items 1 and 7): ``--teams`` runs three teams of ``--per-team``
simulated agents in three worlds, first with one mapper, then with three mappers and two
placerecs (``--mappers 1,3``; ``--repeat N`` runs each N times, for the run-to-run
spread), and reports per mapper instance its CPU, keyframes, maps, hand-overs and
takeovers, and per team its map and joint ATE.

    .venv/bin/python bench/bench_scale.py --teams --per-team 4 --frames 900:1500 --speed 2
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
import urllib.request
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import stack_settings, table, write_report  # noqa: E402
from prometheus_client.parser import text_string_to_metric_families  # noqa: E402

from services.launcher import Scale, Stack, service_plan  # noqa: E402
from shared.jobs import JobQueue  # noqa: E402
from shared.store import Store, connect  # noqa: E402

TICK = os.sysconf("SC_CLK_TCK")


def cpu_s(pid: int) -> float:
    f = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    return (int(f[11]) + int(f[12])) / TICK  # utime, stime (fields 14, 15)


def metric(port: int, name: str, labels: dict[str, str]) -> float:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as r:
        text = r.read().decode()
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            if s.name == name and s.labels == labels:
                return s.value
    return 0.0


@contextlib.contextmanager
def _stack(scale: Scale):
    """The stack at ``scale``, quiet, once started, with each process's CPU seconds then
    (the processes' start, imports and vocabulary, is not per keyframe); stopped after."""
    stack = Stack(stack_settings(log_level="WARNING"), env={"HIVEMAP_LOG_LEVEL": "WARNING"},
                  scale=scale)  # fmt: skip
    stack.start()
    try:
        time.sleep(3)
        yield stack, {c.name: cpu_s(c.proc.pid) for c in stack.children}
    finally:
        stack.stop()


def run(scale: Scale, agents: int, frames: str, speed: float) -> list[dict]:
    with _stack(scale) as (stack, cpu0):
        stack.add("sim-agents", ["sim-agent", "--id", "team", "--count", str(agents),
                                 "--traj", "MH01,MH02,MH03", "--frames", frames,
                                 "--speed", str(speed), "--flush-timeout", "30"],
                  env={"HIVEMAP_LOG_LEVEL": "WARNING"})  # fmt: skip
        t0 = time.monotonic()
        (agents_proc,) = [c.proc for c in stack.children if c.name == "sim-agents"]
        agents_proc.wait(900)
        flight_s = time.monotonic() - t0
        plan = {p.name: p for p in service_plan(stack.settings, scale)}
        pr = [n for n in plan if n.startswith("placerec")]

        def seen() -> float:
            return max(metric(plan[n].http_port, "hivemap_placerec_keyframes_total",
                              {"role": "stored"}) +
                       metric(plan[n].http_port, "hivemap_placerec_keyframes_total",
                              {"role": "queried"}) for n in pr)  # fmt: skip

        # Let place recognition and optimization drain what the team sent.
        last, still = -1.0, 0
        while still < 3:
            time.sleep(2)
            now = seen()
            still = still + 1 if now == last else 0
            last = now
        r = connect(stack.settings.redis_url)
        n_maps = len(Store(r).maps())
        taken = JobQueue(r).taken()
        r.close()
        rows = []
        for c in stack.children:
            if c.name not in plan or c.name == "api":
                continue
            port = plan[c.name].http_port
            row = {"scale": f"p{scale.placerecs}o{scale.optimizers}", "instance": c.name,
                   "cpu_s": cpu_s(c.proc.pid) - cpu0[c.name], "keyframes": last, "maps": n_maps,
                   "flight_s": flight_s}  # fmt: skip
            if c.name.startswith("placerec"):
                row["queried"] = metric(port, "hivemap_placerec_keyframes_total",
                                        {"role": "queried"})  # fmt: skip
            if c.name.startswith("optimizer"):
                row["jobs_done"] = metric(port, "hivemap_optimizer_jobs_total",
                                          {"outcome": "done"})  # fmt: skip
            row["cpu_ms_per_kf"] = 1e3 * row["cpu_s"] / max(last, 1)
            rows.append(row)
        rows.append({"scale": rows[0]["scale"], "instance": "(jobs taken per worker)",
                     "jobs_done": sorted(taken.values())})  # fmt: skip
        return rows


def run_teams(scale: Scale, per_team: int, frames: str, speed: float) -> dict:
    """Three teams of ``per_team`` simulated agents, each team in a world of its own
    (seeds 0, 1, 2) flying MH01-03 over the same hall: every team should end in one map.
    Per mapper instance: CPU from the agents' start, keyframes it stored, maps owned at
    the end, takeovers and hand-overs."""
    from services.team_cli import collect
    from shared.evaluation import evaluate_team

    with _stack(scale) as (stack, cpu0):
        for k in range(3):
            stack.add(f"team{k}", ["sim-agent", "--id", f"t{k}", "--count", str(per_team),
                                   "--traj", "MH01,MH02,MH03", "--frames", frames,
                                   "--world-seed", str(k), "--seed", str(10 * k),
                                   "--speed", str(speed), "--flush-timeout", "60"],
                      env={"HIVEMAP_LOG_LEVEL": "WARNING"})  # fmt: skip
        t0 = time.monotonic()
        for c in [c for c in stack.children if c.name.startswith("team")]:
            c.proc.wait(1800)
        flight_s = time.monotonic() - t0
        plan = {p.name: p for p in service_plan(stack.settings, scale)}
        r = connect(stack.settings.redis_url)
        store = Store(r)
        # Settle: merges and optimizations finish (the map count and keyframes stop moving).
        last, still = None, 0
        while still < 3:
            time.sleep(3)
            now = (tuple(store.maps()), sum(len(store.keyframe_ids(a)) for a in store.agents()))
            still = still + 1 if now == last else 0
            last = now
        maps = store.maps()
        kfs = {m: (store.map_info(m) or {}).get("n_kf", 0) for m in maps}
        evals = evaluate_team(collect(stack.settings.redis_url))
        r.close()
        mappers = []
        for c in stack.children:
            if not c.name.startswith("mapper"):
                continue
            port = plan[c.name].http_port
            mappers.append({
                "instance": c.name, "cpu_s": cpu_s(c.proc.pid) - cpu0[c.name],
                "keyframes": metric(port, "hivemap_stored_total",
                                    {"service": "mapper", "kind": "keyframe"}),
                "maps_owned": metric(port, "hivemap_mapper_maps_owned", {}),
                "takeovers": metric(port, "hivemap_mapper_takeovers", {}),
                "handovers": metric(port, "hivemap_mapper_handovers", {}),
            })  # fmt: skip
        for m in mappers:
            m["cpu_ms_per_kf"] = 1e3 * m["cpu_s"] / max(m["keyframes"], 1)
        return {
            "scale": f"m{scale.mappers}p{scale.placerecs}", "flight_s": flight_s,
            "maps": len(maps), "map_keyframes": kfs,
            "teams": [{"map": e.map_id, "agents": len(e.agents),
                       "joint_ate_mm": 1e3 * e.joint_ate_m} for e in evals],
            "mappers": mappers,
        }  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--agents", type=int, default=6)
    ap.add_argument("--frames", default="900:1500")
    ap.add_argument("--speed", type=float, default=2.0)
    ap.add_argument("--name", default="scale_pools")
    ap.add_argument(
        "--teams",
        action="store_true",
        help="three teams of --per-team agents, 1 mapper vs 3 mappers + 2 placerecs",
    )
    ap.add_argument("--per-team", type=int, default=4)
    ap.add_argument("--mappers", default="1,3",
                    help="with --teams: the runs, by mappers (1: one of each; 3: three "
                         "mappers + 2 placerecs)")  # fmt: skip
    ap.add_argument("--repeat", type=int, default=1,
                    help="with --teams: each run this many times (run-to-run spread)")  # fmt: skip
    args = ap.parse_args()
    load0 = os.getloadavg()
    if args.teams:
        scales = {1: Scale(1, 1, 1), 3: Scale(3, 2, 1)}
        runs = [run_teams(scales[int(m)], args.per_team, args.frames, args.speed)
                for m in args.mappers.split(",") for _ in range(args.repeat)]  # fmt: skip
        rows = [{"scale": r["scale"], **m} for r in runs for m in r["mappers"]]
        print(table(rows, ["scale", "instance", "cpu_s", "keyframes", "cpu_ms_per_kf",
                           "maps_owned", "takeovers", "handovers"]))  # fmt: skip
        for r in runs:
            print(r["scale"], "maps", r["maps"], r["map_keyframes"], "teams", r["teams"])
        doc = {"args": vars(args), "loadavg_before": load0, "loadavg_after": os.getloadavg(),
               "runs": runs}  # fmt: skip
        path = write_report(args.name, doc)
        print(f"wrote {path}")
        return 0
    rows = []
    for scale in (Scale(1, 1, 1), Scale(1, 2, 2)):
        rows += run(scale, args.agents, args.frames, args.speed)
    cols = ["scale", "instance", "cpu_s", "cpu_ms_per_kf", "keyframes", "queried",
            "jobs_done", "maps", "flight_s"]  # fmt: skip
    print(table(rows, cols))
    path = write_report(args.name, {"args": vars(args), "loadavg_before": load0,
                                    "loadavg_after": os.getloadavg(), "rows": rows})  # fmt: skip
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
