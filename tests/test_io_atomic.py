"""fsof_torch.io.atomic: temp file in the same folder + os.replace; a failure leaves no half file."""

from __future__ import annotations

import json
import re
import os

import numpy as np
import pytest
import torch

from fsof_torch.io import (atomic_path, remove_stale_temporaries, to_jsonable, write_bytes, write_json,
                           write_text)


def _leftovers(folder):
    return sorted(p.name for p in folder.iterdir() if ".tmp" in p.name)


class TestSmoke:
    def test_write_text_and_bytes(self, tmp_path):
        write_text(tmp_path / "a.txt", "hello")
        write_bytes(tmp_path / "b.bin", b"\x00\x01")
        assert (tmp_path / "a.txt").read_text() == "hello"
        assert (tmp_path / "b.bin").read_bytes() == b"\x00\x01"
        assert _leftovers(tmp_path) == []

    def test_temp_file_beside_target_keeps_suffix(self, tmp_path):
        with atomic_path(tmp_path / "x.png") as tmp:
            assert tmp.parent == tmp_path and tmp.suffix == ".png" and tmp != tmp_path / "x.png"
            tmp.write_bytes(b"data")
        assert (tmp_path / "x.png").read_bytes() == b"data"

    def test_empty_text_and_bytes_are_files(self, tmp_path):
        """An empty file is data for the raw writers (it once raised 'nothing was written')."""
        write_text(tmp_path / "old.txt", "old")
        write_text(tmp_path / "old.txt", "")
        write_bytes(tmp_path / "e.bin", b"")
        assert (tmp_path / "old.txt").read_bytes() == b"" and (tmp_path / "e.bin").read_bytes() == b""
        assert _leftovers(tmp_path) == []
        with atomic_path(tmp_path / "x.txt", allow_empty=True):
            pass
        assert (tmp_path / "x.txt").read_bytes() == b""

    def test_write_json_converts_tensors_and_arrays(self, tmp_path):
        obj = {"t": torch.tensor([1.5, 2.0]), "a": np.arange(3), "s": np.float32(0.5), "n": None, "p": tmp_path}
        write_json(tmp_path / "x.json", obj)
        back = json.loads((tmp_path / "x.json").read_text())
        assert back == {"t": [1.5, 2.0], "a": [0, 1, 2], "s": 0.5, "n": None, "p": str(tmp_path)}


