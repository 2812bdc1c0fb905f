"""Image sources for the agent, behind one interface: ``open_source(spec)``.

    euroc:PATH                 EuRoC ASL folder (PATH, PATH/mav0 or PATH/mav0/cam0)
    tum:PATH[?calib=FILE]      TUM mono folder: rgb.txt + images, calibration yaml
                               (default PATH/camera.yaml)
    video:FILE[?calib=FILE]    a video file, calibration yaml (default FILE.yaml)
    synthetic:MH01[?seed=S&every=K&frames=A:B&blur=F&rolling=F&exposure=F&samples=N&cache=DIR]
                               rendered on the fly, with ground truth; blur: shutter
                               time, rolling: readout time (fractions of the frame
                               interval), exposure: auto-exposure jump strength (0-1)

Calibration files use the EuRoC sensor.yaml keys (camera_model pinhole,
intrinsics, distortion_coefficients radial-tangential, resolution). Every problem
raises :class:`SourceError` naming the file.
"""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import parse_qs

import cv2
import numpy as np

from shared.camera import CalibrationError, PinholeRadTan
from shared.synthetic.render import Shutter
from shared.trajectory import Trajectory, load_euroc_gt


class SourceError(ValueError):
    """A source that cannot be read: the message names the file."""


@dataclass
class Frame:
    index: int
    stamp_ns: int
    image: np.ndarray  # uint8 grayscale


def _text(path: Path) -> str:
    """An index file's text; bytes that are not UTF-8 are a bad index, not a crash."""
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise SourceError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from e
    except OSError as e:
        raise SourceError(f"{path}: cannot read: {e}") from e


def _calib(path: Path) -> PinholeRadTan:
    try:
        return PinholeRadTan.from_yaml(path)
    except CalibrationError as e:
        raise SourceError(str(e)) from e


def _read_gray(path: Path, cam: PinholeRadTan) -> np.ndarray:
    try:
        if not path.is_file():
            raise SourceError(f"{path}: image file is missing")
    except OSError as e:  # a name the index made up: too long, not encodable
        raise SourceError(f"{path}: bad image path: {e}") from e
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise SourceError(f"{path}: not a readable image (corrupt or unsupported)")
    if img.shape != (cam.height, cam.width):
        raise SourceError(
            f"{path}: image is {img.shape[1]}x{img.shape[0]}, calibration says "
            f"{cam.width}x{cam.height}"
        )
    return img


class ImageSource:
    camera: PinholeRadTan
    name: str
    ground_truth: Trajectory | None = None

    def __iter__(self) -> Iterator[Frame]:
        raise NotImplementedError

    def __len__(self) -> int:
        raise NotImplementedError


class EurocSource(ImageSource):
    def __init__(self, path: str | Path) -> None:
        p = Path(path)
        for cand in (p / "mav0" / "cam0", p / "cam0", p):
            if (cand / "data.csv").exists():
                p = cand
                break
        else:
            raise SourceError(f"{p / 'mav0/cam0/data.csv'}: no EuRoC cam0 index found")
        self.root = p
        self.name = f"euroc:{path}"
        self.camera = _calib(p / "sensor.yaml")
        self.items: list[tuple[int, Path]] = []
        rows = csv.reader(io.StringIO(_text(p / "data.csv"), newline=""))
        try:
            for n, row in enumerate(rows, start=1):
                if not row or row[0].startswith("#"):
                    continue
                try:
                    self.items.append((int(row[0]), p / "data" / row[1].strip()))
                except (ValueError, IndexError) as e:
                    raise SourceError(f"{p / 'data.csv'}:{n}: bad row {row!r}") from e
        except csv.Error as e:  # a NUL byte, an unclosed quote
            raise SourceError(f"{p / 'data.csv'}: not CSV: {e}") from e
        gt = p.parent / "state_groundtruth_estimate0" / "data.csv"
        self.ground_truth = load_euroc_gt(gt) if gt.exists() else None

    def __len__(self) -> int:
        return len(self.items)

    def __iter__(self) -> Iterator[Frame]:
        for i, (t, path) in enumerate(self.items):
            yield Frame(i, t, _read_gray(path, self.camera))


