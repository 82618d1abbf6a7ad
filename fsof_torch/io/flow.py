"""Flow files by extension: ``.png`` (KITTI 16-bit), ``.flo`` (Middlebury), ``.npy`` (NumPy)."""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .atomic import file_target, write_bytes
from .._check import as_path, as_chw_flow, existing_file
from .flo import read_flo, write_flo
from .kitti import flow_valid_pixels, read_kitti_flow, write_kitti_flow

__all__ = ["read_flow", "write_flow"]

_UNKNOWN = 1e9  # |flow| from here up is unknown flow (Middlebury writes 1e10), read as not valid


def read_flow(path: str | os.PathLike) -> tuple[Tensor, Tensor]:
    """A flow file as ``(flow (2, H, W) float32 px, valid (1, H, W) bool)``, chosen by suffix.

    ``.png``: KITTI flow PNG (valid from its B channel). ``.flo``: Middlebury. ``.npy``: an array
    (2, H, W) or (H, W, 2) (a 2 on both ends is read as (2, H, W)), read as float32. For both
    ``.flo`` and ``.npy`` a pixel is valid where its flow is finite and below 1e9 px in magnitude
    in both channels (Middlebury marks unknown flow with 1e10). Non-valid pixels hold 0.
    """
    path = as_path(path)
    suffix = path.suffix.lower()
    if suffix == ".png":
        return read_kitti_flow(path)
    if suffix == ".flo":
        flow = read_flo(path)
    elif suffix == ".npy":
        existing_file(path)
        try:
            array = np.load(path, allow_pickle=False)
        except Exception as err:  # noqa: BLE001 - numpy's header parser raises EOFError, SyntaxError, ...
            raise ValueError(f"path: {str(path)!r} is not a readable .npy array "
                             f"({type(err).__name__}: {err or 'empty file'})") from None
        if not isinstance(array, np.ndarray):  # an .npz archive under a .npy name
            raise ValueError(f"path: {str(path)!r} is not a single .npy array")
        if array.ndim != 3 or 2 not in (array.shape[0], array.shape[2]):
            raise ValueError(f"path: {str(path)!r} holds an array of shape {array.shape}; expected (2, H, W) or (H, W, 2)")
        if not np.issubdtype(array.dtype, np.floating):
            raise ValueError(f"path: {str(path)!r} holds {array.dtype} values; expected floating-point flow")
        if 0 in array.shape:  # checked before the transpose: the message quotes the file's shape
            raise ValueError(f"path: {str(path)!r} holds an empty flow of shape {array.shape}; expected H, W >= 1")
        if array.shape[0] != 2:
            array = array.transpose(2, 0, 1)
        with np.errstate(over="ignore"):  # (a float64 value beyond float32's range: inf, not valid below)
            flow = torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32))
    else:
        raise ValueError(f"path: unknown flow file suffix {path.suffix!r} in {str(path)!r}; expected .png, .flo or .npy")
    valid = (torch.isfinite(flow) & (flow.abs() < _UNKNOWN)).all(dim=0, keepdim=True)
    return torch.where(valid, flow, torch.zeros_like(flow)), valid


def write_flow(path: str | os.PathLike, flow: Tensor | np.ndarray, valid: Tensor | np.ndarray | None = None) -> Path:
    """Write a (2, H, W) flow, chosen by suffix, atomically.

    ``.png``: KITTI (``valid`` kept, flow to 1/64 px). ``.flo`` and ``.npy``: float32, exact; a
    given ``valid`` is stored by writing NaN at invalid pixels (``read_flow`` gives them back as
    not valid); without ``valid`` every pixel with a finite flow is valid and the others are
    written as they are. Flow at valid pixels must be finite and below 1e9 px in magnitude after
    the float32 cast (else ValueError naming ``flow``, before anything is written):
    :func:`read_flow` would read it as not valid.
    """
    path = file_target(path)
    suffix = path.suffix.lower()
    if suffix == ".png":
        return write_kitti_flow(path, flow, valid)
    given = as_chw_flow(flow, "flow").detach().cpu()
    # valid: checked (finite flow where it is valid), or every finite pixel, before the cast
    valid_hw = torch.isfinite(given).all(dim=0) if valid is None else flow_valid_pixels(given, valid)
    flow = given.to(torch.float32)
    large = ~(flow.abs() < _UNKNOWN).all(dim=0) & valid_hw  # 1e9 and up, or beyond float32's range
    if bool(large.any()):
        value = float(given.double().abs().amax(dim=0)[large].max())
        raise ValueError(f"flow: expected |flow| < {_UNKNOWN:g} px at valid pixels after the float32 cast (a "
                         f".flo/.npy file marks larger values unknown), got {value:.4g}")
    if valid is not None:
        flow = torch.where(valid_hw, flow, torch.full_like(flow, float("nan")))
    if suffix == ".flo":
        return write_flo(path, flow)
    if suffix == ".npy":
        buffer = io.BytesIO()
        np.save(buffer, flow.numpy(), allow_pickle=False)
        return write_bytes(path, buffer.getvalue())
    raise ValueError(f"path: unknown flow file suffix {path.suffix!r} in {str(path)!r}; expected .png, .flo or .npy")
