"""``python -m refine``'s path options that the system cannot look up (a name longer than the
file system takes, a loop of symbolic links): exit 2 naming the option before any work. They were
Python's own 'File name too long' (an OSError) or 'Symlink loop' (a RuntimeError) as a traceback,
for an output below a folder still to be created after that folder was made."""

from __future__ import annotations

import os
import re

import pytest

from refine.__main__ import main


@pytest.mark.parametrize("option", ["--out", "--json", "--images", "--calib", "--road", "--poses", "--gt", "--flows",
                                    "--kitti15", "--kitti-odometry"])
@pytest.mark.parametrize("kind", ["long", "loop"])
def test_a_path_the_system_cannot_look_up_is_named(tmp_path, capsys, option, kind):
    (tmp_path / "loop_a").symlink_to("loop_b")
    (tmp_path / "loop_b").symlink_to("loop_a")
    before = sorted(p.name for p in tmp_path.iterdir())
    if kind == "long":
        name = "道" * (os.pathconf(tmp_path, "PC_NAME_MAX") // 3 + 5)  # (90 characters, 270 bytes)
        given = str(tmp_path / "new" / name / "x.json")
    else:
        given = str(tmp_path / "loop_a" / "x.json")
    argv = ["--no-figures", "--no-progress", option, given]
    if option != "--out":
        argv += ["--out", str(tmp_path / "out")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    if kind == "long":
        assert err.startswith(f"error: {option}: {given!r} holds a name of {len(os.fsencode(name))} bytes")
        assert f"longer than the {os.pathconf(tmp_path, 'PC_NAME_MAX')} its file system takes" in err
    else:
        assert err == f"error: {option}: {given!r} leads through a loop of symbolic links; give another path\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing written, no folder made


@pytest.mark.parametrize("option", ["--out", "--images", "--calib", "--road", "--poses", "--flows", "--gt", "--kitti15",
                                    "--kitti-odometry", "--testnet-weights", "--checkpoint"])
def test_an_empty_path_is_refused_not_read_as_the_current_folder(tmp_path, capsys, monkeypatch, option):
    """``--out "$OUT"`` with OUT unset: ``Path('')`` is the current folder, where the run wrote its
    manifest, records and reports (and the inputs were looked for: "no file at '.'"); now argparse's
    exit 2 naming the option, before anything is written."""
    monkeypatch.chdir(tmp_path)
    argv = ["--num-pairs", "1", "--size", "48x160", "--source", "dis", "--odometry", "given", "--no-figures",
            "--no-progress", option, ""]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.endswith(f"error: argument {option}: expected a path, got an empty one ('', which would be the current "
                        f"folder)\n")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("option", ["--out", "--json"])
def test_an_output_on_the_kernels_file_systems_is_refused(tmp_path, capsys, kernel_paths, option):
    """``--out /proc/x`` (or /sys, or /proc itself): the checks passed (root may write into /proc,
    says ``os.access``) and the job failed at its first write. Exit 2 naming the option, before
    any work."""
    for given in kernel_paths if option == "--out" else kernel_paths[1:]:  # (the proc root is no --json file)
        out = [] if option == "--out" else ["--out", str(tmp_path / "out")]
        assert main(["--no-figures", "--no-progress", option, given, *out]) == 2
        assert re.fullmatch(rf"error: {option}: {re.escape(repr(given))} is on the kernel's \w+ file system, .*\n",
                            capsys.readouterr().err)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("option", ["--images", "--calib", "--road", "--poses", "--gt", "--flows", "--testnet-weights",
                                    "--kitti15", "--kitti-odometry"])
def test_a_fifo_given_as_an_input_is_named(tmp_path, capsys, no_hang, option):
    """A FIFO as an input: ``--calib FIFO`` said 'no calibration file at', ``--images FIFO`` 'is a
    file; expected a folder'. Exit 2 naming the option and what it is, before any read."""
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    assert main(["--no-figures", "--no-progress", option, str(fifo), "--out", str(tmp_path / "out")]) == 2
    assert capsys.readouterr().err == (f"error: {option}: {str(fifo)!r} is a FIFO, not a regular file; give a file "
                                       f"(or folder) the job can read\n")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("sample, name", [("--kitti15", n) for n in ("image_10.png", "calib_cam_to_cam.txt", "road.json",
                                                                      "flow_noc_10.png")]
                         + [("--kitti-odometry", n) for n in ("calib.txt", "poses.txt", "road.json")])
@pytest.mark.parametrize("kind", ["fifo", "folder"])
def test_a_samples_file_that_is_a_fifo_or_a_folder_is_named(tmp_path, capsys, no_hang, sample, name, kind):
    """A sample's file that is a FIFO was 'lacks [...]' or 'is a folder'; its ground truth
    (flow_noc_10.png) a FIFO or a folder was left out, the run refined without it (exit 0). Exit 2
    naming the option and the file, before any read."""
    root = tmp_path / "sample"
    files = (["image_10.png", "image_11.png", "calib_cam_to_cam.txt", "road.json", "flow_noc_10.png"]
             if sample == "--kitti15" else ["calib.txt", "poses.txt", "road.json"])
    (root / "image_l").mkdir(parents=True)
    for n in files:
        (root / n).write_text("x")
    (root / name).unlink()
    os.mkfifo(root / name) if kind == "fifo" else (root / name).mkdir()
    assert main(["--no-figures", "--no-progress", sample, str(root), "--out", str(tmp_path / "out")]) == 2
    what = ("is a FIFO, not a regular file; give a file (or folder) the job can read" if kind == "fifo" else
            "is a folder; expected a file")
    assert capsys.readouterr().err == f"error: {sample}: {str(root / name)!r} {what}\n"
