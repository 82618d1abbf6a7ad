"""The output folder of a run: its fingerprint, the manifest ``OUT/run.json``, the lock that keeps
two runs from writing into one folder, and the cleaning of temporaries a killed run left.

A run's *identity* is everything that decides its results: the input (a synthetic scene's preset,
seed, size and noise; a folder's path, calibration and poses contents, camera options), the flow
sources (test-net weights and user networks by their contents), the odometry variants and the
refinement options, the library's version and code (:func:`code_digest`) and the versions of the
libraries it computes with (:func:`dependency_versions`). Its fingerprint is a hash of that identity.
Each pair's record also stores the fingerprint of the pair's own inputs (the contents of its
images and flow, road and ground-truth files, its poses).

Resuming: a record counts as finished only when both fingerprints match the current run's (and
the flow file beside it is the one it was written with: ``refine.job.read_record``).
Every run removes the report and clip summaries of the run before it first (they are written
last), so a run that fails leaves no report that contradicts the records it rewrote.
A rerun into a folder that holds a run of another identity stops with a message naming what
differs (``--overwrite`` deletes that run's outputs first), unless that run left nothing but its
manifest (it stopped before its first record: its manifest is replaced). A manifest that cannot
be read, or names no outputs, beside other files stops every run, ``--overwrite`` too: which files
are that run's is unknown, and the job deletes nothing it cannot name. The number of pairs is
not part of the identity: a longer run of the same inputs reuses the pairs it shares with a shorter one
(and a shorter run reports only its own pairs, leaving the other records for a longer run later).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
from pathlib import Path
from typing import Any, Iterator

from fsof_torch.io import code_digest as library_code_digest
from fsof_torch.io import dependency_versions as library_dependency_versions
from fsof_torch.io.atomic import creation_error

from .inputs import JobError

MANIFEST = "run.json"
LOCK = ".refine.lock"
REPORTS = ("report.md", "report.json")
SUMMARY = "summary.png"  # per source


def fingerprint(identity: Any) -> str:
    """A short stable hash (16 hex digits) of a JSON-able description."""
    from fsof_torch.io import to_jsonable

    text = json.dumps(to_jsonable(identity), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def code_digest() -> str:
    """:func:`fsof_torch.io.code_digest` of the library and the job's own package (``refine``):
    BLAKE2b (hex, 32 characters) of the relative path and bytes of every ``.py`` file of both, read
    once per process. The library's version alone stays the same across the edits of a source
    checkout: a run resumed after its algorithms changed would reuse the records of the old code."""
    return library_code_digest(Path(__file__).parent)


# (:func:`fsof_torch.io.dependency_versions`, read once per process: Python's major.minor, torch
# with its build suffix, OpenCV, kornia, NumPy. DIS's flows move with the OpenCV build: a run
# resumed after an upgrade would mix the old build's records with the new's.)
dependency_versions = library_dependency_versions


def _creatable(path: Path, option: str, *, folder: bool = False) -> None:
    """``path`` can be created (:func:`fsof_torch.io.atomic.creation_error`), else a JobError."""
    bad = creation_error(path, option, folder=folder)
    if bad is not None:
        raise JobError(bad)


def check_out_path(out: Path) -> None:
    """``--out`` must be a folder or not exist yet (checked before any work)."""
    if out.exists() and not out.is_dir():
        raise JobError(f"--out: {str(out)!r} is a file; expected a folder (it is created if missing)")
    _creatable(out, "--out", folder=True)


def given_path(text: str) -> Path:
    """The ``type`` of an option that names a file or folder: an empty path (``--out "$OUT"`` with
    ``OUT`` unset), which ``Path`` reads as the current folder, where the job would then write its
    outputs or look for its inputs, names none: argparse exits 2 naming the option."""
    import argparse

    if not text:
        raise argparse.ArgumentTypeError("expected a path, got an empty one ('', which would be the current folder)")
    return Path(text)


def file_path(text: str) -> Path:
    """The ``type`` of an option that names a file the job writes (``--json``, ``eval train``'s
    ``--dump-first-step``): a path whose last part is no file name (``DIR/``, ``DIR/.``, ``..``,
    which ``Path`` would read as ``DIR``, writing a file of that name) names a folder: argparse
    exits 2 naming the option."""
    import argparse

    if text.endswith((os.sep, os.altsep or os.sep)) or os.path.basename(text) in ("", ".", ".."):
        raise argparse.ArgumentTypeError(f"expected a file path, got {text!r}, which names a folder")
    return Path(text)


def check_json_path(path: Path | None, out: Path, inputs: dict[str, Path | None] | None = None) -> None:
    """``--json`` must name a file that can be written, none of the run's inputs (``inputs``: the
    files and folders the options name, by option; None where not given; a path inside an input
    folder is refused too) and nothing inside ``out`` but ``OUT/report.json`` (the report the job
    writes there anyway): the report, removed at the start and written last, would replace it.
    Checked before any work."""
    if path is None:
        return
    if path.is_dir():
        raise JobError(f"--json: {str(path)!r} is a folder; expected a file path such as {str(path / 'report.json')!r}")
    target = path.resolve()
    for option, given in (inputs or {}).items():
        if given is None:
            continue
        source = given.resolve()
        if target == source:
            raise JobError(f"--json: {str(path)!r} is the input {option}; give another path")
        if target.is_relative_to(source):
            raise JobError(f"--json: {str(path)!r} is inside the input {option} {str(given)!r}; give another path")
    folder = out.resolve()
    if target.is_relative_to(folder) and target != folder / REPORTS[1]:
        # the manifest, the report, the records: the JSON would replace one of them, or they it
        raise JobError(f"--json: {str(path)!r} is inside --out {str(out)!r}, which the job fills; give a path "
                       f"outside it (the report is written to {str(out / REPORTS[1])!r} anyway)")
    other = next((p for p in target.parents if p != folder and holds_run(p)), None)
    if other is not None:  # this run's report in place of that run's report, manifest or a record
        raise JobError(f"--json: {str(path)!r} is inside {str(other)!r}, the output folder of another refine run "
                       f"(its {MANIFEST}), whose report, manifest or records it would replace; give a path outside it")
    _creatable(path, "--json")


def holds_run(folder: Path) -> bool:
    """Whether ``folder`` is a refine run's output folder: it holds the lock a run takes, or a
    manifest (a JSON object with the run's fingerprint and identity)."""
    if (folder / LOCK).is_file():
        return True
    try:
        old = json.loads((folder / MANIFEST).read_text())
    except (OSError, ValueError):
        return False
    return isinstance(old, dict) and "fingerprint" in old and "identity" in old


def check_inputs_outside(out: Path, outputs: list[str], inputs: dict[str, Path | None]) -> None:
    """No input (``inputs``: the files and folders the options name, by option; None where not
    given) lies where the run writes or deletes in ``out``: its manifest and reports, the folders
    of its ``outputs`` (one per flow source), and those of the earlier run in ``out`` (which
    ``--overwrite`` deletes). Else a JobError naming ``--out`` and the input, before any work:
    the flows an earlier run refined, given again as ``--flows``, were deleted by ``--overwrite``
    before they were read."""
    folder = out.resolve()
    earlier: list[str] = []
    with contextlib.suppress(OSError, ValueError, AttributeError):
        old = json.loads((out / MANIFEST).read_text())
        earlier = _outputs(old) if isinstance(old, dict) else []
    files = [folder / name for name in (MANIFEST, *REPORTS)]
    folders = [folder / name for name in dict.fromkeys([*outputs, *earlier])]
    for option, given in inputs.items():
        if given is None:
            continue
        source = given.resolve()
        for target in files + folders:
            if source == target or (target in folders and source.is_relative_to(target)):
                where = "" if source == target else f" inside {str(out / target.name)!r}"
                what = "which the run writes" if target in files or target.name in outputs else \
                    "an earlier run's output, which --overwrite deletes"
                raise JobError(f"--out: {str(out)!r} holds the input {option} {str(given)!r}{where}, {what}; "
                               f"give another --out, or move the input out of it")


@contextlib.contextmanager
def locked(out: Path) -> Iterator[None]:
    """Hold an exclusive lock on ``out`` for the run (released when the process ends, even by
    SIGKILL). A second run into the same folder stops with a message.

    A run that created the lock file and leaves the folder without a manifest (it was refused
    before writing one: a folder of other files, say) removes the lock file again, still holding
    the lock: left there, it made the folder pass for a refine run's (:func:`holds_run`), so that
    ``--json`` into it was refused as another run's output folder."""
    out.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not on POSIX: no lock, as before
        yield
        return
    path = out / LOCK
    try:
        fd, created = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o666), True
    except FileExistsError:
        fd, created = os.open(path, os.O_RDWR | os.O_CREAT, 0o666), False
    held = False
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            other = os.read(fd, 32).decode(errors="replace").strip() or "?"
            raise JobError(f"--out: another refine run (pid {other}) is writing into {str(out)!r}; "
                           f"wait for it, or give another --out") from None
        held = True
        os.ftruncate(fd, 0)
        os.write(fd, str(os.getpid()).encode())
        yield
    finally:
        if held and created and not (out / MANIFEST).exists():
            with contextlib.suppress(OSError):
                path.unlink()
        os.close(fd)


