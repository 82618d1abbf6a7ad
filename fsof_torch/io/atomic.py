"""Atomic file writing: write to a temporary file in the target folder, then ``os.replace``.

A crash (an exception, a killed process) while a file is written leaves the old file, or no file,
at the target path: never half a file. Every writer of :mod:`fsof_torch.io` goes through
:func:`atomic_path`.

The temporary file is named ``.<name>.<random>.tmp<suffix>`` (hidden, beside the target; the copy
of the target's name is cut where the whole would pass 255 bytes, so that every name a file system
takes can be written). A process killed between creating and renaming it (SIGKILL, power loss)
leaves it behind; :func:`remove_stale_temporaries` removes such leftovers from a folder before a
job writes there again.

Permissions follow ``open()``: a new file gets mode ``0o666`` less the process's umask, a file
written over keeps its permission bits (a private ``0o600`` file stays private), and a file the
process may not write (read-only to it: ``os.access``) is a PermissionError naming it, not
replaced; a folder it may not write into is a PermissionError naming the target. The temporary is
the owner's to write (``0o600``) while it is written and gets that mode just before the rename, so
a umask that takes the owner's write bit (``0o222``) gives read-only files, as ``open()`` does,
rather than a temporary nobody can write into. A target that is a symbolic link is written through
it, as ``open()`` writes: the file it points to is replaced (its temporary lies beside that file)
and the link stays. Unlike ``open()``, a file with several hard links is replaced under this name
only: its other names keep the old content.
"""

from __future__ import annotations

import contextlib
import errno
import json
import math
import numbers
import os
import re
import secrets
import stat
from pathlib import Path
from typing import Any, Iterator

from .._check import as_path

__all__ = ["atomic_path", "write_bytes", "write_text", "write_json", "to_jsonable", "remove_stale_temporaries",
           "creation_error"]

