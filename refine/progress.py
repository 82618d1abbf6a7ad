"""The job's progress bars: tqdm on stderr, redrawn as tqdm redraws on a terminal, and in a log
(stderr a file or a pipe, as under CI) at most every :data:`LOG_INTERVAL` seconds, with the step
it is on shown at those redraws only, so that a log holds a few lines of progress rather than one
per step."""

from __future__ import annotations

import sys
from typing import Any, Iterable

#: seconds between two redraws of a bar whose stderr is not a terminal
LOG_INTERVAL = 10.0


def on_terminal() -> bool:
    """Whether stderr, where the bars go, is a terminal."""
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # no stderr, or a closed one
        return False


def progress_bar(iterable: Iterable | None = None, *, enabled: bool = True, **options: Any):
    """A tqdm bar on stderr (``enabled``: shown at all; ``options``: tqdm's), rate-limited in a log."""
    from tqdm import tqdm

    return tqdm(iterable, disable=not enabled, file=sys.stderr,
                mininterval=0.1 if on_terminal() else LOG_INTERVAL, **options)


def show_step(bar, text: str) -> None:
    """Show ``text`` (the step the job is on) after the bar: at once on a terminal, at the bar's
    next redraw in a log."""
    bar.set_postfix_str(text, refresh=on_terminal())
