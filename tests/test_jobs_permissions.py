"""The jobs and inputs the process may not read: a calibration file, a frame inside the --images
folder, a flow or road mask of eval vflow, a file of the tables' --kitti sample, each with its
permissions taken (chmod 000) ended the job in a PermissionError traceback (exit 1). Now one line,
``error: OPTION: 'PATH' cannot be read: permission denied; ...``, naming the option whose path it
is or lies in, and exit status 2, as for the other bad inputs. Run as root, whom the mode does not
stop, the file's open() is made to fail as it fails for any other user."""

from __future__ import annotations

import builtins
import errno
import io
import json
import os
import pathlib
from pathlib import Path

import pytest
import torch

from eval.__main__ import main as eval_main
from refine.__main__ import main as refine_main
from refine.inputs import permission_message

SIZE = (48, 160)


def take_permissions(path: Path, monkeypatch) -> None:
    """``path`` made unreadable: chmod 000, and for root (whom the mode does not stop) open()
    raising for it as it raises for any other user."""
    os.chmod(path, 0)
    if not os.access(path, os.R_OK):
        return
    real = io.open
    denied = os.path.abspath(path)

    def guarded(file, *args, **kwargs):
        if isinstance(file, (str, os.PathLike)) and os.path.abspath(file) == denied:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), os.fspath(file))
        return real(file, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", guarded)
    monkeypatch.setattr(io, "open", guarded)
    if hasattr(pathlib, "_NormalAccessor"):  # (Python 3.10: Path.open calls the io.open its accessor took at import)
        monkeypatch.setattr(pathlib._NormalAccessor, "open", staticmethod(guarded))


@pytest.fixture
def clip(tmp_path) -> Path:
    """Four rendered frames, calib.txt and road masks, as a folder of the user's."""
    from fsof_torch.data.scene import render_pair
    from fsof_torch.io import write_image, write_kitti_calibration, write_road_mask

    pairs = [render_pair("default", i, size=SIZE) for i in range(3)]
    root = tmp_path / "clip"
    (root / "images").mkdir(parents=True)
    (root / "road").mkdir()
    for i, image in enumerate([pairs[0]["image1"], *(p["image2"] for p in pairs)]):
        write_image(root / "images" / f"{i:06d}.png", image)
    for i, p in enumerate(pairs):
        write_road_mask(root / "road" / f"{i:06d}.png", p["road"])
    write_kitti_calibration(root / "calib.txt", pairs[0]["camera"].K[0], cam=0, style="odometry")
    return root


def _refine(clip: Path, out: Path) -> list[str]:
    return ["--images", str(clip / "images"), "--calib", str(clip / "calib.txt"), "--road", str(clip / "road"),
            "--source", "dis", "--odometry", "photometric", "--no-figures", "--no-progress", "--out", str(out)]


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.count("\n") == 1, err
    return err


@pytest.mark.parametrize("unreadable, option", [("calib.txt", "--calib"), ("images/000002.png", "--images")])
def test_refine_names_the_option_of_an_unreadable_input(clip, tmp_path, monkeypatch, capsys, unreadable, option):
    path = clip / unreadable
    take_permissions(path, monkeypatch)
    assert refine_main(_refine(clip, tmp_path / "out")) == 2
    assert _one_line(capsys) == (f"error: {option}: {str(path)!r} cannot be read: permission denied; give the process "
                                 f"access to it, or give another path\n")
    assert not (tmp_path / "out" / "report.json").exists()


def test_eval_vflow_names_flow_and_mask(tmp_path, monkeypatch, capsys):
    from fsof_torch.io import write_flow, write_road_mask

    flow, mask = tmp_path / "f.flo", tmp_path / "road.png"
    write_flow(flow, torch.randn(2, *SIZE))
    road = torch.zeros(1, *SIZE, dtype=torch.bool)
    road[:, SIZE[0] // 2:] = True
    write_road_mask(mask, road)
    take_permissions(mask, monkeypatch)
    assert eval_main(["vflow", "--flow", str(flow), "--mask", str(mask), "--out", str(tmp_path / "v"),
                      "--no-progress"]) == 2
    assert _one_line(capsys) == (f"error: --mask: {str(mask)!r} cannot be read: permission denied; give the process "
                                 f"access to it, or give another path\n")
    monkeypatch.undo()
    take_permissions(flow, monkeypatch)
    assert eval_main(["vflow", "--flow", str(flow), "--out", str(tmp_path / "v"), "--no-progress"]) == 2
    assert _one_line(capsys).startswith(f"error: --flow: {str(flow)!r} cannot be read: permission denied")
    assert not (tmp_path / "v").exists()


def test_eval_tables_names_kitti(tmp_path, monkeypatch, capsys):
    """A file inside the --kitti folder (its road.json)."""
    from fsof_torch.data.scene import render_pair
    from fsof_torch.io import write_kitti_calibration, write_kitti_flow

    pair = render_pair("default", 0, size=SIZE)
    sample = tmp_path / "kitti15_000000"
    sample.mkdir()
    write_kitti_flow(sample / "flow_noc_10.png", pair["flow"], pair["valid"])
    write_kitti_calibration(sample / "calib_cam_to_cam.txt", pair["camera"].K[0], cam=2)
    (sample / "road.json").write_text(json.dumps({"size": list(SIZE), "road_polygon": [[0, 47], [80, 30], [159, 47]]}))
    take_permissions(sample / "road.json", monkeypatch)
    assert eval_main(["tables", "--only", "kitti", "--kitti", str(sample), "--out", str(tmp_path / "t"),
                      "--no-progress"]) == 2
    assert _one_line(capsys).startswith(f"error: --kitti: {str(sample / 'road.json')!r} cannot be read: "
                                        "permission denied")


def test_permission_message_names_the_deepest_option_and_keeps_a_writers_message(tmp_path):
    clip = tmp_path / "clip"
    paths = {"--kitti15": clip, "--flows": clip / "flows", "--out": tmp_path / "out", "--gt": None}
    denied = PermissionError(errno.EACCES, "Permission denied", str(clip / "flows" / "000000.flo"))
    assert permission_message(denied, paths, ("--out",)).startswith(
        f"--flows: {str(clip / 'flows' / '000000.flo')!r} cannot be read: permission denied")
    denied = PermissionError(errno.EACCES, "Permission denied", str(tmp_path / "out" / "dis"))
    assert permission_message(denied, paths, ("--out",)).startswith(
        f"--out: {str(tmp_path / 'out' / 'dis')!r} cannot be written: permission denied")
    # a file no option gives (a library file, say): named alone
    assert permission_message(PermissionError(errno.EACCES, "Permission denied", "/etc/x"), paths) == \
        "'/etc/x': permission denied"
    # the atomic writer's own messages name their target: kept, without the writer's argument
    written = PermissionError(errno.EACCES, f"path: cannot write {str(tmp_path / 'out' / 'r.json')!r}: the folder "
                                            f"is not writable")
    assert permission_message(written, paths) == (f"cannot write {str(tmp_path / 'out' / 'r.json')!r}: the folder "
                                                   f"is not writable")
    assert permission_message(PermissionError("path: 'a' is read-only (mode 0o444)"), paths) == \
        "'a' is read-only (mode 0o444)"


def deny_writes_into(folder: Path, monkeypatch) -> None:
    """The atomic writer's temporaries in ``folder`` refused as for a folder the process may not
    write into (its mode does not stop root)."""
    import fsof_torch.io.atomic as atomic

    real = atomic.os.open

    def guarded(path, *args, **kwargs):
        if Path(path).parent == folder:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), os.fspath(path))
        return real(path, *args, **kwargs)

    monkeypatch.setattr(atomic.os, "open", guarded)


