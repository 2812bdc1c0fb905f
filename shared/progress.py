"""Progress bars for long commands (rendering, team runs, benches), on stderr via rich.

On a terminal they redraw in place; in a log (no TTY) rich prints the final state
once, so logs stay readable. ``HIVEMAP_NO_PROGRESS=1`` turns them off.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterator


@contextlib.contextmanager
def progress(
    description: str, total: float | None = None, unit: str = ""
) -> Iterator[Callable[..., None]]:
    """A bar; yields ``update(advance=1, completed=None, info="")``. ``total=None``: a
    pulsing bar for work of unknown length."""
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    cols = [
        TextColumn("[bold]{task.description}"), BarColumn(),
        MofNCompleteColumn() if total else TextColumn("{task.completed:.0f}"),
        TextColumn(unit), TextColumn("{task.fields[info]}"), TimeElapsedColumn(),
    ]  # fmt: skip
    if total:
        cols.append(TimeRemainingColumn())
    disable = os.environ.get("HIVEMAP_NO_PROGRESS", "") not in ("", "0")
    with Progress(*cols, console=Console(stderr=True), disable=disable) as p:
        task = p.add_task(description, total=total, info="")

        def update(advance: float = 1, completed: float | None = None, info: str | None = None,
                   description: str | None = None) -> None:  # fmt: skip
            kw: dict = {"completed": completed} if completed is not None else {"advance": advance}
            if info is not None:
                kw["info"] = info
            if description is not None:
                kw["description"] = description
            p.update(task, **kw)

        yield update


def track(items, description: str, total: int | None = None):
    """Iterate ``items`` with a bar."""
    n = total if total is not None else (len(items) if hasattr(items, "__len__") else None)
    with progress(description, n) as update:
        for x in items:
            yield x
            update()
