"""What the benchmark scripts share on their command lines: argument types that reject a bad value
while the arguments are parsed, before any work, the data folders they read, the git revision
they time against, the keyword arguments they forward and the ``--json`` file they write; and the
median time of a few calls (:func:`median_ms`).

A type here raises ``argparse.ArgumentTypeError``, so argparse exits with status 2, its usage line
and the option's name: ``argument --repeats: expected an integer >= 1, got '0'``.

The scripts import this module in ``main()``, as they do ``baseline.py``: ``tests/conftest.py``
loads a script by its path, without this folder on ``sys.path``, to test its functions.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import statistics
import subprocess
import time
from pathlib import Path
from typing import Any, Callable, Mapping

REPO = Path(__file__).resolve().parents[1]


def description(doc: str) -> str:
    """The first paragraph of a script's docstring: its ``--help`` description."""
    return doc.strip().split("\n\n")[0]


def int_at_least(minimum: int, maximum: int | None = None, why: str = "") -> Callable[[str], int]:
    """An argparse type: an integer ``>= minimum`` (and ``<= maximum`` where given; ``why``, said
    in the message, is the maximum's reason)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if maximum is not None and (value is None or not minimum <= value <= maximum):
            raise argparse.ArgumentTypeError(f"expected an integer from {minimum} to {maximum}{why}, got {text!r}")
        if value is None or value < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {text!r}")
        return value

    parse.__name__ = f"int_at_least_{minimum}"
    return parse


#: a count of things (repeats, runs, pairs, threads): at least 1
positive_int = int_at_least(1)
#: an index or a count that may be 0 (a pair index, warm-up calls)
nonnegative_int = int_at_least(0)
#: the smallest side of a synthetic image (``--size``): OpenCV's DIS needs 12 pixels, and the
#: road models' tables need a few rows of road
MIN_SIDE = 16


def image_side(text: str) -> int:
    """An argparse type: a side of a synthetic image (``--size H W``), :data:`MIN_SIDE` to the
    renderer's ``MAX_SIDE`` pixels (16 384: a side past it made the renderer raise, a traceback)."""
    from fsof_torch.data.scene.render import MAX_SIDE

    return int_at_least(MIN_SIDE, MAX_SIDE, " (the renderer's largest side)")(text)


def pair_index(text: str) -> int:
    """An argparse type: the index of a pair of a synthetic sequence, 0 to ``MAX_FRAME - 1`` (the
    renderer's frames end at ``fsof_torch.data.scene.render.MAX_FRAME``; pair i ends at frame i + 1)."""
    from fsof_torch.data.scene.render import MAX_FRAME

    return int_at_least(0, MAX_FRAME - 1, f" (the renderer's frames end at {MAX_FRAME})")(text)


