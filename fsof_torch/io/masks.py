"""Road (freespace) masks and label maps: PNG masks, polygon JSON, colour-coded segmentation.

Polygon JSON. Coordinates are pixels (u right, v down, origin at the centre of the top-left
pixel); a polygon is a list of at least three ``[u, v]`` points (finite numbers). A file holds
exactly one of these, with at least one polygon (several polygons are filled as a union; two of
the keys below, or none of their polygons, is a ValueError). A polygon is an outline: one whose
edges cross (a bow tie of swapped vertices) is a ValueError naming the two edges (there are no
holes: a car on the road is left out by giving the road around it as several polygons). A
LabelMe file (``"shapes"``) is a ValueError saying so, not a guess at which labels are road.
The file is UTF-8 text; a byte-order mark is skipped. The layouts:

1. ``{"size": [H, W], "road_polygon": [[u, v], ...]}`` (or ``"polygon"``): one polygon. Other
   keys (``"image"``, ``"note"``, ...) are ignored. This is the format of ``shared/data/*/road.json``.
2. ``{"size": [H, W], "polygons": [[[u, v], ...], ...]}`` (or ``"road_polygons"``): a list of
   polygons.
3. ``{"size": [H, W], "polygons": {"ego_lane": [[u, v], ...], "left_lane": [...]}}``: named
   polygons under ``"polygons"``; or the names at the top level, ``{"size": [H, W], "ego_lane":
   [...], ...}``, when none of the keys above is present (then every key but ``"size"`` must
   name a polygon).
4. ``[[[u, v], ...], ...]``: a bare list of polygons (no size in the file: pass ``size``).

``"size"`` is ``[H, W]``, two positive integers (not floats), at most 65536 each and 2**28
pixels (H * W) in all, so that a corrupt size cannot allocate gigabytes (the same bound holds for
the ``size`` argument). A key that one JSON object holds twice (two ``"road_polygon"`` entries) is
a ValueError naming the file and the key. Every malformed input raises a ValueError or
TypeError that names the file and the offending entry. Polygons may reach far outside the image:
they are clipped to the image (Sutherland–Hodgman, in float64) before they are rasterised with
``cv2.fillPoly`` at 1/16 px vertex precision, so a polygon enclosing the image at ±2e8 px fills it
instead of overflowing OpenCV's 32-bit fixed-point vertices. OpenCV's scan conversion decides the
pixels near the outline to about 0.5 px inside and 1.3 px outside it (:func:`rasterize_polygons`).
Coordinates beyond ±1e15 px (where float64 no longer resolves a pixel) are rejected, in the file
and after :func:`read_road_mask` scales them to its ``size`` (``resize=True``). A polygon is drawn
for the image size its ``"size"`` states: read at another size it is an error unless the caller
asks to scale it (``resize=True``).
"""

from __future__ import annotations

import json
import math
import numbers
import os
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np
import torch
from torch import Tensor

from .._check import as_path, check_bool, check_has_values, tensor_from_array
from .images import check_image_suffix, existing_file, read_image_array, write_image_array

__all__ = ["read_road_mask", "write_road_mask", "rasterize_polygons", "mask_from_colors",
           "read_label_map", "write_label_map"]

_SHIFT = 4  # fixed-point bits of cv2.fillPoly vertices: 1/16 px
_MAX_COORD = 1e15  # beyond it float64 resolves less than a pixel
_ONE = ("road_polygon", "polygon")
_MANY = ("road_polygons", "polygons")