#: the names :func:`atomic_path` gives its temporary files (:func:`_temporary_name`)
TEMPORARY_NAME = re.compile(r"^\..+\.[0-9a-f]{16}\.tmp(\.[^.]*)?$")
_NAME_MAX = 255  # bytes in a file name: ext4, XFS, Btrfs, APFS
#: the errors of a full disk (or a user's quota spent): a write that meets one names its target
NO_SPACE = (errno.ENOSPC, errno.EDQUOT)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, allow_empty: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``.

    The temporary file lives in the same folder (so ``os.replace`` is a rename on one file
    system) and keeps the suffix of ``path`` (so encoders that pick the format from the file
    name, such as ``cv2.imwrite``, still work). If the body raises, the temporary file is removed
    and the exception propagates; ``path`` is untouched. A body that leaves the file empty is an
    OSError ("nothing was written": an encoder that failed quietly) unless ``allow_empty``, for
    writers of raw bytes and text, where an empty file is data.

    As with ``open()``, a file written over keeps its permission bits (a new one gets ``0o666``
    less the umask), a file the process may not write is a PermissionError naming it (never
    replaced), and a symbolic link is written through: the file it points to is replaced.
    A folder at ``path``, or a path that names one (``out/``: :func:`file_target`), is an
    IsADirectoryError naming it, a missing folder a FileNotFoundError
    naming ``path`` (or, where a file stands in the place of one of its folders, naming that file),
    and a FIFO, device or socket at ``path`` (``/dev/null``, or a link to one such as
    ``/dev/stdout``) a ValueError naming it, which the rename would replace with a regular file;
    each raised before anything is written. A full disk (ENOSPC, or a quota: EDQUOT) met while the
    file is written is an OSError of that errno naming ``path`` (the writer's own names no file).

    Example:
        >>> with atomic_path("out.txt") as tmp:          # doctest: +SKIP
        ...     tmp.write_text("hello")
    """
    path = file_target(path)
    if path.is_symlink():  # write through the link, as open() does, rather than replace the link
        path = Path(os.path.realpath(path))
    if path.is_dir():
        raise IsADirectoryError(f"path: {str(path)!r} is a folder; expected a file path")
    special = special_file(path)
    if special is not None:  # (the rename would put a regular file in its place: /dev/null, a FIFO)
        raise ValueError(f"path: {str(path)!r} is {special}, not a regular file; writing it would replace it with "
                         f"one (the file is written beside it and renamed onto it); give a file path")
    folder = path.parent
    if not folder.is_dir():
        blocker = next((p for p in (folder, *folder.parents) if p.exists()), None)
        if blocker is not None and not blocker.is_dir():  # (not "does not exist": the file is there)
            raise FileNotFoundError(f"path: {str(blocker)!r} is a file, not a folder, so {str(path)!r} cannot be "
                                    f"written")
        raise FileNotFoundError(f"path: the folder of {str(path)!r} does not exist")
    if path.exists() and not os.access(path, os.W_OK):
        # open() refuses to write into it; a rename would replace it all the same (a file made
        # read-only to keep it, such as ground truth, was written over)
        raise PermissionError(f"path: {str(path)!r} is read-only (mode {oct(stat.S_IMODE(path.stat().st_mode))}); "
                              f"make it writable to write over it, or write elsewhere")
    tmp, mode = _create_temporary(folder, path)
    try:
        yield tmp
        if not tmp.is_file() or (tmp.stat().st_size == 0 and not allow_empty):
            raise OSError(f"path: nothing was written for {str(path)!r}")
        # flush to the disk before the rename, so that a power loss cannot leave an empty file
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        with contextlib.suppress(FileNotFoundError):
            # open() keeps the permissions of a file it writes over (not its set-id bits: the
            # kernel clears those on a write)
            mode = stat.S_IMODE(path.stat().st_mode) & 0o777
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException as err:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        ours = err.target == tmp if hasattr(err, "target") else getattr(err, "filename", None) in (None, str(tmp))
        if isinstance(err, OSError) and err.errno in NO_SPACE and ours:
            # (the writer's "[Errno 28] No space left on device" names no file, or this one's
            # temporary: a writer that writes through atomic_path itself names that temporary)
            full = OSError(err.errno, f"path: cannot write {str(path)!r}: {os.strerror(err.errno)}")
            full.target = path
            raise full from err
        raise


def file_target(path: object) -> Path:
    """``path``, a file to write, as a ``Path`` (:func:`~fsof_torch._check.as_path`'s checks); a
    text whose last part names a folder (``out/``, ``out/.``, ``..``) is an IsADirectoryError
    naming it: ``Path("out/")`` drops the slash, and a file named ``out`` was written. Every
    writer of :mod:`fsof_torch.io` takes its path through it."""
    target = as_path(path)
    text = os.fspath(path)
    if isinstance(text, str) and (text.endswith((os.sep, os.altsep or os.sep)) or
                                  os.path.basename(text) in (".", "..")):
        raise IsADirectoryError(f"path: {text!r} names a folder; expected a file path")
    return target


def _temporary_name(name: str, suffix: str) -> str:
    """``.<name>.<16 random hex digits>.tmp<suffix>``, the copy of ``name`` cut to keep the whole
    within 255 bytes (the longest file name of common file systems), so that a target whose name
    is just short enough can be written. ``suffix`` is kept (encoders pick the format by it)
    unless it alone leaves no room."""
    token = secrets.token_hex(8)
    if len(os.fsencode(f".x.{token}.tmp{suffix}")) > _NAME_MAX:
        suffix = ""
    while len(name) > 1 and len(os.fsencode(f".{name}.{token}.tmp{suffix}")) > _NAME_MAX:
        name = name[:-1]
    return f".{name}.{token}.tmp{suffix}"


def _create_temporary(folder: Path, path: Path) -> tuple[Path, int]:
    """Create a new, empty temporary (:func:`_temporary_name`) in ``folder``, mode ``0o600``;
    returns it and the mode a new file gets.

    ``os.open`` with mode 0o666 lets the umask decide the final permissions, as for any file a
    program creates (``tempfile.mkstemp`` would make every output private, mode 0o600); reading
    them back from the new file avoids ``os.umask``, which can only be read by setting it (racy
    between threads). The writers reopen the temporary by name, so until the rename it is the
    owner's to write: a umask of 0o222 would otherwise create it read-only."""
    for _ in range(100):
        tmp = folder / _temporary_name(path.name, path.suffix)
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except FileExistsError:  # pragma: no cover - 64 random bits
            continue
        except PermissionError as err:  # (naming the target, not the hidden temporary)
            raise PermissionError(err.errno, f"path: cannot write {str(path)!r}: the folder {str(folder)!r} is "
                                             f"not writable ({err.strerror})") from None
        try:
            mode = stat.S_IMODE(os.fstat(fd).st_mode)
            os.fchmod(fd, 0o600)
        except BaseException:
            os.close(fd)
            tmp.unlink()
            raise
        os.close(fd)
        return tmp, mode
    raise FileExistsError(f"path: could not create a temporary file beside {str(path)!r}")  # pragma: no cover


def remove_stale_temporaries(folder: str | os.PathLike, *, recursive: bool = True) -> list[Path]:
    """Delete the temporary files :func:`atomic_path` left in ``folder`` when a process was
    killed mid-write; returns the paths removed.

    Only names of the pattern ``.<name>.<16 hex digits>.tmp<suffix>`` are touched. Call it
    when no other process writes into ``folder`` (at the start of a job): a temporary being
    written by a live process would be removed under it.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return []
    found = folder.rglob(".*") if recursive else folder.glob(".*")
    removed = []
    for p in sorted(found):
        if TEMPORARY_NAME.match(p.name) and p.is_file():
            with contextlib.suppress(FileNotFoundError):
                p.unlink()
                removed.append(p)
    return removed


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (empty data gives an empty file); returns the path."""
    with atomic_path(path, allow_empty=True) as tmp, open(tmp, "wb") as f:
        f.write(data)
    return Path(path)


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (``""`` gives an empty file); returns the path.
    ``text`` that is not a str (bytes: use :func:`write_bytes`) is a TypeError naming it."""
    if not isinstance(text, str):
        raise TypeError(f"text: expected a str, got {type(text).__name__}")
    return write_bytes(path, text.encode("utf-8"))


def to_jsonable(obj: Any) -> Any:
    """``obj`` with tensors, NumPy arrays and scalars, paths and tuples made JSON-serialisable.

    Non-finite floats (NaN, ±inf) become ``None`` (JSON ``null``): strict JSON has no NaN. Dict
    keys become strings; two keys that give the same string (``1`` and ``"1"``) are a ValueError
    naming them, rather than one silently replacing the other.
    """
    import numpy as np
    import torch

    if isinstance(obj, dict):
        out, keys = {}, {}
        for k, v in obj.items():
            key = str(k)
            if key in keys:
                raise ValueError(f"obj: the keys {keys[key]!r} and {k!r} both become the JSON key {key!r}")
            keys[key] = k
            out[key] = to_jsonable(v)
        return out
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, torch.Tensor):
        return to_jsonable(obj.detach().cpu().tolist())
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item())
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, torch.dtype):
        return str(obj).replace("torch.", "")
    if isinstance(obj, (str, bool)) or obj is None:
        return obj
    if isinstance(obj, numbers.Integral):
        return int(obj)
    if isinstance(obj, numbers.Real):
        value = float(obj)
        # strict JSON has no NaN / inf: write null rather than a file other readers reject
        return value if math.isfinite(value) else None
    raise TypeError(f"obj: cannot write a {type(obj).__name__} as JSON")


def write_json(path: str | os.PathLike, obj: Any, *, indent: int = 2) -> Path:
    """Write ``obj`` as JSON atomically (tensors and arrays become nested lists, NaN/inf null);
    returns the path."""
    text = json.dumps(to_jsonable(obj), indent=indent, allow_nan=False)
    return write_text(path, text + "\n")


def special_file(path: str | os.PathLike) -> str | None:
    """What ``path`` is where it exists (through links) and is neither a regular file nor a folder
    (``"a character device"``, ``"a block device"``, ``"a FIFO"``, ``"a socket"``); None otherwise.
    A file written atomically is renamed onto its path, which would replace such a file."""
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return None
    kinds = ((stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"), (stat.S_ISFIFO, "a FIFO"),
             (stat.S_ISSOCK, "a socket"))
    return next((name for test, name in kinds if test(mode)), None)


def lookup_error(path: str | os.PathLike | None, option: str) -> str | None:
    """Why the system cannot look ``path`` up, as a message naming ``option``; None where it can
    (or where ``path`` is None: not given): a name longer than its file system takes
    (``NAME_MAX`` bytes, 255 on most; 85 characters of CJK text), a path longer in all than
    ``PATH_MAX``, or a loop of symbolic links on the way. Python's own look-ups of such a path
    raise ('File name too long', 'Symlink loop'), so the jobs check every path option with it
    before any other check of the path."""
    if path is None:
        return None
    absolute = Path(os.path.abspath(path))
    name_max, path_max = 255, 4096
    for folder in absolute.parents:  # (the limits of the nearest folder that exists)
        try:
            if folder.is_dir():
                # (-1: the file system states no limit)
                name_max, path_max = (n if n > 0 else math.inf for n in (os.pathconf(folder, "PC_NAME_MAX"),
                                                                          os.pathconf(folder, "PC_PATH_MAX")))
                break
        except (OSError, ValueError, AttributeError):  # (a name too long itself; no pathconf on Windows)
            continue
    long = next((part for part in absolute.parts if len(os.fsencode(part)) > name_max), None)
    if long is not None:
        return (f"{option}: {str(path)!r} holds a name of {len(os.fsencode(long))} bytes, {long[:24]!r}..., longer "
                f"than the {name_max} its file system takes; give a shorter one")
    if len(os.fsencode(str(absolute))) >= path_max:
        return (f"{option}: {str(path)!r} is {len(os.fsencode(str(absolute)))} bytes long as an absolute path, more "
                f"than the {path_max - 1} its file system takes; give a shorter one")
    try:
        os.stat(absolute)
    except OSError as err:
        if err.errno == errno.ELOOP:
            return f"{option}: {str(path)!r} leads through a loop of symbolic links; give another path"
    except ValueError:  # (a NUL byte: no path; the checks that follow name it)
        pass
    return None


#: the types of the kernel's interface file systems (Linux): their files are the kernel's, none is
#: created or replaced there, whatever ``os.access`` says to root (``/proc/x`` and ``/sys/x`` failed
#: at the first write, ``mkdir`` with 'No such file or directory')
KERNEL_FILE_SYSTEMS = frozenset({"proc", "sysfs", "cgroup", "cgroup2", "debugfs", "tracefs", "securityfs",
                                 "configfs", "bpf", "pstore", "efivarfs", "binfmt_misc", "fusectl"})


def kernel_file_system(path: str | os.PathLike) -> str | None:
    """The type of the kernel's interface file system (:data:`KERNEL_FILE_SYSTEMS`: ``"proc"``,
    ``"sysfs"``, ...) that the existing ``path`` lies on, from the process's mount table
    (``/proc/self/mountinfo``); None for another file system, or where there is no such table
    (not Linux)."""
    try:
        with open("/proc/self/mountinfo", encoding="utf-8", errors="surrogateescape") as f:
            lines = f.read().splitlines()
    except OSError:
        return None
    target = os.path.realpath(path)
    best, kind = "", None
    for line in lines:
        fields, _, rest = line.partition(" - ")
        parts = fields.split()
        if len(parts) < 5 or not rest:
            continue
        # (a mount point's spaces, tabs, newlines and backslashes are written as octal escapes)
        point = re.sub(r"\\([0-7]{3})", lambda m: chr(int(m.group(1), 8)), parts[4])
        inside = target == point or target.startswith(point.rstrip("/") + "/")
        if inside and len(point) >= len(best):  # (the last of equal mount points is the one on top)
            best, kind = point, rest.split()[0]
    return kind if kind in KERNEL_FILE_SYSTEMS else None


def creation_error(path: str | os.PathLike, option: str, *, folder: bool = False) -> str | None:
    """Why ``path`` cannot be created (its nearest existing parent is a file, or a folder that
    cannot be written into, or a symbolic link to nothing stands on the way: a drive not mounted),
    as a message naming ``option``; None where it can. ``folder``: ``path`` is to be a folder, which
    a link to nothing at ``path`` cannot become (a file is written through it where its target's
    folder exists, as :func:`atomic_path` writes), and which, where it exists, the process must be
    able to write into. The jobs check their outputs with it before any work."""
    path = Path(path)
    if path.is_symlink() and not path.exists():
        target = Path(os.path.realpath(path))
        if folder or not target.parent.is_dir():
            return (f"{option}: {str(path)!r} is a symbolic link to {str(target)!r}, "
                    + ("which does not exist" if folder else "whose folder does not exist")
                    + "; mount or create it, or give another path")
        path = target
    if folder and path.is_dir() and not os.access(path, os.W_OK | os.X_OK):
        return f"{option}: the folder {str(path)!r} is not writable, so the job cannot write its files into it"
    if path.is_file() and not os.access(path, os.W_OK):
        return f"{option}: {str(path)!r} is read-only, so it cannot be written over"
    special = special_file(path)
    if special is not None:  # (a job removes its earlier output first, then writes a file there)
        return (f"{option}: {str(path)!r} is {special}, not a regular file, which the job would replace with "
                f"its file; give a file path")
    existing = next((p for p in (path, *path.parents) if p.exists()), None)
    kernel = kernel_file_system(existing) if existing is not None else None
    if kernel is not None:
        return (f"{option}: {str(path)!r} is on the kernel's {kernel} file system, where the job cannot write "
                f"its files; give a path on a disk")
    for parent in path.parents:
        if parent.is_symlink() and not parent.exists():
            return (f"{option}: {str(parent)!r} is a symbolic link to {os.path.realpath(parent)!r}, which does not "
                    f"exist, so {str(path)!r} cannot be created; mount or create it, or give another path")
        if parent.exists():
            if not parent.is_dir():
                return f"{option}: {str(parent)!r} is a file, so {str(path)!r} cannot be created"
            if not os.access(parent, os.W_OK | os.X_OK):
                return f"{option}: the folder {str(parent)!r} is not writable, so {str(path)!r} cannot be created"
            return None
    return None