def pair_count(minimum: int = 1, spacing: int = 1) -> Callable[[str], int]:
    """An argparse type: a number n >= ``minimum`` of pairs of a synthetic sequence, ``spacing``
    frames apart from pair 0 on, few enough that the last, pair ``(n - 1) * spacing``, ends within
    the renderer's frames (``MAX_FRAME``: n at most 100 000 one frame apart, 50 000 two apart)."""

    def parse(text: str) -> int:
        from fsof_torch.data.scene.render import MAX_FRAME

        apart = f"pairs {spacing} frames apart; " if spacing > 1 else ""
        why = f" ({apart}the renderer's frames end at {MAX_FRAME})"
        return int_at_least(minimum, (MAX_FRAME - 1) // spacing + 1, why)(text)

    parse.__name__ = f"pair_count_{minimum}"
    return parse


def frame_count(minimum: int = 2) -> Callable[[str], int]:
    """An argparse type: a number n >= ``minimum`` of frames of a synthetic clip, frames 0 .. n - 1
    (the pairs 0 .. n - 2, one frame apart), few enough that the last ends within the renderer's
    frames (``MAX_FRAME``: n at most 100 001)."""

    def parse(text: str) -> int:
        from fsof_torch.data.scene.render import MAX_FRAME

        return int_at_least(minimum, MAX_FRAME + 1, f" (frames from 0; the renderer's frames end at {MAX_FRAME})")(text)

    parse.__name__ = f"frame_count_{minimum}"
    return parse


def odometry_error(parser: argparse.ArgumentParser, given: tuple[float, float] | None) -> tuple[float, float] | None:
    """``--odometry-error SCALE YAW_DEG`` (None: not given) checked before any work: a finite
    SCALE within [0.5, 2] (wheel odometry's distances are off by percents; 0 or a negative scale
    would be standing still or driving backwards) and YAW_DEG degrees a frame within (-45, 45);
    else ``parser.error`` (exit 2)."""
    if given is None:
        return None
    scale, yaw_deg = given
    if not (math.isfinite(scale) and 0.5 <= scale <= 2 and math.isfinite(yaw_deg) and abs(yaw_deg) < 45):
        parser.error(f"--odometry-error: expected a scale within [0.5, 2] and degrees within (-45, 45), got "
                     f"{scale} {yaw_deg}")
    return scale, yaw_deg


def thread_count(text: str) -> int:
    """An argparse type: a number of threads, from 1 to this machine's CPUs (``os.cpu_count()``;
    far more threads than CPUs only slow a timing down, and torch crashes on a huge count)."""
    cpus = os.cpu_count() or 1
    value = int_at_least(1)(text)
    if value > cpus:
        raise argparse.ArgumentTypeError(f"expected at most {cpus} (this machine's CPUs), got {text!r}")
    return value


def scene_seed(text: str) -> int:
    """An argparse type: a synthetic scene's seed, an integer in [0, 2**62) (the library's
    ``MAX_SEED``)."""
    from fsof_torch.data.scene.config import MAX_SEED

    try:
        value = int(text)
    except ValueError:
        value = None
    if value is None or not 0 <= value < MAX_SEED:
        raise argparse.ArgumentTypeError(f"expected an integer in [0, 2**62), got {text!r}")
    return value


def finite_float(text: str) -> float:
    """An argparse type: a finite number."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def size_hw(text: str) -> tuple[int, int]:
    """An argparse type: an image size written ``HxW`` (``375x1242``) of a synthetic scene, each side
    from :data:`MIN_SIDE` (the refine job's smallest images) to the renderer's ``MAX_SIDE``."""
    from fsof_torch.data.scene.render import MAX_SIDE

    parts = text.lower().split("x")
    try:
        size = tuple(int(p) for p in parts)
    except ValueError:
        size = ()
    if len(size) != 2:
        raise argparse.ArgumentTypeError(f"expected HxW with positive sides (such as 375x1242), got {text!r}")
    if not MIN_SIDE <= min(size) <= max(size) <= MAX_SIDE:  # (past them: the job or the renderer failed late)
        raise argparse.ArgumentTypeError(f"expected HxW with sides from {MIN_SIDE} to {MAX_SIDE} (such as "
                                         f"375x1242), got {text!r}")
    return size


def json_object(text: str) -> dict:
    """An argparse type: a JSON object (keyword arguments), such as ``'{"highpass": null}'``."""
    try:
        value = json.loads(text)
    except json.JSONDecodeError as err:
        raise argparse.ArgumentTypeError(f"expected a JSON object, got {text!r} ({err})") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"expected a JSON object, got {text!r} (a {type(value).__name__})")
    return value


def shell_words(text: str) -> str:
    """An argparse type: options for another command, as a shell would split them (kept as written)."""
    try:
        shlex.split(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"cannot split {text!r} as a shell would: {err}") from None
    return text


def check_options(parser: argparse.ArgumentParser, options: Mapping[str, Any], option: str, fn: Callable,
                  reserved: tuple[str, ...] = ()) -> None:
    """``options`` (keyword arguments of ``fn``, given as ``option``) checked before any work: a
    name ``fn`` does not take, or one the script sets itself (``reserved``), and for ``fit_image`` a
    value it would refuse (``check_image_fit_options``), is ``parser.error`` (exit 2) naming
    ``option``, not a TypeError or ValueError traceback after the rendering and the first fits."""
    from fsof_torch._check import check_keywords
    from fsof_torch.estimation.image_fit import check_image_fit_options, fit_image

    try:
        if fn is fit_image:  # (its values too: '{"max_iter": -1}' raised from the first fit)
            check_image_fit_options(options, option, reserved)
        else:
            check_keywords(options, option, fn, reserved)
    except (TypeError, ValueError) as err:
        message = str(err)
        parser.error(message if message.startswith(f"{option}: ") else f"{option}: {message}")


def json_path(parser: argparse.ArgumentParser, given: str | os.PathLike | None,
              inputs: Mapping[str, Path | None] | None = None) -> Path | None:
    """``--json``'s path (None: not asked for), checked before any work, as the jobs check theirs:
    a file path, not a folder, that can be created (its missing folders are created when it is
    written, :func:`write_json`), neither one of the run's input folders (``inputs``, by option;
    None where not given) nor inside one; else ``parser.error`` (exit 2).

    The file an earlier run left there is removed at once: a run that fails later leaves no JSON
    that reads as its own result."""
    from fsof_torch.io.atomic import creation_error

    if given is None:
        return None
    path = Path(given)
    if path.is_dir():
        parser.error(f"--json: {str(path)!r} is a folder; expected a file path such as {str(path / 'out.json')!r}")
    bad = creation_error(path, "--json")
    if bad is not None:
        parser.error(bad)
    for option, folder in (inputs or {}).items():
        if folder is not None and path.resolve().is_relative_to(folder.resolve()):
            parser.error(f"--json: {str(path)!r} is inside the input {option} {str(folder)!r}; give another path")
    if path.is_file() or path.is_symlink():
        path.unlink()
    return path


def write_json(path: Path, obj: Any) -> None:
    """``obj`` written to ``path`` (checked by :func:`json_path`) as JSON, atomically, the missing
    folders above it created (NaN and infinities as null: strict JSON)."""
    from fsof_torch.io import write_json as write

    path.parent.mkdir(parents=True, exist_ok=True)
    write(path, obj)


def data_folder(parser: argparse.ArgumentParser, given: Path | None, default: Path,
                need: tuple[str, ...] = (), option: str = "--data") -> Path:
    """The folder ``option`` (``--data``) names, or ``default`` where it was not given.

    A folder given must exist and hold every one of ``need`` (``parser.error``, exit 2, naming
    ``option``, otherwise); the default may be absent: the script then leaves out what it lacks
    (:func:`present`).
    """
    if given is None:
        return default
    if given.exists() and not given.is_dir():
        parser.error(f"{option}: {str(given)!r} is a file; expected a folder")
    if not given.is_dir():
        parser.error(f"{option}: {str(given)!r} not found")
    missing = [name for name in need if not (given / name).exists()]
    if missing:
        parser.error(f"{option}: {str(given)!r} lacks {', '.join(missing)}")
    return given


def reads_data(parser: argparse.ArgumentParser, given: Path | None, skip: bool, flag: str) -> bool:
    """Whether the real data is read: not with ``flag`` (``--no-real``, ``--skip-kitti``) set,
    where a ``--data`` given as well would be dropped in silence (``parser.error``, exit 2)."""
    if skip and given is not None:
        parser.error(f"--data: {str(given)!r} is not read with {flag}; leave out one of the two")
    return not skip


def samples_folder(parser: argparse.ArgumentParser, given: Path | None, default: Path,
                   samples: Mapping[str, tuple[str, ...]]) -> Path:
    """The folder ``--data`` names, or ``default`` where it was not given, for a script that runs on
    whichever of ``samples`` (a sub-folder's name -> the files it needs) it holds.

    A folder given must exist and hold at least one of the samples whole (``parser.error``, exit
    2, naming what each lacks): a folder named by mistake is an error, not a run that skips every
    sample. The default may lack them all (the script then leaves them out, :func:`present`).
    """
    data = data_folder(parser, given, default)
    if given is None:
        return data
    lacking = []
    for name, need in samples.items():
        missing = [f for f in need if not (data / name / f).exists()]
        if not missing:
            return data
        lacking.append(f"{name}/ not found" if not (data / name).is_dir() else f"{name}/ lacks {', '.join(missing)}")
    parser.error(f"--data: {str(given)!r} holds none of the samples ({'; '.join(lacking)})")


def readable_pair(parser: argparse.ArgumentParser, folder: Path, option: str = "--data") -> None:
    """The KITTI 2015 pair in ``folder`` (``kitti15_000000``'s layout) read as the library's
    ``KittiSampleDataset`` reads it, before any work: the frames against each other and against
    the calibration's ``S_rect`` (camera 2), road.json, flow_noc_10.png against the frames (each
    where the folder has it). What it cannot read, and a road polygon that covers no pixel of the
    frames, is ``parser.error`` (exit 2) naming ``option`` and the library's message, not a
    traceback or a silent run on frames the calibration is not for."""
    from fsof_torch.datasets import KittiSampleDataset

    try:
        item = KittiSampleDataset(folder)[0]
    except (ValueError, FileNotFoundError) as err:
        parser.error(f"{option}: {err}")
    if item.get("road") is not None:
        road_covers(parser, item["road"], option)


def readable_clip(parser: argparse.ArgumentParser, folder: Path, option: str = "--data", poses: bool = False) -> None:
    """The KITTI odometry clip in ``folder`` (``kitti_odometry_straight``'s layout) read as the
    library's ``ImageFolderDataset`` reads it, before any work: the calibration's camera, every
    frame against the first, road.json at the frames' size (a polygon that covers some of them)
    and, with ``poses``, poses.txt. What it cannot read is ``parser.error`` (exit 2) naming
    ``option`` and the library's message, not a traceback after the parts that come before the
    clip's."""
    from fsof_torch import read_kitti_poses
    from fsof_torch.datasets import ImageFolderDataset
    from fsof_torch.io import read_road_mask

    try:
        frames = ImageFolderDataset(folder / "image_l", folder / "calib.txt", cam=0, ground_truth=False)
        for i in range(len(frames)):
            size = tuple(frames[i]["image1"].shape[-2:])
        road = read_road_mask(folder / "road.json", size)
        if poses:
            read_kitti_poses(folder / "poses.txt")
    except (ValueError, FileNotFoundError) as err:
        parser.error(f"{option}: {err}")
    road_covers(parser, road, option)


def road_covers(parser: argparse.ArgumentParser, road: Any, option: str) -> None:
    """A road mask (..., H, W) from road.json that covers no pixel of its frames (a polygon drawn
    for other frames) is ``parser.error`` naming ``option``: the figures over the road would be
    means over no pixel."""
    if not bool(road.any()):
        rows, cols = road.shape[-2:]
        parser.error(f"{option}: road.json: its road polygon covers no pixel of the {rows} x {cols} frames")


def present(folder: Path, need: tuple[str, ...], what: str) -> bool:
    """Whether ``folder`` holds every one of ``need``; if not, prints ``<what> absent: skipped``
    and what is missing."""
    if not folder.is_dir():
        print(f"{what} absent: skipped ({folder} not found)")
        return False
    missing = [name for name in need if not (folder / name).exists()]
    if missing:
        print(f"{what} absent: skipped ({folder} lacks {', '.join(missing)})")
        return False
    return True


def baseline_revision(parser: argparse.ArgumentParser, given: str | None, default: str | None = None,
                      paths: tuple[str, ...] = ("fsof_torch",)) -> str | None:
    """The git revision to time against, checked before any work; ``None``: no baseline.

    ``given`` is ``--baseline``'s value, ``None`` where it was not given (then ``default``);
    ``none`` means no baseline. A revision given that is no commit of this repository holding
    ``paths`` is an error (``parser.error``, exit 2); the default, where git or the revision is
    unavailable (outside a git checkout, a shallow clone), gives no baseline and a note.
    """
    rev = default if given is None else given
    if rev is None or rev.lower() == "none":
        return None
    problem = None
    for spec in (f"{rev}^{{commit}}", *(f"{rev}:{p}" for p in paths)):
        try:
            done = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--verify", "--quiet", spec],
                                  capture_output=True, text=True)
        except OSError as err:
            problem = f"git: {err}"
            break
        if done.returncode != 0:
            problem = done.stderr.strip() or (f"no {spec.split(':')[1]}/ in it" if ":" in spec else "not a commit")
            break
    if problem is None:
        return rev
    if given is not None:
        parser.error(f"--baseline: cannot use revision {rev!r} of {REPO}: {problem}")
    print(f"(no baseline: the default revision {rev!r} is unavailable here: {problem})")
    return None


def median_ms(fn: Callable[[], Any], repeat: int = 3) -> float:
    """The median wall time of ``repeat`` calls of ``fn``, in milliseconds."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)
