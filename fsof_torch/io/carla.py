"""The paper's CARLA data layout (velocity-model experiments), as its official code reads it.

One folder per run, named like ``t10_s0_r-5`` (``r``: the camera roll in degrees; the meaning of
``t`` and ``s`` is not documented, :func:`parse_carla_run_name` returns them as numbers)::

    t10_s0_r-5/
        rgb/00000070.png            RGB frames, 640×480
        optical_flow/00000070.tif   CARLA optical flow of the frame (see read_carla_flow)
        optical_flow/00000070.png   a colour rendering of it (not read)
        semantic/00000070.png       CARLA semantic segmentation in the CityScapes palette
        poses.txt                   vehicle poses, one row per frame

Assumptions, where the paper and its code say nothing (checked against the official scripts
``carla.py`` / ``kitti.py`` of the authors' repository):

- Flow TIFF: float32 in CARLA's normalised units, read by the official code as
  ``np.reshape(np.array(Image.open(path)), (H, W, 2))`` then ``u = x · W``, ``v = -y · H``: we
  read a single-channel (H, 2W) image with x, y interleaved (what that reshape implies). A
  two-channel float32 TIFF is not read: OpenCV, our image decoder, does not decode one (a
  ValueError names the file). The paper calls these values instantaneous velocities (px/s).
- Semantic PNG: road = RGB (128, 64, 128), road line = RGB (157, 234, 50) (CARLA's CityScapes
  palette); both count as road.
- Camera: fx = fy = W / (2 tan(FOV / 2)) with FOV 90°, principal point (W / 2, H / 2), height
  2.4 m, wheelbase 2.7 m: the constants of the official code.
- ``poses.txt``: its format is not published; :func:`fsof_torch.io.read_kitti_poses` reads rows
  of 12 (KITTI 3×4) or 16 numbers, optionally after a frame index.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..geometry.camera import Camera
from .._check import as_path, check_int, check_number
from .atomic import file_target
from .flo import float32_flow
from .images import check_no_broken_links, in_frame_order, read_image, read_image_array, write_image_array
from .masks import mask_from_colors

__all__ = [
    "CARLA_ROAD_COLORS",
    "CARLA_CAMERA_HEIGHT",
    "CARLA_WHEELBASE",
    "read_carla_flow",
    "write_carla_flow",
    "read_carla_road",
    "carla_camera",
    "parse_carla_run_name",
    "CarlaRun",
]

CARLA_ROAD_COLORS = ((128, 64, 128), (157, 234, 50))
CARLA_CAMERA_HEIGHT = 2.4
CARLA_WHEELBASE = 2.7


def read_carla_flow(path: str | os.PathLike) -> tuple[Tensor, Tensor]:
    """A CARLA flow TIFF of the paper's layout as ``(flow (2, H, W) float32, valid (1, H, W) bool)``.

    The file is a single-channel float32 (H, 2W) image, x and y interleaved (as
    :func:`write_carla_flow` writes it); ``u = x · W``, ``v = -y · H`` from CARLA's normalised
    flow (the official code's conversion); valid where finite. Another file (a two-channel
    float32 TIFF, which OpenCV does not decode; another pixel type or channel count; an odd
    width) is a ValueError naming the path.
    """
    array = read_image_array(path, what="CARLA flow TIFF (single-channel float32 (H, 2W), x and y interleaved; "
                                        "OpenCV decodes no two-channel float32 TIFF)")
    if array.dtype != np.float32:
        raise ValueError(f"path: {str(path)!r} holds {array.dtype} values; a CARLA flow TIFF holds float32")
    if array.ndim != 2:
        raise ValueError(f"path: {str(path)!r} has {array.shape[2]} channels; a CARLA flow TIFF is a single-channel "
                         f"(H, 2W) image, x and y interleaved")
    if array.shape[1] % 2:
        raise ValueError(f"path: {str(path)!r} is a single-channel {array.shape} image; a CARLA flow TIFF "
                         f"interleaves x, y and so has an even width")
    array = array.reshape(array.shape[0], array.shape[1] // 2, 2)
    height, width = array.shape[:2]
    flow = np.stack([array[:, :, 0] * width, -array[:, :, 1] * height]).astype(np.float32)
    valid = np.isfinite(flow).all(axis=0)
    flow[:, ~valid] = 0.0
    return torch.from_numpy(flow), torch.from_numpy(valid).unsqueeze(0)


def write_carla_flow(path: str | os.PathLike, flow: Tensor) -> Path:
    """Write a (2, H, W) flow as the paper's CARLA TIFF (single-channel float32 (H, 2W), x and y
    interleaved, ``x = u / W``, ``y = -v / H``), atomically. For tests and synthetic runs.

    ``path`` must end in ``.tif`` or ``.tiff`` (the only format here that stores float32); another
    suffix is a ValueError naming ``path``, and a finite value beyond float32's range (which the
    cast would make inf, read back as an invalid pixel) one naming ``flow``, before anything is
    written. NaN and inf are written as they are (read back as invalid)."""
    path = file_target(path)
    if path.suffix.lower() not in (".tif", ".tiff"):
        raise ValueError(f"path: a CARLA flow file is a float32 TIFF; expected a .tif or .tiff path, got "
                         f"{str(path)!r}")
    flow = float32_flow(flow, "a CARLA flow TIFF")
    _, height, width = flow.shape
    xy = torch.stack([flow[0] / width, -flow[1] / height], dim=-1).numpy()
    return write_image_array(path, np.ascontiguousarray(xy.reshape(height, 2 * width)))


def read_carla_road(path: str | os.PathLike) -> Tensor:
    """Road mask (1, H, W) bool from a CARLA semantic PNG: road or road-line pixels.

    The PNG must be a colour image (3 or 4 channels, CityScapes palette): a single-channel one
    (CARLA's raw class IDs saved as grey) would match no road colour, so it is a ValueError
    naming the path."""
    array = read_image_array(path, what="CARLA semantic PNG (colour, CityScapes palette)")
    channels = 1 if array.ndim == 2 else array.shape[2]
    if channels not in (3, 4):
        raise ValueError(f"path: {str(path)!r} has {channels} channel(s); a CARLA semantic PNG is a colour image "
                         f"(3 or 4 channels, CityScapes palette), not CARLA's raw class IDs")
    # decoded again by read_image, the one definition of the conversion to RGB 0..255
    return mask_from_colors(read_image(path), CARLA_ROAD_COLORS)


def carla_camera(size: tuple[int, int], *, height: float = CARLA_CAMERA_HEIGHT, roll: float = 0.0,
                 pitch: float = 0.0, fov_deg: float = 90.0, dtype: torch.dtype = torch.float64) -> Camera:
    """The camera of the paper's CARLA runs for an image of ``size = (H, W)``: f = W / (2 tan(FOV/2)),
    principal point (W/2, H/2) (as in the official code), height 2.4 m; roll in radians.

    ``size`` is two ints >= 1 (a float side such as 480.5 is an error, not truncated) and
    ``fov_deg`` the horizontal field of view in degrees, a number in (0, 180): else a TypeError or
    ValueError naming the argument (0° divided by zero, 180° gave a focal length of 2e-14 px), as
    is a ``dtype`` that is not a floating-point torch dtype."""
    try:
        sides = None if isinstance(size, (str, bytes, set, dict)) else list(size)
    except TypeError:  # (not iterable)
        sides = None
    if sides is None or len(sides) != 2:
        raise TypeError(f"size: expected (H, W), two ints, got {type(size).__name__} {size!r:.60}")
    h, w = (check_int(s, "size", minimum=1) for s in sides)
    fov = check_number(fov_deg, "fov_deg")
    if not 0.0 < fov < 180.0:
        raise ValueError(f"fov_deg: expected a field of view in (0, 180) degrees, got {fov_deg!r}")
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise TypeError(f"dtype: expected a floating-point torch dtype, got {dtype!r}")
    f = w / (2.0 * math.tan(math.radians(fov) / 2.0))
    K = torch.tensor([[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]], dtype=dtype, device="cpu")
    return Camera(K, height, roll, pitch)


_RUN_FIELD = re.compile(r"([A-Za-z]+)(-?\d+(?:\.\d+)?)")
_ROLL_LIKE = re.compile(r"[rR](?![A-Za-z])")  # r or R, then no letter: meant as the roll


def parse_carla_run_name(name: str) -> dict[str, float]:
    """``"t10_s0_r-5"`` → ``{"t": 10.0, "s": 0.0, "r": -5.0, "roll": -5° in radians}``.

    Parts that are no field (``foo``) are skipped. The roll must read ``r`` then a number
    (``r-5``, ``r2.5``): a part that starts with ``r`` or ``R`` and no other letter but does not
    (``r+5``, ``R-5``, ``r-5deg``, ``r.5``, ``r-2.5e0``), or a second roll part, is a ValueError
    naming the run (it would otherwise be dropped and the roll taken as 0, or the last one)."""
    fields = {}
    roll_part = None
    for part in str(name).split("_"):
        match = _RUN_FIELD.fullmatch(part)
        if _ROLL_LIKE.match(part):
            if not (match and match.group(1) == "r"):
                raise ValueError(f"name: the run {str(name)!r} has the part {part!r}; expected the roll as 'r' "
                                 f"and a number of degrees (r-5, r2.5)")
            if roll_part is not None:
                raise ValueError(f"name: the run {str(name)!r} gives the roll twice ({roll_part!r}, {part!r})")
            roll_part = part
        if match:
            fields[match.group(1)] = float(match.group(2))
    if "r" in fields:
        fields["roll"] = math.radians(fields["r"])
    return fields


class CarlaRun:
    """One run folder of the paper's CARLA layout: frame names and the paths of each frame's files.

    ``frames`` are the stems of ``rgb/*.png`` in frame order: by number where every stem is a
    number (``98``, ``99``, ``100``, unpadded), one text around a number (``f98``, ``f100``) or
    a decimal number or one text around one (``9.967`` before ``10.000``, ``f9.967`` before
    ``f10.000``),
    else by name. Only regular files count, and not
    hidden ones (a name starting with ``.``, such as macOS's ``._99.png``); a frame that is a
    symbolic link to a missing file is a FileNotFoundError naming ``root``.

    Example:
        >>> run = CarlaRun("data/CARLA/t10_s0_r-5")           # doctest: +SKIP
        >>> flow, valid = read_carla_flow(run.path("optical_flow", run.frames[0]))  # doctest: +SKIP
    """

    FOLDERS = {"rgb": ".png", "optical_flow": ".tif", "semantic": ".png"}

    def __init__(self, root: str | os.PathLike):
        self.root = as_path(root, "root")
        if not (self.root / "rgb").is_dir():
            raise FileNotFoundError(f"root: {str(self.root)!r} has no rgb/ folder (expected the paper's CARLA layout)")
        # only regular, visible files: a hidden one (macOS ._NNN.png, an atomic writer's temporary)
        # would change the frame order and so the pairs
        visible = [p for p in (self.root / "rgb").glob("*.png") if not p.name.startswith(".")]
        check_no_broken_links(visible, "root")  # (a frame left out would pair its neighbours)
        self.frames = [p.stem for p in in_frame_order(p for p in visible if p.is_file())]
        if not self.frames:
            raise ValueError(f"root: {str(self.root / 'rgb')!r} holds no PNG frames")
        self.params = parse_carla_run_name(self.root.name)

    def path(self, kind: str, frame: str) -> Path:
        if kind not in self.FOLDERS:
            raise ValueError(f"kind: expected one of {sorted(self.FOLDERS)}, got {kind!r}")
        return self.root / kind / f"{frame}{self.FOLDERS[kind]}"

    @property
    def poses_path(self) -> Path:
        return self.root / "poses.txt"

    def __len__(self) -> int:
        return len(self.frames)

    def __repr__(self) -> str:
        return f"CarlaRun({str(self.root)!r}, frames={len(self.frames)})"
