"""Who may read the API: one bearer token (``HIVEMAP_API_TOKEN``).

HTTP clients send ``Authorization: Bearer <token>``; a browser, which cannot put a
header on a page load or a WebSocket, may send ``?token=<token>`` instead (the viewer
URL ``hivemap up`` prints carries it). Both are FastAPI security schemes, so the
OpenAPI document says what every route needs. Only /health, /ready and /metrics
(probes and Prometheus) stay open; they reveal no agent or map.

Without a token the API is open, which is allowed only while it listens on loopback:
:func:`check_exposure` refuses anything else before a socket is bound.
"""

from __future__ import annotations

import hmac
import ipaddress
from typing import Annotated

from fastapi import HTTPException, Request, Security, WebSocket
from fastapi.responses import JSONResponse
from fastapi.security import APIKeyQuery, HTTPAuthorizationCredentials, HTTPBearer
from starlette.requests import HTTPConnection

from shared.settings import Settings

_bearer = HTTPBearer(
    auto_error=False, scheme_name="bearer", description="HIVEMAP_API_TOKEN as a bearer token"
)
_query = APIKeyQuery(
    name="token", auto_error=False, scheme_name="token",
    description="HIVEMAP_API_TOKEN as a query parameter, for the viewer and WebSockets",
)  # fmt: skip


class InsecureConfig(RuntimeError):
    """The API would serve every agent's position to the network without a token."""


class Unauthorized(HTTPException):
    def __init__(self) -> None:
        super().__init__(
            401, detail="missing or wrong API token", headers={"WWW-Authenticate": "Bearer"}
        )
        self.reason = "unauthorized"


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False  # a host name: it may resolve to anything


def check_exposure(settings: Settings) -> None:
    if not settings.api_token.get_secret_value() and not is_loopback(settings.api_host):
        raise InsecureConfig(
            f"the API would listen on {settings.api_host} without a token: set HIVEMAP_API_TOKEN"
            " (`python -c 'import secrets; print(secrets.token_urlsafe(32))'`) or bind it to"
            " 127.0.0.1"
        )


def token_ok(expected: str, authorization: str | None, query_token: str | None) -> bool:
    """Constant-time check of a header ``Bearer <t>`` or a query token against ``expected``."""
    if not expected:
        return True
    given = None
    if authorization:
        scheme, _, value = authorization.partition(" ")
        if scheme.lower() == "bearer":
            given = value.strip()
    if given is None:
        given = query_token
    return given is not None and hmac.compare_digest(given.encode(), expected.encode())


def connection_ok(conn: HTTPConnection) -> bool:
    """For the WebSocket route (HTTP security dependencies take a Request, not a socket)."""
    expected = conn.app.state.settings.api_token.get_secret_value()
    return token_ok(expected, conn.headers.get("authorization"), conn.query_params.get("token"))


async def refused(ws: WebSocket) -> bool:
    """True when the socket lacks the token; it is then answered with HTTP 401 (WebSocket
    denial response) where the server supports it, else closed with policy violation, and
    never accepted."""
    if connection_ok(ws):
        return False
    from .metrics import API_REJECTED

    API_REJECTED.labels("unauthorized").inc()
    try:
        await ws.send_denial_response(JSONResponse(
            {"error": "missing or wrong API token", "detail": None}, status_code=401,
            headers={"WWW-Authenticate": "Bearer"}))  # fmt: skip
    except RuntimeError:
        await ws.close(code=1008)
    return True


async def require_token(
    request: Request,
    bearer: Annotated[HTTPAuthorizationCredentials | None, Security(_bearer)],
    token: Annotated[str | None, Security(_query)],
) -> None:
    expected = request.app.state.settings.api_token.get_secret_value()
    header = f"Bearer {bearer.credentials}" if bearer is not None else None
    if not token_ok(expected, header, token):
        raise Unauthorized()


Protected = [Security(require_token)]
