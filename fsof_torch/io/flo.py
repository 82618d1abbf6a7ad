"""Middlebury ``.flo`` optical flow files (float32 little-endian, magic 202021.25).

Layout: the 4-byte magic ``202021.25`` (bytes ``PIEH``), the width and the height as int32, then
H·W·2 float32 values, row by row, u and v interleaved. The reader checks the magic and that the
file length is exactly 12 + 8·W·H bytes, before it reads the data (another file under a .flo name
is refused without being read into memory).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .._check import as_chw_flow, existing_file
from .atomic import atomic_path, file_target

__all__ = ["read_flo", "write_flo", "FLO_MAGIC"]

FLO_MAGIC = 202021.25
_HEADER = 12


def read_flo(path: str | os.PathLike) -> Tensor:
    """A Middlebury ``.flo`` file as a (2, H, W) float32 tensor in pixels (channel 0 = u).

    The values come as stored: unknown flow (NaN, inf, or Middlebury's values above 1e9) stays;
    :func:`~fsof_torch.io.read_flow` turns it into a validity mask. Raises ValueError naming the
    path for a wrong magic number, a non-positive size or a file whose length does not match the
    size in its header.
    """
    # the header is checked against the file's length before the data is read: another file
    # under a .flo name (a video of gigabytes) is refused without reading it into memory
    with open(existing_file(path), "rb") as f:
        header = f.read(_HEADER)
        length = os.fstat(f.fileno()).st_size
        if len(header) < _HEADER:
            raise ValueError(f"path: {str(path)!r} is too short for a .flo file ({len(header)} bytes, header needs 12)")
        magic = np.frombuffer(header, dtype="<f4", count=1)[0]
        if magic != np.float32(FLO_MAGIC):
            raise ValueError(f"path: {str(path)!r} has the magic number {float(magic)!r} ({header[:4]!r}); "
                             f"expected {FLO_MAGIC} (b'PIEH') for a .flo file")
        width, height = (int(x) for x in np.frombuffer(header, dtype="<i4", count=2, offset=4))
        if width <= 0 or height <= 0:
            raise ValueError(f"path: {str(path)!r} declares a size of {width}x{height}; expected positive sides")
        expected = _HEADER + 8 * width * height
        if length == expected:
            data = f.read(expected - _HEADER + 1)  # (+1: a file that grew since is read as too long)
            length = _HEADER + len(data)
        if length != expected:
            raise ValueError(f"path: {str(path)!r} has {length} bytes, but its header declares {width}x{height} "
                             f"flow ({expected} bytes): truncated or not a .flo file")
    flow = np.frombuffer(data, dtype="<f4").reshape(height, width, 2)
    return torch.from_numpy(np.ascontiguousarray(flow.transpose(2, 0, 1)).astype(np.float32))


def float32_flow(flow: Tensor | np.ndarray, what: str) -> Tensor:
    """A (2, H, W) flow as a float32 CPU tensor for a file of float32 (``what``: "a .flo file"):
    a finite value beyond float32's range (about 3.4e38), which the cast would turn into inf, is a
    ValueError naming ``flow``; NaN and inf stay as they are."""
    flow = as_chw_flow(flow, "flow").detach().cpu()
    cast = flow.to(torch.float32)
    overflow = torch.isfinite(flow) & ~torch.isfinite(cast)
    if bool(overflow.any()):
        raise ValueError(f"flow: {what} stores float32, which cannot hold {float(flow[overflow][0]):.4g} "
                         f"(finite values up to {torch.finfo(torch.float32).max:.4g})")
    return cast


def write_flo(path: str | os.PathLike, flow: Tensor | np.ndarray) -> Path:
    """Write a (2, H, W) flow in pixels to a Middlebury ``.flo`` file atomically.

    The file stores float32: float32 values are written exactly, others rounded to the nearest
    float32. NaN and inf are written as they are, and so are values of 1e9 and above, which
    :func:`read_flo` returns as stored but :func:`~fsof_torch.io.read_flow` reads as unknown flow
    (Middlebury's convention; :func:`~fsof_torch.io.write_flow` refuses them at valid pixels). A
    finite value beyond float32's range (about 3.4e38), which the cast would turn into inf, is a
    ValueError naming ``flow``, before anything is written.
    """
    cast = float32_flow(flow, "a .flo file")
    _, height, width = cast.shape
    array = cast.numpy().transpose(1, 2, 0)
    header = np.array([FLO_MAGIC], dtype="<f4").tobytes() + np.array([width, height], dtype="<i4").tobytes()
    path = file_target(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(header)
        f.write(np.ascontiguousarray(array, dtype="<f4").tobytes())
    return path
