"""Fuzzing at volume: >= 10,000 inputs per wire decoder and per file loader.

The targets and mutations are tests/fuzz_targets.py's (tests/test_fuzz.py runs a few
hundred under hypothesis). Per decoder: random bytes (1 in 10) and mutations of a valid
message go to the decoder and to the service path that receives it (mapper, placerec,
optimizer, agent); anything but DecodeError from a decoder, any exception from a
service, or a rejection not counted exactly once in hivemap_messages_rejected_total is
a failure. Per loader: only the loader's own error may come out.

    flock /tmp/hivemap-cpu.lock .venv/bin/python bench/bench_fuzz.py [--n 10000] [--seed 0]
"""

from __future__ import annotations

import argparse
import logging
import os
import random
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(ROOT / "tests"))
from common import table, write_report  # noqa: E402
from fuzz_targets import file_targets, mutate, rejected, run_file, run_one, targets  # noqa: E402

from shared.redis_server import RedisServer  # noqa: E402


def fuzz_decoders(n: int, seed: int, redis_url: str) -> list[dict]:
    rows = []
    for t in targets(redis_url):
        rng = random.Random(f"{seed}:{t.name}")
        bad = failures = 0
        examples: list[str] = []
        before = rejected(t.service, t.key) if t.receive else 0.0
        t0 = time.perf_counter()
        for _ in range(n):
            data = rng.randbytes(rng.randrange(600)) if rng.random() < 0.1 else mutate(t.seed, rng)
            try:
                bad += run_one(t, data)
            except AssertionError as e:
                failures += 1
                if len(examples) < 3:
                    examples.append(f"{e} (input {data[:80].hex()}...)")
        dt = time.perf_counter() - t0
        counted = rejected(t.service, t.key) - before if t.receive else None
        rows.append({
            "target": t.name, "receiver": t.service if t.receive else "-", "inputs": n,
            "rejected": bad, "accepted": n - bad, "counted": counted, "failures": failures,
            "us_per_input": 1e6 * dt / n, "examples": examples,
        })  # fmt: skip
        print(f"  {t.name}: {n} inputs, {bad} rejected, {failures} failures", flush=True)
    return rows


def fuzz_loaders(n: int, seed: int) -> list[dict]:
    rows = []
    for t in file_targets():
        rng = random.Random(f"{seed}:{t.name}")
        refused = failures = 0
        examples: list[str] = []
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory(prefix="hivemap-fuzz-") as top:
            for i in range(n):
                d = Path(top) / str(i)
                d.mkdir()
                try:
                    refused += run_file(t, d, t.mutate(t.seed, rng))
                except AssertionError as e:
                    failures += 1
                    if len(examples) < 3:
                        examples.append(str(e))
                for f in sorted(d.rglob("*"), reverse=True):
                    f.rmdir() if f.is_dir() else f.unlink()
                d.rmdir()
        dt = time.perf_counter() - t0
        rows.append({
            "target": t.name, "receiver": t.error.__name__, "inputs": n, "rejected": refused,
            "accepted": n - refused, "counted": None, "failures": failures,
            "us_per_input": 1e6 * dt / n, "examples": examples,
        })  # fmt: skip
        print(f"  {t.name}: {n} files, {refused} refused, {failures} failures", flush=True)
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=10_000, help="inputs per target")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--name", default="fuzz")
    ap.add_argument(
        "--loader-n",
        type=int,
        default=None,
        help="files per loader (default --n; each costs milliseconds of disk and decode)",
    )
    args = ap.parse_args()
    logging.disable(logging.WARNING)  # every rejection logs a warning
    # OpenCV's PNG reader prints libpng complaints on stderr for every broken image.
    os.environ.setdefault("OPENCV_LOG_LEVEL", "OFF")
    load0 = os.getloadavg()
    with RedisServer() as url:
        rows = fuzz_decoders(args.n, args.seed, url)
    rows += fuzz_loaders(args.loader_n or args.n, args.seed)
    ok = all(r["failures"] == 0 for r in rows) and all(
        r["counted"] is None or r["counted"] >= r["rejected"] for r in rows
    )
    path = write_report(args.name, {
        "inputs_per_decoder": args.n, "files_per_loader": args.loader_n or args.n,
        "seed": args.seed, "load_before": load0,
        "load_after": os.getloadavg(), "all_ok": ok, "targets": rows,
    })  # fmt: skip
    print(table(rows, ["target", "receiver", "inputs", "rejected", "counted", "failures",
                       "us_per_input"]))  # fmt: skip
    print(f"{'all ok' if ok else 'FAILURES'}; report {path}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
