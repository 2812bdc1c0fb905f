"""Renderer benchmark (synthetic-world issue, items 1-2).

Speed: frames per second on one core over consecutive frames of each sequence.
Features: ORB (1000 features) keypoint count and 4x4-grid coverage per frame, on
every K-th frame of every MH sequence.

    .venv/bin/python bench/bench_render.py [--every 10] [--speed-frames 100]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from common import table, write_report  # noqa: E402

from shared.progress import track  # noqa: E402
from shared.synthetic.render import Renderer  # noqa: E402
from shared.synthetic.world import World  # noqa: E402
from shared.trajectory import SEQUENCES, load_euroc_gt  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--every", type=int, default=10)
    ap.add_argument("--speed-frames", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    renderer = Renderer(World(args.seed))
    orb = cv2.ORB_create(nfeatures=1000)
    rows = []
    for seq in track(SEQUENCES, "render and ORB per sequence"):
        gt = load_euroc_gt(seq)
        # Speed on consecutive frames from the middle of the flight (textures warm).
        start = len(gt) // 2
        renderer.render(gt.poses[start], start)
        t0 = time.perf_counter()
        for k in range(start, start + args.speed_frames):
            renderer.render(gt.poses[k], k)
        fps = args.speed_frames / (time.perf_counter() - t0)
        counts, cells = [], []
        for k in range(0, len(gt), args.every):
            img, _ = renderer.render(gt.poses[k], k)
            kp = orb.detect(img, None)
            pts = np.array([p.pt for p in kp]).reshape(-1, 2)
            cov = {(int(x * 4 // img.shape[1]), int(y * 4 // img.shape[0])) for x, y in pts}
            counts.append(len(kp))
            cells.append(len(cov))
        c, g = np.array(counts), np.array(cells)
        ok = (c >= 500) & (g >= 12)
        rows.append({
            "seq": seq, "fps_one_core": fps, "frames_checked": len(c),
            "kp_min": int(c.min()), "kp_median": float(np.median(c)),
            "frac_kp_ge_500": float((c >= 500).mean()), "cells_min": int(g.min()),
            "frac_cells_ge_12": float((g >= 12).mean()), "frac_both": float(ok.mean()),
            "pass": bool(fps >= 10 and ok.mean() >= 0.95),
        })  # fmt: skip
        print(f"{seq}: {fps:.1f} fps, {ok.mean():.1%} of {len(c)} frames pass", file=sys.stderr)
    path = write_report("render", {"every": args.every, "seed": args.seed, "sequences": rows})
    print(table(rows, ["seq", "fps_one_core", "frames_checked", "kp_min", "kp_median",
                       "frac_kp_ge_500", "cells_min", "frac_cells_ge_12", "pass"]))  # fmt: skip
    print(f"written {path}")
    return 0 if all(r["pass"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
