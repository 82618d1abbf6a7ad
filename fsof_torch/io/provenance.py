"""What produced a result file: the ``environment`` block of the jobs' JSON outputs.

The same command gives figures that differ in their last digits between CPUs, thread counts,
builds of torch or OpenCV, and devices (a GPU's kernels round otherwise). A reader comparing two
JSON files needs what produced each to tell such a difference from a change of the code or the
options: :func:`environment` gathers it in one dict. The refine job's run identity takes its
``library_code`` and ``dependencies`` from :func:`code_digest` and :func:`dependency_versions`.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import platform
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ..version import __version__

__all__ = ["code_digest", "cpu_name", "dependency_versions", "environment"]

# the installed fsof_torch package (this file is fsof_torch/io/provenance.py)
_LIBRARY = Path(__file__).parent.parent


def code_digest(*packages: str | os.PathLike) -> str:
    """BLAKE2b (hex, 32 characters) of the code that computes a job's results: the relative path
    and bytes of every ``.py`` file of the installed ``fsof_torch`` package, then of each folder of
    ``packages`` (a job's own package, such as ``refine``), read once per process and folder list.
    The library's version alone stays the same across the edits of a source checkout.

    Args:
        packages: folders of Python packages whose code counts too, in this order.

    Returns:
        32 hex digits; the same files give the same digest on every machine (paths are hashed
        relative to each package, under the package folder's name).

    Raises:
        ValueError: naming ``packages``, where one is not a folder.
    """
    folders = tuple(Path(p) for p in packages)
    for folder in folders:
        if not folder.is_dir():
            raise ValueError(f"packages: expected folders of Python packages, got {str(folder)!r}, which is no folder")
    return _digest((_LIBRARY, *folders))


@functools.lru_cache(maxsize=None)
def _digest(packages: tuple[Path, ...]) -> str:
    h = hashlib.blake2b(digest_size=16)
    for package in packages:
        for path in sorted(package.rglob("*.py"), key=lambda p: p.relative_to(package).as_posix()):
            h.update(f"{package.name}/{path.relative_to(package).as_posix()}\0".encode())
            h.update(path.read_bytes())
            h.update(b"\0")
    return h.hexdigest()


@functools.lru_cache(maxsize=None)
def dependency_versions() -> dict[str, str]:
    """The versions of what computes results beside the library's code, read once per process:
    Python's ``major.minor``, torch (with its build suffix, e.g. ``2.5.1+cu121``: a CUDA or CPU
    build), OpenCV (DIS flows, blurs, pyramids), kornia and NumPy. DIS's flows move with the
    OpenCV build. (The returned dict is shared: copy it before changing it.)"""
    import cv2
    import kornia
    import numpy
    import torch

    major, minor, _ = platform.python_version_tuple()
    return {"python": f"{major}.{minor}", "torch": str(torch.__version__), "opencv": cv2.__version__,
            "kornia": kornia.__version__, "numpy": numpy.__version__}


@functools.lru_cache(maxsize=None)
def cpu_name() -> str | None:
    """The CPU's model name as the system states it (Linux: ``model name`` in ``/proc/cpuinfo``;
    macOS: ``sysctl machdep.cpu.brand_string``), else ``platform.processor()``; None where neither
    names one."""
    with contextlib.suppress(OSError):
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key.strip() in ("model name", "Model", "Hardware") and value.strip():
                    return value.strip()
    if platform.system() == "Darwin":
        import subprocess

        with contextlib.suppress(OSError, subprocess.SubprocessError):
            name = subprocess.run(["sysctl", "-n", "machdep.cpu.brand_string"], capture_output=True, text=True,
                                  timeout=5, check=True).stdout.strip()
            if name:
                return name
    return platform.processor() or None


def environment(*, command: str | None = None, options: Mapping[str, Any] | None = None,
                seed: int | None = None, device: Any = "cpu", packages: tuple[str | os.PathLike, ...] = ()
                ) -> dict[str, Any]:
    """What produces a result, as a JSON-able dict (the ``environment`` block of the jobs' JSON
    outputs, ``docs/jobs.md``). Call it where the result is computed: the thread counts are read
    when it is called.

    Args:
        command: the command that ran, e.g. ``"python -m eval tables"``.
        options: its options as parsed (an ``argparse.Namespace``'s ``vars``: defaults included);
            paths and tuples are written as strings and lists, anything else JSON cannot hold by
            its ``repr``.
        seed: the seed the results were drawn with (None where none was).
        device: the torch device the results were computed on (a ``torch.device`` or a string).
        packages: folders of the code that counts beside the library (:func:`code_digest`).

    Returns:
        ``command``, ``options``, ``seed``; ``version`` (the library's) and ``library_code``
        (:func:`code_digest` of the library and ``packages``), ``code_packages`` (the package
        names that digest covers); ``dependencies`` (:func:`dependency_versions`); ``python``
        (the full version), ``platform`` (``platform.platform()``), ``machine``; ``cpu``
        (:func:`cpu_name`) and ``cpu_count``; ``threads`` (``torch`` and ``opencv``: their thread
        counts); ``device``, ``gpu`` (the GPU's name for a CUDA device, else None) and ``cuda``
        (the CUDA version torch was built with, None for a CPU build).

    Example:
        >>> env = environment(command="python -m eval tables", seed=0)
        >>> env["version"] == __version__ and env["seed"] == 0 and env["device"] == "cpu"
        True
    """
    import cv2
    import torch

    from .atomic import to_jsonable

    def jsonable(value: Any) -> Any:
        try:
            return to_jsonable(value)
        except (TypeError, ValueError):
            return repr(value)

    dev = torch.device(device) if device is not None else torch.device("cpu")
    gpu = None
    if dev.type == "cuda" and torch.cuda.is_available():
        gpu = torch.cuda.get_device_name(dev)
    return {
        "command": command,
        "options": None if options is None else {str(k): jsonable(v) for k, v in options.items()},
        "seed": seed,
        "version": __version__,
        "library_code": code_digest(*packages),
        "code_packages": [_LIBRARY.name, *(Path(p).name for p in packages)],
        "dependencies": dict(dependency_versions()),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "machine": platform.machine(),
        "cpu": cpu_name(),
        "cpu_count": os.cpu_count(),
        "threads": {"torch": torch.get_num_threads(), "opencv": cv2.getNumThreads()},
        "device": str(dev),
        "gpu": gpu,
        "cuda": torch.version.cuda,
    }
