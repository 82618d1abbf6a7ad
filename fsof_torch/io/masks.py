"""Road (freespace) masks and label maps: PNG masks, polygon JSON, colour-coded segmentation.

Polygon JSON (like ``shared/data/*/road.json``): ``{"size": [H, W], "road_polygon": [[u, v],
...]}`` in pixel coordinates (u right, v down, origin at the centre of the top-left pixel); also
accepted: ``"polygon"`` or ``"polygons"`` / ``"road_polygons"`` (a list of polygons, filled as a
union). Rasterised with ``cv2.fillPoly`` at 1/16 px vertex precision.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import torch
from torch import Tensor

from .images import read_image_array, write_image_array

__all__ = ["read_road_mask", "write_road_mask", "rasterize_polygons", "mask_from_colors",
           "read_label_map", "write_label_map"]

_SHIFT = 4  # fixed-point bits of cv2.fillPoly vertices: 1/16 px


def rasterize_polygons(polygons: Iterable[Sequence[Sequence[float]]], size: tuple[int, int]) -> Tensor:
    """Fill polygons of pixel coordinates (u, v) into a (1, H, W) bool mask (``cv2.fillPoly``)."""
    import cv2

    height, width = size
    canvas = np.zeros((height, width), dtype=np.uint8)
    pts = []
    for poly in polygons:
        arr = np.asarray(poly, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] < 3:
            raise ValueError(f"polygons: expected lists of at least three (u, v) points, got shape {arr.shape}")
        pts.append(np.round(arr * (1 << _SHIFT)).astype(np.int32))
    if pts:
        cv2.fillPoly(canvas, pts, 1, lineType=cv2.LINE_8, shift=_SHIFT)
    return torch.from_numpy(canvas > 0).unsqueeze(0)


def _polygons_from_json(obj: dict, path: Path) -> list:
    for key in ("road_polygon", "polygon"):
        if key in obj:
            return [obj[key]]
    for key in ("road_polygons", "polygons"):
        if key in obj:
            return list(obj[key])
    raise ValueError(f"path: {str(path)!r} has no 'road_polygon', 'polygon' or 'polygons' entry")


def read_road_mask(path: str | os.PathLike, size: tuple[int, int] | None = None) -> Tensor:
    """A road mask as (1, H, W) bool.

    Args:
        path: a PNG (any channel nonzero = road) or a polygon JSON (see the module docstring).
        size: (H, W) wanted. A PNG of another size is resized with nearest-neighbour sampling. A
            JSON's polygon is drawn at its own ``"size"`` scaled to ``size`` (pixel centres map as
            ``u' + 0.5 = s (u + 0.5)``); a JSON without ``"size"`` needs ``size``.
    """
    import cv2

    path = Path(path)
    if size is not None:
        size = (int(size[0]), int(size[1]))
        if size[0] <= 0 or size[1] <= 0:
            raise ValueError(f"size: expected positive (H, W), got {size!r}")
    if path.suffix.lower() == ".json":
        if not path.is_file():
            raise FileNotFoundError(f"path: no file at {str(path)!r}")
        try:
            obj = json.loads(path.read_text())
        except json.JSONDecodeError as err:
            raise ValueError(f"path: {str(path)!r} is not valid JSON: {err}") from err
        polygons = _polygons_from_json(obj, path)
        own = obj.get("size")
        if own is None and size is None:
            raise ValueError(f"path: {str(path)!r} has no 'size' entry; pass size=(H, W)")
        own = tuple(int(s) for s in own) if own is not None else size
        target = size or own
        sy, sx = target[0] / own[0], target[1] / own[1]
        scaled = [[[sx * (u + 0.5) - 0.5, sy * (v + 0.5) - 0.5] for u, v in poly] for poly in polygons]
        return rasterize_polygons(scaled, target)
    array = read_image_array(path, what="road mask image")
    if array.ndim == 3:
        array = array.max(axis=2)
    mask = array > 0
    if size is not None and mask.shape != size:
        mask = cv2.resize(mask.astype(np.uint8), (size[1], size[0]), interpolation=cv2.INTER_NEAREST) > 0
    return torch.from_numpy(np.ascontiguousarray(mask)).unsqueeze(0)


def write_road_mask(path: str | os.PathLike, mask: Tensor) -> Path:
    """Write a (1, H, W) or (H, W) bool mask as an 8-bit PNG (road = 255), atomically."""
    if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
        raise TypeError(f"mask: expected a bool tensor of shape (1, H, W), got "
                        f"{mask.dtype if isinstance(mask, Tensor) else type(mask).__name__}")
    if mask.dim() == 3 and mask.shape[0] == 1:
        mask = mask[0]
    if mask.dim() != 2:
        raise ValueError(f"mask: expected shape (1, H, W) or (H, W), got {tuple(mask.shape)}")
    return write_image_array(path, mask.detach().cpu().numpy().astype(np.uint8) * 255)


def mask_from_colors(rgb: Tensor | np.ndarray, colors: Iterable[Sequence[int]]) -> Tensor:
    """(1, H, W) bool: pixels of a colour-coded segmentation equal to any of ``colors`` (RGB).

    Args:
        rgb: (3, H, W) RGB tensor (0..255, as :func:`fsof_torch.io.read_image` gives) or an
            (H, W, 3) uint8 RGB array.
    """
    if isinstance(rgb, Tensor):
        if rgb.dim() != 3 or rgb.shape[0] != 3:
            raise ValueError(f"rgb: expected shape (3, H, W), got {tuple(rgb.shape)}")
        array = rgb.detach().cpu().round().to(torch.int64).permute(1, 2, 0).numpy()
    else:
        array = np.asarray(rgb).astype(np.int64)
    mask = np.zeros(array.shape[:2], dtype=bool)
    for color in colors:
        mask |= (array == np.asarray(color, dtype=np.int64).reshape(1, 1, 3)).all(axis=2)
    return torch.from_numpy(mask).unsqueeze(0)


def read_label_map(path: str | os.PathLike) -> Tensor:
    """A single-channel 8- or 16-bit label PNG as an (H, W) int64 tensor."""
    array = read_image_array(path, what="label map (single-channel 8/16-bit PNG)")
    if array.ndim != 2 or array.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"path: {str(path)!r} is {array.dtype} with shape {array.shape}; expected a "
                         f"single-channel 8- or 16-bit label map")
    return torch.from_numpy(array.astype(np.int64))


def write_label_map(path: str | os.PathLike, labels: Tensor) -> Path:
    """Write (H, W) integer labels as a PNG atomically: 8-bit when all labels fit, else 16-bit."""
    if not isinstance(labels, Tensor) or labels.is_floating_point() or labels.dtype == torch.bool:
        raise TypeError(f"labels: expected an integer tensor of shape (H, W), got "
                        f"{labels.dtype if isinstance(labels, Tensor) else type(labels).__name__}")
    if labels.dim() == 3 and labels.shape[0] == 1:
        labels = labels[0]
    if labels.dim() != 2:
        raise ValueError(f"labels: expected shape (H, W), got {tuple(labels.shape)}")
    lo, hi = int(labels.min()), int(labels.max())
    if lo < 0 or hi > 65535:
        raise ValueError(f"labels: expected values in 0..65535, got the range [{lo}, {hi}]")
    dtype = np.uint8 if hi <= 255 else np.uint16
    return write_image_array(path, labels.detach().cpu().numpy().astype(dtype))
