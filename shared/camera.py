"""Pinhole camera with radial-tangential (plumb-bob) distortion, as EuRoC cam0.

Projection is written out in numpy so it vectorizes over many points and keeps the
exact model the renderer and the simulated agent must agree on; undistortion uses
OpenCV's iterative ``cv2.undistortPoints`` rather than a hand-rolled solver.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

EUROC_FX = 458.654  # EuRoC cam0's focal length, the project's default camera


class CalibrationError(ValueError):
    """A calibration file is missing, unreadable or not a pinhole/radtan camera."""


@dataclass(frozen=True)
class PinholeRadTan:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        return np.array([self.k1, self.k2, self.p1, self.p2])

    def distort_normalized(self, xy: np.ndarray) -> np.ndarray:
        x = xy[..., 0]
        y = xy[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
        xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
        yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
        return np.stack([xd, yd], axis=-1)

    def project(self, X_c: np.ndarray, min_depth: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
        """Project (N, 3) camera-frame points to distorted pixels; returns (uv, valid).

        valid is False behind the camera, outside the image, or where the
        distortion polynomial folds back (too far off-axis for the model).
        """
        X_c = np.asarray(X_c, dtype=float)
        z = X_c[:, 2]
        front = z > min_depth
        zs = np.where(front, z, 1.0)
        xy = X_c[:, :2] / zs[:, None]
        # The radtan polynomial is only monotonic near the optical axis; beyond
        # that radius points wrap back into the image, so they are rejected.
        r2 = (xy**2).sum(axis=1)
        monotonic = r2 < self.max_r2
        d = self.distort_normalized(xy)
        uv = np.empty_like(d)
        uv[:, 0] = self.fx * d[:, 0] + self.cx
        uv[:, 1] = self.fy * d[:, 1] + self.cy
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= self.width - 1) & (uv[:, 1] >= 0)
        inside &= uv[:, 1] <= self.height - 1
        return uv, front & monotonic & inside

    @functools.cached_property
    def max_r2(self) -> float:
        # Radius where d(r*(1+k1 r^2+k2 r^4))/dr = 0, i.e. 1 + 3 k1 r^2 + 5 k2 r^4 = 0.
        # Once per camera (the parameters are frozen): np.roots on every projection was
        # a tenth of a simulated keyframe's cost.
        if self.k1 >= 0 and self.k2 >= 0:
            return np.inf
        roots = (
            np.roots([5.0 * self.k2, 3.0 * self.k1, 1.0])
            if self.k2 != 0
            else np.array([-1.0 / (3.0 * self.k1)])
        )
        pos = [r.real for r in np.atleast_1d(roots) if abs(r.imag) < 1e-12 and r.real > 0]
        return float(min(pos)) * 0.95 if pos else np.inf

    def undistort_points(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels (N, 2) -> normalized image coordinates (N, 2) on z=1."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        if len(uv) == 0:
            return np.zeros((0, 2))
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-10)
        xy = cv2.undistortPoints(uv, self.K, self.dist, None, None, None, crit)
        return xy.reshape(-1, 2)

    def undistort_pixels(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels -> ideal pinhole pixels with the same K."""
        xy = self.undistort_points(uv)
        return np.stack([self.fx * xy[:, 0] + self.cx, self.fy * xy[:, 1] + self.cy], axis=1)

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels -> unit bearing vectors (N, 3) in the camera frame."""
        xy = self.undistort_points(uv)
        rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)

    def to_array(self) -> np.ndarray:
        """The 10 numbers a keyframe message carries (``NewKeyframe.calib``)."""
        return np.array([self.width, self.height, self.fx, self.fy, self.cx, self.cy,
                         self.k1, self.k2, self.p1, self.p2], dtype=np.float64)  # fmt: skip

    @staticmethod
    def from_array(a: np.ndarray) -> PinholeRadTan:
        a = [float(x) for x in a]
        return PinholeRadTan(int(a[0]), int(a[1]), *a[2:])

    # -- loading ---------------------------------------------------------------
    @staticmethod
    def euroc_cam0() -> PinholeRadTan:
        return PinholeRadTan(
            752, 480, EUROC_FX, 457.296, 367.215, 248.375,
            -0.28340811, 0.07395907, 0.00019359, 1.76187114e-05,
        )  # fmt: skip

    def to_euroc_yaml(self) -> str:
        data = {
            "sensor_type": "camera",
            "comment": "VI-Sensor cam0 (MT9M034), as written by HiveMap",
            "rate_hz": 20,
            "resolution": [self.width, self.height],
            "camera_model": "pinhole",
            "intrinsics": [self.fx, self.fy, self.cx, self.cy],
            "distortion_model": "radial-tangential",
            "distortion_coefficients": [self.k1, self.k2, self.p1, self.p2],
            "T_BS": {"cols": 4, "rows": 4, "data": np.eye(4).ravel().tolist()},
        }
        return yaml.safe_dump(data, sort_keys=False)

    @staticmethod
    def from_yaml(path: str | Path) -> PinholeRadTan:
        """Read an EuRoC ``sensor.yaml`` (or the same keys in any yaml file)."""
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise CalibrationError(f"{path}: cannot read calibration: {e}") from e
        try:
            # EuRoC files start with a %YAML directive and use OpenCV tags in places.
            lines = [ln for ln in text.splitlines() if not ln.startswith("%")]
            data = yaml.safe_load("\n".join(lines).replace("!!opencv-matrix", ""))
        except yaml.YAMLError as e:
            raise CalibrationError(f"{path}: not valid YAML: {e}") from e
        if not isinstance(data, dict):
            raise CalibrationError(f"{path}: expected a mapping of calibration keys")
        return PinholeRadTan.from_dict(data, source=str(path))

    @staticmethod
    def from_dict(data: dict, source: str = "calibration") -> PinholeRadTan:
        model = data.get("camera_model", "pinhole")
        if model != "pinhole":
            raise CalibrationError(f"{source}: camera_model {model!r} is not 'pinhole'")
        dmodel = data.get("distortion_model", "radial-tangential")
        if dmodel not in ("radial-tangential", "radtan", "plumb_bob"):
            raise CalibrationError(
                f"{source}: distortion_model {dmodel!r} is not radial-tangential"
            )
        try:
            w, h = (int(v) for v in data["resolution"])
            fx, fy, cx, cy = (float(v) for v in data["intrinsics"])
            d = [float(v) for v in data.get("distortion_coefficients", [0, 0, 0, 0])]
        except (KeyError, TypeError, ValueError) as e:
            raise CalibrationError(
                f"{source}: needs resolution [w, h], intrinsics [fx, fy, cx, cy] and "
                f"distortion_coefficients [k1, k2, p1, p2]: {e!r}"
            ) from e
        if len(d) != 4:
            raise CalibrationError(f"{source}: expected 4 distortion coefficients, got {len(d)}")
        if w <= 0 or h <= 0 or fx <= 0 or fy <= 0:
            raise CalibrationError(f"{source}: resolution and focal lengths must be positive")
        if not (0 <= cx <= w and 0 <= cy <= h):
            raise CalibrationError(f"{source}: principal point ({cx}, {cy}) outside the image")
        return PinholeRadTan(w, h, fx, fy, cx, cy, *d)