def _as_polygon(poly: object, where: str) -> np.ndarray:
    """(N, 2) float64 vertices from a list of [u, v] points or an (N, 2) array, checked; ``where``
    names the polygon in errors."""
    if isinstance(poly, Tensor):
        check_has_values(poly, where)
        poly = poly.detach().cpu().numpy()
    if isinstance(poly, np.ndarray):
        if poly.ndim != 2 or poly.shape[1] != 2 or not (np.issubdtype(poly.dtype, np.integer)
                                                        or np.issubdtype(poly.dtype, np.floating)):
            raise ValueError(f"{where}: expected an (N, 2) array of numeric (u, v) points, got "
                             f"{poly.dtype} of shape {poly.shape}")
        points = [tuple(p) for p in poly.astype(np.float64).tolist()]
    elif isinstance(poly, (list, tuple)):
        points = poly
    else:
        raise TypeError(f"{where}: expected a list of [u, v] points, got {type(poly).__name__} {poly!r:.60}")
    if len(points) < 3:
        raise ValueError(f"{where}: expected at least three (u, v) points, got {len(points)}")
    for i, point in enumerate(points):
        if not isinstance(point, (list, tuple)) or len(point) != 2:
            raise ValueError(f"{where}[{i}]: expected a point [u, v] (two numbers), got {point!r:.60}")
        for c in point:
            if isinstance(c, bool) or not isinstance(c, numbers.Real):
                raise TypeError(f"{where}[{i}]: expected numeric coordinates [u, v], got {point!r:.60}")
            try:
                finite = math.isfinite(c)
            except OverflowError:  # an integer beyond float64 (JSON allows any): finite, and far off
                finite = True
            if not finite:
                raise ValueError(f"{where}[{i}]: expected finite coordinates, got {point!r:.60}")
            if abs(c) > _MAX_COORD:  # exact for ints of any size
                raise ValueError(f"{where}[{i}]: coordinates beyond ±{_MAX_COORD:g} px are not pixels, "
                                 f"got {point!r:.60}")
    return np.asarray(points, dtype=np.float64).reshape(-1, 2)


def _check_simple(poly: np.ndarray, where: str) -> None:
    """A road outline that crosses itself is a mistake (two vertices swapped make a bow tie of a
    quadrilateral), which filling would turn into another road: a ValueError naming ``where`` and
    the two edges."""
    d = poly - poly[0]
    u = d[np.argmax(np.hypot(d[:, 0], d[:, 1]))]  # (to the vertex farthest from the first)
    if np.abs(d[:, 0] * u[1] - d[:, 1] * u[0]).max() <= 1e-12 * float(u @ u):  # (0 <= 0: one point)
        raise ValueError(f"{where}: encloses no area (its points lie on one line), so it would fill only the "
                         f"pixels along that line; expected the outline of the road, got {poly.tolist()!r:.80}")
    crossing = _crossing(poly)
    if crossing is not None:
        edge = [f"{k} ({poly[k].tolist()} to {poly[(k + 1) % len(poly)].tolist()})" for k in crossing]
        raise ValueError(f"{where}: crosses itself (its edges {edge[0]} and {edge[1]}), so its parts would be "
                         f"filled by turns (two vertices swapped make a bow tie of an outline); give the outline "
                         f"in order, or its parts as separate polygons")


def _crossing(poly: np.ndarray) -> tuple[int, int] | None:
    """Two edges (i < j, the first such i; edge k runs from vertex k to k + 1) of a polygon (N, 2)
    that cross at a point inside both, or None. Edges that only touch (a vertex on another edge,
    adjacent edges, collinear overlaps, a closing vertex repeated) do not count. Only edges whose
    extents in u overlap are compared (found by sorting): a few per edge for an outline."""
    a = poly
    b = np.roll(poly, -1, axis=0)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    # cross products within rounding of exactly collinear count as 0 (the polygon's extent squared)
    tol = 1e-12 * float(np.ptp(poly, axis=0).max()) ** 2

    def side(o: np.ndarray, p: np.ndarray, q: np.ndarray) -> np.ndarray:
        """which side of the line o -> p the point q lies on: 1, -1, or 0 (on it)"""
        c = (p[:, 0] - o[:, 0]) * (q[:, 1] - o[:, 1]) - (p[:, 1] - o[:, 1]) * (q[:, 0] - o[:, 0])
        return np.where(np.abs(c) <= tol, 0.0, np.sign(c))

    order = np.argsort(lo[:, 0], kind="stable")
    starts = lo[order, 0]
    # in u order, edge p overlaps the edges p + 1 .. end[p] - 1 (those starting before it ends)
    end = np.searchsorted(starts, hi[order, 0], side="right")
    counts = np.maximum(end - np.arange(len(poly)) - 1, 0)
    found = []
    for first in range(0, len(poly), 4096):  # (bounded memory for long edges, which overlap many)
        rows = np.arange(first, min(len(poly), first + 4096))
        c = counts[rows]
        pos = np.repeat(rows, c)
        nxt = pos + 1 + np.arange(int(c.sum())) - np.repeat(np.cumsum(c) - c, c)
        i, j = order[pos], order[nxt]
        keep = (lo[i, 1] <= hi[j, 1]) & (lo[j, 1] <= hi[i, 1])
        i, j = i[keep], j[keep]
        proper = ((side(a[i], b[i], a[j]) * side(a[i], b[i], b[j]) < 0)
                  & (side(a[j], b[j], a[i]) * side(a[j], b[j], b[i]) < 0))
        found += sorted(zip(np.minimum(i, j)[proper].tolist(), np.maximum(i, j)[proper].tolist()))[:1]
    return min(found) if found else None


