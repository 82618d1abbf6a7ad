"""``python -m eval``'s output and input paths that the system cannot look up (a name the file
system cannot hold, a loop of symbolic links): exit 2 naming the option before any work (the
system's 'File name too long' was a traceback, or, under a folder still to be created, came once
the work was done; a loop was Path.resolve's RuntimeError)."""

from __future__ import annotations

import os
import re

import pytest

from eval.__main__ import main
from eval.paths import bad_lookup

FAST = {"synth": ["--pairs", "1", "--size", "20", "40"], "tables": ["--quick", "--only", "cvc12"],
        "noise": ["--quick", "--no-plots"], "train": ["--steps", "1"], "vflow": []}


def _long(tmp_path, ascii_: bool) -> str:
    limit = os.pathconf(tmp_path, "PC_NAME_MAX")
    # (90 CJK characters are 270 bytes: a name of ordinary length in characters)
    return "a" * (limit + 45) if ascii_ else "道" * (limit // 3 + 5)


@pytest.mark.parametrize("job, option", [("synth", "--out"), ("synth", "--json"), ("tables", "--out"),
                                         ("tables", "--json"), ("noise", "--out"), ("noise", "--json"),
                                         ("train", "--out"), ("train", "--json"), ("train", "--dump-first-step"),
                                         ("vflow", "--out"), ("vflow", "--json")])
@pytest.mark.parametrize("ascii_", [True, False])
def test_a_name_too_long_is_named(tmp_path, capsys, job, option, ascii_):
    name = _long(tmp_path, ascii_)
    given = tmp_path / "new" / name / "x"  # (below a folder still to be created: found only on writing)
    argv = [job, *FAST[job], "--no-progress", option, str(given)]
    if option != "--out":
        argv += ["--out", str(tmp_path / "out")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {option}: {str(given)!r} holds a name of {len(os.fsencode(name))} bytes")
    assert f"longer than the {os.pathconf(tmp_path, 'PC_NAME_MAX')} its file system takes" in err
    assert list(tmp_path.iterdir()) == []  # nothing written, no folder made


def test_a_kitti_folder_with_a_name_too_long_is_named(tmp_path, capsys):
    given = tmp_path / _long(tmp_path, True)
    assert main(["tables", "--only", "kitti", "--kitti", str(given), "--out", str(tmp_path / "out")]) == 2
    assert capsys.readouterr().err.startswith(f"error: --kitti: {str(given)!r} holds a name of")


def test_a_path_too_long_in_all_is_named(tmp_path, capsys):
    given = tmp_path.joinpath(*["b"] * (os.pathconf(tmp_path, "PC_PATH_MAX") // 2 + 1))
    assert main(["noise", "--quick", "--no-plots", "--no-progress", "--out", str(given)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: --out: {str(given)!r} is {len(os.fsencode(str(given)))} bytes long as an absolute")
    assert list(tmp_path.iterdir()) == []


def test_bad_lookup_takes_a_name_at_the_limit(tmp_path):
    limit = os.pathconf(tmp_path, "PC_NAME_MAX")
    assert bad_lookup(tmp_path / ("a" * limit), "--out") is None
    assert bad_lookup(tmp_path / ("a" * (limit + 1)), "--out").startswith("--out: ")
    assert bad_lookup(None, "--out") is None
    (tmp_path / ("a" * limit)).mkdir()  # (the system takes it)


OUTPUTS = {"synth": ["--out", "--json"], "tables": ["--out", "--json"], "noise": ["--out", "--json"],
           "train": ["--out", "--json", "--dump-first-step"], "vflow": ["--out", "--json"]}


@pytest.mark.parametrize("job, option, other", [(job, option, other) for job, options in OUTPUTS.items()
                                                for option in options for other in options if other != option])
@pytest.mark.parametrize("through", ["self", "l1/x"])
def test_a_loop_of_symbolic_links_is_named(tmp_path, capsys, job, option, other, through):
    (tmp_path / "self").symlink_to("self")
    (tmp_path / "l1").symlink_to("l2")
    (tmp_path / "l2").symlink_to("l1")
    given = tmp_path / through
    argv = [job, *FAST[job], "--no-progress", option, str(given), other, str(tmp_path / "new" / "x")]
    assert main(argv) == 2
    assert capsys.readouterr().err == (f"error: {option}: {str(given)!r} leads through a loop of symbolic links; "
                                       f"give another path\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["l1", "l2", "self"]


def test_a_kitti_folder_through_a_loop_is_named(tmp_path, capsys):
    (tmp_path / "self").symlink_to("self")
    assert main(["tables", "--only", "kitti", "--kitti", str(tmp_path / "self"), "--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err == (f"error: --kitti: {str(tmp_path / 'self')!r} leads through a loop of "
                                       f"symbolic links; give another path\n")


def test_bad_lookup_where_the_file_system_states_no_limit(tmp_path, monkeypatch):
    """os.pathconf gives -1 where a file system states no limit: no name is refused for its length
    (every name was, as longer than -1 bytes)."""
    monkeypatch.setattr(os, "pathconf", lambda path, name: -1)
    assert bad_lookup(tmp_path / "a", "--out") is None
    assert bad_lookup(tmp_path / ("a" * 300), "--out") is None


@pytest.mark.parametrize("option", ["--flow", "--mask"])
@pytest.mark.parametrize("kind", ["long", "loop"])
def test_vflow_inputs_the_system_cannot_look_up_are_named(tmp_path, capsys, option, kind):
    """vflow's --flow and --mask, compared with its outputs before any work, were the same
    tracebacks."""
    (tmp_path / "self").symlink_to("self")
    given = tmp_path / (_long(tmp_path, True) + ".png" if kind == "long" else "self")
    flow = tmp_path / "flow.png"  # (not read: the paths are checked first)
    argv = ["vflow", "--no-progress", "--out", str(tmp_path / "out"), "--json", str(tmp_path / "v.json")]
    argv += ["--flow", str(given)] if option == "--flow" else ["--flow", str(flow), "--mask", str(given)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {option}: {str(given)!r} ")
    assert ("holds a name of" if kind == "long" else "leads through a loop of symbolic links") in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["self"]


@pytest.mark.parametrize("job, option", [("synth", "--out"), ("tables", "--out"), ("tables", "--kitti"),
                                         ("noise", "--out"), ("train", "--out"), ("vflow", "--out"),
                                         ("vflow", "--flow"), ("vflow", "--mask")])
def test_an_empty_path_is_refused_not_read_as_the_current_folder(tmp_path, capsys, monkeypatch, job, option):
    """``--out "$OUT"`` with OUT unset: ``Path('')`` is the current folder, into which synth rendered
    its sequence, tables, noise and vflow wrote their files (removing an earlier run's there) and train
    its state_dicts; now argparse's exit 2 naming the option, before anything is written."""
    monkeypatch.chdir(tmp_path)
    # (the other options keep a run that took the path short)
    small = {"synth": ["--pairs", "1", "--size", "16", "48"], "tables": ["--only", "cvc12", "--quick"],
             "noise": ["--quick", "--no-plots"], "train": ["--steps", "1", "--size", "16", "48", "--train-pairs", "1",
                                                            "--test-pairs", "1", "--batch", "1"],
             "vflow": ["--size", "32", "96"] if option == "--out" else []}
    argv = [job, option, "", "--no-progress", *small[job]]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.endswith(f"error: argument {option}: expected a path, got an empty one ('', which would be the current "
                        f"folder)\n")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("job, option", [(job, option) for job, options in OUTPUTS.items() for option in options])
def test_an_output_on_the_kernels_file_systems_is_refused(tmp_path, capsys, kernel_paths, job, option):
    """``--out /proc/x`` (or /sys): the checks passed (root may write into /proc, says
    ``os.access``) and ``eval synth`` stopped with mkdir's traceback, the others after their work
    at the first write. Exit 2 naming the option, before any work."""
    for given in kernel_paths[1:]:  # (below the file systems' roots)
        out = [] if option == "--out" else ["--out", str(tmp_path / "out")]
        assert main([job, *FAST[job], "--no-progress", option, given, *out]) == 2
        assert re.fullmatch(rf"error: {option}: {re.escape(repr(given))} is on the kernel's \w+ file system, .*\n",
                            capsys.readouterr().err)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("job, option, name", [("vflow", "--flow", None), ("vflow", "--mask", None),
                                               ("tables", "--kitti", None),
                                               ("tables", "--kitti", "calib_cam_to_cam.txt"),
                                               ("tables", "--kitti", "flow_noc_10.png")])
def test_a_fifo_given_as_an_input_is_named(tmp_path, capsys, no_hang, job, option, name):
    """A FIFO as ``vflow``'s ``--flow`` or ``--mask``, as ``tables``' ``--kitti`` or one of its
    files, said 'no file at', 'no KITTI sample at' or 'no calibration file at'. Exit 2 naming the
    option and what it is, before any read."""
    fifo = tmp_path / "pipe"
    argv = [job, "--no-progress", option, str(fifo), "--out", str(tmp_path / "out")]
    if name is not None:  # (a sample folder holding a FIFO)
        sample = tmp_path / "kitti15"
        sample.mkdir()
        for n in ("flow_noc_10.png", "road.json", "calib_cam_to_cam.txt", "image_10.png", "image_11.png"):
            (sample / n).write_text("x")
        fifo = sample / name
        fifo.unlink()
        argv[3] = str(sample)
    if option == "--mask":
        (tmp_path / "flow.npy").write_text("x")
        argv += ["--flow", str(tmp_path / "flow.npy")]
    if job == "tables":
        argv += ["--only", "kitti"]
    os.mkfifo(fifo)
    assert main(argv) == 2
    assert capsys.readouterr().err == (f"error: {option}: {str(fifo)!r} is a FIFO, not a regular file; give a file "
                                       f"(or folder) the job can read\n")
    assert not (tmp_path / "out").exists()
