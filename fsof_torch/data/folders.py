"""Image pairs of a folder of frames with a KITTI calibration, and optional poses, road masks and
ground-truth flows matched to the pairs by name: the layout of your own recordings, which
``python -m refine --images`` reads through :class:`ImageFolderDataset`.

Pairs: consecutive frames (i, i + step) of the folder sorted by name (by number where every name
is a number, or one text around a number: ``5.png`` before ``10.png``, ``frame_9.png`` before
``frame_10.png``; by value where every name is a decimal number or one text around one,
``9.967.png`` before ``10.000.png``, ``left_9.967.png`` before ``left_10.000.png``), each named after its first frame; or KITTI flow pairs
(``NAME_10`` / ``NAME_11``) by name, named ``NAME``, where every image's name ends in ``_10`` or
``_11``, or where complete pairs stand under at least two different names
(:func:`kitti_flow_layout`): every image of such a folder must then be in a complete pair (an
image without its partner is an error naming it, never paired with another scene's frame nor
dropped). A clip whose frames share one ``NAME`` (``frame_00`` ... ``frame_50``) is a clip. A
folder of frames named by a number beside images named otherwise (``preview.png``, a second
camera's ``right_*``) is an error naming them (:func:`check_one_naming`).

Files are matched to pairs by name only, never by position (:func:`match_files`): the pair ``NAME``
takes ``NAME.<ext>`` (or its first image's stem) from a folder; a pair without such a file, or
with two (``0001.png`` and ``0001.flo``), is an error naming the argument and the file.

Image size against the calibration: a KITTI ``calib_cam_to_cam.txt`` states the rectified size
(``S_rect_0N``), ``calib_size`` states it for other files; every image must have exactly that
size. Without either, every image must have the size of the first pair, and the principal point
must lie in the middle third of that image (|c_x − (W−1)/2| ≤ W/6, likewise for y): a calibration
made for images twice as large or half as large fails this test (its principal point lies a
quarter or a half of the image away from the centre), a camera's own offset (KITTI: 11 px of
1242) passes it, and one farther off (frames cropped after calibration) passes with
``calib_size``. Everything that can be checked without reading every pair is checked when the
dataset is made; the other pairs' sizes when they load.
"""

from __future__ import annotations

import math
import numbers
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import Dataset

from .._check import as_path, check_has_values, check_int, check_number, check_size, existing_file, tensor_from_array
from ..geometry.camera import Camera, read_kitti_calibration, split_calibration_line
from ..geometry.egomotion import check_pose_steps, ego_motion_from_pose, relative_pose
from ..io.flow import read_flow
from ..io.images import (check_frame_names, check_no_broken_links, decimal_times, existing_folder, frame_counts,
                         frame_numbers, in_frame_order, read_image)
from ..io.kitti import check_rigid_poses, read_kitti_poses
from ..io.masks import read_road_mask
from .items import check_item_options, make_item

__all__ = ["IMAGE_SUFFIXES", "FLOW_SUFFIXES", "FramePair", "ImageFolderDataset", "calibration_size",
           "check_index", "check_mounting", "check_one_naming", "frame_pairs", "kitti_flow_layout", "list_images",
           "match_files", "principal_point_off_centre"]

# every suffix write_image writes (.webp too: its frames were left out of a folder) and the PNM ones
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".webp", ".ppm", ".pgm", ".tif", ".tiff")
FLOW_SUFFIXES = (".png", ".flo", ".npy")
KITTI_HEIGHT = 1.65  # metres; KITTI's files do not record the camera height

# what a road mask reader may raise on a malformed file (each one was a traceback once)
_MASK_ERRORS = (ValueError, TypeError, KeyError, IndexError, ZeroDivisionError, UnicodeDecodeError,
                AttributeError, OverflowError)


def check_index(index: int, length: int) -> int:
    """A dataset index (negative counts from the end) -> its position, or IndexError / TypeError (a
    bool is no index). An int, or what a list takes as one: a 0-d integer tensor or array (the
    indices ``Subset(dataset, torch.randperm(n))`` hands over)."""
    if _integer_scalar(index):
        index = int(index)
    if isinstance(index, bool) or not isinstance(index, numbers.Integral):
        raise TypeError(f"index: expected an int, got {type(index).__name__} {index!r:.60}")
    if not -length <= index < length:
        raise IndexError(f"index: {index} out of range for a dataset of {length} pairs")
    return int(index) % length


def _integer_scalar(index: object) -> bool:
    """Whether ``index`` is a 0-d integer (not bool) tensor on a real device or NumPy array."""
    if isinstance(index, Tensor):
        return (index.dim() == 0 and not index.is_floating_point() and not index.is_complex()
                and index.dtype != torch.bool and index.device.type != "meta")
    return isinstance(index, np.ndarray) and index.ndim == 0 and np.issubdtype(index.dtype, np.integer)