def _clip(poly: np.ndarray, lo: tuple[float, float], hi: tuple[float, float]) -> np.ndarray:
    """Sutherland–Hodgman clipping of a polygon (N, 2) to the box [lo, hi] (u, v), in float64.

    Correct for any polygon against a convex box (concave ones may gain edges along the box's
    border, which lies outside every pixel centre here and so changes no pixel)."""
    for axis in (0, 1):
        for bound, inside in ((lo[axis], lambda x, b: x >= b), (hi[axis], lambda x, b: x <= b)):
            if len(poly) == 0:
                return poly
            out = []
            prev = poly[-1]
            for cur in poly:
                cur_in, prev_in = inside(cur[axis], bound), inside(prev[axis], bound)
                if cur_in != prev_in:
                    t = (bound - prev[axis]) / (cur[axis] - prev[axis])
                    point = prev + t * (cur - prev)
                    point[axis] = bound  # exactly on the border, whatever the rounding of t
                    out.append(point)
                if cur_in:
                    out.append(cur)
                prev = cur
            poly = np.asarray(out, dtype=np.float64).reshape(-1, 2)
    return poly


def rasterize_polygons(polygons: Iterable[Sequence[Sequence[float]]], size: tuple[int, int]) -> Tensor:
    """Fill polygons of pixel coordinates (u, v) into a (1, H, W) bool mask (``cv2.fillPoly``).

    The mask is the union of the polygons, each filled on its own (where two overlap, both fill).
    A pixel is filled where its centre is inside a polygon, and also where the polygon's outline
    passes through it (OpenCV draws the outline's pixels too), within the tolerance of OpenCV's
    scan conversion, which works at whole pixels (vertices on a 1/16 px grid, but the rows of
    vertices and the outline's pixels rounded to whole pixels, and edges leaving the image cut at
    whole pixels): a pixel whose centre lies up to about 0.5 px inside a polygon's outline may stay
    empty, and one whose centre lies up to about 1.3 px outside it may be filled. Measured on
    random triangles (distance of the pixel centre from the outline): at most 0.33 px inside and
    1.13 px outside for triangles within the image, 0.52 px and 1.33 px for triangles reaching
    beyond it. Polygons are clipped to the image first, so any finite coordinates up to ±1e15 px
    work. A polygon that crosses itself is filled by the even-odd rule (a pentagram's centre stays
    empty); :func:`read_road_mask` refuses such a road outline. ``size`` (H, W) is at most 65536
    a side and 2**28 pixels in all.
    """
    import cv2

    height, width = _check_size(size, "size")
    canvas = np.zeros((height, width), dtype=np.uint8)
    if isinstance(polygons, (str, bytes)) or not isinstance(polygons, Iterable):
        raise TypeError(f"polygons: expected a list of polygons, got {type(polygons).__name__}")
    # one pixel beyond the centres of the border pixels: no pixel centre lies on the clip border
    lo, hi = (-1.0, -1.0), (float(width), float(height))
    pts = []
    for k, poly in enumerate(polygons):
        clipped = _clip(_as_polygon(poly, f"polygons[{k}]"), lo, hi)
        if len(clipped) >= 3:
            pts.append(np.round(clipped * (1 << _SHIFT)).astype(np.int32))
    for p in pts:  # (one call for all would fill their overlaps by the even-odd rule: as holes)
        cv2.fillPoly(canvas, [p], 1, lineType=cv2.LINE_8, shift=_SHIFT)
    return torch.from_numpy(canvas > 0).unsqueeze(0)


