"""Motion blur, rolling shutter and auto-exposure jumps of the synthetic camera, and
the on-disk render cache of the ``synthetic:`` source."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.agent.sources import SourceError, interpolate_pose, open_source
from shared.synthetic.render import Renderer, Shutter, exposure_gain
from shared.synthetic.world import World
from shared.trajectory import load_euroc_gt


@pytest.fixture(scope="module")
def renderer() -> Renderer:
    return Renderer(World(0))


def _sharpness(img: np.ndarray) -> float:
    return float(cv2.Laplacian(img.astype(np.float32), cv2.CV_32F).var())


def test_still_camera_blurs_nothing(renderer):
    gt = load_euroc_gt("MH03")
    T = gt.poses[900]
    sharp, _ = renderer.render(T, 900)
    still, _ = renderer.render_exposure(lambda tau: T, 0.05, 900, Shutter(blur=0.5, samples=4))
    # Same pixels up to the warp's bilinear resampling of an identity map.
    assert np.abs(sharp.astype(int) - still.astype(int)).mean() < 1.0


def _sharp_and_exposed(renderer, shutter: Shutter) -> tuple[np.ndarray, np.ndarray]:
    """Frame 900 of MH03 at its timestamp's pose, and exposed through ``shutter`` for
    0.15 s along the motion."""
    gt = load_euroc_gt("MH03")
    k = 900

    def pose_at(tau: float) -> np.ndarray:
        return interpolate_pose(gt, gt.stamps_ns[k] * 1e-9 + tau)

    sharp, _ = renderer.render(gt.poses[k], k)
    exposed, _ = renderer.render_exposure(pose_at, 0.15, k, shutter)
    return sharp, exposed


def test_motion_blur_smears_along_the_motion(renderer):
    sharp, blurred = _sharp_and_exposed(renderer, Shutter(blur=0.5))
    assert abs(float(blurred.mean()) - float(sharp.mean())) < 3  # light is conserved
    assert _sharpness(blurred) < 0.6 * _sharpness(sharp)
    # Centred on the timestamp: the blurred frame still lines up with the sharp one.
    a = cv2.GaussianBlur(sharp, (0, 0), 4).astype(np.float32)
    b = cv2.GaussianBlur(blurred, (0, 0), 4).astype(np.float32)
    ncc = ((a - a.mean()) * (b - b.mean())).mean() / (a.std() * b.std())
    assert ncc > 0.8


def test_rolling_shutter_shears_rows(renderer):
    glob, rs = _sharp_and_exposed(renderer, Shutter(rolling=1.0))
    d = np.abs(glob.astype(int) - rs.astype(int))
    # The middle row is read at the timestamp; the first and last rows are not.
    h = glob.shape[0]
    assert d[h // 2 - 5 : h // 2 + 5].mean() < d[:20].mean()
    assert d[h // 2 - 5 : h // 2 + 5].mean() < d[-20:].mean()


def test_exposure_jumps_are_seeded_occasional_and_settle():
    t = np.arange(0, 120, 0.05)
    g = exposure_gain(3, t, 1.0)
    assert np.array_equal(g, exposure_gain(3, t, 1.0))
    steps = np.abs(np.diff(g))
    jumps = int((steps > 0.15).sum())
    assert 2 <= jumps <= 30
    assert np.median(np.abs(g - 1)) < 0.05  # back to normal most of the time
    assert (exposure_gain(3, t, 0.0) == 1).all()


def test_source_options_and_cache(tmp_path):
    spec = f"synthetic:MH03?frames=900:902&blur=0.5&exposure=1&cache={tmp_path}"
    src = open_source(spec)
    assert src.shutter == Shutter(blur=0.5, exposure=1.0)
    first = [f.image for f in src]
    files = sorted(p.name for p in next(tmp_path.iterdir()).iterdir())
    assert files == ["900.png", "901.png"]
    again = [f.image for f in open_source(spec)]
    assert all(np.array_equal(a, b) for a, b in zip(first, again, strict=True))
    # Sharp frames do not depend on the frame rate, blurred ones do: separate entries.
    list(open_source(f"synthetic:MH03?frames=900:901&blur=0.5&exposure=1&every=2&cache={tmp_path}"))
    assert len(list(tmp_path.iterdir())) == 2
    with pytest.raises(SourceError):
        open_source("synthetic:MH03?blur=-1")
    with pytest.raises(SourceError):
        open_source("synthetic:MH03?blur=lots")
