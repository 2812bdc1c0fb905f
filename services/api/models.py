"""Response models of the REST API."""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel

from shared.geometry import pose_to_tq


class PoseOut(BaseModel):
    agent: str
    map_id: str
    stamp_ns: int
    t: float
    position: list[float]
    quaternion_xyzw: list[float]
    kf_ref: int
    tracking: str
    fps: float


class AgentOut(BaseModel):
    agent: str
    map_id: str
    n_kf: int
    n_mp: int
    scale_to_map: float
    last_pose: PoseOut | None


class KeyframeOut(BaseModel):
    id: int
    stamp_ns: int
    position: list[float]
    quaternion_xyzw: list[float]


class TrajectoryOut(BaseModel):
    agent: str
    map_id: str
    frame: str = "map"
    keyframes: list[KeyframeOut]


class MapOut(BaseModel):
    map_id: str
    agents: list[str]
    n_kf: int
    created_ns: int
    keyframes_per_agent: dict[str, int] = {}
    merged_into: str | None = None


class PointsOut(BaseModel):
    map_id: str
    n: int
    points: list[list[float]]


class ErrorOut(BaseModel):
    error: str
    detail: object | None = None


def pose_out(doc: dict) -> PoseOut:
    p, q = pose_to_tq(np.asarray(doc["T_m_c"], float))
    return PoseOut(
        agent=doc["agent"], map_id=doc.get("map_id", ""), stamp_ns=int(doc["stamp_ns"]),
        t=int(doc["stamp_ns"]) * 1e-9, position=p.tolist(), quaternion_xyzw=q.tolist(),
        kf_ref=int(doc.get("kf_ref", -1)), tracking=str(doc.get("tracking", "ok")),
        fps=float(doc.get("fps", 0.0)),
    )  # fmt: skip
