"""``python -m eval``'s ``--json`` never lands inside a refine run's output folder, nor inside a
sequence that ``eval synth`` rendered: the JSON (an earlier one removed at the start, written last)
replaced that run's report.json, its manifest or a record, or the sequence's meta.json (which then
no longer read back). Every subcommand refuses it before any work, exit 2 naming ``--json``."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from eval.__main__ import main as eval_main
from refine.__main__ import main as refine_main


@pytest.fixture(scope="module")
def refine_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("refine") / "run"
    assert refine_main(["--num-pairs", "1", "--size", "48x160", "--source", "dis", "--odometry", "given",
                        "--no-figures", "--no-progress", "--out", str(out)]) == 0
    return out


ARGVS = [
    ["vflow", "--no-progress"],
    ["synth", "--pairs", "1", "--size", "48", "160", "--no-progress"],
    ["noise", "--quick", "--no-progress"],
    ["tables", "--quick", "--no-kitti", "--no-progress"],
    ["train", "--steps", "1", "--no-progress"],
]


@pytest.mark.parametrize("argv", ARGVS)
@pytest.mark.parametrize("name", ["report.json", "run.json", "dis/given/pairs/000000.json"])
def test_json_inside_a_refine_run_is_refused(tmp_path, capsys, refine_run, argv, name):
    before = {p: p.read_bytes() for p in refine_run.rglob("*") if p.is_file()}
    target = refine_run / name
    out = ["--out", str(tmp_path / "out")] if argv[0] != "train" else []
    assert eval_main([*argv, *out, "--json", str(target)]) == 2
    err = capsys.readouterr().err
    assert f"error: --json: {str(target)!r} is inside {str(refine_run.resolve())!r}, the output folder of a refine " \
           f"run" in err, err
    assert {p: p.read_bytes() for p in refine_run.rglob("*") if p.is_file()} == before
    assert not (tmp_path / "out").exists()


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "seq"
    assert eval_main(["synth", "--pairs", "1", "--size", "16", "24", "--no-progress", "--out", str(out)]) == 0
    return out


@pytest.mark.parametrize("argv", ARGVS)
@pytest.mark.parametrize("name", ["meta.json", "params/000000.json", "v.json"])
def test_json_inside_a_rendered_sequence_is_refused(tmp_path, capsys, sequence, argv, name):
    """(vflow --json SEQ/meta.json wrote its report there, exit 0, and SyntheticFlowDataset(SEQ)
    then raised 'has no num_pairs entry')."""
    from fsof_torch.data.datasets import SyntheticFlowDataset

    before = {p: p.read_bytes() for p in sequence.rglob("*") if p.is_file()}
    target = sequence / name
    out = ["--out", str(tmp_path / "out")] if argv[0] != "train" else []
    assert eval_main([*argv, *out, "--json", str(target)]) == 2
    err = capsys.readouterr().err
    assert f"error: --json: {str(target)!r} is inside {str(sequence.resolve())!r}, a rendered sequence" in err, err
    assert {p: p.read_bytes() for p in sequence.rglob("*") if p.is_file()} == before
    assert not (tmp_path / "out").exists()
    assert len(SyntheticFlowDataset(sequence)) == 1


def test_json_beside_a_rendered_sequence_is_written(tmp_path, sequence):
    """A --json beside the sequence's folder (not inside it) is a path like any other."""
    target = sequence.parent / "tables.json"
    assert eval_main(["tables", "--only", "cvc12", "--size", "16", "24", "--pairs", "1", "--no-progress",
                      "--out", str(tmp_path / "out"), "--json", str(target)]) == 0
    assert target.is_file()


def run_job(argv: list[str], out, json_path) -> int:
    """``refine`` (a one-pair run) where ``argv`` is ``["refine"]``, else ``eval`` with ``argv``,
    into ``out`` (not for ``train``, which has no output folder by default), with ``--json``."""
    if argv == ["refine"]:
        return refine_main(["--num-pairs", "1", "--size", "48x160", "--source", "dis", "--odometry", "given",
                            "--no-figures", "--no-progress", "--out", str(out), "--json", str(json_path)])
    return eval_main([*argv, *(["--out", str(out)] if argv[0] != "train" else []), "--json", str(json_path)])


@pytest.mark.parametrize("argv", [["refine"], *ARGVS])
def test_json_on_a_fifo_is_refused(tmp_path, capsys, argv):
    """``--json`` naming a FIFO (or, run as root, a device such as /dev/null) was removed at the
    start and replaced by the JSON, a regular file: exit 0 and the FIFO gone. Now exit 2 naming
    ``--json``, before any work."""
    import os
    import stat

    fifo = tmp_path / "pipe.json"
    os.mkfifo(fifo)
    assert run_job(argv, tmp_path / "out", fifo) == 2
    err = capsys.readouterr().err
    assert f"error: --json: {str(fifo)!r} is a FIFO, not a regular file, which the job would replace" in err, err
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv", [["refine"], ["vflow", "--size", "48", "160", "--no-progress"],
                                  ["tables", "--only", "cvc12", "--size", "16", "24", "--pairs", "1", "--no-progress"]])
def test_json_through_a_link_keeps_the_link(tmp_path, argv):
    """A ``--json`` that is a symbolic link is written through it, as fsof_torch.io.atomic writes
    (and open()): the jobs removed the link itself at the start, then wrote a regular file in its
    place, leaving the file it pointed to with the earlier run's JSON."""
    import json

    (tmp_path / "runs").mkdir()
    real = tmp_path / "runs" / "first.json"
    real.write_text('{"stale": true}\n')
    link = tmp_path / "latest.json"
    link.symlink_to(real)
    assert run_job(argv, tmp_path / "out", link) == 0
    assert link.is_symlink() and link.resolve() == real.resolve()
    written = json.loads(real.read_text())
    assert "stale" not in written and written != {}
    if argv == ["refine"]:
        assert written == json.loads((tmp_path / "out" / "report.json").read_text())


@pytest.mark.parametrize("argv", [["refine"], *ARGVS])
@pytest.mark.parametrize("suffix", ["/", "/.", "//"])
def test_json_ending_in_a_slash_is_refused(tmp_path, capsys, argv, suffix):
    """``--json DIR/`` names a folder; ``Path`` dropped the slash, and the job wrote a file named
    ``DIR``. Now exit 2 naming ``--json``, before any work: nothing is written."""
    given = f"{tmp_path / 'report'}{suffix}"
    assert run_job(argv, tmp_path / "out", given) == 2
    err = capsys.readouterr().err
    assert f"error: argument --json: expected a file path, got {given!r}, which names a folder" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_dump_first_step_ending_in_a_slash_is_refused(tmp_path, capsys):
    given = f"{tmp_path / 'dump'}/"
    assert eval_main(["train", "--steps", "1", "--no-progress", "--dump-first-step", given]) == 2
    err = capsys.readouterr().err
    assert f"error: argument --dump-first-step: expected a file path, got {given!r}, which names a folder" in err, err
    assert list(tmp_path.iterdir()) == []


def test_a_file_path_names_a_file():
    from refine.resume import file_path

    assert file_path("a/b.json") == Path("a/b.json") and file_path("b") == Path("b")
    assert file_path("./x.json") == Path("x.json") and file_path("a/.b") == Path("a/.b")
    for text in ("", ".", "..", "a/", "a/.", "a/..", "/"):
        with pytest.raises(argparse.ArgumentTypeError, match="expected a file path"):
            file_path(text)