def _differences(old: Any, new: Any, prefix: str = "") -> list[str]:
    """Human-readable paths where two identities differ."""
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for k in sorted(set(old) | set(new), key=str):
            out += _differences(old.get(k), new.get(k), f"{prefix}{k}" if not prefix else f"{prefix}.{k}")
        return out
    if old != new:
        a, b = (json.dumps(x, sort_keys=True, default=str) for x in (old, new))
        return [f"{prefix or 'identity'}: {_excerpt(a, b)} -> {_excerpt(b, a)}"]
    return []


def _excerpt(text: str, other: str, width: int = 40) -> str:
    """``text`` in at most ``width`` characters, showing where it first differs from ``other``:
    its start where the difference lies in it, else ``...`` and the part from a few characters
    before the difference (two long paths that differ only in a later folder, such as KITTI's
    ``.../2011_09_26_drive_0001_sync/image_02/data`` and ``..._0002_sync/...``, cut to their
    common start alone read as the same path)."""
    if len(text) <= width:
        return text
    first = next((k for k, (x, y) in enumerate(zip(text, other)) if x != y), min(len(text), len(other)))
    context = 10  # characters shown before the first difference, and at least as many after it
    start = 0 if first + context <= width - 3 else first - context
    head = "..." if start else ""
    body = text[start:]
    return head + (body if len(head) + len(body) <= width else body[:width - len(head) - 3] + "...")


