"""Mapper CPU per keyframe in one process, without transport (issue 18 item 1): N
simulated agents (the load ramp's: MH01-MH05 in one landmark world, seeds 0..N-1) fly
into ONE server map (each agent's local map placed by its first ground-truth pose, as a
merge would place it), their batches interleaved as they would arrive; the mapper's own
work per batch (registration, the Redis transaction, point fusion, a culling round per
group of GROUP_MAX batches, a feedback chunk per agent every FEEDBACK_EVERY batches of
it) runs on one thread against a real redis-server, and its CPU is timed per stage; the
keyframe events it would publish go through a place-recognition service in the same
process (timed apart: placerec's CPU per keyframe; ``--no-placerec`` to leave it out).
Deterministic: the same messages and the same order every run, so two commits compare
without the noise of the full stack's scheduling (the ramp's 8-agent step is the
end-to-end check).

    .venv/bin/python bench/bench_mapper_cpu.py [--agents 8] [--frames 0:1200]
        [--profile FILE.prof] [--name NAME]

Writes bench/results/NAME.json (default mapper_cpu.json).
"""

from __future__ import annotations

import argparse
import cProfile
import random
import sys
import time
import zlib
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy as np  # noqa: E402
from common import write_report  # noqa: E402

from services.agent.comm import CommModule  # noqa: E402
from services.agent.sim_agent import LandmarkWorld, SimAgent  # noqa: E402
from services.mapper.feedback import build_chunk  # noqa: E402
from services.mapper.service import GROUP_MAX, MapperService  # noqa: E402
from services.placerec.service import PlacerecService  # noqa: E402
from services.placerec.vocabulary import Vocabulary  # noqa: E402
from shared import keys  # noqa: E402
from shared.geometry import Sim3  # noqa: E402
from shared.messages import Ack  # noqa: E402
from shared.redis_server import RedisServer  # noqa: E402
from shared.settings import Settings  # noqa: E402
from shared.trajectory import SEQUENCES, Trajectory, load_euroc_gt  # noqa: E402

FEEDBACK_EVERY = 2  # an agent's batches per feedback chunk (~1 Hz at ~2.3 keyframes/s)


def flight(world, agent: str, seq: str, frames: slice, seed: int):
    """(payload, first ground-truth pose) of every batch a simulated agent sends, each
    acked as sent."""
    gt = load_euroc_gt(seq)
    gt = Trajectory(gt.stamps_ns[frames], gt.poses[frames])
    comm = CommModule(agent, rate_hz=1e9, session=zlib.crc32(agent.encode()))
    sim = SimAgent(gt, world, seed=seed)
    out, t = [], 0.0
    while not sim.done:
        kf = sim.step()[2]
        if kf is None:
            continue
        comm.add_keyframe(kf.kf)
        comm.add_map_points(kf.new_mps)
        msg = comm.next_message(t, 0, kf.kf.id)
        out.append(msg.encode())
        comm.on_ack(Ack(agent, "m", np.array([k.id for k in msg.new_kfs], np.int64),
                        msg.new_mps.ids.astype(np.int64), 0, 0), t)  # fmt: skip
        t += 1.0
    return out, gt.poses[0]