class TestExceptions:
    def test_write_text_refuses_bytes(self, tmp_path):
        """bytes once raised AttributeError ('bytes' object has no attribute 'encode')."""
        with pytest.raises(TypeError, match=r"^text: expected a str, got bytes$"):
            write_text(tmp_path / "t.txt", b"abc")
        assert not (tmp_path / "t.txt").exists() and _leftovers(tmp_path) == []

    def test_failure_midway_leaves_no_file(self, tmp_path):
        with pytest.raises(RuntimeError, match="boom"):
            with atomic_path(tmp_path / "out.txt") as tmp:
                tmp.write_bytes(b"half of")
                raise RuntimeError("boom")
        assert not (tmp_path / "out.txt").exists()
        assert _leftovers(tmp_path) == []

    def test_failure_keeps_old_file(self, tmp_path):
        write_text(tmp_path / "out.txt", "old")
        with pytest.raises(RuntimeError):
            with atomic_path(tmp_path / "out.txt") as tmp:
                tmp.write_text("new, half")
                raise RuntimeError("crash")
        assert (tmp_path / "out.txt").read_text() == "old"
        assert _leftovers(tmp_path) == []

    def test_nothing_written_is_an_error(self, tmp_path):
        with pytest.raises(OSError, match="nothing was written"):
            with atomic_path(tmp_path / "empty.txt"):
                pass
        assert not (tmp_path / "empty.txt").exists()
        assert _leftovers(tmp_path) == []

    def test_missing_folder(self, tmp_path):
        with pytest.raises(FileNotFoundError, match="does not exist"):
            write_text(tmp_path / "no" / "x.txt", "a")

    @pytest.mark.parametrize("below", [("x.flo",), ("sub", "x.flo")])
    def test_a_file_where_a_folder_should_be_is_named(self, tmp_path, below):
        """write_flow('out.png/x.flo') with out.png a file said "the folder of ... does not exist",
        though out.png was there (a file); now the FileNotFoundError names the file in the way.
        Nothing is written, and a missing folder still says it does not exist."""
        import torch

        from fsof_torch.io import write_flow

        (tmp_path / "out.png").write_bytes(b"png")
        target = tmp_path.joinpath("out.png", *below)
        with pytest.raises(FileNotFoundError, match=r"^path: '.*out\.png' is a file, not a folder, so "
                                                     r"'.*x\.flo' cannot be written$"):
            write_flow(target, torch.zeros(2, 3, 4))
        assert [p.name for p in tmp_path.iterdir()] == ["out.png"]
        assert (tmp_path / "out.png").read_bytes() == b"png"
        with pytest.raises(FileNotFoundError, match=r"^path: the folder of '.*no/sub/x\.flo' does not exist$"):
            write_flow(tmp_path / "no" / "sub" / "x.flo", torch.zeros(2, 3, 4))

    def test_json_rejects_unknown_objects(self, tmp_path):
        with pytest.raises(TypeError, match="cannot write a object"):
            to_jsonable(object())

    @pytest.mark.parametrize("obj, first, second", [({1: "a", "1": "b"}, "1", "'1'"),
                                                    ({"x": {"1": 0, 1: 1}}, "'1'", "1"),
                                                    ({None: 0, "None": 1}, "None", "'None'")])
    def test_json_keys_that_collide(self, tmp_path, obj, first, second):
        """{1: "a", "1": "b"} once became {"1": "b"}."""
        with pytest.raises(ValueError, match=rf"obj: the keys {first} and {second} both become the JSON key"):
            to_jsonable(obj)
        with pytest.raises(ValueError, match="both become the JSON key"):
            write_json(tmp_path / "k.json", obj)
        assert not (tmp_path / "k.json").exists()

    def test_json_non_finite_becomes_null(self, tmp_path):
        write_json(tmp_path / "nan.json", {"x": float("nan"), "t": torch.tensor([1.0, float("inf")])})
        assert json.loads((tmp_path / "nan.json").read_text()) == {"x": None, "t": [1.0, None]}


class TestPermissions:
    @pytest.mark.parametrize("umask", [0o022, 0o077, 0o002, 0o222, 0o277])
    def test_mode_follows_umask(self, tmp_path, umask):
        """Written files get 0o666 less the umask, as open() gives (not mkstemp's private 0o600)."""
        import os
        import stat

        old = os.umask(umask)
        try:
            write_text(tmp_path / "a.txt", "x")
        finally:
            os.umask(old)
        assert stat.S_IMODE((tmp_path / "a.txt").stat().st_mode) == 0o666 & ~umask

    @pytest.mark.parametrize("umask", [0o022, 0o222, 0o277])
    def test_temporary_is_the_owners_to_write(self, tmp_path, umask):
        """The writers reopen the temporary by name: under a umask that takes the owner's write bit
        it was created read-only, and every write failed (for any user but root, who passes)."""
        import os
        import stat

        old = os.umask(umask)
        try:
            with atomic_path(tmp_path / "a.bin") as tmp:
                mode = stat.S_IMODE(tmp.stat().st_mode)
                tmp.write_bytes(b"x")
        finally:
            os.umask(old)
        assert mode == 0o600
        assert stat.S_IMODE((tmp_path / "a.bin").stat().st_mode) == 0o666 & ~umask

    def test_read_only_umask_writes_like_open(self, tmp_path):
        """Under umask 0o222 a write succeeds and gives a read-only file, as open() does (for root,
        who writes into read-only files, this passed before too: the mode test above is the one
        that shows the fix as any user)."""
        import stat

        old = os.umask(0o222)
        try:
            write_bytes(tmp_path / "a.bin", b"hello")
        finally:
            os.umask(old)
        assert (tmp_path / "a.bin").read_bytes() == b"hello"
        assert stat.S_IMODE((tmp_path / "a.bin").stat().st_mode) == 0o444 and _leftovers(tmp_path) == []


    @pytest.mark.parametrize("mode", [0o600, 0o640, 0o444])
    def test_file_written_over_keeps_its_mode(self, tmp_path, mode, monkeypatch):
        """open() keeps the mode of a file it writes over; a private 0o600 file once became 0o644.
        A read-only file is written over by root only (others: test_read_only_file_is_not_written_over):
        another user is given root's view through os.access, which decides for the writer."""
        import stat

        import fsof_torch.io.atomic as atomic

        if os.geteuid() != 0:
            monkeypatch.setattr(atomic.os, "access", lambda p, m: True)
        path = tmp_path / "secret.json"
        path.write_text("{}")
        os.chmod(path, mode)
        old = os.umask(0o022)
        try:
            write_json(path, {"token": 1})
        finally:
            os.umask(old)
        assert stat.S_IMODE(path.stat().st_mode) == mode and json.loads(path.read_text()) == {"token": 1}