def _outputs(old: dict) -> list[str]:
    """The output folders a manifest names (none where its ``outputs`` is not a list of names)."""
    outputs = old.get("outputs")
    if isinstance(outputs, list) and all(isinstance(o, str) for o in outputs):
        return outputs
    return []


def _no_results(out: Path, old: dict) -> bool:
    """Whether ``out`` holds nothing of the run of manifest ``old`` but the manifest and empty
    output folders (a run that stopped before its first record, e.g. on an error in the clip's fit)."""
    outputs = _outputs(old)
    for p in out.iterdir():
        if p.name in (LOCK, MANIFEST) or _temporary(p):
            continue
        if p.name in outputs and p.is_dir() and not any(q.is_file() and not _temporary(q) for q in p.rglob("*")):
            continue
        return False
    return True


def _temporary(path: Path) -> bool:
    """Whether ``path`` is named like the temporary of an atomic write (a killed run's, or one being
    written: :func:`fsof_torch.io.atomic.remove_stale_temporaries`), which is no result of a run."""
    from fsof_torch.io.atomic import TEMPORARY_NAME

    return bool(TEMPORARY_NAME.match(path.name))


def remove_temporaries(out: Path, outputs: list[str]) -> None:
    """Remove the temporaries a killed run left where the job writes: beside the manifest and
    reports in ``out`` and, at any depth, in the output folders ``outputs`` (one per flow source;
    not through a link). Other folders in ``out`` are left alone: another job may be writing
    into one of them (a temporary removed under it fails its write)."""
    from fsof_torch.io import remove_stale_temporaries

    remove_stale_temporaries(out, recursive=False)
    for sub in dict.fromkeys(outputs):
        target = out / sub
        if target.is_dir() and not target.is_symlink() and target.resolve().parent == out.resolve():
            remove_stale_temporaries(target)


