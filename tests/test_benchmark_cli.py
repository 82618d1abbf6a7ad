"""The benchmark scripts' command lines: ``--help`` answers at once with the docstring's whole first
paragraph and a help text for every option, and a bad value exits 2 while the arguments are
parsed, naming its option, before any measurement (``benchmarks/cli.py``).

Each ``--help`` runs in its own process, as a user runs the script; the bad values of every script
run in one process (``runpy``, one import of torch for all), each under a time limit, so that a
value the script takes and starts measuring with fails the test instead of running it."""

from __future__ import annotations

import argparse
import ast
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
SHARED_MODULES = {"baseline", "cli"}  # imported by the scripts, not scripts themselves
SCRIPTS = sorted(p.stem for p in BENCHMARKS.glob("*.py") if p.stem not in SHARED_MODULES)
ABSENT = "/nonexistent/fsof-benchmark-data"
#: stands for a folder made for the test, holding file.txt (a file), nonempty/ (a folder with a
#: file) and empty/ (a folder without the KITTI samples)
TMP = "<tmp>"

# (script, arguments, what stderr must name); every one exits 2
BAD = [
    ("auto_road", ["--repeat", "0"], "--repeat"),
    ("auto_road", ["--pairs", "100000", "--no-real", "--no-slow"], "--pairs"),  # (past the renderer's MAX_FRAME)
    ("auto_road", ["--data", ABSENT, "--no-synthetic", "--no-slow"], "--data"),
    ("auto_road", ["--data", f"{TMP}/empty", "--no-synthetic", "--no-slow"], "--data"),
    ("auto_road", ["--data", f"{TMP}/empty", "--no-real"], "is not read with --no-real"),  # (dropped in silence)
    ("bench_compile", ["--repeats", "0"], "--repeats"),
    ("camera_setups", ["--pairs", "-1"], "--pairs"),
    ("camera_setups", ["--setups", "no-such-camera"], "--setups"),
    ("camera_setups", ["--noise", "-1"], "--noise"),
    ("camera_setups", ["--seed", "-1"], "--seed"),
    ("bench_fit", ["--repeats", "0"], "--repeats"),
    ("bench_fit", ["--baseline", "no-such-revision"], "--baseline"),
    ("bench_image_fit", ["--repeats", "0"], "--repeats"),
    ("bench_image_fit", ["--baseline", "no-such-revision"], "--baseline"),
    ("bench_image_fit", ["--kitti15", "--data", ABSENT], "--data"),
    ("bench_image_fit", ["--kitti15", "--data", f"{TMP}/empty"], "--kitti15"),
    ("bench_image_fit", ["--data", ABSENT], "--data"),  # (no fallback on the synthetic pair)
    ("bench_image_fit", ["--data", f"{TMP}/empty"], "--data"),
    ("bench_image_fit", ["--baseline", "09d064e"], "--baseline"),  # (a revision without fit_image)
    ("bench_model", ["--batch", "1", "0"], "--batch"),
    ("bench_model", ["--batch", "1", "1"], "--batch"),
    ("bench_model", ["--warmup", "-1"], "--warmup"),
    ("bench_model", ["--threads", "100000"], "--threads"),
    ("bench_model", ["--json", TMP], "--json"),  # (a folder)
    ("bench_model", ["--json", f"{TMP}/file.txt/out.json"], "--json"),
    ("bench_fit", ["--json", TMP], "--json"),
    ("bench_fit", ["--json", f"{TMP}/file.txt/out.json"], "--json"),
    ("bench_refine", ["--json", TMP], "--json"),
    ("fit_kitti", ["--json", f"{TMP}/file.txt/out.json"], "--json"),
    ("real_road", ["--json", TMP], "--json"),
    ("real_road", ["--estimator", "[1]"], "--estimator"),
    ("real_road", ["--estimator", '{"bogus": 1}'], "--estimator"),
    ("real_road", ["--estimator", '{"smooth_sigma": -1}'], "--estimator"),
    ("bench_quickstart", ["--runs", "0"], "--runs"),
    ("bench_quickstart", ["--args", "--pairs 'unclosed"], "--args"),
    ("bench_refine", ["--rounds", "0"], "--rounds"),
    ("bench_refine", ["--repeats", "-1"], "--repeats"),
    ("bench_refine", ["--baseline", "no-such-revision"], "--baseline"),
    ("bench_scene", ["--size", "0", "0"], "--size"),
    ("bench_scene", ["--size", "1", "1"], "--size"),
    ("bench_scene", ["--repeats", "0"], "--repeats"),
    ("bench_smooth_attitude", ["--repeats", "0"], "--repeats"),
    ("bench_smooth_attitude", ["--threads", "0"], "--threads"),
    ("bench_smooth_attitude", ["--threads", "100000"], "--threads"),
    ("bench_smooth_attitude", ["--sizes", "-5"], "--sizes"),
    ("bench_testnet", ["--repeats", "0"], "--repeats"),
    ("bench_testnet", ["--iters", "0"], "--iters"),
    ("bench_warp", ["--repeats", "3"], "--repeats"),  # (no options: unrecognised)
    ("clip_memory", ["--size", "abc"], "--size"),
    ("clip_memory", ["--size", "15x64"], "--size"),  # (the job refused it after the clip was written)
    ("clip_memory", ["--size", "16385x64"], "--size"),  # (the renderer raised: a traceback)
    ("clip_memory", ["--lengths", "2"], "--lengths"),
    ("clip_memory", ["--lengths", "11", "100002"], "--lengths"),  # (its last frame past the renderer's MAX_FRAME)
    ("clip_memory", ["--baseline", "no-such-revision"], "--baseline"),
    ("clip_memory", ["--seed", "-1"], "--seed"),
    ("clip_memory", ["--keep", f"{TMP}/file.txt"], "--keep"),
    ("clip_memory", ["--keep", f"{TMP}/nonempty"], "--keep"),  # (an earlier clip's frames would mix in)
    ("failsafe", ["--pairs", "3"], "--pairs"),  # (no options: unrecognised)
    ("fit_confidence", ["--data", ABSENT], "--data"),
    ("fit_confidence", ["--kitti", ABSENT], "--kitti"),  # (was named --data)
    ("fit_confidence", ["--kitti", f"{TMP}/empty"], "--kitti"),
    ("fit_confidence", ["--kitti", f"{TMP}/badpair"], "--kitti"),  # (read in part 3: a traceback)
    ("fit_confidence", ["--data", f"{TMP}/badclip/kitti_odometry_straight"], "--data"),  # (read in part 1)
    ("fit_covariance", ["--data", ABSENT], "--data"),
    ("fit_covariance", ["--data", f"{TMP}/empty"], "--data"),
    ("fit_covariance", ["--data", f"{TMP}/badclip/kitti_odometry_straight"], "--data"),  # (read in part 2)
    ("fit_covariance", ["--pairs", "-1"], "--pairs"),
    ("fit_kitti", ["--data", ABSENT], "--data"),
    ("fit_kitti", ["--data", f"{TMP}/empty"], "--data"),
    ("fit_road_models", ["--data", ABSENT], "--data"),
    ("fit_road_models", ["--data", f"{TMP}/empty", "--skip-kitti"], "is not read with --skip-kitti"),
    ("fit_road_models", ["--size", "0", "10"], "--size"),
    ("fit_road_models", ["--size", "1", "1"], "--size"),
    ("fit_road_models", ["--size", "16385", "16", "--skip-kitti"], "--size"),  # (the renderer raised)
    ("fit_road_models", ["--pairs", "-1"], "--pairs"),
    ("fit_road_models", ["--pairs", "100000", "--skip-kitti"], "--pairs"),
    ("gate_chance", ["--draws", "0"], "--draws"),
    ("gate_chance", ["--error", "0"], "--error"),
    ("image_fit_settings", ["{bad"], "SETTING"),
    ("image_fit_settings", ["[1, 2]"], "SETTING"),
    ("image_fit_settings", ['{"bogus": 1}'], "SETTING"),
    ("image_fit_settings", ["--noise", "-1"], "--noise"),
    ("image_fit_settings", ["--noise", "nan"], "--noise"),
    ("image_formation", ["--pairs", "0"], "--pairs"),
    ("image_formation", ["--pairs", "50001"], "--pairs"),  # (the turning scene's last pair: 100000)
    ("image_formation", ["--matched-sigma", "0"], "--matched-sigma"),
    ("image_formation", ["--warped"], "--warped"),
    ("image_formation", ["--matched-sigma", "nan"], "--matched-sigma"),
    ("kitti_photometric", ["--data", ABSENT], "--data"),
    ("presets_refiner", ["--pairs", "-1"], "--pairs"),
    ("presets_refiner", ["--pairs", "100000"], "--pairs"),
    ("presets_refiner", ["--odometry-error", "nan", "0"], "--odometry-error"),
    ("presets_refiner", ["--odometry-error", "-1", "0"], "--odometry-error"),
    ("presets_refiner", ["--odometry-error", "0", "0"], "--odometry-error"),
    ("presets_refiner", ["--odometry-error", "1", "90"], "--odometry-error"),
    ("presets_refiner", ["--seed", "-1"], "--seed"),
    ("real_road", ["--pairs", "0"], "--pairs"),
    ("real_road", ["--slalom", "0", "10"], "--slalom"),
    ("real_road", ["--steps", "1,x"], "--steps"),
    ("real_road", ["--steps", "1,-1"], "--steps"),
    ("real_road", ["--steps", "0,0"], "--steps"),
    ("real_road", ["--steps", "1", "--step", "2"], "--steps"),
    ("real_road", ["--slalom", "25", "10"], "--slalom"),
    ("real_road", ["--slalom", "6", "1"], "--slalom"),
    ("real_road", ["--slalom", "6", "2"], "--slalom"),  # (sin(2 pi k / 2) = 0: no frame turned)
    ("real_road", ["--slalom", "nan", "10"], "--slalom"),
    ("real_road", ["--height", "0"], "--height"),
    ("scene_realism", ["--data", ABSENT], "--data"),
    ("scene_realism", ["--data", f"{TMP}/empty"], "--data"),  # (a folder named must hold a sample)
    ("scene_road_motion", ["--seeds", "0"], "--seeds"),
    ("scene_road_motion", ["--frames", "1"], "--frames"),
    ("scene_road_motion", ["--frames", "100001"], "--frames"),
    ("scene_road_motion", ["--pairs", "100000"], "--pairs"),
    ("sequence_synthetic", ["--options", "{bad"], "--options"),
    ("sequence_synthetic", ["--threads", "0"], "--threads"),
    ("sequence_synthetic", ["--pairs", "0"], "--pairs"),
    ("sequence_synthetic", ["--pairs", "100001"], "--pairs"),
    ("sequence_synthetic", ["--seed", "-1"], "--seed"),
    ("sequence_synthetic", ["--options", '{"bogus": 1}'], "--options"),
    ("sequence_synthetic", ["--options", '{"init": {}}'], "--options"),  # (fit_sequence sets it)
    # (a value fit_image refuses: a traceback from the first fit, after the rendering)
    ("sequence_synthetic", ["--options", '{"max_iter": -1}'], "--options: max_iter"),
    ("sequence_synthetic", ["--options", '{"levels": "x"}'], "--options: levels"),
    ("image_fit_settings", ['{"inlier_threshold": -1}'], "SETTING: inlier_threshold"),
    ("turn_screen", ["--data", ABSENT], "--data"),
    ("turn_screen", ["--data", f"{TMP}/empty"], "--data"),
    ("turn_screen", ["--data", f"{TMP}/badclip"], "--data"),  # (read after the synthetic part)
    ("turn_screen", ["--data", f"{TMP}/empty", "--no-real"], "is not read with --no-real"),
]
# a failing run of the job: exits 1 naming the run (the single option passed as documented)
QUICKSTART_FAILS = ("bench_quickstart", ["--runs", "1", "--args", "--no-such-option"])

