"""``python -m refine`` in-process (``refine.__main__.main``) on tiny inputs: the pipeline, its
outputs, resuming by fingerprint, and every bad input exiting 2 with a message naming the option."""

from __future__ import annotations

import functools
import json
import math
import os
import re
import stat
from pathlib import Path

import pytest
import torch

from refine.__main__ import main

SIZE = (48, 160)
TINY = ["--size", f"{SIZE[0]}x{SIZE[1]}", "--no-progress"]


@pytest.fixture(scope="module")
def scene_pairs():
    from fsof_torch.data.scene import render_pair

    return [render_pair("default", i, size=SIZE) for i in range(2)]


@pytest.fixture
def user_folder(tmp_path, scene_pairs) -> Path:
    """Three frames of the synthetic scene in a user layout: images, calib, poses, road PNGs,
    ground truth and predicted flows (ground truth + noise) in two file formats."""
    from fsof_torch.io import (write_flow, write_image, write_kitti_calibration, write_kitti_poses,
                               write_road_mask)

    root = tmp_path / "data"
    for d in ("images", "road", "gt", "flows"):
        (root / d).mkdir(parents=True)
    p0, p1 = scene_pairs
    for i, im in enumerate([p0["image1"], p0["image2"], p1["image2"]]):
        write_image(root / "images" / f"{i:06d}.png", im)
    write_kitti_calibration(root / "calib.txt", p0["camera"].K[0], cam=0, style="odometry")
    write_kitti_poses(root / "poses.txt", torch.stack([p0["pose1"], p0["pose2"], p1["pose2"]]))
    g = torch.Generator().manual_seed(0)
    for i, (p, ext) in enumerate([(p0, ".flo"), (p1, ".npy")]):
        write_road_mask(root / "road" / f"{i:06d}.png", p["road"])
        write_flow(root / "gt" / f"{i:06d}.png", p["flow"], p["valid"])
        noisy = p["flow"] + 1.5 * torch.randn(p["flow"].shape, generator=g)
        write_flow(root / "flows" / f"{i:06d}{ext}", noisy)
    return root


def _mounting(scene_pairs) -> list[str]:
    cam = scene_pairs[0]["camera"]
    return ["--roll-deg", str(math.degrees(float(cam.roll[0]))),
            "--pitch-deg", str(math.degrees(float(cam.pitch[0]))), "--height", str(float(cam.height[0]))]


def _user(user_folder, out, *extra) -> list[str]:
    return ["--images", str(user_folder / "images"), "--calib", str(user_folder / "calib.txt"),
            "--out", str(out), "--no-progress", "--no-figures", *extra]


def _rows(report: Path) -> dict[tuple[str, str], dict]:
    summary = json.loads(report.read_text())
    return {(r["source"], r["variant"]): r for r in summary["rows"]}


def _err(capsys, argv) -> str:
    assert main(argv) == 2
    return capsys.readouterr().err


# -- smoke ----------------------------------------------------------------------------------------

