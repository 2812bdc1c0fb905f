"""Trajectories: EuRoC ground truth, TUM files, and ATE after Sim(3) alignment.

ATE follows evo's ``evo_ape -as``: Umeyama alignment with scale over associated
poses, then RMSE of translation differences. Tests check these numbers against evo.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from shared.geometry import pose_from_tq, pose_to_tq, umeyama

SEQUENCES = ("MH01", "MH02", "MH03", "MH04", "MH05")


@dataclass
class Trajectory:
    stamps_ns: np.ndarray  # (N,) int64
    poses: np.ndarray  # (N, 4, 4) T_w_c

    def __len__(self) -> int:
        return len(self.stamps_ns)

    @property
    def positions(self) -> np.ndarray:
        return self.poses[:, :3, 3]

    def path_length(self) -> float:
        return float(np.linalg.norm(np.diff(self.positions, axis=0), axis=1).sum())


def gt_path(seq: str) -> Path:
    if seq not in SEQUENCES:
        raise ValueError(f"unknown sequence {seq!r}; expected one of {', '.join(SEQUENCES)}")
    return Path(str(resources.files("shared") / "data" / "euroc_gt" / f"{seq}_GT.txt"))


def load_euroc_gt(seq_or_path: str | Path) -> Trajectory:
    """EuRoC csv rows: t_ns, px, py, pz, qw, qx, qy, qz (camera to world)."""
    p = Path(seq_or_path)
    path = gt_path(str(seq_or_path)) if not p.exists() else p
    data = np.loadtxt(path, delimiter=",", comments="#", dtype=np.float64)
    # Timestamps are 19-digit integers; parse them as text to keep the nanoseconds.
    with open(path) as f:
        stamps = [int(ln.split(",")[0].split(".")[0]) for ln in f if ln[:1].isdigit()]
    poses = np.stack([pose_from_tq(r[1:4], np.array([r[5], r[6], r[7], r[4]])) for r in data])
    return Trajectory(np.array(stamps, dtype=np.int64), poses)


def format_tum(stamps_ns: np.ndarray, poses: np.ndarray) -> str:
    lines = []
    for t, T in zip(stamps_ns, poses, strict=True):
        p, q = pose_to_tq(T)
        sec, ns = divmod(int(t), 1_000_000_000)
        lines.append(
            f"{sec}.{ns:09d} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} "
            f"{q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}"
        )
    return "\n".join(lines) + ("\n" if lines else "")


def write_tum(path: str | Path, traj: Trajectory) -> None:
    Path(path).write_text(format_tum(traj.stamps_ns, traj.poses))


def parse_tum(text: str) -> Trajectory:
    stamps, poses = [], []
    for ln in text.splitlines():
        ln = ln.strip()
        if not ln or ln.startswith("#"):
            continue
        f = ln.split()
        if len(f) != 8:
            raise ValueError(f"TUM line needs 8 fields, got {len(f)}: {ln!r}")
        sec, _, frac = f[0].partition(".")
        stamps.append(int(sec) * 1_000_000_000 + int((frac + "000000000")[:9]))
        v = [float(x) for x in f[1:]]
        poses.append(pose_from_tq(np.array(v[:3]), np.array(v[3:])))
    if not poses:
        return Trajectory(np.zeros(0, np.int64), np.zeros((0, 4, 4)))
    return Trajectory(np.array(stamps, dtype=np.int64), np.stack(poses))


def read_tum(path: str | Path) -> Trajectory:
    return parse_tum(Path(path).read_text())


def associate(est: Trajectory, ref: Trajectory, max_diff_ns: int = 10_000_000):
    """Index pairs (i_est, i_ref) of nearest stamps within max_diff (as evo does)."""
    if len(est) == 0 or len(ref) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    j = np.searchsorted(ref.stamps_ns, est.stamps_ns)
    j = np.clip(j, 1, len(ref) - 1)
    left = ref.stamps_ns[j - 1]
    right = ref.stamps_ns[j]
    pick = np.where(np.abs(est.stamps_ns - left) <= np.abs(right - est.stamps_ns), j - 1, j)
    if len(ref) == 1:
        pick = np.zeros(len(est), int)
    ok = np.abs(ref.stamps_ns[pick] - est.stamps_ns) <= max_diff_ns
    return np.nonzero(ok)[0], pick[ok]


@dataclass
class AteResult:
    rmse: float
    mean: float
    max: float
    n: int
    scale: float
    path_length: float

    @property
    def percent_of_path(self) -> float:
        return 100.0 * self.rmse / self.path_length if self.path_length > 0 else float("nan")


def aligned_errors(
    est: Trajectory, ref: Trajectory, align_scale: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Per associated pose of ``est``, its position error after the whole trajectory's
    alignment onto ``ref`` (Sim(3), or SE(3) without ``align_scale``): (indices into
    ``est``, indices into ``ref``, errors, the alignment's scale). What :func:`ate`
    summarizes; per pose, where along a flight the error is."""
    ie, ir = associate(est, ref)
    if len(ie) < 3:
        raise ValueError(f"only {len(ie)} associated poses; need at least 3")
    P = est.positions[ie]
    G = ref.positions[ir]
    S = umeyama(P, G, with_scale=align_scale)
    return ie, ir, np.linalg.norm(S.apply(P) - G, axis=1), S.s


def ate(est: Trajectory, ref: Trajectory, align_scale: bool = True) -> AteResult:
    _, ir, err, scale = aligned_errors(est, ref, align_scale)
    ref_assoc = Trajectory(ref.stamps_ns[ir], ref.poses[ir])
    return AteResult(
        float(np.sqrt((err**2).mean())), float(err.mean()), float(err.max()), len(err), scale,
        ref_assoc.path_length(),
    )  # fmt: skip
