"""Image sources on tiny datasets the tests write, including corrupt ones."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from services.agent.render_cli import write_euroc
from services.agent.sources import SourceError, open_source
from shared.camera import PinholeRadTan

CAM = PinholeRadTan.euroc_cam0()


def _img(k: int) -> np.ndarray:
    rng = np.random.default_rng(k)
    return rng.integers(0, 256, (CAM.height, CAM.width), dtype=np.uint8)


@pytest.fixture()
def euroc(tmp_path) -> Path:
    write_euroc(tmp_path, "MH01", seed=0, every=10, frames="0:30", quiet=True)
    return tmp_path


def test_euroc_source_reads_rendered_folder(euroc):
    src = open_source(f"euroc:{euroc}")
    frames = list(src)
    assert len(src) == len(frames) == 3
    assert src.camera == CAM
    assert frames[0].image.shape == (480, 752)
    stamps = [int(ln.split(",")[0]) for ln in
              (euroc / "mav0/cam0/data.csv").read_text().splitlines()[1:]]  # fmt: skip
    assert [f.stamp_ns for f in frames] == stamps
    assert open_source(f"euroc:{euroc / 'mav0'}").camera == CAM


def test_euroc_corrupt_and_missing_files_are_named(euroc):
    data = sorted((euroc / "mav0/cam0/data").iterdir())
    data[1].write_bytes(data[1].read_bytes()[:100])  # truncated PNG
    with pytest.raises(SourceError, match=data[1].name):
        list(open_source(f"euroc:{euroc}"))
    data[1].unlink()
    with pytest.raises(SourceError, match="missing"):
        list(open_source(f"euroc:{euroc}"))
    (euroc / "mav0/cam0/sensor.yaml").write_text("camera_model: pinhole\nintrinsics: [1]\n")
    with pytest.raises(SourceError, match="sensor.yaml"):
        open_source(f"euroc:{euroc}")
    with pytest.raises(SourceError, match="data.csv"):
        open_source(f"euroc:{euroc / 'nothing'}")


def _tum(tmp_path: Path, n: int = 3) -> Path:
    (tmp_path / "rgb").mkdir(parents=True)
    lines = ["# color images"]
    for k in range(n):
        t = 1305031102.175304 + k * 0.033
        name = f"rgb/{t:.6f}.png"
        cv2.imwrite(str(tmp_path / name), cv2.cvtColor(_img(k), cv2.COLOR_GRAY2BGR))
        lines.append(f"{t:.6f} {name}")
    (tmp_path / "rgb.txt").write_text("\n".join(lines) + "\n")
    (tmp_path / "camera.yaml").write_text(CAM.to_euroc_yaml())
    return tmp_path


def test_tum_source(tmp_path):
    p = _tum(tmp_path)
    frames = list(open_source(f"tum:{p}"))
    assert len(frames) == 3 and frames[0].stamp_ns == 1305031102175304000
    assert np.array_equal(frames[2].image, _img(2))  # color converted back to gray


def test_tum_errors(tmp_path):
    p = _tum(tmp_path)
    (p / "rgb.txt").write_text("1305031102.1 rgb/x.png\nnot-a-time\n")
    with pytest.raises(SourceError, match=r"rgb.txt:2"):
        open_source(f"tum:{p}")
    (p / "rgb.txt").unlink()
    with pytest.raises(SourceError, match="rgb.txt"):
        open_source(f"tum:{p}")
    q = _tum(tmp_path / "other")
    (q / "camera.yaml").write_text("camera_model: kannala_brandt\n")
    with pytest.raises(SourceError, match="camera.yaml"):
        open_source(f"tum:{q}")
    small = CAM.to_euroc_yaml().replace("- 752", "- 640")
    (q / "camera.yaml").write_text(small)
    with pytest.raises(SourceError, match="calibration says"):
        list(open_source(f"tum:{q}"))


def test_video_source(tmp_path):
    path = tmp_path / "flight.avi"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, (CAM.width, CAM.height))
    assert vw.isOpened()
    for k in range(5):
        vw.write(cv2.cvtColor(_img(k), cv2.COLOR_GRAY2BGR))
    vw.release()
    (tmp_path / "flight.avi.yaml").write_text(CAM.to_euroc_yaml())
    frames = list(open_source(f"video:{path}"))
    assert len(frames) == 5 and frames[1].stamp_ns == 50_000_000
    bad = tmp_path / "bad.avi"
    bad.write_bytes(b"not a video at all" * 100)
    with pytest.raises(SourceError, match="bad.avi"):
        open_source(f"video:{bad}?calib={tmp_path / 'flight.avi.yaml'}")
    with pytest.raises(SourceError, match="missing.yaml"):
        open_source(f"video:{path}?calib={tmp_path / 'missing.yaml'}")


def test_synthetic_source_and_bad_specs():
    src = open_source("synthetic:MH03?seed=1&every=5&frames=0:15")
    frames = list(src)
    assert len(frames) == 3 and src.ground_truth is not None
    assert [f.stamp_ns for f in frames] == src.ground_truth.stamps_ns.tolist()
    for bad in ["MH01", "nope:x", "synthetic:MH09", "synthetic:MH01?frames=a:b", "euroc:"]:
        with pytest.raises(SourceError):
            open_source(bad)
