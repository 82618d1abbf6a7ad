"""KITTI formats: flow PNGs, odometry poses, calibration files.

Flow PNG (DESIGN.md §8): 16-bit, 3 channels; in OpenCV's BGR order B = valid (0/1),
G = v·64 + 2^15, R = u·64 + 2^15. Flow is stored to 1/64 px (rounded to the nearest step, so
a round trip is exact to 1/128 px) in the range [-512, 512 - 1/64] px.

Poses: one row per frame, the 12 numbers of the 3×4 camera-to-world matrix [R | t] row by row
(KITTI odometry convention; ``cam1_T_cam0 = inv(P1) @ P0``).

Calibration: reading lives in :func:`fsof_torch.camera.read_kitti_calibration` (re-exported
here); :func:`write_kitti_calibration` writes a ``P_rect_02:``-style file that it reads back.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from .._check import all_finite, as_chw_flow, check_has_values, existing_file, tensor_from_array
from ..geometry.camera import Camera, check_camera_index, read_kitti_calibration
from .atomic import write_text
from .images import check_image_suffix, read_image_array, write_image_array

__all__ = [
    "read_kitti_flow",
    "write_kitti_flow",
    "read_kitti_poses",
    "write_kitti_poses",
    "check_rigid_poses",
    "check_kitti_flow_range",
    "read_kitti_calibration",
    "write_kitti_calibration",
    "KITTI_FLOW_SCALE",
    "KITTI_FLOW_MAX",
    "KITTI_FLOW_MIN",
]

KITTI_FLOW_SCALE = 64.0
_OFFSET = 2.0 ** 15
KITTI_FLOW_MAX = (65535 - _OFFSET) / KITTI_FLOW_SCALE  # 511.984375 px
KITTI_FLOW_MIN = -_OFFSET / KITTI_FLOW_SCALE  # -512 px
_ROTATION_TOL = 1e-3


def read_kitti_flow(path: str | os.PathLike) -> tuple[Tensor, Tensor]:
    """A KITTI flow PNG as ``(flow (2, H, W) float32 px, valid (1, H, W) bool)``.

    Flow at invalid pixels is returned as 0. Raises ValueError naming the path for a truncated
    PNG, an 8-bit PNG, or a PNG without exactly three channels.
    """
    array = read_image_array(path, what="KITTI flow PNG (16-bit, 3 channels)")
    if array.dtype != np.uint16:
        raise ValueError(f"path: {str(path)!r} is a {array.dtype} image ({8 * array.dtype.itemsize}-bit); "
                         f"a KITTI flow PNG is 16-bit")
    channels = 1 if array.ndim == 2 else array.shape[2]
    if channels != 3:
        raise ValueError(f"path: {str(path)!r} has {channels} channel(s); a KITTI flow PNG has 3 (valid, v, u)")
    valid = array[:, :, 0] > 0
    uv = (array[:, :, [2, 1]].astype(np.float32) - np.float32(_OFFSET)) / np.float32(KITTI_FLOW_SCALE)
    uv[~valid] = 0.0
    flow = torch.from_numpy(np.ascontiguousarray(uv.transpose(2, 0, 1)))
    return flow, torch.from_numpy(valid).unsqueeze(0)


def write_kitti_flow(path: str | os.PathLike, flow: Tensor | np.ndarray, valid: Tensor | np.ndarray | None = None) -> Path:
    """Write a flow as a KITTI 16-bit PNG atomically.

    Args:
        flow: (2, H, W) float, pixels, channel 0 = u.
        valid: (1, H, W) or (H, W) bool; default: every pixel with a finite flow.

    Flow is rounded to 1/64 px. Valid pixels must lie in [-512, 511.98] px (else ValueError);
    invalid pixels are written as 0 flow, whatever they held (NaN included). ``path`` must end in
    .png (the format is a 16-bit PNG).
    """
    path = check_image_suffix(path, (".png",), "KITTI flow")
    flow = as_chw_flow(flow, "flow").detach().cpu().double()
    valid_hw = flow_valid_pixels(flow, valid)
    check_kitti_flow_range(flow, valid_hw)
    stored = torch.where(valid_hw, flow, torch.zeros_like(flow))
    coded = (stored * KITTI_FLOW_SCALE + _OFFSET).round().clamp(0, 65535).to(torch.int32).numpy().astype(np.uint16)
    bgr = np.stack([valid_hw.numpy().astype(np.uint16), coded[1], coded[0]], axis=2)
    return write_image_array(path, bgr)


def check_kitti_flow_range(flow: Tensor, valid: Tensor, name: str = "flow") -> None:
    """ValueError naming ``name`` (and the range) unless ``flow`` (2, H, W) lies within
    [:data:`KITTI_FLOW_MIN`, :data:`KITTI_FLOW_MAX`] px, what a KITTI flow PNG holds, at every
    ``valid`` pixel ((H, W) bool, on the flow's device)."""
    held = flow[:, valid]
    if held.numel():
        lo, hi = float(held.min()), float(held.max())
        if lo < KITTI_FLOW_MIN or hi > KITTI_FLOW_MAX:
            raise ValueError(f"{name}: a KITTI flow PNG holds [{KITTI_FLOW_MIN}, {KITTI_FLOW_MAX}] px, got the range "
                             f"[{lo!r}, {hi!r}] at valid pixels")


def flow_valid_pixels(flow: Tensor, valid: Tensor | np.ndarray | None) -> Tensor:
    """The (H, W) bool pixels a flow writer stores as valid, checked (shared by the flow writers).

    Args:
        flow: (2, H, W) float flow.
        valid: (1, H, W) or (H, W) bool, or None: every pixel with a finite flow.

    Raises TypeError for a ``valid`` that is not bool, ValueError for one of another size than
    ``flow`` or for NaN or inf flow at a valid pixel.
    """
    _, height, width = flow.shape
    if valid is None:
        return torch.isfinite(flow).all(dim=0)
    if isinstance(valid, np.ndarray) and valid.dtype != np.bool_:  # (an object array: torch's own TypeError)
        raise TypeError(f"valid: expected a bool tensor of shape (1, H, W), got a NumPy array of dtype {valid.dtype}")
    if isinstance(valid, np.ndarray):
        valid = tensor_from_array(valid)
    if not isinstance(valid, Tensor) or valid.dtype != torch.bool:
        raise TypeError(f"valid: expected a bool tensor of shape (1, H, W), got "
                        f"{valid.dtype if isinstance(valid, Tensor) else type(valid).__name__}")
    if tuple(valid.shape) not in ((1, height, width), (height, width)):
        raise ValueError(f"valid: expected shape (1, {height}, {width}) to match flow, got {tuple(valid.shape)}")
    check_has_values(valid, "valid")
    valid_hw = valid.detach().cpu().reshape(height, width)
    # the per-pixel test only when some value is not finite (one reduction otherwise)
    if not all_finite(flow) and not bool((torch.isfinite(flow).all(dim=0) | ~valid_hw).all()):
        raise ValueError("flow: expected finite values at valid pixels, got NaN or inf")
    return valid_hw


def read_kitti_poses(path: str | os.PathLike) -> Tensor:
    """Poses of a KITTI odometry file as (N, 4, 4) float64 camera-to-world matrices.

    Each non-empty line holds 12 numbers (the 3×4 [R | t] row by row). Also accepted, for other
    data sets written in the same spirit: 16 numbers (the full 4×4, last row 0 0 0 1), or 13 / 17
    numbers with a leading frame index. Poses pair with frames by position, so the indices must
    be 0, 1, 2, ... in order, and every row of a file has the same length. ``#`` starts a
    comment; a UTF-8 byte-order mark is skipped.

    Raises ValueError naming the path (and the line) for a binary file, a row of the wrong
    length or of another length than the first row, a frame index out of sequence (a gap, a
    repeat, a fraction, a negative number), and (naming the first such line) non-finite values,
    a 16-number row whose last four are not 0 0 0 1, or a 3×3 block that is not a rotation
    (|RᵀR − I| > 1e-3 or det R <= 0: an all-zero block is singular); see :func:`check_rigid_poses`.
    """
    path = existing_file(path, "poses file")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as err:
        raise ValueError(f"path: {str(path)!r} is not a text poses file (undecodable byte at offset "
                         f"{err.start})") from None
    rows = []
    lines = []
    row_length = 0
    for n, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        numbers = line.replace(",", " ").split()
        try:
            values = [float(x) for x in numbers]
        except ValueError as err:
            raise ValueError(f"path: line {n} of {str(path)!r} is not a row of numbers: {line[:60]!r}") from err
        if len(values) not in (12, 13, 16, 17):
            raise ValueError(f"path: line {n} of {str(path)!r} has {len(values)} numbers; expected 12 (KITTI 3×4 pose)")
        if rows and len(values) != row_length:
            raise ValueError(f"path: line {n} of {str(path)!r} has {len(values)} numbers but line {lines[0]} has "
                             f"{row_length}; expected rows of one length in a file")
        row_length = len(values)
        if len(values) in (13, 17):  # a leading frame index: the poses pair with frames by position
            if values[0] != len(rows):
                raise ValueError(f"path: line {n} of {str(path)!r} has the frame index {numbers[0]!r}; expected "
                                 f"{len(rows)} (indices 0, 1, 2, ... in order: poses pair with frames by position)")
            values = values[1:]
        if len(values) == 12:
            values = values + [0.0, 0.0, 0.0, 1.0]
        rows.append(values)
        lines.append(n)
    if not rows:
        raise ValueError(f"path: {str(path)!r} holds no poses")
    poses = torch.tensor(rows, dtype=torch.float64, device="cpu").reshape(-1, 4, 4)
    check_rigid_poses(poses, lambda i: f"path: line {lines[i]} of {str(path)!r}")
    return poses


def check_rigid_poses(poses: Tensor, describe: Callable[[int], str]) -> None:
    """Check (N, 4, 4) camera-to-world poses the way :func:`read_kitti_poses` checks a file's: each
    pose finite, its last row 0 0 0 1 (to 1e-9, 1e-5 relative) and its 3×3 block a rotation
    (|RᵀR − I| ≤ 1e-3, det R > 0). Raises a ValueError whose message starts with ``describe(i)``
    for the first pose ``i`` that fails (``"path: line 3 of 'poses.txt'"``, ``"poses: pose 2"``).
    Shared by the poses reader and writer and by the datasets that take poses."""
    poses = poses.detach().to("cpu", torch.float64)
    finite = torch.isfinite(poses).flatten(1).all(dim=1)
    values = torch.where(finite.view(-1, 1, 1), poses, torch.eye(4, dtype=torch.float64, device="cpu"))  # (NaN compares False)
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64, device="cpu")
    rigid_row = torch.isclose(values[:, 3], bottom.expand(len(values), 4), rtol=1e-5, atol=1e-9).all(dim=1)
    # The 3×3 block must be a rotation: an all-zero or scaled block is singular or not rigid, and
    # relative poses (its inverse) would be inf or wrong. KITTI's rows, printed to 7 digits, are
    # orthonormal to 2e-7; the tolerance leaves room for other writers' rounding.
    R = values[:, :3, :3]
    error = (R.transpose(1, 2) @ R - torch.eye(3, dtype=R.dtype, device="cpu")).abs().flatten(1).amax(dim=1)
    det = torch.linalg.det(R)
    bad = (~(finite & rigid_row & (error <= _ROTATION_TOL) & (det > 0))).nonzero().flatten()
    if not bad.numel():
        return
    i = int(bad[0])  # the first bad pose, whatever is wrong with it
    if not bool(finite[i]):
        raise ValueError(f"{describe(i)} holds NaN or inf")
    if not bool(rigid_row[i]):
        raise ValueError(f"{describe(i)} is not a rigid pose: its last row is "
                         f"{' '.join(f'{x:g}' for x in poses[i, 3].tolist())}, not 0 0 0 1")
    raise ValueError(f"{describe(i)} is not a rigid pose: its 3×3 block is not a rotation (|RᵀR − I| up to "
                     f"{float(error[i]):.3g}, det {float(det[i]):.3g}; an all-zero block is singular)")


