"""Renderer: EuRoC cam0 images (752x480, radial-tangential) of a :class:`World`.

Each visible tile is rasterized into an ideal pinhole canvas by OpenCV: the tile's
texture is warped with its plane homography (``cv2.warpPerspective`` on the tile's
bounding box only), its footprint filled with ``cv2.fillConvexPoly`` after clipping
at the near plane, and a z-buffer of inverse depth (linear in pixel coordinates for
a plane) decides visibility. The texture level comes from the tile's mip pyramid by
texels per pixel, so far surfaces do not alias. Lens distortion is then applied to
the whole canvas with one precomputed ``cv2.remap``. No per-pixel Python loop.
"""

from __future__ import annotations

import cv2
import numpy as np

from shared.camera import PinholeRadTan

from .texture import TEX_PX, TextureCache
from .world import World

NEAR = 0.05
FAR = 45.0
LIGHT = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])


class Renderer:
    def __init__(
        self,
        world: World,
        camera: PinholeRadTan | None = None,
        noise_sigma: float = 2.0,
        exposure_amp: float = 0.12,
        seed: int | None = None,
    ) -> None:
        self.world = world
        self.cam = camera or PinholeRadTan.euroc_cam0()
        self.noise_sigma = noise_sigma
        self.exposure_amp = exposure_amp
        self.seed = world.seed if seed is None else seed
        self.textures = TextureCache(world.seed)
        self._setup_canvas()

    def _setup_canvas(self) -> None:
        """An ideal pinhole canvas large enough for every distorted pixel."""
        cam = self.cam
        u, v = np.meshgrid(np.arange(cam.width, dtype=np.float64),
                           np.arange(cam.height, dtype=np.float64))  # fmt: skip
        xy = cam.undistort_points(np.stack([u.ravel(), v.ravel()], axis=1))
        f = cam.fx
        lo = xy.min(axis=0) * f
        hi = xy.max(axis=0) * f
        pad = 2.0
        self.cx = -lo[0] + pad
        self.cy = -lo[1] * (cam.fx / cam.fy) + pad
        self.fx, self.fy = cam.fx, cam.fy
        self.cw = int(np.ceil(hi[0] - lo[0] + 2 * pad)) + 1
        self.ch = int(np.ceil((hi[1] - lo[1]) * cam.fy / cam.fx + 2 * pad)) + 1
        self.Kc = np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])
        mx = (xy[:, 0] * self.fx + self.cx).reshape(cam.height, cam.width).astype(np.float32)
        my = (xy[:, 1] * self.fy + self.cy).reshape(cam.height, cam.width).astype(np.float32)
        self.map1, self.map2 = cv2.convertMaps(mx, my, cv2.CV_16SC2)
        self.mapx, self.mapy = mx, my
        uu, vv = np.meshgrid(np.arange(self.cw, dtype=np.float32),
                             np.arange(self.ch, dtype=np.float32))  # fmt: skip
        self._xn = (uu - self.cx) / self.fx
        self._yn = (vv - self.cy) / self.fy
        self._tan_x = max(abs(lo[0]), abs(hi[0])) / f
        self._tan_y = max(abs(lo[1]), abs(hi[1])) / f

    def visible_tiles(self, T_w_c: np.ndarray) -> np.ndarray:
        w = self.world
        R, C = T_w_c[:3, :3], T_w_c[:3, 3]
        facing = np.einsum("ij,ij->i", w.tile_normal, C - w.tile_center) > 0
        Xc = (w.tile_center - C) @ R
        r = w.tile_radius
        ok = facing & (Xc[:, 2] + r > NEAR) & (np.linalg.norm(Xc, axis=1) - r < FAR)
        zc = np.maximum(Xc[:, 2], 0.0)
        ok &= np.abs(Xc[:, 0]) - r * 1.5 <= zc * self._tan_x
        ok &= np.abs(Xc[:, 1]) - r * 1.5 <= zc * self._tan_y
        return np.nonzero(ok)[0]

    def render(self, T_w_c: np.ndarray, frame: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """(image uint8 HxW, depth float32 HxW in metres along the optical axis)."""
        canvas = np.zeros((self.ch, self.cw), np.float32)
        invz = np.zeros((self.ch, self.cw), np.float32)
        w = self.world
        R, C = T_w_c[:3, :3], T_w_c[:3, 3]
        Rt = R.T
        vis = self.visible_tiles(T_w_c)
        # Front to back, so a tile hidden behind nearer ones is skipped before any
        # per-pixel work (most of a cluttered hall is occluded).
        order = np.argsort(np.linalg.norm(w.tile_center[vis] - C, axis=1) - w.tile_radius[vis])
        corners_all = np.stack(
            [w.tile_origin, w.tile_origin + w.tile_U, w.tile_origin + w.tile_U + w.tile_V,
             w.tile_origin + w.tile_V], axis=1)[vis[order]]  # fmt: skip
        Pc_all = (corners_all - C) @ R
        for i, Pc in zip(vis[order].tolist(), Pc_all, strict=True):
            O, U, V, n = w.tile_origin[i], w.tile_U[i], w.tile_V[i], w.tile_normal[i]
            poly = Pc if Pc[:, 2].min() >= NEAR else _clip_near(Pc)
            if len(poly) < 3:
                continue
            uv = np.empty((len(poly), 2))
            uv[:, 0] = self.fx * poly[:, 0] / poly[:, 2] + self.cx
            uv[:, 1] = self.fy * poly[:, 1] / poly[:, 2] + self.cy
            x0 = max(int(np.floor(uv[:, 0].min())), 0)
            y0 = max(int(np.floor(uv[:, 1].min())), 0)
            x1 = min(int(np.ceil(uv[:, 0].max())) + 1, self.cw)
            y1 = min(int(np.ceil(uv[:, 1].max())) + 1, self.ch)
            if x1 <= x0 or y1 <= y0:
                continue
            nc = Rt @ n
            Oc = Rt @ (O - C)
            dc = float(nc @ Oc)
            if dc >= -1e-9:
                continue  # seen edge-on or from behind
            sl = (slice(y0, y1), slice(x0, x1))
            zmin = float(poly[:, 2].min())
            if invz[sl].min() > 1.0 / zmin:
                continue  # every pixel of its box already shows something nearer
            # Inverse depth of the plane, linear in pixel coordinates.
            iz = (nc[0] * self._xn[sl] + nc[1] * self._yn[sl] + nc[2]) / np.float32(dc)
            mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
            pts = np.round((uv - [x0, y0]) * 16).astype(np.int32)
            cv2.fillConvexPoly(mask, pts, 1, cv2.LINE_8, 4)
            win = (mask > 0) & (iz > invz[sl])
            if not win.any():
                continue
            # Texels per pixel at the tile's visible centroid picks the mip level.
            cen = poly.sum(axis=0) / len(poly)
            zc = float(cen[2])
            cos = abs(float(nc @ cen)) / float(np.sqrt(cen @ cen))
            texel = np.linalg.norm(U) / TEX_PX
            tpp = zc / self.fx / texel / max(np.sqrt(cos), 0.2)
            pyr = self.textures.pyramid(i)
            level = int(np.clip(np.floor(np.log2(max(tpp, 1e-6))), 0, len(pyr) - 1))
            tex = pyr[level]
            S = tex.shape[0]
            H = self.Kc @ np.stack([Rt @ (U / S), Rt @ (V / S), Oc], axis=1)
            H = np.array([[1, 0, -x0], [0, 1, -y0], [0, 0, 1.0]]) @ H
            warped = cv2.warpPerspective(tex, H, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR,
                                         borderMode=cv2.BORDER_REFLECT)  # fmt: skip
            shade = w.tiles[i].albedo * (0.6 + 0.4 * max(float(n @ LIGHT), 0.0))
            np.copyto(canvas[sl], warped * np.float32(shade), where=win)
            np.copyto(invz[sl], iz, where=win)
        img = cv2.remap(canvas, self.map1, self.map2, cv2.INTER_LINEAR)
        iz = cv2.remap(invz, self.map1, self.map2, cv2.INTER_NEAREST)
        depth = np.where(iz > 0, 1.0 / np.maximum(iz, 1e-9), 0.0).astype(np.float32)
        return self._sensor(img, frame), depth

    def _sensor(self, img: np.ndarray, frame: int) -> np.ndarray:
        """Mild exposure drift and sensor noise, deterministic per (seed, frame)."""
        rng = np.random.default_rng([self.seed, 7919, frame])
        gain = 1.0 + self.exposure_amp * np.sin(2 * np.pi * frame / 300.0 + self.seed)
        out = img * np.float32(gain)
        if self.noise_sigma > 0:
            out += rng.normal(0, self.noise_sigma, img.shape).astype(np.float32)
        return np.clip(out, 0, 255).astype(np.uint8)


def _clip_near(P: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman clip of a polygon (camera frame) against z >= NEAR."""
    out = []
    n = len(P)
    for k in range(n):
        a, b = P[k], P[(k + 1) % n]
        ina, inb = a[2] >= NEAR, b[2] >= NEAR
        if ina:
            out.append(a)
        if ina != inb:
            t = (NEAR - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.array(out) if out else np.zeros((0, 3))
