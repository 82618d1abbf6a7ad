"""Peak memory of the refine job on clips of user images of growing length, one thread.

Writes a clip of the synthetic ``default`` scene (as many frames as the longest of ``--lengths``,
at ``--size``) in the layout of a folder of your own (``images/``, ``calib.txt``, ``road/``;
docs/jobs.md), then runs, for each length, the job on the clip's first frames as a user would::

    python -m refine --images DIR/images --calib DIR/calib.txt --road DIR/road \\
        --height H --roll-deg R --pitch-deg P --source dis --odometry sequence \\
        --no-figures --no-progress --threads 1 --out OUT

(DIS flow, the clip's road motion from its images), each in its own process with
OMP_NUM_THREADS=1, and prints its peak resident memory (``ru_maxrss`` of that process, as
``/usr/bin/time -v`` reports it) with the ratio to the shortest clip's, and its wall time; and,
in this process, the median time to read one pair (``ImageFolderDataset``: two PNG images and a
road mask), which the clip's streamed fit does three times per pair.

``--baseline REV`` runs the job of another git revision (its ``fsof_torch`` and ``refine``
extracted with ``git archive``) on the same clips, after the current one.

    python benchmarks/clip_memory.py [--lengths 11 26 51] [--size 375x1242] [--keep DIR] [--baseline REV]

``--keep DIR`` (a new or empty folder) keeps the clip there.
"""

from __future__ import annotations

import argparse
import io
import math
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def write_clip(root: Path, frames: int, size: tuple[int, int], seed: int) -> list[str]:
    """Frames 000000.png ... of the default scene, calib.txt, one road PNG per pair; returns the
    job's mounting options (the scene's camera)."""
    import torch

    from fsof_torch.data.scene import render_pair
    from fsof_torch.io import write_image, write_kitti_calibration, write_road_mask

    for d in ("images", "road"):
        (root / d).mkdir(parents=True, exist_ok=True)
    camera = None
    for i in range(frames - 1):  # pair i: frames i and i + 1 (consecutive pairs share a frame)
        pair = render_pair("default", i, seed=seed, size=size)
        if i == 0:
            write_image(root / "images" / f"{i:06d}.png", pair["image1"])
            camera = pair["camera"]
        write_image(root / "images" / f"{i + 1:06d}.png", pair["image2"])
        write_road_mask(root / "road" / f"{i:06d}.png", pair["road"])
    write_kitti_calibration(root / "calib.txt", camera.K[0].to(torch.float64), cam=0, style="odometry")
    return ["--height", repr(float(camera.height[0])), "--roll-deg", repr(math.degrees(float(camera.roll[0]))),
            "--pitch-deg", repr(math.degrees(float(camera.pitch[0])))]


def prefix(clip: Path, root: Path, frames: int) -> None:
    """A clip of the first ``frames`` frames of ``clip`` (symbolic links, to absolute paths: a
    relative target would be read from the link's own folder)."""
    clip = clip.resolve()
    for d in ("images", "road"):
        (root / d).mkdir(parents=True)
        for f in sorted((clip / d).iterdir())[:frames if d == "images" else frames - 1]:
            (root / d / f.name).symlink_to(f)
    (root / "calib.txt").symlink_to(clip / "calib.txt")


def extract(rev: str, folder: Path) -> Path:
    """``fsof_torch/`` and ``refine/`` of git revision ``rev`` in ``folder``."""
    archive = subprocess.run(["git", "-C", str(REPO), "archive", rev, "fsof_torch", "refine"],
                             capture_output=True, check=True).stdout
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(folder, filter="data")
    return folder


