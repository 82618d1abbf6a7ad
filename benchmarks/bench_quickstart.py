"""Wall and CPU time of the Quick start job, ``python -m refine`` with no arguments, on a loaded
machine: two runs side by side, each started with no arguments in its own fresh working folder
(so each writes its own ``refine_out/synthetic-default/``), as a user meets it when another job
shares the cores.

Each run is measured with ``/usr/bin/time -v`` (wall clock, and user + system CPU of the process
and its children). Prints one row per run and the machine's core count. The job's defaults decide
what is measured (sources, odometry variants, figures, one intra-op thread), so rerun this after
changing them.

Run: ``python benchmarks/bench_quickstart.py [--runs 2] [--args "..."]``; ``--args`` takes the
job's options as one string, split as a shell would, even a single option
(``--args "--no-figures"``, or ``--args=--no-figures``). A run that fails is reported by its number
with the end of its error output, and the script exits 1.
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _parse(text: str) -> dict[str, float]:
    """Wall seconds and user + system CPU seconds from ``/usr/bin/time -v``'s report."""
    user = float(re.search(r"User time \(seconds\): ([\d.]+)", text).group(1))
    system = float(re.search(r"System time \(seconds\): ([\d.]+)", text).group(1))
    wall = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): ([\d:.]+)", text).group(1)
    seconds = 0.0
    for part in wall.split(":"):
        seconds = seconds * 60 + float(part)
    rss = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", text).group(1))
    return {"wall_s": seconds, "cpu_s": user + system, "user_s": user, "sys_s": system, "max_rss_mb": rss / 1024}


def _joined(argv: list[str]) -> list[str]:
    """``argv`` with ``--args VALUE`` written ``--args=VALUE``: argparse takes a separate value that
    looks like an option (``--args "--no-figures"``) for an option of its own."""
    out, rest = [], list(argv)
    while rest:
        word = rest.pop(0)
        out.append(f"--args={rest.pop(0)}" if word == "--args" and rest else word)
    return out


def main(argv: list[str] | None = None) -> int:
    from cli import description, positive_int, shell_words

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--runs", type=positive_int, default=2, help="runs started side by side (default 2)")
    parser.add_argument("--args", type=shell_words, default="",
                        help='extra options for each run, one string split as a shell would ("--no-figures '
                             '--num-pairs 2"; default: none, the Quick start)')
    args = parser.parse_args(_joined(sys.argv[1:] if argv is None else argv))
    time_bin = shutil.which("time") or "/usr/bin/time"
    if not Path(time_bin).is_file():
        print("needs /usr/bin/time (GNU time)", file=sys.stderr)
        return 2
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    with tempfile.TemporaryDirectory() as tmp:
        procs = []
        env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
        for i in range(args.runs):
            cwd = Path(tmp) / f"run{i}"
            cwd.mkdir()
            cmd = [time_bin, "-v", sys.executable, "-m", "refine", *shlex.split(args.args)]
            procs.append(subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.DEVNULL,
                                          stderr=subprocess.PIPE, text=True))
        errors = [p.communicate()[1] for p in procs]  # (every run waited for before the folder goes)
    failed = [(i, p.returncode) for i, p in enumerate(procs) if p.returncode != 0]
    for i, code in failed:
        # the job's own output, without time's report after it
        job = re.split(r"Command exited with non-zero status|Command terminated by signal|\tCommand being timed:",
                       errors[i])[0]
        print(f"run {i} of {args.runs} failed (exit status {code}): python -m refine {args.args}\n"
              f"{job[-2000:].rstrip()}", file=sys.stderr)
    if failed:
        return 1
    rows = [_parse(err) for err in errors]
    print(f"python -m refine {args.args} ({args.runs} runs side by side, {os.cpu_count()} cores)")
    print(f"{'run':>4} {'wall s':>8} {'CPU s':>8} {'user s':>8} {'sys s':>7} {'max RSS MB':>11}")
    for i, r in enumerate(rows):
        print(f"{i:>4} {r['wall_s']:>8.1f} {r['cpu_s']:>8.1f} {r['user_s']:>8.1f} {r['sys_s']:>7.1f} {r['max_rss_mb']:>11.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
