"""Virtual KITTI 2: flow PNGs, camera intrinsics and extrinsics, class segmentation.

Flow PNG (``frames/forwardFlow/Camera_N/flow_XXXXX.png``): 16-bit, 3 channels; in OpenCV's BGR
order B = 0 marks invalid flow (sky, ...), G and R hold v and u normalised by the image size:
``R = (2^16 - 1) · (u / (W - 1) + 1) / 2`` and ``G = (2^16 - 1) · (v / (H - 1) + 1) / 2``, so
``u = (2 R / (2^16 - 1) - 1) (W - 1)``. Resolution: 2 (W - 1) / 65535 px (0.038 px at W = 1242).

Text ground truth (``vkitti_2.0.3_textgt/SceneXX/<variation>/``), one header line then rows:
``intrinsic.txt``: ``frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]``;
``extrinsic.txt``: ``frame cameraID`` then the 16 numbers of a 4×4 matrix row by row, which
VKITTI documents as the world-to-camera transform (``camera_T_world``, camera x right, y down,
z forward); :func:`vkitti2_camera_poses` inverts it into KITTI-style camera-to-world poses for
:func:`fsof_torch.egomotion.ego_motion_from_pose`.
``colors.txt``: ``Category r g b`` then one class a row (``Road 100 60 100``, ...); the class
segmentation PNG (``classgt_XXXXX.png``) colours each pixel with its class colour.
"""

from __future__ import annotations

import numbers
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .._check import as_path, as_chw_flow, existing_file, result_dtype, skip_values
from .images import check_image_suffix, read_image_array, write_image_array
from .kitti import check_rigid_poses, flow_valid_pixels

__all__ = [
    "read_vkitti2_flow",
    "write_vkitti2_flow",
    "read_vkitti2_intrinsics",
    "read_vkitti2_extrinsics",
    "vkitti2_camera_poses",
    "read_vkitti2_colors",
    "read_vkitti2_classes",
]

_MAX16 = 2.0 ** 16 - 1.0


def read_vkitti2_flow(path: str | os.PathLike) -> tuple[Tensor, Tensor]:
    """A Virtual KITTI 2 flow PNG as ``(flow (2, H, W) float32 px, valid (1, H, W) bool)``.

    Flow at invalid pixels (B = 0) is 0. Raises ValueError naming the path for a truncated,
    8-bit or non-3-channel PNG.
    """
    array = read_image_array(path, what="Virtual KITTI 2 flow PNG (16-bit, 3 channels)")
    if array.dtype != np.uint16:
        raise ValueError(f"path: {str(path)!r} is a {array.dtype} image; a Virtual KITTI 2 flow PNG is 16-bit")
    channels = 1 if array.ndim == 2 else array.shape[2]
    if channels != 3:
        raise ValueError(f"path: {str(path)!r} has {channels} channel(s); a Virtual KITTI 2 flow PNG has 3")
    height, width = array.shape[:2]
    valid = array[:, :, 0] > 0
    # computed in float64 so that a round trip through write_vkitti2_flow is exact to one code step
    norm = 2.0 / _MAX16 * array[:, :, [2, 1]].astype(np.float64) - 1.0
    uv = norm * np.array([width - 1, height - 1], dtype=np.float64)
    uv[~valid] = 0.0
    flow = torch.from_numpy(np.ascontiguousarray(uv.transpose(2, 0, 1)).astype(np.float32))
    return flow, torch.from_numpy(valid).unsqueeze(0)


