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

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from shared.camera import PinholeRadTan
from shared.geometry import se3_inv as _se3_inv

from .texture import TEX_PX, TextureCache
from .world import World

NEAR = 0.05
FAR = 45.0
LIGHT = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])


@dataclass(frozen=True)
class Shutter:
    """How the camera takes a frame (all off: an ideal instantaneous global shutter).

    blur: exposure time as a fraction of the frame interval (motion blur);
    rolling: readout time of the whole frame as a fraction of the frame interval;
    exposure: strength of auto-exposure jumps (0 off, 1: the gain jumps by up to
        +-45 % a few times a minute and the camera's loop pulls it back within ~0.5 s);
    samples: poses averaged inside the exposure (0: from the motion, ~2 px apart).
    """

    blur: float = 0.0
    rolling: float = 0.0
    exposure: float = 0.0
    samples: int = 0

    @property
    def off(self) -> bool:
        return self.blur <= 0 and self.rolling <= 0 and self.exposure <= 0

    def tag(self) -> str:
        return f"b{self.blur:g}-r{self.rolling:g}-x{self.exposure:g}-n{self.samples}"


def exposure_gain(seed: int, t_s: np.ndarray | float, strength: float,
                  rate_hz: float = 0.07, settle_s: float = 0.15) -> np.ndarray:  # fmt: skip
    """Auto-exposure jumps: at Poisson instants (``rate_hz``; seeded) the gain steps by a
    factor of up to 1 +- 0.45 * strength, then decays back with time constant
    ``settle_s`` -- what a camera's exposure loop does when a bright light enters the
    view. A deterministic function of time, so every frame rate sees the same light."""
    t = np.atleast_1d(np.asarray(t_s, np.float64))
    if strength <= 0:
        return np.ones_like(t)
    rng = np.random.default_rng([seed, 4241])
    horizon = float(t.max()) + 1.0
    n = rng.poisson(rate_hz * horizon) + 1
    when = np.sort(rng.uniform(0, horizon, n))
    mag = rng.uniform(0.25, 0.45, n) * strength * rng.choice([-1.0, 1.0], n)
    g = np.zeros_like(t)
    for w, m in zip(when, mag, strict=True):
        dt = t - w
        g += np.where(dt >= 0, m * np.exp(-np.maximum(dt, 0) / settle_s), 0.0)
    return np.clip(1.0 + g, 0.3, 2.0)


def _interp_rows(Ts: np.ndarray, knots: np.ndarray, row_t: np.ndarray):
    """Rotation (slerp) and translation (linear) at each row time between pose knots."""
    R = Slerp(knots, Rotation.from_matrix(Ts[:, :3, :3]))(row_t).as_matrix()
    t = np.stack([np.interp(row_t, knots, Ts[:, i, 3]) for i in range(3)], 1)
    return R, t.astype(np.float32)


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
        canvas, invz = self._raster(T_w_c)
        return self._finish(canvas, invz, frame)

    def render_exposure(self, pose_at: Callable[[float], np.ndarray], frame_dt: float,
                        frame: int, shutter: Shutter, gain: float = 1.0,
                        ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
        """A frame taken with a real shutter around time 0 (seconds, relative).

        ``pose_at(tau)`` gives T_w_c at ``tau`` seconds from the frame's timestamp. The
        scene is rasterized once, at the timestamp; the exposure is then the mean of
        the canvas warped to several poses spread over the shutter time, centred on the
        timestamp (``shutter.blur`` of the frame interval), each row at its own time
        when the shutter rolls (``shutter.rolling``: readout of the whole frame, as a
        fraction of the frame interval, top row first). The warp moves each pixel with
        the depth seen at the timestamp, which is exact for the small motions inside
        one exposure except at occlusion edges. ``gain`` scales the light (auto-exposure).
        """
        T_c = pose_at(0.0)
        canvas, invz = self._raster(T_c)
        t_exp = shutter.blur * frame_dt
        t_rs = shutter.rolling * frame_dt
        if t_exp <= 0 and t_rs <= 0:
            return self._finish(canvas * np.float32(gain), invz, frame)
        n = shutter.samples or self._samples(pose_at, T_c, invz, t_exp)
        taus = (np.arange(n) + 0.5) / n * t_exp - t_exp / 2 if t_exp > 0 else np.zeros(1)
        # Row r is read (r / H - 1/2) * t_rs after the centre row.
        row_t = (np.arange(self.ch, dtype=np.float64) / self.ch - 0.5) * t_rs
        z = np.where(invz > 0, 1.0 / np.maximum(invz, 1e-9), FAR).astype(np.float32)
        X = np.stack([self._xn * z, self._yn * z, z], axis=-1)  # canvas pixels, camera frame
        Tc_inv = _se3_inv(T_c)
        acc = np.zeros_like(canvas)
        for tau in taus.tolist():
            if t_rs > 0:
                # Poses at a few row times, interpolated between: rows change slowly.
                knots = np.linspace(row_t[0], row_t[-1], 9)
                Ts = np.stack([Tc_inv @ pose_at(tau + k) for k in knots])
                R, t = _interp_rows(Ts, knots, row_t)
                Xc = np.einsum("rij,rwj->rwi", R.astype(np.float32), X) + t[:, None, :]
            else:
                T = Tc_inv @ pose_at(tau)
                Xc = X @ T[:3, :3].T.astype(np.float32) + T[:3, 3].astype(np.float32)
            zc = np.maximum(Xc[..., 2], NEAR)
            mx = (self.fx * Xc[..., 0] / zc + self.cx).astype(np.float32)
            my = (self.fy * Xc[..., 1] / zc + self.cy).astype(np.float32)
            acc += cv2.remap(canvas, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        return self._finish(acc * np.float32(gain / len(taus)), invz, frame)

    def _samples(self, pose_at, T_c: np.ndarray, invz: np.ndarray, t_exp: float) -> int:
        """Enough poses that neighbouring copies are ~2 px apart (a smooth streak; at most
        12, past which the streak is long enough that tracking sees it as a smear)."""
        if t_exp <= 0:
            return 1
        g = invz[::24, ::24]
        z = np.where(g > 0, 1.0 / np.maximum(g, 1e-9), FAR)
        X = np.stack([self._xn[::24, ::24] * z, self._yn[::24, ::24] * z, z], -1).reshape(-1, 3)
        uv = []
        for tau in (-t_exp / 2, t_exp / 2):
            T = _se3_inv(T_c) @ pose_at(tau)
            Xc = X @ T[:3, :3].T + T[:3, 3]
            zc = np.maximum(Xc[:, 2], NEAR)
            uv.append(np.stack([self.fx * Xc[:, 0] / zc, self.fy * Xc[:, 1] / zc], 1))
        streak = float(np.percentile(np.linalg.norm(uv[1] - uv[0], axis=1), 95))
        return int(np.clip(np.ceil(streak / 2.0) + 1, 2, 12))

    def _raster(self, T_w_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ideal pinhole canvas (radiance) and its inverse depth."""
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
        return canvas, invz

    def _finish(self, canvas: np.ndarray, invz: np.ndarray, frame: int):
        """Lens distortion, exposure drift and sensor noise of a radiance canvas."""
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
