"""What the job works on, and where it comes from: image pairs loaded through the library's
datasets (a rendered sequence, a folder of your images, the shared KITTI samples), whose items
follow the one item contract of ``fsof_torch.data.items`` (``image1``, ``image2``, ``camera``,
``flow``, ``valid``, ``road``, ``odometry``, ``relative_pose``, ...).

What stays here is the job's own: checking its options (a bad one exits 2 with a ``JobError``
naming the option and the file: the datasets' errors name their argument, and are renamed to the
option that gave it), matching ``--flows`` to the pairs by name (the datasets' matcher), and each
pair's identity for resuming (the contents of its files, its poses). Pairs load lazily, so a
resumed run does not read or render finished pairs (but the clip's fit, ``refine.calibrate``,
reads every pair again); everything that can be checked without loading every pair is checked
before any work (the datasets check it when they are made).
"""

from __future__ import annotations

import hashlib
import inspect
import math
import os
import re
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

import torch
from torch import Tensor

from fsof_torch import Camera
from fsof_torch.refinement.auto_road import detect_road
from fsof_torch.datasets import ImageFolderDataset
from fsof_torch.data.folders import kitti_flow_layout, list_images  # noqa: F401 (the job's clip test)


class JobError(Exception):
    """A problem with the job's inputs or options: reported as ``error: ...`` with exit code 2."""


def permission_message(err: PermissionError, paths: dict[str, Path | None], outputs: tuple[str, ...] = ()) -> str:
    """The one-line message of a job (exit 2) for a file or folder the process may not read or
    write (``err``, as ``open()``, ``os.listdir`` or a look-up raise it), naming the option whose
    path it is or lies in: ``paths`` maps the job's path options to their paths (None: not given),
    ``outputs`` names those of them that are written (the others are read). Where ``err`` names
    no file (a writer's own message, naming its target), its message as it is."""
    if err.filename is None:
        return (err.strerror if err.errno is not None and err.strerror else str(err)).removeprefix("path: ")
    name = os.fsdecode(err.filename)
    target = Path(os.path.abspath(name))
    holders = [(option, Path(os.path.abspath(path))) for option, path in paths.items() if path is not None]
    holders = [(option, path) for option, path in holders if target == path or target.is_relative_to(path)]
    if not holders:
        return f"{name!r}: permission denied"
    option = max(holders, key=lambda held: len(held[1].parts))[0]  # (the deepest: a file of --flows inside --images' folder)
    done = "written" if option in outputs else "read"
    return f"{option}: {name!r} cannot be {done}: permission denied; give the process access to it, or give another path"


@dataclass
class PairSpec:
    """One image pair of the job, loaded on demand.

    ``load()`` returns the dataset's item (``fsof_torch.data.items``: ``image1``, ``image2``
    (3, H, W) float32 0..255, ``camera`` (batch 1, float64), ``flow``/``valid`` ground truth,
    ``road`` (None: detected), ``odometry``, ``relative_pose``, ...). ``identity()`` describes
    the pair's inputs (file contents, poses, render index) for the resume fingerprint. Known
    without loading, where the input has them: ``frames``, the stems of its two image files, and
    ``poses``, its two frames' camera-to-world poses (2, 4, 4) float64 (for the clip's checks,
    ``refine.calibrate.check_clip``).
    """

    name: str
    load: Callable[[], dict[str, Any]]
    flow_files: dict[str, Path] = field(default_factory=dict)
    identity: Callable[[], dict[str, Any]] = dict
    frames: tuple[str, str] | None = None
    poses: Tensor | None = None


#: the digests :func:`file_digest` took within :func:`digests_read_once`, by path; None outside it
_read_once: dict[str, str] | None = None


def special_input(path: Path | None, option: str) -> str | None:
    """Why the input ``path`` (an option's file or folder, or a file of its folder; None: not
    given) cannot be read: a FIFO, device or socket (:func:`fsof_torch.io.atomic.special_file`),
    which the job's readers took for a missing file ("no file at"), a folder, or a sample's
    missing file; the message names ``option``. None where it is a file, a folder or nothing."""
    from fsof_torch.io.atomic import special_file

    special = special_file(path) if path is not None else None
    if special is None:
        return None
    return f"{option}: {str(path)!r} is {special}, not a regular file; give a file (or folder) the job can read"