class TumSource(ImageSource):
    def __init__(self, path: str | Path, calib: str | None = None) -> None:
        p = Path(path)
        self.name = f"tum:{path}"
        idx = p / "rgb.txt"
        if not idx.is_file():
            raise SourceError(f"{idx}: TUM index file is missing")
        self.camera = _calib(Path(calib) if calib else p / "camera.yaml")
        self.items: list[tuple[int, Path]] = []
        for n, ln in enumerate(_text(idx).splitlines(), start=1):
            ln = ln.strip()
            if not ln or ln.startswith("#"):
                continue
            parts = ln.split()
            try:
                sec, _, frac = parts[0].partition(".")
                t = int(sec) * 1_000_000_000 + int((frac + "000000000")[:9])
                self.items.append((t, p / parts[1]))
            except (ValueError, IndexError) as e:
                raise SourceError(f"{idx}:{n}: bad line {ln!r}") from e
        gt = p / "groundtruth.txt"
        if gt.exists():
            from shared.trajectory import read_tum

            self.ground_truth = read_tum(gt)

    def __len__(self) -> int:
        return len(self.items)

    def __iter__(self) -> Iterator[Frame]:
        for i, (t, path) in enumerate(self.items):
            yield Frame(i, t, _read_gray(path, self.camera))


class VideoSource(ImageSource):
    def __init__(self, path: str | Path, calib: str | None = None) -> None:
        self.path = Path(path)
        self.name = f"video:{path}"
        if not self.path.is_file():
            raise SourceError(f"{self.path}: video file is missing")
        self.camera = _calib(Path(calib) if calib else Path(str(self.path) + ".yaml"))
        cap = cv2.VideoCapture(str(self.path))
        ok = cap.isOpened()
        self._n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) if ok else 0
        self._fps = cap.get(cv2.CAP_PROP_FPS) if ok else 0
        cap.release()
        if not ok:
            raise SourceError(f"{self.path}: cannot be opened as a video")

    def __len__(self) -> int:
        return self._n

    def __iter__(self) -> Iterator[Frame]:
        cap = cv2.VideoCapture(str(self.path))
        i = 0
        try:
            while True:
                ok, img = cap.read()
                if not ok:
                    break
                if img.ndim == 3:
                    img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
                cam = self.camera
                if img.shape != (cam.height, cam.width):
                    raise SourceError(
                        f"{self.path}: frame {i} is {img.shape[1]}x{img.shape[0]}, "
                        f"calibration says {cam.width}x{cam.height}"
                    )
                t = int(round(i * 1e9 / self._fps)) if self._fps > 0 else i * 50_000_000
                yield Frame(i, t, img)
                i += 1
        finally:
            cap.release()
        if i == 0:
            raise SourceError(f"{self.path}: no frame could be decoded")


class SyntheticSource(ImageSource):
    """Renders the synthetic world along a real EuRoC trajectory, on the fly.

    ``shutter`` turns on motion blur, rolling shutter and auto-exposure jumps (see
    :class:`shared.synthetic.render.Shutter`); the poses inside an exposure come from
    the ground truth, interpolated. Rendered frames are kept on disk (``cache_dir``,
    default ``$HIVEMAP_RENDER_CACHE`` or ~/.cache/hivemap/renders; ``""`` turns it off):
    a frame is a pure function of its key, and a blurred one costs several warps.
    """

    def __init__(self, seq: str, seed: int = 0, every: int = 1, frames: str = "",
                 shutter: Shutter | None = None, cache_dir: str | None = None) -> None:  # fmt: skip
        from shared.synthetic.render import Renderer
        from shared.synthetic.world import World

        try:
            gt = load_euroc_gt(seq)
        except ValueError as e:
            raise SourceError(str(e)) from e
        sl = _slice(frames)
        every = max(1, every)
        idx = np.arange(len(gt))[sl][::every]
        self.index = idx
        self.full_gt = gt
        self.ground_truth = Trajectory(gt.stamps_ns[idx], gt.poses[idx])
        self.renderer = Renderer(World(seed))
        self.camera = self.renderer.cam
        self.seq, self.seed, self.every = seq, seed, every
        self.shutter = shutter or Shutter()
        if self.shutter.blur < 0 or self.shutter.rolling < 0 or self.shutter.exposure < 0:
            raise SourceError(f"synthetic:{seq}: blur, rolling and exposure must be >= 0")
        self.frame_dt = float(np.median(np.diff(gt.stamps_ns))) * 1e-9 * every
        self.name = f"synthetic:{seq}?seed={seed}"
        if cache_dir is None:
            cache_dir = os.environ.get(
                "HIVEMAP_RENDER_CACHE", str(Path.home() / ".cache" / "hivemap" / "renders")
            )
        self.cache = self._cache_path(Path(cache_dir)) if cache_dir else None

    def _cache_path(self, root: Path) -> Path:
        sh = self.shutter
        # A sharp frame is the same at any frame rate; a blurred one spans a share of
        # the frame interval, which depends on ``every``.
        motion = "" if sh.blur <= 0 and sh.rolling <= 0 else f"-e{self.every}"
        return root / f"v{RENDER_VERSION}-{self.seq}-s{self.seed}-{sh.tag()}{motion}"

    def __len__(self) -> int:
        return len(self.index)

    def _pose_at(self, k: int):
        gt = self.full_gt
        t0 = float(gt.stamps_ns[k]) * 1e-9

        def pose_at(tau: float) -> np.ndarray:
            return interpolate_pose(gt, t0 + tau)

        return pose_at

    def render(self, i: int) -> np.ndarray:
        k = int(self.index[i])
        if self.cache is not None:
            path = self.cache / f"{k}.png"
            if path.is_file():
                img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
                if img is not None and img.shape == (self.camera.height, self.camera.width):
                    return img
        if self.shutter.off:
            img, _ = self.renderer.render(self.ground_truth.poses[i], k)
        else:
            from shared.synthetic.render import exposure_gain

            t = (self.full_gt.stamps_ns[k] - self.full_gt.stamps_ns[0]) * 1e-9
            g = float(exposure_gain(self.seed, t, self.shutter.exposure)[0])
            img, _ = self.renderer.render_exposure(self._pose_at(k), self.frame_dt, k,
                                                   self.shutter, g)  # fmt: skip
        if self.cache is not None:
            self.cache.mkdir(parents=True, exist_ok=True)
            tmp = self.cache / f".{k}.{os.getpid()}.png"
            # Written aside and renamed: a reader in another process never sees half a file.
            if cv2.imwrite(str(tmp), img):
                os.replace(tmp, self.cache / f"{k}.png")
        return img

    def __iter__(self) -> Iterator[Frame]:
        gt = self.ground_truth
        for i in range(len(self.index)):
            yield Frame(i, int(gt.stamps_ns[i]), self.render(i))


