"""How far registration places an agent's new keyframes from the truth, from a run
recorded with ``HIVEMAP_FEEDBACK_DUMP`` (the mapper's ``reg`` records: each keyframe's
pose chained from its predecessor, the pose refinement made of it, and ``lam``)::

    .venv/bin/python bench/registration_errors.py /tmp/dump agent1=MH01,agent2=MH02

Each record is scored in the frame of the agent's next recorded frame correction
(``fc``): its settled keyframes aligned to the ground truth (Sim(3)), the keyframe's
chained and refined positions compared with the truth at its stamp. Per agent and
10 s window of its flight: the median and largest error of both (mm), how far the
refinement moved it, how often a refinement was accepted and made it worse, the range
of ``lam``, and the alignment's own RMS (the settled map's error); then, over the
accepted refinements, the share that moved the keyframe closer to the truth.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from shared.feedback_dump import load  # noqa: E402
from shared.geometry import umeyama  # noqa: E402
from shared.trajectory import load_euroc_gt  # noqa: E402


def scored(recs: list[dict], agent: str, seq: str) -> np.ndarray:
    """Rows (t_s, chained_m, refined_m, moved_m, lam, accepted, settled_rms_m) of
    ``agent``'s registration records."""
    gt = load_euroc_gt(seq)

    def gt_at(st: np.ndarray) -> np.ndarray:
        i = np.clip(np.searchsorted(gt.stamps_ns, st), 0, len(gt) - 1)
        return gt.poses[i][..., :3, 3]

    regs = sorted((r for r in recs if r["who"] == "mapper" and r["kind"] == "reg"
                   and r["agent"] == agent), key=lambda r: r["wall_ns"])  # fmt: skip
    fcs = sorted((r for r in recs if r["who"] == "mapper" and r["kind"] == "fc"
                  and r["agent"] == agent and r["T_m"] is not None),
                 key=lambda r: r["wall_ns"])  # fmt: skip
    walls = np.array([r["wall_ns"] for r in fcs])
    frames: dict[int, tuple | None] = {}
    rows = []
    for r in regs:
        j = int(np.searchsorted(walls, r["wall_ns"]))
        if j >= len(fcs):
            continue
        if j not in frames:
            f = fcs[j]
            opt = f["optimized"]
            if opt.sum() < 8:
                frames[j] = None
            else:
                c, g = f["T_m"][opt, :3, 3], gt_at(f["stamps"][opt])
                S = umeyama(c, g, with_scale=True)
                frames[j] = (S, float(np.sqrt(np.mean(np.sum((S.apply(c) - g) ** 2, axis=1)))))
        if frames[j] is None:
            continue
        S, rms = frames[j]
        g = gt_at(np.array([r["stamp_ns"]]))[0]
        a = S.apply(r["T_init"][None, :3, 3])[0]
        b = S.apply(r["T"][None, :3, 3])[0]
        t = (r["stamp_ns"] - gt.stamps_ns[0]) * 1e-9
        rows.append((t, np.linalg.norm(a - g), np.linalg.norm(b - g), np.linalg.norm(b - a),
                     r["lam"], float(r["accepted"]), rms))  # fmt: skip
    return np.array(rows, float).reshape(-1, 7)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dump")
    ap.add_argument("agents", help="agent=SEQ pairs, comma-separated: agent1=MH01,agent2=MH02")
    args = ap.parse_args()
    recs = load(args.dump)
    for pair in args.agents.split(","):
        agent, seq = pair.split("=")
        A = scored(recs, agent, seq)
        if not len(A):
            print(f"{agent}: no registration records")
            continue
        print(f"{agent} ({seq}), {len(A)} keyframes; errors in mm")
        print(
            "  window     n  chained(med/max)  refined(med/max)  moved  acc%  worse%  lam"
            "          settled_rms"
        )
        for w in range(0, int(A[:, 0].max()) + 10, 10):
            B = A[(A[:, 0] >= w) & (A[:, 0] < w + 10)]
            if not len(B):
                continue
            print(f"  {w:4d}-{w + 10:<4d} {len(B):3d}  {np.median(B[:, 1]) * 1e3:6.1f} "
                  f"{B[:, 1].max() * 1e3:7.1f}    {np.median(B[:, 2]) * 1e3:6.1f} "
                  f"{B[:, 2].max() * 1e3:7.1f}   {np.median(B[:, 3]) * 1e3:5.1f}  "
                  f"{B[:, 5].mean() * 100:4.0f}  {np.mean(B[:, 2] > B[:, 1]) * 100:5.0f}  "
                  f"{B[:, 4].min():.3f}-{B[:, 4].max():.3f}  "
                  f"{np.median(B[:, 6]) * 1e3:6.1f}")  # fmt: skip
        acc = A[:, 5] > 0
        if acc.any():
            d = (A[acc, 2] - A[acc, 1]) * 1e3
            print(
                f"  accepted refinements {acc.sum()}: {np.mean(d < 0) * 100:.0f} % closer to "
                f"the truth, median change {np.median(d):+.1f} mm"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
