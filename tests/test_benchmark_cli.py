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

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
SHARED_MODULES = {"baseline", "cli"}  # imported by the scripts, not scripts themselves
SCRIPTS = sorted(p.stem for p in BENCHMARKS.glob("*.py") if p.stem not in SHARED_MODULES)
ABSENT = "/nonexistent/fsof-benchmark-data"

# (script, arguments, what stderr must name); every one exits 2
BAD = [
    ("auto_road", ["--repeat", "0"], "--repeat"),
    ("auto_road", ["--data", ABSENT, "--no-synthetic", "--no-slow"], "--data"),
    ("bench_compile", ["--repeats", "0"], "--repeats"),
    ("bench_fit", ["--repeats", "0"], "--repeats"),
    ("bench_fit", ["--baseline", "no-such-revision"], "--baseline"),
    ("bench_image_fit", ["--repeats", "0"], "--repeats"),
    ("bench_image_fit", ["--baseline", "no-such-revision"], "--baseline"),
    ("bench_image_fit", ["--kitti15", "--data", ABSENT], "--kitti15"),
    ("bench_model", ["--batch", "1", "0"], "--batch"),
    ("bench_model", ["--warmup", "-1"], "--warmup"),
    ("bench_quickstart", ["--runs", "0"], "--runs"),
    ("bench_quickstart", ["--args", "--pairs 'unclosed"], "--args"),
    ("bench_refine", ["--rounds", "0"], "--rounds"),
    ("bench_refine", ["--repeats", "-1"], "--repeats"),
    ("bench_refine", ["--baseline", "no-such-revision"], "--baseline"),
    ("bench_scene", ["--size", "0", "0"], "--size"),
    ("bench_scene", ["--repeats", "0"], "--repeats"),
    ("bench_smooth_attitude", ["--repeats", "0"], "--repeats"),
    ("bench_smooth_attitude", ["--threads", "0"], "--threads"),
    ("bench_smooth_attitude", ["--sizes", "-5"], "--sizes"),
    ("bench_testnet", ["--repeats", "0"], "--repeats"),
    ("bench_testnet", ["--iters", "0"], "--iters"),
    ("bench_warp", ["--repeats", "3"], "--repeats"),  # (no options: unrecognised)
    ("clip_memory", ["--size", "abc"], "--size"),
    ("clip_memory", ["--lengths", "2"], "--lengths"),
    ("clip_memory", ["--baseline", "no-such-revision"], "--baseline"),
    ("failsafe", ["--pairs", "3"], "--pairs"),  # (no options: unrecognised)
    ("fit_confidence", ["--data", ABSENT], "--data"),
    ("fit_kitti", ["--data", ABSENT], "--data"),
    ("fit_road_models", ["--data", ABSENT], "--data"),
    ("fit_road_models", ["--size", "0", "10"], "--size"),
    ("fit_road_models", ["--pairs", "-1"], "--pairs"),
    ("gate_chance", ["--draws", "0"], "--draws"),
    ("gate_chance", ["--error", "0"], "--error"),
    ("image_fit_settings", ["{bad"], "SETTING"),
    ("image_fit_settings", ["[1, 2]"], "SETTING"),
    ("image_formation", ["--pairs", "0"], "--pairs"),
    ("kitti_photometric", ["--data", ABSENT], "--data"),
    ("presets_refiner", ["--pairs", "-1"], "--pairs"),
    ("presets_refiner", ["--odometry-error", "nan", "0"], "--odometry-error"),
    ("real_road", ["--pairs", "0"], "--pairs"),
    ("real_road", ["--height", "0"], "--height"),
    ("scene_realism", ["--data", ABSENT], "--data"),
    ("scene_road_motion", ["--seeds", "0"], "--seeds"),
    ("scene_road_motion", ["--frames", "1"], "--frames"),
    ("sequence_synthetic", ["--options", "{bad"], "--options"),
    ("sequence_synthetic", ["--threads", "0"], "--threads"),
    ("sequence_synthetic", ["--pairs", "0"], "--pairs"),
]

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
    results.append({"code": code, "stdout": stdout.getvalue()[-3000:], "stderr": stderr.getvalue()[-3000:]})
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
def empty(tmp_path_factory) -> Path:
    """A data folder without the KITTI samples."""
    return tmp_path_factory.mktemp("no_samples")


