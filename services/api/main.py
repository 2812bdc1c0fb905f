"""The API app: REST for agents and maps, a WebSocket of live poses, a live viewer.

Reads only: all state comes from Redis through shared.store (written by the mapper;
its docstring is the schema), live poses as its ``LivePose`` records.
"""

from __future__ import annotations

import time

from fastapi import FastAPI, HTTPException, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from shared.settings import Settings
from shared.store import Store, connect

from .errors import http_error, validation_error
from .metrics import API_REJECTED, REQUEST_SECONDS, REQUESTS
from .models import ErrorOut
from .routes import agents, health, live, maps, viewer, ws
from .security import Protected, check_exposure

# What the data routes may answer besides 200, all in the one error shape (errors.py).
ERRORS = {
    401: {"model": ErrorOut, "description": "missing or wrong API token"},
    404: {"model": ErrorOut, "description": "unknown agent or map"},
    422: {"model": ErrorOut, "description": "malformed request"},
}


def create_app(settings: Settings) -> FastAPI:
    """Raises :class:`~.security.InsecureConfig` for a non-loopback host without a token."""
    check_exposure(settings)
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

    limit = settings.api_max_body_bytes

    @app.middleware("http")
    async def bound_body(request: Request, call_next):
        # Every route is a GET: a body is never needed, so a large one is refused before
        # anything reads it (a chunked body without a length is refused as well).
        length = request.headers.get("content-length")
        chunked = "chunked" in request.headers.get("transfer-encoding", "").lower()
        if chunked or (length is not None and (not length.isdigit() or int(length) > limit)):
            API_REJECTED.labels("body_too_large").inc()
            return JSONResponse({"error": f"request body over {limit} bytes", "detail": None},
                                status_code=413)  # fmt: skip
        return await call_next(request)

    if settings.api_cors_origins:
        from fastapi.middleware.cors import CORSMiddleware

        app.add_middleware(
            CORSMiddleware, allow_origins=settings.api_cors_origins, allow_methods=["GET"],
            allow_headers=["Authorization"],
        )  # fmt: skip

    app.include_router(health.router)
    for r in (agents.router, maps.router):
        app.include_router(r, dependencies=Protected, responses=ERRORS)
    app.include_router(viewer.router)  # the page route checks it; its script and style hold no data
    # The WebSocket routes check the token themselves, before accepting.
    app.include_router(ws.router)
    app.include_router(live.router)
    return app
