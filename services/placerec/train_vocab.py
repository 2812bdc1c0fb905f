"""Train the shipped ORB vocabulary on frames of a synthetic world.

The world uses seed 1234, which no test or benchmark renders (they use seeds 0
and 1), so place-recognition results are never measured on training images.
Frames come from every K-th pose of the EuRoC MH01..MH05 ground truth and ORB is
extracted exactly as the agent does (``Extractor`` on EuRoC cam0).

    python -m services.placerec.train_vocab [--every 10] [--k 10] [--levels 5] [--out PATH]
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def render_descriptors(
    seed: int, every: int, sequences: tuple[str, ...]
) -> tuple[np.ndarray, np.ndarray, int]:
    """ORB descriptors of every ``every``-th ground-truth frame: (desc, image id, n frames)."""
    import cv2

    from shared.camera import PinholeRadTan
    from shared.orb import Extractor
    from shared.synthetic.render import Renderer
    from shared.synthetic.world import World
    from shared.trajectory import load_euroc_gt

    cv2.setNumThreads(1)
    cam = PinholeRadTan.euroc_cam0()
    renderer = Renderer(World(seed), cam)
    extract = Extractor(cam)
    descs, ids = [], []
    n = 0
    for seq in sequences:
        gt = load_euroc_gt(seq)
        for k in range(every // 2, len(gt), every):
            img, _ = renderer.render(gt.poses[k], k)
            f = extract(img)
            descs.append(f.desc)
            ids.append(np.full(len(f.desc), n, np.int32))
            n += 1
    return np.concatenate(descs), np.concatenate(ids), n


def main(argv: list[str] | None = None) -> int:
    from services.placerec.vocabulary import default_path, train

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1234, help="synthetic world seed (not 0 or 1)")
    ap.add_argument("--every", type=int, default=10, help="use every K-th ground-truth frame")
    ap.add_argument("--sequences", default="MH01,MH02,MH03,MH04,MH05")
    ap.add_argument("--k", type=int, default=10, help="branching factor")
    ap.add_argument("--levels", type=int, default=5, help="tree depth")
    ap.add_argument("--fv-level", type=int, default=2, help="feature-vector level from the root")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    if args.seed in (0, 1):
        ap.error("seeds 0 and 1 are the test/benchmark worlds; train on another one")
    out = args.out or default_path()
    seqs = tuple(s.strip() for s in args.sequences.split(",") if s.strip())

    t0 = time.perf_counter()
    desc, img_id, n_frames = render_descriptors(args.seed, args.every, seqs)
    t_render = time.perf_counter() - t0
    print(f"rendered {n_frames} frames (world seed {args.seed}, {','.join(seqs)}, every "
          f"{args.every}th): {len(desc)} ORB descriptors in {t_render:.1f} s")  # fmt: skip

    t1 = time.perf_counter()
    voc = train(desc, img_id, k=args.k, levels=args.levels, fv_level=args.fv_level, seed=0)
    t_train = time.perf_counter() - t1
    voc.meta = {
        "world_seed": args.seed,
        "sequences": list(seqs),
        "every": args.every,
        "frames": n_frames,
        "descriptors": int(len(desc)),
        "extractor": "shared.orb.Extractor(euroc_cam0, 1000)",
        "train_seconds": round(t_train, 1),
    }
    voc.save(out)
    size = out.stat().st_size
    print(f"trained k={voc.k} L={voc.levels}: {voc.n_nodes} nodes, {voc.n_words} words in "
          f"{t_train:.1f} s")  # fmt: skip
    print(f"wrote {out} ({size / 1e6:.2f} MB); total {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    sys.exit(main())
