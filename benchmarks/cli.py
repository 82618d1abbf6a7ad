"""What the benchmark scripts share on their command lines: argument types that reject a bad value
while the arguments are parsed, before any work, the data folders they read and the git revision
they time against.

A type here raises ``argparse.ArgumentTypeError``, so argparse exits with status 2, its usage line
and the option's name: ``argument --repeats: expected an integer >= 1, got '0'``.

The scripts import this module in ``main()``, as they do ``baseline.py``: ``tests/conftest.py``
loads a script by its path, without this folder on ``sys.path``, to test its functions.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import subprocess
from pathlib import Path
from typing import Callable

REPO = Path(__file__).resolve().parents[1]


def description(doc: str) -> str:
    """The first paragraph of a script's docstring: its ``--help`` description."""
    return doc.strip().split("\n\n")[0]


def int_at_least(minimum: int) -> Callable[[str], int]:
    """An argparse type: an integer ``>= minimum``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {text!r}")
        return value

    parse.__name__ = f"int_at_least_{minimum}"
    return parse


#: a count of things (repeats, runs, pairs, threads): at least 1
positive_int = int_at_least(1)
#: an index or a count that may be 0 (a pair index, warm-up calls)
nonnegative_int = int_at_least(0)


def finite_float(text: str) -> float:
    """An argparse type: a finite number."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def size_hw(text: str) -> tuple[int, int]:
    """An argparse type: an image size written ``HxW`` (``375x1242``), both sides >= 1."""
    parts = text.lower().split("x")
    try:
        size = tuple(int(p) for p in parts)
    except ValueError:
        size = ()
    if len(size) != 2 or min(size) < 1:
        raise argparse.ArgumentTypeError(f"expected HxW with positive sides (such as 375x1242), got {text!r}")
    return size


def json_object(text: str) -> dict:
    """An argparse type: a JSON object (keyword arguments), such as ``'{"highpass": null}'``."""
    try:
        value = json.loads(text)
    except json.JSONDecodeError as err:
        raise argparse.ArgumentTypeError(f"expected a JSON object, got {text!r} ({err})") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"expected a JSON object, got {text!r} (a {type(value).__name__})")
    return value


def shell_words(text: str) -> str:
    """An argparse type: options for another command, as a shell would split them (kept as written)."""
    try:
        shlex.split(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"cannot split {text!r} as a shell would: {err}") from None
    return text


def data_folder(parser: argparse.ArgumentParser, given: Path | None, default: Path,
                need: tuple[str, ...] = ()) -> Path:
    """The folder ``--data`` names, or ``default`` where it was not given.

    A folder given must exist and hold every one of ``need`` (``parser.error``, exit 2, otherwise);
    the default may be absent: the script then leaves out what it lacks (:func:`present`).
    """
    if given is None:
        return default
    if not given.is_dir():
        parser.error(f"--data: {str(given)!r} not found")
    missing = [name for name in need if not (given / name).exists()]
    if missing:
        parser.error(f"--data: {str(given)!r} lacks {', '.join(missing)}")
    return given


def present(folder: Path, need: tuple[str, ...], what: str) -> bool:
    """Whether ``folder`` holds every one of ``need``; if not, prints ``<what> absent: skipped``
    and what is missing."""
    if not folder.is_dir():
        print(f"{what} absent: skipped ({folder} not found)")
        return False
    missing = [name for name in need if not (folder / name).exists()]
    if missing:
        print(f"{what} absent: skipped ({folder} lacks {', '.join(missing)})")
        return False
    return True


def baseline_revision(parser: argparse.ArgumentParser, given: str | None, default: str | None = None,
                      paths: tuple[str, ...] = ("fsof_torch",)) -> str | None:
    """The git revision to time against, checked before any work; ``None``: no baseline.

    ``given`` is ``--baseline``'s value, ``None`` where it was not given (then ``default``);
    ``none`` means no baseline. A revision given that is no commit of this repository holding
    ``paths`` is an error (``parser.error``, exit 2); the default, where git or the revision is
    unavailable (outside a git checkout, a shallow clone), gives no baseline and a note.
    """
    rev = default if given is None else given
    if rev is None or rev.lower() == "none":
        return None
    problem = None
    for spec in (f"{rev}^{{commit}}", *(f"{rev}:{p}" for p in paths)):
        try:
            done = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--verify", "--quiet", spec],
                                  capture_output=True, text=True)
        except OSError as err:
            problem = f"git: {err}"
            break
        if done.returncode != 0:
            problem = done.stderr.strip() or (f"no {spec.split(':')[1]}/ in it" if ":" in spec else "not a commit")
            break
    if problem is None:
        return rev
    if given is not None:
        parser.error(f"--baseline: cannot use revision {rev!r} of {REPO}: {problem}")
    print(f"(no baseline: the default revision {rev!r} is unavailable here: {problem})")
    return None