def test_help_exits_zero(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "--kitti15" in out and "--net" in out and "--checkpoint" in out


@pytest.mark.parametrize("script, module, argv", [
    ("fsof-refine", "refine", ["--bogus"]),
    ("fsof-eval", "eval", ["--bogus"]),
    ("fsof-eval", "eval", ["synth", "--out", "o", "--bogus"]),
])
def test_the_console_scripts_usage_names_the_script(tmp_path, script, module, argv):
    """The console scripts pyproject installs (fsof-refine, fsof-eval) name themselves in their
    usage and errors, as the same job run with python -m names the module (they printed `usage:
    python -m refine`, a command the user had not typed)."""
    import re
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    # (the [project.scripts] table read by hand: tomllib is Python 3.11's, README promises 3.10)
    table = (root / "pyproject.toml").read_text().split("[project.scripts]", 1)[1].split("\n[", 1)[0]
    entry = re.search(rf'^{re.escape(script)}\s*=\s*"([^"]+)"', table, re.M).group(1)
    target, function = entry.split(":")
    # the wrapper pip writes for a [project.scripts] entry
    wrapper = tmp_path / script
    wrapper.write_text(f"import re\nimport sys\nfrom {target} import {function}\n"
                       f"if __name__ == '__main__':\n"
                       f"    sys.argv[0] = re.sub(r'(-script\\.pyw|\\.exe)?$', '', sys.argv[0])\n"
                       f"    sys.exit({function}())\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    sub = " synth" if argv[0] == "synth" else ""
    for command, name in (([sys.executable, str(wrapper)], script), ([sys.executable, "-m", module], f"python -m {module}")):
        done = subprocess.run([*command, *argv], capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120)
        assert done.returncode == 2, done.stderr
        assert done.stderr.startswith(f"usage: {name}{sub} [-h]"), done.stderr
        assert f"\n{name}{sub}: error: " in done.stderr and "--bogus" in done.stderr


def test_help_states_the_size_bound_of_the_constant(capsys, monkeypatch):
    """--size and --calib-size say the bound they check, the renderer's MAX_SIDE (the help held
    the literal 16384 beside the imported constant)."""
    import fsof_torch.data.scene.render as render

    monkeypatch.setattr(render, "MAX_SIDE", 4096)
    assert main(["--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "image size, each side 16 to 4096" in out and "calibration is for, each side 16 to 4096" in out
    assert "16384" not in out


def test_synthetic_default_pipeline(tmp_path, capsys):
    out = tmp_path / "out"
    old = os.umask(0o022)
    try:
        rc = main(["--num-pairs", "2", "--source", "dis", "--out", str(out), "--json", str(tmp_path / "r.json"), *TINY])
    finally:
        os.umask(old)
    assert rc == 0
    printed = capsys.readouterr().out
    assert "| road before | after | Δ% | all before | after | Δ% |" in printed
    for metric in ("census distance (0-1)", "SSIM dissimilarity (0-1)", "L1 photometric error (0-255)",
                   "end-point error (px)"):
        assert f"| {metric} |" in printed
        if not metric.startswith("end"):  # (the end-point error has no non-occluded row)
            assert f"| {metric}, non-occluded |" in printed
    rows = _rows(out / "report.json")
    assert set(rows) == {("dis", "given"), ("dis", "fit"), ("dis", "photometric")}
    given = rows[("dis", "given")]
    assert given["pairs"] == 2 and given["refined"] == 2
    # the scene's odometry and road mask are exact: the refined road flow is the truth
    assert given["epe_road_after"] < 0.05 < given["epe_road_before"]
    rec = json.loads((out / "dis" / "given" / "pairs" / "000000.json").read_text())
    assert 0 < rec["after"]["photo_road_noc_n"] <= rec["after"]["photo_road_n"]
    # the fits' own confidence: a flow fit's residual in pixels, an image fit's in grey levels
    # with its two image tests
    fitted = json.loads((out / "dis" / "fit" / "pairs" / "000000.json").read_text())
    assert fitted["fit_success"] is True and fitted["fit_residual_px"] >= 0 and "fit_correlation" not in fitted
    imaged = json.loads((out / "dis" / "photometric" / "pairs" / "000000.json").read_text())
    assert imaged["fit_success"] is (imaged["fit_correlation"] >= 0.5 and imaged["fit_inlier_share"] >= 0.25)
    assert imaged["fit_residual_grey"] >= 0 and "fit_residual_px" not in imaged
    # census and SSIM beside L1, road and overall, pooled over the pairs' pixels (KITTI style)
    summary = json.loads((out / "report.json").read_text())
    records = [r for r in summary["pairs"] if r["variant"] == "given"]
    for key in ("census_road", "census_all", "ssim_road", "ssim_all_noc", "photo_road", "epe_road"):
        for stage in ("before", "after"):
            pooled = (sum(r[stage][key] * r[stage][f"{key}_n"] for r in records)
                      / sum(r[stage][f"{key}_n"] for r in records))
            assert given[f"{key}_{stage}"] == pytest.approx(pooled, rel=1e-12), (key, stage)
    # the exact road flow matches the images better than DIS by the census distance
    assert given["census_road_after"] < given["census_road_before"]
    assert 0 < rec["after"]["census_road_n"] <= rec["after"]["photo_road_n"]
    assert rec["rank"] == 0 and len(rec["fingerprint"]) == 16 and len(rec["input_fingerprint"]) == 16
    assert (tmp_path / "r.json").is_file() and (out / "report.md").is_file() and (out / "run.json").is_file()
    from fsof_torch.io import read_kitti_flow

    flow, valid = read_kitti_flow(out / "dis" / "given" / "flow" / "000001.png")
    assert flow.shape == (2, *SIZE) and bool(valid.all())
    for f in ("figures/000000.png", "figures/000001.png", "summary.png"):
        assert (out / "dis" / f).is_file(), f
    assert not list(out.rglob("*.tmp*"))  # atomic writes leave no temporary files
    # outputs are readable per the umask (0o644 here), not private
    for p in [out / "report.md", out / "dis" / "summary.png", out / "dis" / "given" / "flow" / "000001.png"]:
        assert stat.S_IMODE(p.stat().st_mode) == 0o644, p
    summary = json.loads((out / "report.json").read_text())
    assert summary["world_size"] == 1 and summary["records_computed"] == 6
    assert summary["identity"]["input"] == {"kind": "synthetic", "preset": "default", "seed": 0,
                                            "size": list(SIZE), "noise": None}


def test_default_out_is_named_after_the_input(tmp_path, monkeypatch, user_folder):
    from refine.options import build_parser, default_out

    parse = build_parser().parse_args
    assert default_out(parse([])) == Path("refine_out/synthetic-default")
    assert default_out(parse(["--seed", "3", "--size", "48x160"])) == Path("refine_out/synthetic-default-seed3-48x160")
    assert default_out(parse(["--images", str(user_folder / "images")])) == Path("refine_out/data-images")
    # two clips in the documented layout (CLIP/images) do not meet in one folder
    assert default_out(parse(["--images", str(tmp_path / "clip_a" / "images")])) == Path("refine_out/clip_a-images")
    assert default_out(parse(["--images", "/images"])) == Path("refine_out/images")
    monkeypatch.chdir(tmp_path)
    assert main(["--num-pairs", "1", "--source", "dis", "--odometry", "given", "--no-figures", *TINY]) == 0
    assert (tmp_path / "refine_out" / "synthetic-default-48x160" / "report.json").is_file()


# -- resuming -------------------------------------------------------------------------------------

def test_resume_skips_finished_pairs(tmp_path):
    out = tmp_path / "out"
    args = ["--num-pairs", "2", "--source", "dis", "--odometry", "given", "--no-figures", "--out", str(out), *TINY]
    assert main(args) == 0
    rec0 = out / "dis" / "given" / "pairs" / "000000.json"
    rec1 = out / "dis" / "given" / "pairs" / "000001.json"
    stamp0 = rec0.stat().st_mtime_ns
    text1 = rec1.read_text()
    rec1.unlink()  # as if the run had stopped before the second pair finished
    assert main(args) == 0
    assert rec0.stat().st_mtime_ns == stamp0  # finished pair not redone
    assert rec1.is_file() and json.loads(rec1.read_text()) == json.loads(text1)
    summary = json.loads((out / "report.json").read_text())
    assert summary["rows"][0]["pairs"] == 2
    assert summary["records_resumed"] == 1 and summary["records_computed"] == 1
    assert "1 of 2 records were finished by an earlier run" in (out / "report.md").read_text()
    assert main([*args, "--overwrite"]) == 0
    assert rec0.stat().st_mtime_ns != stamp0


def test_a_changed_library_is_another_run(tmp_path, monkeypatch, capsys):
    """The library's version is the same across the edits of a source checkout: a run resumed
    after the code that computes its results changed reused the old code's records. The code's
    digest is in the identity: the rerun is refused, naming it; --overwrite redoes the pairs."""
    from refine import resume

    out = tmp_path / "out"
    args = ["--num-pairs", "1", "--source", "dis", "--odometry", "given", "--no-figures", "--out", str(out), *TINY]
    assert main(args) == 0
    manifest = json.loads((out / "run.json").read_text())
    assert manifest["identity"]["library_code"] == resume.code_digest()
    assert re.fullmatch(r"[0-9a-f]{32}", resume.code_digest())
    monkeypatch.setattr(resume, "code_digest", lambda: "0" * 32)  # as after an edit of fsof_torch
    capsys.readouterr()
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: --out: {str(out)!r} holds the results of another run (library_code: "), err
    assert main([*args, "--overwrite"]) == 0
    summary = json.loads((out / "report.json").read_text())
    assert summary["records_resumed"] == 0 and summary["records_computed"] == 1
    assert summary["identity"]["library_code"] == "0" * 32


def test_other_dependency_versions_are_another_run(tmp_path, monkeypatch, capsys):
    """DIS's flows move with the OpenCV build: a run resumed after an upgrade of OpenCV (or of
    torch, kornia, NumPy, Python) reused the old build's records beside the new one's. The
    versions are in the identity: the rerun is refused, naming the one that differs; --overwrite
    redoes the pairs."""
    import platform

    import cv2
    import kornia
    import numpy

    from refine import resume

    out = tmp_path / "out"
    args = ["--num-pairs", "1", "--source", "dis", "--odometry", "given", "--no-figures", "--out", str(out), *TINY]
    assert main(args) == 0
    manifest = json.loads((out / "run.json").read_text())
    python = ".".join(platform.python_version_tuple()[:2])
    assert manifest["identity"]["dependencies"] == {"python": python, "torch": torch.__version__,
                                                    "opencv": cv2.__version__, "kornia": kornia.__version__,
                                                    "numpy": numpy.__version__}
    built = cv2.__version__
    monkeypatch.setattr(cv2, "__version__", "0.0.1-other")  # as after an upgrade of OpenCV
    # (read once per process: a fresh cache here, the process's own one back after the test)
    monkeypatch.setattr(resume, "dependency_versions", functools.lru_cache(resume.dependency_versions.__wrapped__))
    capsys.readouterr()
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err == (f"error: --out: {str(out)!r} holds the results of another run (dependencies.opencv: "
                   f'"{built}" -> "0.0.1-other"); '
                   f"give another --out, or --overwrite to replace them\n"), err
    assert main([*args, "--overwrite"]) == 0
    summary = json.loads((out / "report.json").read_text())
    assert summary["records_resumed"] == 0 and summary["records_computed"] == 1
    assert summary["identity"]["dependencies"]["opencv"] == "0.0.1-other"
    assert main(args) == 0  # the same versions again: resumed
    assert json.loads((out / "report.json").read_text())["records_resumed"] == 1


def test_the_code_digest_covers_the_library_and_the_job(tmp_path, monkeypatch):
    """code_digest hashes the path and bytes of every .py file of fsof_torch and of refine."""
    import hashlib
    import shutil

    import fsof_torch
    from refine import resume

    copy = tmp_path / "copy"
    for package in (Path(fsof_torch.__file__).parent, Path(resume.__file__).parent):
        shutil.copytree(package, copy / package.name, ignore=shutil.ignore_patterns("__pycache__"))

    def digest(root: Path) -> str:  # (the same recipe, written out)
        h = hashlib.blake2b(digest_size=16)
        for name in ("fsof_torch", "refine"):
            for path in sorted((root / name).rglob("*.py"), key=lambda p: p.relative_to(root / name).as_posix()):
                h.update(f"{name}/{path.relative_to(root / name).as_posix()}\0".encode() + path.read_bytes() + b"\0")
        return h.hexdigest()

    assert resume.code_digest() == digest(copy)


def test_the_report_says_what_produced_it_and_the_identity_stays(tmp_path, check_environment):
    """report.json (and --json) carry an environment block: the command and its options, the seed,
    the code digest and versions the identity holds, and beside them the CPU, the thread counts and
    the device, which the identity leaves out. The identity keeps its keys and values (an earlier
    run of the same inputs and code resumes): the code digest by its recipe
    (test_the_code_digest_covers_the_library_and_the_job), the rest as written here."""
    import platform

    import cv2
    import kornia
    import numpy

    from refine import resume

    out = tmp_path / "out"
    args = ["--num-pairs", "1", "--source", "dis", "--odometry", "given", "--no-figures", "--threads", "1",
            "--out", str(out), "--json", str(tmp_path / "r.json"), *TINY]
    assert main(args) == 0
    report = json.loads((out / "report.json").read_text())
    assert json.loads((tmp_path / "r.json").read_text()) == report
    env = report["environment"]
    check_environment(env, job="refine", command="python -m refine", seed=0)
    assert env["options"]["num_pairs"] == 1 and env["options"]["size"] == list(SIZE) and env["threads"]["torch"] == 1
    identity = json.loads((out / "run.json").read_text())["identity"]
    assert report["identity"] == identity
    assert identity == {
        "version": "0.1.0", "library_code": resume.code_digest(),
        "dependencies": {"python": ".".join(platform.python_version_tuple()[:2]), "torch": torch.__version__,
                         "opencv": cv2.__version__, "kornia": kornia.__version__, "numpy": numpy.__version__},
        "input": {"kind": "synthetic", "preset": "default", "seed": 0, "size": list(SIZE), "noise": None},
        "sources": ["dis"], "variants": ["given"], "mode": "replace", "scale": 2.0, "fit_roll": False,
        "fit_pitch": False, "road": None, "calibrate_pitch": False, "odometry_sigma": None, "testnet_weights": None,
        "net": None, "outputs": ["dis"], "photometric": ["census", "ssim", "l1"]}
    assert env["library_code"] == identity["library_code"] and env["dependencies"] == identity["dependencies"]
    assert main(args) == 0  # the same run again: resumed, whatever the environment block holds
    assert json.loads((out / "report.json").read_text())["records_resumed"] == 1


def test_a_record_whose_flow_file_was_truncated_or_replaced_is_redone(tmp_path):
    """The records are finished, but one flow file beside them was truncated and another replaced
    by a flow of another run (here another variant's): those pairs are redone and their flows
    written again, not reported as this run's beside files that do not hold them."""
    out = tmp_path / "out"
    args = ["--num-pairs", "2", "--source", "dis", "--odometry", "given,fit", "--no-figures", "--out", str(out),
            *TINY]
    assert main(args) == 0
    flows = {n: out / "dis" / "given" / "flow" / f"{n}.png" for n in ("000000", "000001")}
    written = {n: f.read_bytes() for n, f in flows.items()}
    flows["000000"].write_bytes(written["000000"][:100])
    flows["000001"].write_bytes((out / "dis" / "fit" / "flow" / "000001.png").read_bytes())
    assert main(args) == 0
    summary = json.loads((out / "report.json").read_text())
    assert summary["records_resumed"] == 0 and summary["records_computed"] == 4
    assert {n: f.read_bytes() for n, f in flows.items()} == written
    assert main(args) == 0  # the flows it wrote itself: reused
    assert json.loads((out / "report.json").read_text())["records_resumed"] == 4


def test_a_shorter_rerun_reports_only_its_own_pairs(tmp_path):
    """The number of pairs is not part of a run's identity: a run of 1 pair into the folder of a
    run of 2 reuses pair 0 and reports it alone; pair 1's record stays, for a longer run later,
    which reuses both."""
    out = tmp_path / "out"
    args = ["--source", "dis", "--odometry", "given", "--no-figures", "--out", str(out), *TINY]
    assert main(["--num-pairs", "2", *args]) == 0
    rec1 = out / "dis" / "given" / "pairs" / "000001.json"
    stamp1 = rec1.stat().st_mtime_ns
    assert main(["--num-pairs", "1", *args]) == 0
    summary = json.loads((out / "report.json").read_text())
    assert [p["pair"] for p in summary["pairs"]] == ["000000"] and summary["rows"][0]["pairs"] == 1
    assert summary["records_resumed"] == 1 and summary["records_computed"] == 0
    assert rec1.is_file() and rec1.stat().st_mtime_ns == stamp1
    assert main(["--num-pairs", "2", *args]) == 0
    summary = json.loads((out / "report.json").read_text())
    assert summary["records_resumed"] == 2 and summary["records_computed"] == 0



def test_a_redone_pairs_figure_never_shows_its_old_records(tmp_path, user_folder, scene_pairs):
    """A pair's flow replaced, the rerun with --no-figures: the pair is redone and its figure (drawn
    from the old flow) and the clip summary are gone, the other pair's figure is kept; the next
    run with figures redraws the pair (its figure missing) and reuses the other."""
    import numpy as np

    out = tmp_path / "out"
    args = ["--images", str(user_folder / "images"), "--calib", str(user_folder / "calib.txt"),
            "--road", str(user_folder / "road"), "--flows", str(user_folder / "flows"), "--odometry", "fit",
            "--out", str(out), "--no-progress", *_mounting(scene_pairs)]
    assert main(args) == 0
    fig0, fig1, summary = (out / "files" / "figures" / "000000.png", out / "files" / "figures" / "000001.png",
                           out / "files" / "summary.png")
    stamp0 = fig0.stat().st_mtime_ns
    assert fig1.is_file() and summary.is_file()
    np.save(user_folder / "flows" / "000001.npy", np.zeros((2, *SIZE), np.float32))  # pair 1's flow replaced
    assert main([*args, "--no-figures"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["records_computed"] == 1 and report["records_resumed"] == 1
    assert not fig1.exists() and not summary.exists()
    assert fig0.stat().st_mtime_ns == stamp0
    assert main(args) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["records_computed"] == 1 and report["records_resumed"] == 1
    assert fig1.is_file() and summary.is_file() and fig0.stat().st_mtime_ns == stamp0


def test_dollar_signs_in_the_folder_and_frame_names_are_drawn_as_they_are(tmp_path, user_folder, scene_pairs,
                                                                          monkeypatch):
    """A folder ``run$$1`` and frames ``f$_$0.png`` ...: matplotlib read the text between two ``$``
    as mathtext, so the run failed drawing its clip summary after its last pair (exit 2 with
    matplotlib's ParseException, no report), and a folder ``d$1$2`` was titled ``d12``. The
    titles and the pair names on the axis are now drawn character for character."""
    import shutil

    from fsof_torch.evaluation import figures

    root = tmp_path / "run$$1"
    for d in ("images", "road", "flows"):
        shutil.copytree(user_folder / d, root / d)
        for f in sorted((root / d).iterdir()):
            f.rename(f.with_name(f"f$_${int(f.stem)}{f.suffix}"))
    texts = []
    saved = figures.save_figure

    def save(fig, path, **kw):  # the texts as matplotlib draws them: (what is drawn, whether as math)
        texts.extend(t._preprocess_math(t.get_text()) for t in fig.findobj(lambda o: hasattr(o, "get_text"))
                     if "$" in t.get_text())
        return saved(fig, path, **kw)

    monkeypatch.setattr(figures, "save_figure", save)
    out = tmp_path / "out"
    assert main(["--images", str(root / "images"), "--calib", str(user_folder / "calib.txt"), "--road",
                 str(root / "road"), "--flows", str(root / "flows"), "--odometry", "fit", "--out", str(out),
                 "--no-progress", *_mounting(scene_pairs)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert [r["pair"] for r in report["pairs"]] == ["f$_$0", "f$_$1"]
    assert (out / "files" / "summary.png").is_file() and (out / "files" / "figures" / "f$_$1.png").is_file()
    drawn = [text for text, math in texts if not math]
    assert len(drawn) == len(texts) and any(f"refine: {root / 'images'}: flow source" in t for t in drawn)
    assert any(t.startswith("pair f$_$1, flow source 'files'") for t in drawn) and "f$_$0" in drawn


def test_a_rerun_that_fails_leaves_no_report_of_the_run_before(tmp_path, user_folder, scene_pairs, capsys):
    """The rerun redoes pair 0 (its flow replaced) and stops on pair 1's broken flow file: the
    earlier report (in --out and at --json), which no longer matches pair 0's record, is gone, not
    left beside it."""
    from fsof_torch.io import write_flow

    out = tmp_path / "out"
    extra = tmp_path / "elsewhere.json"  # --json outside --out: the same report, the same fate
    args = _user(user_folder, out, "--road", str(user_folder / "road"), "--flows", str(user_folder / "flows"),
                 "--odometry", "fit", "--json", str(extra), *_mounting(scene_pairs))
    assert main(args) == 0
    assert (out / "report.md").is_file() and (out / "report.json").is_file() and extra.is_file()
    rec0 = out / "files" / "fit" / "pairs" / "000000.json"
    old = json.loads(rec0.read_text())
    write_flow(user_folder / "flows" / "000000.flo", torch.zeros(2, *SIZE))
    (user_folder / "flows" / "000001.npy").write_bytes(b"garbage")
    assert "--flows:" in _err(capsys, args)
    assert json.loads(rec0.read_text())["input_fingerprint"] != old["input_fingerprint"]  # pair 0 was redone
    assert not (out / "report.md").exists() and not (out / "report.json").exists() and not extra.exists()

def test_overwrite_into_a_folder_without_a_manifest_removes_its_report_and_summaries(tmp_path):
    """A folder of refine outputs whose run.json is gone, written into with --overwrite by a run of
    other options with --no-figures: the earlier report and clip summary are removed when the run
    starts, as after a run with a manifest; they no longer sat beside the new records (the
    summary for good: a run without figures never writes it again)."""
    out = tmp_path / "out"
    base = ["--num-pairs", "1", "--source", "dis", "--odometry", "given", "--out", str(out), *TINY]
    assert main(base) == 0
    summary_png = out / "dis" / "summary.png"
    assert summary_png.is_file()
    (out / "run.json").unlink()
    assert main([*base, "--mode", "confidence", "--no-figures", "--overwrite"]) == 0
    assert not summary_png.exists()
    report = json.loads((out / "report.json").read_text())
    assert report["mode"] == "confidence" and report["records_computed"] == 1


def test_rerun_with_other_options_is_refused_then_replaced(tmp_path, capsys):
    """A finished folder and a rerun with another fusion mode: refused with what differs; with
    --overwrite the work is redone and the report describes the new run."""
    out = tmp_path / "out"
    base = ["--num-pairs", "1", "--source", "dis", "--odometry", "given", "--no-figures", "--out", str(out), *TINY]
    assert main(base) == 0
    err = _err(capsys, [*base, "--mode", "confidence"])
    assert "--out:" in err and "another run" in err and "mode" in err and "--overwrite" in err
    assert json.loads((out / "report.json").read_text())["mode"] == "replace"  # untouched
    assert main([*base, "--mode", "confidence", "--overwrite"]) == 0
    summary = json.loads((out / "report.json").read_text())
    assert summary["mode"] == "confidence" and summary["records_resumed"] == 0
    assert {r["mode"] for r in summary["pairs"]} == {"confidence"}
    assert "fusion mode `confidence`" in (out / "report.md").read_text()


def test_rerun_with_other_inputs_is_refused(tmp_path, capsys, user_folder, scene_pairs):
    """A synthetic run, then user images into the same --out: refused, never reported as new."""
    out = tmp_path / "out"
    assert main(["--num-pairs", "2", "--source", "dis", "--odometry", "given", "--no-figures",
                 "--out", str(out), *TINY]) == 0
    before = (out / "report.json").read_text()
    err = _err(capsys, _user(user_folder, out, "--road", str(user_folder / "road"), "--source", "dis",
                             *_mounting(scene_pairs)))
    assert "--out:" in err and "input.kind" in err and "synthetic" in err
    assert (out / "report.json").read_text() == before


def test_a_refusal_shows_where_two_long_paths_differ(tmp_path, capsys, user_folder, scene_pairs):
    """Two drives in KITTI's raw layout (``<drive>/image_00/data``) differ in a folder deep in
    their paths, and share the default --out (``image_00-data``): the refusal showed both paths cut
    to their common start, ``"/.../kitti_raw/... -> "/.../kitti_raw/...``, the same text twice;
    it shows the part where they differ."""
    import shutil

    root = tmp_path / "datasets" / "kitti_raw"
    drives = [root / f"2011_09_26_drive_000{i}_sync" / "image_00" / "data" for i in (1, 2)]
    for d in drives:
        shutil.copytree(user_folder / "images", d)
    out = tmp_path / "out"
    args = ["--calib", str(user_folder / "calib.txt"), "--road", str(user_folder / "road"), "--source", "dis",
            "--odometry", "given", "--poses", str(user_folder / "poses.txt"), "--out", str(out), "--no-progress",
            "--no-figures", *_mounting(scene_pairs)]
    assert main(["--images", str(drives[0]), *args]) == 0
    err = _err(capsys, ["--images", str(drives[1]), *args])
    old, new = re.search(r"input\.images: (.*?) -> (.*?)\); give another --out", err).groups()
    assert old != new, err
    assert "drive_0001_sync/image_00/data" in old and "drive_0002_sync/image_00/data" in new, err
    assert len(old) <= 40 and len(new) <= 40


def test_a_difference_is_shown_in_at_most_40_characters_around_where_it_starts():
    from refine.resume import _differences

    x = "x" * 50
    assert _differences({"mode": "replace"}, {"mode": "confidence"}) == ['mode: "replace" -> "confidence"']
    assert _differences({"a": "1" + x}, {"a": "2" + x}) == [f'a: "1{x[:35]}... -> "2{x[:35]}...']
    assert _differences({"a": x + "1"}, {"a": x + "2"}) == [f'a: ...{x[:10]}1" -> ...{x[:10]}2"']
    long = [_differences({"a": x + str(i) + x}, {"a": x + "-" + x})[0] for i in range(3)]
    assert long[0] == f'a: ...{x[:10]}0{x[:23]}... -> ...{x[:10]}-{x[:23]}...'
    assert len({line.split(" -> ")[0] for line in long}) == 3


def test_the_same_road_folder_spelled_otherwise_is_the_same_run(tmp_path, user_folder, scene_pairs, monkeypatch):
    """--road d/road, ./d/road and its absolute path name one folder (the input identity pins its
    resolved path and contents): the rerun reuses every record. Another road folder is refused."""
    import shutil

    monkeypatch.chdir(user_folder.parent)
    out = tmp_path / "out"
    args = _user(user_folder, out, "--source", "dis", "--odometry", "fit", *_mounting(scene_pairs))
    assert main([*args, "--road", "data/road"]) == 0
    assert json.loads((out / "run.json").read_text())["identity"]["road"] == "given"
    for road in ("./data/road", str(user_folder / "road"), "data/../data/road/"):
        assert main([*args, "--road", road]) == 0, road
        summary = json.loads((out / "report.json").read_text())
        assert summary["records_resumed"] == 2 and summary["records_computed"] == 0, road
    shutil.copytree(user_folder / "road", tmp_path / "road2")
    assert main([*args, "--road", str(tmp_path / "road2")]) == 2


def test_a_run_that_recorded_the_road_as_typed_is_resumed(tmp_path, user_folder, scene_pairs, monkeypatch, capsys):
    """Earlier runs kept --road as it was typed in their identity: a rerun of the same road folder,
    however spelled, reuses their records (a run of another road folder is refused naming it)."""
    import shutil

    from refine import resume

    monkeypatch.chdir(user_folder.parent)
    out = tmp_path / "out"
    args = _user(user_folder, out, "--source", "dis", "--odometry", "fit", *_mounting(scene_pairs))
    assert main([*args, "--road", "data/road"]) == 0
    # turn the folder into one an earlier run wrote: the road as typed, in the manifest and records
    manifest = json.loads((out / "run.json").read_text())
    old = {**manifest["identity"], "road": "data/road"}
    fp = resume.fingerprint(old)
    (out / "run.json").write_text(json.dumps({**manifest, "fingerprint": fp, "identity": old}))
    for rec in (out / "dis" / "fit" / "pairs").glob("*.json"):
        rec.write_text(json.dumps({**json.loads(rec.read_text()), "fingerprint": fp}))
    assert main([*args, "--road", str(user_folder / "road")]) == 0
    summary = json.loads((out / "report.json").read_text())
    assert summary["records_resumed"] == 2 and summary["records_computed"] == 0
    assert json.loads((out / "run.json").read_text())["fingerprint"] == fp
    shutil.copytree(user_folder / "road", tmp_path / "other")
    err = _err(capsys, [*args, "--road", str(tmp_path / "other")])
    assert "holds the results of another run" in err and "input.road" in err


def test_the_device_is_in_the_identity_off_the_cpu(tmp_path, capsys, monkeypatch):
    """A GPU rounds otherwise: a --device cuda rerun of a CPU run is another run (refused naming
    the device); on the CPU the identity holds no device key (runs from before it was recorded)."""
    import refine.__main__ as cli

    out = tmp_path / "out"
    args = ["--num-pairs", "1", "--source", "dis", "--odometry", "given", "--no-figures", "--out", str(out), *TINY]
    assert main(args) == 0
    assert "device" not in json.loads((out / "run.json").read_text())["identity"]
    if not torch.cuda.is_available():  # the identity of a cuda run, without a GPU: stop at the folder's check
        monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
        monkeypatch.setattr(cli, "_run_shard", lambda *a, **k: pytest.fail("a cuda run reused the CPU's folder"))
    err = _err(capsys, [*args, "--device", "cuda"])
    assert "holds the results of another run" in err and 'device: null -> "cuda"' in err


def test_a_folder_with_another_runs_manifest_but_no_results_is_taken(tmp_path):
    """A run stopped before its first record (e.g. on an error in the clip's fit) leaves only its
    manifest and empty output folders: a run of other options takes the folder; one with a
    record (or a report) of the other run is refused."""
    from refine import resume
    from refine.inputs import JobError

    out = tmp_path / "out"
    resume.prepare(out, {"mode": "replace", "outputs": ["dis"]}, overwrite=False)
    (out / "dis" / "given" / "pairs").mkdir(parents=True)
    manifest = resume.prepare(out, {"mode": "confidence", "outputs": ["dis"]}, overwrite=False)
    assert json.loads((out / "run.json").read_text()) == manifest and manifest["identity"]["mode"] == "confidence"
    assert not (out / "dis").exists()
    (out / "dis" / "given" / "pairs").mkdir(parents=True)
    (out / "dis" / "given" / "pairs" / "000000.json").write_text("{}")
    with pytest.raises(JobError, match=r"^--out: .* holds the results of another run \(mode: "):
        resume.prepare(out, {"mode": "replace", "outputs": ["dis"]}, overwrite=False)
    (out / "dis" / "given" / "pairs" / "000000.json").unlink()
    (out / "report.md").write_text("")
    with pytest.raises(JobError, match=r"holds the results of another run"):
        resume.prepare(out, {"mode": "replace", "outputs": ["dis"]}, overwrite=False)


def test_poses_that_give_the_clip_no_scale_stop_under_poses(tmp_path, user_folder, scene_pairs, capsys):
    """Poses that do not move are refused under --poses before any work; poses that move too little
    for the clip's fit to take a scale from them stop it under --poses (not the library's
    ``poses:``), and the corrected run into the same folder is not refused as another run's."""
    from fsof_torch.io import read_kitti_poses, write_kitti_poses

    P = read_kitti_poses(user_folder / "poses.txt")
    write_kitti_poses(tmp_path / "still.txt", P[[0, 0, 0]])
    out = tmp_path / "out"
    args = _user(user_folder, out, "--road", str(user_folder / "road"), "--source", "dis", *_mounting(scene_pairs))
    err = _err(capsys, [*args, "--poses", str(tmp_path / "still.txt")])
    assert err.startswith("error: --poses: the poses do not move (no pair's step exceeds 1e-06 m), so they give "
                          "the clip's fit (--odometry sequence) no scale"), err
    assert not (out / "run.json").exists()
    write_kitti_poses(tmp_path / "half.txt", P[[0, 0, 2]])  # the first pair stands still: the median step is 0
    err = _err(capsys, [*args, "--poses", str(tmp_path / "half.txt"), "--odometry", "sequence"])
    assert err.startswith("error: --poses: their translations give no scale"), err
    far = P.clone()  # poses in other units: a camera 30 times as high (millimetres stop at the steps)
    far[:, :3, 3] *= 30
    write_kitti_poses(tmp_path / "far.txt", far)
    err = _err(capsys, [*args, "--poses", str(tmp_path / "far.txt"), "--odometry", "sequence"])
    assert re.match(r"error: --poses: their translations give a camera height of \d+(\.\d+)? m, \d+(\.\d+)? times "
                    r"the camera's 1\.65 m", err), err
    assert main([*args, "--poses", str(user_folder / "poses.txt"), "--odometry", "sequence"]) == 0
    assert "height_m" in json.loads((out / "report.json").read_text())["calibrated_mounting"]


def test_changed_input_file_redoes_that_pair(tmp_path, user_folder, scene_pairs):
    out = tmp_path / "out"
    args = _user(user_folder, out, "--road", str(user_folder / "road"), "--source", "dis", "--odometry", "fit",
                 *_mounting(scene_pairs))
    assert main(args) == 0
    rec0, rec1 = (out / "dis" / "fit" / "pairs" / f"{i:06d}.json" for i in (0, 1))
    stamps = [r.stat().st_mtime_ns for r in (rec0, rec1)]
    from fsof_torch.io import write_image

    write_image(user_folder / "images" / "000002.png", scene_pairs[1]["image2"].flip(-1))  # pair 000001 only
    assert main(args) == 0
    assert rec0.stat().st_mtime_ns == stamps[0] and rec1.stat().st_mtime_ns != stamps[1]
    summary = json.loads((out / "report.json").read_text())
    assert summary["records_resumed"] == 1 and summary["records_computed"] == 1


def test_a_clip_uses_the_sequence_and_a_changed_frame_redoes_the_clip(tmp_path, user_folder, scene_pairs):
    """User images of a clip: the default variant is the clip's road motion (fit_sequence), its
    mounting is reported, and changing any frame redoes every pair of the clip."""
    out = tmp_path / "out"
    args = _user(user_folder, out, "--road", str(user_folder / "road"), "--source", "dis", *_mounting(scene_pairs))
    assert main(args) == 0
    summary = json.loads((out / "report.json").read_text())
    assert {r["variant"] for r in summary["rows"]} == {"sequence"}
    assert set(summary["calibrated_mounting"]) == {"roll_deg", "pitch_deg"}
    rec = json.loads((out / "dis" / "sequence" / "pairs" / "000000.json").read_text())
    assert rec["model"] == "plane" and "gate" in rec and rec["odometry"]["z_d"] > 0.5
    recs = [out / "dis" / "sequence" / "pairs" / f"{i:06d}.json" for i in (0, 1)]
    stamps = [r.stat().st_mtime_ns for r in recs]
    from fsof_torch.io import write_image

    write_image(user_folder / "images" / "000002.png", scene_pairs[1]["image2"].flip(-1))  # pair 000001's frame
    assert main(args) == 0
    assert all(r.stat().st_mtime_ns != t for r, t in zip(recs, stamps))


def test_a_frame_saved_anew_during_the_clips_fit_redoes_the_clip(tmp_path, user_folder, scene_pairs, monkeypatch):
    """A frame saved anew once the clip's fit has read it (the run goes on with the motion fitted to
    the old frame): the records must not carry the new frame's digest, or the rerun, fitting the new
    frame, reused them as its results. Now the clip's inputs are digested before the fit: the rerun
    redoes every pair, and its records equal a fresh run's."""
    import refine.__main__ as job
    from fsof_torch.io import write_image

    fit_clip = job._fit_clip

    def fit_then_save(*args, **kw):
        fitted = fit_clip(*args, **kw)
        write_image(user_folder / "images" / "000002.png", scene_pairs[1]["image2"].flip(-1))
        return fitted

    monkeypatch.setattr(job, "_fit_clip", fit_then_save)
    run = lambda out: _user(user_folder, out, "--road", str(user_folder / "road"), "--source", "dis",  # noqa: E731
                            "--odometry", "sequence", *_mounting(scene_pairs))
    assert main(run(tmp_path / "out")) == 0
    monkeypatch.setattr(job, "_fit_clip", fit_clip)
    assert main(run(tmp_path / "out")) == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["records_resumed"] == 0 and report["records_computed"] == 2
    assert main(run(tmp_path / "fresh")) == 0
    for pair in ("000000", "000001"):
        rerun, fresh = (json.loads((tmp_path / o / "dis" / "sequence" / "pairs" / f"{pair}.json").read_text())
                        for o in ("out", "fresh"))
        assert rerun["odometry"] == fresh["odometry"] and rerun["input_fingerprint"] == fresh["input_fingerprint"]


def test_the_clips_frames_are_digested_once_under_a_bar(tmp_path, user_folder, scene_pairs, monkeypatch, capsys):
    """Before the clip's fit the job digests every frame for the run's identity, each frame twice
    (the second image of one pair, the first of the next) and with nothing on the terminal: 6.7 s
    on a 4540-frame clip before the first bar. Each file is read once now, under a bar counting
    pairs, and the clip's fingerprint is the one it was (earlier runs resume)."""
    from refine import inputs
    from refine.job import clip_fingerprint, input_fingerprint
    from refine.resume import fingerprint

    m = _mounting_values(scene_pairs)
    specs, _ = inputs.user_pairs(images=user_folder / "images", calib=user_folder / "calib.txt", cam=None,
                                 height=m["--height"], roll_deg=m["--roll-deg"], pitch_deg=m["--pitch-deg"],
                                 poses=None, flows=None, road=str(user_folder / "road"), gt=None)
    before = fingerprint({"clip": [input_fingerprint(s) for s in specs]})
    read = []
    digest = inputs._read_digest
    monkeypatch.setattr(inputs, "_read_digest", lambda path: read.append(str(path)) or digest(path))
    capsys.readouterr()
    assert clip_fingerprint(specs, progress=True) == before
    frame = str(user_folder / "images" / "000001.png")
    assert sorted(read) == sorted(set(read)) and read.count(frame) == 1
    err = capsys.readouterr().err
    assert "clip: digest: 100%" in err and "2/2" in err and "pair/s" in err
    read.clear()
    assert clip_fingerprint(specs, progress=True) == before and read.count(frame) == 1  # (read anew)
    capsys.readouterr()
    assert clip_fingerprint(specs, progress=False) == before  # (--no-progress)
    assert capsys.readouterr().err == ""
    assert inputs.file_digest(user_folder / "calib.txt") == digest(user_folder / "calib.txt")


def test_the_clips_bars_count_pairs(tmp_path, user_folder, scene_pairs, capsys):
    """The bars of a clip's run count pairs: "clip: load" showed it/s."""
    args = _user(user_folder, tmp_path / "out", "--road", str(user_folder / "road"), "--source", "dis",
                 "--odometry", "sequence", *_mounting(scene_pairs))
    args.remove("--no-progress")
    assert main(args) == 0
    err = capsys.readouterr().err
    assert "clip: digest" in err and "clip: load" in err and "refine" in err
    assert "it/s" not in err and "s/it" not in err


def _mounting_values(scene_pairs) -> dict[str, float]:
    """The values of the job's mounting options, as the job parses them."""
    m = _mounting(scene_pairs)
    return {option: float(value) for option, value in zip(m[::2], m[1::2])}


def _dataset_and_camera(user_folder, scene_pairs, **options):
    """The user folder's pairs and camera, read by the library's dataset with the job's mounting
    options."""
    from fsof_torch.datasets import ImageFolderDataset

    m = _mounting_values(scene_pairs)
    dataset = ImageFolderDataset(user_folder / "images", user_folder / "calib.txt", camera_height=m["--height"],
                                 roll=math.radians(m["--roll-deg"]), pitch=math.radians(m["--pitch-deg"]),
                                 road=user_folder / "road", camera_dtype=torch.float64, **options)
    items = [dataset[i] for i in range(len(dataset))]
    return items, dataset.camera


def _list_fit(items, camera, poses=None):
    """The clip's fit of its frames held as a list (the reference for the streamed fit)."""
    from fsof_torch import fit_sequence

    frames = [it["image1"] for it in items] + [items[-1]["image2"]]
    return fit_sequence(frames, [it["road"] for it in items], camera.to(torch.float64), poses=poses)


def test_a_clip_run_reports_the_fit_of_its_frames_reading_each_pair_a_few_times(tmp_path, user_folder,
                                                                                 scene_pairs, monkeypatch):
    """--odometry sequence streams the clip: each pair is read once for its road mask, once per
    pass of the clip's fit and once for its refinement; the calibrated mounting and each pair's
    success are those of fit_sequence on the list of the clip's frames."""
    from fsof_torch.datasets import ImageFolderDataset

    reads: dict[int, int] = {}
    getitem = ImageFolderDataset.__getitem__

    def counted(self, i):
        reads[i] = reads.get(i, 0) + 1
        return getitem(self, i)

    monkeypatch.setattr(ImageFolderDataset, "__getitem__", counted)
    out = tmp_path / "out"
    assert main(_user(user_folder, out, "--road", str(user_folder / "road"), "--source", "dis",
                      "--odometry", "sequence", *_mounting(scene_pairs))) == 0
    monkeypatch.undo()
    assert reads == {0: 4, 1: 4}
    items, camera = _dataset_and_camera(user_folder, scene_pairs)
    seq = _list_fit(items, camera)
    summary = json.loads((out / "report.json").read_text())
    assert summary["calibrated_mounting"] == {"roll_deg": math.degrees(seq.mounting["roll"]),
                                              "pitch_deg": math.degrees(seq.mounting["pitch"])}
    for i in range(len(items)):
        rec = json.loads((out / "dis" / "sequence" / "pairs" / f"{i:06d}.json").read_text())
        assert rec["clip_fit_success"] is bool(seq.fits[i].success.all())


def test_fit_clip_loads_each_pair_three_times_and_fits_like_a_list(user_folder, scene_pairs):
    """refine.calibrate.fit_clip: one load per pair for its road mask (road_for called once), one per
    pass of fit_sequence; the motion, mounting (with the poses' height) and success of the list
    of frames."""
    from dataclasses import replace

    from refine.calibrate import fit_clip
    from refine.inputs import user_pairs

    m = _mounting_values(scene_pairs)
    specs, camera = user_pairs(images=user_folder / "images", calib=user_folder / "calib.txt", cam=None,
                               height=m["--height"], roll_deg=m["--roll-deg"], pitch_deg=m["--pitch-deg"],
                               poses=user_folder / "poses.txt", flows=None, road=str(user_folder / "road"), gt=None)
    loads = {s.name: 0 for s in specs}
    roads = []

    def counted(spec):
        def load():
            loads[spec.name] += 1
            return spec.load()
        return replace(spec, load=load)

    def road_for(pair):
        roads.append(pair["road"])
        return pair["road"], {"index": len(roads) - 1}

    clip = fit_clip([counted(s) for s in specs], camera, road_for, progress=False)
    assert loads == {s.name: 3 for s in specs} and len(roads) == len(specs)
    for k, s in enumerate(specs):  # the masks the fit used, and what road_for said, by pair
        mask, info = clip.road(s.name)
        assert torch.equal(mask, roads[k].reshape(mask.shape).bool()) and info == {"index": k}
    items, _ = _dataset_and_camera(user_folder, scene_pairs, poses=user_folder / "poses.txt")
    # the poses as fit_clip chains them: camera-to-world with the world at the first camera
    P = [torch.eye(4, dtype=torch.float64)]
    for it in items:
        P.append(P[-1] @ torch.linalg.inv(it["relative_pose"]))
    seq = _list_fit(items, camera, torch.stack(P))
    for i, s in enumerate(specs):
        assert clip.motion[s.name] == {"model": "plane", **{k: float(v[i]) for k, v in seq.params.items()}}
        assert clip.success[s.name] is bool(seq.fits[i].success.all())
    assert clip.mounting == {"roll_deg": math.degrees(seq.mounting["roll"]),
                             "pitch_deg": math.degrees(seq.mounting["pitch"]), "height_m": seq.mounting["height"]}


def test_fit_clip_that_calibrates_nothing_gives_the_motion_fitted_with_the_nominal_camera():
    """A vehicle creeping by 4 mm a frame, with poses: its fits succeed and move, but their images show
    the attitude less than the prior does, so nothing is calibrated and the nominal camera (2 m high
    here) stays. fit_sequence's translations were still those at the poses' height (1.59 m), and the
    clip's motion paired them with the nominal camera: the road's flow scaled by 1.59 / 2. The motion
    is the one fitted with the nominal camera, as without poses."""
    from fsof_torch import fit_sequence
    from fsof_torch.data.scene import render_sequence
    from refine.calibrate import fit_clip
    from refine.inputs import PairSpec

    pairs = render_sequence("body-motion", 2, seed=0, speed=0.04)
    camera = pairs[0]["camera"].to(torch.float64).replace(height=2.0)

    def specs(poses: bool) -> list:
        items = [{"image1": p["image1"], "image2": p["image2"], "road": p["road"], "camera": p["camera"],
                  "relative_pose": torch.linalg.inv(p["pose2"].double()) @ p["pose1"].double() if poses else None}
                 for p in pairs]
        return [PairSpec(f"{k:06d}", lambda item=item: item) for k, item in enumerate(items)]

    clip = fit_clip(specs(True), camera, lambda pair: (pair["road"], {}), progress=False)
    assert clip.fitted == 0 and all(clip.success.values())
    assert float(clip.camera.height[0]) == 2.0 and "height_m" not in clip.mounting
    # the reference: the frames fitted with the nominal camera, no poses (nothing calibrated: one pass)
    frames = [p["image1"] for p in pairs] + [pairs[-1]["image2"]]
    roads = [p["road"] for p in pairs]
    alone = fit_sequence(frames, roads, camera, keep_fits=False)
    assert alone.calibrated_from == 0
    for k, name in enumerate(clip.motion):
        assert clip.motion[name] == {"model": "plane", **{n: float(v[k]) for n, v in alone.params.items()}}
    assert clip.motion == fit_clip(specs(False), camera, lambda pair: (pair["road"], {}), progress=False).motion
    # (the poses did give fit_sequence another height, and its translations at it)
    poses = torch.stack([p["pose1"] for p in pairs] + [pairs[-1]["pose2"]]).double()
    metric = fit_sequence(frames, roads, camera, poses=poses, keep_fits=False)
    assert metric.calibrated_from == 0 and metric.mounting["height"] < 1.8
    assert float(metric.params["z_d"][0]) < 0.9 * clip.motion["000000"]["z_d"]


def test_clip_frames_and_packed_masks():
    """ClipFrames: frame k < N is pair k's first image, frame N the last pair's second, one pair
    cached; PackedMasks give back the masks bit for bit (sizes not a multiple of 8)."""
    from refine.calibrate import ClipFrames, PackedMasks
    from refine.inputs import PairSpec

    g = torch.Generator().manual_seed(0)
    images = [torch.rand(3, 5, 7, generator=g) for _ in range(4)]
    loads = []

    def spec(k):
        def load():
            loads.append(k)
            return {"image1": images[k], "image2": images[k + 1]}
        return PairSpec(f"{k:06d}", load)

    frames = ClipFrames([spec(k) for k in range(3)])
    assert len(frames) == 4
    assert all(frames[j] is images[j] for j in range(4)) and loads == [0, 1, 2]
    assert frames[3] is images[3] and frames[0] is images[0] and loads == [0, 1, 2, 0]
    with pytest.raises(IndexError, match="frame 4 of a clip of 4 frames"):
        frames[4]
    masks = PackedMasks()
    originals = [torch.rand(1, 5, 7, generator=g) < 0.5 for _ in range(3)]
    for mask in originals:
        masks.append(mask)
    assert len(masks) == 3
    assert all(masks[k].dtype == torch.bool and torch.equal(masks[k], originals[k]) for k in range(3))


def test_packed_masks_keep_a_repeated_mask_once():
    """One road polygon or mask file for every pair gives every pair the same mask: the clip keeps
    its packed bytes once, not once a pair (58 kB a pair at 375×1242: 260 MB over a KITTI odometry
    sequence of 4541 frames), and each pair still gets its mask back, a tensor of its own."""
    from refine.calibrate import PackedMasks

    road = torch.zeros(1, 375, 1242, dtype=torch.bool)
    road[:, 200:, 300:900] = True
    other = road.clone()
    other[:, 374, 0] = True
    import tracemalloc

    masks = PackedMasks()
    one = math.ceil(375 * 1242 / 8)  # (58 219 bytes: 465 750 pixels, 8 a byte)
    tracemalloc.start()  # (NumPy reports its arrays' data to it)
    try:
        for _ in range(500):
            masks.append(road.clone())
        held, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert len(masks) == 500 and masks.nbytes == one
    assert held < 4 * one  # (not 500 masks' 29 MB)
    for mask in (other, other, road):  # a change is kept; a mask equal to an earlier but not the last one too
        masks.append(mask)
    assert len(masks) == 503 and masks.nbytes == 3 * one
    expected = [road] * 500 + [other, other, road]
    assert all(torch.equal(masks[k], expected[k]) for k in (0, 1, 499, 500, 501, 502))
    first = masks[0]
    first.fill_(False)  # (a caller's edit of one pair's mask reaches no other pair's)
    assert torch.equal(masks[1], road) and torch.equal(masks[0], road)


def test_calibrate_pitch_without_poses(tmp_path, user_folder, scene_pairs):
    """--calibrate-pitch from the images alone: every variant refines with the calibrated camera."""
    out = tmp_path / "out"
    args = _user(user_folder, out, "--road", str(user_folder / "road"), "--source", "dis", "--odometry", "fit",
                 "--calibrate-pitch")
    assert main(args) == 0
    summary = json.loads((out / "report.json").read_text())
    pitch = summary["calibrated_mounting"]["pitch_deg"]
    # the nominal pitch is 0 (no --pitch-deg); the scene's camera is pitched
    true = math.degrees(float(scene_pairs[0]["camera"].pitch[0]))
    assert abs(pitch - true) < 0.5
    for name in ("000000", "000001"):
        rec = json.loads((out / "dis" / "fit" / "pairs" / f"{name}.json").read_text())
        assert rec["refined"] and rec["pitch"] == pytest.approx(math.radians(pitch), abs=1e-9)


@pytest.mark.parametrize("size", [SIZE, (96, 320)])
def test_calibrate_pitch_with_auto_road(tmp_path, size, monkeypatch):
    """--calibrate-pitch with --road auto: the clip's masks are found in the images first, once
    per pair: the refinement of every source uses those detections (and records them). At 48 x 160
    the road is too faint to find (the pairs are flagged), no pair's fit succeeds and nothing is
    calibrated (the report says so); at 96 x 320 the clip calibrates the camera's pitch."""
    import fsof_torch
    from fsof_torch.data.scene import render_pair
    from fsof_torch.io import write_image, write_kitti_calibration

    pairs = [render_pair("default", i, size=size) for i in range(2)]
    (tmp_path / "images").mkdir()
    for i, im in enumerate([pairs[0]["image1"], pairs[0]["image2"], pairs[1]["image2"]]):
        write_image(tmp_path / "images" / f"{i:06d}.png", im)
    write_kitti_calibration(tmp_path / "calib.txt", pairs[0]["camera"].K[0], cam=0, style="odometry")
    detected = []
    detect_road = fsof_torch.detect_road

    def counting(*args, **kwargs):
        det = detect_road(*args, **kwargs)
        detected.append(int(det.mask.sum()))
        return det

    monkeypatch.setattr(fsof_torch, "detect_road", counting)
    out = tmp_path / "out"
    args = _user(tmp_path, out, "--road", "auto", "--source", "dis,testnet", "--odometry", "photometric",
                 "--calibrate-pitch")
    assert main(args) == 0
    summary = json.loads((out / "report.json").read_text())
    true = math.degrees(float(pairs[0]["camera"].pitch[0]))
    if size == SIZE:
        assert summary["calibrated_mounting"] is None
        assert any(n.startswith("Mounting not calibrated: no pair's fit over the clip succeeded (0 of 2)")
                   for n in summary["notes"])
    else:
        pitch = summary["calibrated_mounting"]["pitch_deg"]
        assert abs(pitch - true) < 1.0
        # the nominal pitch is 0 (no --pitch-deg): the calibration moved more than half way to the truth
        assert abs(true) > 0.5 and pitch / true > 0.5
        assert any(n.startswith("Mounting calibrated over the clip from its images (the fits of 2 of 2 pairs)")
                   for n in summary["notes"])
    assert len(detected) == len(pairs)  # once per pair, not once more per source
    for source in ("dis", "testnet"):
        for k in range(len(pairs)):
            rec = json.loads((out / source / "photometric" / "pairs" / f"{k:06d}.json").read_text())
            assert rec["road"] == "auto" and "road_flag" in rec
            assert rec["road_auto_pixels"] == detected[k]
            assert (rec["road_flag"] == "ok") == (size != SIZE)


def test_a_clip_whose_fits_all_fail_keeps_the_nominal_mounting(tmp_path, user_folder, monkeypatch):
    """Where no pair's fit over the clip succeeds nothing is calibrated: --calibrate-pitch refines
    with the nominal camera (pitch and roll 0 here), and the report says so instead of stating a
    calibrated mounting."""
    import dataclasses

    import refine.calibrate

    fit_sequence = refine.calibrate.fit_sequence

    def failing(*args, **kwargs):
        seq = fit_sequence(*args, **kwargs)
        return dataclasses.replace(seq, success=torch.zeros_like(seq.success), calibrated_from=0)

    monkeypatch.setattr(refine.calibrate, "fit_sequence", failing)
    out = tmp_path / "out"
    assert main(_user(user_folder, out, "--road", str(user_folder / "road"), "--source", "dis", "--odometry",
                      "fit", "--calibrate-pitch")) == 0
    summary = json.loads((out / "report.json").read_text())
    assert summary["calibrated_mounting"] is None
    assert ("Mounting not calibrated: no pair's fit over the clip succeeded (0 of 2); every variant uses the "
            "nominal mounting (pitch 0.00°, roll 0.00°), so --calibrate-pitch changed nothing.") in summary["notes"]
    assert not any(n.startswith("Mounting calibrated") for n in summary["notes"])
    for name in ("000000", "000001"):
        rec = json.loads((out / "dis" / "fit" / "pairs" / f"{name}.json").read_text())
        assert rec["pitch"] == 0.0 and rec["roll"] == 0.0


def test_the_mounting_note_of_a_clip_that_does_not_move_says_why():
    """A clip whose fits succeed on still frames only calibrates nothing (they measure no mounting):
    the note says so, not that no pair's fit succeeded."""
    from types import SimpleNamespace

    from refine.__main__ import _mounting_note

    mounting = {"pitch_deg": 0.0, "roll_deg": 0.0}
    still = SimpleNamespace(mounting=mounting, fitted=0, success={"000000": True, "000001": True})
    assert _mounting_note(still, True, 2).startswith(
        "Mounting not calibrated: the 2 of 2 pairs whose fits succeeded do not move, or too little for their "
        "images to show it (still frames, or a vehicle creeping by millimetres, measure no mounting); every "
        "variant uses the nominal mounting (pitch 0.00°, roll 0.00°)")
    failed = SimpleNamespace(mounting=mounting, fitted=0, success={"000000": False, "000001": False})
    assert _mounting_note(failed, False, 2).startswith(
        "Mounting not calibrated: no pair's fit over the clip succeeded (0 of 2); variants sequence / given_pitch")


def test_the_mounting_note_says_how_many_pairs_the_fit_redone_with_it_confirms():
    """A mounting calibrated from the clip's first fits is followed by the fit redone with it, whose
    success the sequence records hold: the note gives both counts, so that a calibration from 1 of 3
    pairs beside three records reading "the clip's fit failed" is not a contradiction; it names
    the variants the run has."""
    from types import SimpleNamespace

    from refine.__main__ import _mounting_note

    mounting = {"pitch_deg": -2.96, "roll_deg": 2.73}
    failed = SimpleNamespace(mounting=mounting, fitted=1, success={"000000": False, "000001": False, "000002": False})
    assert _mounting_note(failed, False, 3, ["sequence"]) == (
        "Mounting calibrated over the clip from its images (the fits of 1 of 3 pairs): pitch -2.96°, roll 2.73°; "
        "variant sequence uses it. The clip's fit, redone with it, succeeded on 0 of 3 pairs: no pair confirms "
        "the mounting (a road mask that holds more than the road, such as one covering the whole image, misleads "
        "the fit).")
    ok = SimpleNamespace(mounting=mounting, fitted=3, success={"000000": True, "000001": False, "000002": True})
    assert _mounting_note(ok, True, 3, ["photometric"]).endswith(
        "; every variant uses it. The clip's fit, redone with it, succeeded on 2 of 3 pairs.")
    assert "; variants sequence / given_pitch use it. " in _mounting_note(ok, False, 3, ["sequence", "given_pitch"])


@pytest.mark.slow
def test_a_whole_image_road_on_a_kitti_clip_gives_a_report_that_agrees_with_its_records(shared_data, tmp_path):
    """Road masks covering the whole image on frames 9-12 of the shared KITTI clip: the first fits
    calibrate a mounting from 1 of 3 pairs, and the fit redone with it fails on all three; the
    note says so, as the records' clip_fit_success do (it said 'from 1 of 3 pairs' and nothing
    of the three failures)."""
    import shutil

    from fsof_torch.io import write_road_mask

    clip = shared_data / "kitti_odometry_straight"
    if not clip.is_dir():
        pytest.skip("kitti_odometry_straight absent")
    (tmp_path / "images").mkdir()
    (tmp_path / "road").mkdir()
    for i in range(9, 13):
        shutil.copy(clip / "image_l" / f"{i:06d}.png", tmp_path / "images")
        if i < 12:
            write_road_mask(tmp_path / "road" / f"{i:06d}.png", torch.ones(1, 370, 1226, dtype=torch.bool))
    (tmp_path / "poses.txt").write_text("".join(clip.joinpath("poses.txt").read_text().splitlines(True)[9:13]))
    out = tmp_path / "out"
    assert main(["--images", str(tmp_path / "images"), "--calib", str(clip / "calib.txt"), "--road",
                 str(tmp_path / "road"), "--poses", str(tmp_path / "poses.txt"), "--odometry", "sequence",
                 "--out", str(out), "--no-progress", "--no-figures"]) == 0
    summary = json.loads((out / "report.json").read_text())
    success = [r["clip_fit_success"] for r in summary["pairs"]]
    (note,) = [n for n in summary["notes"] if n.startswith("Mounting")]
    assert summary["calibrated_mounting"] is not None
    assert note.startswith("Mounting calibrated over the clip from its images (the fits of 1 of 3 pairs)")
    assert success == [False] * 3
    assert "The clip's fit, redone with it, succeeded on 0 of 3 pairs: no pair confirms the mounting" in note
    assert note in (out / "report.md").read_text()


def test_stale_temporaries_are_removed(tmp_path):
    """A SIGKILL mid-write leaves hidden temporaries; the next run into the folder removes them."""
    out = tmp_path / "out"
    args = ["--num-pairs", "1", "--source", "dis", "--odometry", "given", "--out", str(out), *TINY]
    assert main(args) == 0
    stale = [out / "dis" / "given" / "flow" / ".000000.png.0123456789abcdef.tmp.png",
             out / "dis" / "figures" / ".000000.png.fedcba9876543210.tmp.png",
             out / ".report.json.00000000000000aa.tmp.json"]
    for p in stale:
        p.write_bytes(b"half a file")
    assert main(args) == 0
    assert not any(p.exists() for p in stale)
    assert not list(out.rglob("*.tmp*"))


def test_only_the_jobs_own_temporaries_are_removed_and_none_by_a_refused_run(tmp_path, capsys):
    """The cleaning of a killed run's temporaries went through every folder under --out, before
    the folder was even taken: --out naming a folder that holds another job's output (an eval
    run writing into results/eval) deleted that job's temporary under it, the write in flight
    (its rename then fails), and the run was refused anyway. Now a refused run touches nothing,
    and a run removes temporaries only beside its manifest and in its output folders."""
    base = ["--num-pairs", "1", "--source", "dis", "--odometry", "given", *TINY]
    results = tmp_path / "results"
    (results / "eval").mkdir(parents=True)
    (results / "notes.txt").write_text("mine")
    theirs = results / "eval" / ".metrics.json.0123456789abcdef.tmp.json"
    theirs.write_text("being written")
    assert "but no refine run" in _err(capsys, [*base, "--out", str(results)])
    assert theirs.read_text() == "being written"
    assert main([*base, "--out", str(results), "--overwrite"]) == 0  # written into: its own folders only
    assert theirs.read_text() == "being written"
    # a run killed while writing its manifest left the lock and the manifest's temporary: taken, cleaned
    killed = tmp_path / "killed"
    killed.mkdir()
    (killed / ".refine.lock").write_text("123")
    (killed / ".run.json.00000000000000ab.tmp.json").write_text("{")
    assert main([*base, "--out", str(killed)]) == 0
    assert not list(killed.rglob("*.tmp*"))
    # one killed while writing its first flow left no result: a run of other options replaces it
    first = killed / "dis" / "given" / "flow" / ".000000.png.00000000000000cd.tmp.png"
    for p in killed.rglob("*"):
        if p.is_file() and p.name not in ("run.json", ".refine.lock"):
            p.unlink()
    first.write_bytes(b"half a file")
    assert main([*base, "--out", str(killed), "--mode", "confidence"]) == 0
    assert not first.exists()
    assert json.loads((killed / "report.json").read_text())["mode"] == "confidence"


def test_a_second_run_into_a_locked_folder_is_refused(tmp_path, capsys):
    from refine.resume import locked

    out = tmp_path / "out"
    with locked(out):
        err = _err(capsys, ["--num-pairs", "1", "--source", "dis", "--no-figures", "--out", str(out), *TINY])
    assert "another refine run" in err and str(os.getpid()) in err


def test_a_refused_run_leaves_no_lock_in_a_folder_of_other_files(tmp_path, capsys):
    """--out naming a folder of the user's files is refused; the refused run left its lock file
    there, which made the folder pass for a refine run's output folder: a later --json into it
    was refused as 'the output folder of another refine run (its run.json)', which it never was."""
    from refine.resume import LOCK, holds_run

    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    base = ["--num-pairs", "1", "--source", "dis", "--odometry", "given", "--no-figures", *TINY]
    err = _err(capsys, [*base, "--out", str(mine)])
    assert "already holds files (notes.txt) but no refine run" in err
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"] and not holds_run(mine)
    assert main([*base, "--out", str(tmp_path / "out"), "--json", str(mine / "report.json")]) == 0
    assert json.loads((mine / "report.json").read_text())["rows"]
    # a run's folder keeps its lock (a run refused there keeps it too), and so does one taken with --overwrite
    assert (tmp_path / "out" / LOCK).is_file()
    assert _err(capsys, [*base, "--mode", "confidence", "--out", str(tmp_path / "out")])
    assert (tmp_path / "out" / LOCK).is_file() and holds_run(tmp_path / "out")
    (mine / "report.json").unlink()
    assert main([*base, "--out", str(mine), "--overwrite"]) == 0
    assert (mine / LOCK).is_file() and holds_run(mine)


def test_outputs_under_a_folder_that_cannot_be_written_are_refused_first(tmp_path, capsys, monkeypatch):
    """--out and --json under a folder the process cannot write into: exit 2 naming the option,
    before any work (as the eval job checks its own; the test runs as any user, so the folder's
    permission is what os.access reports)."""
    import fsof_torch.io.atomic as atomic

    locked_dir = tmp_path / "locked"
    locked_dir.mkdir()
    monkeypatch.setattr(atomic.os, "access", lambda path, mode: Path(path) != locked_dir)
    base = ["--num-pairs", "1", "--source", "dis", "--no-figures", *TINY]
    err = _err(capsys, [*base, "--out", str(locked_dir / "out")])
    assert f"--out: the folder {str(locked_dir)!r} is not writable" in err
    err = _err(capsys, [*base, "--out", str(tmp_path / "out"), "--json", str(locked_dir / "r.json")])
    assert f"--json: the folder {str(locked_dir)!r} is not writable" in err
    assert not (tmp_path / "out").exists()


def test_road_auto_on_images_too_small_for_it_exits_2_before_any_work(tmp_path, scene_pairs, capsys):
    """--road auto on images with a side under 32 pixels (the job takes 16) stopped on the first
    pair with the library's 'seed_level: 1 leaves fewer than 16 pixels ...', naming no option, after
    the run had begun; now exit 2 naming --road and the size before any work, as for a given road
    such images run."""
    from fsof_torch.io import write_image, write_kitti_calibration

    err = _err(capsys, ["--size", "20x66", "--road", "auto", "--num-pairs", "2", "--out", str(tmp_path / "s"),
                        "--no-progress", "--no-figures"])
    assert err.startswith("error: --road: auto finds the road on images with sides of at least 32 pixels (its "
                          "first estimate works on them at half size); --size is 20x66"), err
    images = tmp_path / "images"
    images.mkdir()
    for i in range(3):
        write_image(images / f"{i:06d}.png", scene_pairs[0]["image1"][:, :24, :80])
    write_kitti_calibration(tmp_path / "calib.txt", torch.tensor([[40.0, 0, 39.5], [0, 40.0, 11.5], [0, 0, 1]]),
                            cam=0, style="odometry")
    base = ["--images", str(images), "--calib", str(tmp_path / "calib.txt"), "--out", str(tmp_path / "u"),
            "--odometry", "photometric", "--no-progress", "--no-figures"]
    err = _err(capsys, [*base, "--road", "auto"])
    assert err.startswith(f"error: --road: auto finds the road on images with sides of at least 32 pixels (its "
                          f"first estimate works on them at half size); {str(images / '000000.png')!r} is 24x80"), err
    assert not (tmp_path / "s").exists() and not (tmp_path / "u").exists()
    (tmp_path / "road.json").write_text('{"size": [24, 80], "road_polygon": [[0, 23], [79, 23], [40, 12]]}')
    assert main([*base, "--road", str(tmp_path / "road.json")]) == 0


def test_testnet_source_confidence_mode(tmp_path):
    out = tmp_path / "out"
    rc = main(["--num-pairs", "1", "--source", "testnet", "--odometry", "given", "--mode", "confidence",
               "--no-figures", "--out", str(out), *TINY])
    assert rc == 0
    summary = json.loads((out / "report.json").read_text())
    assert summary["mode"] == "confidence" and any("random weights" in n for n in summary["notes"])


def test_road_auto_starts_from_a_partly_non_finite_flow(monkeypatch):
    """--road auto passes DIS's flow on with its NaN pixels (detect_road leaves them out, pixel by
    pixel); the job used to drop the whole flow from the detection for one such pixel."""
    import types

    import fsof_torch
    from fsof_torch.data.scene import render_pair
    from refine.job import road_mask

    p = render_pair("default", 1, size=(96, 320))
    pred = p["flow"] + 0.5
    pred[:, 80, 100] = float("nan")
    seen, detect = [], fsof_torch.detect_road
    monkeypatch.setattr(fsof_torch, "detect_road", lambda *a, **k: seen.append(k.get("flow")) or detect(*a, **k))
    road, road_from, info = road_mask({"image1": p["image1"], "image2": p["image2"], "road": p["road"]}, pred,
                                      p["camera"], types.SimpleNamespace(road_auto=True, road_options={}))
    assert road_from == "auto" and len(seen) == 1 and seen[0] is not None
    torch.testing.assert_close(seen[0][0], pred, rtol=0, atol=0, equal_nan=True)
    direct = detect(p["image1"][None], p["image2"][None], p["camera"], flow=pred[None])
    assert torch.equal(road, direct.usable_mask[0]) and info["road_flag"] == direct.flag[0] == "ok"


@pytest.mark.parametrize("size", ["48x160", "96x320"])
def test_synthetic_road_auto(tmp_path, size, capsys):
    """--road auto: at 48 x 160 the road's detail is too faint to judge, and the pair is flagged
    and left as predicted; at 96 x 320 the road is found and refined. Flag, reason and coverage
    are recorded per pair and in the report, and printed with it."""
    out = tmp_path / "out"
    rc = main(["--num-pairs", "1", "--source", "dis", "--odometry", "fit", "--road", "auto", "--no-figures",
               "--out", str(out), "--size", size, "--no-progress"])
    assert rc == 0
    rec = json.loads((out / "dis" / "fit" / "pairs" / "000000.json").read_text())
    assert rec["road"] == "auto"
    assert rec["road_max_height_m"] >= 0.3  # the step the evidence could show
    if size == "48x160":
        # (no parallax or texture the 48 x 160 images can show: either flag, with its reason)
        assert rec["road_flag"] in ("textureless", "static") and rec["road_reason"] != ""
        assert rec["road_pixels"] == 0 and 0.0 <= rec["road_coverage"] <= 1.0 and not rec["refined"]
        assert rec["after"]["epe_all"] == rec["before"]["epe_all"]
        line = f"  - flagged, left unrefined: 000000: {rec['road_flag']} ({rec['road_reason']})"
        printed, report = capsys.readouterr().out, (out / "report.md").read_text()
        assert line in printed.splitlines() and line in report.splitlines()
        # the road columns measured nothing: the '–' note names an empty road as a cause
        assert "e.g. the source gave no finite flow, or the road mask was empty)" in report
    else:
        assert rec["road_flag"] == "ok" and rec["road_reason"] == ""
        assert rec["refined"] and rec["road_pixels"] > 0 and 0.0 < rec["road_coverage"] <= 1.0
        assert rec["after"]["epe_road"] < 0.6 * rec["before"]["epe_road"]
    report = (out / "report.md").read_text()
    assert "Auto road (found in the images):" in report
    # (the step of the pairs ok: a flagged pair's evidence showed none)
    assert (f"the step the evidence could show: {rec['road_max_height_m']:g} m (1 pair)" in report) \
        == (rec["road_flag"] == "ok")
    assert json.loads((out / "report.json").read_text())["pairs"][0]["road_flag"] == rec["road_flag"]
    # (a run without --road-options has the identity it had: no road_options)
    assert "road_options" not in json.loads((out / "run.json").read_text())["identity"]


def test_auto_road_lines_give_the_steps_of_the_pairs_ok():
    """The report's steps are those the evidence of the pairs ok could show: a static pair (every
    step tried, none showed) or one without motion (the first step, no evidence) adds none (was:
    "1.2 m (1 pair)" beside "0 of 2 pairs ok")."""
    from refine.report import auto_road_lines

    def rec(pair, flag, step):
        return {"pair": pair, "road_flag": flag, "road_reason": "" if flag == "ok" else "why", "road_coverage": 0.3,
                "road_max_height_m": step}

    lines = auto_road_lines({"pairs": [rec("a", "static", 1.2), rec("b", "no_motion", 0.3)]})
    assert lines[0] == "- Auto road (found in the images): 0 of 2 pairs ok"
    lines = auto_road_lines({"pairs": [rec("a", "static", 1.2), rec("b", "ok", 0.6), rec("c", "ok", 0.3)]})
    assert lines[0].endswith("; the step the evidence could show: 0.3 m (1 pair), 0.6 m (1 pair)")
    assert lines[1:] == ["  - flagged, left unrefined: a: static (why)"]


def test_road_auto_is_detected_once_per_pair_from_dis_for_every_source(tmp_path, monkeypatch):
    """--road auto without a clip fit: each pair's road is detected once, from DIS's flow, and
    every source is refined on it (its records, and the report's summary, are the pair's)."""
    import fsof_torch

    detected = []
    detect_road = fsof_torch.detect_road

    def counting(*args, **kwargs):
        det = detect_road(*args, **kwargs)
        detected.append((int(det.mask.sum()), float(det.coverage[0])))
        return det

    monkeypatch.setattr(fsof_torch, "detect_road", counting)
    base = ["--num-pairs", "2", "--odometry", "given", "--road", "auto", "--no-figures", "--no-progress",
            "--size", "96x320"]
    assert main([*base, "--source", "dis,testnet", "--out", str(tmp_path / "both")]) == 0
    assert len(detected) == 2  # once per pair, not once more per source
    by_source = {}
    for r in json.loads((tmp_path / "both" / "report.json").read_text())["pairs"]:
        by_source.setdefault(r["source"], []).append((r["road_auto_pixels"], r["road_coverage"]))
    assert by_source["dis"] == by_source["testnet"] == detected
    # the road of a run without the dis source is DIS's too, not the random test net's
    first = list(detected)
    assert main([*base, "--source", "testnet", "--out", str(tmp_path / "testnet")]) == 0
    records = json.loads((tmp_path / "testnet" / "report.json").read_text())["pairs"]
    assert [(r["road_auto_pixels"], r["road_coverage"]) for r in records] == detected[2:] == first
    # (the synthetic road at this size is found: both pairs ok)
    assert "2 of 2 pairs ok" in (tmp_path / "both" / "report.md").read_text()


def test_user_data_flow_files_poses_and_gt(tmp_path, user_folder, scene_pairs):
    out = tmp_path / "out"
    rc = main(_user(user_folder, out, "--poses", str(user_folder / "poses.txt"), "--flows", str(user_folder / "flows"),
                    "--road", str(user_folder / "road"), "--gt", str(user_folder / "gt"), "--odometry", "given,fit",
                    *_mounting(scene_pairs)))
    assert rc == 0
    rows = _rows(out / "report.json")
    given, fit = rows[("files", "given")], rows[("files", "fit")]
    assert given["pairs"] == 2
    # poses -> odometry through the calibration file: the model matches the rendered road
    assert given["epe_road_after"] < 0.1 < 1.0 < given["epe_road_before"]
    assert fit["epe_road_after"] < 0.5 * fit["epe_road_before"]
    rec = json.loads((out / "files" / "given" / "pairs" / "000000.json").read_text())
    for k in ("x_d", "z_d", "yaw"):
        assert rec["odometry"][k] == pytest.approx(scene_pairs[0]["odometry"][k], abs=1e-6)


def test_the_poses_odometry_at_a_height_not_given_is_noted(tmp_path, user_folder, scene_pairs):
    """The road flow of odometry from poses scales with 1 / height; where --height is not given,
    the report notes the 1.65 m assumed (KITTI's camera). Here the scene's camera is 1.65 m high:
    the note is there, and the given odometry's flow is the scene's road flow; --height given, none."""
    note = ("Camera height not given (--height): 1.65 m, KITTI's camera, is assumed; the road flow of the odometry "
            "from --poses (variant given) scales with 1 / height: give the camera's height above the road, or "
            "--calibrate-pitch (with poses it calibrates the height over the clip).")
    for extra, noted in (((), True), (("--height", "1.65"), False)):
        out = tmp_path / f"out{len(extra)}"
        assert main(_user(user_folder, out, "--poses", str(user_folder / "poses.txt"), "--road",
                          str(user_folder / "road"), "--gt", str(user_folder / "gt"), "--odometry", "given",
                          *_mounting(scene_pairs)[:4], *extra)) == 0
        summary = json.loads((out / "report.json").read_text())
        assert [n for n in summary["notes"] if n.startswith("Camera height")] == ([note] if noted else [])
        assert (note in (out / "report.md").read_text()) == noted
    assert _rows(tmp_path / "out0" / "report.json")[("dis", "given")]["epe_road_after"] < 0.1


def test_a_change_from_zero_prints_n_a_not_the_mark_of_no_pixel(tmp_path, user_folder, scene_pairs):
    """A source that is the ground truth itself has end-point error 0 before refinement: no
    percentage of 0 (``null`` in the JSON), printed 'n/a' with a note, not the '–' of a metric
    measured over no pixel."""
    import numpy as np

    from fsof_torch.io import read_flow

    (tmp_path / "exact").mkdir()
    for i in range(2):
        flow, _ = read_flow(user_folder / "gt" / f"{i:06d}.png")
        np.save(tmp_path / "exact" / f"{i:06d}.npy", flow.numpy())
    out = tmp_path / "out"
    assert main(_user(user_folder, out, "--poses", str(user_folder / "poses.txt"), "--flows", str(tmp_path / "exact"),
                      "--road", str(user_folder / "road"), "--gt", str(user_folder / "gt"), "--odometry", "given",
                      *_mounting(scene_pairs))) == 0
    row = _rows(out / "report.json")[("files", "given")]
    assert row["epe_road_before"] == 0.0 and row["epe_road_after"] > 0.0 and row["epe_road_change_pct"] is None
    report = (out / "report.md").read_text()
    (line,) = [ln for ln in report.splitlines() if ln.startswith("|") and "end-point error" in ln]
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[4:7] == ["0.000", f'{row["epe_road_after"]:.3f}', "n/a"]
    assert cells[7:10] == ["0.000", f'{row["epe_all_after"]:.3f}', "n/a"]
    assert "–" not in line
    assert report.count("'n/a' in a Δ% column: the error before refinement is 0") == 1
    assert "'–': measured over no pixel" not in report  # every metric was measured


def test_a_change_that_rounds_to_zero_prints_0_0_not_minus_0_0():
    """A Δ% between -0.05 and 0 (an error that barely moved) rounds to zero: the table prints 0.0,
    as for no change at all, not '-0.0'; the JSON keeps the exact change."""
    from refine.report import table_markdown

    row = {"source": "dis", "variant": "given", "refined": 1, "pairs": 1,
           "epe_road_before": 2.0, "epe_road_after": 1.9992, "epe_road_change_pct": 100.0 * (1.9992 - 2.0) / 2.0,
           "epe_all_before": 3.0, "epe_all_after": 2.97, "epe_all_change_pct": 100.0 * (2.97 - 3.0) / 3.0}
    (line,) = [ln for ln in table_markdown({"rows": [row]}).splitlines() if "end-point error" in ln]
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[4:10] == ["2.000", "1.999", "0.0", "3.000", "2.970", "-1.0"]


def test_the_title_of_a_one_pair_run_says_pair(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["--num-pairs", "1", "--source", "dis", "--odometry", "given", "--no-figures", "--out", str(out),
                 *TINY]) == 0
    title = f"refine: synthetic 'default' sequence, 1 pair, {SIZE[0]}x{SIZE[1]}"
    assert (out / "report.md").read_text().splitlines()[0] == f"# {title}"
    assert f"\n{title}\n" in capsys.readouterr().out
    assert json.loads((out / "report.json").read_text())["title"] == title


def test_user_data_polygon_json_road(tmp_path, user_folder, scene_pairs):
    poly = {"size": list(SIZE), "road_polygon": [[0, 47], [40, 36], [120, 36], [159, 47]]}
    (user_folder / "road.json").write_text(json.dumps(poly))
    out = tmp_path / "out"
    rc = main(_user(user_folder, out, "--road", str(user_folder / "road.json"), "--source", "dis",
                    *_mounting(scene_pairs)))
    assert rc == 0
    assert _rows(out / "report.json")[("dis", "sequence")]["pairs"] == 2



def test_user_data_polygon_drawn_for_another_size_exits_2(tmp_path, user_folder, scene_pairs, capsys):
    """--road FILE with a polygon drawn for twice the images' size was stretched over them and the
    job ran on that road (exit 0): exit 2 naming --road, the file and both sizes, before any work."""
    poly = {"size": [2 * SIZE[0], 2 * SIZE[1]], "road_polygon": [[0, 95], [80, 72], [240, 72], [319, 95]]}
    (user_folder / "road.json").write_text(json.dumps(poly))
    out = tmp_path / "out"
    rc = main(_user(user_folder, out, "--road", str(user_folder / "road.json"), "--source", "dis",
                    *_mounting(scene_pairs)))
    err = capsys.readouterr().err
    assert rc == 2 and (f"error: --road: {str(user_folder / 'road.json')!r} is a polygon drawn for "
                        f"{2 * SIZE[0]}x{2 * SIZE[1]} images (its 'size'), but size is {SIZE[0]}x{SIZE[1]}; ") in err, err
    assert not (out / "run.json").exists()



def test_a_pair_left_unrefined_reports_no_motion_and_why(tmp_path, user_folder, scene_pairs, capsys, monkeypatch):
    """A pair whose fit fails is left unrefined: its record's motion is null, not the refiner's
    placeholder zeros (which counted as a forward motion of 0 m in the report's z_d error, 1.2 m
    off the poses, and were drawn as an estimate), the report's notes name it and say why, and
    its figure's 'after' columns say it was left unrefined (they repeat the prediction)."""
    from fsof_torch.evaluation.figures import PairFigure
    from fsof_torch.io import write_flow

    titles = {}
    update = PairFigure.update

    def spy(self, **kwargs):
        titles[kwargs["title"].split(",")[0]] = list(kwargs["flows"])
        return update(self, **kwargs)

    monkeypatch.setattr(PairFigure, "update", spy)

    noise = 40 * torch.randn(2, *SIZE, generator=torch.Generator().manual_seed(0))
    write_flow(user_folder / "flows" / "000001.npy", noise)  # no road plane in it: the fit fails
    out = tmp_path / "out"
    args = _user(user_folder, out, "--road", str(user_folder / "road"), "--poses", str(user_folder / "poses.txt"),
                 "--flows", str(user_folder / "flows"), "--odometry", "fit", *_mounting(scene_pairs))
    assert main([a for a in args if a != "--no-figures"]) == 0
    assert titles == {"pair 000000": ["before (files)", "after, odometry 'fit'"],
                      "pair 000001": ["before (files)", "after, odometry 'fit' (left unrefined)"]}
    recs = [json.loads((out / "files" / "fit" / "pairs" / f"{i:06d}.json").read_text()) for i in range(2)]
    assert recs[0]["refined"] and not recs[1]["refined"] and recs[1]["fit_success"] is False
    assert set(recs[1]["odometry"]) == set(recs[0]["odometry"]) and all(v is None for v in recs[1]["odometry"].values())
    row = _rows(out / "report.json")[("files", "fit")]
    assert row["refined"] == 1
    assert row["z_d_abs_error_m"] == pytest.approx(abs(recs[0]["odometry"]["z_d"] - recs[0]["odometry_given"]["z_d"]))
    note = ("- Left unrefined (the prediction kept): files / fit: 1 of 2 pair(s): the ego-motion fit to the flow "
            "failed: 000001 (the records hold each fit's residual and the gate's decision).")
    assert note in capsys.readouterr().out and note in (out / "report.md").read_text()


@pytest.mark.parametrize("road", ["road", "auto"])
def test_a_frame_dark_enough_to_pass_for_a_0_1_image_is_flagged_not_the_job_stopped(tmp_path, user_folder,
                                                                                      scene_pairs, road, capsys):
    """A clip's frame whose brightest pixel is 1 grey level (a lens cap, a tunnel): the job reads
    8-bit files and knows their range, so the library's guess that such values are a 0..1 image
    does not stop the job (it exited 2, 'values in [0, 1] look like 0..1 images'); the two pairs
    that hold the frame are reported, their prediction kept, with the reason."""
    from fsof_torch.io import write_image

    dim = (scene_pairs[0]["image2"] > 128).to(torch.uint8)  # grey levels 0 and 1
    write_image(user_folder / "images" / "000001.png", dim)
    out = tmp_path / "out"
    road_arg = str(user_folder / "road") if road == "road" else "auto"
    args = _user(user_folder, out, "--road", road_arg, "--source", "dis", "--odometry", "sequence,photometric",
                 *_mounting(scene_pairs))
    assert main([a for a in args if a != "--no-figures"]) == 0
    printed = capsys.readouterr().out
    for variant in ("sequence", "photometric"):
        for name in ("000000", "000001"):
            rec = json.loads((out / "dis" / variant / "pairs" / f"{name}.json").read_text())
            assert rec["refined"] is False
            assert rec["after"] == rec["before"]  # (the prediction kept)
            assert any(name in line and "unrefined" in line for line in printed.splitlines())  # (the reason)


def test_unrefined_notes_explain_each_pair_once():
    """Each unrefined pair is explained once: a given empty road and a flagged auto road by their own
    notes, an auto road found 'ok' but empty (which no other note names) here, grouped by reason."""
    from refine.report import unrefined_notes

    base = {"source": "dis", "variant": "fit", "refined": False, "prediction_finite": 1.0, "road_pixels": 10}
    records = [{**base, "pair": "a", "road": "given", "road_pixels": 0},
               {**base, "pair": "b", "road": "auto", "road_flag": "implausible"},
               {**base, "pair": "c", "road": "auto", "road_flag": "ok", "road_pixels": 0},
               {**base, "pair": "d", "road": "auto", "road_flag": "ok", "fit_success": False, "fit_residual_px": 3.0},
               {**base, "pair": "e", "road": "auto", "road_flag": "ok", "fit_success": False, "fit_residual_px": 2.0},
               {**base, "pair": "f", "road": "auto", "road_flag": "ok", "refined": True}]
    assert unrefined_notes(records) == [
        "Left unrefined (the prediction kept): dis / fit: 3 of 6 pair(s): the road mask is empty: c; the ego-motion "
        "fit to the flow failed: d, e (the records hold each fit's residual and the gate's decision)."]


def test_a_road_too_small_to_fit_is_not_blamed_on_the_gate(tmp_path, user_folder, scene_pairs, capsys):
    """A road mask of 50 pixels (fewer than the refiner's min_pixels, 100): the photometric variant
    estimates nothing there and leaves the pair unrefined. Its note says so; it said the images'
    gate kept the prediction, though the gate, handed no pixel, judged nothing (no cell, no point)."""
    from fsof_torch.io import write_road_mask

    road = scene_pairs[1]["road"]
    small = torch.zeros_like(road)
    small[:, 35:40, 70:80] = True
    assert bool(road[small].all())  # (road pixels: the model is defined there)
    write_road_mask(user_folder / "road" / "000001.png", small)
    out = tmp_path / "out"
    args = _user(user_folder, out, "--road", str(user_folder / "road"), "--source", "dis", "--odometry",
                 "photometric", *_mounting(scene_pairs))
    assert main(args) == 0
    rec = json.loads((out / "dis" / "photometric" / "pairs" / "000001.json").read_text())
    assert rec["road_pixels"] == 50 and not rec["refined"] and "fit_success" not in rec
    assert rec["gate"]["cells"] == 0
    note = ("- Left unrefined (the prediction kept): dis / photometric: 1 of 2 pair(s): too few usable road pixels "
            "to fit: 000001 (the records hold each fit's residual and the gate's decision).")
    assert note in capsys.readouterr().out and note in (out / "report.md").read_text()


def test_pairs_whose_road_mask_is_empty_are_named(tmp_path, user_folder, scene_pairs, capsys):
    """One empty mask in the road folder: the run goes on, leaves that pair unrefined and names it
    in the report's notes and on the console. Every mask empty: it stops under --road before any
    work (refine.inputs), not with a report of nothing refined."""
    from fsof_torch.io import write_road_mask

    zero = torch.zeros(1, *SIZE, dtype=torch.bool)
    write_road_mask(user_folder / "road" / "000001.png", zero)
    out = tmp_path / "out"
    args = _user(user_folder, out, "--road", str(user_folder / "road"), "--source", "dis", "--odometry", "fit",
                 *_mounting(scene_pairs))
    assert main(args) == 0
    note = "- Warning: road mask empty: 000001 (1 of 2 pair(s)): left unrefined"
    assert note in capsys.readouterr().out and note in (out / "report.md").read_text()
    rec = json.loads((out / "dis" / "fit" / "pairs" / "000001.json").read_text())
    assert rec["road_pixels"] == 0 and not rec["refined"]
    write_road_mask(user_folder / "road" / "000000.png", zero)
    err = _err(capsys, _user(user_folder, tmp_path / "out2", "--road", str(user_folder / "road"),
                             *_mounting(scene_pairs)))
    assert err.startswith("error: --road: ") and "holds no road pixel inside the 48x160 images" in err
    assert not (tmp_path / "out2").exists()

# -- errors ---------------------------------------------------------------------------------------

def test_missing_and_mismatched_inputs(tmp_path, user_folder, capsys):
    base = ["--images", str(user_folder / "images"), "--out", str(tmp_path / "o"), "--no-progress"]
    assert "--calib: user data needs" in _err(capsys, [*base, "--road", "auto"])
    calib = ["--calib", str(user_folder / "calib.txt")]
    assert "--road: user data needs road masks" in _err(capsys, [*base, *calib])
    assert "--images: no folder" in _err(capsys, ["--images", str(tmp_path / "nope"), *calib, "--road", "auto"])
    assert "--calib: no calibration file" in _err(capsys, [*base, "--calib", str(tmp_path / "x.txt"), "--road", "auto"])
    (tmp_path / "calib_dir").mkdir()  # (a folder: exit 2 naming it as a folder, not a traceback)
    assert "--calib: '" + str(tmp_path / "calib_dir") + "' is a folder; expected a calibration file" in _err(
        capsys, [*base, "--calib", str(tmp_path / "calib_dir"), "--road", "auto"])
    (user_folder / "flows" / "000001.npy").unlink()
    err = _err(capsys, [*base, *calib, "--road", "auto", "--flows", str(user_folder / "flows")])
    assert "--flows: no file for pair 000001" in err
    short = tmp_path / "short.txt"
    short.write_text((user_folder / "poses.txt").read_text().splitlines()[0] + "\n")
    assert "--poses:" in _err(capsys, [*base, *calib, "--road", "auto", "--poses", str(short)])
    assert "user data needs --poses" in _err(capsys, [*base, *calib, "--road", "auto", "--odometry", "given"])
    assert "--flows needs --images" in _err(capsys, ["--flows", str(user_folder / "flows"), "--out", str(tmp_path / "o")])
    assert "unknown preset" in _err(capsys, ["--preset", "nope", "--out", str(tmp_path / "o")])
    assert main(["--mode", "blend"]) == 2  # argparse's own error
    # a size beyond any camera's frame is refused before anything is written (was: a render that
    # filled memory, a traceback and exit 1, run.json already in --out)
    assert main(["--threads", "100000000", "--out", str(tmp_path / "huge")]) == 2  # (crashed torch's pool)
    assert "--threads: expected at most this machine's" in capsys.readouterr().err
    for option in ("--size", "--calib-size"):
        assert main([option, "16x1000000", "--out", str(tmp_path / "huge")]) == 2
        assert "expected sides of at most 16384 pixels, got '16x1000000'" in capsys.readouterr().err
        assert not (tmp_path / "huge").exists()


@pytest.mark.parametrize("option", ["--flows", "--road", "--gt"])
def test_files_are_never_paired_by_position(tmp_path, user_folder, capsys, option):
    """Two files for two pairs, but one named for neither pair: exit 2 naming the option and the
    pair, where sorted order would have given pair 000001 the wrong file."""
    folder = user_folder / option[2:]
    (old,) = [p for p in folder.iterdir() if p.stem == "000001"]
    old.rename(folder / f"000002{old.suffix}")
    road = [] if option == "--road" else ["--road", str(user_folder / "road")]
    err = _err(capsys, _user(user_folder, tmp_path / "o", option, str(folder), *road))
    assert f"{option}: no file for pair 000001" in err and str(folder) in err
    assert not (tmp_path / "o" / "run.json").exists()  # stopped before any work


def test_ambiguous_file_names(tmp_path, user_folder, capsys):
    from fsof_torch.io import write_flow

    write_flow(user_folder / "flows" / "000000.npy", torch.zeros(2, *SIZE))  # beside 000000.flo
    err = _err(capsys, _user(user_folder, tmp_path / "o", "--road", "auto", "--flows", str(user_folder / "flows")))
    assert "--flows: pair 000000 matches 2 files" in err


def test_mismatched_image_sizes(tmp_path, user_folder, capsys):
    from fsof_torch.io import write_image

    write_image(user_folder / "images" / "000002.png", torch.zeros(3, 40, 100))
    err = _err(capsys, _user(user_folder, tmp_path / "o", "--road", str(user_folder / "road")))
    assert "--images: 000002.png is 40x100 but 000000.png is 48x160" in err


def test_images_of_another_size_than_the_calibration(tmp_path, user_folder, scene_pairs, capsys):
    """Images at half the calibrated size: the principal point falls outside the images' middle
    half (odometry calib.txt has no size); a stated size (S_rect row, --calib-size) must match."""
    import torch.nn.functional as F

    from fsof_torch.io import write_image, write_kitti_calibration

    half = tmp_path / "half"
    half.mkdir()
    for p in sorted((user_folder / "images").iterdir()):
        from fsof_torch.io import read_image

        write_image(half / p.name, F.avg_pool2d(read_image(p)[None], 2)[0])
    args = ["--images", str(half), "--calib", str(user_folder / "calib.txt"), "--road", "auto",
            "--out", str(tmp_path / "o"), "--no-progress"]
    err = _err(capsys, args)
    assert "--images: 000000.png is 24x80" in err and "principal point" in err and "calib.txt" in err
    assert "--images: 000000.png is 24x80 but the calibration" in _err(capsys, [*args, "--calib-size", "48x160"])
    cam2cam = tmp_path / "calib_cam_to_cam.txt"
    write_kitti_calibration(cam2cam, scene_pairs[0]["camera"].K[0], cam=2)
    cam2cam.write_text(cam2cam.read_text() + "S_rect_02: 1.600000e+02 4.800000e+01\n")
    args[3] = str(cam2cam)
    assert "is for 48x160 images" in _err(capsys, args)
    double = tmp_path / "double"
    double.mkdir()
    from fsof_torch.io import read_image

    for p in sorted((user_folder / "images").iterdir()):
        write_image(double / p.name, F.interpolate(read_image(p)[None], scale_factor=2.0, mode="bilinear")[0])
    err = _err(capsys, ["--images", str(double), "--calib", str(user_folder / "calib.txt"), "--road", "auto",
                        "--out", str(tmp_path / "o"), "--no-progress"])
    assert "--images: 000000.png is 96x320" in err and "middle third" in err


def test_crashes_of_the_past_exit_2(tmp_path, user_folder, scene_pairs, capsys):
    """Each input that once ended in a traceback: exit 2 with a message naming the option."""
    base = ["--num-pairs", "1", "--source", "dis", "--no-figures", *TINY]
    # --json pointing at a folder: refused before the work, not after it
    (tmp_path / "jdir").mkdir()
    err = _err(capsys, [*base, "--out", str(tmp_path / "o1"), "--json", str(tmp_path / "jdir")])
    assert "--json:" in err and "is a folder" in err and not (tmp_path / "o1").exists()
    # --out an existing file
    (tmp_path / "file").write_text("x")
    assert "--out:" in _err(capsys, [*base, "--out", str(tmp_path / "file")])
    # a binary calibration file
    binary = tmp_path / "calib.bin"
    binary.write_bytes(bytes(range(256)) * 4)
    err = _err(capsys, ["--images", str(user_folder / "images"), "--calib", str(binary), "--road", "auto",
                        "--out", str(tmp_path / "o2"), "--no-progress"])
    assert "--calib:" in err and "calib.bin" in err
    user = _user(user_folder, tmp_path / "o3")
    # singular poses (an all-zero rotation)
    rows = (user_folder / "poses.txt").read_text().splitlines()
    rows[1] = " ".join(["0"] * 12)
    bad_poses = tmp_path / "poses.txt"
    bad_poses.write_text("\n".join(rows) + "\n")
    err = _err(capsys, [*user, "--road", "auto", "--poses", str(bad_poses)])
    assert "--poses:" in err and "line 2" in err and "not a rigid pose" in err
    # road JSON that is a number, or has size [0, 0]
    for text in ("5", json.dumps({"size": [0, 0], "road_polygon": [[0, 40], [100, 40], [50, 47]]})):
        (tmp_path / "road.json").write_text(text)
        err = _err(capsys, [*user, "--road", str(tmp_path / "road.json"), *_mounting(scene_pairs)])
        assert "--road:" in err and "road.json" in err
    # garbage and wrong-keys test-net weights
    (tmp_path / "garbage.pt").write_bytes(b"not a checkpoint" * 10)
    err = _err(capsys, [*base, "--source", "testnet", "--out", str(tmp_path / "o4"),
                        "--testnet-weights", str(tmp_path / "garbage.pt")])
    assert "--testnet-weights:" in err and "garbage.pt" in err
    torch.save({"conv.weight": torch.zeros(3)}, tmp_path / "wrong.pt")
    err = _err(capsys, [*base, "--source", "testnet", "--out", str(tmp_path / "o5"),
                        "--testnet-weights", str(tmp_path / "wrong.pt")])
    assert "--testnet-weights:" in err and "does not fit TinyRAFT" in err and "unexpected keys ['conv.weight']" in err
    assert not (tmp_path / "o4" / "run.json").exists() and not (tmp_path / "o5" / "run.json").exists()


def test_evaluate_noc_leaves_out_occluded_pixels():
    """With ground truth, the 'noc' photometric error covers only its valid pixels: a pixel
    occluded in image 2 (invalid ground truth) whose brightness no flow can match is left out."""
    from refine.measure import evaluate

    H, W = 6, 8
    image1 = torch.full((3, H, W), 100.0)
    image2 = image1.clone()
    image2[:, 2, 3] = 160.0  # an occluder in image 2 at one road pixel
    valid = torch.ones(1, H, W, dtype=torch.bool)
    valid[0, 2, 3] = False
    zero = torch.zeros(2, H, W)
    pair = {"image1": image1, "image2": image2, "flow": zero, "valid": valid}
    road = torch.zeros(1, H, W, dtype=torch.bool)
    road[0, 1:4, 1:6] = True
    before, after = evaluate(pair, zero, zero.clone(), road)
    for m in (before, after):
        assert m["photo_road_n"] == 15 and m["photo_road_noc_n"] == 14
        assert m["photo_road"] == pytest.approx(60.0 / 15)
        assert m["photo_road_noc"] == 0.0
        assert m["photo_all_noc_n"] == H * W - 1 and m["photo_all_noc"] == 0.0
        assert m["epe_road_n"] == 14 and m["epe_road"] == 0.0
    # without ground truth there is nothing to tell occlusion by
    before, _ = evaluate({"image1": image1, "image2": image2}, zero, zero, road)
    assert "photo_road_noc" not in before


def test_a_metric_over_no_pixel_has_no_value():
    """A flow that is NaN everywhere leaves no pixel to measure: the metrics are None, not 0."""
    from refine.measure import evaluate

    H, W = 6, 8
    image = torch.full((3, H, W), 100.0)
    nan = torch.full((2, H, W), float("nan"))
    road = torch.ones(1, H, W, dtype=torch.bool)
    pair = {"image1": image, "image2": image.clone(), "flow": torch.zeros(2, H, W),
            "valid": torch.ones(1, H, W, dtype=torch.bool)}
    for m in evaluate(pair, nan, nan.clone(), road):
        for key in ("census_road", "ssim_all", "photo_road_noc", "epe_road", "fl_all"):
            assert m[key] is None and m[f"{key}_n"] == 0, key


@pytest.mark.parametrize("value", [float("inf"), float("-inf")])
def test_an_infinite_flow_is_left_out_like_nan(value):
    """inf, at one pixel or everywhere, is left out as NaN is: the maps hold 0 there (not the
    dtype's largest value, whose end-point error overflows) and the metrics the same numbers."""
    from fsof_torch.data.scene import render_pair
    from refine.measure import evaluate, flow_maps

    p = render_pair("default", 0, size=SIZE)
    pair = {"image1": p["image1"], "image2": p["image2"], "flow": p["flow"], "valid": p["valid"]}
    y, x = (int(i) for i in (p["valid"] & p["road"])[0].nonzero()[0])
    pred, with_nan = p["flow"] + 0.8, p["flow"] + 0.8
    pred[:, y, x], with_nan[:, y, x] = value, float("nan")
    maps = flow_maps(pair, pred)
    assert maps["flow"][:, y, x].tolist() == [0.0, 0.0] and not maps["finite"][0, y, x]
    assert torch.isfinite(maps["e_E"]).all()
    refined = torch.where(p["road"], p["flow"], pred)
    measured = evaluate(pair, pred, refined, p["road"])
    assert measured == evaluate(pair, with_nan, torch.where(p["road"], p["flow"], with_nan), p["road"])
    assert measured[0]["epe_road_n"] == int((p["valid"] & p["road"]).sum()) - 1
    everywhere = torch.full_like(pred, value)
    for m in evaluate(pair, everywhere, everywhere.clone(), p["road"]):
        assert m["epe_road"] is None and m["epe_road_n"] == 0 and m["census_all"] is None


@pytest.fixture(scope="module")
def refined_pair():
    """A synthetic pair, a prediction (the truth + 0.8 px, with a NaN on the road) and its
    refinement (the truth on the road)."""
    from fsof_torch.data.scene import render_pair

    p = render_pair("default", 0, size=(64, 200))
    pred = p["flow"] + 0.8
    pred[:, 60, 100] = float("nan")
    refined = torch.where(p["road"], p["flow"], pred)
    return {"image1": p["image1"], "image2": p["image2"], "flow": p["flow"], "valid": p["valid"]}, pred, refined, p["road"]


def test_maps_of_a_refinement_are_computed_where_it_changed_the_flow(refined_pair):
    """With the prediction's maps as reference only the box around the changed pixels is
    computed: every map equals the whole image's, bit for bit but SSIM (its convolutions may sum
    in another order on a smaller image)."""
    from refine.measure import flow_maps

    pair, pred, refined, _ = refined_pair
    before = flow_maps(pair, pred)
    whole = flow_maps(pair, refined)
    boxed = flow_maps(pair, refined, reference=before)
    assert set(boxed) == set(whole)
    for key in whole:
        if key == "ssim":
            torch.testing.assert_close(boxed[key], whole[key], rtol=1e-6, atol=1e-7)
        else:
            assert torch.equal(boxed[key], whole[key]), key
    same = flow_maps(pair, pred.clone(), reference=before)  # nothing changed: the reference's maps
    assert all(torch.equal(same[k], before[k]) for k in before)


def test_compare_census_and_ssim_on_the_pixels_both_flows_define(refined_pair):
    """compare's photometric means, against means taken here with boolean indexing over the road
    pixels where both flows are finite and both kinds' windows lie in image 2."""
    from fsof_torch import photometric_error_map
    from refine.measure import evaluate

    pair, pred, refined, road = refined_pair
    before, after = evaluate(pair, pred, refined, road)
    finite = torch.isfinite(pred).all(0, keepdim=True)
    for kind, prefix in (("census", "census"), ("ssim", "ssim"), ("l1", "photo")):
        maps = [photometric_error_map(pair["image1"][None], pair["image2"][None], torch.nan_to_num(f)[None], kind=kind)
                for f in (pred, refined)]
        common = finite & maps[0][1][0] & maps[1][1][0]
        for stage, (error, _) in zip((before, after), maps):
            for region, mask in (("road", road), ("all", torch.ones_like(road)),
                                 ("road_noc", road & pair["valid"])):
                sel = common & mask
                assert stage[f"{prefix}_{region}_n"] == int(sel.sum())
                assert stage[f"{prefix}_{region}"] == pytest.approx(float(error[0][sel].double().mean()), rel=1e-9)
    assert after["census_road"] < before["census_road"] and after["epe_road"] < 1e-6


def test_class_sums_add_in_pixel_order():
    """The per-class float64 sums equal bincount's with weights and a plain loop that adds the
    pixels in order, bit for bit (values of mixed magnitude, where the order of additions shows)."""
    from refine.measure import _class_sums, _labels

    g = torch.Generator().manual_seed(5)
    classes = torch.randint(0, 4, (1, 23, 31), generator=g)
    own = torch.rand(1, 23, 31, generator=g) > 0.2
    values = (torch.rand(1, 23, 31, generator=g) * 10.0 ** torch.randint(-6, 7, (1, 23, 31), generator=g)).float()
    labels, counts = _labels(classes, own, 4)
    sums = _class_sums(labels, values, 4)
    weights = values.reshape(-1).double()
    assert sums == torch.bincount(labels, weights=weights, minlength=5)[:4].tolist()
    loop = [0.0] * 5
    for label, value in zip(labels.tolist(), weights.tolist()):
        loop[label] += value
    assert sums == loop[:4]
    assert counts == [int(((classes == c) & own).sum()) for c in range(4)]


def test_error_panel_is_epe_with_ground_truth_else_census(refined_pair):
    """A figure shows end-point error where there is ground truth; without it the census distance
    (not L1, which exposure changes and brightness-matching flows fool)."""
    from refine.measure import error_panel, flow_maps

    pair, pred, _, _ = refined_pair
    maps = flow_maps(pair, pred)
    error, valid, label = error_panel(maps)
    assert label == "end-point error (px)" and torch.equal(error, maps["e_E"])
    assert torch.equal(valid, maps["gt_valid"] & maps["finite"])
    maps = flow_maps({**pair, "flow": None, "valid": None}, pred)
    error, valid, label = error_panel(maps)
    assert label == "census distance (0-1)" and torch.equal(error, maps["census"])
    assert not bool(valid[0, 60, 100])  # the NaN pixel has no value


def test_max_flow_is_the_99th_percentile_of_valid_magnitudes():
    from refine.measure import max_flow

    H, W = 10, 20
    gt = torch.zeros(2, H, W)
    gt[0] = torch.arange(H * W, dtype=torch.float32).reshape(H, W)  # magnitudes 0..199
    valid = torch.ones(1, H, W, dtype=torch.bool)
    valid[0, :, 10:] = False  # keep 100 values: 0..9, 20..29, ...
    kept = torch.sort(gt[0][valid[0]]).values
    assert max_flow({"flow": gt, "valid": valid}, gt) == float(kept[math.ceil(0.99 * 100) - 1])
    road = torch.zeros(1, H, W, dtype=torch.bool)
    road[0, 5:, :] = True  # the road's valid magnitudes: 100..109, 120..129, ...
    kept = torch.sort(gt[0][(valid & road)[0]]).values
    assert max_flow({"flow": gt, "valid": valid}, gt, road) == float(kept[math.ceil(0.99 * 50) - 1])
    assert max_flow({"flow": gt, "valid": valid}, gt, torch.zeros_like(road)) == max_flow({"flow": gt, "valid": valid}, gt)


# -- the shared real data -------------------------------------------------------------------------

@pytest.mark.slow
def test_kitti15_dis_refined_with_photometric_odometry(shared_data, tmp_path):
    """DIS refined with ego-motion estimated from the images: road EPE vs ground truth <= 1 px."""
    root = shared_data / "kitti15_000000"
    if not root.is_dir():
        pytest.skip("kitti15_000000 absent")
    out = tmp_path / "out"
    rc = main(["--kitti15", str(root), "--odometry", "photometric", "--out", str(out), "--no-progress",
               "--no-figures"])
    assert rc == 0
    row = _rows(out / "report.json")[("dis", "photometric")]
    assert row["epe_road_before"] > 5.0
    assert row["epe_road_after"] <= 1.0


def test_scene_noise_option(tmp_path, capsys):
    """--scene-noise renders noisy images: the refined road flow (exact, with the scene's
    odometry) then has a higher photometric floor than on the noise-free sequence."""
    floors = []
    for noise in ("0", "3.8"):
        rc = main(["--num-pairs", "1", "--source", "dis", "--odometry", "given", "--scene-noise", noise,
                   "--no-figures", "--out", str(tmp_path / noise), "--json", str(tmp_path / f"{noise}.json"), *TINY])
        assert rc == 0
        (row,) = json.loads((tmp_path / f"{noise}.json").read_text())["rows"]
        assert row["epe_road_after"] < 1e-3
        floors.append(row["photo_road_after"])
    assert floors[1] > floors[0]  # (at 48x160 the noise is area-scaled to about 0.5 grey levels)
    assert "--scene-noise: expected >= 0" in _err(capsys, ["--scene-noise", "-1", "--out", str(tmp_path / "o")])


def test_num_pairs_beyond_the_scenes_last_frame_names_the_option(tmp_path, capsys):
    """--num-pairs beyond the scenes' last frame (MAX_FRAME = 100 000) is exit 2 naming --num-pairs,
    not the renderer's argument num_pairs, and nothing is written."""
    err = _err(capsys, ["--num-pairs", "100001", "--out", str(tmp_path / "o")])
    assert err.startswith("error: --num-pairs: expected 1 to 100000, got 100001")
    assert "--num-pairs: expected 1 to 100000, got 0" in _err(capsys, ["--num-pairs", "0", "--out", str(tmp_path / "o")])
    assert not (tmp_path / "o").exists()


def test_odometry_sigma_lets_the_images_move_the_odometry(tmp_path, capsys):
    """given_images holds the odometry's planar motion; with --odometry-sigma the images move it,
    the report says so, and a rerun with other widths is another run."""
    base = ["--num-pairs", "1", "--source", "dis", "--odometry", "given_images", "--no-figures", *TINY]

    def used(out):
        rec = json.loads((out / "dis" / "given_images" / "pairs" / "000000.json").read_text())
        return rec["odometry"], rec["odometry_given"]

    assert main([*base, "--out", str(tmp_path / "held")]) == 0
    motion, given = used(tmp_path / "held")
    assert all(motion[k] == pytest.approx(given[k], abs=1e-6) for k in ("x_d", "z_d", "yaw"))
    sigma = ["--odometry-sigma", "0.05", "0.05", "0.2"]
    assert main([*base, *sigma, "--out", str(tmp_path / "moved")]) == 0
    motion, given = used(tmp_path / "moved")
    assert abs(motion["z_d"] - given["z_d"]) > 1e-3
    # the report's z_d error covers it, as the other variants that estimate the motion (it left it out)
    assert _rows(tmp_path / "moved" / "report.json")[("dis", "given_images")]["z_d_abs_error_m"] == pytest.approx(
        abs(motion["z_d"] - given["z_d"]), rel=1e-12)
    assert "z_d_abs_error_m" not in _rows(tmp_path / "held" / "report.json")[("dis", "given_images")]
    assert "within 0.05 m sideways, 0.05 m forward and 0.2° of yaw" in (tmp_path / "moved" / "report.md").read_text()
    err = _err(capsys, [*base, "--odometry-sigma", "0.05", "0.05", "0.5", "--out", str(tmp_path / "moved")])
    assert "another run" in err and "odometry_sigma" in err
    assert "--odometry-sigma: applies to the variant given_images, which this run does not use (--odometry " \
           "photometric)" in _err(capsys, [*TINY, *sigma, "--odometry", "photometric", "--out", str(tmp_path / "o")])
    assert "--odometry-sigma: expected three finite widths > 0 (X_M Z_M YAW_DEG), got 0.05 -1 0.2" in _err(
        capsys, [*base, "--odometry-sigma", "0.05", "-1", "0.2", "--out", str(tmp_path / "o")])
    assert not (tmp_path / "o").exists()



def test_fit_options_reach_the_image_estimates_and_make_another_run(tmp_path, capsys, monkeypatch, user_folder,
                                                                    scene_pairs):
    """--fit-options JSON: fit_image's options for the variants that estimate from the images (the
    refiner's estimator) and for the clip's fit (fit_sequence); the report says so, a rerun with
    other options is another run, and bad options exit 2 before any work."""
    import refine.calibrate as calibrate
    import refine.job as job

    seen = {"estimator": [], "sequence": []}
    estimator, fit_sequence = job.ImageMotionEstimator, calibrate.fit_sequence

    def recording_estimator(**options):
        seen["estimator"].append(options)
        return estimator(**options)

    def recording_sequence(*args, **options):
        seen["sequence"].append(options)
        return fit_sequence(*args, **options)

    monkeypatch.setattr(job, "ImageMotionEstimator", recording_estimator)
    monkeypatch.setattr(calibrate, "fit_sequence", recording_sequence)
    options = ["--fit-options", '{"max_points": 800, "smooth_sigma": 0.5}']
    base = ["--num-pairs", "1", "--source", "dis", "--odometry", "photometric", "--no-figures", *TINY]
    assert main([*base, *options, "--out", str(tmp_path / "a")]) == 0
    assert seen["estimator"] == [{"odometry_sigma": None, "max_points": 800, "smooth_sigma": 0.5}]
    assert "fit_image's options {\"max_points\": 800, \"smooth_sigma\": 0.5} (--fit-options)" in \
        (tmp_path / "a" / "report.md").read_text()
    err = _err(capsys, [*base, "--fit-options", '{"max_points": 900}', "--out", str(tmp_path / "a")])
    assert "another run" in err and "fit_options" in err
    # the clip's fit takes them too
    clip = _user(user_folder, tmp_path / "clip", "--road", str(user_folder / "road"), "--source", "dis",
                 *_mounting(scene_pairs), *options)
    assert main(clip) == 0
    assert seen["sequence"] and all(o["max_points"] == 800 and o["smooth_sigma"] == 0.5 for o in seen["sequence"])
    # checked before any work, naming the option
    for bad, says in (('{"max_points": 800', "expected a JSON object"), ("[1, 2]", "expected a JSON object"),
                      ('{"bogus": 1}', "unknown options ['bogus']"), ('{"camera": 1}', "camera"),
                      ('{"smooth_sigma": -1}', "smooth_sigma: expected a number >= 0")):
        err = _err(capsys, [*base, "--fit-options", bad, "--out", str(tmp_path / "o")])
        assert err.startswith("error: --fit-options") and says in err, (bad, err)
    err = _err(capsys, [*TINY, "--num-pairs", "1", "--odometry", "fit", *options, "--out", str(tmp_path / "o")])
    assert "--fit-options: applies to the road motion from the images" in err
    assert not (tmp_path / "o").exists()


def test_road_options_reach_the_detection_and_make_another_run(tmp_path, capsys, monkeypatch, scene_pairs):
    """--road-options JSON: detect_road's options for --road auto, which change the road found (a
    seed 40 m deep finds 2032 pixels of the 48 x 160 scene where the default 20 m finds none); the
    report says so, a rerun with the same options resumes, one with others (or none) is another run."""
    import fsof_torch
    from refine.sources import dis_flow

    seen, detect = [], fsof_torch.detect_road
    monkeypatch.setattr(fsof_torch, "detect_road", lambda *a, **k: seen.append(k) or detect(*a, **k))
    out = tmp_path / "a"
    base = [*TINY, "--num-pairs", "1", "--source", "dis", "--odometry", "fit", "--road", "auto", "--no-figures"]
    options = ["--road-options", '{"seed_depth_m": 40}']
    assert main([*base, *options, "--out", str(out)]) == 0
    assert len(seen) == 1 and seen[0]["seed_depth_m"] == 40
    rec = json.loads((out / "dis" / "fit" / "pairs" / "000000.json").read_text())
    p = scene_pairs[0]  # (the job's pair 000000)
    args = (p["image1"][None], p["image2"][None], p["camera"].to(torch.float64))
    flow = dis_flow(p["image1"], p["image2"])[None]
    deeper, default = detect(*args, flow=flow, seed_depth_m=40), detect(*args, flow=flow)
    assert rec["road_auto_pixels"] == int(deeper.mask.sum()) != int(default.mask.sum())
    assert rec["road_flag"] == deeper.flag[0] != default.flag[0]
    summary = json.loads((out / "report.json").read_text())
    assert summary["identity"]["road_options"] == {"seed_depth_m": 40}
    assert "- The road found in the images with detect_road's options {\"seed_depth_m\": 40} (--road-options)." \
        in (out / "report.md").read_text().splitlines()
    capsys.readouterr()
    assert main([*base, *options, "--out", str(out)]) == 0 and len(seen) == 1  # (resumed: nothing detected)
    assert json.loads((out / "report.json").read_text())["records_resumed"] == 1
    for other in (["--road-options", '{"seed_depth_m": 30}'], []):
        err = _err(capsys, [*base, *other, "--out", str(out)])
        assert "another run" in err and "road_options" in err, err


def test_road_options_are_refused_before_any_work(tmp_path, capsys, user_folder):
    """--road-options: malformed JSON, not an object, a name detect_road does not take (the names
    it takes listed) or one the job sets, a bad value (detect_road's message), a run without --road
    auto: exit 2 naming the option and quoting what came, before the output folder is made; what the
    images' size or the camera's height allow, at the first pair's detection."""
    o = tmp_path / "o"
    base = [*TINY, "--num-pairs", "1", "--source", "dis", "--odometry", "fit", "--road", "auto", "--no-figures",
            "--out", str(o)]
    names = ("['edges', 'follow_path', 'height_window', 'level', 'max_height_m', 'min_coverage', 'min_height_m', 'min_misfit_px', "
             "'refit', 'seed_depth_m', 'seed_level', 'seed_width_m', 'slow_max_height_m', 'window', 'z']")
    for bad, says in (('{"seed_depth_m": 40', "expected a JSON object of detect_road keyword arguments, got "
                                              "'{\"seed_depth_m\": 40' (Expecting ',' delimiter"),
                      ("[40]", "expected a JSON object of detect_road keyword arguments, got '[40]'"),
                      ('{"seed_dept_m": 40}', f"unknown options ['seed_dept_m'] of detect_road; expected some of {names}"),
                      ('{"camera": 1}', "options ['camera'] of detect_road are set by"),
                      ('{"seed_depth_m": -1}', "seed_depth_m: expected a finite number > 0, got -1"),
                      ('{"window": 4}', "window: expected an odd int >= 3 (pixels at the working resolution), got 4"),
                      ('{"refit": 1}', "refit: expected True or False, got int 1")):
        err = _err(capsys, [*base, "--road-options", bad])
        assert err.startswith(f"error: --road-options: {says}"), (bad, err)
    assert not o.exists()
    # no road found in the images to pass them to: refused, as every option the run would ignore
    given = [a for a in base if a not in ("--road", "auto")]
    for argv, masks in ((given, "the synthetic scene's own road mask"),
                        (_user(user_folder, o, "--road", str(user_folder / "road")), f"--road {user_folder / 'road'}"),
                        (["--kitti15", str(tmp_path / "k15"), "--out", str(o)], "the folder's road.json")):
        assert _err(capsys, [*argv, "--road-options", '{"z": 3}']).startswith(
            "error: --road-options: applies to the road found in the images (--road auto), which this run does "
            f"not use (its road masks: {masks})\n")
    assert not o.exists()
    # a kerb above the camera (1.65 m here) needs the camera: named as the option that gave it
    high = '{"min_height_m": 2, "max_height_m": 3, "slow_max_height_m": null}'
    assert _err(capsys, [*base, "--road-options", high]) == ("error: --road-options: min_height_m: expected below "
                                                             "the camera's height [1.65] m, got 2.0\n")
    assert not list(o.rglob("pairs/*.json"))  # (no pair finished)


def test_a_flagged_auto_road_advises_the_road_options_that_act_on_it(scene_pairs):
    """The detection's reason for an empty seed advises a deeper seed_depth_m, a keyword argument
    of detect_road: the job's report gives the --road-options that does it (twice the depth used,
    at least 40 m, the run's other road options kept), while the record keeps the library's reason."""
    from fsof_torch import detect_road
    from refine.report import auto_road_lines, job_advice

    p = scene_pairs[0]
    motion = {"model": "paper", **{k: torch.tensor([v]) for k, v in p["odometry"].items()}}  # (the scene's)
    det = detect_road(p["image1"][None], p["image2"][None], p["camera"], motion=motion, seed_depth_m=1.0)
    reason = det.reason[0]
    assert det.flag[0] == "empty" and reason.endswith("or a deeper seed_depth_m") and "--road" not in reason
    advice = reason.removesuffix("seed_depth_m")
    assert job_advice(reason, None) == advice + "seed: --road-options '{\"seed_depth_m\": 40}'"
    assert job_advice(reason, {"seed_depth_m": 1, "z": 3}) == advice + \
        "seed: --road-options '{\"seed_depth_m\": 40, \"z\": 3}'"
    assert job_advice(reason, {"seed_depth_m": 30.5}) == advice + "seed: --road-options '{\"seed_depth_m\": 61}'"
    assert job_advice("only 2.4 % of the road ahead carries evidence", {"z": 3}) == \
        "only 2.4 % of the road ahead carries evidence"
    rec = {"pair": "000000", "road_flag": "empty", "road_reason": reason, "road_coverage": 0.0}
    lines = auto_road_lines({"pairs": [rec], "identity": {"road_options": {"seed_depth_m": 1}}})
    assert lines[1] == f"  - flagged, left unrefined: 000000: empty ({advice}seed: --road-options " \
                       "'{\"seed_depth_m\": 40}')"


def test_flow_beyond_the_png_range_is_marked_not_lost(tmp_path, user_folder, scene_pairs):
    """A predicted flow of 600 px on a band outside the road (a KITTI flow PNG holds ±512 px):
    the job finishes, its metrics take the flow as it is, and the written PNG marks those pixels
    invalid, which the record counts."""
    from fsof_torch.io import read_kitti_flow, write_flow

    flows = tmp_path / "far"
    flows.mkdir()
    for i, p in enumerate(scene_pairs):
        far = p["flow"].clone()
        far[0, :10] = 600.0  # the top rows: sky, never road
        write_flow(flows / f"{i:06d}.flo", far)
    out = tmp_path / "out"
    rc = main(_user(user_folder, out, "--flows", str(flows), "--road", str(user_folder / "road"),
                    "--odometry", "photometric", *_mounting(scene_pairs)))
    assert rc == 0
    rec = json.loads((out / "files" / "photometric" / "pairs" / "000000.json").read_text())
    W = scene_pairs[0]["flow"].shape[-1]
    assert rec["flow_png_dropped"] == 10 * W
    written, valid = read_kitti_flow(out / "files" / "photometric" / "flow" / "000000.png")
    assert not valid[..., :10, :].any() and valid[..., 10:, :].all()


def test_kitti_odometry_clip_without_road_json_takes_road_auto(tmp_path, user_folder, capsys):
    """Another clip in the KITTI odometry sample's layout, without a road polygon: refused with a
    message naming road.json and --road auto, and run with --road auto (the road found in the
    images, recorded per pair; the report's title and notes name the clip and the road's origin)."""
    import shutil

    clip = tmp_path / "other_street"
    shutil.copytree(user_folder / "images", clip / "image_l")
    for name in ("calib.txt", "poses.txt"):
        shutil.copy(user_folder / name, clip / name)
    out = tmp_path / "out"
    argv = ["--kitti-odometry", str(clip), "--out", str(out), "--no-progress", "--no-figures"]
    assert "lacks road.json (or pass --road auto)" in _err(capsys, argv)
    assert main([*argv, "--road", "auto"]) == 0
    # the default variants: the paper's model on the poses, the poses with the images, the clip's
    # fit, the images alone
    assert set(_rows(out / "report.json")) == {("dis", v) for v in ("given", "given_images", "sequence", "photometric")}
    for pair in ("000000", "000001"):
        rec = json.loads((out / "dis" / "photometric" / "pairs" / f"{pair}.json").read_text())
        assert rec["road"] == "auto" and (rec["road_flag"] == "ok") == (rec["road_reason"] == "")
    report = (out / "report.md").read_text()
    assert "refine: KITTI odometry clip other_street" in report
    assert "Road mask: found in the images of each pair (--road auto)" in report


def test_a_road_json_edited_during_a_run_does_not_mark_old_results_as_its_own(tmp_path, user_folder, monkeypatch):
    """A clip's one road.json (and its calibration) is read when the run starts; saved anew while
    the run goes on, the pairs refined after that with the polygon read at the start carried the
    new file's digest, so that the rerun reused them as results of the new polygon (its report
    mixed both). Now each pair's record holds the digest of what was read: the rerun redoes every
    pair, and its records equal a fresh run's."""
    import shutil

    import fsof_torch.io

    clip = tmp_path / "clip"
    shutil.copytree(user_folder / "images", clip / "image_l")
    for name in ("calib.txt", "poses.txt"):
        shutil.copy(user_folder / name, clip / name)
    H, W = SIZE

    def polygon(width: int) -> str:
        return json.dumps({"size": [H, W], "road_polygon": [[W // 2 - width, H], [W // 2, H // 2],
                                                            [W // 2 + width, H]]})

    (clip / "road.json").write_text(polygon(70))
    write_json = fsof_torch.io.write_json

    def save_then_edit(path, obj, *args, **kw):  # the user saves another polygon after the first record
        out = write_json(path, obj, *args, **kw)
        if path.parent.name == "pairs":
            (clip / "road.json").write_text(polygon(20))
        return out

    monkeypatch.setattr(fsof_torch.io, "write_json", save_then_edit)
    argv = ["--kitti-odometry", str(clip), "--odometry", "given", "--no-progress", "--no-figures"]
    assert main([*argv, "--out", str(tmp_path / "out")]) == 0
    monkeypatch.setattr(fsof_torch.io, "write_json", write_json)
    assert main([*argv, "--out", str(tmp_path / "out")]) == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["records_resumed"] == 0 and report["records_computed"] == 2
    assert main([*argv, "--out", str(tmp_path / "fresh")]) == 0
    for pair in ("000000", "000001"):
        rerun, fresh = (json.loads((tmp_path / o / "dis" / "given" / "pairs" / f"{pair}.json").read_text())
                        for o in ("out", "fresh"))
        assert rerun["road_pixels"] == fresh["road_pixels"] > 0
        assert rerun["input_fingerprint"] == fresh["input_fingerprint"]


def test_options_the_input_does_not_use_are_refused(tmp_path, user_folder, capsys):
    """An option the chosen input would ignore exits 2 naming it, before any work."""
    out = ["--out", str(tmp_path / "o"), "--no-progress"]
    user = _user(user_folder, tmp_path / "o", "--road", "auto")
    for extra, option in ((["--preset", "crest"], "--preset"), (["--num-pairs", "2"], "--num-pairs"),
                          (["--seed", "3"], "--seed"), (["--scene-noise", "1"], "--scene-noise"),
                          (TINY[:2], "--size")):
        assert f"{option}: applies to the synthetic scenes, not to --images" in _err(capsys, [*user, *extra])
    # the message says every input the option applies to: the KITTI samples take --height, the
    # odometry clip --pitch-deg (it said "applies to --images" alone)
    for extra, where in ((["--cam", "2"], "--images"), (["--roll-deg", "1"], "--images"),
                         (["--height", "1.5"], "--images, --kitti15 and --kitti-odometry"),
                         (["--pitch-deg", "1"], "--images and --kitti-odometry")):
        assert f"{extra[0]}: applies to {where} (the synthetic scenes have their own camera)" in _err(
            capsys, [*out, *TINY, *extra])
    kitti15, odometry = ["--kitti15", str(tmp_path / "k15"), *out], ["--kitti-odometry", str(tmp_path / "odo"), *out]
    for argv, option in (([*kitti15, "--calib", str(user_folder / "calib.txt")], "--calib"),
                         ([*kitti15, "--pitch-deg", "1"], "--pitch-deg"),
                         ([*odometry, "--roll-deg", "1"], "--roll-deg"),
                         ([*odometry, "--poses", str(user_folder / "poses.txt")], "--poses"),
                         ([*odometry, "--gt", str(user_folder / "gt")], "--gt")):
        where = "--images and --kitti-odometry" if option == "--pitch-deg" else "--images"
        assert f"{option}: applies to {where} (--" in _err(capsys, argv) or option in ("--poses", "--gt")
    # the reason fits the option: a sample's poses and ground truth are its own, or it has none
    for argv, reason in ((odometry, "--poses: applies to --images (--kitti-odometry has its own poses.txt)"),
                         (kitti15, "--poses: applies to --images (the KITTI 2015 pair has no poses)")):
        assert reason in _err(capsys, [*argv, "--poses", str(user_folder / "poses.txt")])
    for argv, reason in ((kitti15, "--gt: applies to --images (the KITTI 2015 pair has its own flow_noc_10.png)"),
                         (odometry, "--gt: applies to --images (the KITTI odometry clip has no ground-truth flow)")):
        assert reason in _err(capsys, [*argv, "--gt", str(user_folder / "gt")])
    assert "--road: --kitti15 uses its own road.json" in _err(capsys, [*kitti15, "--road", str(user_folder / "road")])
    assert "--odometry given: the KITTI 2015 pair has no poses" in _err(capsys, [*kitti15, "--odometry", "fit,given"])
    # a bad mounting value is named by its own option, not by the sample's
    assert "--height: expected > 0 m" in _err(capsys, [*kitti15, "--height", "-1"])
    # --road auto tests for kerbs of detect_road's min_height_m (0.1 m), below the camera: a camera as low
    # was named by that option, which the job does not have, after the first pair's flow had run
    for argv in ([*kitti15, "--road", "auto"], [*odometry, "--road", "auto"], user):
        assert _err(capsys, [*argv, "--height", "0.1"]).startswith(
            "error: --height: --road auto tests for kerbs 0.1 m high, below the camera: expected a camera higher "
            "than 0.1 m above the road, got 0.1\n")
    assert "--pitch-deg: expected a finite number" in _err(capsys, [*odometry, "--pitch-deg", "nan"])
    # an angle the camera cannot take is named by its option, in degrees (it was 'pitch: ... rad, got [1.658]')
    for argv, option, value in (([*odometry, "--pitch-deg", "90"], "--pitch-deg", "90"),
                                ([*user, "--pitch-deg", "95"], "--pitch-deg", "95"),
                                ([*user, "--roll-deg", "-120"], "--roll-deg", "-120")):
        assert _err(capsys, argv).startswith(f"error: {option}: expected an angle between -90 and 90 degrees (a "
                                             f"camera upright and facing the road), got {value}\n")
    assert "--testnet-weights: the run has no testnet source" in _err(
        capsys, [*user, "--testnet-weights", str(tmp_path / "w.pt")])
    assert "--fit-roll: applies to the variant fit" in _err(capsys, [*user, "--fit-roll"])
    assert "--net and --flows: give one of them" in _err(
        capsys, [*user, "--net", "mypkg:make", "--flows", str(user_folder / "flows")])
    assert not (tmp_path / "o").exists()


def test_net_options_without_the_net_source_are_refused(tmp_path, user_folder, capsys):
    """--net, --checkpoint and --net-contract with sources that leave out net would be ignored:
    refused before any work, naming them."""
    out = tmp_path / "o"
    user = _user(user_folder, out, "--road", "auto", "--source", "dis")
    assert _err(capsys, [*user, "--net", "mypkg:make"]).startswith(
        "error: --net: the run has no net source (sources: dis); add net to --source")
    assert _err(capsys, [*user, "--net", "mypkg:make", "--checkpoint", str(tmp_path / "w.pt"), "--net-contract",
                         "raft"]).startswith("error: --net and --checkpoint and --net-contract: the run has no net "
                                             "source (sources: dis)")
    assert _err(capsys, ["--source", "dis,testnet", "--net", "mypkg:make", "--out", str(out), *TINY]).startswith(
        "error: --net: the run has no net source (sources: dis,testnet)")
    assert not out.exists()


def test_scale_applies_to_confidence_only(tmp_path, capsys):
    """--scale with --mode replace (which has no scale) is refused; a confidence run without it
    uses 2 px and has the fingerprint of one given --scale 2."""
    out = tmp_path / "out"
    base = ["--num-pairs", "1", "--source", "dis", "--odometry", "given", "--no-figures", "--out", str(out), *TINY]
    assert _err(capsys, [*base, "--scale", "7"]).startswith(
        "error: --scale: applies to --mode confidence, not to --mode replace")
    assert _err(capsys, [*base, "--mode", "confidence", "--scale", "0"]).startswith(
        "error: --scale: expected a finite value > 0 px, got 0.0")
    assert not out.exists()
    assert main([*base, "--mode", "confidence"]) == 0
    first = json.loads((out / "report.json").read_text())
    assert first["scale_px"] == 2.0 and first["identity"]["scale"] == 2.0
    assert main([*base, "--mode", "confidence", "--scale", "2"]) == 0
    again = json.loads((out / "report.json").read_text())
    assert again["fingerprint"] == first["fingerprint"] and again["records_resumed"] == 1
    assert "another run (scale: 2.0 -> 3.0)" in _err(capsys, [*base, "--mode", "confidence", "--scale", "3"])


@pytest.mark.parametrize("device, message", [
    ("meta", "--device: 'meta' holds no data (shapes only); give cpu or cuda"),
    ("mps", "--device: cannot place a tensor on 'mps' ("),
])
def test_a_device_that_cannot_hold_the_job_is_refused_before_any_work(tmp_path, capsys, device, message):
    out = tmp_path / "out"
    err = _err(capsys, ["--num-pairs", "1", "--source", "dis", "--no-figures", "--device", device,
                        "--out", str(out), *TINY])
    assert err.startswith(f"error: {message}"), err
    assert not out.exists()


def test_a_corrupt_flow_file_is_named_under_flows(tmp_path, user_folder, scene_pairs, capsys):
    (user_folder / "flows" / "000001.npy").unlink()
    (user_folder / "flows" / "000001.png").write_bytes(b"garbage\n")
    err = _err(capsys, _user(user_folder, tmp_path / "out", "--flows", str(user_folder / "flows"), "--road",
                             str(user_folder / "road"), "--odometry", "given", "--poses",
                             str(user_folder / "poses.txt"), *_mounting(scene_pairs)))
    assert err.startswith(f"error: --flows: {str(user_folder / 'flows' / '000001.png')!r} is not a PNG file"), err


@pytest.mark.parametrize("manifest", ["[]", "5", '{"fingerprint": "x", "outputs": 5}',
                                      '{"fingerprint": "x", "outputs": ["dis", 5]}'])
def test_a_manifest_that_is_json_but_not_a_manifest(tmp_path, manifest):
    """run.json holding JSON that is not a manifest (a list, a number, outputs not a list of names)
    reads as an unreadable one: a folder without results is taken, one with results refused, with
    --overwrite too (it names no outputs to delete), never a traceback."""
    from refine import resume
    from refine.inputs import JobError

    out = tmp_path / "out"
    out.mkdir()
    identity = {"mode": "replace", "outputs": ["dis"]}
    (out / "run.json").write_text(manifest)
    assert resume.prepare(out, identity, overwrite=False)["identity"] == identity
    (out / "run.json").write_text(manifest)
    (out / "report.md").write_text("")
    for overwrite in (False, True):
        with pytest.raises(JobError, match=r"^--out: .* holds the results of another run whose manifest .* cannot "
                                           r"be read"):
            resume.prepare(out, identity, overwrite=overwrite)
    assert (out / "report.md").exists() and (out / "run.json").read_text() == manifest


def test_overwrite_over_an_unreadable_manifest_is_refused_and_deletes_nothing(tmp_path, capsys):
    """--overwrite deletes the outputs the earlier run's manifest names: where run.json cannot be
    read it names none, so the earlier run's folders would stay beside the new ones (and its
    report): refused with exit 2 naming the manifest, every file left as it was."""
    out = tmp_path / "out"
    base = ["--num-pairs", "1", "--no-figures", "--out", str(out), *TINY]
    assert main([*base, "--source", "dis", "--odometry", "given,fit"]) == 0
    (out / "run.json").write_text("not json")
    before = sorted(p.relative_to(out) for p in out.rglob("*"))
    err = _err(capsys, [*base, "--source", "dis", "--odometry", "given", "--overwrite"])
    assert err.startswith(f"error: --out: {str(out)!r} holds the results of another run whose manifest "
                          f"{str(out / 'run.json')!r} cannot be read"), err
    assert "--overwrite deletes none of them; delete them (or the folder) yourself, or give another --out" in err
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == before
    assert (out / "dis" / "fit" / "pairs" / "000000.json").is_file()


def test_a_record_that_is_json_but_not_a_record_is_redone(tmp_path):
    out = tmp_path / "out"
    args = ["--num-pairs", "1", "--source", "dis", "--odometry", "given", "--no-figures", "--out", str(out), *TINY]
    assert main(args) == 0
    record = out / "dis" / "given" / "pairs" / "000000.json"
    done = json.loads(record.read_text())
    for text in ("[]", "5", '"x"'):
        record.write_text(text)
        assert main(args) == 0
        summary = json.loads((out / "report.json").read_text())
        assert summary["records_resumed"] == 0 and summary["records_computed"] == 1
        assert json.loads(record.read_text())["after"] == done["after"]


def test_an_input_error_on_another_process_stops_this_one_with_its_message(tmp_path, capsys, monkeypatch):
    """Under torchrun the processes exchange their pairs' input errors before the collectives:
    rank 0, whose pairs were fine, stops with the other rank's message (exit 2) instead of waiting
    in the all-reduce; another rank whose pairs were fine stops quietly (exit 2); the rank that
    failed reports its own. (The world is simulated: its collectives return what the other rank
    would give: ``elsewhere``.)"""
    from refine import distributed, inputs

    other = "--flows: 'flows/000001.png' is not a PNG file"
    calls, elsewhere = [], {}

    def gather(obj, world):
        calls.append(obj)
        return [obj, elsewhere["error"]] if world.rank == 0 else [elsewhere["error"], obj]

    monkeypatch.setattr(distributed, "gather_objects", gather)
    monkeypatch.setattr(distributed, "broadcast_object", lambda obj, world: obj)
    monkeypatch.setattr(distributed, "all_reduce_sum", lambda values, world: values.clone())
    base = ["--num-pairs", "2", "--source", "dis", "--odometry", "given", "--no-figures", *TINY]
    elsewhere["error"] = other
    for rank in (0, 1):
        monkeypatch.setattr(distributed, "init", lambda device, rank=rank: distributed.World(rank, 2, rank, "gloo"))
        out = tmp_path / f"r{rank}"
        assert main([*base, "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert err == (f"error: {other} (on rank 1)\n" if rank == 0 else ""), err
        assert calls == [None]  # its own pairs went well; nothing else was gathered
        assert (out / "dis" / "given" / "pairs" / f"{rank:06d}.json").is_file()
        assert not (out / "report.json").exists()
        calls.clear()

    # rank 1 of 2, whose pair (000001) fails to load: it reports its own error
    synthetic_pairs = inputs.synthetic_pairs
    message = "--size: pair 000001 cannot be rendered (simulated)"

    def broken():
        raise inputs.JobError(message)

    def pairs(*args, **kwargs):
        specs = synthetic_pairs(*args, **kwargs)
        specs[1].load = broken
        return specs

    monkeypatch.setattr(inputs, "synthetic_pairs", pairs)
    elsewhere["error"] = None
    assert _err(capsys, [*base, "--out", str(tmp_path / "r1b")]) == f"error: {message}\n"
    assert calls == [message]


@pytest.mark.parametrize("error", [PermissionError, IsADirectoryError])
def test_a_file_a_process_may_not_read_is_exchanged_under_torchrun(tmp_path, capsys, monkeypatch, error):
    """Under torchrun a pair's file that its process may not read (a PermissionError), or finds a
    folder, was not among the errors the processes exchange: that process ended in a traceback
    and the others waited in their collectives for good. Now it is exchanged as the others are:
    the process that met it reports it (exit 2), named as without torchrun, and so does rank 0."""
    import errno

    from refine import distributed, inputs

    calls = []

    def gather(obj, world):  # (this process is rank 1 of 2; rank 0's pairs went well)
        calls.append(obj)
        return [None, obj]

    monkeypatch.setattr(distributed, "gather_objects", gather)
    monkeypatch.setattr(distributed, "broadcast_object", lambda obj, world: obj)
    monkeypatch.setattr(distributed, "init", lambda device: distributed.World(1, 2, 1, "gloo"))
    synthetic_pairs = inputs.synthetic_pairs
    denied = str(tmp_path / "frames" / "000001.png")

    def broken():
        raise error(errno.EACCES if error is PermissionError else errno.EISDIR, "simulated", denied)

    def pairs(*args, **kwargs):
        specs = synthetic_pairs(*args, **kwargs)
        specs[1].load = broken
        return specs

    monkeypatch.setattr(inputs, "synthetic_pairs", pairs)
    argv = ["--num-pairs", "2", "--source", "dis", "--odometry", "given", "--no-figures", "--out",
            str(tmp_path / "out"), *TINY]
    message = f"{denied!r}: permission denied" if error is PermissionError else f"[Errno 21] simulated: {denied!r}"
    assert _err(capsys, argv) == f"error: {message}\n"
    assert calls == [message]


def test_json_naming_an_input_is_refused_and_the_input_kept(tmp_path, user_folder, capsys):
    """--json naming a file the run reads (or a file inside a folder it reads) is refused before
    any work, naming --json and the option: the job removes the --json file at its start, which
    deleted the calibration or the road polygon."""
    polygon = user_folder / "road.json"
    polygon.write_text('{"size": [48, 160], "road_polygon": [[0, 47], [159, 47], [110, 28], [50, 28]]}')
    weights = tmp_path / "w.pt"
    weights.write_bytes(b"x")
    out = tmp_path / "out"
    for option, path, extra in (("--calib", user_folder / "calib.txt", ["--road", str(polygon)]),
                                ("--road", polygon, ["--road", str(polygon)]),
                                ("--poses", user_folder / "poses.txt", ["--road", "auto", "--poses",
                                                                        str(user_folder / "poses.txt")]),
                                ("--testnet-weights", weights, ["--road", "auto", "--source", "testnet",
                                                                "--testnet-weights", str(weights)])):
        before = path.read_bytes()
        err = _err(capsys, [*_user(user_folder, out, *extra), "--json", str(path)])
        assert err.startswith(f"error: --json: {str(path)!r} is the input {option}; give another path"), err
        assert path.read_bytes() == before
    inside = user_folder / "gt" / "000000.json"
    err = _err(capsys, [*_user(user_folder, out, "--road", "auto", "--gt", str(user_folder / "gt")),
                        "--json", str(inside)])
    assert err.startswith(f"error: --json: {str(inside)!r} is inside the input --gt {str(user_folder / 'gt')!r}")
    assert not out.exists() and not inside.exists()


def test_an_input_inside_the_outputs_of_out_is_refused_and_kept(tmp_path, user_folder, capsys):
    """Flows an earlier run refined, given again as --flows with that run's --out and --overwrite,
    were deleted with the earlier run's outputs before they were read (the job then stopped on a
    bare 'No such file or directory'). An input inside a folder the run writes, or an earlier
    run's that --overwrite deletes, is refused before any work, naming --out and the input."""
    out = tmp_path / "out"
    base = _user(user_folder, out, "--road", "auto", "--odometry", "photometric", "--threads", "1")
    assert main(base) == 0
    refined = out / "dis" / "photometric" / "flow"
    before = {p.name: p.read_bytes() for p in refined.iterdir()}
    err = _err(capsys, [*base, "--flows", str(refined), "--overwrite"])
    assert err.startswith(f"error: --out: {str(out)!r} holds the input --flows {str(refined)!r} inside "
                          f"{str(out / 'dis')!r}, an earlier run's output, which --overwrite deletes"), err
    assert {p.name: p.read_bytes() for p in refined.iterdir()} == before
    assert json.loads((out / "run.json").read_text())["outputs"] == ["dis"]  # the earlier run's, untouched
    # an input inside the folder of a source the run writes, without an earlier run there
    (tmp_path / "out2" / "dis").mkdir(parents=True)
    images = tmp_path / "out2" / "dis" / "images"
    (user_folder / "images").rename(images)
    err = _err(capsys, ["--images", str(images), "--calib", str(user_folder / "calib.txt"), "--road", "auto",
                        "--out", str(tmp_path / "out2"), "--no-progress", "--no-figures"])
    assert err.startswith(f"error: --out: {str(tmp_path / 'out2')!r} holds the input --images {str(images)!r} "
                          f"inside {str(tmp_path / 'out2' / 'dis')!r}, which the run writes"), err
    assert not (tmp_path / "out2" / "run.json").exists()
    # a folder above the inputs stays an --out (the inputs' top-level files are not the job's)
    assert main(["--images", str(images), "--calib", str(user_folder / "calib.txt"), "--road", "auto",
                 "--odometry", "photometric", "--out", str(images), "--overwrite", "--no-progress",
                 "--no-figures"]) == 0


@pytest.mark.parametrize("name", ["report.md", "run.json", "dis/given/pairs/000000.json", "."])
def test_json_inside_out_is_refused_but_its_report_json(tmp_path, capsys, name):
    """--json inside --out would replace (or be replaced by) the job's own files: the Markdown
    report, the manifest a later --overwrite reads, a record. Refused before any work; the one
    exception is OUT/report.json, the report itself."""
    from refine import resume
    from refine.inputs import JobError

    out = tmp_path / "out"
    target = out / name
    err = _err(capsys, ["--num-pairs", "1", "--source", "dis", "--odometry", "given", "--no-figures",
                        "--out", str(out), "--json", str(target), *TINY])
    assert err.startswith(f"error: --json: {str(target)!r} is inside --out {str(out)!r}, which the job fills"), err
    assert not out.exists()
    resume.check_json_path(out / "report.json", out)
    resume.check_json_path(out / "sub" / ".." / "report.json", out)
    with pytest.raises(JobError, match="is inside --out"):
        resume.check_json_path(out / "sub" / ".." / "report.md", out)


@pytest.mark.parametrize("name", ["report.json", "run.json", "dis/given/pairs/000000.json", "dis/new.json"])
def test_json_inside_another_runs_out_is_refused(tmp_path, capsys, name):
    """--json inside the output folder of another refine run replaced that run's report.json (its
    report.md then described one run, its report.json another), its manifest (the folder could no
    longer be resumed nor overwritten) or a record. Refused before any work, that run's files kept."""
    base = ["--num-pairs", "1", "--source", "dis", "--odometry", "given", "--no-figures", *TINY]
    first = tmp_path / "first"
    assert main([*base, "--out", str(first)]) == 0
    before = {p: p.read_bytes() for p in first.rglob("*") if p.is_file()}
    target = first / name
    err = _err(capsys, [*base, "--odometry", "fit", "--out", str(tmp_path / "second"), "--json", str(target)])
    assert err.startswith(f"error: --json: {str(target)!r} is inside {str(first.resolve())!r}, the output folder of another "
                          f"refine run"), err
    assert {p: p.read_bytes() for p in first.rglob("*") if p.is_file()} == before
    assert not (tmp_path / "second").exists()
    # a path beside it, or this run's own report.json, is taken
    assert main([*base, "--out", str(first), "--json", str(first / "report.json")]) == 0
    assert main([*base, "--out", str(tmp_path / "second"), "--json", str(tmp_path / "second.json")]) == 0


@pytest.mark.parametrize("argv, option", [
    (["--kitti-odometry", "{odo}", "--num-pairs", "4"], "--num-pairs"),  # (4: the synthetic default)
    (["--kitti-odometry", "{odo}", "--size", "375x1242"], "--size"),
    (["--kitti-odometry", "{odo}", "--seed", "0"], "--seed"),
    (["--kitti15", "{odo}", "--preset", "default"], "--preset"),
    (["--num-pairs", "1", "--height", "1.65"], "--height"),
    (["--num-pairs", "1", "--pitch-deg", "0"], "--pitch-deg"),
    (["--num-pairs", "1", "--roll-deg", "0"], "--roll-deg"),
    (["--kitti15", "{odo}", "--pitch-deg", "0"], "--pitch-deg"),
    (["--num-pairs", "1", "--net-contract", "auto"], "--net-contract"),
])
def test_options_the_input_does_not_use_are_refused_at_their_default_too(tmp_path, capsys, argv, option):
    """An option given for another input is refused when given, whatever its value: at its default
    it was accepted and ignored (--num-pairs 4 with a 50-pair clip ran all 50 pairs)."""
    argv = [a.format(odo=tmp_path / "odo") for a in argv]
    err = _err(capsys, [*argv, "--out", str(tmp_path / "o"), "--no-progress"])
    assert err.startswith(f"error: {option}"), err
    assert "applies to" in err or "needs --net" in err
    assert not (tmp_path / "o").exists()


def test_progress_bars_in_a_log_are_rate_limited(monkeypatch):
    """On a terminal the bar is redrawn at every step; in a log (stderr not a terminal) only when
    it opens and closes within fsof_torch.io.progress.LOG_INTERVAL, the steps shown at those redraws."""
    import io
    import sys

    from fsof_torch.io.progress import progress_bar, show_text

    class Stream(io.StringIO):
        def __init__(self, tty):
            super().__init__()
            self.tty = tty

        def isatty(self):
            return self.tty

    redraws = {}
    for tty in (True, False):
        monkeypatch.setattr(sys, "stderr", Stream(tty))
        bar = progress_bar(range(3), desc="refine", unit="pair")
        for i in bar:
            for step in ("loading", "refining", "drawing"):
                show_text(bar, f"{i:06d}: {step}")
        bar.close()
        redraws[tty] = sys.stderr.getvalue().count("\r")
        assert "3/3" in sys.stderr.getvalue()
    assert redraws[True] >= 9 and redraws[False] <= 3, redraws
    monkeypatch.setattr(sys, "stderr", Stream(False))
    bar = progress_bar(range(3), enabled=False)
    list(bar)
    assert sys.stderr.getvalue() == ""


def test_a_bar_in_a_log_whose_steps_slow_down_is_redrawn_at_the_interval_with_its_count(monkeypatch):
    """In a log, tqdm learnt from the fast first steps to read the clock only every so many steps:
    when the steps then slowed (a clip's pairs after its cached ones), the log fell silent for
    several intervals, and tqdm's monitor thread redrew the bar with the count of its previous
    redraw beside the text of the step it was on (``8/50 ..., 000011: loading the pair``). Now
    every step past the interval redraws it, with the steps done so far."""
    import io
    import re
    import sys
    import time

    from fsof_torch.io import progress
    from fsof_torch.io.progress import progress_bar, show_text

    monkeypatch.setattr(progress, "LOG_INTERVAL", 0.1)
    monkeypatch.setattr(sys, "stderr", io.StringIO())  # (not a terminal)
    bar = progress_bar(range(26), desc="refine", unit="pair")
    for i in bar:
        show_text(bar, f"{i:06d}: working")
        time.sleep(0.005 if i < 20 else 0.15)  # each of the last six steps longer than the interval
    bar.close()
    lines = [ln for ln in sys.stderr.getvalue().split("\r") if ln.strip()]
    shown = [(int(m[1]), int(m[2])) for m in (re.search(r"(\d+)/26 .*, (\d+): working", ln) for ln in lines) if m]
    # every redraw after the first step shows the steps done: the text is that of the last of them
    assert all(n == step + 1 for n, step in shown), lines
    # a redraw after each slow step (past the interval), not only at the end
    assert {n for n, _ in shown} >= {21, 22, 23, 24, 25, 26}, lines


def test_a_folder_option_given_a_file_or_a_broken_link_says_so(tmp_path, user_folder, capsys):
    """--images, --flows, --gt given a file, or a link to a folder not mounted, exited 2 with "no
    folder at" the path, which is there; the message now says what is there."""
    frame = user_folder / "images" / "000000.png"
    link = tmp_path / "mounted"
    link.symlink_to("/nonexistent-drive/clip")
    base = ["--calib", str(user_folder / "calib.txt"), "--road", str(user_folder / "road"), "--no-progress",
            "--no-figures", "--out", str(tmp_path / "out")]
    images = ["--images", str(user_folder / "images")]
    for argv, option in ((["--images", str(frame)], "--images"), ([*images, "--flows", str(frame)], "--flows"),
                         ([*images, "--gt", str(frame)], "--gt")):
        err = _err(capsys, [*base, *argv]).strip()
        assert err == f"error: {option}: {str(frame)!r} is a file; expected a folder", err
    err = _err(capsys, [*base, "--images", str(link)])
    assert err.startswith(f"error: --images: {str(link)!r} is a symbolic link to '/nonexistent-drive/clip', "
                          f"which does not exist"), err
    assert not (tmp_path / "out").exists()


def test_a_run_without_stderr_runs_without_its_bars(tmp_path, monkeypatch, capsys):
    """A process started with its stderr closed (``2>&-``, a service, ``pythonw``) has
    ``sys.stderr`` None: the bars were drawn there all the same and the run died at its first
    step (exit 1, nothing on stdout, only run.json written); now it runs without them and writes
    its report."""
    import sys

    from fsof_torch.io.progress import progress_bar

    monkeypatch.setattr(sys, "stderr", None)
    assert list(progress_bar(range(3), desc="refine")) == [0, 1, 2]
    out = tmp_path / "out"
    argv = ["--num-pairs", "1", "--size", f"{SIZE[0]}x{SIZE[1]}", "--source", "dis", "--odometry", "given",
            "--no-figures", "--out", str(out)]
    assert main(argv) == 0
    report = json.loads((out / "report.json").read_text())
    assert [(r["pairs"], r["refined"]) for r in report["rows"]] == [(1, 1)]
    assert "report:" in capsys.readouterr().out


def test_a_run_logs_a_few_lines_of_progress_and_its_error_on_a_line_of_its_own(tmp_path, user_folder, scene_pairs,
                                                                                capsys):
    """A run with its bar on, stderr captured (not a terminal): a few redraws, not one per step;
    an input error on a later pair is printed after the bar has ended its line."""
    (user_folder / "flows" / "000001.npy").unlink()
    (user_folder / "flows" / "000001.png").write_bytes(b"garbage\n")
    argv = ["--images", str(user_folder / "images"), "--calib", str(user_folder / "calib.txt"), "--no-figures",
            "--road", str(user_folder / "road"), "--odometry", "given", "--poses", str(user_folder / "poses.txt"),
            *_mounting(scene_pairs), "--out", str(tmp_path / "out")]
    assert main([*argv, "--flows", str(user_folder / "flows")]) == 2
    err = capsys.readouterr().err
    last = err.rstrip("\n").split("\n")[-1]
    assert last.startswith("error: --flows: ") and "refine:" in err and err.count("\r") <= 3, err
    (user_folder / "flows" / "000001.png").unlink()
    assert main([*argv, "--overwrite"]) == 0
    err = capsys.readouterr().err
    assert "2/2" in err and err.count("\r") <= 3, err


def test_an_in_process_run_gives_the_callers_thread_counts_back(tmp_path):
    """refine's main() set torch's and OpenCV's thread counts for the process to --threads and left
    them so: a caller in Python (a notebook, a test) went on single-threaded after a run. The
    counts it had are restored when main() returns, also from a run that fails."""
    import cv2

    torch_threads, cv2_threads = torch.get_num_threads(), cv2.getNumThreads()
    try:
        torch.set_num_threads(2)
        cv2.setNumThreads(3)
        out = tmp_path / "out"
        assert main(["--num-pairs", "1", "--source", "dis", "--no-figures", "--threads", "1", "--out", str(out),
                     *TINY]) == 0
        assert (torch.get_num_threads(), cv2.getNumThreads()) == (2, 3)
        # a run refused after the counts were set (its --out holds another run's results)
        assert main(["--num-pairs", "1", "--source", "dis", "--no-figures", "--threads", "1", "--out", str(out),
                     "--seed", "5", *TINY]) == 2
        assert (torch.get_num_threads(), cv2.getNumThreads()) == (2, 3)
    finally:
        torch.set_num_threads(torch_threads)
        cv2.setNumThreads(cv2_threads)