def prepare(out: Path, identity: dict, *, overwrite: bool) -> dict[str, Any]:
    """Make ``out`` ready for the run of ``identity``: refuse (or with ``overwrite`` clear) a
    folder that holds the results of another run, replace the manifest of one that left none
    (a killed write's temporaries count as no result); refuse, even with ``overwrite``, one whose
    manifest names no outputs (it cannot be read) beside other files; then, the folder taken,
    remove the stale temporaries where the job writes (:func:`remove_temporaries`: a refused run
    touches nothing), the earlier report and clip summaries (:func:`remove_reports`), also those
    in a folder without a manifest that ``overwrite`` writes into; write the manifest. Call under
    :func:`locked`, before any record is written. Returns the manifest (with ``fingerprint``)."""
    from fsof_torch.io import write_json

    out.mkdir(parents=True, exist_ok=True)
    fp = fingerprint(identity)
    manifest_path = out / MANIFEST
    old = None
    if manifest_path.is_file():
        try:
            old = json.loads(manifest_path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError):
            old = None
        if not isinstance(old, dict):  # not JSON, or JSON but not a manifest (``[]``, ``5``)
            old = {"fingerprint": None, "identity": "unreadable"}
    if old is not None and old.get("fingerprint") != fp:
        if not _no_results(out, old) and not _outputs(old):
            # --overwrite deletes the outputs a manifest names: this one names none, and the
            # files beside it may be anyone's (deleting them all could lose what is not the job's)
            raise JobError(f"--out: {str(out)!r} holds the results of another run whose manifest "
                           f"{str(manifest_path)!r} cannot be read (not a refine manifest naming its outputs), "
                           f"so the job cannot tell that run's files from others"
                           f"{' and --overwrite deletes none of them' if overwrite else ''}; delete them (or "
                           f"the folder) yourself, or give another --out")
        if not overwrite and not _no_results(out, old):
            diffs = _differences(old.get("identity"), json.loads(json.dumps(identity, default=str)))
            raise JobError(f"--out: {str(out)!r} holds the results of another run ("
                           + "; ".join(diffs[:4]) + ("; ..." if len(diffs) > 4 else "")
                           + "); give another --out, or --overwrite to replace them")
        for sub in _outputs(old):
            target = (out / sub).resolve()
            if target.parent == out.resolve() and target.is_dir():
                shutil.rmtree(target)
    elif old is None:
        leftovers = [p.name for p in out.iterdir() if p.name != LOCK and not _temporary(p)]
        if leftovers and not overwrite:
            raise JobError(f"--out: {str(out)!r} already holds files ({', '.join(sorted(leftovers)[:4])}) "
                           f"but no refine run ({MANIFEST}); give a new or empty folder, or --overwrite "
                           f"to write into it anyway")
    outputs = identity.get("outputs", [])
    # (only now, the folder taken: a run refused here leaves it as it was)
    remove_temporaries(out, [*outputs, *(_outputs(old) if old is not None else [])])
    # the earlier run's report would outlive the records this run rewrites; so would that of a
    # folder without a manifest that --overwrite writes into (and, with --no-figures, its clip
    # summaries for good)
    remove_reports(out, outputs)
    manifest = {"fingerprint": fp, "identity": identity, "outputs": outputs}
    write_json(manifest_path, manifest)
    return manifest


def remove_reports(out: Path, sources: list[str]) -> None:
    """Remove the report (``report.md``, ``report.json``) and the clip summaries
    (``<source>/summary.png``) of an earlier run in ``out``: they describe its records, which this
    run may rewrite (and, should it fail, leave rewritten), and are written again last."""
    for path in [out / name for name in REPORTS] + [out / s / SUMMARY for s in sources]:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