def test_a_folder_inside_out_that_cannot_be_written_exits_2(tmp_path, monkeypatch, capsys):
    """A folder of an earlier run's outputs that the process may not write into (another user's
    run, resumed): a PermissionError traceback, exit 1; now the writer's message and exit 2."""
    out = tmp_path / "out"
    pairs = out / "dis" / "given" / "pairs"
    deny_writes_into(pairs, monkeypatch)
    assert refine_main(["--num-pairs", "1", "--size", "48x160", "--source", "dis", "--odometry", "given",
                        "--no-figures", "--no-progress", "--out", str(out)]) == 2
    assert _one_line(capsys) == (f"error: cannot write {str(pairs / '000000.json')!r}: the folder {str(pairs)!r} is "
                                 f"not writable (Permission denied)\n")


def test_eval_names_an_output_it_cannot_write(tmp_path, monkeypatch, capsys):
    out = tmp_path / "v"
    out.mkdir()
    deny_writes_into(out, monkeypatch)
    assert eval_main(["vflow", "--size", "32", "96", "--out", str(out), "--no-progress"]) == 2
    assert _one_line(capsys) == (f"error: cannot write {str(out / 'vflow_map.png')!r}: the folder {str(out)!r} is "
                                 f"not writable (Permission denied)\n")


@pytest.mark.parametrize("job", ["refine", "synth", "train", "tables", "noise", "vflow"])
def test_an_existing_out_folder_that_cannot_be_written_is_refused_before_any_work(tmp_path, monkeypatch, capsys, job):
    """--out, a folder that exists but that the process may not write into (chmod a-w, another
    user's), passed the checks, which looked at the folder above it: train trained, vflow fitted,
    refine took its lock, then a traceback (now: the writer's PermissionError, exit 2, after the
    work). Now exit 2 naming --out before any work. (The test runs as any user: the folder's
    permission is what os.access reports.)"""
    import fsof_torch.io.atomic as atomic

    out = tmp_path / "out"
    out.mkdir()
    monkeypatch.setattr(atomic.os, "access", lambda path, mode: Path(path) != out)
    small = {"refine": ["--num-pairs", "1", "--size", "48x160", "--source", "dis", "--odometry", "given", "--no-figures"],
             "synth": ["--pairs", "1", "--size", "16", "48"], "tables": ["--only", "cvc12", "--quick"],
             "noise": ["--quick", "--no-plots"], "vflow": ["--size", "32", "96"],
             "train": ["--steps", "1", "--size", "16", "48", "--train-pairs", "1", "--test-pairs", "1", "--batch", "1"]}
    argv = [*small[job], "--out", str(out), "--no-progress"]
    assert (refine_main(argv) if job == "refine" else eval_main([job, *argv])) == 2
    assert _one_line(capsys) == (f"error: --out: the folder {str(out)!r} is not writable, so the job cannot write its "
                                 f"files into it\n")
    assert list(out.iterdir()) == []