@pytest.fixture(scope="module")
def runs(tmp_path_factory, empty) -> dict[tuple[str, tuple[str, ...]], dict]:
    """{(script, arguments): its exit code, stdout and stderr} of BAD and of runs on ``empty``,
    all from one process."""
    tmp = tmp_path_factory.mktemp("bench_cli")
    cases = [(script, args) for script, args, _ in BAD]
    cases += [("auto_road", ["--data", str(empty), "--no-synthetic", "--no-slow"]),
              ("fit_kitti", ["--data", str(empty)])]
    (tmp / "cases.json").write_text(json.dumps(cases))
    subprocess.run([sys.executable, "-c", DRIVER, str(BENCHMARKS), str(tmp / "cases.json"), str(tmp / "out.json")],
                   check=True, timeout=300, cwd=BENCHMARKS.parent)
    results = json.loads((tmp / "out.json").read_text())
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
def test_help_exits_0_with_the_first_paragraph_and_every_option_described(script):
    done = subprocess.run([sys.executable, str(BENCHMARKS / f"{script}.py"), "--help"], capture_output=True,
                          text=True, timeout=60, cwd=BENCHMARKS.parent)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("usage:")
    first = _docstring(BENCHMARKS / f"{script}.py").strip().split("\n\n")[0]
    # argparse wraps the text anew (and breaks lines after hyphens): compare without whitespace
    assert "".join(first.split()) in "".join(done.stdout.split()), done.stdout
    assert _undescribed(done.stdout) == [], done.stdout


@pytest.mark.parametrize("script, args, option", BAD, ids=[f"{s}:{' '.join(a)}" for s, a, _ in BAD])
def test_a_bad_value_exits_2_naming_its_option(runs, script, args, option):
    result = runs[(script, tuple(args))]
    assert result["code"] == 2, result
    assert "usage:" in result["stderr"] and "Traceback" not in result["stderr"], result["stderr"]
    # the error line itself names the option (the usage line above it lists every option)
    last = result["stderr"].strip().splitlines()[-1]
    assert ": error: " in last and option in last, result["stderr"]


def test_absent_samples_are_skipped_with_a_note(runs, empty):
    auto = runs[("auto_road", ("--data", str(empty), "--no-synthetic", "--no-slow"))]
    assert auto["code"] in (0, None), auto
    assert "KITTI pair kitti15_000000 absent: skipped" in auto["stdout"]
    assert "KITTI clip kitti_odometry_straight absent: skipped" in auto["stdout"]
    # a folder named explicitly must hold the pair
    kitti = runs[("fit_kitti", ("--data", str(empty)))]
    last = kitti["stderr"].strip().splitlines()[-1]
    assert kitti["code"] == 2 and "--data" in last and "lacks" in last, kitti


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


def test_size_json_and_float_types(cli):
    assert cli.size_hw("375x1242") == (375, 1242) and cli.size_hw("48X160") == (48, 160)
    for bad in ("abc", "0x10", "10", "1x2x3"):
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
    for given, message in ((tmp_path / "absent", "not found"), (tmp_path / "pair", "lacks calib.txt")):
        with pytest.raises(SystemExit) as exit_:
            cli.data_folder(parser, given, default, ("road.json", "calib.txt"))
        assert exit_.value.code == 2 and "--data" in capsys.readouterr().err
    assert not cli.present(tmp_path / "pair", ("calib.txt",), "the pair")
    assert "the pair absent: skipped" in capsys.readouterr().out
    assert cli.present(tmp_path / "pair", ("road.json",), "the pair")


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