def write_vkitti2_flow(path: str | os.PathLike, flow: Tensor, valid: Tensor | None = None) -> Path:
    """Write a (2, H, W) flow in the Virtual KITTI 2 PNG encoding, atomically.

    ``valid`` (1, H, W) or (H, W) bool defaults to the finite pixels; flow must be finite at valid
    pixels (invalid pixels are written as 0 flow, whatever they held). Valid flow must lie within
    ±(W - 1) horizontally and ±(H - 1) vertically, the range of the encoding: an image 1 pixel
    wide (high) stores u = 0 (v = 0) only, since the reader scales by W - 1 = 0 (H - 1); else a
    ValueError naming ``flow``. ``path`` must end in .png (another suffix: a ValueError naming it).
    """
    path = check_image_suffix(path, (".png",), "Virtual KITTI 2 flow")
    flow = as_chw_flow(flow, "flow").detach().cpu().double()
    _, height, width = flow.shape
    valid_hw = flow_valid_pixels(flow, valid)
    stored = torch.where(valid_hw, flow, torch.zeros_like(flow))
    limit = torch.tensor([width - 1, height - 1], dtype=torch.float64, device="cpu").view(2, 1, 1)
    beyond = stored.abs() > limit
    if bool(beyond.any()):
        channel = 0 if bool(beyond[0].any()) else 1
        value = float(stored[channel][beyond[channel]].abs().max())
        raise ValueError(f"flow: the Virtual KITTI 2 encoding holds |u| <= {width - 1}, |v| <= {height - 1} px "
                         f"(the image's width and height less one); got |{'uv'[channel]}| = {value:.6g} at a "
                         f"valid pixel")
    norm = stored / limit.clamp_min(1)
    coded = ((norm + 1) / 2 * _MAX16).round().to(torch.int32).numpy().astype(np.uint16)
    bgr = np.stack([valid_hw.numpy().astype(np.uint16), coded[1], coded[0]], axis=2)
    return write_image_array(path, bgr)


def _read_table(path: str | os.PathLike, columns: int, what: str) -> tuple[np.ndarray, np.ndarray]:
    """A VKITTI2 table's rows (float64, one a row) and their line numbers. Each row starts with a
    frame number and a cameraID, whole numbers >= 0, and no (frame, cameraID) pair comes twice."""
    path = existing_file(path, f"VKITTI2 {what}")  # (a folder: IsADirectoryError; a broken link says so)
    rows = []
    lines = []
    seen: dict[tuple[float, float], int] = {}
    for n, line in enumerate(_read_text(path, what).splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        if n == 1 and not _is_number(parts[0]):
            continue  # the header line
        if len(parts) != columns:
            raise ValueError(f"path: line {n} of {str(path)!r} has {len(parts)} columns; a VKITTI2 {what} has {columns}")
        try:
            values = [float(x) for x in parts]
        except ValueError as err:
            raise ValueError(f"path: line {n} of {str(path)!r} is not a row of numbers: {line[:60]!r}") from err
        if not all(np.isfinite(values)):
            raise ValueError(f"path: line {n} of {str(path)!r} holds NaN or inf: {line[:60]!r}")
        frame, camera = values[0], values[1]
        if not (frame >= 0 and frame.is_integer() and camera >= 0 and camera.is_integer()):
            raise ValueError(f"path: line {n} of {str(path)!r} starts with frame {parts[0]!r}, cameraID {parts[1]!r}; "
                             f"expected whole numbers >= 0")
        if (frame, camera) in seen:
            raise ValueError(f"path: line {n} of {str(path)!r} repeats frame {int(frame)} of camera {int(camera)} "
                             f"(line {seen[frame, camera]}); expected one row each")
        seen[frame, camera] = n
        rows.append(values)
        lines.append(n)
    if not rows:
        raise ValueError(f"path: {str(path)!r} holds no rows")
    return np.asarray(rows, dtype=np.float64), np.asarray(lines, dtype=np.int64)


def _read_text(path: Path, what: str) -> str:
    try:
        return path.read_text(encoding="utf-8-sig")  # (a byte-order mark is skipped)
    except UnicodeDecodeError as err:
        raise ValueError(f"path: {str(path)!r} is not a text file (a VKITTI2 {what}; undecodable byte at offset "
                         f"{err.start})") from None


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _select_camera(table: tuple[np.ndarray, np.ndarray], camera: int, path) -> tuple[np.ndarray, np.ndarray]:
    """The rows of ``camera`` and their line numbers, sorted by frame."""
    if isinstance(camera, bool) or not isinstance(camera, numbers.Integral):
        raise TypeError(f"camera: expected an int, got {camera!r}")
    rows, lines = table
    mine = rows[:, 1] == int(camera)
    if not mine.any():
        cams = sorted({int(c) for c in rows[:, 1]})
        raise ValueError(f"camera: {str(path)!r} has no rows for camera {camera}; it has cameras {cams}")
    order = np.argsort(rows[mine, 0], kind="stable")
    return rows[mine][order], lines[mine][order]


def read_vkitti2_intrinsics(path: str | os.PathLike, camera: int = 0) -> tuple[Tensor, Tensor]:
    """``intrinsic.txt`` of one camera → ``(frames (N,) int64, K (N, 3, 3) float64)``, sorted by frame.

    ``camera`` is the int cameraID (0 left, 1 right): TypeError for anything else (``"0"``, True).
    A row whose frame or cameraID is no whole number >= 0, that repeats a (frame, cameraID), or
    whose focal lengths K[0,0], K[1,1] are not > 0 is a ValueError naming the file and the line.
    """
    rows, lines = _select_camera(_read_table(path, 6, "intrinsic.txt"), camera, path)
    bad = (rows[:, 2] <= 0) | (rows[:, 3] <= 0)
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"path: line {lines[i]} of {str(as_path(path))!r} has the focal lengths K[0,0] = "
                         f"{rows[i, 2]:g}, K[1,1] = {rows[i, 3]:g}; expected both > 0")
    K = np.zeros((len(rows), 3, 3))
    K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = rows[:, 2], rows[:, 3], rows[:, 4], rows[:, 5], 1.0
    return torch.from_numpy(rows[:, 0].astype(np.int64)), torch.from_numpy(K)


