"""Import an earlier git revision of the library beside the current one, for interleaved timings.

``load_baseline("09d064e")`` extracts ``fsof_torch/`` of that revision (``git archive``) into a
temporary folder, renames the package to ``fsof_torch_<sha>`` (its relative imports then resolve
inside the copy), renames the strings that must be unique per process (the custom op namespace
``fsof_torch::…`` and the pytree type name ``"fsof_torch.…"``), and imports it. The copy has its
own classes: build its inputs with its own ``Camera``.

Used by ``bench_fit.py`` and ``bench_refine.py`` (``--baseline REV``).
"""

from __future__ import annotations

import atexit
import importlib
import io
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path
from types import ModuleType

REPO = Path(__file__).resolve().parents[1]
#: the revision before the road-model family and the one solver: a flat package (fsof_torch/fit.py, ...)
DEFAULT_BASELINE = "09d064e"


def load_baseline(rev: str = DEFAULT_BASELINE) -> ModuleType:
    """The ``fsof_torch`` package of git revision ``rev``, imported as ``fsof_torch_<sha>``.

    Raises:
        RuntimeError: ``rev`` is not a revision of this repository (or git is missing).
    """
    try:
        sha = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", f"{rev}^{{commit}}"],
                             capture_output=True, text=True, check=True).stdout.strip()
        archive = subprocess.run(["git", "-C", str(REPO), "archive", sha, "fsof_torch"],
                                 capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as err:
        detail = getattr(err, "stderr", b"") or b""
        detail = detail.decode() if isinstance(detail, bytes) else detail
        raise RuntimeError(f"baseline: cannot read revision {rev!r} from {REPO}: {detail.strip() or err}") from None
    name = f"fsof_torch_{sha}"
    if name in sys.modules:
        return sys.modules[name]
    folder = Path(tempfile.mkdtemp(prefix="fsof_baseline_"))
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        try:
            tar.extractall(folder, filter="data")
        except TypeError:  # a Python without extraction filters (the archive is this repository's)
            tar.extractall(folder)
    package = folder / name
    (folder / "fsof_torch").rename(package)
    for path in package.rglob("*.py"):
        text = path.read_text()
        renamed = text.replace("fsof_torch::", f"{name}::").replace('"fsof_torch.', f'"{name}.')
        if renamed != text:
            path.write_text(renamed)
    sys.path.insert(0, str(folder))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.remove(str(folder))
