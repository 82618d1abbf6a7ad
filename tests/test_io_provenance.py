"""fsof_torch.io.provenance: the environment block of the jobs' JSON outputs, the code digest and
the dependency versions."""

from __future__ import annotations

import hashlib
import json
import os
import platform
from pathlib import Path

import pytest
import torch

import fsof_torch
from fsof_torch.io import code_digest, cpu_name, dependency_versions, environment

ROOT = Path(__file__).resolve().parents[1]


def test_public_names():
    import fsof_torch.io as io

    for name in ("code_digest", "cpu_name", "dependency_versions", "environment"):
        assert name in io.__all__ and callable(getattr(io, name))


def test_environment_values():
    import cv2
    import kornia
    import numpy

    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        env = environment(command="python -m eval tables", seed=7, options={"size": (4, 5), "out": Path("o")},
                          packages=(ROOT / "eval",))
    finally:
        torch.set_num_threads(threads)
    assert env["command"] == "python -m eval tables" and env["seed"] == 7
    assert env["options"] == {"size": [4, 5], "out": "o"}
    assert env["version"] == fsof_torch.__version__
    assert env["library_code"] == code_digest(ROOT / "eval") and env["code_packages"] == ["fsof_torch", "eval"]
    assert env["dependencies"] == {"python": ".".join(platform.python_version_tuple()[:2]),
                                   "torch": torch.__version__, "opencv": cv2.__version__,
                                   "kornia": kornia.__version__, "numpy": numpy.__version__}
    assert env["python"] == platform.python_version() and env["machine"] == platform.machine()
    assert env["cpu"] == cpu_name() and env["cpu_count"] == os.cpu_count()
    assert env["threads"] == {"torch": 1, "opencv": cv2.getNumThreads()}  # (read when called)
    assert env["device"] == "cpu" and env["gpu"] is None and env["cuda"] == torch.version.cuda
    assert json.loads(json.dumps(env)) == env  # JSON as it is


def test_environment_defaults_and_odd_options():
    class Spec:
        def __repr__(self) -> str:
            return "Spec()"

    env = environment(options={"spec": Spec(), "nan": float("nan")}, device=torch.device("cpu"))
    assert env["command"] is None and env["seed"] is None and env["code_packages"] == ["fsof_torch"]
    assert env["options"] == {"spec": "Spec()", "nan": None}  # (what JSON cannot hold, by its repr)
    assert env["library_code"] == code_digest() and env["device"] == "cpu"
    assert environment()["options"] is None


def test_dependency_versions_is_a_copy_in_the_environment():
    env = environment()
    env["dependencies"]["torch"] = "changed"
    assert dependency_versions()["torch"] == torch.__version__


def test_code_digest_recipe(tmp_path):
    """The path (under the package's name) and bytes of every .py file, the library first: a copy
    of the files gives the same digest; an edit another."""
    import shutil

    library = Path(fsof_torch.__file__).parent
    job = tmp_path / "job"
    job.mkdir()
    (job / "a.py").write_text("x = 1\n")
    (job / "notes.txt").write_text("not code")

    def digest() -> str:  # (the recipe, written out)
        h = hashlib.blake2b(digest_size=16)
        for package in (library, job):
            for path in sorted(package.rglob("*.py"), key=lambda p: p.relative_to(package).as_posix()):
                h.update(f"{package.name}/{path.relative_to(package).as_posix()}\0".encode() + path.read_bytes() + b"\0")
        return h.hexdigest()

    assert code_digest(job) == digest()
    assert code_digest(str(job)) == code_digest(job)
    other = tmp_path / "other" / "job"
    shutil.copytree(job, other)
    (other / "a.py").write_text("x = 2\n")
    assert code_digest(other) != code_digest(job)
    assert code_digest(job) != code_digest()


def test_code_digest_refuses_what_is_no_folder(tmp_path):
    (tmp_path / "f.py").write_text("")
    for bad in (tmp_path / "missing", tmp_path / "f.py"):
        with pytest.raises(ValueError, match=r"packages: expected folders of Python packages, got '.*', which is no folder"):
            code_digest(bad)


def test_cpu_name_reads_proc_cpuinfo(monkeypatch):
    """The first ``model name`` of a made-up ``/proc/cpuinfo`` (as x86 Linux writes it; Arm's
    ``Model`` where it has none), whatever machine runs the test."""
    import io

    import fsof_torch.io.provenance as provenance

    assert cpu_name() == cpu_name()  # (read once, then cached)
    real_open = open
    xeon, pi = "Intel(R) Xeon(R) CPU @ 2.20GHz", "Raspberry Pi 4 Model B Rev 1.4"
    for info, name in [(f"processor\t: 0\nvendor_id\t: GenuineIntel\nmodel name\t: {xeon}\n"
                        f"processor\t: 1\nmodel name\t: {xeon}\n", xeon),
                       (f"processor\t: 0\nBogoMIPS\t: 108.00\n\nModel\t\t: {pi}\n", pi)]:
        monkeypatch.setattr(provenance, "open", lambda path, *a, info=info, **k: io.StringIO(info)
                            if path == "/proc/cpuinfo" else real_open(path, *a, **k), raising=False)
        assert cpu_name.__wrapped__() == name  # (past the cache of the real machine's name)


def test_a_reader_that_ignores_the_block_reads_as_before(tmp_path):
    """A result with the block beside its keys: a reader that takes the keys it knows gets them as
    they were written (the block is one more key, never a change of the others)."""
    from fsof_torch.io import write_json

    result = {"settings": {"seed": 0}, "rows": [{"e_E": 0.5}]}
    write_json(tmp_path / "r.json", {**result, "environment": environment(seed=0)})
    read = json.loads((tmp_path / "r.json").read_text())
    assert {k: read[k] for k in result} == result
