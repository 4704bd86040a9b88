"""Progress bars every long step of selpath shares (rich only: importing this module never imports dask, so a
device's acquisition loop and ``selpath validate`` stay light)."""

from __future__ import annotations

from rich import get_console
from rich.progress import BarColumn, MofNCompleteColumn, TextColumn


def show_bars(progress: bool) -> bool:
    """Whether to draw progress bars: asked for, and on a terminal (a log file gets the engine's lines only)."""
    return progress and get_console().is_terminal


#: the columns every progress bar of selpath starts with (the unit and elapsed time follow): what, bar, done/total
BAR_COLUMNS = (TextColumn("   {task.description}"), BarColumn(bar_width=30), MofNCompleteColumn())
