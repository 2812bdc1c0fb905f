"""/maps: server maps, their keyframes per agent and their point clouds."""

from __future__ import annotations

from collections import Counter

from fastapi import APIRouter, Query

from shared.store import Store

from .. import feed
from ..deps import StoreDep
from ..errors import found
from ..models import MapOut, PointsOut

router = APIRouter(prefix="/maps", tags=["maps"])


def _map(store: Store, map_id: str) -> dict:
    return found(store.map_info(map_id), "map", map_id)


@router.get("", response_model=list[MapOut])
def list_maps(store: StoreDep) -> list[MapOut]:
    return [MapOut(**i) for m in store.maps() if (i := store.map_info(m)) is not None]


@router.get("/{map_id}", response_model=MapOut)
def get_map(map_id: str, store: StoreDep) -> MapOut:
    info = _map(store, map_id)
    per_agent = Counter(a for a, _ in store.map_keyframes(map_id))
    return MapOut(**info, keyframes_per_agent=dict(per_agent))


@router.get("/{map_id}/points", response_model=PointsOut)
def map_points(
    map_id: str, store: StoreDep, limit: int = Query(feed.POINTS_CAP, ge=1, le=200_000)
) -> PointsOut:
    """Map point positions in the map frame (every agent whose data is in the map). Past
    ``limit``, an even selection of them, shared out among the map's agents;
    ``n_total`` says how many there are."""
    _map(store, map_id)
    d = feed.points(store, map_id, limit)
    pts = [d["xyz"][i : i + 3] for i in range(0, len(d["xyz"]), 3)]
    return PointsOut(map_id=map_id, n=len(pts), n_total=d["n_total"], points=pts)
