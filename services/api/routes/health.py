"""Liveness, readiness and Prometheus metrics."""

from __future__ import annotations

import redis
from fastapi import APIRouter, Response
from fastapi.responses import JSONResponse

from shared.metrics import metrics_text

from ..deps import StoreDep

router = APIRouter(tags=["health"])


@router.get("/health")
def health() -> dict:
    return {"status": "ok"}


@router.get("/ready", responses={503: {"description": "Redis unreachable", "content": {
    "application/json": {"schema": {"type": "object"}}}}})  # fmt: skip
def ready(store: StoreDep):
    try:
        store.ping()
    except redis.RedisError as e:
        return JSONResponse({"status": "not ready", "error": f"redis: {e}"}, status_code=503)
    return {"status": "ready"}


TEXT = {"text/plain": {"schema": {"type": "string"}}}


PROMETHEUS = {200: {"description": "Prometheus text format", "content": TEXT}}


@router.get("/metrics", response_class=Response, responses=PROMETHEUS)
def metrics() -> Response:
    body, ctype = metrics_text()
    return Response(body, media_type=ctype)