# runs each (script, arguments) as `python benchmarks/<script>.py ARGS` would, in this one process
DRIVER = r"""
import contextlib, io, json, runpy, signal, sys, traceback
folder, cases, out = sys.argv[1], json.load(open(sys.argv[2])), sys.argv[3]
sys.path.insert(0, folder)

def too_long(*_):
    raise TimeoutError("still running: the value was taken")

signal.signal(signal.SIGALRM, too_long)
results = []
for script, args in cases:
    sys.argv = [f"{folder}/{script}.py", *args]
    stdout, stderr = io.StringIO(), io.StringIO()
    code = None
    signal.alarm(60)
    try:
        with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            runpy.run_path(sys.argv[0], run_name="__main__")
    except SystemExit as exit_:
        code = exit_.code
    except BaseException:
        code = "raised: " + traceback.format_exc()[-1500:]
    finally:
        signal.alarm(0)
    results.append({"code": code, "stdout": stdout.getvalue()[-20000:], "stderr": stderr.getvalue()[-3000:]})
json.dump(results, open(out, "w"))
"""


def _load_cli():
    spec = importlib.util.spec_from_file_location("benchmarks_cli", BENCHMARKS / "cli.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def cli():
    return _load_cli()


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[tuple[str, tuple[str, ...]], dict]:
    """{(script, arguments): its exit code, stdout and stderr} of BAD, QUICKSTART_FAILS and every
    script's ``--help``, all from one process (``TMP`` in the arguments: a folder made for them)."""
    tmp = tmp_path_factory.mktemp("bench_cli")
    folder = tmp / "paths"
    (folder / "nonempty").mkdir(parents=True)
    (folder / "nonempty" / "000000.png").write_bytes(b"")
    (folder / "empty").mkdir()
    (folder / "file.txt").write_text("a file\n")
    (folder / "badpair").mkdir()  # (a KITTI 2015 pair's files, none of them readable)
    for name in ("image_10.png", "image_11.png", "calib_cam_to_cam.txt", "road.json"):
        (folder / "badpair" / name).write_bytes(b"garbage")
    clip = folder / "badclip" / "kitti_odometry_straight"  # (a clip's files, none of them readable)
    (clip / "image_l").mkdir(parents=True)
    for name in ("image_l/000000.png", "image_l/000001.png", "calib.txt", "road.json", "poses.txt"):
        (clip / name).write_bytes(b"garbage")
    cases = [(script, args) for script, args, _ in BAD] + [QUICKSTART_FAILS]
    cases += [(script, ["--help"]) for script in SCRIPTS]
    given = [(script, [a.replace(TMP, str(folder)) for a in args]) for script, args in cases]
    (tmp / "cases.json").write_text(json.dumps(given))
    subprocess.run([sys.executable, "-c", DRIVER, str(BENCHMARKS), str(tmp / "cases.json"), str(tmp / "out.json")],
                   check=True, timeout=400, cwd=BENCHMARKS.parent)
    results = json.loads((tmp / "out.json").read_text())
    assert (folder / "file.txt").read_text() == "a file\n" and list((folder / "empty").iterdir()) == []
    return {(script, tuple(args)): result for (script, args), result in zip(cases, results)}


def _docstring(path: Path) -> str:
    return ast.get_docstring(ast.parse(path.read_text()), clean=False) or ""


def _undescribed(help_text: str) -> list[str]:
    """The options that ``--help`` lists without a help text."""
    lines = help_text.splitlines()
    bare = []
    for i, line in enumerate(lines):
        if not line.startswith("  -"):
            continue
        entry = line.strip()
        described_here = "  " in entry
        following = lines[i + 1] if i + 1 < len(lines) else ""
        continued = following.startswith(" " * 4) and not following.lstrip().startswith("-")
        if not (described_here or continued):
            bare.append(entry)
    return bare


def test_every_script_is_listed():
    assert len(SCRIPTS) >= 23 and "auto_road" in SCRIPTS and "cli" not in SCRIPTS
    assert {script for script, _, _ in BAD} == set(SCRIPTS)


@pytest.mark.parametrize("script", SCRIPTS)
def test_help_exits_0_with_the_first_paragraph_and_every_option_described(runs, script):
    done = runs[(script, ("--help",))]
    assert done["code"] == 0 and done["stderr"] == "", done
    assert done["stdout"].startswith("usage:")
    first = _docstring(BENCHMARKS / f"{script}.py").strip().split("\n\n")[0]
    # argparse wraps the text anew (and breaks lines after hyphens): compare without whitespace
    assert "".join(first.split()) in "".join(done["stdout"].split()), done["stdout"]
    assert _undescribed(done["stdout"]) == [], done["stdout"]


@pytest.mark.parametrize("script, args, option", BAD, ids=[f"{s}:{' '.join(a)}" for s, a, _ in BAD])
def test_a_bad_value_exits_2_naming_its_option(runs, script, args, option):
    result = runs[(script, tuple(args))]
    assert result["code"] == 2, result
    assert "usage:" in result["stderr"] and "Traceback" not in result["stderr"], result["stderr"]
    # the error line itself names the option (the usage line above it lists every option)
    last = result["stderr"].strip().splitlines()[-1]
    assert ": error: " in last and option in last, result["stderr"]


def test_a_folder_named_must_hold_what_the_script_reads(runs):
    """Only the default data folder may lack the samples (they are then skipped with a note): a
    folder named by --data is checked before any work."""
    kitti = runs[("fit_kitti", ("--data", f"{TMP}/empty"))]
    assert "lacks" in kitti["stderr"].strip().splitlines()[-1], kitti
    for script, args in (("auto_road", ("--data", f"{TMP}/empty", "--no-synthetic", "--no-slow")),
                         ("scene_realism", ("--data", f"{TMP}/empty"))):
        last = runs[(script, args)]["stderr"].strip().splitlines()[-1]
        assert ("holds none of the samples (kitti15_000000/ not found; kitti_odometry_straight/ not found)"
                in last), last
    assert "absent: skipped" not in runs[("auto_road", ("--data", f"{TMP}/empty", "--no-synthetic",
                                                          "--no-slow"))]["stdout"]


def test_a_failing_quickstart_run_is_named(runs):
    script, args = QUICKSTART_FAILS
    result = runs[(script, tuple(args))]
    assert result["code"] == 1, result
    assert "run 0 of 1 failed (exit status 2): python -m refine --no-such-option" in result["stderr"], result
    assert "unrecognized arguments: --no-such-option" in result["stderr"]
    assert "Command being timed" not in result["stderr"]  # (time's report left out)


def test_quickstart_args_take_a_single_option(load_benchmark):
    joined = load_benchmark("bench_quickstart")._joined
    assert joined(["--runs", "1", "--args", "--no-figures"]) == ["--runs", "1", "--args=--no-figures"]
    assert joined(["--args=--num-pairs 2", "--runs", "3"]) == ["--args=--num-pairs 2", "--runs", "3"]
    assert joined(["--args"]) == ["--args"]  # (argparse then says it expects one argument)


@pytest.mark.parametrize("text, value", [("1", 1), ("12", 12)])
def test_positive_int_takes_counts(cli, text, value):
    assert cli.positive_int(text) == value


@pytest.mark.parametrize("text", ["0", "-3", "1.5", "abc", ""])
def test_positive_int_rejects_the_rest(cli, text):
    with pytest.raises(argparse.ArgumentTypeError, match="expected an integer >= 1"):
        cli.positive_int(text)


def test_nonnegative_int_takes_0(cli):
    assert cli.nonnegative_int("0") == 0
    with pytest.raises(argparse.ArgumentTypeError, match=">= 0, got '-1'"):
        cli.nonnegative_int("-1")


def test_pair_types_end_at_the_renderers_last_frame(cli):
    """A pair index or count past the renderer's frames (MAX_FRAME) is refused while parsing, naming
    the bound (it used to end in a traceback from the renderer, after the work before it)."""
    from fsof_torch.data.scene.render import MAX_FRAME

    assert cli.pair_index("0") == 0 and cli.pair_index(str(MAX_FRAME - 1)) == MAX_FRAME - 1
    for bad in ("-1", str(MAX_FRAME), "x"):
        with pytest.raises(argparse.ArgumentTypeError, match=rf"from 0 to {MAX_FRAME - 1} \(the renderer's frames "
                                                             rf"end at {MAX_FRAME}\), got '{bad}'"):
            cli.pair_index(bad)
    assert cli.pair_count()(str(MAX_FRAME)) == MAX_FRAME and cli.pair_count(2)("2") == 2
    with pytest.raises(argparse.ArgumentTypeError, match=f"from 1 to {MAX_FRAME} "):
        cli.pair_count()(str(MAX_FRAME + 1))
    with pytest.raises(argparse.ArgumentTypeError, match=f"from 2 to {MAX_FRAME} "):
        cli.pair_count(2)("1")
    # pairs 0, 2, ..., 2 (n - 1): the last may be MAX_FRAME - 2 or MAX_FRAME - 1, not MAX_FRAME
    two = cli.pair_count(spacing=2)
    assert two(str(MAX_FRAME // 2)) == MAX_FRAME // 2
    with pytest.raises(argparse.ArgumentTypeError, match="pairs 2 frames apart"):
        two(str(MAX_FRAME // 2 + 1))


def test_frame_count_ends_at_the_renderers_last_frame(cli):
    """A clip of n frames from frame 0 ends at frame n - 1: at most MAX_FRAME, so n at most
    MAX_FRAME + 1 (a longer one ended in the renderer's traceback after rendering the frames)."""
    from fsof_torch.data.scene.render import MAX_FRAME

    three = cli.frame_count(3)
    assert three("3") == 3 and three(str(MAX_FRAME + 1)) == MAX_FRAME + 1
    for bad in ("2", str(MAX_FRAME + 2), "x"):
        with pytest.raises(argparse.ArgumentTypeError, match=rf"from 3 to {MAX_FRAME + 1} \(frames from 0; the "
                                                             rf"renderer's frames end at {MAX_FRAME}\), got '{bad}'"):
            three(bad)


def test_odometry_error_bounds(cli, capsys):
    parser = argparse.ArgumentParser(prog="bench")
    assert cli.odometry_error(parser, None) is None
    assert cli.odometry_error(parser, [1.03, -0.2]) == (1.03, -0.2)
    for bad in ([0.0, 0.0], [-1.0, 0.0], [float("inf"), 0.0], [1.0, float("nan")], [1.0, 45.0], [2.5, 0.0]):
        assert "--odometry-error: expected a scale within [0.5, 2]" in _error(capsys, cli.odometry_error, parser, bad)


def test_size_json_and_float_types(cli):
    assert cli.size_hw("375x1242") == (375, 1242) and cli.size_hw("48X160") == (48, 160)
    assert cli.size_hw("16x16384") == (16, 16384)
    for bad in ("abc", "0x10", "10", "1x2x3", "15x64", "64x16385"):
        with pytest.raises(argparse.ArgumentTypeError, match="HxW"):
            cli.size_hw(bad)
    assert cli.json_object('{"highpass": null}') == {"highpass": None}
    for bad in ("{bad", "[1]", "3"):
        with pytest.raises(argparse.ArgumentTypeError, match="a JSON object"):
            cli.json_object(bad)
    assert cli.finite_float("-0.5") == -0.5
    for bad in ("nan", "inf", "x"):
        with pytest.raises(argparse.ArgumentTypeError, match="finite"):
            cli.finite_float(bad)


def test_description_is_the_whole_first_paragraph(cli):
    doc = "What it is for,\ncontinued on a second line.\n\nDetails.\n"
    assert cli.description(doc) == "What it is for,\ncontinued on a second line."


def test_data_folder_given_must_exist_and_hold_the_files(cli, tmp_path, capsys):
    parser = argparse.ArgumentParser(prog="bench")
    default = tmp_path / "default"
    assert cli.data_folder(parser, None, default) == default  # (the default may be absent)
    (tmp_path / "pair").mkdir()
    (tmp_path / "pair" / "road.json").write_text("{}")
    assert cli.data_folder(parser, tmp_path / "pair", default, ("road.json",)) == tmp_path / "pair"
    for given, message in ((tmp_path / "absent", "not found"), (tmp_path / "pair", "lacks calib.txt"),
                           (tmp_path / "pair" / "road.json", "is a file; expected a folder")):  # (was "not found")
        with pytest.raises(SystemExit) as exit_:
            cli.data_folder(parser, given, default, ("road.json", "calib.txt"))
        err = capsys.readouterr().err
        assert exit_.value.code == 2 and "--data" in err and message in err
    assert not cli.present(tmp_path / "pair", ("calib.txt",), "the pair")
    assert "the pair absent: skipped" in capsys.readouterr().out
    assert cli.present(tmp_path / "pair", ("road.json",), "the pair")


def test_a_clip_whose_road_polygon_covers_no_pixel_exits_2(cli, tmp_path, capsys):
    """``readable_clip``: a road.json polygon beside the frames (drawn for other frames) is refused
    naming the option, as the figures over the road would be means over no pixel; one on the
    frames passes."""
    from fsof_torch.io import write_image, write_kitti_calibration

    parser = argparse.ArgumentParser(prog="bench")
    clip = tmp_path / "clip"
    (clip / "image_l").mkdir(parents=True)
    for i in range(2):
        write_image(clip / "image_l" / f"{i:06d}.png", torch.full((1, 40, 64), 100.0 + i))
    K = torch.tensor([[50.0, 0.0, 32.0], [0.0, 50.0, 20.0], [0.0, 0.0, 1.0]])
    write_kitti_calibration(clip / "calib.txt", K, cam=0, style="odometry")
    for polygon, refused in (([[100, 5], [120, 5], [120, 30]], True), ([[5, 39], [30, 25], [60, 39]], False)):
        (clip / "road.json").write_text(json.dumps({"size": [40, 64], "road_polygon": polygon}))
        if refused:
            with pytest.raises(SystemExit) as exit_:
                cli.readable_clip(parser, clip, "--clip")
            assert exit_.value.code == 2
            assert "--clip: road.json: its road polygon covers no pixel of the 40 x 64 frames" in capsys.readouterr().err
        else:
            cli.readable_clip(parser, clip, "--clip")


def test_baseline_revision(cli, tmp_path, capsys, monkeypatch):
    parser = argparse.ArgumentParser(prog="bench")
    assert cli.baseline_revision(parser, "none", "HEAD") is None
    assert cli.baseline_revision(parser, None, None) is None
    with pytest.raises(SystemExit) as exit_:
        cli.baseline_revision(parser, "no-such-revision")
    assert exit_.value.code == 2 and "--baseline" in capsys.readouterr().err
    # outside a git checkout: the default falls back on no baseline, a revision given is an error
    monkeypatch.setattr(cli, "REPO", tmp_path)
    assert cli.baseline_revision(parser, None, "HEAD") is None
    assert "no baseline" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exit_:
        cli.baseline_revision(parser, "HEAD")
    assert exit_.value.code == 2


def test_thread_count_seed_and_side(cli, monkeypatch):
    monkeypatch.setattr(cli.os, "cpu_count", lambda: 4)
    assert cli.thread_count("4") == 4
    for bad, message in (("5", "at most 4"), ("0", ">= 1"), ("x", ">= 1")):
        with pytest.raises(argparse.ArgumentTypeError, match=message):
            cli.thread_count(bad)
    assert cli.scene_seed("0") == 0 and cli.scene_seed(str(2**62 - 1)) == 2**62 - 1
    for bad in ("-1", str(2**62), "1.5", "x"):
        with pytest.raises(argparse.ArgumentTypeError, match=r"in \[0, 2\*\*62\)"):
            cli.scene_seed(bad)
    assert cli.image_side(str(cli.MIN_SIDE)) == cli.MIN_SIDE and cli.image_side("16384") == 16384
    for bad in (str(cli.MIN_SIDE - 1), "16385"):  # (16385: the renderer raised, a traceback)
        with pytest.raises(argparse.ArgumentTypeError, match=f"from {cli.MIN_SIDE} to 16384"):
            cli.image_side(bad)


def _error(capsys, fn, *args) -> str:
    """What ``fn(*args)`` says as ``parser.error`` (it exits 2)."""
    with pytest.raises(SystemExit) as exit_:
        fn(*args)
    assert exit_.value.code == 2
    return capsys.readouterr().err.strip().splitlines()[-1]


def test_json_path_checks_the_path_and_removes_an_earlier_file(cli, tmp_path, capsys):
    parser = argparse.ArgumentParser(prog="bench")
    assert cli.json_path(parser, None) is None
    earlier = tmp_path / "out.json"
    earlier.write_text('{"from": "an earlier run"}')
    assert cli.json_path(parser, str(earlier)) == earlier and not earlier.exists()
    assert "is a folder" in _error(capsys, cli.json_path, parser, tmp_path)
    (tmp_path / "file").write_text("")
    assert "is a file, so" in _error(capsys, cli.json_path, parser, tmp_path / "file" / "out.json")
    data = tmp_path / "data"
    (data / "pair").mkdir(parents=True)
    (data / "pair" / "road.json").write_text("{}")
    last = _error(capsys, cli.json_path, parser, data / "pair" / "road.json", {"--data": data, "--clip": None})
    assert "--json" in last and "inside the input --data" in last
    assert (data / "pair" / "road.json").read_text() == "{}"  # (refused, not removed)
    # missing folders are created when it is written; NaN is written as null
    deep = cli.json_path(parser, tmp_path / "new" / "folder" / "out.json")
    cli.write_json(deep, {"x": float("nan"), "rows": [1, 2]})
    assert json.loads(deep.read_text()) == {"x": None, "rows": [1, 2]}


def test_samples_folder_given_must_hold_one_sample(cli, tmp_path, capsys):
    parser = argparse.ArgumentParser(prog="bench")
    samples = {"pair": ("road.json", "image_10.png"), "clip": ("image_l",)}
    default = tmp_path / "default"
    assert cli.samples_folder(parser, None, default, samples) == default  # (the default may lack them)
    (tmp_path / "pair").mkdir()
    (tmp_path / "pair" / "road.json").write_text("{}")
    last = _error(capsys, cli.samples_folder, parser, tmp_path, default, samples)
    assert last.endswith(f"--data: {str(tmp_path)!r} holds none of the samples (pair/ lacks image_10.png; "
                         "clip/ not found)"), last
    (tmp_path / "clip" / "image_l").mkdir(parents=True)
    assert cli.samples_folder(parser, tmp_path, default, samples) == tmp_path
    assert "not found" in _error(capsys, cli.samples_folder, parser, tmp_path / "absent", default, samples)


def test_check_options_names_the_option(cli, capsys):
    def fit(image, *, highpass=4.0, init=None):
        return image

    parser = argparse.ArgumentParser(prog="bench")
    cli.check_options(parser, {"highpass": None}, "--options", fit, reserved=("image", "init"))
    last = _error(capsys, cli.check_options, parser, {"bogus": 1}, "--options", fit, ("image", "init"))
    assert "--options: unknown options ['bogus'] of fit" in last
    assert "--options" in _error(capsys, cli.check_options, parser, {"init": 1}, "--options", fit, ("image", "init"))


def test_clip_memory_links_a_kept_clip_given_by_a_relative_path(tmp_path, monkeypatch):
    """``clip_memory.py --keep DIR`` with a relative DIR: the shorter clips it links in a temporary
    folder reach the kept frames (a relative link target, read from the link's own folder, reached
    nothing, and the job found 0 images)."""
    spec = importlib.util.spec_from_file_location("benchmarks_clip_memory", BENCHMARKS / "clip_memory.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    clip = tmp_path / "kept"
    for d, names in (("images", ("000000.png", "000001.png", "000002.png")), ("road", ("000000.png", "000001.png"))):
        (clip / d).mkdir(parents=True)
        for name in names:
            (clip / d / name).write_bytes(d.encode())
    (clip / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    monkeypatch.chdir(tmp_path)
    part = tmp_path / "elsewhere" / "clip2"
    module.prefix(Path("kept"), part, 2)
    assert sorted(p.name for p in (part / "images").iterdir()) == ["000000.png", "000001.png"]
    assert [p.read_bytes() for p in sorted((part / "images").iterdir())] == [b"images", b"images"]
    assert [p.read_bytes() for p in (part / "road").iterdir()] == [b"road"]
    assert (part / "calib.txt").read_text().startswith("P0:")
