"""``hivemap sim render``: a EuRoC ASL folder rendered from the synthetic world.

It lives with the agent because it writes what the agent's ``synthetic:`` image source
produces (``shared/`` knows no service): ``euroc:DIR`` then replays the same frames.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from pathlib import Path

from shared.progress import progress
from shared.settings import Settings


def write_euroc(
    out: Path,
    seq: str,
    seed: int,
    every: int,
    frames: str,
    quiet: bool = False,
    shutter=None,
) -> int:
    import cv2

    from shared.trajectory import write_tum

    from .sources import SyntheticSource

    src = SyntheticSource(seq, seed, every, frames, shutter, cache_dir="")
    cam_dir = out / "mav0" / "cam0"
    (cam_dir / "data").mkdir(parents=True, exist_ok=True)
    (cam_dir / "sensor.yaml").write_text(src.camera.to_euroc_yaml())
    n = len(src)
    t0 = time.monotonic()
    bar = contextlib.nullcontext(lambda **_: None) if quiet else progress(
        f"render {seq}", n, "frames")  # fmt: skip
    with open(cam_dir / "data.csv", "w") as f, bar as update:
        f.write("#timestamp [ns],filename\n")
        for k, fr in enumerate(src, 1):
            name = f"{fr.stamp_ns}.png"
            cv2.imwrite(str(cam_dir / "data" / name), fr.image)
            f.write(f"{fr.stamp_ns},{name}\n")
            update(completed=k, info=f"{k / max(time.monotonic() - t0, 1e-9):5.1f} fps")
    write_tum(out / f"{seq}_gt.tum", src.ground_truth)
    return n


def cmd_render(args: argparse.Namespace, settings: Settings) -> int:
    from .sources import SourceError

    try:
        from shared.synthetic.render import Shutter

        sh = Shutter(args.blur, args.rolling, args.exposure)
        n = write_euroc(Path(args.out), args.traj, args.seed, args.every, args.frames,
                        shutter=sh)  # fmt: skip
    except SourceError as e:
        print(f"hivemap sim render: {e}", file=sys.stderr)
        return 2
    print(f"wrote {n} frames to {args.out}/mav0/cam0 and {args.traj}_gt.tum")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sim", help="synthetic world tools")
    ss = p.add_subparsers(dest="sim_command", required=True)
    r = ss.add_parser("render", help="render a EuRoC ASL folder along an MH trajectory")
    r.add_argument("--traj", required=True, help="MH01..MH05")
    r.add_argument("--out", required=True)
    r.add_argument("--seed", type=int, default=0, help="world seed")
    r.add_argument("--every", type=int, default=1, help="keep every K-th frame")
    r.add_argument("--frames", default="", help="A:B frame range")
    r.add_argument(
        "--blur",
        type=float,
        default=0.0,
        help="motion blur: shutter time as a fraction of the frame interval",
    )
    r.add_argument(
        "--rolling",
        type=float,
        default=0.0,
        help="rolling shutter: readout time as a fraction of the frame interval",
    )
    r.add_argument("--exposure", type=float, default=0.0, help="auto-exposure jumps, strength 0..1")
    r.set_defaults(func=cmd_render)