_MAX_SIDE = 1 << 16  # pixels a side: beyond any camera's frame (a corrupt size would fill memory)
_MAX_PIXELS = 1 << 28  # H * W: a 16384 x 16384 mask; 65536 x 65536 would allocate 4 GB


def _check_size(size: object, name: str) -> tuple[int, int]:
    """(H, W): two positive ints (a float such as 375.0 or 375.5 is rejected, not truncated), at
    most 65536 each and 2**28 pixels (H * W) in all."""
    if not isinstance(size, (list, tuple)) or len(size) != 2:
        raise ValueError(f"{name}: expected [H, W] (two positive integers), got {size!r:.60}")
    for s in size:
        if isinstance(s, bool) or not isinstance(s, numbers.Integral):
            raise TypeError(f"{name}: expected integer sides [H, W], got {size!r:.60}")
        if s <= 0:
            raise ValueError(f"{name}: expected positive sides [H, W], got {list(size)!r}")
        if s > _MAX_SIDE:
            raise ValueError(f"{name}: expected sides [H, W] of at most {_MAX_SIDE} pixels, got {list(size)!r:.60}")
    if int(size[0]) * int(size[1]) > _MAX_PIXELS:  # (Python ints: NumPy int32 sides would wrap around)
        raise ValueError(f"{name}: expected at most 2**28 = {_MAX_PIXELS} pixels (H * W), got {list(size)!r}")
    return int(size[0]), int(size[1])


class _RepeatedKey(ValueError):
    """A key that one JSON object of a polygon file holds twice (``args[0]``)."""


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """``json.loads``' object hook: a dict of ``pairs``, raising :class:`_RepeatedKey` where a key
    comes twice (``json`` keeps the last silently: the polygon meant is a guess)."""
    obj: dict[str, Any] = {}
    for key, value in pairs:
        if key in obj:
            raise _RepeatedKey(key)
        obj[key] = value
    return obj


def _polygons_from_json(obj: Any, where: str) -> list[tuple[str, Any]]:
    """(name, polygon) pairs of a parsed polygon JSON (formats 1-4 of the module docstring)."""
    if isinstance(obj, list):
        if not obj:
            raise ValueError(f"{where}: holds no polygon (an empty list; an empty mask is a PNG, not a polygon file)")
        return [(f"{where}[{i}]", p) for i, p in enumerate(obj)]
    if not isinstance(obj, dict):
        raise TypeError(f"{where}: expected a JSON object {{'size': [H, W], 'road_polygon': [...]}} or a "
                        f"list of polygons, got {type(obj).__name__} {obj!r:.60}")
    keys = [key for key in _ONE + _MANY if key in obj]
    if not keys and "shapes" in obj:  # (its other keys would be read as named polygons, its size missed)
        raise ValueError(f"{where} looks like a LabelMe file ('shapes'), which holds labelled shapes; expected "
                         f"{{'size': [H, W], 'road_polygon': [[u, v], ...]}}: put the road shapes' points under "
                         f"'polygons' and [imageHeight, imageWidth] as 'size'")
    if len(keys) > 1:
        # which one was meant is a guess: filling one and dropping the other would hide the mistake
        raise ValueError(f"{where}: has both {keys[0]!r} and {keys[1]!r} entries; expected one of "
                         f"'road_polygon', 'polygon', 'polygons', 'road_polygons'")
    if not keys:
        named = [(f"{where}[{name!r}]", p) for name, p in obj.items() if name != "size"]
        if not named:
            raise ValueError(f"{where}: has no 'road_polygon', 'polygon' or 'polygons' entry (nor named polygons)")
        return named
    key = keys[0]
    value = obj[key]
    if key in _ONE:
        return [(f"{where}[{key!r}]", value)]
    if isinstance(value, dict):
        named = [(f"{where}[{key!r}][{name!r}]", p) for name, p in value.items()]
    elif isinstance(value, list):
        named = [(f"{where}[{key!r}][{i}]", p) for i, p in enumerate(value)]
    else:
        raise TypeError(f"{where}[{key!r}]: expected a list of polygons or a dict of named polygons, "
                        f"got {type(value).__name__}")
    if not named:
        raise ValueError(f"{where}[{key!r}]: holds no polygon (an empty mask is a PNG, not a polygon file)")
    return named