def file_digest(path: Path) -> str:
    """BLAKE2b of a file's bytes (hex, 32 characters): the file's identity for resuming. Within
    :func:`digests_read_once`, a file's digest taken there before is taken again from memory."""
    if _read_once is None:
        return _read_digest(path)
    key = os.fspath(path)
    if key not in _read_once:
        _read_once[key] = _read_digest(path)
    return _read_once[key]


@contextmanager
def digests_read_once() -> Iterator[None]:
    """Within it, :func:`file_digest` reads each file once: a clip's frame is the second image of
    one pair and the first of the next, whose identities both digest it (a long clip's frames take
    seconds to read). The same digests as without it, so the same identities."""
    global _read_once
    outer = _read_once
    _read_once = {} if outer is None else outer
    try:
        yield
    finally:
        _read_once = outer


def _read_digest(path: Path) -> str:
    """:func:`file_digest`, read from the file."""
    h = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def odometry_from_pose(cam1_T_cam0: Tensor, camera: Camera) -> dict[str, float]:
    """The planar ego-motion (x_d, z_d, yaw) of a relative camera pose (4, 4), under the camera's
    mounting (its roll and pitch relate camera and vehicle frames)."""
    from fsof_torch import ego_motion_from_pose

    ego = ego_motion_from_pose(cam1_T_cam0.to(torch.float64).unsqueeze(0), camera.to(torch.float64))
    return {"x_d": float(ego.x_d[0]), "z_d": float(ego.z_d[0]), "yaw": float(ego.yaw[0])}


# -- the datasets' errors as the job's -------------------------------------------------------------

#: a user folder's dataset arguments -> the options that give them
USER_OPTIONS = {"images": "--images", "calib": "--calib", "cam": "--cam", "poses": "--poses", "road": "--road",
                "gt": "--gt", "calib_size": "--calib-size", "camera_height": "--height"}


@contextmanager
def options_of(options: dict[str, str] | str) -> Iterator[None]:
    """Re-raise a dataset's error (``"<argument>: ..."``) as a JobError naming the option that gave
    the argument: ``options`` maps arguments to options, or is one option for every argument."""
    try:
        yield
    except (ValueError, TypeError, FileNotFoundError, IsADirectoryError) as err:
        argument, sep, rest = str(err).partition(": ")
        if not (sep and re.fullmatch(r"[a-z_0-9]+", argument)):
            raise  # not a message about an argument: raised as it came (the job's main reports
            # a ValueError or FileNotFoundError with exit 2, anything else as a traceback)
        # a reader's own argument inside the dataset's ("poses: path: line 2 of ...") means nothing to the user
        rest = rest.removeprefix("path: ")
        if isinstance(options, str):
            raise JobError(f"{options}: {argument}: {rest}") from None
        if argument not in options:
            raise
        raise JobError(f"{options[argument]}: {rest.replace('calib_size=(H, W)', '--calib-size HxW')}") from None


def _spec(name: str, dataset, i: int, options: dict[str, str] | str, identity: Callable[[], dict[str, Any]],
          flow_files: dict[str, Path] | None = None) -> PairSpec:
    def load() -> dict[str, Any]:
        with options_of(options):
            return dataset[i]
    frames = poses = None
    if isinstance(dataset, ImageFolderDataset):  # a folder's: its files and poses are known without loading
        p = dataset.pairs[i]
        frames = (p.image1.stem, p.image2.stem)
        if dataset.poses is not None:
            poses = torch.stack([dataset.poses[p.frame1], dataset.poses[p.frame2]]).to(torch.float64)
    return PairSpec(name, load, flow_files or {}, identity, frames, poses)


def _dataset_digests(dataset: ImageFolderDataset) -> dict[str, str]:
    """The contents of the files ``dataset`` read when it was built, and holds since: its
    calibration and the clip's one road file (a polygon or a mask), by role. Taken right after it
    is built, for :func:`_file_identity`: taken when each pair was checked, later in the run, a
    file edited meanwhile gave the records of later pairs its new digest over results of the
    contents the dataset had read, and a rerun reused them as results of the new file."""
    files = {"road": dataset.road_file, "calib": dataset.calib}
    return {k: file_digest(f) for k, f in files.items() if f is not None}