def check_mounting(camera_height: object, roll: object, pitch: object,
                   dtype: torch.dtype = torch.float64) -> tuple[float, float, float]:
    """``camera_height`` (m), ``roll`` and ``pitch`` (rad) as a :class:`Camera` of ``dtype`` takes
    them (height within its bounds, |angle| < π/2), as floats; errors name the argument (checked
    before any calibration is read, so that they never blame ``calib``)."""
    camera_height = check_number(camera_height, "camera_height", positive=True)
    roll, pitch = check_number(roll, "roll"), check_number(pitch, "pitch")
    try:
        Camera(torch.eye(3, dtype=torch.float64, device="cpu"), camera_height, roll, pitch).to(dtype)  # (dtype's bounds)
    except ValueError as err:
        message = str(err)
        raise ValueError("camera_" + message if message.startswith("height:") else message) from None
    return camera_height, roll, pitch


def list_images(folder: str | os.PathLike, name: str = "images") -> list[Path]:
    """The image files of ``folder`` in frame order (at least 2; hidden files, named ``.*``, left
    out; ``name`` is the argument the errors name): by number where every file's name is a number
    (``0.png``, ``5.png``, ``10.png``: frames numbered without zero padding) or one text around a
    number (``frame_9.png`` before ``frame_10.png``: :func:`fsof_torch.io.images.frame_numbers`),
    by value where every name is a decimal number or one text around one (timestamps ``9.967.png``
    before ``10.000.png``, ``left_9.967.png`` before ``left_10.000.png``),
    else by name (:func:`fsof_torch.io.images.in_frame_order`). Two files of one frame name
    (``000000.png`` and ``000000.jpg``) are a ValueError naming ``name``; a frame that is a
    symbolic link to a missing file a FileNotFoundError naming ``name`` (never a frame left out,
    which would pair its neighbours). Frames of a clip named by a number beside images named
    otherwise (``preview.png`` beside ``000000.png`` ..., or ``left_000001.png`` ... beside
    ``right_000001.png`` ...), or series named alike but for one number (``cam0_000001.png`` ...
    beside ``cam1_000001.png`` ...), are a ValueError naming ``name`` and the others
    (:func:`check_one_naming`): sorted by name, the last frame would be paired with them."""
    folder = existing_folder(folder, name)
    # (hidden files are no frames: macOS's ``._000001.png`` beside each frame, a writer's temporary)
    entries = [p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")]
    check_no_broken_links(entries, name)
    images = in_frame_order((p for p in entries if p.is_file()), name)
    if len(images) < 2:
        raise ValueError(f"{name}: {str(folder)!r} holds {len(images)} image(s); a pair needs at least 2"
                         + _frames_below(folder))
    check_one_naming(images, name)
    return images


def _frames_below(folder: Path) -> str:
    """Where ``folder``'s sub-folders hold images (a KITTI raw camera folder, ``image_02/``, holds
    its frames in ``data/``; an odometry sequence, ``sequences/00/``, in ``image_0/`` ...), the
    text that names them for an error; "" where none does."""
    held = []
    for sub in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
        count = sum(1 for p in sub.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))
        if count:
            held.append(f"{str(sub)!r} ({count} image{'s' if count > 1 else ''})")
    if not held:
        return ""
    several = len(held) > 1
    return (f"; its sub-folder{'s' if several else ''} {', '.join(held[:4])}{', ...' if len(held) > 4 else ''} "
            f"{'hold' if several else 'holds'} images: give the folder of one camera's frames")


