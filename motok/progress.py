"""One place for progress bars: rich bars with rates, silenced by ``--quiet`` or when not a TTY
in CI logs (where a bar would spam), so every long loop gets the same look.

What is shown is decided in one place: :func:`configure` (the CLI calls it with ``--quiet``;
library users may too), the ``MOTOK_NO_PROGRESS`` environment variable (any value: no bars,
for scripts and torchrun workers) and whether stderr is a terminal.
"""

from __future__ import annotations

import os
import sys

from rich.console import Console
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TaskProgressColumn, TextColumn,
                           TimeElapsedColumn, TimeRemainingColumn)

console = Console(stderr=True)
_quiet = False


def configure(*, quiet: bool) -> None:
    """``quiet=True``: no progress bars and no :func:`info` chatter for the rest of the process.
    Results (tables, JSON) are still printed; errors always are."""
    global _quiet
    _quiet = bool(quiet)


def enabled() -> bool:
    """Whether bars are drawn: not quiet, no ``MOTOK_NO_PROGRESS``, and stderr is a terminal."""
    return not _quiet and os.environ.get("MOTOK_NO_PROGRESS") is None and sys.stderr.isatty()


class _Rate(TextColumn):
    def __init__(self, unit: str):
        super().__init__("")
        self.unit = unit

    def render(self, task):
        from rich.text import Text
        speed = task.finished_speed or task.speed
        return Text("" if speed is None else f"{speed:,.0f} {self.unit}/s", style="progress.data.speed")


def make_progress(unit: str = "it", extra: str = "") -> Progress:
    """A rich Progress with count, rate and ETA; ``extra`` is a format string over task.fields."""
    cols = [TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TaskProgressColumn(),
            _Rate(unit), TimeElapsedColumn(), TimeRemainingColumn()]
    if extra:
        cols.append(TextColumn(extra))
    return Progress(*cols, console=console, disable=not enabled(), transient=False)


def info(msg: str) -> None:
    """A line of chatter on stderr (what was written where), silenced by ``quiet``."""
    if not _quiet:
        console.print(msg)
