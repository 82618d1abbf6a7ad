"""``python -m refine``'s path options that the system cannot look up (a name longer than the
file system takes, a loop of symbolic links): exit 2 naming the option before any work. They were
Python's own 'File name too long' (an OSError) or 'Symlink loop' (a RuntimeError) as a traceback,
for an output below a folder still to be created after that folder was made."""

from __future__ import annotations

import os

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
def test_an_output_on_the_kernels_file_systems_is_refused(tmp_path, capsys, option):
    """``--out /proc/x`` (or /sys): the checks passed (root may write into /proc, says
    ``os.access``) and the job failed at its first write. Exit 2 naming the option, before any work."""
    from fsof_torch.io.atomic import kernel_file_system

    paths = [p for p, root, kind in (("/proc/x", "/proc", "proc"), ("/sys/x/y", "/sys", "sysfs"), ("/proc", "/proc", "proc"))
             if os.path.isdir(root) and kernel_file_system(root) == kind and (option == "--out" or p != root)]
    if not paths:
        pytest.skip("no /proc or /sys of the kernel's here")
    for given in paths:
        argv = ["--no-figures", "--no-progress", option, given]
        if option != "--out":
            argv += ["--out", str(tmp_path / "out")]
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"error: {option}: {given!r} is on the kernel's ") and err.count("\n") == 1
    assert list(tmp_path.iterdir()) == []
