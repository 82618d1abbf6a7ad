"""The jobs when the reader of their stdout goes away (``python -m refine ... | head``): every
file is written before anything is printed, and the job ends with one line on stderr and exit
status 1, not a traceback. Before, ``eval tables``, ``eval noise``, ``eval train``, ``eval vflow``
and ``eval synth --json`` printed their tables before writing their files (the trained nets too),
and lost them to the BrokenPipeError;
``refine`` wrote its report first but ended with a traceback."""

from __future__ import annotations

import contextlib
import io
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from eval.__main__ import main as eval_main
from refine.__main__ import main as refine_main

ROOT = Path(__file__).resolve().parents[1]


class ClosedPipe(io.TextIOBase):
    """A stdout whose reader went away: every write raises BrokenPipeError (as a closed pipe's)."""

    def write(self, text: str) -> int:
        raise BrokenPipeError(32, "Broken pipe")

    def fileno(self) -> int:
        raise io.UnsupportedOperation("fileno")


def closed(main, argv: list[str]) -> int:
    """``main(argv)`` with a stdout whose reader went away."""
    with contextlib.redirect_stdout(ClosedPipe()):
        return main(argv)


@pytest.fixture
def keep_threads():
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


def _one_line(err: str, name: str, kept: str) -> None:
    assert err.endswith(f"{name}: stdout was closed by its reader (a broken pipe); {kept}\n"), err
    assert "Traceback" not in err, err


def test_eval_tables_writes_its_files_before_printing(tmp_path, capsys):
    out = tmp_path / "t"
    rc = closed(eval_main, ["tables", "--quick", "--size", "48", "160", "--pairs", "1", "--no-kitti", "--out", str(out),
                    "--no-progress"])
    assert rc == 1
    _one_line(capsys.readouterr().err, "eval tables", "the files written so far are kept, each one whole")
    tables = json.loads((out / "tables.json").read_text())
    assert set(tables) == {"settings", "cvc12", "carla", "environment"}
    md = (out / "tables.md").read_text()
    assert "## CVC12-like" in md and "## CARLA-like" in md


def test_eval_noise_writes_its_files_before_printing(tmp_path, capsys):
    out = tmp_path / "noise"
    rc = closed(eval_main, ["noise", "--quick", "--size", "48", "160", "--pose-size", "60", "200", "--sigmas", "0",
                    "--pose-sigmas", "0", "--trials", "2", "--no-plots", "--out", str(out), "--no-progress"])
    assert rc == 1
    _one_line(capsys.readouterr().err, "eval noise", "the files written so far are kept, each one whole")
    data = json.loads((out / "noise.json").read_text())
    assert [r["sigma"] for r in data["noise_robustness"]] == [0.0]


def test_eval_train_writes_its_nets_before_printing(tmp_path, capsys, keep_threads):
    out = tmp_path / "nets"
    rc = closed(eval_main, ["train", "--steps", "1", "--size", "32", "64", "--batch", "1", "--iters", "1",
                    "--train-pairs", "1", "--test-pairs", "1", "--threads", "1", "--no-progress",
                    "--json", str(tmp_path / "train.json"), "--out", str(out)])
    assert rc == 1
    _one_line(capsys.readouterr().err, "eval train", "the files written so far are kept, each one whole")
    report = json.loads((tmp_path / "train.json").read_text())
    assert set(report["metrics"]) == {"untrained", "unsupervised", "unsupervised+freespace"}
    nets = sorted(p.name for p in out.iterdir())
    assert len(nets) == 2 and all(torch.load(out / n, weights_only=True) for n in nets), nets


def test_eval_synth_writes_its_json_before_printing(tmp_path, capsys):
    """``synth --json`` wrote its summary after printing the pairs' table, and lost it."""
    out, summary = tmp_path / "synth", tmp_path / "synth.json"
    rc = closed(eval_main, ["synth", "--pairs", "1", "--size", "32", "64", "--out", str(out), "--json", str(summary),
                            "--no-progress"])
    assert rc == 1
    _one_line(capsys.readouterr().err, "eval synth", "the files written so far are kept, each one whole")
    data = json.loads(summary.read_text())
    assert data["num_pairs"] == 1 and [r["index"] for r in data["pairs"]] == [0]


def test_eval_vflow_writes_its_json_before_printing(tmp_path, capsys):
    """``vflow`` printed the fitted curve before writing vflow.json, and lost it."""
    out = tmp_path / "vflow"
    rc = closed(eval_main, ["vflow", "--size", "48", "96", "--out", str(out), "--no-progress"])
    assert rc == 1
    _one_line(capsys.readouterr().err, "eval vflow", "the files written so far are kept, each one whole")
    data = json.loads((out / "vflow.json").read_text())
    assert data["curve"]["success"] is True and (out / "vflow_map.png").is_file()


def test_refine_ends_with_one_line_and_its_report_written(tmp_path, capsys):
    out = tmp_path / "out"
    rc = closed(refine_main, ["--num-pairs", "1", "--source", "dis", "--no-figures", "--out", str(out), "--size", "48x160",
                      "--no-progress"])
    assert rc == 1
    _one_line(capsys.readouterr().err, "refine", "the pairs finished and the report written so far are kept")
    assert json.loads((out / "report.json").read_text())["pairs"]
    assert "| road before |" in (out / "report.md").read_text()


def test_a_real_closed_pipe_ends_without_a_traceback(tmp_path):
    """The process as a shell runs it, its stdout a pipe closed before it prints: Python's flush
    of stdout at exit must not raise either (stdout is pointed at the null device)."""
    out = tmp_path / "synth"
    job = subprocess.Popen([sys.executable, "-m", "eval", "synth", "--out", str(out), "--pairs", "1", "--size", "32",
                            "64", "--no-progress"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    job.stdout.close()
    err = job.stderr.read().decode()
    assert job.wait(timeout=300) == 1, err
    assert err == "eval synth: stdout was closed by its reader (a broken pipe); the files written so far are " \
                  "kept, each one whole\n", err
    assert json.loads((out / "meta.json").read_text())["num_pairs"] == 1
