"""Injected dependencies: the Store is built once per app from its settings."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from shared.store import Store


def get_store(request: Request) -> Store:
    return request.app.state.store


StoreDep = Annotated[Store, Depends(get_store)]