class TestTargets:
    def test_symlink_is_written_through(self, tmp_path):
        """open() writes into the file a link points to; the link was once replaced by a file."""
        (tmp_path / "data").mkdir()
        real = tmp_path / "data" / "real.txt"
        real.write_text("old")
        link = tmp_path / "link.txt"
        link.symlink_to(real)
        assert write_text(link, "new") == link
        assert link.is_symlink() and real.read_text() == "new"
        dangling = tmp_path / "dangling.txt"
        dangling.symlink_to(tmp_path / "data" / "made.txt")
        write_text(dangling, "made")
        assert dangling.is_symlink() and (tmp_path / "data" / "made.txt").read_text() == "made"
        assert _leftovers(tmp_path) == [] and _leftovers(tmp_path / "data") == []

    @pytest.mark.parametrize("name", ["x" * 251 + ".txt", "x" * 226 + ".png", "ä" * 125 + ".json",
                                      "a." + "s" * 253])
    def test_longest_names_are_written(self, tmp_path, name):
        """The temporary's name adds 22 bytes and the suffix to the target's: a 230-byte name once
        failed with ENAMETOOLONG. The copy of the name is cut; the suffix stays where it fits."""
        from fsof_torch.io.atomic import TEMPORARY_NAME

        assert len(os.fsencode(name)) <= 255
        with atomic_path(tmp_path / name) as tmp:
            assert len(os.fsencode(tmp.name)) <= 255 and TEMPORARY_NAME.match(tmp.name)
            assert tmp.suffix == (tmp_path / name).suffix or len(tmp_path.joinpath(name).suffix) > 200
            tmp.write_bytes(b"1")
        assert (tmp_path / name).read_bytes() == b"1" and _leftovers(tmp_path) == []

    def test_read_only_file_is_not_written_over(self, tmp_path, monkeypatch):
        """A file the process may not write (chmod a-w to keep it: ground truth) was replaced by the
        rename all the same, where open() refuses it. Root writes into any file: the test takes the
        view of another user through os.access, which decides for the writer as for open()."""
        import fsof_torch.io.atomic as atomic

        path = tmp_path / "flow_gt.txt"
        path.write_text("precious")
        os.chmod(path, 0o444)
        if os.geteuid() == 0:
            real = os.access
            monkeypatch.setattr(atomic.os, "access", lambda p, mode: not (mode & os.W_OK) and real(p, mode))
        with pytest.raises(PermissionError, match=r"^path: '.*flow_gt\.txt' is read-only \(mode 0o444\); make it "
                                                  r"writable to write over it"):
            write_text(path, "overwritten")
        assert path.read_text() == "precious" and _leftovers(tmp_path) == []
        assert atomic.creation_error(path, "--json") == f"--json: {str(path)!r} is read-only, so it cannot be written over"

    def test_folder_not_writable_names_the_target(self, tmp_path, monkeypatch):
        """A folder the process may not write into: the error quoted the hidden temporary's name."""
        import errno

        import fsof_torch.io.atomic as atomic

        real_open = os.open

        def refuse(file, flags, mode=0o777):  # what a non-root user meets in a read-only folder
            raise PermissionError(errno.EACCES, "Permission denied", str(file))

        os.chmod(tmp_path, 0o555)
        try:
            if os.geteuid() == 0:
                monkeypatch.setattr(atomic.os, "open", refuse)
            with pytest.raises(PermissionError, match=rf"path: cannot write '.*out\.png': the folder "
                                                      rf"'{tmp_path}' is not writable \(Permission denied\)"):
                write_bytes(tmp_path / "out.png", b"1")
        finally:
            monkeypatch.setattr(atomic.os, "open", real_open)
            os.chmod(tmp_path, 0o755)
        assert list(tmp_path.iterdir()) == []

    def test_folder_at_the_target(self, tmp_path):
        """A folder where the file goes once failed in os.replace, quoting the temporary's name."""
        (tmp_path / "out.txt").mkdir()
        with pytest.raises(IsADirectoryError, match=r"^path: '.*out\.txt' is a folder; expected a file path$"):
            write_text(tmp_path / "out.txt", "x")
        assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


