"""One progress-bar style for every stage (rich)."""

from __future__ import annotations

import sys

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

console = Console(stderr=True)


def progress(disable: bool | None = None) -> Progress:
    """A rich Progress for frames: description, bar, n/N, elapsed, eta, extra fields."""
    if disable is None:
        disable = not sys.stderr.isatty() and not _force()
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        TextColumn("{task.fields[info]}"),
        console=console,
        disable=disable,
        transient=False,
    )


def _force() -> bool:
    import os

    return os.environ.get("WHITECAP_PROGRESS", "") == "1"
