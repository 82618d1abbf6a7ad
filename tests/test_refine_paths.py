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