def write_kitti_poses(path: str | os.PathLike, poses: Tensor | np.ndarray) -> Path:
    """Write (N, 4, 4) or (N, 3, 4) camera-to-world poses in the KITTI odometry format, atomically
    (12 numbers a row, each with Python's ``repr``: the shortest text that reads back as the same
    float64, so a round trip is exact, as :func:`write_kitti_calibration`'s).

    The poses must be what :func:`read_kitti_poses` reads back: finite, a rotation block, and for
    (N, 4, 4) the last row 0 0 0 1 (the format does not store it); else a ValueError naming
    ``poses`` and the first bad pose (:func:`check_rigid_poses`), before anything is written."""
    if isinstance(poses, np.ndarray):
        poses = tensor_from_array(poses)
    if not isinstance(poses, Tensor) or not poses.is_floating_point():
        raise TypeError(f"poses: expected a float tensor of shape (N, 4, 4), got "
                        f"{poses.dtype if isinstance(poses, Tensor) else type(poses).__name__}")
    if poses.dim() == 2 and poses.shape[-2:] in ((4, 4), (3, 4)):
        poses = poses.unsqueeze(0)
    if poses.dim() != 3 or tuple(poses.shape[-2:]) not in ((4, 4), (3, 4)):
        raise ValueError(f"poses: expected shape (N, 4, 4) or (N, 3, 4), got {tuple(poses.shape)}")
    if poses.shape[0] == 0:
        raise ValueError(f"poses: expected at least one pose, got shape {tuple(poses.shape)}")
    check_has_values(poses, "poses")
    full = poses.detach().cpu().double()
    if full.shape[1] == 3:  # the last row the format leaves out
        full = torch.cat([full, torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64, device="cpu").expand(len(full), 1, 4)], dim=1)
    check_rigid_poses(full, lambda i: f"poses: pose {i}")
    rows = full[:, :3, :].reshape(-1, 12).tolist()
    text = "".join(" ".join(repr(float(x)) for x in row) + "\n" for row in rows)
    return write_text(path, text)


