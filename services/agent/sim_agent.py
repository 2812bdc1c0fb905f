"""Feature-level simulated agent: no images, the same messages as the real agent.

It flies a real EuRoC trajectory through a world of fixed landmarks (each with its
own 256-bit descriptor), observes them through the EuRoC cam0 model with pixel
noise and descriptor bit flips, and estimates its pose like a drifting VO would:
each frame-to-frame motion is perturbed in rotation and translation, and the
translation is multiplied by a scale that drifts. With every noise set to zero the
estimate is the ground truth expressed in the frame of the first camera.

Cheap by design (the load-test agent): per frame a few 4x4 products; per keyframe
one vectorized pass over the landmarks that keeps those inside the view cone and
projects only them (~3 ms on this Xeon, so tens of agents share one core).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field

import cv2
import numpy as np

from shared.camera import PinholeRadTan
from shared.geometry import relative, se3_inv
from shared.messages import MapPoints, NewKeyframe
from shared.trajectory import SEQUENCES, Trajectory, load_euroc_gt


@dataclass
class DriftModel:
    """Noise of the simulated VO, per metre travelled (random walk) and per second."""

    rot_deg_per_sqrt_m: float = 0.05
    trans_m_per_sqrt_m: float = 0.005
    scale_drift_per_s: float = 0.0  # deterministic relative scale change per second
    scale_rw_per_sqrt_s: float = 0.0005
    pixel_sigma: float = 0.7
    bit_flip: float = 0.03
    depth_sigma_rel: float = 0.01

    @staticmethod
    def zero() -> DriftModel:
        return DriftModel(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


class LandmarkWorld:
    """Fixed landmarks on the walls, floor, ceiling and pillars of a hall that
    contains every MH trajectory. Deterministic from the seed; shared by all agents
    of a run so that their observations of a place agree."""

    def __init__(self, seed: int = 0, density: float = 12.0, margin: float = 4.0) -> None:
        rng = np.random.default_rng(seed)
        pos = np.concatenate([load_euroc_gt(s).positions for s in SEQUENCES])
        lo = pos.min(axis=0) - margin
        hi = pos.max(axis=0) + margin
        lo[2] = pos[:, 2].min() - 1.5
        hi[2] = pos[:, 2].max() + 3.0
        pts = [self._box_surface(rng, lo, hi, density)]
        # Pillars away from the flight paths give near structure and parallax.
        n_pillars = 0
        while n_pillars < 40:
            c = rng.uniform(lo[:2] + 1, hi[:2] - 1)
            if np.min(np.linalg.norm(pos[::20, :2] - c, axis=1)) < 1.5:
                continue
            half = rng.uniform(0.2, 0.6, size=2)
            plo = np.array([c[0] - half[0], c[1] - half[1], lo[2]])
            phi = np.array([c[0] + half[0], c[1] + half[1], hi[2]])
            pts.append(self._box_surface(rng, plo, phi, density * 2, sides_only=True))
            n_pillars += 1
        self.points = np.concatenate(pts)
        # float32 copy for culling only (a margin covers its rounding): half the memory
        # traffic of the one pass over every landmark that each keyframe makes.
        self.points32 = self.points.astype(np.float32)
        self.descriptors = rng.integers(0, 256, size=(len(self.points), 32), dtype=np.uint8)
        self.lo, self.hi = lo, hi

    @staticmethod
    def _box_surface(rng, lo, hi, density, sides_only: bool = False) -> np.ndarray:
        ext = hi - lo
        faces = []
        for axis in range(3):
            if sides_only and axis == 2:
                continue
            a, b = [i for i in range(3) if i != axis]
            area = ext[a] * ext[b]
            for side in (lo[axis], hi[axis]):
                n = rng.poisson(area * density)
                p = np.empty((n, 3))
                p[:, axis] = side
                p[:, a] = rng.uniform(lo[a], hi[a], n)
                p[:, b] = rng.uniform(lo[b], hi[b], n)
                faces.append(p)
        return np.concatenate(faces)


@dataclass
class SimKeyframe:
    kf: NewKeyframe
    new_mps: MapPoints
    landmarks: np.ndarray  # landmark ids observed (for covisibility)


@dataclass
class SimAgentState:
    frame: int = 0
    T_l_c: np.ndarray = field(default_factory=lambda: np.eye(4))
    scale: float = 1.0


class SimAgent:
    """Steps through a trajectory; :meth:`step` returns the frame's estimated pose and,
    when the frame becomes a keyframe, the keyframe with its new map points."""

    def __init__(
        self,
        traj: Trajectory,
        world: LandmarkWorld,
        camera: PinholeRadTan | None = None,
        drift: DriftModel | None = None,
        seed: int = 0,
        kf_dist: float = 0.25,
        kf_angle_deg: float = 10.0,
        kf_max_dt: float = 1.0,
        max_features: int = 1000,
        max_range: float = 12.0,
        covis_window: int = 50,
    ) -> None:
        self.traj = traj
        self.world = world
        self.cam = camera or PinholeRadTan.euroc_cam0()
        self.drift = drift or DriftModel()
        self.rng = np.random.default_rng(seed)
        self.kf_dist, self.kf_angle = kf_dist, np.deg2rad(kf_angle_deg)
        self._kf_cos = float(np.cos(self.kf_angle))
        self.kf_max_dt_ns = int(kf_max_dt * 1e9)
        self.max_features, self.max_range = max_features, max_range
        self.state = SimAgentState()
        self.next_kf_id = 0
        self.next_mp_id = 0
        self._mp_of_lm = np.full(len(world.points), -1, np.int64)  # landmark -> map point
        self.last_kf: tuple[int, np.ndarray, np.ndarray, int] | None = None  # id, T_l, T_w, ns
        self.recent: OrderedDict[int, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self.covis_window = covis_window
        self._cone2 = _view_cone_tan2(self.cam)
        self._frustum = _view_frustum(self.cam)

    @property
    def lm_to_mp(self) -> dict[int, int]:
        """Landmark id -> this agent's map point id, for the landmarks it has mapped."""
        lms = np.nonzero(self._mp_of_lm >= 0)[0]
        return dict(zip(lms.tolist(), self._mp_of_lm[lms].tolist(), strict=True))

    def __len__(self) -> int:
        return len(self.traj)

    @property
    def done(self) -> bool:
        return self.state.frame >= len(self.traj)

    def _perturbed_motion(self, T_rel: np.ndarray, dt: float) -> np.ndarray:
        d = self.drift
        dist = float(np.linalg.norm(T_rel[:3, 3]))
        st = self.state
        if d.scale_drift_per_s or d.scale_rw_per_sqrt_s:
            st.scale *= float(
                np.exp(d.scale_drift_per_s * dt + d.scale_rw_per_sqrt_s * np.sqrt(dt)
                       * self.rng.standard_normal())
            )  # fmt: skip
        T = T_rel.copy()
        if d.rot_deg_per_sqrt_m:
            w = self.rng.standard_normal(3) * np.deg2rad(d.rot_deg_per_sqrt_m) * np.sqrt(dist)
            # cv2.Rodrigues: the same matrix as exp_so3 to 1e-16 at a ninth of the cost
            # (scipy's Rotation per single vector was a tenth of a simulated agent's CPU).
            T[:3, :3] = cv2.Rodrigues(w)[0] @ T[:3, :3]
        T[:3, 3] = st.scale * T[:3, 3]
        if d.trans_m_per_sqrt_m:
            T[:3, 3] += self.rng.standard_normal(3) * d.trans_m_per_sqrt_m * np.sqrt(dist)
        return T

    def step(self) -> tuple[int, np.ndarray, SimKeyframe | None]:
        """Advance one frame: (stamp_ns, T_l_c estimate, keyframe or None)."""
        k = self.state.frame
        if k >= len(self.traj):
            raise StopIteration
        T_w_c = self.traj.poses[k]
        stamp = int(self.traj.stamps_ns[k])
        if k > 0:
            T_rel = relative(self.traj.poses[k - 1], T_w_c)
            dt = (stamp - int(self.traj.stamps_ns[k - 1])) * 1e-9
            self.state.T_l_c = self.state.T_l_c @ self._perturbed_motion(T_rel, dt)
        self.state.frame += 1
        kf = self._maybe_keyframe(stamp, T_w_c) if self._is_keyframe(stamp, T_w_c) else None
        return stamp, self.state.T_l_c.copy(), kf

    def _is_keyframe(self, stamp: int, T_w_c: np.ndarray) -> bool:
        if self.last_kf is None:
            return True
        _, _, T_w_last, t_last = self.last_kf
        # Without forming the relative pose (per frame, for every simulated agent): its
        # translation's length is the distance between the centres, and the cosine of
        # its angle is (trace(R_last^T R) - 1) / 2 = (sum(R_last * R) - 1) / 2.
        d = T_w_c[:3, 3] - T_w_last[:3, 3]
        cos_a = 0.5 * (float(np.sum(T_w_last[:3, :3] * T_w_c[:3, :3])) - 1.0)
        return (
            float(d @ d) > self.kf_dist * self.kf_dist
            or cos_a < self._kf_cos
            or stamp - t_last > self.kf_max_dt_ns
        )

    def observe(self, T_w_c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Visible landmark ids, their true camera-frame points and noisy pixels."""
        c, R = T_w_c[:3, 3], T_w_c[:3, :3]
        # Projecting every landmark of the hall cost most of a keyframe; only points in
        # the depth range and inside a cone that contains the image can be valid. The
        # cull runs in float32 over all landmarks as three matrix-vector products (an
        # (N, 3) @ (3, 3) product is slow in numpy), with a 5 cm margin on the depth for
        # float32's rounding; the exact tests are repeated in float64 on the survivors.
        P32 = self.world.points32
        r = R.astype(np.float32)
        off = c.astype(np.float32) @ r
        x = P32 @ r[:, 0] - off[0]
        y = P32 @ r[:, 1] - off[1]
        z = P32 @ r[:, 2] - off[2]
        zn = z + np.float32(0.05)
        cand = (z > 0.15) & (zn < self.max_range + 0.1)
        cand &= x * x + y * y <= np.float32(self._cone2) * zn * zn
        near = np.nonzero(cand)[0]
        D = self.world.points[near] - c
        X_c = D @ R
        x, y, z = X_c[:, 0], X_c[:, 1], X_c[:, 2]
        cand = (z > 0.2) & (z < self.max_range) & (x * x + y * y <= self._cone2 * z * z)
        lim = self.max_range
        cand &= (np.abs(D[:, 0]) < lim) & (np.abs(D[:, 1]) < lim) & (np.abs(D[:, 2]) < lim)
        # The cone is round, the image is not: half of what it keeps cannot project into
        # the image, and projecting (distortion, bounds) is the dearest step per point.
        x0, x1, y0, y1 = self._frustum
        cand &= (x >= x0 * z) & (x <= x1 * z) & (y >= y0 * z) & (y <= y1 * z)
        near, X_c = near[cand], X_c[cand]
        uv, valid = self.cam.project(X_c, min_depth=0.2)
        ids = near[valid]
        X_c, uv = X_c[valid], uv[valid]
        if len(ids) > self.max_features:
            keep = self.rng.choice(len(ids), self.max_features, replace=False)
            keep.sort()
            ids, X_c, uv = ids[keep], X_c[keep], uv[keep]
        if self.drift.pixel_sigma:
            uv = uv + self.rng.normal(0.0, self.drift.pixel_sigma, uv.shape)
        return ids, X_c, uv

    def _maybe_keyframe(self, stamp: int, T_w_c: np.ndarray) -> SimKeyframe:
        T_l_c = self.state.T_l_c.copy()
        ids, X_c, uv = self.observe(T_w_c)
        desc = self.world.descriptors[ids].copy()
        if self.drift.bit_flip:
            desc ^= _bit_flips(self.rng, len(ids), self.drift.bit_flip)
        kf_id = self.next_kf_id
        self.next_kf_id += 1
        mp_ids = self._mp_of_lm[ids]
        new_idx = np.nonzero(mp_ids < 0)[0]
        mp_ids[new_idx] = self.next_mp_id + np.arange(len(new_idx))
        self._mp_of_lm[ids[new_idx]] = mp_ids[new_idx]
        self.next_mp_id += len(new_idx)
        # New map points sit where this keyframe's (scaled, noisy) depth puts them.
        p_ref = X_c[new_idx] * self.state.scale
        if self.drift.depth_sigma_rel and len(new_idx):
            p_ref *= 1.0 + self.rng.normal(0, self.drift.depth_sigma_rel, (len(new_idx), 1))
        new_mps = MapPoints(
            mp_ids[new_idx].copy(),
            np.full(len(new_idx), kf_id, np.int64),
            p_ref.astype(np.float64),
            self.world.descriptors[ids[new_idx]].copy(),
        )
        # Parent: the recent keyframe sharing the most landmarks (covisibility).
        pred_id, T_pred, parent_id, T_par = -1, np.eye(4), -1, np.eye(4)
        if self.last_kf is not None:
            pred_id = self.last_kf[0]
            T_pred = se3_inv(self.last_kf[1]) @ T_l_c
            # Shared landmarks with every recent keyframe in one pass (ids are sorted):
            # the first keyframe with the highest count wins, as a scan in order would.
            owners = list(self.recent)
            lms = np.concatenate([v[0] for v in self.recent.values()])
            who = np.repeat(np.arange(len(owners)), [len(v[0]) for v in self.recent.values()])
            seen = np.zeros(len(self._mp_of_lm), bool)
            seen[ids] = True
            hit = seen[lms]
            w = np.bincount(who[hit], minlength=len(owners))
            best = owners[int(np.argmax(w))] if len(owners) else pred_id
            parent_id = best
            T_par = se3_inv(self.recent[best][1]) @ T_l_c
        kf = NewKeyframe(
            id=kf_id,
            stamp_ns=stamp,
            T_l_kf=T_l_c,
            pred_id=pred_id,
            T_pred_kf=T_pred,
            parent_id=parent_id,
            T_par_kf=T_par,
            keypoints=uv.astype(np.float32),
            octaves=self.rng.integers(0, 4, len(ids)).astype(np.uint8),
            descriptors=desc,
            mp_ids=mp_ids,
            calib=self.cam.to_array(),
        )
        self.recent[kf_id] = (ids, T_l_c)
        while len(self.recent) > self.covis_window:
            self.recent.popitem(last=False)
        self.last_kf = (kf_id, T_l_c, T_w_c, stamp)
        return SimKeyframe(kf, new_mps, ids)


def _bit_flips(rng: np.random.Generator, n: int, p: float) -> np.ndarray:
    """(n, 32) bytes whose 256 bits each are set with probability ``p``, independently.

    Drawn as the gaps between set bits (geometric), not as a uniform per bit: ~p of
    the random numbers (30x fewer at p = 0.03), which was a third of a simulated
    keyframe's cost."""
    total = n * 256
    out = np.zeros(total // 8, np.uint8)
    if total == 0 or p <= 0:
        return out.reshape(n, 32)
    pos = np.empty(0, np.int64)
    last = -1
    while last < total:
        k = int(total * p + 6.0 * np.sqrt(total * p) + 16)
        step = np.cumsum(rng.geometric(p, size=k)) + last
        pos = np.concatenate([pos, step])
        last = int(step[-1])
    pos = pos[pos < total]
    # Positions are distinct, so a byte's set bits add up to their OR.
    out[:] = np.bincount(pos >> 3, weights=1 << (7 - (pos & 7)), minlength=total // 8)
    return out.reshape(n, 32)


def _image_border(cam: PinholeRadTan) -> np.ndarray:
    """Undistorted normalized coordinates of 200 samples along each side of the image."""
    w, h = cam.width - 1, cam.height - 1
    t = np.linspace(0.0, 1.0, 200)
    z = np.zeros_like(t)
    edge = np.concatenate([np.stack([t * w, z], 1), np.stack([t * w, z + h], 1),
                           np.stack([z, t * h], 1), np.stack([z + w, t * h], 1)])  # fmt: skip
    return cam.undistort_points(edge)


def _view_frustum(cam: PinholeRadTan) -> tuple[float, float, float, float]:
    """Bounds (x0, x1, y0, y1) on x/z and y/z of every ray that projects into the
    image: the box around the undistorted image border, widened by 5 % of its size on
    each side (the border is sampled)."""
    u = _image_border(cam)
    (x0, y0), (x1, y1) = u.min(axis=0), u.max(axis=0)
    mx, my = 0.05 * (x1 - x0), 0.05 * (y1 - y0)
    return float(x0 - mx), float(x1 + mx), float(y0 - my), float(y1 + my)


def _view_cone_tan2(cam: PinholeRadTan) -> float:
    """Squared tangent of a cone around the optical axis that contains every ray that
    projects into the image (10 % margin), for culling before projection."""
    r2 = float((_image_border(cam) ** 2).sum(axis=1).max())
    return min(r2 * 1.21, cam.max_r2)
