"""JSON errors: every refusal has the same shape and is counted by reason."""

from __future__ import annotations

from typing import TypeVar

from fastapi import HTTPException, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from .metrics import API_REJECTED

T = TypeVar("T")


class NotFound(HTTPException):
    def __init__(self, what: str, ident: str) -> None:
        super().__init__(404, detail=f"unknown {what} {ident!r}")
        self.reason = f"unknown_{what}"


def found(value: T | None, what: str, ident: str) -> T:
    """``value``, or a 404 naming what was not found."""
    if value is None:
        raise NotFound(what, ident)
    return value


async def http_error(request: Request, exc: HTTPException) -> JSONResponse:
    reason = getattr(exc, "reason", f"http_{exc.status_code}")
    API_REJECTED.labels(reason).inc()
    return JSONResponse({"error": str(exc.detail), "detail": None}, status_code=exc.status_code,
                        headers=getattr(exc, "headers", None))  # fmt: skip


async def validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    API_REJECTED.labels("malformed_request").inc()
    detail = [{"loc": list(e.get("loc", ())), "msg": e.get("msg", "")} for e in exc.errors()]
    return JSONResponse({"error": "malformed request", "detail": detail}, status_code=422)