def _file_identity(dataset: ImageFolderDataset, i: int, read: dict[str, str],
                   flow: Path | None = None) -> Callable[[], dict[str, Any]]:
    """The pair's identity for resuming: the contents of its images, flow, ground-truth, road
    (its own mask, read with the pair, or the dataset's one polygon) and calibration files (those
    the dataset read when it was built: ``read``, :func:`_dataset_digests`), and its two poses (a
    changed file or pose redoes the pair)."""
    def describe() -> dict[str, Any]:
        p = dataset.pairs[i]
        files = {"image1": p.image1, "image2": p.image2, "flow": flow, "gt": p.gt, "road": p.road}
        digests = {**read, **{k: file_digest(f) for k, f in files.items() if f is not None}}
        P = dataset.poses
        return {"files": digests,
                "poses": torch.cat([P[p.frame1].flatten(), P[p.frame2].flatten()]).tolist() if P is not None else None}
    return describe


MIN_SIDE = 16  # pixels: DIS needs 12; --size asks for 16
#: pixels: ``--road auto``'s detection (``detect_road``, which estimates the motion) starts on the
#: images averaged over 2 x 2 pixels (its ``seed_level=1``), which needs 16 of them a side
AUTO_ROAD_MIN_SIDE = 32


def check_image_size(dataset: ImageFolderDataset, option: str, road_auto: bool = False) -> None:
    """The pairs' images (the first pair's size: the others must match it) have sides of at least
    ``MIN_SIDE`` pixels, as ``--size`` asks of the synthetic scenes: DIS and the road's fits need
    them (with ``road_auto``, :data:`AUTO_ROAD_MIN_SIDE`). Else a JobError naming ``option``, the
    file and its size."""
    H, W = dataset.size
    first = dataset.pairs[0].image1
    if min(H, W) < MIN_SIDE:
        raise JobError(f"{option}: {str(first)!r} is {H}x{W}; the job needs images with sides of at least "
                       f"{MIN_SIDE} pixels")
    if road_auto:
        check_auto_road_size((H, W), repr(str(first)))


def check_auto_road_size(size: tuple[int, int], what: str) -> None:
    """``--road auto`` needs images with sides of at least :data:`AUTO_ROAD_MIN_SIDE` pixels, else a
    JobError naming ``--road`` and ``what`` (the images: a file, or the scene's size), before any
    work (the detection raised on the first pair: 'seed_level: 1 leaves fewer than 16 pixels')."""
    H, W = size
    if min(H, W) < AUTO_ROAD_MIN_SIDE:
        raise JobError(f"--road: auto finds the road on images with sides of at least {AUTO_ROAD_MIN_SIDE} pixels "
                       f"(its first estimate works on them at half size); {what} is {H}x{W}: give larger "
                       f"images, or the road instead of auto")


def check_road_has_pixels(dataset: ImageFolderDataset, road: str) -> None:
    """A given road (``--road``: one file, or a folder of masks) holds a road pixel inside the
    images for some pair; else a JobError naming ``--road``, before any work: every pair would be
    left unrefined. Reads the masks up to the first with a pixel (mostly one file). A mask that
    cannot be read, or has another size, is left to its pair's load to name; pairs whose own
    mask alone is empty are named in the report's notes (``refine.report.unmeasured_notes``)."""
    from fsof_torch.io import read_road_mask

    H, W = dataset.size
    files = [dataset.road_file] if dataset.road_file is not None else [p.road for p in dataset.pairs]
    for f in files:
        try:  # a polygon is drawn at the images' size, as the dataset draws it
            mask = read_road_mask(f, (H, W) if f.suffix.lower() == ".json" else None)
        except (ValueError, TypeError, OSError):
            return
        if tuple(mask.shape[-2:]) != (H, W) or bool(mask.any()):
            return
    which = "" if dataset.road_file is not None else f" (the masks of all {len(files)} pairs are empty)"
    raise JobError(f"--road: {road!r} holds no road pixel inside the {H}x{W} images{which}, so no pair could "
                   f"be refined; give masks or a polygon that cover the road, or --road auto")


# -- synthetic -----------------------------------------------------------------------------------