class TestStaleTemporaries:
    def test_removes_only_leftovers_of_atomic_writes(self, tmp_path):
        """A killed writer leaves '.<name>.<16 hex>.tmp<suffix>'; other hidden or .tmp files stay."""
        (tmp_path / "sub").mkdir()
        stale = [tmp_path / ".x.png.0123456789abcdef.tmp.png", tmp_path / "sub" / ".r.json.fedcba9876543210.tmp.json",
                 tmp_path / ".noext.00000000000000aa.tmp"]
        keep = [tmp_path / ".hidden", tmp_path / "user.tmp", tmp_path / ".x.png.nothex0123456789.tmp.png",
                tmp_path / "x.png"]
        for p in stale + keep:
            p.write_bytes(b"1")
        removed = remove_stale_temporaries(tmp_path)
        assert sorted(removed) == sorted(stale)
        assert all(p.exists() for p in keep) and not any(p.exists() for p in stale)

    def test_pattern_matches_what_atomic_path_creates(self, tmp_path):
        with pytest.raises(RuntimeError):
            with atomic_path(tmp_path / "f.flo") as tmp:
                name = tmp.name
                raise RuntimeError("killed")
        # a temporary of that very name (as a SIGKILL would leave it) is recognised
        (tmp_path / name).write_bytes(b"half")
        assert remove_stale_temporaries(tmp_path) == [tmp_path / name]

    def test_missing_folder_is_empty(self, tmp_path):
        assert remove_stale_temporaries(tmp_path / "none") == []


def test_creation_error_names_the_option(tmp_path, monkeypatch):
    """A path can be created where its nearest existing parent is a folder the process can write
    into; otherwise the message says why, naming the option."""
    import fsof_torch.io.atomic as atomic
    from fsof_torch.io.atomic import creation_error

    assert creation_error(tmp_path / "a" / "b.json", "--json") is None
    (tmp_path / "f").write_text("x")
    assert creation_error(tmp_path / "f" / "b.json", "--json") == (
        f"--json: {str(tmp_path / 'f')!r} is a file, so {str(tmp_path / 'f' / 'b.json')!r} cannot be created")
    monkeypatch.setattr(atomic.os, "access", lambda path, mode: False)
    assert creation_error(tmp_path / "a", "--out") == (
        f"--out: the folder {str(tmp_path)!r} is not writable, so {str(tmp_path / 'a')!r} cannot be created")


