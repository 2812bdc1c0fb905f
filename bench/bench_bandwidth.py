"""Agent -> server traffic without a server (agent issue 17, item 4): the real VO and its
communication module on a rendered sequence, every message encoded as it would go on
the wire (compact form) and acknowledged at once, so the bytes are what the agent
sends with a loss-free link and no resends. Per sequence: kB per second of flight and
per keyframe, and what they are made of (keypoints, new points, point updates,
keyframe updates); the full (uncompact) encoding of the same messages beside it.
Deterministic (offline VO, inline local BA). The traffic with a real server, and the
server's ATE, come from ``bench_vo.py``.

    .venv/bin/python bench/bench_bandwidth.py [--seqs MH01,MH02,MH03] [--frames A:B]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from common import table, write_report  # noqa: E402

from services.agent.comm import CommModule  # noqa: E402
from services.agent.loop import AgentStats, Frame  # noqa: E402
from services.agent.runner import VOProducer  # noqa: E402
from services.agent.sources import open_source  # noqa: E402
from shared.messages import Ack  # noqa: E402
from shared.settings import Settings  # noqa: E402


def run(seq: str, frames: str) -> dict:
    cv2.setNumThreads(1)
    settings = Settings()
    src = open_source(f"synthetic:{seq}" + (f"?frames={frames}" if frames else ""))
    prod = VOProducer(src, "bw", vo_params=settings.vo, mp_update_rel=settings.comm.mp_update_rel)
    comm = CommModule.from_settings("bw", settings.comm)
    prod.bind(comm, AgentStats("bw"))
    n = {"bytes": 0, "bytes_full": 0, "messages": 0, "keyframes": 0, "keypoints": 0,
         "new_points": 0, "point_updates": 0, "kf_updates": 0}  # fmt: skip

    def send(now: float) -> None:
        msg = comm.next_message(now, 0, max(prod._sent_kfs, default=-1))
        if msg is None:
            return
        n["bytes"] += len(msg.encode(compact=True))
        n["bytes_full"] += len(msg.encode())
        n["messages"] += 1
        n["keyframes"] += len(msg.new_kfs)
        n["keypoints"] += sum(len(k.keypoints) for k in msg.new_kfs)
        n["new_points"] += len(msg.new_mps)
        n["point_updates"] += len(msg.mp_updates)
        n["kf_updates"] += len(msg.kf_updates)
        kfs = np.array([k.id for k in msg.new_kfs], np.int64)
        comm.on_ack(Ack("bw", "m", kfs, msg.new_mps.ids.copy(), -1, 0), now)

    t0 = now = None
    for f in src:
        t0 = f.stamp_ns if t0 is None else t0
        now = (f.stamp_ns - t0) * 1e-9
        prod.step(Frame(f.stamp_ns, f.image))
        send(now)
    prod.finish()
    for i in range(100):
        send(now + 1 + 0.5 * i)
    flight = (src.ground_truth.stamps_ns[-1] - src.ground_truth.stamps_ns[0]) * 1e-9
    kfs = max(1, n["keyframes"])
    return {
        "seq": seq, "frames": len(src), "flight_s": flight, **n,
        "kB_per_s": n["bytes"] / flight / 1e3, "kB_per_s_full_form": n["bytes_full"] / flight / 1e3,
        "kB_per_kf": n["bytes"] / kfs / 1e3, "keypoints_per_kf": n["keypoints"] / kfs,
    }  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seqs", default="MH01,MH02,MH03")
    ap.add_argument("--frames", default="")
    ap.add_argument("--name", default="bandwidth")
    args = ap.parse_args()
    rows = []
    for seq in args.seqs.split(","):
        rows.append(run(seq, args.frames))
        print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    path = write_report(args.name, {"frames": args.frames, "rows": rows})
    print(table(rows, ["seq", "frames", "keyframes", "kB_per_s", "kB_per_s_full_form",
                       "kB_per_kf", "keypoints_per_kf", "new_points", "point_updates",
                       "kf_updates"]))  # fmt: skip
    print(f"written {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