def synthetic_pairs(preset: str, num_pairs: int, *, seed: int, size: tuple[int, int] | None,
                    road: str | None, noise: float | None = None) -> list[PairSpec]:
    """Pairs of a rendered sequence (``fsof_torch.datasets.SceneDataset``), with the scene's exact
    ground truth, road mask and odometry (``road="auto"``: the job detects the road instead, see
    ``refine.job.road_mask``); ``noise`` overrides the preset's sensor noise (grey levels at
    375×1242)."""
    from fsof_torch import scene
    from fsof_torch.datasets import SceneDataset

    if preset not in scene.PRESETS:
        raise JobError(f"--preset: unknown preset {preset!r}; choose from {', '.join(sorted(scene.PRESETS))}")
    from fsof_torch.data.scene.render import MAX_FRAME

    if not 1 <= num_pairs <= MAX_FRAME:  # (the scenes' frames end at MAX_FRAME)
        raise JobError(f"--num-pairs: expected 1 to {MAX_FRAME}, got {num_pairs}")
    if noise is not None and not noise >= 0:
        raise JobError(f"--scene-noise: expected >= 0 grey levels, got {noise}")
    if road == "auto" and size is not None:
        check_auto_road_size(size, "--size")
    overrides = {} if noise is None else {"noise": float(noise)}
    with options_of({"size": "--size", "seed": "--seed", "noise": "--scene-noise"}):
        dataset = SceneDataset(preset, num_pairs, seed=seed, size=size, camera_dtype=torch.float64, **overrides)
    # the scene and its options are in the run's fingerprint; a pair is its index
    return [_spec(f"{i:06d}", dataset, i, {"size": "--size"}, lambda i=i: {"index": i}) for i in range(num_pairs)]


# -- user data -----------------------------------------------------------------------------------

def check_mounting(height: float, roll_deg: float = 0.0, pitch_deg: float = 0.0, road_auto: bool = False) -> None:
    """``--height`` (m, > 0; with ``road_auto``, above the kerb ``detect_road`` tests for, its
    ``min_height_m``), ``--roll-deg`` and ``--pitch-deg``: finite, the angles within ±90°
    (as the camera takes them: upright and facing the road), checked before any dataset is built
    (so that a bad value is named by its own option, in its own unit)."""
    for name, value in (("--height", height), ("--roll-deg", roll_deg), ("--pitch-deg", pitch_deg)):
        if not math.isfinite(value):
            raise JobError(f"{name}: expected a finite number, got {value}")
    if not height > 0:
        raise JobError(f"--height: expected > 0 m, got {height}")
    kerb = inspect.signature(detect_road).parameters["min_height_m"].default
    if road_auto and not height > kerb:  # (the detection raised on the first pair, naming its min_height_m)
        raise JobError(f"--height: --road auto tests for kerbs {kerb} m high, below the camera: expected a camera "
                       f"higher than {kerb} m above the road, got {height}")
    for name, value in (("--roll-deg", roll_deg), ("--pitch-deg", pitch_deg)):
        if not abs(value) < 90:
            raise JobError(f"{name}: expected an angle between -90 and 90 degrees (a camera upright and facing "
                           f"the road), got {value:g}")


def user_pairs(*, images: Path, calib: Path, cam: int | None, height: float, roll_deg: float,
               pitch_deg: float, poses: Path | None, flows: Path | None, road: str | None,
               gt: Path | None, calib_size: tuple[int, int] | None = None) -> tuple[list[PairSpec], Camera]:
    """Pairs of consecutive images of a folder (``fsof_torch.datasets.ImageFolderDataset``) with
    the options' inputs, checked before any work: files matched by name, poses rigid and enough,
    the road file readable, the first pair's size against the calibration (the others when they
    load)."""
    from fsof_torch.data.folders import match_files

    check_mounting(height, roll_deg, pitch_deg, road_auto=road == "auto")
    if road is None:
        raise JobError("--road: user data needs road masks: a folder of PNGs, a polygon JSON, or 'auto'")
    with options_of(USER_OPTIONS):
        dataset = ImageFolderDataset(images, calib, cam=cam, camera_height=height, roll=math.radians(roll_deg),
                                     pitch=math.radians(pitch_deg), poses=poses,
                                     road=None if road == "auto" else road, gt=gt, calib_size=calib_size,
                                     camera_dtype=torch.float64)
    read = _dataset_digests(dataset)
    check_image_size(dataset, "--images", road_auto=road == "auto")
    if road != "auto":
        check_road_has_pixels(dataset, road)
    names = [p.name for p in dataset.pairs]
    stems = {p.name: [p.image1.stem] for p in dataset.pairs}
    with options_of({"flows": "--flows"}):
        flow_files = match_files(flows, names, what="flows", stems=stems) if flows is not None else {}
    specs = [_spec(p.name, dataset, i, USER_OPTIONS, _file_identity(dataset, i, read, flow_files.get(p.name)),
                   {"files": flow_files[p.name]} if p.name in flow_files else {})
             for i, p in enumerate(dataset.pairs)]
    return specs, dataset.camera