def check_one_naming(images: Sequence[Path], name: str = "images") -> None:
    """A folder's frames in name order must not be a clip named by a number beside images named
    otherwise: where the names are not all one text around a number, nor decimal times (which
    :func:`fsof_torch.io.images.in_frame_order` sorts by their numbers), but two or more share one
    text around their numbers (``000000`` ..., ``frame_1`` ...) and others do not (``preview``, a
    second camera's ``right_000001`` ... beside ``left_000001`` ...), or where one number tells
    series of one naming apart (``cam0_000001`` ..., ``cam1_000001`` ...), a ValueError names ``name``,
    the folder and the names: sorted by name, the clip's last frame would be paired with another
    image, or one camera's last frame with another camera's first. KITTI flow pairs
    (:func:`kitti_flow_layout`), which pair by name, and names without a number are not checked."""
    stems = [p.stem for p in images]
    if frame_numbers(stems) is not None or decimal_times(stems) is not None or kitti_flow_layout(images, name):
        return
    namings: dict[tuple[str, ...], list[Path]] = {}
    for p in images:
        texts = tuple(re.split(r"[0-9]+", p.stem))
        namings.setdefault(texts if len(texts) > 1 else (p.stem,), []).append(p)
    clips = [v for k, v in namings.items() if len(k) > 1 and len(v) >= 2]
    folder = repr(str(images[0].parent))
    for clip in clips:
        if series := _numbered_series(clip):
            shown = "; ".join(f"{v[0].name} ... {v[-1].name} ({len(v)})" if len(v) > 1 else v[0].name
                              for v in series[:4]) + ("; ..." if len(series) > 4 else "")
            raise ValueError(f"{name}: {folder} holds {len(series)} series of frames named alike but for one number "
                             f"({shown}), such as two cameras' (cam0_000001, cam1_000001): sorted by name, one "
                             f"series' last frame would be paired with the next one's first: keep one clip of one "
                             f"camera in the folder")
    if not clips or (len(clips) == 1 and len(clips[0]) == len(images)):
        return
    shown = [f"{v[0].name} ... {v[-1].name} ({len(v)})" if len(v) > 1 else v[0].name
             for v in sorted(namings.values(), key=len, reverse=True)]
    listed = "; ".join(shown[:5]) + ("; ..." if len(shown) > 5 else "")
    raise ValueError(f"{name}: {folder} holds frames named by a number beside images named otherwise ({listed}); "
                     f"sorted by name, one clip's last frame would be paired with another image: keep one clip "
                     f"of one camera in the folder, its frames named alike (000000.png, 000001.png, ...)")


def _numbered_series(images: Sequence[Path]) -> list[list[Path]]:
    """The series in name order among ``images``, frames named alike around numbers, where one
    number tells series apart: without it, two frames would share every other number (two
    cameras' ``cam0_000001``, ``cam1_000001``; a stereo pair's ``000001_0``, ``000001_1``). Empty
    where no number does (a frame counter beside a timestamp: each unique)."""
    numbers = [tuple(int(n) for n in re.findall(r"[0-9]+", p.stem)) for p in images]
    varying = [k for k in range(len(numbers[0])) if len({n[k] for n in numbers}) > 1]
    if len(varying) < 2:
        return []
    # (the number that tells series apart takes the fewest values: two cameras, many frames)
    for k in sorted(varying, key=lambda k: len({n[k] for n in numbers})):
        rest = [tuple(n[j] for j in varying if j != k) for n in numbers]
        if len(set(rest)) < len(rest):
            series: dict[int, list[Path]] = {}
            for n, p in zip(numbers, images):
                series.setdefault(n[k], []).append(p)
            return list(series.values())
    return []


def _kitti_partner(stem: str) -> str | None:
    """The other image's name of a KITTI flow pair (``NAME_10`` <-> ``NAME_11``); None for others."""
    if stem.endswith("_10"):
        return stem[:-3] + "_11"
    if stem.endswith("_11"):
        return stem[:-3] + "_10"
    return None


def kitti_flow_layout(images: Iterable[Path], name: str = "images") -> bool:
    """Whether the images are KITTI flow pairs (``NAME_10`` / ``NAME_11``, paired by name), not one
    clip: every image's name ends in ``_10`` or ``_11``, or complete pairs stand under at least two
    different names ``NAME`` (KITTI's multiview folders: ``000000_00`` ... ``000000_20``,
    ``000001_00`` ...). Every image of such a layout must be in a complete pair: one without its
    partner (a ``NAME_10`` without ``NAME_11``, or another image beside the pairs, such as the
    other frames of KITTI's multiview folders) raises a ValueError naming ``name`` (the argument
    the images came from), the folder and the images. A clip, whose complete pairs (if any) share
    one ``NAME`` (``frame_00`` to ``frame_11``, ``NAME_00`` to ``NAME_50``), stays a clip."""
    paths = [Path(p) for p in images]
    stems = {p.stem for p in paths}
    paired_names = {s[:-3] for s in stems if s.endswith("_10") and _kitti_partner(s) in stems}
    if len(paired_names) < 2 and not all(_kitti_partner(s) is not None for s in stems):
        return False
    orphans = [p for p in paths if _kitti_partner(p.stem) not in stems]
    if orphans:
        folders = sorted({str(p.parent) for p in paths})
        where = repr(folders[0]) if len(folders) == 1 else f"{len(paths)} images"
        shown = ", ".join(p.name for p in orphans[:5]) + (", ..." if len(orphans) > 5 else "")
        others = ("" if all(_kitti_partner(p.stem) for p in orphans)
                  else " and move other images out (frames of a clip: names that do not end in _10 or _11)")
        raise ValueError(f"{name}: {where} holds KITTI flow pairs (NAME_10 / NAME_11, paired by name), but "
                         f"{len(orphans)} image(s) have no partner: {shown}; give each NAME_10 its NAME_11"
                         f"{others}")
    return True


