"""How far a recorded run's final map holds given keyframe pairs from the truth.

For a loop the mapper logged as left unsatisfied or overruled ("loop Q-C after the
correction: ..."), this says whether the map or the loop's measurement was wrong: the
pair's relative pose in the last map state recorded (``HIVEMAP_FEEDBACK_DUMP``, see
bench/replay_feedback.py), in metres by the similarity of all recorded keyframes onto
the truth, against the same pair's relative pose in the ground truth::

    .venv/bin/python bench/loop_truth.py DUMP OUT 1099511627957-2199023255626 ...

(pairs as the log names them: keyframe gids; OUT: the run's output directory.)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import replay_feedback as rf  # noqa: E402

from shared.geometry import log_so3, se3_inv, umeyama  # noqa: E402
from shared.ids import agent_index_of, local_id_of  # noqa: E402
from shared.trajectory import read_tum  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dump")
    ap.add_argument("out")
    ap.add_argument("pairs", nargs="+", help="Q-C keyframe gids, as the mapper logs them")
    args = ap.parse_args()
    recorded = rf.runs(args.dump)
    last = {ag: [r for r in a["all_fcs"] if r["T_l"] is not None][-1] for ag, a in recorded.items()}
    gts = {ag: read_tum(Path(args.out) / f"{ag}_gt.tum") for ag in recorded}
    P = np.concatenate([r["T_m"][:, :3, 3] for r in last.values()])
    G = np.concatenate([rf.truth_at(gts[ag], r["stamps"])[:, :3, 3] for ag, r in last.items()])
    to_m = umeyama(P, G).s

    def pose(g: int) -> tuple[np.ndarray, np.ndarray]:
        ag = f"agent{int(agent_index_of(g))}"
        r = last[ag]
        i = int(np.nonzero(r["ids"] == int(local_id_of(g)))[0][0])
        return r["T_m"][i], rf.truth_at(gts[ag], r["stamps"][i : i + 1])[0]

    print(f"{'pair':>28} {'truth_m':>8} {'map_m':>7} {'rot_deg':>8} {'trans_mm':>9}")
    for pair in args.pairs:
        q, c = (int(x) for x in pair.split("-"))
        (Mq, Gq), (Mc, Gc) = pose(q), pose(c)
        rel_m, rel_t = se3_inv(Mq) @ Mc, se3_inv(Gq) @ Gc
        t_m = rel_m[:3, 3] * to_m
        rot = np.degrees(np.linalg.norm(log_so3(rel_m[:3, :3] @ rel_t[:3, :3].T)))
        print(f"{pair:>28} {np.linalg.norm(rel_t[:3, 3]):8.3f} {np.linalg.norm(t_m):7.3f} "
              f"{rot:8.2f} {1e3 * np.linalg.norm(t_m - rel_t[:3, 3]):9.1f}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
