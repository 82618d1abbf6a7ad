"""The jobs and the atomic writer when the disk fills (ENOSPC) or a quota is spent (EDQUOT): the
writer's own error ("[Errno 28] No space left on device") named no file, and both jobs ended in a
traceback. Now the error names the file that did not fit (none is left there, half written or as a
temporary), and the jobs end with one line on stderr and exit status 1. The full disk is simulated
by an fsync that fails as a full disk's (NFS and delayed allocation report it there)."""

from __future__ import annotations

import errno
import json
import os

import pytest

import fsof_torch.io.atomic as atomic
from eval.__main__ import main as eval_main
from fsof_torch.io import write_json
from refine.__main__ import main as refine_main


def fill_the_disk(monkeypatch, after: int = 0, code: int = errno.ENOSPC) -> None:
    """Every atomic write after the first ``after`` fails as on a full disk."""
    calls = {"n": 0}
    real = os.fsync

    def fsync(fd):
        calls["n"] += 1
        if calls["n"] > after:
            raise OSError(code, os.strerror(code))
        return real(fd)

    monkeypatch.setattr(atomic.os, "fsync", fsync)


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EDQUOT])
def test_a_full_disk_names_the_file(tmp_path, monkeypatch, code):
    (tmp_path / "r.json").write_text('{"old": 1}')
    fill_the_disk(monkeypatch, code=code)
    for name in ("r.json", "new.json"):
        with pytest.raises(OSError) as info:
            write_json(tmp_path / name, {"a": 1})
        assert info.value.errno == code
        assert info.value.strerror == f"path: cannot write {str(tmp_path / name)!r}: {os.strerror(code)}"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.json"]  # (no temporary, no new file)
    assert json.loads((tmp_path / "r.json").read_text()) == {"old": 1}


def test_nested_writes_name_the_file_that_did_not_fit(tmp_path, monkeypatch):
    """A writer that itself writes through atomic_path (a pair of synth, written whole: every
    file to its temporary, then all renamed) names the outer target, not its hidden temporary, and
    not each of the other files whose writes unwound after it (eval synth named all ten, nested)."""
    import contextlib

    from fsof_torch.io import atomic_path, write_bytes

    fill_the_disk(monkeypatch, after=1)  # (the first file fits, the second does not)
    with pytest.raises(OSError) as info:
        with contextlib.ExitStack() as stack:
            tmps = [stack.enter_context(atomic_path(tmp_path / name)) for name in ("c.png", "b.png", "a.png")]
            for tmp in tmps[::-1]:
                write_bytes(tmp, b"1")
    assert info.value.strerror == f"path: cannot write {str(tmp_path / 'b.png')!r}: No space left on device"
    assert list(tmp_path.iterdir()) == []


def test_other_errors_are_not_renamed(tmp_path, monkeypatch):
    fill_the_disk(monkeypatch, code=errno.EIO)
    with pytest.raises(OSError) as info:
        write_json(tmp_path / "r.json", {"a": 1})
    assert info.value.errno == errno.EIO and info.value.strerror == os.strerror(errno.EIO)


def test_refine_on_a_full_disk(tmp_path, monkeypatch, capsys):
    """The manifest is written, then the first pair's flow does not fit."""
    out = tmp_path / "out"
    fill_the_disk(monkeypatch, after=1)
    assert refine_main(["--num-pairs", "1", "--size", "48x160", "--source", "dis", "--odometry", "given",
                        "--no-figures", "--no-progress", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err
    flow = out / "dis" / "given" / "flow" / "000000.png"
    assert err == (f"refine: cannot write {str(flow)!r}: No space left on device; the pairs finished so far are "
                   f"kept: make room and run the command again (without --overwrite) to resume\n")
    assert not flow.exists() and not [p for p in out.rglob(".*") if ".tmp" in p.name]
    monkeypatch.undo()  # (room made: the run resumes in the same folder)
    assert refine_main(["--num-pairs", "1", "--size", "48x160", "--source", "dis", "--odometry", "given",
                        "--no-figures", "--no-progress", "--out", str(out)]) == 0
    assert flow.is_file() and (out / "report.json").is_file()


def test_eval_on_a_full_disk(tmp_path, monkeypatch, capsys):
    out = tmp_path / "v"
    fill_the_disk(monkeypatch)
    assert eval_main(["vflow", "--size", "48", "160", "--no-progress", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert err.startswith(f"eval vflow: cannot write {str(out / 'vflow_map.png')!r}: No space left on device; the "
                          f"files written so far are kept, each one whole\n"), err
    assert not list(out.iterdir())