def frame_pairs(images: Sequence[Path], step: int = 1) -> list[tuple[str, int, int]]:
    """``(name, i, j)``: the pairs of ``images`` as positions in the list. Consecutive frames
    (i, i + step) named after frame i; KITTI flow pairs by name (``NAME_10`` / ``NAME_11`` ->
    ``NAME``, step 1 only). Two images of one frame name (``000000.png`` and ``000000.jpg``,
    whose pairs would share a name and its files) are a ValueError naming ``images``."""
    step = check_int(step, "step", minimum=1)
    check_frame_names(images, "images")
    if kitti_flow_layout(images):
        if step != 1:
            raise ValueError(f"step: KITTI flow pairs (NAME_10 / NAME_11) pair by name; expected 1, got {step}")
        position = {Path(p).stem: i for i, p in enumerate(images)}
        return [(s[:-3], position[s], position[s[:-3] + "_11"])
                for s in sorted(s for s in position if s.endswith("_10"))]
    return [(Path(images[i]).stem, i, i + step) for i in range(len(images) - step)]


def match_files(folder: str | os.PathLike, names: Sequence[str], *, what: str,
                suffixes: Sequence[str] = FLOW_SUFFIXES,
                stems: dict[str, list[str]] | None = None) -> dict[str, Path]:
    """One file per pair from ``folder``, by name: the pair's name or one of its ``stems`` (its
    first image's), with any of ``suffixes``. A pair without such a file, or with two
    (``0001.png`` and ``0001.flo``), raises an error that starts with ``what`` (the argument) and
    names the pair and the folder: files are never paired by position."""
    folder = existing_folder(folder, what)
    by_stem: dict[str, list[Path]] = {}
    entries = [p for p in sorted(folder.iterdir()) if p.suffix.lower() in suffixes]
    check_no_broken_links(entries, what)
    for p in entries:
        if p.is_file():
            by_stem.setdefault(p.stem, []).append(p)
    out: dict[str, Path] = {}
    for name in names:
        candidates = list(dict.fromkeys([name, *(stems or {}).get(name, [])]))
        found = [p for s in candidates for p in by_stem.get(s, [])]
        if len(found) > 1:
            raise ValueError(f"{what}: pair {name} matches {len(found)} files in {str(folder)!r} "
                             f"({', '.join(p.name for p in found)}); keep one")
        if not found:
            near = sorted(by_stem)[:3]
            raise ValueError(f"{what}: no file for pair {name} in {str(folder)!r}: expected "
                             f"{' or '.join(s + '.*' for s in candidates)} ({', '.join(suffixes)}); "
                             f"the folder has {sum(len(v) for v in by_stem.values())} such file(s)"
                             + (f", e.g. {', '.join(near)}" if near else ""))
        out[name] = found[0]
    return out


def calibration_size(calib: str | os.PathLike, cam: int) -> tuple[int, int] | None:
    """The rectified image size (H, W) a KITTI ``calib_cam_to_cam.txt`` states for camera
    ``cam`` (``S_rect_0N: W H``), or None when the file has no such row (odometry ``calib.txt``).
    A row that is not two finite sizes of at least one pixel is a ValueError naming ``calib``. A
    byte-order mark is skipped, as :func:`read_kitti_calibration` skips it."""
    calib = Path(calib)
    try:
        text = calib.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        return None  # the calibration reader reports the file
    for line in text.splitlines():
        key, sep, rest = line.partition(":")
        if sep and key.strip() == f"S_rect_0{cam}":
            try:
                w, h = (float(x) for x in rest.split())
                if not all(math.isfinite(v) and round(v) >= 1 for v in (w, h)):
                    raise ValueError
            except ValueError:
                raise ValueError(f"calib: {str(calib)!r} has an S_rect_0{cam} row that is not 'W H' "
                                 f"(two sizes of at least one pixel): {line.strip()[:60]!r}") from None
            return int(round(h)), int(round(w))
    return None


def principal_point_off_centre(camera: Camera, size: tuple[int, int]) -> tuple[float, float] | None:
    """The principal point ``(c_x, c_y)`` of ``camera`` (batch 1) where it lies outside the middle
    third of an image of ``size`` (H, W): |c_x − (W−1)/2| > W/6 or |c_y − (H−1)/2| > H/6; None
    where it lies inside. A calibration made for images twice or half as large puts it there (a
    quarter or a half of the image off centre); a camera's own offset (KITTI: 11 px of 1242) does
    not. The datasets' test of a calibration that states no image size."""
    H, W = size
    cx, cy = float(camera.cx[0]), float(camera.cy[0])
    if abs(cx - (W - 1) / 2) > W / 6 or abs(cy - (H - 1) / 2) > H / 6:
        return cx, cy
    return None


