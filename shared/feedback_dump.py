"""Opt-in recorder of the frame-correction feedback loop, for offline replay.

With ``HIVEMAP_FEEDBACK_DUMP=DIR`` set, the mapper records the inputs of every frame
correction it sends (the agent's keyframes as the VO sent them and as the map holds
them), merges and applied optimizations; the agent records at which frame each
correction arrived and whether its gate took it. Each process appends pickled dicts
to its own file in DIR (``{who}-{pid}.pkl``); :func:`load` reads them back. Off (the
default), :func:`record` is a no-op.
"""

from __future__ import annotations

import os
import pickle
import threading
import time
from pathlib import Path

_lock = threading.Lock()
_files: dict[tuple[str, str], object] = {}


def enabled() -> bool:
    return bool(os.environ.get("HIVEMAP_FEEDBACK_DUMP"))


def record(who: str, kind: str, **fields) -> None:
    d = os.environ.get("HIVEMAP_FEEDBACK_DUMP")
    if not d:
        return
    fields.update(kind=kind, who=who, wall_ns=time.time_ns())
    with _lock:
        f = _files.get((d, who))
        if f is None:
            Path(d).mkdir(parents=True, exist_ok=True)
            f = _files[(d, who)] = open(Path(d) / f"{who}-{os.getpid()}.pkl", "ab")  # noqa: SIM115
        pickle.dump(fields, f, protocol=pickle.HIGHEST_PROTOCOL)
        f.flush()


def load(d: str | Path, pattern: str = "*.pkl") -> list[dict]:
    """Every record in DIR, in wall-clock order."""
    out = []
    for p in sorted(Path(d).glob(pattern)):
        with open(p, "rb") as f:
            while True:
                try:
                    out.append(pickle.load(f))
                except EOFError:
                    break
    out.sort(key=lambda r: r["wall_ns"])
    return out