# Bump when the renderer's output changes, so cached frames of the old one are not used.
RENDER_VERSION = 1


def interpolate_pose(gt: Trajectory, t_s: float) -> np.ndarray:
    """T_w_c at time ``t_s`` (seconds): slerp between the neighbouring ground-truth
    poses, clamped at the ends."""
    from scipy.spatial.transform import Rotation, Slerp

    st = gt.stamps_ns * 1e-9
    j = int(np.clip(np.searchsorted(st, t_s), 1, len(st) - 1))
    a, b = st[j - 1], st[j]
    u = float(np.clip((t_s - a) / (b - a), 0.0, 1.0)) if b > a else 0.0
    Ra, Rb = gt.poses[j - 1, :3, :3], gt.poses[j, :3, :3]
    T = np.eye(4)
    T[:3, :3] = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([Ra, Rb])))(u).as_matrix()
    T[:3, 3] = (1 - u) * gt.poses[j - 1, :3, 3] + u * gt.poses[j, :3, 3]
    return T


def _slice(spec: str) -> slice:
    if not spec:
        return slice(None)
    a, _, b = spec.partition(":")
    try:
        return slice(int(a) if a else None, int(b) if b else None)
    except ValueError as e:
        raise SourceError(f"frames {spec!r}: expected A:B") from e


def open_source(spec: str) -> ImageSource:
    kind, sep, rest = spec.partition(":")
    if not sep or not rest:
        raise SourceError(f"source {spec!r}: expected euroc:PATH, tum:PATH, video:FILE or "
                          "synthetic:MH01")  # fmt: skip
    target, _, query = rest.partition("?")
    q = {k: v[-1] for k, v in parse_qs(query, keep_blank_values=True).items()}
    if kind == "euroc":
        return EurocSource(target)
    if kind == "tum":
        return TumSource(target, q.get("calib"))
    if kind == "video":
        return VideoSource(target, q.get("calib"))
    if kind == "synthetic":
        try:
            sh = Shutter(float(q.get("blur", 0)), float(q.get("rolling", 0)),
                         float(q.get("exposure", 0)), int(q.get("samples", 0)))  # fmt: skip
            return SyntheticSource(target, int(q.get("seed", 0)), int(q.get("every", 1)),
                                   q.get("frames", ""), sh, q.get("cache"))  # fmt: skip
        except ValueError as e:
            if isinstance(e, SourceError):
                raise
            raise SourceError(f"source {spec!r}: {e}") from e
    raise SourceError(f"source {spec!r}: unknown kind {kind!r}")