def read_vkitti2_extrinsics(path: str | os.PathLike, camera: int = 0) -> tuple[Tensor, Tensor]:
    """``extrinsic.txt`` of one camera → ``(frames (N,) int64, camera_T_world (N, 4, 4) float64)``;
    ``camera`` and the frame checks as in :func:`read_vkitti2_intrinsics`. Each matrix must be
    rigid as :func:`fsof_torch.io.read_kitti_poses` requires of a pose (last row 0 0 0 1, a
    rotation block: :func:`fsof_torch.io.kitti.check_rigid_poses`), else a ValueError naming the file
    and the line."""
    rows, lines = _select_camera(_read_table(path, 18, "extrinsic.txt"), camera, path)
    T = rows[:, 2:].reshape(-1, 4, 4)
    check_rigid_poses(torch.from_numpy(T), lambda i: f"path: line {lines[i]} of {str(as_path(path))!r}")
    return torch.from_numpy(rows[:, 0].astype(np.int64)), torch.from_numpy(T)


def vkitti2_camera_poses(camera_T_world: Tensor) -> Tensor:
    """Camera-to-world poses (N, 4, 4) (KITTI convention) from VKITTI2 world-to-camera extrinsics
    (N, 4, 4), in at least float32. Each must be a rigid pose (finite, last row 0 0 0 1, a rotation
    block: :func:`fsof_torch.io.kitti.check_rigid_poses`, as :func:`read_vkitti2_extrinsics` checks a
    file's), else a ValueError naming the first that is not."""
    if not isinstance(camera_T_world, Tensor) or not camera_T_world.is_floating_point():
        got = camera_T_world.dtype if isinstance(camera_T_world, Tensor) else type(camera_T_world).__name__
        raise TypeError(f"camera_T_world: expected a float tensor of shape (N, 4, 4), got {got}")
    if camera_T_world.dim() != 3 or tuple(camera_T_world.shape[-2:]) != (4, 4):
        raise ValueError(f"camera_T_world: expected shape (N, 4, 4), got {tuple(camera_T_world.shape)}")
    T = camera_T_world.to(result_dtype(camera_T_world))
    if not skip_values(T):
        check_rigid_poses(T, lambda i: f"camera_T_world: matrix {i}")
    return torch.linalg.inv_ex(T).inverse


