"""The synthetic world and renderer: geometry, conventions, determinism."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from shared.geometry import se3_inv, transform_points
from shared.synthetic.render import Renderer
from shared.synthetic.world import World
from shared.trajectory import SEQUENCES, load_euroc_gt


@pytest.fixture(scope="module")
def world() -> World:
    return World(0)


@pytest.fixture(scope="module")
def renderer(world) -> Renderer:
    return Renderer(world)


def test_world_contains_every_flight_with_clearance(world):
    for seq in SEQUENCES:
        p = load_euroc_gt(seq).positions
        assert (p > world.lo).all() and (p < world.hi).all(), seq
        assert world.min_clearance(p) >= 0.9, seq
    assert len(world.boxes) >= 50
    assert {b.kind for b in world.boxes} == {"box", "pillar", "shelf"}


def test_image_format_and_depth(renderer):
    gt = load_euroc_gt("MH01")
    img, depth = renderer.render(gt.poses[500], 500)
    assert img.shape == (480, 752) and img.dtype == np.uint8
    assert depth.shape == (480, 752) and (depth > 0).all() and depth.max() < 45
    assert img.std() > 20  # textured, not flat


def test_geometric_truth_reprojection_ncc(renderer):
    """Pixels of frame 1 with their rendered depth, moved through the ground-truth
    poses and the camera model into frame 2, land on matching image patches."""
    gt = load_euroc_gt("MH01")
    i1, i2 = 1000, 1002
    im1, d1 = renderer.render(gt.poses[i1], i1)
    im2, d2 = renderer.render(gt.poses[i2], i2)
    cam = renderer.cam
    rng = np.random.default_rng(0)
    ui = np.stack([rng.integers(20, cam.width - 20, 1500),
                   rng.integers(20, cam.height - 20, 1500)], axis=1)  # fmt: skip
    z = d1[ui[:, 1], ui[:, 0]]
    rays = cam.unproject(ui.astype(float))
    X1 = rays / rays[:, 2:3] * z[:, None]
    X2 = transform_points(se3_inv(gt.poses[i2]) @ gt.poses[i1], X1)
    uv2, ok = cam.project(X2)
    f1, f2 = im1.astype(np.float32), im2.astype(np.float32)
    ncc = []
    for k in np.nonzero(ok)[0]:
        x, y = uv2[k]
        if not (10 <= x < cam.width - 10 and 10 <= y < cam.height - 10):
            continue
        if abs(d2[int(round(y)), int(round(x))] - X2[k, 2]) > 0.03 * X2[k, 2]:
            continue  # occluded in frame 2
        p1 = cv2.getRectSubPix(f1, (11, 11), (float(ui[k, 0]), float(ui[k, 1])))
        if p1.std() < 10:
            continue  # no texture to correlate
        p2 = cv2.getRectSubPix(f2, (11, 11), (float(x), float(y)))
        a, b = p1 - p1.mean(), p2 - p2.mean()
        ncc.append(float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum() + 1e-9)))
    ncc = np.array(ncc)
    assert len(ncc) > 500
    assert (ncc >= 0.9).mean() >= 0.90, (ncc >= 0.9).mean()
    # The same test with a wrong convention (no distortion) must fail.
    wrong = np.array([cam.fx, cam.fy]) * (X2[:, :2] / X2[:, 2:3]) + [cam.cx, cam.cy]
    diff = np.linalg.norm(wrong[ok] - uv2[ok], axis=1)
    assert np.median(diff) > 2.0


def test_same_seed_same_images_other_seed_other_world():
    gt = load_euroc_gt("MH02")
    a = Renderer(World(3)).render(gt.poses[700], 700)[0]
    b = Renderer(World(3)).render(gt.poses[700], 700)[0]
    c = Renderer(World(4)).render(gt.poses[700], 700)[0]
    assert np.array_equal(a, b)
    assert np.abs(a.astype(int) - c.astype(int)).mean() > 20
    assert [x.lo.tolist() for x in World(3).boxes] != [x.lo.tolist() for x in World(4).boxes]


def test_orb_finds_spread_features(renderer):
    orb = cv2.ORB_create(1000)
    gt = load_euroc_gt("MH04")
    for k in (100, 900, 1700):
        img, _ = renderer.render(gt.poses[k], k)
        kp = orb.detect(img, None)
        pts = np.array([p.pt for p in kp])
        cells = {(int(x * 4 // 752), int(y * 4 // 480)) for x, y in pts}
        assert len(kp) >= 500 and len(cells) >= 12
