"""Output paths through a symbolic link to nothing (a drive not mounted): ``--out`` such a link,
or a folder under one, ended ``refine`` and ``eval`` with a FileExistsError traceback (``mkdir``
on the link), eval's after its work; a ``--json`` link whose target's folder is missing, with a
FileNotFoundError traceback after the work. Now each exits 2 before any work, naming the option,
the link and its target. A ``--json`` link whose target's folder exists is written through, the
link kept, as fsof_torch.io.atomic writes."""

from __future__ import annotations

import json

import pytest

from eval.__main__ import main as eval_main
from fsof_torch.io.atomic import creation_error
from refine.__main__ import main as refine_main


def run(job: str, tmp_path, out, json_path=None) -> int:
    extra = ["--json", str(json_path)] if json_path is not None else []
    if job == "refine":
        return refine_main(["--num-pairs", "1", "--size", "48x160", "--source", "dis", "--odometry", "given",
                            "--no-figures", "--no-progress", "--out", str(out), *extra])
    return eval_main(["vflow", "--size", "48", "160", "--no-progress", "--out", str(out), *extra])


@pytest.fixture
def links(tmp_path):
    gone = tmp_path / "unmounted"  # (never created)
    (tmp_path / "out_link").symlink_to(gone / "out")
    (tmp_path / "json_link").symlink_to(gone / "r.json")
    return tmp_path / "out_link", tmp_path / "json_link", gone


@pytest.mark.parametrize("job", ["refine", "vflow"])
def test_out_through_a_link_to_nothing(tmp_path, capsys, links, job):
    out_link, _, gone = links
    assert run(job, tmp_path, out_link) == 2
    err = capsys.readouterr().err
    assert err == (f"error: --out: {str(out_link)!r} is a symbolic link to {str(gone / 'out')!r}, which does not "
                   f"exist; mount or create it, or give another path\n"), err
    assert run(job, tmp_path, out_link / "sub") == 2
    assert f"error: --out: {str(out_link)!r} is a symbolic link to {str(gone / 'out')!r}, which does not exist, " \
           f"so {str(out_link / 'sub')!r} cannot be created" in capsys.readouterr().err
    assert not gone.exists()


@pytest.mark.parametrize("job", ["refine", "vflow"])
def test_json_through_a_link_to_nothing(tmp_path, capsys, links, job):
    out_link, json_link, gone = links
    assert run(job, tmp_path, tmp_path / "out", json_link) == 2
    err = capsys.readouterr().err
    assert err == (f"error: --json: {str(json_link)!r} is a symbolic link to {str(gone / 'r.json')!r}, whose "
                   f"folder does not exist; mount or create it, or give another path\n"), err
    assert run(job, tmp_path, tmp_path / "out", out_link / "r.json") == 2
    assert f"error: --json: {str(out_link)!r} is a symbolic link" in capsys.readouterr().err
    assert not (tmp_path / "out").exists() and not gone.exists()
    # the drive mounted: the JSON is written through the link, which stays
    gone.mkdir()
    assert run(job, tmp_path, tmp_path / "out", json_link) == 0
    assert json_link.is_symlink() and isinstance(json.loads((gone / "r.json").read_text()), dict)


def test_creation_error(tmp_path):
    (tmp_path / "dir").mkdir()
    (tmp_path / "to_dir").symlink_to(tmp_path / "dir" / "new.json")
    assert creation_error(tmp_path / "to_dir", "--json") is None  # (a file written through it)
    assert creation_error(tmp_path / "to_dir", "--out", folder=True) == (
        f"--out: {str(tmp_path / 'to_dir')!r} is a symbolic link to {str(tmp_path / 'dir' / 'new.json')!r}, which "
        f"does not exist; mount or create it, or give another path")
    assert creation_error(tmp_path / "dir", "--out", folder=True) is None
    assert creation_error(tmp_path / "new", "--out", folder=True) is None
