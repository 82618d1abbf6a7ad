"""The evaluation job's output paths and image sizes, checked before any work, as the refine job
checks its own: a folder option names a folder or a path that can be created; a file option names
no folder and a path whose missing folders can be created (the job creates them when it writes);
``--json`` names none of the job's other outputs nor a file in another run's output folder that is read
back (a refine run's, a rendered sequence's); a size has no side above :data:`MAX_SIDE`. Each
check returns the error message, naming the option, or None. Once the checks pass, a job removes
the files an earlier run left in its folder (:func:`remove_outputs`), so that the folder never
mixes two runs."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Iterable

from fsof_torch.data.scene.render import MAX_SIDE  # noqa: F401 (the largest side of a size option, the renderer's)
from fsof_torch.io.atomic import creation_error
from fsof_torch.io.atomic import lookup_error as bad_lookup  # (the refine job's check too)
# (the types of path options: an empty path is refused, and for a file one ending in '/')
from refine.resume import file_path, given_path  # noqa: F401


def bad_file(path: Path | None, option: str, out: Path | None = None) -> str | None:
    """``path`` (None: not asked for) can be written as a file (:func:`bad_lookup`), and is neither
    ``out`` (the job's ``--out`` folder, None: none) nor a folder above it (``--out`` would be
    created as a folder there)."""
    if path is None:
        return None
    bad = bad_lookup(path, option)
    if bad is not None:
        return bad
    if path.is_dir():
        return f"{option}: {str(path)!r} is a folder; expected a file path"
    if out is not None and bad_lookup(out, "--out") is None and out.resolve().is_relative_to(path.resolve()):
        return f"{option}: {str(path)!r} is --out {str(out)!r} or a folder above it; expected a file path outside it"
    return creation_error(path, option)


def bad_folder(path: Path | None, option: str, files: Iterable[str] = ()) -> str | None:
    """``path`` (None: not asked for) is a folder or can be created (:func:`bad_lookup`), and none
    of the ``files`` the job writes into it is a folder."""
    if path is None:
        return None
    bad = bad_lookup(path, option)
    if bad is not None:
        return bad
    if path.exists() and not path.is_dir():
        return f"{option}: {str(path)!r} is a file; expected a folder (it is created if missing)"
    bad = creation_error(path, option, folder=True)
    if bad is not None:
        return bad
    for name in files:
        if (path / name).is_dir():
            return f"{option}: {str(path / name)!r} is a folder, where the job writes a file"
    return None


def bad_json_target(path: Path | None, outputs: Iterable[Path],
                    inputs: dict[str, Path | None] | None = None) -> str | None:
    """``--json`` (``path``, None: not asked for) names none of the files the job writes
    (``outputs``) or reads (``inputs``, by option; None where not given), nor a path inside an
    input folder (a sample's other files): the JSON, written last, would replace it. (A path the
    system cannot look up is not compared: :func:`bad_lookup` names it, in :func:`bad_file` or
    :func:`bad_folder`.)"""
    if path is None or bad_lookup(path, "--json") is not None:
        return None
    target = path.resolve()
    for option, given in (inputs or {}).items():
        if given is None or bad_lookup(given, option) is not None:
            continue
        if given.resolve() == target:
            return f"--json: {str(path)!r} is the input {option}; give another path"
        if given.is_dir() and target.is_relative_to(given.resolve()):
            return f"--json: {str(path)!r} is inside the input {option} {str(given)!r}; give another path"
    for output in outputs:
        if bad_lookup(output, "--out") is None and output.resolve() == target:
            return (f"--json: {str(path)!r} names {output.name}, a file the job writes into {str(output.parent)!r}; "
                    f"give another path")
    return other_run_above(path)


def other_run_above(path: Path) -> str | None:
    """``--json`` (``path``) lies in no output folder of another run that is read back: a refine
    run's (:func:`refine_run_above`) or a sequence that ``eval synth`` wrote
    (:func:`sequence_above`). (A path the system cannot look up is :func:`bad_lookup`'s to name.)"""
    if bad_lookup(path, "--json") is not None:
        return None
    return first_bad(refine_run_above(path), sequence_above(path))


def sequence_above(path: Path) -> str | None:
    """``--json`` (``path``) lies in no folder of a rendered sequence (a ``meta.json`` of the
    synthetic layout, :data:`fsof_torch.io.layout.SYNTHETIC_FORMAT`): the JSON would replace the
    sequence's meta.json or a pair's params, and the sequence would no longer read back."""
    from fsof_torch.io.layout import SYNTHETIC_FORMAT

    for folder in path.resolve().parents:
        try:
            meta = json.loads((folder / "meta.json").read_text())
        except (OSError, ValueError):
            continue
        if isinstance(meta, dict) and meta.get("format") == SYNTHETIC_FORMAT:
            return (f"--json: {str(path)!r} is inside {str(folder)!r}, a rendered sequence (its meta.json), "
                    f"whose files it would replace; give a path outside it")
    return None


def refine_run_above(path: Path) -> str | None:
    """``--json`` (``path``) lies in no output folder of a refine run (:func:`refine.resume.holds_run`):
    the JSON, removed at the start and written last, would replace that run's report.json, its
    manifest or a record."""
    from refine.resume import holds_run

    other = next((p for p in path.resolve().parents if holds_run(p)), None)
    if other is None:
        return None
    return (f"--json: {str(path)!r} is inside {str(other)!r}, the output folder of a refine run (its run.json), "
            f"whose report, manifest or records it would replace; give a path outside it")


def bad_out_inputs(out: Path, names: Iterable[str], inputs: dict[str, Path | None]) -> str | None:
    """None of the files ``names`` that the job writes into ``out``, or removes there before it
    writes (:func:`remove_outputs`), is an input (``inputs``, by option; None where not given):
    a flow file named like a figure, given with its folder as ``--out``, was deleted and replaced.
    (A path the system cannot look up is not compared: :func:`bad_lookup` names it.)"""
    if bad_lookup(out, "--out") is not None:
        return None
    for option, given in inputs.items():
        if given is None or bad_lookup(given, option) is not None:
            continue
        for name in names:
            if (out / name).resolve() == given.resolve():
                return (f"--out: {str(out)!r} holds the input {option} {str(given)!r} as {name}, a file the job "
                        f"removes and writes there; give another --out")
    return None


def bad_size(size: Iterable[int] | None, option: str) -> str | None:
    """``size`` (H, W; None: not given) has no side above :data:`MAX_SIDE`."""
    if size is None or max(size) <= MAX_SIDE:
        return None
    return f"{option}: expected H, W <= {MAX_SIDE}, got {list(size)}"


def first_bad(*messages: str | None) -> str | None:
    """The first message that is not None."""
    return next((m for m in messages if m is not None), None)


def remove_outputs(folder: Path, names: Iterable[str]) -> None:
    """Remove the files ``names`` from ``folder``, every file the job can write there, before the
    job writes any: an earlier run's, which this run may not write again (a plot it skips, a JSON
    it writes elsewhere), would stay beside the new ones and read as this run's. For a symbolic
    link that is the file it points to, which the job writes through it: the link stays."""
    for name in names:
        path = folder / name
        if path.is_symlink():  # the job writes through a link (fsof_torch.io.atomic): its file is the output
            path = Path(os.path.realpath(path))
        if path.is_file():  # (a folder of that name is not the job's: left)
            path.unlink()


def make_parent(path: Path) -> Path:
    """Create the folders above ``path`` (checked by :func:`bad_file` before the work)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    return path