def read_time(clip: Path, mounting: list[str], pairs: int = 10) -> float:
    """Median seconds to read one pair of the clip as the job does (one thread)."""
    import statistics

    import torch

    from fsof_torch.datasets import ImageFolderDataset

    torch.set_num_threads(1)
    m = dict(zip(mounting[::2], (float(v) for v in mounting[1::2])))
    dataset = ImageFolderDataset(clip / "images", clip / "calib.txt", camera_height=m["--height"],
                                 roll=math.radians(m["--roll-deg"]), pitch=math.radians(m["--pitch-deg"]),
                                 road=clip / "road", camera_dtype=torch.float64)
    times = []
    for i in range(min(pairs, len(dataset))):
        t = time.perf_counter()
        dataset[i]
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def run_job(code: Path, clip: Path, out: Path, mounting: list[str]) -> tuple[float, float]:
    """The job of the package in ``code`` on ``clip``: (peak RSS in MB, wall seconds)."""
    argv = [sys.executable, "-m", "refine", "--images", str(clip / "images"), "--calib", str(clip / "calib.txt"),
            "--road", str(clip / "road"), *mounting, "--source", "dis", "--odometry", "sequence",
            "--no-figures", "--no-progress", "--threads", "1", "--out", str(out)]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(code)}
    with tempfile.TemporaryFile() as err:
        t = time.perf_counter()
        # the job's own package: `python -m` puts the working folder first on the path
        proc = subprocess.Popen(argv, cwd=code, env=env, stdout=subprocess.DEVNULL, stderr=err)
        _, status, usage = os.wait4(proc.pid, 0)  # this process's own peak, not all children's
        wall = time.perf_counter() - t
        proc.returncode = os.waitstatus_to_exitcode(status)
        if proc.returncode != 0:
            err.seek(0)
            raise RuntimeError(f"the job failed ({proc.returncode}):\n{err.read().decode()}")
    return usage.ru_maxrss / 1024, wall  # ru_maxrss: KiB on Linux


def main(argv: list[str] | None = None) -> int:
    from cli import baseline_revision, description, frame_count, scene_seed, size_hw

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--lengths", type=frame_count(3), nargs="+", default=[11, 26, 51],
                        help="clip lengths in frames, each from 3 to 100 001 (frames 0 to 100 000, the "
                             "renderer's last) (default 11 26 51)")
    parser.add_argument("--size", type=size_hw, default=(375, 1242), metavar="HxW",
                        help="HxW, each side from 16 to 16384 (default: KITTI's)")
    parser.add_argument("--seed", type=scene_seed, default=0, help="the scene's seed, in [0, 2**62) (default 0)")
    parser.add_argument("--keep", type=Path, default=None, metavar="DIR",
                        help="write the clip here (kept) instead of a temporary folder: a new or empty folder, "
                             "so that no earlier clip's frames mix in")
    parser.add_argument("--baseline", default=None, metavar="REV", help="also run the job of this git revision")
    args = parser.parse_args(argv)
    if args.keep is not None:
        from fsof_torch.io.atomic import creation_error

        if args.keep.exists() and not args.keep.is_dir():
            parser.error(f"--keep: {str(args.keep)!r} is a file; expected a new or empty folder")
        if args.keep.is_dir() and any(args.keep.iterdir()):
            parser.error(f"--keep: {str(args.keep)!r} is not empty; expected a new or empty folder (an earlier "
                         f"clip's frames would mix with this one's)")
        bad = creation_error(args.keep, "--keep")
        if bad is not None:
            parser.error(bad)
    args.baseline = baseline_revision(parser, args.baseline, paths=("fsof_torch", "refine"))
    size = args.size
    work = Path(tempfile.mkdtemp(prefix="clip_memory_"))
    try:
        clip = args.keep if args.keep is not None else work / "clip"
        print(f"writing a clip of {max(args.lengths)} frames at {size[0]}x{size[1]} to {clip} ...", flush=True)
        mounting = write_clip(clip, max(args.lengths), size, args.seed)
        codes = {"current": REPO}
        if args.baseline is not None:
            codes[args.baseline] = extract(args.baseline, work / "baseline")
        rows = []
        for label, code in codes.items():
            for n in sorted(args.lengths):
                part = work / f"clip{n}"
                if not part.exists():
                    prefix(clip, part, n)
                rss, wall = run_job(code, part, work / f"out-{label}-{n}", mounting)
                rows.append((label, n, rss, wall))
                print(f"  {label}: {n} frames: {rss:.0f} MB, {wall:.1f} s", flush=True)
        print(f"\nreading one pair: {1e3 * read_time(clip, mounting):.1f} ms (median of 10)")
        print(f"refine job, --odometry sequence, DIS, {size[0]}x{size[1]}, one thread")
        print(f"{'code':>10} {'frames':>6} {'peak RSS MB':>11} {'ratio':>6} {'wall s':>7} {'s/pair':>6}")
        for label, n, rss, wall in rows:
            first = next(r for r in rows if r[0] == label)[2]
            print(f"{label:>10} {n:6d} {rss:11.0f} {rss / first:6.2f} {wall:7.1f} {wall / (n - 1):6.2f}")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
