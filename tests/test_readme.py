"""The README works as a user meets it: its first Python example runs from an empty folder (no
data, no ../shared), its Quick start is two commands, CI runs its test command, and the front
door stays short and free of files a user does not have."""

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


def _first_python_block(text: str) -> str:
    return re.search(r"```python\n(.*?)```", text, re.S).group(1)


def _quick_start_commands(text: str) -> list[str]:
    block = re.search(r"## Quick start\n+```bash\n(.*?)```", text, re.S).group(1)
    return [line.strip() for line in block.splitlines() if line.strip()]


def test_readme_quick_start_has_two_commands():
    commands = _quick_start_commands(README.read_text())
    assert len(commands) == 2
    assert "pip install" in commands[0] and commands[0].endswith("python -m refine")
    assert "pip install" in commands[1] and "pytest" in commands[1]


def test_ci_runs_the_readme_test_command():
    """.ci/run's last command is the README's test command, character for character."""
    test_command = _quick_start_commands(README.read_text())[1]
    lines = [line.strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()]
    commands = [line for line in lines if line and not line.startswith("#")]
    assert commands[-1] == test_command


def test_readme_first_python_example_runs_in_an_empty_folder(tmp_path):
    """The first ```python block, run as a script from an empty folder without ../shared."""
    assert not (tmp_path.parent / "shared").exists()
    script = tmp_path / "example.py"
    script.write_text(_first_python_block(README.read_text()))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    out = done.stdout
    # the fit recovers the scene's forward motion (the renderer's odometry, independent of the model)
    fitted, true = (float(x) for x in re.search(r"fitted z_d ([\d.]+) m, true ([\d.]+) m", out).groups())
    assert abs(fitted - true) < 0.01 * true
    # refinement lowers the road's end-point error of the noisy prediction
    epe = {name: float(v) for name, v in re.findall(r"(before|after): road EPE ([\d.]+) px", out)}
    assert set(epe) == {"before", "after"}
    assert epe["after"] < 0.5 * epe["before"]


def test_readme_is_a_front_door():
    text = README.read_text()
    assert len(text.splitlines()) <= 350
    for image in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text):
        assert (ROOT / image).is_file(), image


def test_user_docs_mention_no_files_users_lack():
    """README and docs/ speak to users: no design notes, no commit hashes, no acceptance targets."""
    banned = re.compile(r"DESIGN\.md|CONVENTIONS\.md|SOURCE\.md|git show|issue's target|"
                        r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")
    for page in [README, *sorted((ROOT / "docs").glob("*.md"))]:
        hits = [(n, m.group(0)) for n, line in enumerate(page.read_text().splitlines(), 1)
                for m in banned.finditer(line)]
        assert not hits, f"{page.relative_to(ROOT)}: {hits}"
