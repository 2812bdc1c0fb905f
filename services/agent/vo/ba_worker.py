"""Local BA in a process of its own, so that tracking never waits for it.

GTSAM's optimizer (through its pybind11 wrapper) holds the GIL for the whole solve,
so a thread would stall tracking as surely as running inline: 60-370 ms per keyframe
measured, several frame periods of a 20 Hz camera. A single worker process does the
solve; the VO hands it a window and applies the result when it is back (ORB-SLAM's
LocalMapping thread, with the same tolerance: tracking goes on against the map as it
was).

The window goes as a few flat arrays (:func:`pack_job`), not as the dicts and the list
of observation tuples ``local_ba`` takes: the executor pickles on a thread of the
agent's process, holding the GIL, and ~7500 observations each with its own small
ndarray took 25-50 ms a keyframe to pickle (profiled, MH02) -- a stall of the tracking
thread as long as a frame period. As arrays: ~1 ms. The values are the same bits, in
the same order, so the worker solves exactly the problem the inline BA would.
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import Future, ProcessPoolExecutor

import numpy as np

from .local_ba import BAResult, local_ba


def _ready() -> bool:
    return True


_ARRAYS = ("poses", "fixed", "points", "obs")  # the rest of a job goes as it is


def pack_job(job: dict) -> dict:
    """``local_ba``'s keyword arguments as flat arrays (cheap to pickle)."""
    poses, points, obs = job["poses"], job["points"], job["obs"]
    n = len(obs)
    return {
        "kf_ids": np.fromiter(poses, np.int64, len(poses)),
        "poses": np.array(list(poses.values()), np.float64).reshape(-1, 4, 4),
        "fixed": np.fromiter(job["fixed"], np.int64, len(job["fixed"])),
        "mp_ids": np.fromiter(points, np.int64, len(points)),
        "points": np.array(list(points.values()), np.float64).reshape(-1, 3),
        "obs_kf": np.fromiter((o[0] for o in obs), np.int64, n),
        "obs_mp": np.fromiter((o[1] for o in obs), np.int64, n),
        "obs_xy": np.array([o[2] for o in obs], np.float64).reshape(-1, 2),
        **{k: v for k, v in job.items() if k not in _ARRAYS},
    }


def unpack_job(p: dict) -> dict:
    packed = ("kf_ids", "mp_ids", "obs_kf", "obs_mp", "obs_xy") + _ARRAYS
    return {
        "poses": dict(zip(p["kf_ids"].tolist(), p["poses"], strict=True)),
        "fixed": set(p["fixed"].tolist()),
        "points": dict(zip(p["mp_ids"].tolist(), p["points"], strict=True)),
        "obs": list(zip(p["obs_kf"].tolist(), p["obs_mp"].tolist(), p["obs_xy"], strict=True)),
        **{k: v for k, v in p.items() if k not in packed},
    }


def pack_result(r: BAResult) -> tuple:
    out = np.array(r.outliers, np.int64).reshape(-1, 2)
    return (np.fromiter(r.poses, np.int64, len(r.poses)),
            np.array(list(r.poses.values()), np.float64).reshape(-1, 4, 4),
            np.fromiter(r.points, np.int64, len(r.points)),
            np.array(list(r.points.values()), np.float64).reshape(-1, 3),
            out, r.iterations, r.error_before, r.error_after)  # fmt: skip


def unpack_result(t: tuple) -> BAResult:
    kf_ids, poses, mp_ids, points, out, iters, e0, e1 = t
    return BAResult(dict(zip(kf_ids.tolist(), poses, strict=True)),
                    dict(zip(mp_ids.tolist(), points, strict=True)),
                    [tuple(o) for o in out.tolist()], iters, e0, e1)  # fmt: skip


_STOP = None  # the worker's end of BAWorker's abort flag (a multiprocessing Event)


def _init(stop) -> None:
    global _STOP
    _STOP = stop


def _solve(packed: dict) -> tuple:
    return pack_result(local_ba(**unpack_job(packed), should_stop=_STOP.is_set))


class BAWorker:
    def __init__(self) -> None:
        # spawn, not fork: the parent runs Zenoh's threads, which a fork would copy
        # in whatever state they were.
        ctx = multiprocessing.get_context("spawn")
        self._stop = ctx.Event()
        self._pool = ProcessPoolExecutor(1, mp_context=ctx, initializer=_init,
                                         initargs=(self._stop,))  # fmt: skip
        self._fut: Future | None = None
        # Start the process (imports numpy and GTSAM, ~1 s) before the first frame.
        self._pool.submit(_ready).result()

    @property
    def busy(self) -> bool:
        return self._fut is not None

    def submit(self, job: dict) -> None:
        assert self._fut is None, "one local BA at a time"
        self._stop.clear()
        self._fut = self._pool.submit(_solve, pack_job(job))

    def abort(self) -> None:
        """Ask the running BA to end after its current iteration (its result, as far
        as it got, still comes back through :meth:`result`)."""
        if self._fut is not None:
            self._stop.set()

    def result(self, wait: bool = False) -> BAResult | None:
        if self._fut is None or not (wait or self._fut.done()):
            return None
        fut, self._fut = self._fut, None
        return unpack_result(fut.result())

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)