def test_the_kernels_file_systems_are_found_in_the_mount_table(tmp_path, monkeypatch, mount_table):
    """A path on the kernel's proc or sysfs (or another of its interfaces) cannot be created,
    whatever ``os.access`` says to root: ``--out /proc/x`` failed at mkdir, after the checks. The
    mount table's escaped mount points, and a disk mounted below such a file system, are read right."""
    from fsof_torch.io.atomic import creation_error, kernel_file_system

    spaced = tmp_path / "a b"
    (spaced / "disk").mkdir(parents=True)
    escaped = str(spaced).replace(" ", "\\040")
    table = ("22 1 0:21 / / rw - ext4 /dev/vda rw\n"
             f"23 22 0:22 / {escaped} rw,relatime - sysfs sysfs rw\n"
             f"24 23 0:23 / {escaped}/disk rw shared:5 - ext4 /dev/vdb rw\n")
    mount_table(table)
    assert kernel_file_system(spaced) == "sysfs" and kernel_file_system(tmp_path) is None
    assert kernel_file_system(spaced / "disk") is None
    assert creation_error(spaced / "x" / "y.json", "--json") == (
        f"--json: {str(spaced / 'x' / 'y.json')!r} is on the kernel's sysfs file system, where the job cannot "
        f"write its files; give a path on a disk")
    assert creation_error(spaced / "disk" / "x", "--out", folder=True) is None
    monkeypatch.undo()
    if os.path.isdir("/proc") and kernel_file_system("/proc") == "proc":
        assert creation_error("/proc/x", "--out", folder=True).startswith("--out: '/proc/x' is on the kernel's proc")
        assert creation_error("/proc/self/status", "--json").startswith("--json: '/proc/self/status' is on the")
    assert creation_error(tmp_path / "x", "--out", folder=True) is None


def test_a_fifo_or_device_is_not_replaced(tmp_path):
    """The rename put a regular file in the place of a FIFO, and (run as root) of a device: a job's
    ``--json /dev/null`` deleted the device node. Now a ValueError naming it, nothing written; the
    jobs' check (creation_error) says so before any work. /dev/null is only stat'ed here."""
    import stat

    from fsof_torch.io.atomic import creation_error, special_file

    fifo = tmp_path / "pipe.json"
    os.mkfifo(fifo)
    link = tmp_path / "link.json"
    link.symlink_to(fifo)
    for target in (fifo, link):
        with pytest.raises(ValueError, match=rf"^path: '{fifo}' is a FIFO, not a regular file; writing it would "
                                             rf"replace it"):
            write_json(target, {"a": 1})
        assert creation_error(target, "--json") == (
            f"--json: {str(target)!r} is a FIFO, not a regular file, which the job would replace with its file; "
            f"give a file path")
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode) and link.is_symlink() and _leftovers(tmp_path) == []
    if os.path.exists("/dev/null"):
        assert special_file("/dev/null") == "a character device"
        assert creation_error("/dev/null", "--json").startswith("--json: '/dev/null' is a character device")
    assert special_file(tmp_path) is None and special_file(tmp_path / "none") is None
    (tmp_path / "f.json").write_text("{}")
    assert special_file(tmp_path / "f.json") is None and creation_error(tmp_path / "f.json", "--json") is None


@pytest.mark.parametrize("given", ["out/", "out/.", "sub/.."])
def test_every_writer_refuses_a_path_that_names_a_folder(tmp_path, monkeypatch, given):
    """``write_flow("out/")`` wrote a file named ``out`` (``Path`` drops the slash), where a
    folder was meant: every writer now raises IsADirectoryError naming ``path``, writing
    nothing."""
    import fsof_torch.io as fio

    monkeypatch.chdir(tmp_path)
    flow, image = torch.zeros(2, 4, 4), torch.zeros(3, 4, 4)
    calls = {"write_flo": (flow,), "write_flow": (flow,), "write_kitti_flow": (flow,), "write_image": (image,),
             "write_image_array": (np.zeros((4, 4, 3), np.uint8),), "write_road_mask": (torch.ones(1, 4, 4) > 0,),
             "write_label_map": (torch.zeros(4, 4, dtype=torch.uint8),), "write_depth_png": (torch.ones(1, 4, 4),),
             "write_carla_flow": (flow,), "write_vkitti2_flow": (flow,), "write_kitti_poses": (torch.eye(4)[None],),
             "write_kitti_calibration": (torch.eye(3),), "write_json": ({"a": 1},), "write_text": ("x",),
             "write_bytes": (b"x",)}
    for name, args in calls.items():
        with pytest.raises(IsADirectoryError, match=rf"^path: {re.escape(repr(given))} names a folder; expected a "
                                                    r"file path$"):
            getattr(fio, name)(given, *args)
    assert list(tmp_path.iterdir()) == []
