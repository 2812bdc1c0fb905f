"""The agent in flight (issue 17 items 2 and 6): single agents, fast and blurred.

For each sequence x frame step (``every``) x camera (sharp, or motion blur with the
shutter open half the frame interval plus auto-exposure jumps) x server (``--no-server``
or a `hivemap up` stack): one real agent (`hivemap agent --source synthetic:...`). Per
run, on the agent's reported pose (``*_online.tum``, the VO through the server's
correction) and on its raw VO (``*_vo.tum``):

- ATE after Sim(3) alignment (evo's ``evo_ape -as``), in metres and % of the path;
- longest time lost in a row (s) and frames lost;
- jumps: the change of the aligned position error from one reported frame to the next
  (what the drone would see as a teleport; a fast but true motion is not a jump).
  Counted over 5 cm and 10 cm, only where the VO's own error does not jump by as much
  at that frame (``jumps_*``), and the largest reported jump of all (``max_jump_m``);
- with a server: how many server maps the agent was in (one map: ``maps`` = 1).

    .venv/bin/python bench/bench_flight.py [--seqs MH03,MH04,MH05] [--every 1,2,3]
        [--cameras sharp,blur] [--server off,on] [--frames 0:1500] [--seed 0]
        [--name flight]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from common import run_agent, stack_settings, table, write_report  # noqa: E402

from services.launcher import Stack, _hivemap_exe  # noqa: E402
from shared.geometry import umeyama  # noqa: E402
from shared.trajectory import Trajectory, associate, ate, read_tum  # noqa: E402

CAMERAS = {"sharp": "", "blur": "blur=0.5&exposure=1"}


def aligned_errors(est: Trajectory, gt: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """Stamps and position error vectors of ``est`` after Sim(3) alignment to ``gt``."""
    ie, ig = associate(est, gt)
    S = umeyama(est.positions[ie], gt.positions[ig], with_scale=True)
    return est.stamps_ns[ie], S.apply(est.positions[ie]) - gt.positions[ig]


def jumps(est: Trajectory, gt: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """Per reported frame (after the first): stamp and the change of its aligned error."""
    st, e = aligned_errors(est, gt)
    return st[1:], np.linalg.norm(np.diff(e, axis=0), axis=1)


def flight_metrics(online: Trajectory, vo: Trajectory | None, gt: Trajectory) -> dict:
    a = ate(online, gt)
    st, j = jumps(online, gt)
    own = np.ones(len(j), bool)  # jumps the VO does not have at the same frame
    vj = None
    if vo is not None:
        vst, vj_all = jumps(vo, gt)
        at = dict(zip(vst.tolist(), vj_all.tolist(), strict=True))
        vj = np.array([at.get(s, 0.0) for s in st.tolist()])
    out = {"path_m": a.path_length, "ate_m": a.rmse, "ate_pct": a.percent_of_path,
           "max_jump_m": float(j.max()) if len(j) else 0.0}  # fmt: skip
    for cm in (5, 10):
        thr = cm / 100
        if vj is not None:
            own = vj <= thr
        big = (j > thr) & own
        out[f"jumps_{cm}cm"] = int(big.sum())
        out[f"max_own_jump_{cm}cm_m"] = float(j[big].max()) if big.any() else 0.0
    if vo is not None:
        av = ate(vo, gt)
        out["vo_ate_m"], out["vo_ate_pct"] = av.rmse, av.percent_of_path
        out["vo_max_jump_m"] = float(vj_all.max()) if len(vj_all) else 0.0
    return out


def run(seq: str, every: int, camera: str, server: bool, frames: str, seed: int) -> dict:
    q = [f"seed={seed}", f"every={every}"] + ([f"frames={frames}"] if frames else [])
    q += [CAMERAS[camera]] if CAMERAS[camera] else []
    src = f"synthetic:{seq}?{'&'.join(q)}"
    out = Path(tempfile.mkdtemp(prefix=f"hivemap-flight-{seq}-"))
    agent = f"fl-{seq.lower()}"
    argv = _hivemap_exe() + ["agent", "--id", agent, "--source", src, "--out", str(out)]
    stack = None
    t0 = time.monotonic()
    try:
        if server:
            stack = Stack(stack_settings())
            stack.start(with_api=False)
            argv += ["--server", stack.zenoh_endpoint]
        else:
            argv += ["--no-server"]
        st, gt = run_agent(argv, out, agent)
    finally:
        if stack is not None:
            stack.stop()
    online = read_tum(out / f"{agent}_online.tum")
    vo = read_tum(out / f"{agent}_vo.tum") if server else None
    row = {"seq": seq, "every": every, "camera": camera, "server": server, "seed": seed,
           "frames": st["frames"], **flight_metrics(online, vo, gt),
           "longest_lost_s": st["longest_lost_s"], "lost_frames": st["lost_frames"],
           "keyframes": st["keyframes"], "track_ms_median": 1e3 * st["track_s_median"],
           "maps": len(st.get("server_maps", [])) if server else None,
           "corrections": st.get("corrections"), "seconds": time.monotonic() - t0,
           "out": str(out)}  # fmt: skip
    return row


COLS = ["seq", "every", "camera", "server", "frames", "path_m", "ate_m", "ate_pct", "vo_ate_m",
        "longest_lost_s", "lost_frames", "jumps_5cm", "jumps_10cm", "max_own_jump_10cm_m",
        "max_jump_m", "maps"]  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seqs", default="MH03,MH04,MH05")
    ap.add_argument("--every", default="1,2,3")
    ap.add_argument("--cameras", default="sharp,blur")
    ap.add_argument("--server", default="off,on")
    ap.add_argument("--frames", default="")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--name", default="flight")
    args = ap.parse_args()
    rows = []
    for server in args.server.split(","):
        for camera in args.cameras.split(","):
            for every in (int(e) for e in args.every.split(",")):
                for seq in args.seqs.split(","):
                    rows.append(run(seq, every, camera, server == "on", args.frames, args.seed))
                    print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
                    # Written after every run: a long bench that stops early keeps its rows.
                    path = write_report(args.name, {"frames": args.frames, "seed": args.seed,
                                                    "rows": rows})  # fmt: skip
    print(table(rows, COLS))
    print(f"written {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
