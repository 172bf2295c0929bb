"""Console output (rich): one console on stderr, quiet mode, a training progress bar, and the one
formatter of numbers in tables and reports."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TaskID, TextColumn, TimeElapsedColumn

console = Console(stderr=True, highlight=False)  # progress and logs
results = Console(highlight=False)  # what a command was asked to show (stdout, never silenced)
_quiet = False


def fmt(v: float | None, nd: int = 3, missing: str = "n/a") -> str:
    """A number with `nd` decimals for tables and reports; `missing` where there is none."""
    return missing if v is None else f"{v:.{nd}f}"


def set_quiet(q: bool) -> None:
    global _quiet
    _quiet = q
    console.quiet = q


def log(msg: str) -> None:
    if not _quiet:
        console.print(msg)


BAR = TaskID(0)  # the one task of a `progress_bar`


@contextlib.contextmanager
def progress_bar(description: str, total: int) -> Iterator[Progress]:
    """A progress bar with a free-text status field (`progress.update(task, status=...)`)."""
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TextColumn("{task.fields[status]}"),
        console=console,
        disable=_quiet,
        transient=False,
    ) as prog:
        prog.add_task(description, total=total, status="")
        yield prog