# -- the shared KITTI samples --------------------------------------------------------------------

def kitti15_pairs(root: Path, *, height: float, road_auto: bool = False) -> tuple[list[PairSpec], Camera]:
    """A KITTI 2015 pair in the layout of ``kitti15_000000`` (``fsof_torch.datasets.KittiSampleDataset``):
    image_10/image_11, calib_cam_to_cam.txt (P_rect_02), road.json (not read with ``road_auto``:
    the job detects the road), flow_noc_10.png (ground truth, where present). The pair is named
    after the folder."""
    from fsof_torch.datasets import KittiSampleDataset

    need = ["image_10.png", "image_11.png", "calib_cam_to_cam.txt"] + ([] if road_auto else ["road.json"])
    check_mounting(height, road_auto=road_auto)
    # (the ground truth is optional: one that is no file was left out, the report saying there is none)
    for bad in (special_input(root / n, "--kitti15") for n in (*need, "flow_noc_10.png")):
        if bad is not None:
            raise JobError(bad)
    folders = [n for n in (*need, "flow_noc_10.png") if (root / n).is_dir()]
    if folders:
        raise JobError(f"--kitti15: {str(root / folders[0])!r} is a folder; expected a file")
    missing = [n for n in need if not (root / n).is_file()]
    if missing:
        hint = "" if road_auto or missing != ["road.json"] else " (or pass --road auto)"
        raise JobError(f"--kitti15: {str(root)!r} lacks {missing}{hint}")
    with options_of("--kitti15"):
        dataset = KittiSampleDataset(root, cam=2, camera_height=height, camera_dtype=torch.float64,
                                     road_json=not road_auto)
    read = _dataset_digests(dataset)
    check_image_size(dataset, "--kitti15", road_auto)
    name = dataset.pairs[0].name
    return [_spec(name, dataset, 0, "--kitti15", _file_identity(dataset, 0, read))], dataset.camera


def kitti_odometry_pairs(root: Path, *, height: float, pitch_deg: float,
                         road_auto: bool = False) -> tuple[list[PairSpec], Camera]:
    """A KITTI odometry clip in the layout of ``kitti_odometry_straight``
    (``fsof_torch.datasets.KittiOdometryDataset``): image_l/ (cam 0), calib.txt (P0), poses.txt,
    road.json (not read with ``road_auto``: the job detects the road); the frames that have a
    pose."""
    from fsof_torch.datasets import KittiOdometryDataset

    check_mounting(height, pitch_deg=pitch_deg, road_auto=road_auto)
    for n in ("image_l", "calib.txt", "poses.txt") + (() if road_auto else ("road.json",)):
        path, folder = root / n, n == "image_l"
        if (bad := special_input(path, "--kitti-odometry")) is not None:
            raise JobError(bad)
        if path.exists() and not (path.is_dir() if folder else path.is_file()):
            # (a folder road.json was no road at all: the road was detected, the report said road.json)
            raise JobError(f"--kitti-odometry: {str(path)!r} is {'not a folder' if folder else 'a folder'}; "
                           f"expected {'the folder of frames' if folder else 'a file'}")
        if not path.exists():
            hint = " (or pass --road auto)" if n == "road.json" else ""
            raise JobError(f"--kitti-odometry: {str(root)!r} lacks {n}{hint}")
    with options_of("--kitti-odometry"):
        dataset = KittiOdometryDataset(root, cam=0, camera_height=height, pitch=math.radians(pitch_deg),
                                       camera_dtype=torch.float64, road_json=not road_auto)
    read = _dataset_digests(dataset)
    check_image_size(dataset, "--kitti-odometry", road_auto)
    specs = [_spec(p.name, dataset, i, "--kitti-odometry", _file_identity(dataset, i, read))
             for i, p in enumerate(dataset.pairs)]
    return specs, dataset.camera
