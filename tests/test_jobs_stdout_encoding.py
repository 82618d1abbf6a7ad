"""The jobs print their tables (Δ%, σ, °) to a stdout whose encoding may lack those characters: a
stdout redirected to a file on Windows writes cp1252, ``PYTHONIOENCODING=ascii`` ASCII. Once its
files were written, ``refine`` then ended with ``error: 'charmap' codec can't encode character
'\\u0394' ...`` and exit status 2 (a bad input, it said), ``eval noise`` with a traceback. Now such
a character is printed as its escape, as Python prints to stderr, and the run succeeds."""

from __future__ import annotations

import io
import sys

import pytest

from eval.__main__ import main as eval_main
from fsof_torch.io.progress import tolerant_stdout
from refine.__main__ import main as refine_main


def cp1252_stdout(monkeypatch) -> io.TextIOWrapper:
    """A stdout that writes cp1252 (set inside the test: pytest sets its capture at the call)."""
    stream = io.TextIOWrapper(io.BytesIO(), encoding="cp1252", errors="strict")
    monkeypatch.setattr(sys, "stdout", stream)
    return stream


def _printed(stream: io.TextIOWrapper) -> str:
    stream.flush()
    return stream.buffer.getvalue().decode("cp1252")


def test_refine(tmp_path, monkeypatch):
    stdout = cp1252_stdout(monkeypatch)
    assert refine_main(["--num-pairs", "1", "--size", "48x160", "--source", "dis", "--odometry", "given",
                        "--no-figures", "--no-progress", "--out", str(tmp_path / "out")]) == 0
    printed = _printed(stdout)
    assert "| road before | after | \\u0394% | all before | after | \\u0394% |" in printed, printed
    assert stdout.errors == "strict"  # (restored)


def test_eval_noise(tmp_path, monkeypatch):
    stdout = cp1252_stdout(monkeypatch)
    assert eval_main(["noise", "--quick", "--trials", "1", "--no-plots", "--no-progress",
                      "--out", str(tmp_path / "n")]) == 0
    printed = _printed(stdout)
    assert "\\u03c3 px" in printed and printed.rstrip().endswith(f"wrote {tmp_path / 'n' / 'noise.json'}")
    assert stdout.errors == "strict"


def test_tolerant_stdout_leaves_other_streams(monkeypatch):
    """A stdout without ``reconfigure`` (a notebook's) is left as it is; an error inside comes out."""
    class Plain(io.StringIO):
        pass

    monkeypatch.setattr(sys, "stdout", Plain())
    with pytest.raises(RuntimeError, match="inside"):
        with tolerant_stdout():
            print("Δ")
            raise RuntimeError("inside")
    assert sys.stdout.getvalue() == "Δ\n"
