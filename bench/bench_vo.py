"""Agent benchmark (on-board VO issue, items 1-3; server-mapping issue, items 1-2).

For each rendered sequence: the `hivemap up` stack (router, redis, mapper) and one
real agent (`hivemap agent --source synthetic:MHxx`) that runs its VO on every
frame and streams to the mapper. Reported: ATE of the online per-frame poses after
Sim(3) alignment (ours and evo's), longest time lost, tracking time per frame,
mapping time per keyframe, agent -> server bytes per second of flight, keyframe
latency (agent publish -> ack, and mapper received -> acked), and the server-map
keyframe trajectory ATE against the agent's own keyframe poses.

    .venv/bin/python bench/bench_vo.py [--seqs MH01,MH02,MH03] [--frames A:B] [--seed S]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import (  # noqa: E402
    mapper_latency_mean_ms,
    mapper_metrics,
    run_agent,
    stack_settings,
    synthetic_spec,
    table,
    write_report,
)

from services.launcher import Stack, _hivemap_exe  # noqa: E402
from services.team_cli import wait_settled  # noqa: E402
from shared.progress import track  # noqa: E402
from shared.store import Store, connect  # noqa: E402
from shared.trajectory import Trajectory, ate, read_tum  # noqa: E402


def evo_ate(est: Path, ref: Path) -> float | None:
    try:
        from evo.core import metrics, sync
        from evo.tools import file_interface
    except ImportError:
        return None
    r, e = file_interface.read_tum_trajectory_file(str(ref)), \
        file_interface.read_tum_trajectory_file(str(est))  # fmt: skip
    r, e = sync.associate_trajectories(r, e)
    e.align(r, correct_scale=True)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((r, e))
    return float(ape.get_statistic(metrics.StatisticsType.rmse))


def run_alone(seq: str, frames: str, seed: int = 0) -> dict:
    """The agent with no server at all (``--no-server``): on-board VO only."""
    out = Path(tempfile.mkdtemp(prefix=f"hivemap-vo-alone-{seq}-"))
    agent = f"vo-{seq}"
    src = synthetic_spec(seq, frames, seed)
    argv = _hivemap_exe() + ["agent", "--id", agent, "--source", src, "--no-server",
                             "--out", str(out)]  # fmt: skip
    st, gt = run_agent(argv, out, agent)
    online = read_tum(out / f"{agent}_online.tum")
    a_online = ate(online, gt)
    return {
        "seq": seq, "seed": seed, "server": False, "frames": st["frames"],
        "path_m": a_online.path_length,
        "ate_online_m": a_online.rmse, "ate_online_pct": a_online.percent_of_path,
        "ate_online_evo_m": evo_ate(out / f"{agent}_online.tum", out / f"{agent}_gt.tum"),
        "longest_lost_s": st["longest_lost_s"],
        "track_ms_median": 1e3 * st["track_s_median"], "track_ms_p95": 1e3 * st["track_s_p95"],
        "map_ms_per_kf": 1e3 * st["map_s_median"], "keyframes": st["keyframes"],
    }  # fmt: skip


def run(seq: str, frames: str, seed: int = 0) -> dict:
    settings = stack_settings()
    stack = Stack(settings)
    stack.start(with_api=False)
    out = Path(tempfile.mkdtemp(prefix=f"hivemap-vo-{seq}-"))
    agent = f"vo-{seq}"
    try:
        src = synthetic_spec(seq, frames, seed)
        argv = _hivemap_exe() + ["agent", "--id", agent, "--source", src,
                                 "--server", stack.zenoh_endpoint, "--out", str(out)]  # fmt: skip
        st, gt = run_agent(argv, out, agent)
        # The server's keyframes as the server leaves them: after the optimizations the
        # agent's last loops asked for (read at once, a run scored a map whose newest
        # keyframes no optimization had yet placed; see team_cli.wait_settled).
        t_settle = time.monotonic()
        wait_settled(stack, timeout=180.0)
        settle_s = time.monotonic() - t_settle
        metrics = mapper_metrics(stack)
        store = Store(connect(stack.settings.redis_url))
        ids, stamps, poses = store.trajectory(agent)
    finally:
        stack.stop()
    online = read_tum(out / f"{agent}_online.tum")  # the VO's poses through the correction
    kfs = read_tum(out / f"{agent}_keyframes.tum")
    a_online = ate(online, gt)
    a_vo = ate(read_tum(out / f"{agent}_vo.tum"), gt)
    a_kf = ate(kfs, gt)
    a_server = ate(Trajectory(stamps, poses), gt)
    flight_s = (gt.stamps_ns[-1] - gt.stamps_ns[0]) * 1e-9
    return {
        "seq": seq, "seed": seed, "frames": st["frames"], "path_m": a_online.path_length,
        "ate_online_m": a_online.rmse, "ate_online_pct": a_online.percent_of_path,
        "ate_online_evo_m": evo_ate(out / f"{agent}_online.tum", out / f"{agent}_gt.tum"),
        "ate_vo_m": a_vo.rmse, "longest_lost_s": st["longest_lost_s"],
        "track_ms_median": 1e3 * st["track_s_median"], "track_ms_p95": 1e3 * st["track_s_p95"],
        "map_ms_per_kf": 1e3 * st["map_s_median"], "keyframes": st["keyframes"],
        "bytes_per_s": st["bytes"] / flight_s,
        # All the agent sends: keyframe batches (with resends) and its live poses.
        "pose_bytes_per_s": st.get("pose_bytes", 0) / flight_s,
        "total_bytes_per_s": (st["bytes"] + st.get("pose_bytes", 0)) / flight_s,
        "kf_resent": st.get("kf_resent"), "mp_updates": st.get("mp_updates"),
        "ack_latency_median_ms": 1e3 * st["ack_latency_median_s"],
        "ack_latency_p95_ms": 1e3 * st["ack_latency_p95_s"],
        "mapper_latency_mean_ms": mapper_latency_mean_ms(metrics, agent, missing=None),
        "ate_agent_kf_m": a_kf.rmse, "ate_server_kf_m": a_server.rmse,
        "server_kfs": int(len(ids)), "server_settle_s": settle_s,
    }  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seqs", default="MH01,MH02,MH03")
    ap.add_argument("--frames", default="")
    ap.add_argument("--seed", type=int, default=0, help="the synthetic world's seed")
    ap.add_argument("--no-server", action="store_true", help="the agent alone (issue item 1-2)")
    ap.add_argument("--name", default="", help="results name (default: vo[_alone][_partial])")
    args = ap.parse_args()
    rows = []
    for seq in track(args.seqs.split(","), "sequences"):
        rows.append((run_alone if args.no_server else run)(seq, args.frames, args.seed))
        print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    name = args.name or (
        "vo" + ("_alone" if args.no_server else "") + ("_partial" if args.frames else "")
    )
    path = write_report(name, {"rows": rows})
    if args.no_server:
        print(table(rows, ["seq", "frames", "path_m", "ate_online_m", "ate_online_pct",
                           "ate_online_evo_m", "longest_lost_s", "track_ms_median",
                           "track_ms_p95", "map_ms_per_kf", "keyframes"]))  # fmt: skip
        print(f"written {path}")
        return 0
    print(table(rows, ["seq", "frames", "path_m", "ate_online_m", "ate_online_pct",
                       "ate_online_evo_m", "ate_vo_m", "longest_lost_s", "track_ms_median",
                       "track_ms_p95", "map_ms_per_kf", "bytes_per_s",
                       "total_bytes_per_s"]))  # fmt: skip
    print(table(rows, ["seq", "keyframes", "server_kfs", "ack_latency_median_ms",
                       "ack_latency_p95_ms", "mapper_latency_mean_ms", "ate_agent_kf_m",
                       "ate_server_kf_m"]))  # fmt: skip
    print(f"written {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
