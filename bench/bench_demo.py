"""Demo benchmark (issue #2, item 8): the `hivemap demo` stack with three simulated
agents on MH01-MH03 in real time; per agent the keyframe latency (agent publish ->
stored and acked, measured by the agent) and bytes/s on the wire.

    .venv/bin/python bench/bench_demo.py [--seconds 60] [--speed 1]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402

from services.launcher import Stack, _hivemap_exe  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, default=60.0, help="flight time per agent")
    ap.add_argument("--speed", type=float, default=1.0)
    args = ap.parse_args()
    frames = int(args.seconds * 20 * args.speed)
    settings = common.stack_settings()
    stack = Stack(settings)
    stack.start()
    out = Path(tempfile.mkdtemp(prefix="hivemap-bench-"))
    procs = []
    try:
        for i, seq in enumerate(["MH01", "MH02", "MH03"]):
            agent = f"agent{i + 1}"
            argv = _hivemap_exe() + [
                "sim-agent", "--id", agent, "--traj", seq, "--speed", str(args.speed),
                "--seed", str(i + 1), "--frames", f"0:{frames}", "--out", str(out),
            ]  # fmt: skip
            env = {**__import__("os").environ, "HIVEMAP_ZENOH__CONNECT": json.dumps(
                [stack.zenoh_endpoint]), "HIVEMAP_LOG_LEVEL": "WARNING"}  # fmt: skip
            procs.append((agent, seq, subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL)))
        common.wait_agents(procs, args.seconds / args.speed, "3 agents flying")
        metrics = common.mapper_metrics(stack)
    finally:
        common.stop_agents(procs, stack)
    rows = []
    for agent, seq, p in procs:
        st = common.agent_stats(out, agent)
        rows.append({
            "agent": agent, "traj": seq, "keyframes": st["keyframes"],
            "acked": st["acked_keyframes"], "all_acked": st["all_acked"],
            "latency_median_ms": 1e3 * st["ack_latency_median_s"],
            "latency_p95_ms": 1e3 * st["ack_latency_p95_s"],
            "server_latency_mean_ms": common.mapper_latency_mean_ms(metrics, agent),
            "bytes_per_s": st["bytes_per_s"], "messages": st["messages"],
            "exit": p.returncode,
        })  # fmt: skip
    report = {"seconds": args.seconds, "speed": args.speed, "agents": rows}
    path = common.write_report("demo", report)
    print(common.table(rows, ["agent", "traj", "keyframes", "acked", "latency_median_ms",
                       "latency_p95_ms", "server_latency_mean_ms", "bytes_per_s"]))  # fmt: skip
    print(f"written {path}")
    return 0 if all(r["all_acked"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