def _has_camera_row(calib: Path, cam: int) -> bool:
    """Whether a KITTI calibration file has a row for camera ``cam`` (``P_rect_0N:``, ``PN:``, or,
    in a file without labelled P rows, an unlabelled row N + 1), well formed or not, as
    :func:`read_kitti_calibration` looks for it."""
    try:
        text = calib.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        return True  # the calibration reader reports the file
    keys, unlabelled = set(), 0
    for line in filter(None, map(str.strip, text.splitlines())):
        key, _ = split_calibration_line(line)
        if key is not None:
            keys.add(key)
        else:
            unlabelled += 1
    labelled = any(re.fullmatch(r"P(_rect_)?[0-9]+", k) for k in keys)
    return f"P_rect_0{cam}" in keys or f"P{cam}" in keys or (unlabelled > cam and not labelled)


def _read_camera(calib: Path, cam: int | None, height: float, roll: float, pitch: float) -> tuple[Camera, int]:
    """A float64 camera from a KITTI calibration file and the camera index used: ``cam``, or
    without it camera 2 (the left colour camera) where the file has a row for it, else camera 0.
    A camera-2 row that is there but malformed (11 numbers, NaN) raises, never falls back."""
    try:  # (a folder, or a link to a missing file, is named as such: not "no file")
        existing_file(calib, "calibration file")
    except OSError as err:
        raise type(err)(f"calib: {str(err).removeprefix('path: ')}") from None
    if cam is not None and not 0 <= cam <= 3:
        raise ValueError(f"cam: expected 0..3, got {cam}")
    c = cam if cam is not None else (2 if _has_camera_row(calib, 2) else 0)
    try:
        P = read_kitti_calibration(calib, c)
    except ValueError as err:
        raise ValueError(f"calib: {str(err).removeprefix('path: ')}") from None
    try:
        return Camera.from_projection(P, height, roll, pitch), c
    except ValueError as err:
        raise ValueError(f"calib: {str(calib)!r} camera {c}: {err}") from None


def _check_not_frames(frames: Sequence[Path], given: dict[str, Iterable[Path | None]]) -> None:
    """A ValueError naming the argument where a file it gives is one of the frames: ``road`` (or
    ``gt``) pointed at the images' folder, or at a frame, read each pair's own image as its mask,
    every nonzero pixel road (or a 16-bit frame as a flow), silently. A file is a frame where it is
    the same file (``os.stat``'s device and inode: through links, hard links too; one stat a file,
    cheap for the thousands of frames of a long clip)."""
    def identity(path: Path) -> tuple[int, int] | None:
        try:
            st = os.stat(path)
        except (OSError, ValueError):  # (a missing file is no frame: its reader names it)
            return None
        return st.st_dev, st.st_ino

    own = {identity(p): p for p in frames}
    own.pop(None, None)
    for what, files in given.items():
        for f in files:
            frame = own.get(identity(f)) if f is not None else None
            if frame is not None:
                raise ValueError(f"{what}: {str(f)!r} is one of the images (the frame {frame.name}), not a "
                                 f"{'road mask' if what == 'road' else 'flow'}: give the folder or file of the "
                                 f"{'masks' if what == 'road' else 'ground-truth flows'}, not the images'")


def _read_road(path: Path, size: tuple[int, int] | None) -> Tensor:
    """A road mask file; whatever the reader rejects names ``road`` and the file: the reader's own
    message (which names ``path`` and the file) under ``road``, or anything else wrapped. A
    polygon drawn for another size than ``size`` is the reader's error (never stretched)."""
    try:
        return read_road_mask(path, size)
    except FileNotFoundError:
        raise FileNotFoundError(f"road: no file at {str(path)!r}") from None
    except _MASK_ERRORS as err:
        named, sep, rest = str(err).partition(f"path: {str(path)!r}")
        if sep and not named:
            raise ValueError(f"road: {str(path)!r}{rest}") from None
        raise ValueError(f"road: {str(path)!r} is not a usable road mask ({type(err).__name__}: {err})") from None


@dataclass(frozen=True)
class FramePair:
    """The files of one pair: its images (``frame1``, ``frame2`` their positions among the
    dataset's frames, which index its poses), and its own road mask and ground-truth flow."""

    name: str
    image1: Path
    image2: Path
    frame1: int
    frame2: int
    road: Path | None = None
    gt: Path | None = None


