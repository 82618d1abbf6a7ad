"""Tests of fsof_torch.io.progress.warnings_above_bars: a warning shown while a bar is drawn on
stderr is written on lines of its own, and the jobs show theirs so."""

from __future__ import annotations

import io
import re
import sys
import warnings

import pytest
import torch

from fsof_torch.io.progress import progress_bar, warnings_above_bars


def show_as_python_does(message, category, filename, lineno, file=None, line=None):
    """Python's own display of a warning (which pytest's recorder replaces within a test)."""
    (sys.stderr if file is None else file).write(warnings.formatwarning(message, category, filename, lineno, line))


def lines_of(text: str) -> list[str]:
    """The lines a log viewer shows: a carriage return starts a line too."""
    return re.split("[\r\n]", text)


def loop_that_warns(stream: io.StringIO) -> str:
    """A bar over three steps on ``stream`` (a log: not a terminal) whose second step warns."""
    bar = progress_bar(range(3), desc="loop", unit="step")
    for i in bar:
        if i == 1:
            line = sys._getframe().f_lineno + 1
            warnings.warn("step 1 went wrong", RuntimeWarning)
    return f"{__file__}:{line}: RuntimeWarning: step 1 went wrong"


def test_a_warning_during_a_bar_starts_a_line_of_its_own(monkeypatch):
    """Without it the warning followed the bar's text on the bar's line (``loop:  33%|... 1/3 [...]
    /path/x.py:12: RuntimeWarning: ...``); within it the bar is cleared, the warning written from the
    start of a line, and the bar drawn again below it."""
    got = {}
    for redirected in (False, True):
        stream = io.StringIO()
        monkeypatch.setattr(sys, "stderr", stream)
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            warnings.showwarning = show_as_python_does
            if redirected:
                with warnings_above_bars():
                    shown = loop_that_warns(stream)
                assert warnings.showwarning is show_as_python_does  # (put back)
            else:
                shown = loop_that_warns(stream)
        got[redirected] = stream.getvalue()
    assert shown in got[False] and shown not in lines_of(got[False]), got[False]  # (on the bar's line)
    err = got[True]
    assert shown in lines_of(err), err
    before, _, after = err.partition(shown)
    assert before.rstrip(" \r").endswith("[00:00<?, ?step/s]"), err  # (the bar drawn, then cleared)
    assert before.endswith("\r") and after.startswith("\n") and "\rloop:" in after, err
    assert "3/3" in after and after.endswith("\n"), err


def test_warnings_within_are_filtered_and_recorded_as_before():
    """A filter, an error filter and a recorder (pytest.warns) act as they do without it."""
    with pytest.warns(RuntimeWarning, match="^recorded$"), warnings_above_bars():
        warnings.warn("recorded", RuntimeWarning)
    with warnings.catch_warnings(), warnings_above_bars():
        warnings.simplefilter("error")
        with pytest.raises(RuntimeWarning, match="raised"):
            warnings.warn("raised", RuntimeWarning)
    with warnings.catch_warnings(record=True) as got, warnings_above_bars():
        warnings.simplefilter("ignore")
        warnings.warn("ignored", RuntimeWarning)
    assert got == []


def test_a_warning_during_the_training_jobs_bar_starts_a_line_of_its_own(monkeypatch, capsys):
    """``python -m eval train --odometry fit``: the freespace loss's warning of a failed fit was
    written after the training bar's text, on its line (``unsupervised+freespace:  50%|...
    freespace=0.015]/path/eval/train.py:239: RuntimeWarning: road: ...``)."""
    from eval import train
    from eval.__main__ import main

    threads = torch.get_num_threads()
    real = train.build_loss

    def build_loss(*args, **kwargs):
        loss = real(*args, **kwargs)

        def warning_loss(*a, **k):
            warnings.warn("the road model is defined at none of the road pixels", RuntimeWarning)
            return loss(*a, **k)

        return warning_loss

    monkeypatch.setattr(train, "build_loss", build_loss)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            warnings.showwarning = show_as_python_does
            assert main(["train", "--steps", "1", "--size", "32", "64", "--batch", "1", "--iters", "1",
                         "--train-pairs", "1", "--test-pairs", "1", "--threads", "1"]) == 0
    finally:
        torch.set_num_threads(threads)
    err = capsys.readouterr().err
    warned = [ln for ln in lines_of(err) if "RuntimeWarning: the road model is defined at none" in ln]
    assert len(warned) == 2 and all(ln.startswith(f"{__file__}:") for ln in warned), err


def test_print_above_bars_writes_a_line_of_its_own(monkeypatch):
    """A job's warning printed while a bar is drawn: on a line of its own, the bar drawn again below
    it; where the process has no stderr, nowhere (print's None file is stdout, among the results)."""
    from fsof_torch.io.progress import print_above_bars

    monkeypatch.setattr(sys, "stderr", io.StringIO())
    with progress_bar(total=2, desc="fits", unit="fit") as bar:
        bar.update(1)
        print_above_bars("warning: a row over no pixel")
    err = sys.stderr.getvalue()
    before, found, after = err.partition("warning: a row over no pixel\n")
    assert found and before.endswith("\r") and lines_of(before)[-1] == "", err
    assert after.startswith("\rfits:") and "1/2" in after, err
    monkeypatch.setattr(sys, "stderr", None)
    monkeypatch.setattr(sys, "stdout", io.StringIO())
    print_above_bars("warning: nowhere")
    assert sys.stdout.getvalue() == ""


@pytest.mark.parametrize("setting, shown", [("1", False), ("", True), (None, True)])
def test_tqdms_environment_variable_turns_the_bars_off(tmp_path, setting, shown):
    """``TQDM_DISABLE=1``, tqdm's switch for every bar of a process (CI logs), turned off plain tqdm
    bars but not these: the ``disable`` they passed replaced it. Now it turns them off too, the
    library's and the jobs'; unset or empty, they are shown."""
    import os
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    env = {k: v for k, v in os.environ.items() if not k.startswith("TQDM_")}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(root), env.get("PYTHONPATH")]))
    if setting is not None:
        env["TQDM_DISABLE"] = setting
    script = ("from fsof_torch.io.progress import progress_bar\n"
              "assert list(progress_bar(range(3), desc='loop')) == [0, 1, 2]\n"
              "from fsof_torch import render_sequence\n"
              "render_sequence('default', 1, size=(16, 32), progress=True)\n")
    done = subprocess.run([sys.executable, "-c", script], env=env, cwd=tmp_path, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    if shown:
        assert "loop: 100%" in done.stderr and "render default: 100%" in done.stderr, done.stderr
    else:
        assert done.stderr == ""
