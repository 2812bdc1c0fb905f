"""The API app: REST for agents and maps, a WebSocket of live poses, a live viewer.

Reads only: all state comes from Redis through shared.store (written by the mapper;
its docstring is the schema), live poses as its ``LivePose`` records.
"""

from __future__ import annotations

import time

from fastapi import FastAPI, HTTPException, Request
from fastapi.exceptions import RequestValidationError

from shared.settings import Settings
from shared.store import Store, connect

from .errors import http_error, validation_error
from .metrics import REQUEST_SECONDS, REQUESTS
from .routes import agents, health, live, maps, viewer, ws


def create_app(settings: Settings) -> FastAPI:
    app = FastAPI(
        title="HiveMap",
        version="0.1.0",
        description="Collaborative monocular SLAM: agents, maps, live poses.",
    )
    app.state.settings = settings
    app.state.store = Store(connect(settings.redis_url))
    app.add_exception_handler(HTTPException, http_error)
    app.add_exception_handler(RequestValidationError, validation_error)
    from starlette.exceptions import HTTPException as StarletteHTTPException

    app.add_exception_handler(StarletteHTTPException, http_error)

    @app.middleware("http")
    async def count(request: Request, call_next):
        t0 = time.perf_counter()
        response = await call_next(request)
        route = request.scope.get("route")
        path = getattr(route, "path", "unmatched")
        REQUESTS.labels(path, str(response.status_code)).inc()
        REQUEST_SECONDS.labels(path).observe(time.perf_counter() - t0)
        return response

    for r in (agents.router, maps.router, health.router, ws.router, live.router, viewer.router):
        app.include_router(r)
    return app
