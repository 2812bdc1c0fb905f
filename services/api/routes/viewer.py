"""GET /: the live viewer, and /static/*: its script and style.

Written here as plain JavaScript on Canvas 2D, no front-end library: the page is three
small files the API serves from the package, so it works offline (no CDN) and needs no
npm build step in `make install` or the container. Canvas 2D with a pixel buffer for map
points draws tens of thousands of points and 16 agents well above 30 fps in software
(tests/test_viewer.py measures it in Chromium); a WebGL library would buy little here.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse

from ..errors import NotFound
from ..security import Protected

router = APIRouter()

STATIC = Path(__file__).resolve().parents[1] / "static"
FILES = {"viewer.js": "text/javascript", "viewer.css": "text/css"}


# The page needs the token (a viewer URL without it gets a clear 401, not a blank map);
# its script and style hold no data and load without it, as a browser sends no token there.
@router.get("/", include_in_schema=False, dependencies=Protected)
def viewer() -> FileResponse:
    return FileResponse(STATIC / "viewer.html", media_type="text/html",
                        headers={"Cache-Control": "no-cache"})  # fmt: skip


@router.get("/static/{name}", include_in_schema=False)
def static(name: str) -> FileResponse:
    if name not in FILES:
        raise NotFound("file", name)
    return FileResponse(STATIC / name, media_type=FILES[name],
                        headers={"Cache-Control": "no-cache"})  # fmt: skip
