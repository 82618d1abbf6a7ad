"""What identifies a user's network (``--net``) for resuming: its factory, contract, checkpoint and
every file of the user's code that importing and building it loaded (refine.sources.net_identity),
through user packages and modules written to tmp_path."""

from __future__ import annotations

import importlib
import json
import os
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from refine.__main__ import main
from refine.inputs import JobError, file_digest
from refine.sources import NetSpec, build_user_net, net_identity

SIZE = (45, 150)

NETWORK = '''
import torch


class Constant(torch.nn.Module):
    """A RAFT-contract network whose flow is (SCALE, 0) everywhere."""

    flow_contract = "raft"

    def __init__(self, scale):
        super().__init__()
        self.scale = scale

    def forward(self, image1, image2):
        flow = torch.zeros(image1.shape[0], 2, *image1.shape[-2:])
        flow[:, 0] = self.scale
        return [flow]
'''


@pytest.fixture
def project(tmp_path, monkeypatch):
    """A folder on sys.path for the user's code and the prefix of its modules' names (unique to the
    process); those modules are forgotten afterwards (and between runs, as a new process would)."""
    root = tmp_path / "project"
    root.mkdir()
    monkeypatch.syspath_prepend(str(root))
    monkeypatch.setattr(sys, "dont_write_bytecode", True)  # (an edit within the second is read again)

    prefix = f"u{os.getpid()}"

    def forget():
        for name in [n for n in sys.modules if n.startswith(prefix)]:
            del sys.modules[name]
        importlib.invalidate_caches()

    yield root, prefix, forget
    forget()


def _write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(textwrap.dedent(text))


def _identity(factory: str, checkpoint: Path | None = None) -> dict:
    spec = NetSpec(factory, "auto", checkpoint)
    build_user_net(spec)
    return net_identity(spec)


def _run(out: Path, factory: str, *extra: str) -> int:
    return main(["--num-pairs", "1", "--odometry", "given", "--no-figures", "--no-progress",
                 "--size", f"{SIZE[0]}x{SIZE[1]}", "--out", str(out), "--net", factory, *extra])