def read_road_mask(path: str | os.PathLike, size: tuple[int, int] | None = None, *,
                   resize: bool = False) -> Tensor:
    """A road mask as (1, H, W) bool.

    Args:
        path: a PNG (any colour channel nonzero = road; an alpha channel is ignored; a KITTI
            road benchmark ground truth, road magenta and the rest of the valid area red, reads
            the magenta; a float image, such as a TIFF, only where it holds 0 and one road value:
            a probability map is a ValueError; a JPEG or lossy WebP is a ValueError too: its
            compression leaves small nonzero values beside the road's edges, which would read as
            road) or a polygon JSON (the formats in the module docstring).
        size: (H, W) of the images the mask is for. A PNG must have it, and a JSON's polygon
            must have been drawn for it (its ``"size"``): a mask of another size is another
            image's road, and a ValueError naming the file and both sizes unless ``resize``. A
            JSON without ``"size"`` is drawn at ``size`` (it needs ``size``). None: the mask at
            its own size.
        resize: with ``size``, resample a mask of another size to it, pixel centres mapping as
            ``u' + 0.5 = s (u + 0.5)`` (as :meth:`~fsof_torch.Camera.scaled`): a PNG by the source
            pixel nearest each new pixel's centre (as ``F.interpolate``'s ``"nearest-exact"``), a polygon
            scaled from its ``"size"``. Only right where the images are the mask's own
            images resized (KITTI's 375x1242 and 370x1226 frames are different crops, not
            resized copies).

    Raises:
        ValueError / TypeError naming ``path`` (and the entry) for a file that is not valid
        UTF-8 JSON, a key given twice in one object, a missing or malformed size (or one of
        over 2**28 pixels, as for ``size``), a malformed polygon, two polygon entries or no
        polygon, a vertex beyond ±1e15 px once scaled to ``size``, a mask or polygon of another
        size than ``size`` without ``resize``; FileNotFoundError for a missing file,
        IsADirectoryError for a folder.
    """
    path = as_path(path)
    if size is not None:
        size = _check_size(list(size) if isinstance(size, (tuple, torch.Size)) else size, "size")
    resize = check_bool(resize, "resize")
    if path.suffix.lower() == ".json":
        existing_file(path)
        where = f"path: {str(path)!r}"
        try:
            # (a byte-order mark, as Windows editors write one, is skipped, as the calibration and
            # poses readers skip it: json refused the file)
            obj = json.loads(path.read_bytes().decode("utf-8-sig"), object_pairs_hook=_unique_keys)
        except _RepeatedKey as err:
            raise ValueError(f"{where} has the key {err.args[0]!r} twice in one object; keep one") from None
        except UnicodeDecodeError as err:
            raise ValueError(f"{where} is not a text (UTF-8) JSON file (undecodable byte at offset "
                             f"{err.start})") from None
        except ValueError as err:  # JSONDecodeError, or an integer of over 4300 digits
            raise ValueError(f"{where} is not valid JSON: {err}") from None
        except RecursionError:
            raise ValueError(f"{where} is nested too deeply to be a road polygon file") from None
        named = _polygons_from_json(obj, where)
        own = obj.get("size") if isinstance(obj, dict) else None
        if own is None and size is None:
            raise ValueError(f"{where} has no 'size' entry; pass size=(H, W)")
        own = _check_size(own, f"{where}['size']") if own is not None else size
        target = size or own
        if target != own and not resize:
            raise ValueError(_other_size(where, "a polygon drawn for {}x{} images (its 'size')", own, target))
        sy, sx = target[0] / own[0], target[1] / own[1]
        polygons = []
        for name, poly in named:
            arr = _as_polygon(poly, name)
            _check_simple(arr, name)
            # pixel centres map as u' + 0.5 = s (u + 0.5)
            scaled = np.stack([sx * (arr[:, 0] + 0.5) - 0.5, sy * (arr[:, 1] + 0.5) - 0.5], axis=1)
            far = np.flatnonzero((np.abs(scaled) > _MAX_COORD).any(axis=1))
            if far.size:
                i = int(far[0])
                raise ValueError(f"{name}[{i}]: coordinates beyond ±{_MAX_COORD:g} px are not pixels, got "
                                 f"[{arr[i, 0]:.6g}, {arr[i, 1]:.6g}] scaled from size {list(own)} to "
                                 f"{list(target)}: [{scaled[i, 0]:.6g}, {scaled[i, 1]:.6g}]")
            polygons.append(scaled)
        return rasterize_polygons(polygons, target)
    array = read_image_array(path, what="road mask image")
    _refuse_lossy(path, "it leaves small nonzero values beside the road's edges, which a mask reads as road (any "
                  "nonzero value is road); save road masks as PNG (write_road_mask)")
    if array.dtype.kind == "f":  # (a float TIFF: a mask only where it holds 0 and one other value)
        values = np.unique(array)
        if not (np.isfinite(values).all() and values.min() >= 0 and np.count_nonzero(values) <= 1):
            shown = ", ".join(f"{v:g}" for v in values[:4]) + (", ..." if len(values) > 4 else "")
            raise ValueError(f"path: {str(path)!r} is a {array.dtype} image with the values {shown}, not a mask "
                             f"(0 and one road value): a probability map or a depth, which no one threshold "
                             f"turns into road; threshold it yourself (write_road_mask(path, prob > 0.5))")
    if array.ndim == 3:
        # the alpha channel (grey + alpha, BGRA) is opacity, not road: an opaque mask would be all road
        if array.shape[2] in (2, 4):
            array = array[:, :, :-1]
        road = _kitti_road_ground_truth(array)
        array = array.max(axis=2) if road is None else road
    mask = array > 0
    if size is not None and mask.shape != size:
        if not resize:
            raise ValueError(_other_size(f"path: {str(path)!r}", "a {}x{} mask", mask.shape, size))
        # each new pixel u' takes the source pixel nearest its centre (u' + 0.5) N / n - 0.5, in integers:
        # floor((2 u' + 1) N / 2n) (OpenCV's INTER_NEAREST took a k x k block's top-left, (k - 1) / 2 px short)
        rows, cols = ((2 * np.arange(n, dtype=np.int64) + 1) * N // (2 * n) for n, N in zip(size, mask.shape))
        mask = mask[np.ix_(rows, cols)]
    return torch.from_numpy(np.ascontiguousarray(mask)).unsqueeze(0)


def _refuse_lossy(path: Path, why: str) -> None:
    """A ValueError naming ``path`` where the file is a JPEG or a WebP in its lossy coding (by its
    bytes, whatever its suffix): their compression changes the values of data images (``why``
    says how)."""
    with open(path, "rb") as f:
        head = f.read(16)
    if head[:3] == b"\xff\xd8\xff":
        kind = "a JPEG"
    elif head[:4] == b"RIFF" and head[8:16] == b"WEBPVP8 ":  # (VP8L is WebP's lossless coding)
        kind = "a WebP in its lossy coding (VP8)"
    else:
        return
    raise ValueError(f"path: {str(path)!r} is {kind}, whose compression is lossy: {why}")


def _other_size(where: str, what: str, own: tuple[int, int], size: tuple[int, int]) -> str:
    """The message for a mask of another size than ``size``: ``what`` with its size (``own``)."""
    h, w = size
    return (f"{where} is {what.format(*own)}, but size is {h}x{w}; stretched over {h}x{w} images it would be "
            f"another image's road: give a mask drawn for images of that size (read_road_mask(..., resize=True) "
            f"resamples one where the images are its own images resized)")


def _kitti_road_ground_truth(bgr: np.ndarray) -> np.ndarray | None:
    """The road of a KITTI road benchmark ground truth (``gt_image_2/*_road_*.png``), where a
    colour PNG is one: every coloured pixel red (R = max, G = 0), road magenta (B > 0: the
    devkit's road area), the rest of the valid area red (B = 0). Read as any channel nonzero,
    the red non-road would be road. None for any other image."""
    if bgr.shape[2] != 3 or bgr.dtype.kind != "u" or bgr[:, :, 1].any():  # (its PNGs are 8-bit)
        return None
    blue, red = bgr[:, :, 0], bgr[:, :, 2]
    top = np.iinfo(bgr.dtype).max
    coloured = (blue > 0) | (red > 0)
    if not ((red[coloured] == top).all() and (coloured & (blue == 0)).any() and (blue > 0).any()):
        return None
    return blue


def write_road_mask(path: str | os.PathLike, mask: Tensor | np.ndarray) -> Path:
    """Write a (1, H, W) or (H, W) bool mask (a tensor or a NumPy array) as an 8-bit PNG (road =
    255), atomically.

    ``path`` must end in .png (a JPEG would blur the mask's edges into road). A mask of another
    dtype (uint8 0/1 or 0/255, float) is a TypeError, as for the ``valid`` masks of the flow
    writers: an integer or float array may as well be a grey image or a probability map, which
    no one threshold turns into a mask; pass ``mask > 0`` (or your threshold).
    """
    path = check_image_suffix(path, (".png",), "road mask")
    if isinstance(mask, np.ndarray):
        mask = tensor_from_array(mask)
    if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
        got = f"dtype {mask.dtype}" if isinstance(mask, Tensor) else type(mask).__name__
        raise TypeError(f"mask: expected a bool tensor or array of shape (1, H, W) or (H, W), got {got}; "
                        f"threshold it yourself, e.g. mask > 0")
    given = tuple(mask.shape)  # (quoted as it came, not as squeezed)
    if mask.dim() == 3 and mask.shape[0] == 1:
        mask = mask[0]
    if mask.dim() != 2 or min(mask.shape) < 1:
        raise ValueError(f"mask: expected shape (1, H, W) or (H, W) with H, W >= 1, got {given}")
    check_has_values(mask, "mask")
    return write_image_array(path, mask.detach().cpu().numpy().astype(np.uint8) * 255)


def mask_from_colors(rgb: Tensor | np.ndarray, colors: Iterable[Sequence[int]]) -> Tensor:
    """(1, H, W) bool: pixels of a colour-coded segmentation equal to any of ``colors`` (RGB).

    Args:
        rgb: (3, H, W) RGB tensor (0..255, as :func:`fsof_torch.io.read_image` gives) or an
            (H, W, 3) integer RGB array (uint8; uint16 for 16-bit colours).
        colors: (r, g, b) triples of integers in 0..255 (0..65535 for a uint16 array); another
            value is a ValueError naming it (it could match no pixel, or a NaN one).
    """
    if isinstance(rgb, Tensor):
        if rgb.dim() != 3 or rgb.shape[0] != 3:
            raise ValueError(f"rgb: expected shape (3, H, W), got {tuple(rgb.shape)}")
        check_has_values(rgb, "rgb")
        # non-finite values match no colour
        array = torch.nan_to_num(rgb.detach().cpu().double(), nan=-1.0, posinf=-1.0, neginf=-1.0)
        array = array.round().to(torch.int64).permute(1, 2, 0).numpy()
        top = 255
    elif isinstance(rgb, np.ndarray):
        if rgb.ndim != 3 or rgb.shape[2] != 3 or not np.issubdtype(rgb.dtype, np.integer):
            raise ValueError(f"rgb: expected an integer (H, W, 3) array, got {rgb.dtype} of shape {rgb.shape}")
        array = rgb.astype(np.int64)
        top = 65535 if rgb.dtype == np.uint16 else 255
    else:
        raise TypeError(f"rgb: expected a (3, H, W) tensor or an (H, W, 3) uint8 array, got {type(rgb).__name__}")
    mask = np.zeros(array.shape[:2], dtype=bool)
    for i, color in enumerate(colors):
        if not (isinstance(color, (tuple, list)) and len(color) == 3
                and all(isinstance(c, numbers.Integral) and not isinstance(c, bool) for c in color)):
            raise ValueError(f"colors[{i}]: expected an (r, g, b) triple of integers, got {color!r}")
        if not all(0 <= c <= top for c in color):
            raise ValueError(f"colors[{i}]: expected components in 0..{top}, got {tuple(color)!r}")
        mask |= (array == np.asarray(color, dtype=np.int64).reshape(1, 1, 3)).all(axis=2)
    return torch.from_numpy(mask).unsqueeze(0)


def read_label_map(path: str | os.PathLike) -> Tensor:
    """A single-channel 8- or 16-bit label PNG as an (H, W) int64 tensor. A grey PNG of 1, 2 or
    4 bits gives its stored values too (labels 0..1, 0..3, 0..15), not the 8-bit intensities
    OpenCV expands them to (1 -> 255, 85, 17). A JPEG or lossy WebP is a ValueError naming the
    path: its compression changes labels."""
    array = read_image_array(path, what="label map (single-channel 8/16-bit PNG)")
    _refuse_lossy(path, "it changes labels, most of all beside the edges of regions; save label maps as PNG "
                  "(write_label_map)")
    if array.ndim != 2 or array.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"path: {str(path)!r} is {array.dtype} with shape {array.shape}; expected a "
                         f"single-channel 8- or 16-bit label map")
    with open(path, "rb") as f:  # the PNG signature, then IHDR: length, type, W, H, bit depth, colour type
        head = f.read(26)
    if head[12:16] == b"IHDR" and head[25] == 0 and head[24] in (1, 2, 4):  # grey under 8 bits
        array = array // (255 // (2 ** head[24] - 1))  # (OpenCV repeats the bits: v -> v * 255 / (2^n - 1))
    return torch.from_numpy(array.astype(np.int64))