def write_kitti_calibration(path: str | os.PathLike, K: Tensor | np.ndarray, *, cam: int = 2,
                            style: str = "cam_to_cam") -> Path:
    """Write a KITTI calibration file atomically with the rectified projection ``P = [K | 0]``.

    Args:
        K: (3, 3) or (3, 4) (a 3×4 projection is written as is).
        cam: camera index of the row (``P_rect_0{cam}`` / ``P{cam}``).
        style: ``"cam_to_cam"`` (raw ``calib_cam_to_cam.txt`` rows ``P_rect_0N:``) or
            ``"odometry"`` (``calib.txt`` rows ``PN:``; rows P0..P{cam} are all written with this
            projection, so files stay readable by tools that count rows).

    ``K`` (the first three columns of a 3×4) must be what :meth:`fsof_torch.camera.Camera.from_kitti`
    reads back as a camera: finite, focal lengths > 0, upper-triangular with ``K[2, 2] = 1`` (a
    transposed K, principal point in the last row, is not), else a ValueError naming ``K``, before
    anything is written.

    Numbers are written with Python's ``repr`` (the shortest text that reads back as the same
    float64, e.g. ``721.5377``, ``240.51256666666666``), so
    :func:`fsof_torch.camera.read_kitti_calibration` (and any reader of whitespace-separated
    floats) reads the result back exactly.
    """
    if isinstance(K, np.ndarray):
        K = tensor_from_array(K)
    if not isinstance(K, Tensor) or not K.is_floating_point():
        raise TypeError(f"K: expected a float tensor of shape (3, 3), got "
                        f"{K.dtype if isinstance(K, Tensor) else type(K).__name__}")
    check_has_values(K, "K")
    if K.dim() == 3 and K.shape[0] == 1:
        K = K[0]
    if tuple(K.shape) == (3, 3):
        P = torch.cat([K.double(), torch.zeros(3, 1, dtype=torch.float64, device=K.device)], dim=1)
    elif tuple(K.shape) == (3, 4):
        P = K.double()
    else:
        raise ValueError(f"K: expected shape (3, 3) or (3, 4), got {tuple(K.shape)}")
    if not bool(torch.isfinite(P).all()):  # the reader refuses a row holding NaN or inf
        raise ValueError(f"K: expected finite values, got {P[:, :3].tolist() if K.shape[1] == 3 else P.tolist()}")
    try:  # the constructor's checks of K, which Camera.from_kitti and the datasets apply to the file
        Camera(P[:, :3], 1.0)
    except ValueError as err:
        raise ValueError(f"{err}; a file of it would not read back as a camera (Camera.from_kitti)") from None
    cam = check_camera_index(cam)
    row = " ".join(repr(x) for x in P.detach().cpu().reshape(-1).tolist())
    if style == "cam_to_cam":
        text = f"P_rect_0{cam}: {row}\n"
    elif style == "odometry":
        text = "".join(f"P{i}: {row}\n" for i in range(int(cam) + 1))
    else:
        raise ValueError(f"style: expected 'cam_to_cam' or 'odometry', got {style!r}")
    return write_text(path, text)