def test_editing_a_module_of_the_networks_package_makes_another_run(project, tmp_path, capsys):
    """mynets/raft.py builds its network from mynets/layers.py: editing layers.py and rerunning
    into the same --out reused the records of the old code (only raft.py was in the identity);
    now the rerun is another run (refused, naming the module; --overwrite redoes the pair with
    the new code), while a file the network does not import may change freely."""
    from fsof_torch.data.scene import render_pair

    root, pkg, forget = project
    _write(root / pkg / "__init__.py", "")
    _write(root / pkg / "layers.py", NETWORK + "SCALE = 1.0\n")
    _write(root / pkg / "raft.py", f"from {pkg} import layers\n\n\ndef build():\n"
                                   f"    return layers.Constant(layers.SCALE)\n")
    _write(root / pkg / "unused.py", "X = 1\n")
    out, factory = tmp_path / "out", f"{pkg}.raft:build"

    def epe_road(scale: float) -> float:  # the road's mean end-point error of the flow (scale, 0)
        pair = render_pair("default", 0, size=SIZE)
        m = (pair["road"] & pair["valid"])[0]
        flow = torch.zeros_like(pair["flow"])
        flow[0] = scale
        return float(torch.sqrt(((flow - pair["flow"]) ** 2).sum(0))[m].double().mean())

    def report() -> dict:
        return json.loads((out / "report.json").read_text())

    assert _run(out, factory) == 0
    assert report()["pairs"][0]["before"]["epe_road"] == pytest.approx(epe_road(1.0), rel=1e-5)
    forget()
    _write(root / pkg / "unused.py", "X = 2\n")
    assert _run(out, factory) == 0
    assert report()["records_resumed"] == 1 and report()["records_computed"] == 0
    forget()
    _write(root / pkg / "layers.py", NETWORK + "SCALE = 4.0\n")
    capsys.readouterr()
    assert _run(out, factory) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: --out: {str(out)!r} holds the results of another run (net.code.{pkg}.layers: "), err
    forget()
    assert _run(out, factory, "--overwrite") == 0
    assert report()["records_resumed"] == 0 and report()["records_computed"] == 1
    assert report()["pairs"][0]["before"]["epe_road"] == pytest.approx(epe_road(4.0), rel=1e-5)
    assert report()["identity"]["net"]["code"] == {pkg: file_digest(root / pkg / "__init__.py"),
                                                   f"{pkg}.layers": file_digest(root / pkg / "layers.py")}


def test_a_top_level_modules_siblings_and_its_factorys_lazy_imports_count_but_not_the_environment(project):
    """net.py beside layers.py (imported at the top) and lazy.py (imported inside the factory):
    both are the user's code; a package in a virtual environment inside the project, torch and
    fsof_torch are not."""
    root, name, _ = project
    venv = root / ".venv" / "lib" / "python3" / "site-packages"
    _write(venv / f"{name}_installed.py", "X = 1\n")
    sys.path.insert(0, str(venv))
    try:
        _write(root / f"{name}_layers.py", NETWORK)
        _write(root / f"{name}_lazy.py", "SCALE = 2.0\n")
        _write(root / f"{name}_net.py", f"import {name}_layers, {name}_installed\nimport fsof_torch\n\n\n"
                                        f"def build():\n    import {name}_lazy\n\n"
                                        f"    return {name}_layers.Constant({name}_lazy.SCALE)\n")
        identity = _identity(f"{name}_net:build")
    finally:
        sys.path.remove(str(venv))
    assert f"{name}_installed" in sys.modules
    assert identity == {"factory": f"{name}_net:build", "contract": "auto",
                        "module_file": file_digest(root / f"{name}_net.py"), "checkpoint": None,
                        "code": {f"{name}_layers": file_digest(root / f"{name}_layers.py"),
                                 f"{name}_lazy": file_digest(root / f"{name}_lazy.py")}}


def test_a_namespace_package_counts_its_loaded_modules(project):
    """A package without __init__.py: its folder is the user's code as a regular package's."""
    root, pkg, _ = project
    _write(root / pkg / "layers.py", NETWORK)
    _write(root / pkg / "nets" / "raft.py", f"from {pkg} import layers\n\n\ndef build():\n"
                                            f"    return layers.Constant(1.0)\n")
    identity = _identity(f"{pkg}.nets.raft:build")
    assert identity["module_file"] == file_digest(root / pkg / "nets" / "raft.py")
    assert identity["code"] == {f"{pkg}.layers": file_digest(root / pkg / "layers.py")}


def test_a_network_in_one_module_keeps_its_identity(project):
    """No other file of the user's code: the identity has the keys it had (no "code"), so the
    runs of such a network resume as before; so does the library's own test net."""
    root, name, _ = project
    _write(root / f"{name}.py", NETWORK + "\n\ndef build():\n    return Constant(1.0)\n")
    assert _identity(f"{name}:build") == {"factory": f"{name}:build", "contract": "auto",
                                          "module_file": file_digest(root / f"{name}.py"), "checkpoint": None}
    assert set(_identity("fsof_torch:TinyRAFT")) == {"factory", "contract", "module_file", "checkpoint"}


def test_the_checkpoint_counts_by_its_contents_wherever_it_lies(tmp_path):
    """A copy under another path and a symlink to it are the same checkpoint; a folder is named
    as a folder (it was 'no file at', as if nothing were there)."""
    from fsof_torch import TinyRAFT

    torch.save(TinyRAFT(seed=3).state_dict(), tmp_path / "a.pt")
    (tmp_path / "copy").mkdir()
    (tmp_path / "copy" / "b.pt").write_bytes((tmp_path / "a.pt").read_bytes())
    (tmp_path / "link.pt").symlink_to(tmp_path / "a.pt")
    torch.save(TinyRAFT(seed=4).state_dict(), tmp_path / "other.pt")
    ids = {name: _identity("fsof_torch:TinyRAFT", tmp_path / name) for name in ("a.pt", "copy/b.pt", "link.pt")}
    assert ids["a.pt"] == ids["copy/b.pt"] == ids["link.pt"]
    assert ids["a.pt"]["checkpoint"] == file_digest(tmp_path / "a.pt")
    assert _identity("fsof_torch:TinyRAFT", tmp_path / "other.pt")["checkpoint"] != ids["a.pt"]["checkpoint"]
    with pytest.raises(JobError, match=r"^--checkpoint: '.*copy' is a folder; expected a file"):
        _identity("fsof_torch:TinyRAFT", tmp_path / "copy")


def test_the_users_module_is_imported_once_by_a_run(project, tmp_path):
    """The identity reads the modules the build loaded: a module with side effects on import is
    not imported a second time for it."""
    root, name, _ = project
    log = tmp_path / "imports.log"
    _write(root / f"{name}_layers.py", NETWORK + f"\nopen({str(log)!r}, 'a').write('layers\\n')\n")
    _write(root / f"{name}.py", f"import {name}_layers\nopen({str(log)!r}, 'a').write('net\\n')\n\n\n"
                                f"def build():\n    return {name}_layers.Constant(1.0)\n")
    assert _run(tmp_path / "out", f"{name}:build") == 0
    assert log.read_text().split() == ["layers", "net"]
    identity = json.loads((tmp_path / "out" / "report.json").read_text())["identity"]["net"]
    assert identity["code"] == {f"{name}_layers": file_digest(root / f"{name}_layers.py")}


def test_main_called_again_in_one_process_runs_the_networks_files_as_they_are_now(project, tmp_path):
    """main() called twice in one process, layers.py and the factory's module edited in between
    (no forget() here): the second call ran the network the first call had imported, under an
    identity that held the digests of the edited files. Now it imports them anew: its flow is the
    edited network's, as a new process's, and the module imported by each call runs once."""
    from fsof_torch.data.scene import render_pair

    root, name, _ = project
    log = tmp_path / "imports.log"
    pair = render_pair("default", 0, size=SIZE)
    road = (pair["road"] & pair["valid"])[0]

    def epe_road(scale: float) -> float:  # the road's mean end-point error of the flow (scale, 0)
        flow = torch.zeros_like(pair["flow"])
        flow[0] = scale
        return float(torch.sqrt(((flow - pair["flow"]) ** 2).sum(0))[road].double().mean())

    def write(scale: float, offset: float) -> None:
        _write(root / f"{name}_layers.py", NETWORK + f"\nSCALE = {scale}\n")
        _write(root / f"{name}.py", f"import {name}_layers\nopen({str(log)!r}, 'a').write('net\\n')\n\n\n"
                                    f"def build():\n    return {name}_layers.Constant({name}_layers.SCALE + {offset})\n")

    results = []
    for k, (scale, offset) in enumerate([(1.0, 0.0), (4.0, 0.0), (4.0, 3.0)]):
        write(scale, offset)
        out = tmp_path / f"out{k}"
        assert _run(out, f"{name}:build") == 0
        report = json.loads((out / "report.json").read_text())
        assert report["identity"]["net"]["module_file"] == file_digest(root / f"{name}.py")
        assert report["identity"]["net"]["code"] == {f"{name}_layers": file_digest(root / f"{name}_layers.py")}
        results.append(report["pairs"][0]["before"]["epe_road"])
    assert results == pytest.approx([epe_road(1.0), epe_road(4.0), epe_road(7.0)], rel=1e-5)
    assert log.read_text().split() == ["net"] * 3


@pytest.mark.parametrize("given, dotted, folder", [("nets/raft.py", "nets.raft", "."),
                                                   ("./nets/raft.py", "nets.raft", "."),
                                                   ("nets.raft.py", "nets.raft", "."),
                                                   ("/abs/nets/raft.py", "raft", "/abs/nets")])
def test_a_module_given_as_a_file_path_is_named_with_its_dotted_name(given, dotted, folder):
    with pytest.raises(JobError) as caught:
        build_user_net(NetSpec(f"{given}:build"))
    assert str(caught.value) == (f"--net: {given!r} is a file path, not a module name; give the module's dotted "
                                 f"name with the folder it is found from on PYTHONPATH, e.g. --net {dotted}:build "
                                 f"with PYTHONPATH={folder}")