def run(n: int, frames: slice, profile: Path | None, placerec: bool = True) -> dict:
    world = LandmarkWorld(0)
    flights = {}
    for i in range(n):
        agent = f"r{n}-{i}"
        flights[agent] = flight(world, agent, SEQUENCES[i % len(SEQUENCES)], frames, i)
    # Interleaved: one batch of each agent in turn.
    order = []
    longest = max(len(f[0]) for f in flights.values())
    for k in range(longest):
        order += [(a, f[0][k]) for a, f in flights.items() if k < len(f[0])]
    stage = dict.fromkeys(("ingest", "store", "fuse", "cull", "feedback", "events"), 0.0)
    # Per group of batches (what a batch queued behind the group waits for), not only
    # the sums: the mapper's p95 latency is made of these.
    # (Keyframe events are only summed: they run with place recognition on alone.)
    per_group: dict[str, list[float]] = {k: [] for k in stage if k != "events"}
    t_group = 0.0
    # The mapper's CPU per keyframe over the flight, by tenths of the batches: the map
    # grows denser as agents fly over each other's places, and each keyframe costs more.
    per_batch = {k: np.zeros(len(order)) for k in stage if k != "events"}
    pr_s = 0.0
    matches = 0
    with RedisServer() as url:
        settings = Settings(redis_url=url)
        svc = MapperService(settings)
        pr = PlacerecService(settings, Vocabulary.load()) if placerec else None
        m = svc.settings.mapper
        first = next(iter(flights))
        for a, (_, T0) in flights.items():
            S = Sim3(T0[:3, :3].copy(), T0[:3, 3].copy(), 1.0)
            svc.handler(a, map_id=None if a == first else f"map-{first}", S_m_l=S)
        smap = svc.maps[f"map-{first}"]
        rng = random.Random(0)
        sent: dict[str, set] = {}
        count: dict[str, int] = {}
        prof = cProfile.Profile() if profile else None
        clock = time.process_time
        if prof:
            prof.enable()
        t_all = clock()
        group = []
        for j, (a, payload) in enumerate(order):
            t0 = clock()
            batch = svc.decode_kf(f"hivemap/agent/{a}/up/kf", payload)
            h = svc.handler(a)
            pre = h.undistorted(batch)
            group.append((h, batch, time.time_ns(), svc.ingest(h, batch, pre)))
            t1 = clock()
            stage["ingest"] += t1 - t0
            t_group += t1 - t0
            per_batch["ingest"][j] += t1 - t0
            if len(group) < GROUP_MAX and j + 1 < len(order):
                continue
            svc.store_and_ack(group)
            t2 = clock()
            stage["store"] += t2 - t1
            per_group["ingest"].append(t_group)
            per_group["store"].append(t2 - t1)
            t_group = 0.0
            agents = [g[0] for g in group]
            if pr is not None:
                evs = [svc.collab.kf_event(smap.map_id, kg).encode()
                       for g in group for kg in g[3].res.new_kfs]  # fmt: skip
                t5 = clock()
                stage["events"] += t5 - t2
                for ev in evs:
                    matches += len(pr.handle(keys.map_kf(smap.map_id), ev))
                pr_s += clock() - t5
                t2 = clock()
            group = []
            svc.fuse(smap)
            t3 = clock()
            stage["fuse"] += t3 - t2
            per_group["fuse"].append(t3 - t2)
            svc.cull(smap, rng)
            t4 = clock()
            stage["cull"] += t4 - t3
            per_group["cull"].append(t4 - t3)
            for h in agents:
                count[h.agent] = count.get(h.agent, 0) + 1
                if count[h.agent] % FEEDBACK_EVERY == 0:
                    chunk = build_chunk(h, m.feedback_k, sent.setdefault(h.agent, set()),
                                        time.time_ns(), svc.names,
                                        m.feedback_correction_kfs)  # fmt: skip
                    if chunk is not None:
                        chunk.encode()
            t6 = clock()
            stage["feedback"] += t6 - t4
            per_group["feedback"].append(t6 - t4)
            # Each stage of the group spread over its batches (the group ends at batch j).
            span = slice(j - len(agents) + 1, j + 1)
            for k in ("store", "fuse", "cull", "feedback"):
                per_batch[k][span] += per_group[k][-1] / len(agents)
        total = clock() - t_all - pr_s
        if prof:
            prof.disable()
            prof.dump_stats(str(profile))
        n_kf = len(order)
        inv = smap.check_invariants()
        out = {
            "agents": n,
            "frames": f"{frames.start}:{frames.stop}",
            "batches": n_kf,
            "keyframes_in_map": len(smap.kfs),
            "points_in_map": len(smap.mps),
            "invariants_ok": inv == [],
            "mapper_cpu_ms_per_kf": 1e3 * total / n_kf,
            "stage_ms_per_kf": {k: round(1e3 * v / n_kf, 3) for k, v in stage.items()},
            "stage_ms_per_group": {
                k: {
                    "p50": round(1e3 * float(np.median(v)), 2),
                    "p95": round(1e3 * float(np.percentile(v, 95)), 2),
                    "max": round(1e3 * max(v), 2),
                }
                for k, v in per_group.items()
                if v
            },
            "mapper_cpu_ms_per_kf_by_tenth": [
                round(1e3 * float(np.mean(part)), 2)
                for part in np.array_split(sum(per_batch.values()), 10)
            ],
            "stage_ms_per_kf_by_tenth": {
                k: [round(1e3 * float(np.mean(part)), 2) for part in np.array_split(v, 10)]
                for k, v in per_batch.items()
            },
            "placerec_cpu_ms_per_kf": 1e3 * pr_s / n_kf if pr is not None else None,
            "placerec_matches": matches,
        }
        svc.store.close()
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--agents", type=int, default=8)
    ap.add_argument("--frames", default="0:1200")
    ap.add_argument("--profile", type=Path, default=None, help="cProfile stats to FILE")
    ap.add_argument("--name", default="mapper_cpu")
    ap.add_argument("--no-placerec", action="store_true",
                    help="without place recognition on the keyframe events")  # fmt: skip
    args = ap.parse_args()
    a, _, b = args.frames.partition(":")
    out = run(args.agents, slice(int(a), int(b)), args.profile, not args.no_placerec)
    print(out)
    write_report(args.name, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
