"""Procedural textures: unique per tile, natural-looking, with corners at every scale.

Each tile's texture is generated from (world seed, tile id): multi-octave value noise
for the natural base, then blobs, rectangles ("posters", crates), line segments
("cracks", seams) and small specks, so ORB finds corners near and far and bag-of-
words can tell places apart. Mip pyramids come from ``cv2.pyrDown``; an LRU cache
keeps the tiles near the camera in memory.
"""

from __future__ import annotations

from collections import OrderedDict

import cv2
import numpy as np

TEX_PX = 384  # texels per tile side (about 5 mm texels on 2 m tiles)


def _value_noise(rng: np.random.Generator, size: int) -> np.ndarray:
    out = np.zeros((size, size), np.float32)
    amp = 1.0
    for cells in (3, 6, 12, 24, 48, 96):
        g = rng.random((cells + 1, cells + 1)).astype(np.float32)
        out += amp * cv2.resize(g, (size, size), interpolation=cv2.INTER_CUBIC)
        amp *= 0.6
    out -= out.min()
    return out / max(float(out.max()), 1e-6)


def make_texture(seed: int, tile_id: int, size: int = TEX_PX) -> np.ndarray:
    rng = np.random.default_rng([seed, tile_id])
    base = 70 + 110 * _value_noise(rng, size)
    img = base.astype(np.uint8)
    # Large structures: posters and panels with hard edges.
    for _ in range(rng.integers(1, 4)):
        x0, y0 = rng.integers(0, size, 2)
        w, h = rng.integers(size // 10, size // 2, 2)
        col = int(rng.integers(10, 245))
        cv2.rectangle(img, (int(x0), int(y0)), (int(x0 + w), int(y0 + h)), col, -1)
        # Print on the poster: smaller rectangles and text-like bars.
        for _ in range(rng.integers(3, 12)):
            px, py = x0 + rng.integers(0, max(w, 2)), y0 + rng.integers(0, max(h, 2))
            pw, ph = rng.integers(3, max(4, w // 3)), rng.integers(2, max(3, h // 4))
            cv2.rectangle(img, (int(px), int(py)), (int(px + pw), int(py + ph)),
                          int(rng.integers(0, 256)), -1)  # fmt: skip
    # Blobs and stains.
    for _ in range(rng.integers(3, 10)):
        c = tuple(int(v) for v in rng.integers(0, size, 2))
        ax = tuple(int(v) for v in rng.integers(3, size // 8, 2))
        cv2.ellipse(img, c, ax, float(rng.uniform(0, 180)), 0, 360,
                    int(rng.integers(0, 256)), -1)  # fmt: skip
    # Cracks and seams.
    for _ in range(rng.integers(1, 6)):
        p = rng.integers(0, size, 4)
        cv2.line(img, (int(p[0]), int(p[1])), (int(p[2]), int(p[3])), int(rng.integers(0, 256)),
                 int(rng.integers(1, 4)))  # fmt: skip
    # Fine specks: corners for close-up views.
    n = int(rng.integers(150, 400))
    xy = rng.integers(0, size - 3, (n, 2))
    vals = rng.integers(0, 256, n)
    for (x, y), v in zip(xy, vals, strict=True):
        img[y : y + 3, x : x + 3] = v
    return img


class TextureCache:
    """Mip pyramids of tile textures, generated on first use (LRU)."""

    def __init__(self, seed: int, capacity: int = 600) -> None:
        self.seed = seed
        self.capacity = capacity
        self._cache: OrderedDict[int, list[np.ndarray]] = OrderedDict()

    def pyramid(self, tile_id: int) -> list[np.ndarray]:
        pyr = self._cache.get(tile_id)
        if pyr is not None:
            self._cache.move_to_end(tile_id)
            return pyr
        tex = make_texture(self.seed, tile_id)
        pyr = [tex]
        while pyr[-1].shape[0] > 8:
            pyr.append(cv2.pyrDown(pyr[-1]))
        self._cache[tile_id] = pyr
        if len(self._cache) > self.capacity:
            self._cache.popitem(last=False)
        return pyr
