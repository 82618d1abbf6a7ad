"""The README's API example runs as written (it reads the shared KITTI pair)."""

import os
import re
from pathlib import Path

import torch

README = Path(__file__).resolve().parents[1] / "README.md"


def _api_example() -> str:
    text = README.read_text()
    section = text[text.index("## The API in a few examples"):]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_readme_quick_start_has_two_commands():
    text = README.read_text()
    block = re.search(r"## Quick start\n+```bash\n(.*?)```", text, re.S).group(1)
    commands = [line for line in block.splitlines() if line.strip()]
    assert len(commands) == 2
    assert "python -m refine" in commands[0] and "pytest" in commands[1]


def test_readme_api_example_runs(shared_data, capsys):
    cwd = os.getcwd()
    os.chdir(README.parent)
    try:
        namespace: dict = {}
        exec(compile(_api_example(), "README.md", "exec"), namespace)
    finally:
        os.chdir(cwd)
    refined_metrics = namespace["fs"].flow_metrics(namespace["refined"], namespace["gt"], namespace["road"],
                                                   namespace["gt_valid"])
    assert refined_metrics["e_E"] < 0.5
    assert torch.isfinite(namespace["loss"]).all()
    assert "e_E" in capsys.readouterr().out
