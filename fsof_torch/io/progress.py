"""Progress bars of the library's long loops and of the jobs: tqdm on stderr, redrawn as tqdm
redraws on a terminal (or as a notebook's widget), and in a log (stderr a file or a pipe, as under
CI) at most every :data:`LOG_INTERVAL` seconds, with the text shown after the bar updated at those
redraws only, so that a log holds a few lines of progress rather than one per step. And the jobs'
way out where their stdout's reader went away (:func:`silence_stdout`), their stdout where its
encoding lacks a character they print (:func:`tolerant_stdout`), and their warnings while a bar is
drawn (:func:`warnings_above_bars`, :func:`print_above_bars`)."""

from __future__ import annotations

import contextlib
import os
import sys
import warnings
from typing import Any, Iterable, Iterator

__all__ = ["LOG_INTERVAL", "on_terminal", "print_above_bars", "progress_bar", "show_text", "show_values",
           "silence_stdout", "tolerant_stdout", "warnings_above_bars"]

#: seconds between two redraws of a bar whose stderr is not a terminal
LOG_INTERVAL = 10.0


def on_terminal() -> bool:
    """Whether stderr, where the bars go, is a terminal."""
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # no stderr, or a closed one
        return False


def progress_bar(iterable: Iterable | None = None, *, enabled: bool = True, **options: Any):
    """A tqdm bar (``enabled``: shown at all; ``options``: tqdm's): a notebook's widget in a
    notebook, else on stderr, rate-limited in a log; none where the process has no stderr
    (``sys.stderr`` None: started with its stderr closed, ``2>&-``, or by ``pythonw``), where
    drawing one would raise at its first step. Otherwise shown unless tqdm's environment variable
    ``TQDM_DISABLE`` turns off every tqdm bar of the process (a ``disable`` passed to tqdm
    replaced it: the bars stayed on)."""
    from tqdm import notebook
    from tqdm.auto import tqdm

    if not enabled or sys.stderr is None:
        options = {**options, "disable": True}
    if issubclass(tqdm, notebook.tqdm):  # (a notebook's widget: no log to flood)
        return tqdm(iterable, **options)
    if not on_terminal():
        # the clock read at every step: tqdm's own step count between reads, learnt while the steps
        # were fast, left a log silent for several intervals once they slowed, then its monitor
        # thread redrew the bar with the count of its last redraw beside the text of the step now
        options = {"miniters": 1, **options}
    return tqdm(iterable, file=sys.stderr, mininterval=0.1 if on_terminal() else LOG_INTERVAL, **options)


def print_above_bars(text: str) -> None:
    """Print ``text`` (a job's warning) on stderr on lines of its own: a bar being drawn there is
    cleared and drawn again below it (tqdm's ``tqdm.write``), rather than ``text`` following the
    bar's text on the bar's line. Nothing where the process has no stderr (``print`` would write it
    to stdout, among the results)."""
    if sys.stderr is None:
        return
    from tqdm import tqdm

    tqdm.write(text, file=sys.stderr)


def show_text(bar, text: str) -> None:
    """Show ``text`` (the step a loop is on) after the bar: at once on a terminal, at the bar's
    next redraw in a log."""
    bar.set_postfix_str(text, refresh=on_terminal())


def show_values(bar, values: dict[str, str]) -> None:
    """Show ``values`` (e.g. the loss terms) after the bar: at once on a terminal, at the bar's
    next redraw in a log."""
    bar.set_postfix(values, refresh=on_terminal())


def silence_stdout() -> None:
    """Point stdout at the null device, after writing to it raised BrokenPipeError: its reader went
    away (``python -m refine ... | head``). What the job prints later, and Python's own flush of
    stdout at exit, then go nowhere instead of raising again (Python's documented remedy for
    EPIPE, "Note on SIGPIPE" in the ``signal`` module's documentation). A stdout that is no file
    (a test's capture) is left as it is."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, ValueError, OSError):
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
    finally:
        os.close(devnull)


@contextlib.contextmanager
def tolerant_stdout() -> Iterator[None]:
    """Within it, a character that stdout's encoding lacks is printed as its escape (``\\u0394``
    for the tables' Δ, ``\\u03c3`` for σ), as Python prints to stderr, rather than raising
    UnicodeEncodeError once the job's files are written: a stdout redirected to a file on Windows
    writes cp1252, which has neither, and ``PYTHONIOENCODING=ascii`` neither. Its own error
    handler comes back after. A stdout that cannot be reconfigured (a notebook's, a test's
    capture) is left as it is."""
    stream = sys.stdout
    errors = getattr(stream, "errors", None)
    try:
        stream.reconfigure(errors="backslashreplace")
        changed = True
    except (AttributeError, ValueError, OSError):
        changed = False
    try:
        yield
    finally:
        if changed:
            with contextlib.suppress(ValueError, OSError):  # (a closed pipe: its flush)
                stream.reconfigure(errors=errors)


@contextlib.contextmanager
def warnings_above_bars() -> Iterator[None]:
    """Within it, a warning shown while a bar is drawn on stderr is written on lines of its own: the
    bar is cleared, the warning written from the start of the line, and the bar drawn again below it
    (tqdm's ``tqdm.write``), on a terminal and in a log alike. Without it, the warning followed the
    bar's text on the bar's line (``unsupervised+freespace:  50%|... freespace=0.015]/path/train.py:239:
    RuntimeWarning: ...``). Warnings are shown as before otherwise (``warnings.showwarning`` in place
    when it was entered: a filter, ``-W error`` and a recorder such as ``pytest.warns`` act as
    before); it is put back after."""
    from tqdm import tqdm

    shown = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        with tqdm.external_write_mode(file=sys.stderr if file is None else file):
            shown(message, category, filename, lineno, file, line)

    warnings.showwarning = show
    try:
        yield
    finally:
        if warnings.showwarning is show:  # (unless replaced within: that one stays, as it would without)
            warnings.showwarning = shown
