"""A deterministic indoor world that contains every EuRoC Machine Hall flight.

The hall is a box (floor, ceiling, four walls) around all five trajectories, filled
with boxes, pillars and shelves that keep ``clearance`` metres from every flight
path. Every surface is split into square tiles of ``tile_m`` metres, each with its
own texture seed, so no two places look alike. Everything is axis-aligned, which
keeps clipping, projection and the geometric tests simple and exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shared.trajectory import SEQUENCES, load_euroc_gt


@dataclass(frozen=True)
class Tile:
    """A textured rectangle: points O + s*U + t*V for s, t in [0, 1]."""

    id: int
    origin: np.ndarray  # (3,)
    U: np.ndarray  # (3,) edge vector
    V: np.ndarray  # (3,) edge vector
    normal: np.ndarray  # (3,) unit, facing the free space
    albedo: float  # brightness factor of the surface


@dataclass(frozen=True)
class Box:
    lo: np.ndarray
    hi: np.ndarray
    kind: str


def _flight_points() -> np.ndarray:
    return np.concatenate([load_euroc_gt(s).positions[::5] for s in SEQUENCES])


class World:
    def __init__(
        self, seed: int = 0, tile_m: float = 2.0, clearance: float = 1.0, n_objects: int = 70
    ) -> None:
        self.seed = seed
        self.tile_m = tile_m
        rng = np.random.default_rng(seed)
        pts = _flight_points()
        lo = pts.min(axis=0) - np.array([4.0, 4.0, 0.0])
        hi = pts.max(axis=0) + np.array([4.0, 4.0, 0.0])
        lo[2] = pts[:, 2].min() - 1.2
        hi[2] = pts[:, 2].max() + 2.5
        self.lo, self.hi = lo, hi
        self.boxes: list[Box] = []
        tries = 0
        while len(self.boxes) < n_objects and tries < 5000:
            tries += 1
            kind = rng.choice(["box", "pillar", "shelf"], p=[0.55, 0.25, 0.2])
            if kind == "box":
                size = rng.uniform([0.4, 0.4, 0.3], [2.0, 2.0, 1.8])
            elif kind == "pillar":
                w = rng.uniform(0.3, 0.8)
                size = np.array([w, w, hi[2] - lo[2]])
            else:
                size = np.array(
                    [rng.uniform(1.5, 4.0), rng.uniform(0.3, 0.6), rng.uniform(1.5, 3.0)]
                )
                if rng.random() < 0.5:
                    size = size[[1, 0, 2]]
            c = rng.uniform(lo[:2] + size[:2] / 2, hi[:2] - size[:2] / 2)
            blo = np.array([c[0] - size[0] / 2, c[1] - size[1] / 2, lo[2]])
            bhi = blo + size
            # Distance from every flight point to the box must exceed the clearance.
            d = np.maximum(np.maximum(blo - pts, pts - bhi), 0.0)
            if np.linalg.norm(d, axis=1).min() < clearance:
                continue
            self.boxes.append(Box(blo, bhi, str(kind)))
        self.tiles: list[Tile] = []
        self._build_tiles(rng)

    # --- geometry -------------------------------------------------------------------------
    def _add_rect(self, rng, origin, U, V, normal) -> None:
        """Split a rectangle into tiles of about tile_m."""
        nu = max(1, int(np.ceil(np.linalg.norm(U) / self.tile_m)))
        nv = max(1, int(np.ceil(np.linalg.norm(V) / self.tile_m)))
        du, dv = U / nu, V / nv
        albedo = float(rng.uniform(0.75, 1.15))
        for i in range(nu):
            for j in range(nv):
                self.tiles.append(
                    Tile(len(self.tiles), origin + i * du + j * dv, du, dv, normal, albedo)
                )

    def _box_faces(self, rng, lo, hi, inward: bool, skip_bottom: bool) -> None:
        ex = hi - lo
        X, Y, Z = np.eye(3)
        sgn = -1.0 if inward else 1.0
        faces = [
            (lo, Y * ex[1], Z * ex[2], -X),  # x = lo
            (lo + X * ex[0], Z * ex[2], Y * ex[1], X),  # x = hi
            (lo, Z * ex[2], X * ex[0], -Y),  # y = lo
            (lo + Y * ex[1], X * ex[0], Z * ex[2], Y),  # y = hi
            (lo, X * ex[0], Y * ex[1], -Z),  # z = lo (bottom)
            (lo + Z * ex[2], Y * ex[1], X * ex[0], Z),  # z = hi (top)
        ]
        for k, (o, U, V, n) in enumerate(faces):
            if skip_bottom and k == 4:
                continue
            self._add_rect(rng, o, U, V, sgn * n)

    def _build_tiles(self, rng) -> None:
        self._box_faces(rng, self.lo, self.hi, inward=True, skip_bottom=False)
        for b in self.boxes:
            self._box_faces(rng, b.lo, b.hi, inward=False, skip_bottom=True)
        self.tile_origin = np.array([t.origin for t in self.tiles])
        self.tile_U = np.array([t.U for t in self.tiles])
        self.tile_V = np.array([t.V for t in self.tiles])
        self.tile_normal = np.array([t.normal for t in self.tiles])
        self.tile_center = self.tile_origin + 0.5 * (self.tile_U + self.tile_V)
        self.tile_radius = 0.5 * np.linalg.norm(self.tile_U + self.tile_V, axis=1)

    def min_clearance(self, points: np.ndarray) -> float:
        """Smallest distance from any of ``points`` to an obstacle (for tests)."""
        best = np.inf
        for b in self.boxes:
            d = np.maximum(np.maximum(b.lo - points, points - b.hi), 0.0)
            best = min(best, float(np.linalg.norm(d, axis=1).min()))
        return best

    def landmarks(self, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """``n`` points spread over the surfaces by area, with their tile ids (for the
        feature-level simulated agent: the same geometry as the rendered world)."""
        rng = np.random.default_rng(seed)
        area = np.linalg.norm(np.cross(self.tile_U, self.tile_V), axis=1)
        ids = rng.choice(len(self.tiles), size=n, p=area / area.sum())
        s, t = rng.random(n), rng.random(n)
        pts = self.tile_origin[ids] + s[:, None] * self.tile_U[ids] + t[:, None] * self.tile_V[ids]
        return pts, ids
