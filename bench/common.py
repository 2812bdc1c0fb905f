"""Helpers shared by the bench scripts: JSON reports and plain tables."""

from __future__ import annotations

import contextlib
import json
import os
import platform
import subprocess
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def git_rev() -> str:
    try:
        return subprocess.check_output(["git", "rev-parse", "--short", "HEAD"], text=True,
                                       cwd=RESULTS.parent).strip()  # fmt: skip
    except Exception:
        return "unknown"


def machine() -> dict:
    """What a timing depends on: the same code measured 2.5x slower mapper latencies on
    one 2-core machine than on another, so reports name the CPU and the load."""
    info = {"cpus": os.cpu_count(), "python": platform.python_version()}
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            k, _, v = (x.strip() for x in line.partition(":"))
            if k in ("model name", "cpu MHz"):
                info.setdefault(k, v)  # the first CPU's line; the others repeat it
    with contextlib.suppress(OSError):
        info["loadavg_1m_at_write"] = os.getloadavg()[0]
    return info


def write_report(name: str, data: dict) -> Path:
    RESULTS.mkdir(parents=True, exist_ok=True)
    data = {
        "bench": name,
        "when": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "commit": git_rev(),
        "machine": machine(),
        **data,
    }
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(data, indent=2, default=float) + "\n")
    return path


def table(rows: list[dict], cols: list[str]) -> str:
    cells = [[str(c) for c in cols]] + [[_fmt(r.get(c, "")) for c in cols] for r in rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(cols))]
    lines = ["  ".join(v.rjust(w) for v, w in zip(row, widths, strict=True)) for row in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)