class ImageFolderDataset(Dataset):
    """Image pairs of a folder of frames with a KITTI calibration (see the module docstring);
    items follow the contract of :mod:`fsof_torch.data.items`.

    Args:
        images: a folder of frames, or the frames' files in order (each checked to be a file here).
        calib: a KITTI ``calib_cam_to_cam.txt`` (``P_rect_0N``) or odometry ``calib.txt`` (``PN``);
            None: items without a camera.
        cam: camera index in ``calib`` (default: 2 where the file has it, else 0).
        camera_height: metres above the road; ``roll``, ``pitch``: the mounting in radians.
        poses: camera-to-world poses, one per frame in order: a KITTI poses file of exactly one line
            per frame (line i for frame i in sorted order), or an (N, 4, 4) float tensor or NumPy
            array (N at least the frames; copied, and checked as a file is: finite, last row 0 0 0 1,
            each 3×3 block a rotation, else a ValueError naming ``poses`` and the pose), in metres:
            two consecutive frames' poses farther apart than a road vehicle travels between them (100 m a frame,
            :func:`~fsof_torch.geometry.egomotion.check_pose_steps`; poses in millimetres) are a
            ValueError naming ``poses`` and the frames. Items then carry
            ``relative_pose`` (``inverse(P_j) @ P_i``), its planar ``odometry`` under the camera's
            mounting (``roll``, ``pitch``; with ``calib=None`` too) and ``pose_residual``.
        road: a folder of masks matched by name, or one mask file for every pair: a PNG of the
            images' size (never resized), or a polygon JSON drawn for the images' size (one drawn
            for another size is a ValueError, never stretched).
        gt: a folder of ground-truth flows matched by name (KITTI PNG, ``.flo``, ``.npy``).
        calib_size: ``(H, W)`` the calibration is for (default: the file's ``S_rect`` row; one that
            differs from the file's row is a ValueError naming ``calib_size``).
        step: pair frames (i, i + step) of a clip.
        dtype: float dtype of images and flows; ``camera_dtype`` of the camera (default ``dtype``).
        ground_truth: False -> no flow, valid, road, odometry, relative_pose.

    Errors name the argument (``images``, ``calib``, ``cam``, ``poses``, ``road``, ``gt``) and the
    file: a ``FileNotFoundError`` for a missing file or folder, a ``ValueError`` for one that does
    not fit, a ``TypeError`` for an argument that is no path (nor, for ``images``, a list of
    paths; for ``poses``, a tensor or array). ``camera_height``, ``roll`` and ``pitch`` are
    checked first, as the camera takes them (:func:`check_mounting`; with ``calib=None`` too),
    with errors naming them.
    """

    def __init__(self, images: str | os.PathLike | Sequence[str | os.PathLike],
                 calib: str | os.PathLike | None = None, *, cam: int | None = None,
                 camera_height: float = KITTI_HEIGHT, roll: float = 0.0, pitch: float = 0.0,
                 poses: str | os.PathLike | Tensor | np.ndarray | None = None, road: str | os.PathLike | None = None,
                 gt: str | os.PathLike | None = None, calib_size: tuple[int, int] | None = None, step: int = 1,
                 dtype: torch.dtype = torch.float32, camera_dtype: torch.dtype | None = None,
                 ground_truth: bool = True):
        camera_dtype = check_item_options(dtype, camera_dtype, ground_truth)
        cam = check_int(cam, "cam", optional=True)  # (with calib=None too: cam=7 or "2" was taken silently)
        if cam is not None and not 0 <= cam <= 3:
            raise ValueError(f"cam: expected 0..3, got {cam}")
        for what, given in (("calib", calib), ("road", road), ("gt", gt)):  # (not a bare TypeError of Path())
            if given is not None:
                as_path(given, what)
        if isinstance(poses, np.ndarray):  # as a tensor (copied and checked in _read_poses)
            poses = tensor_from_array(poses)
        elif poses is not None and (isinstance(poses, bool) or not isinstance(poses, (str, os.PathLike, Tensor))):
            raise TypeError(f"poses: expected a poses file or an (N, 4, 4) float tensor, got {type(poses).__name__} "
                            f"{poses!r:.60}")
        if isinstance(images, (str, os.PathLike)):
            self.frames = list_images(images)
        else:
            if isinstance(images, (bytes, bytearray)) or not isinstance(images, Iterable):
                raise TypeError(f"images: expected a folder or a list of image files, got {type(images).__name__} "
                                f"{images!r:.60}")
            self.frames = [as_path(p, "images") for p in images]
            if len(self.frames) < 2:
                raise ValueError(f"images: {len(self.frames)} image(s) given; a pair needs at least 2")
            for frame in self.frames:  # (checked here, as a folder's frames are, not when a pair loads)
                if frame.is_dir():
                    raise IsADirectoryError(f"images: {str(frame)!r} is a folder; expected an image file")
                if not frame.is_file():
                    raise FileNotFoundError(f"images: no file at {str(frame)!r}")
        pairs = frame_pairs(self.frames, step)
        if not pairs:
            raise ValueError(f"images: {len(self.frames)} frames make no pair (i, i + step) with step {step}")
        names = [n for n, _, _ in pairs]
        stems = {n: [self.frames[i].stem] for n, i, _ in pairs}
        self.dtype, self.ground_truth = dtype, ground_truth
        camera_height, roll, pitch = check_mounting(camera_height, roll, pitch, camera_dtype)
        self.calib = Path(calib) if calib is not None else None
        # a file argument that links to a missing file (a drive not mounted) says so, not "no file at"
        for what, given in (("calib", calib), ("road", road), ("poses", poses), ("gt", gt)):
            if isinstance(given, (str, os.PathLike)):
                check_no_broken_links([given], what)
        self.camera: Camera | None = None
        self.calib_size = check_size(calib_size, "calib_size") if calib_size is not None else None
        if self.calib is not None:
            camera64, used = _read_camera(self.calib, cam, camera_height, roll, pitch)
            self._camera64 = camera64
            self.camera = camera64.to(camera_dtype)
            stated = calibration_size(self.calib, used)
            if self.calib_size is not None and stated not in (None, self.calib_size):
                # the file's own size is the one its projection is for: another one is a mistake
                raise ValueError(f"calib_size: {self.calib_size[0]}x{self.calib_size[1]} is not the size "
                                 f"{str(self.calib)!r} states for camera {used} (S_rect_0{used}: "
                                 f"{stated[0]}x{stated[1]}); leave it out, or give the calibration of that size")
            self.calib_size = self.calib_size or stated
        else:
            self._camera64 = None
        # the mounting the odometry is projected under: the calibrated camera's, or without a
        # calibration the given roll and pitch (not a level camera whatever was given)
        self._mounting64 = self._camera64 if self._camera64 is not None else Camera(
            torch.eye(3, dtype=torch.float64, device="cpu"), camera_height, roll, pitch)
        self.poses = self._read_poses(poses, max(j for _, _, j in pairs) + 1) if poses is not None else None

        road_files: dict[str, Path] = {}
        self.road_file: Path | None = None
        if road is not None:
            rp = Path(road)
            # (a missing path named like a mask file, road.json or road.png, is a missing file)
            if rp.suffix.lower() in (".json", *IMAGE_SUFFIXES) and not rp.is_dir() or rp.is_file():
                if not rp.is_file():
                    raise FileNotFoundError(f"road: no file at {str(rp)!r}")
                self.road_file = rp
            else:
                road_files = match_files(rp, names, what="road", suffixes=IMAGE_SUFFIXES, stems=stems)
        gt_files = match_files(gt, names, what="gt", stems=stems) if gt is not None else {}
        _check_not_frames(self.frames, {"road": [*road_files.values(), self.road_file], "gt": gt_files.values()})
        self.pairs = [FramePair(n, self.frames[i], self.frames[j], i, j, road_files.get(n), gt_files.get(n))
                      for n, i, j in pairs]

        # the first pair, before any work: its size fixes the dataset's (or meets the calibration's)
        first = self.pairs[0].image1
        self.size = tuple(self._read_image(first).shape[-2:])
        self._check_calibrated_size(first)
        self._road_mask: Tensor | None = None
        if self.road_file is not None and self.road_file.suffix.lower() == ".json":
            self._road_mask = _read_road(self.road_file, self.size)  # a polygon drawn for the images' size
        elif self.road_file is not None:  # a mask, never resized: it must have the images' size
            self._road_mask = self._checked("road", self.road_file, _read_road(self.road_file, None))

    def _read_poses(self, poses: str | os.PathLike | Tensor, need: int) -> Tensor:
        if isinstance(poses, Tensor):
            if not poses.is_floating_point():
                raise TypeError(f"poses: expected an (N, 4, 4) float tensor, got dtype {poses.dtype}")
            if poses.dim() != 3 or poses.shape[-2:] != (4, 4):
                raise ValueError(f"poses: expected an (N, 4, 4) float tensor, got {tuple(poses.shape)} {poses.dtype}")
            check_has_values(poses, "poses", "to pair frames")
            # a copy in float64, checked as a poses file is: finite, last row 0 0 0 1, rotation blocks
            P, where = poses.detach().to("cpu", torch.float64, copy=True), "the poses"
            check_rigid_poses(P, lambda i: f"poses: pose {i} of the tensor")
        else:
            path = Path(poses)
            if not path.is_file():
                raise FileNotFoundError(f"poses: no file at {str(path)!r}")
            try:
                P = read_kitti_poses(path)
            except ValueError as err:
                raise ValueError(f"poses: {str(err).removeprefix('path: ')}") from None
            where = repr(str(path))
        if isinstance(poses, Tensor):
            if P.shape[0] < need:
                raise ValueError(f"poses: {where} has {P.shape[0]} poses for {need} images")
        elif P.shape[0] != len(self.frames):
            # line i is image i: a file with more lines would be read by position, silently
            raise ValueError(f"poses: {where} has {P.shape[0]} poses for {len(self.frames)} images: one line "
                             f"per image, line i for image i in sorted order, so a poses file of a longer "
                             f"sequence (KITTI: line n for frame n) must be cut to these frames")
        n = min(P.shape[0], len(self.frames))
        numbers = frame_counts(f.stem for f in self.frames[:n])  # (frames missing between two: a longer step)
        check_pose_steps(P[:n], "poses", labels=[f"the pose of {f.name}" for f in self.frames[:n]],
                         frames_apart=None if numbers is None else [b - a for a, b in zip(numbers, numbers[1:])])
        return P

    def _check_calibrated_size(self, image: Path) -> None:
        H, W = self.size
        if self.calib_size is not None:
            if self.size != self.calib_size:
                stated = f"the calibration {str(self.calib)!r}" if self.calib is not None else "calib_size"
                raise ValueError(f"images: {image.name} is {H}x{W} but {stated} is for "
                                 f"{self.calib_size[0]}x{self.calib_size[1]} images; resize the images, or give the "
                                 f"calibration of this size")
            return
        if self.camera is None:
            return
        off = principal_point_off_centre(self._camera64, self.size)
        if off is not None:
            cx, cy = off
            raise ValueError(f"images: {image.name} is {H}x{W}, but the principal point of {str(self.calib)!r} "
                             f"({cx:.1f}, {cy:.1f}) lies outside the middle third of such an image, as a "
                             f"calibration of another image size puts it (give images of the calibrated size); a "
                             f"camera whose principal point lies that far off centre (frames cropped after "
                             f"calibration, the crop's K) states the size with calib_size=(H, W)")

    def _read_image(self, path: Path) -> Tensor:
        try:
            return read_image(path)
        except FileNotFoundError as err:
            raise FileNotFoundError(f"images: {str(err).removeprefix('path: ')}") from None
        except IsADirectoryError as err:  # (a file replaced by a folder since the dataset was made)
            raise IsADirectoryError(f"images: {str(err).removeprefix('path: ')}") from None
        except ValueError as err:
            raise ValueError(f"images: {str(err).removeprefix('path: ')}") from None

    def _checked(self, what: str, path: Path, x: Tensor) -> Tensor:
        """``x`` if it has the images' size, else an error naming ``what`` and the file."""
        if tuple(x.shape[-2:]) != self.size:
            if what == "images":
                raise ValueError(f"images: {path.name} is {x.shape[-2]}x{x.shape[-1]} but {self.pairs[0].image1.name} "
                                 f"is {self.size[0]}x{self.size[1]}; all images need one size (the calibration's)")
            raise ValueError(f"{what}: {path.name} is {tuple(x.shape[-2:])}, the images {self.size}")
        return x

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, index: int) -> dict[str, Any]:
        i = check_index(index, len(self))
        pair = self.pairs[i]
        image1, image2 = (self._checked("images", p, self._read_image(p)) for p in (pair.image1, pair.image2))
        truth: dict[str, Any] = {}
        if self.ground_truth:
            if self._road_mask is not None:
                truth["road"] = self._road_mask.clone()
            elif pair.road is not None:
                truth["road"] = self._checked("road", pair.road, _read_road(pair.road, None))
            if pair.gt is not None:
                try:
                    flow, valid = read_flow(pair.gt)
                except FileNotFoundError as err:  # (removed since the dataset was made)
                    raise FileNotFoundError(f"gt: {str(err).removeprefix('path: ')}") from None
                except ValueError as err:
                    raise ValueError(f"gt: {str(err).removeprefix('path: ')}") from None
                truth["flow"], truth["valid"] = self._checked("gt", pair.gt, flow).to(self.dtype), valid
            if self.poses is not None:
                truth.update(self._motion(pair))
        # each item its own camera: editing one item's K must not change the next item's
        camera = None if self.camera is None else self.camera.to(self.camera.dtype, copy=True)
        return make_item(image1.to(self.dtype), image2.to(self.dtype), index=i, name=pair.name,
                         camera=camera, **truth)

    def _motion(self, pair: FramePair) -> dict[str, Any]:
        """The pair's relative pose, its planar odometry under the camera's mounting and the rest."""
        P = self.poses
        cam1_T_cam0 = relative_pose(P[pair.frame1][None], P[pair.frame2][None])[0]
        ego = ego_motion_from_pose(cam1_T_cam0[None], self._mounting64)
        return {"relative_pose": cam1_T_cam0,
                "odometry": {"x_d": float(ego.x_d[0]), "z_d": float(ego.z_d[0]), "yaw": float(ego.yaw[0])},
                "pose_residual": {"y_d": float(ego.y_d[0]), "rotation": float(ego.rotation_residual[0].norm())}}