def write_label_map(path: str | os.PathLike, labels: Tensor | np.ndarray) -> Path:
    """Write (H, W) integer labels (a tensor or a NumPy array) as a PNG atomically: 8-bit when
    all labels fit, else 16-bit.

    ``path`` must end in .png (other formats are lossy or 8-bit only: label 300 would read back as 255).
    """
    path = check_image_suffix(path, (".png",), "label map")
    integer = (labels.dtype.kind in "iu" if isinstance(labels, np.ndarray) else isinstance(labels, Tensor)
               and not (labels.is_floating_point() or labels.is_complex() or labels.dtype == torch.bool))
    if not integer:
        got = f"dtype {labels.dtype}" if isinstance(labels, (Tensor, np.ndarray)) else type(labels).__name__
        raise TypeError(f"labels: expected an integer tensor or array of shape (H, W), got {got}")
    given = tuple(labels.shape)
    if labels.ndim == 3 and labels.shape[0] == 1:
        labels = labels[0]
    if labels.ndim != 2 or min(labels.shape) < 1:
        raise ValueError(f"labels: expected shape (H, W) with H, W >= 1, got {given}")
    check_has_values(labels, "labels")
    if isinstance(labels, Tensor):
        labels = labels.detach().cpu().numpy()
    lo, hi = int(labels.min()), int(labels.max())  # (in NumPy: exact for every integer type)
    if lo < 0 or hi > 65535:
        raise ValueError(f"labels: expected values in 0..65535, got the range [{lo}, {hi}]")
    dtype = np.uint8 if hi <= 255 else np.uint16
    return write_image_array(path, labels.astype(dtype))
