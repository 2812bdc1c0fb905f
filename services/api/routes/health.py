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


@router.get("/ready")
def ready(store: StoreDep):
    try:
        store.ping()
    except redis.RedisError as e:
        return JSONResponse({"status": "not ready", "error": f"redis: {e}"}, status_code=503)
    return {"status": "ready"}


@router.get("/metrics")
def metrics() -> Response:
    body, ctype = metrics_text()
    return Response(body, media_type=ctype)