def read_vkitti2_colors(path: str | os.PathLike) -> dict[str, tuple[int, int, int]]:
    """``colors.txt`` → ``{class name: (r, g, b)}`` in file order; components are integers in
    0..255 and each class comes once (else a ValueError naming the file and the line)."""
    path = existing_file(path, "VKITTI2 colors.txt")
    colors: dict[str, tuple[int, int, int]] = {}
    lines: dict[str, int] = {}
    for n, line in enumerate(_read_text(path, "colors.txt").splitlines(), 1):
        parts = line.split()
        if not parts or (n == 1 and parts[0] == "Category"):
            continue
        if len(parts) < 4:
            raise ValueError(f"path: line {n} of {str(path)!r} is not 'Name r g b': {line[:60]!r}")
        try:
            rgb = tuple(int(x) for x in parts[-3:])
        except ValueError as err:
            raise ValueError(f"path: line {n} of {str(path)!r} is not 'Name r g b': {line[:60]!r}") from err
        if not all(0 <= c <= 255 for c in rgb):  # packed into 24 bits, it would be another colour
            raise ValueError(f"path: line {n} of {str(path)!r} has a colour component outside 0..255: {line[:60]!r}")
        name = " ".join(parts[:-3])
        if name in lines:  # (the dict would keep the first one's place with the second one's colour)
            raise ValueError(f"path: line {n} of {str(path)!r} repeats the class {name!r} of line {lines[name]}; "
                             f"expected each class once")
        colors[name] = rgb
        lines[name] = n
    if not colors:
        raise ValueError(f"path: {str(path)!r} holds no classes")
    return colors


def read_vkitti2_classes(path: str | os.PathLike, colors: dict[str, tuple[int, int, int]]) -> Tensor:
    """A class segmentation PNG → (H, W) int64 class indices in the order of ``colors`` (-1: no class).

    ``labels == list(colors).index("Road")`` is the road mask. Each colour of ``colors`` must be
    three integers in 0..255 (else a ValueError naming ``colors[name]``).
    """
    _check_colors(colors)
    array = read_image_array(path, what="Virtual KITTI 2 class segmentation PNG")
    if array.ndim != 3 or array.shape[2] < 3 or array.dtype != np.uint8:
        raise ValueError(f"path: {str(path)!r} is {array.dtype} with shape {array.shape}; expected an 8-bit colour PNG")
    rgb = array[:, :, 2::-1].astype(np.int64)
    code = (rgb[:, :, 0] << 16) | (rgb[:, :, 1] << 8) | rgb[:, :, 2]
    labels = np.full(code.shape, -1, dtype=np.int64)
    for index, rgb in enumerate(colors.values()):
        r, g, b = (int(c) for c in rgb)  # (a NumPy uint8 would overflow when shifted)
        labels[code == ((r << 16) | (g << 8) | b)] = index
    return torch.from_numpy(labels)


def _check_colors(colors: object) -> None:
    """``colors`` a dict of class name -> (r, g, b), three ints in 0..255 (a component beyond them
    would take another colour's code once packed into 24 bits)."""
    if not isinstance(colors, Mapping):
        raise TypeError(f"colors: expected a dict of class name -> (r, g, b), got {type(colors).__name__}")
    for name, rgb in colors.items():
        if (not isinstance(rgb, (tuple, list)) or len(rgb) != 3
                or not all(isinstance(c, (int, np.integer)) and not isinstance(c, bool) and 0 <= c <= 255 for c in rgb)):
            raise ValueError(f"colors[{name!r}]: expected three integers in 0..255, got {rgb!r}")
