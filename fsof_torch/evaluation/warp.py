"""Backward warping of an image by a flow field: the one warp of the project (DESIGN.md §6).

    warped(p) = image(p + flow(p)),   in_bounds(p) = p + flow(p) ∈ [0, W-1] × [0, H-1]

Convention: pixel (u, v) with origin at the centre of the top-left pixel, u to the right, v down;
flow (B, 2, H, W) in pixels, channel 0 = u, channel 1 = v. With the forward flow F_12 of a pair
(I_1, I_2), ``warp_backward(I_2, F_12)`` reconstructs I_1 wherever the point stays visible.

How the sampling is done, and why. kornia's ``remap`` normalises pixel maps with the
corner-aligned (``align_corners=True``) convention whatever flag reaches ``grid_sample``, so a
pixel map sampled with ``align_corners=False`` (kornia's default) is shifted by half a pixel
(kornia issue #4504; measured here: an identity map changes the KITTI image 000000_10 by up to
191 grey levels, 3.7 on average). This module therefore normalises the coordinates itself, in
one place (:func:`normalize_coordinates`), and samples with one convention whatever
``align_corners`` the caller gives: edge-aligned (``align_corners=False``), the one whose
normalisation is defined on a 1-pixel-wide or -high axis too (where the corner-aligned scale
divides by zero, and a tap one pixel outside would read the only pixel instead of the padding).

Even then, ``grid_sample`` un-normalises in floating point, and the round trip pixel -> [-1, 1]
-> pixel is not exact in float32 (an identity map changed that image by up to 0.016 grey levels).
So bilinear sampling is done as four nearest-neighbour taps at the integer corners (robust to
that rounding) weighted by the fractional parts, which are exact: the identity flow returns the
image bit for bit, whole-pixel shifts equal ``torch.roll`` on the interior, and the result does
not depend on ``align_corners`` at all, on any image size. The price: about 2-3x the time of a single bilinear
kornia ``remap`` for forward + backward, more for a forward pass alone (one CPU thread;
``python benchmarks/bench_warp.py`` prints the table), and the memory of the four corners' grid
and taps (80 bytes a pixel of a float32 RGB image): without autograd, a frame of more than
``_BAND_POINTS`` sample points is warped a band of rows at a time.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from .._check import (autocast_off, check_bool, check_finite, check_float_tensor, check_same_device, check_shape,
                      is_number, option_error, result_dtype, scalar)

__all__ = ["normalize_coordinates", "warp_backward", "WarpBackward", "band_rows"]

_MODES = ("bilinear", "nearest")
# The sampler's convention, whatever the caller's align_corners (see the module docstring).
_SAMPLE_ALIGN_CORNERS = False
_PADDING = ("zeros", "border")
# Sample points per band of a bilinear warp without autograd (warp_backward): a KITTI frame
# (375 x 1242 = 465 750 pixels) is one band
_BAND_POINTS = 1 << 19


def normalize_coordinates(coords: Tensor, size: int, *, align_corners: bool) -> Tensor:
    """Pixel coordinates along one axis of ``size`` pixels -> grid_sample's [-1, 1] range.

    ``align_corners=True``: -1 and 1 are the centres of the first and last pixel;
    ``align_corners=False``: -1 and 1 are the outer edges of those pixels. Pass the same flag to
    the sampler. A singleton axis maps its only pixel to 0 (the corner-aligned scale is
    undefined there, and grid_sample then ignores the coordinate anyway). Elementwise: a NaN
    coordinate stays NaN. ``align_corners`` is True or False (TypeError otherwise: a string
    "False" would otherwise be taken as True).
    """
    check_float_tensor(coords, "coords")
    check_bool(align_corners, "align_corners")
    size = scalar(size, "size")  # (a 0-d integer tensor as its int)
    if not is_number(size, integer=True) or size < 1:
        raise option_error(size, f"size: expected a positive int (pixels along the axis), got {size!r}", integer=True)
    size = int(size)
    if size == 1:
        return coords * 2.0
    if align_corners:
        return coords * (2.0 / (size - 1)) - 1.0
    return (coords * 2.0 + 1.0) / size - 1.0


def _sample_nearest(image: Tensor, x: Tensor, y: Tensor, *, align_corners: bool,
                    padding_mode: str) -> Tensor:
    """image (B, C, H, W) at integer-valued pixel coordinates x, y (B, h, w) -> (B, C, h, w)."""
    from kornia.geometry.transform import remap

    H, W = image.shape[-2:]
    return remap(image, normalize_coordinates(x, W, align_corners=align_corners),
                 normalize_coordinates(y, H, align_corners=align_corners), mode="nearest",
                 padding_mode=padding_mode, align_corners=align_corners, normalized_coordinates=True)


def _sample_corners(image: Tensor, x0: Tensor, y0: Tensor, *, align_corners: bool,
                    padding_mode: str) -> Tensor:
    """image (B, C, H, W) at the four integer corners (x0, y0), (x0+1, y0), (x0, y0+1),
    (x0+1, y0+1) of every sample point (x0, y0 (B, h, w), integer-valued) -> (B, C, 4h, w), the
    corners stacked along rows in that order.

    One nearest-neighbour ``grid_sample`` call over a grid built by normalising the first corner
    once and adding a pixel's step for the others: a quarter of the normalising and stacking that
    four pixel maps handed to kornia's ``remap`` cost. A step's rounding moves a sample point by
    far less than the half pixel that would change its nearest tap, so the taps are the same
    (tests/test_warp.py checks them against indexing)."""
    B, _, H, W = image.shape
    h, w = x0.shape[-2:]  # (the sample points: the image's size, or a band of its rows)
    base = torch.stack([normalize_coordinates(x0, W, align_corners=align_corners),
                        normalize_coordinates(y0, H, align_corners=align_corners)], dim=-1)  # (B, h, w, 2)
    one = torch.ones((), dtype=base.dtype, device=base.device)
    zero = torch.zeros((), dtype=base.dtype, device=base.device)
    step_x = (normalize_coordinates(one, W, align_corners=align_corners)
              - normalize_coordinates(zero, W, align_corners=align_corners))
    step_y = (normalize_coordinates(one, H, align_corners=align_corners)
              - normalize_coordinates(zero, H, align_corners=align_corners))
    steps = torch.stack([torch.stack([zero, zero]), torch.stack([step_x, zero]),
                         torch.stack([zero, step_y]), torch.stack([step_x, step_y])])  # (4, 2)
    grid = (base.unsqueeze(1) + steps.view(1, 4, 1, 1, 2)).reshape(B, 4 * h, w, 2)
    return torch.nn.functional.grid_sample(image, grid, mode="nearest", padding_mode=padding_mode,
                                           align_corners=align_corners)


def _corner_and_weight(x: Tensor, size: int) -> tuple[Tensor, Tensor]:
    """The integer corner below the coordinates ``x`` along an axis of ``size`` pixels
    (detached) and the weight of the corner above it, ``x - corner`` (exact, carries the flow's
    gradient).

    The corner is ``floor(x)``, except on the last pixel: a sample point exactly at ``size - 1``
    takes the corner ``size - 2`` with weight 1. The value is the same (lerp returns its end
    exactly at weight 1), but no in-bounds point then has a tap outside the image, in its value
    or its gradient: the flow's gradient there is the one-sided difference I(size-1) - I(size-2),
    whatever the padding. On a one-pixel axis the only in-bounds point is 0, which has no
    neighbour to take a difference with: its weight is detached (gradient 0). Without a gradient
    to the coordinates the plain ``floor(x)`` is taken (the same values, one pass less)."""
    xd = x.detach()
    if not x.requires_grad:
        x0 = torch.floor(xd)
        return x0, x - x0
    last = xd == size - 1
    if size > 1:
        x0 = torch.floor(xd).masked_fill_(last, size - 2)
        return x0, x - x0
    x0 = torch.floor(xd)
    weight = x - x0
    return x0, torch.where(last, weight.detach(), weight)


def warp_backward(image: Tensor, flow: Tensor, *, align_corners: bool = True,
                  mode: str = "bilinear", padding_mode: str = "zeros") -> tuple[Tensor, Tensor]:
    """Sample ``image`` at ``p + flow(p)``: the second frame warped back onto the first.

    Args:
        image: (B, C, H, W) float, any range (the values are only interpolated), finite: a NaN
            pixel would reach every output pixel whose bilinear taps touch it, so a non-finite
            value anywhere raises ValueError (replace or inpaint such pixels first).
        flow: (B, 2, H, W) float, pixels, channel 0 = u (right), channel 1 = v (down); finite.
        align_corners: kept for the signature of kornia / ``grid_sample``: both values give the
            same result, bit for bit and on any image size (the taps are sampled at integer pixel
            positions with one convention; a tap outside the image reads the padding).
        mode: ``"bilinear"`` (differentiable in image and flow) or ``"nearest"`` (differentiable
            in the image only; the flow gets no gradient).
        padding_mode: what a tap outside the image reads: ``"zeros"`` or ``"border"``
            (the nearest edge pixel). Affects only pixels that ``in_bounds`` marks invalid,
            their values and gradients: an in-bounds sample point exactly on the last column
            or row is interpolated towards the inside (the flow's gradient there is the
            one-sided difference to the pixel before it).

    Returns:
        warped: (B, C, H, W), dtype the promotion of image's and flow's dtypes. Sampling and
            coordinates are computed in at least float32, also under ``torch.autocast``.
        in_bounds: (B, 1, H, W) bool, True where the sample point ``p + flow(p)`` lies in
            [0, W-1] × [0, H-1] (the closed range of pixel centres). Elsewhere ``warped`` is
            finite but mixes in padding: mask it out.

    Example:
        >>> img = torch.arange(12.0).reshape(1, 1, 3, 4)
        >>> flow = torch.zeros(1, 2, 3, 4); flow[:, 0] = 1.0   # sample one pixel to the right
        >>> warped, ok = warp_backward(img, flow)
        >>> warped[0, 0, 0].tolist(), ok[0, 0, 0].tolist()
        ([1.0, 2.0, 3.0, 0.0], [True, True, True, False])
    """
    check_float_tensor(image, "image")
    check_float_tensor(flow, "flow")
    dims = check_shape(image, "image", ("B", "C", "H", "W"))
    check_shape(flow, "flow", ("B", 2, "H", "W"), dims)
    check_same_device({"image": image, "flow": flow})
    if mode not in _MODES:
        raise ValueError(f"mode: expected one of {_MODES}, got {mode!r}")
    if padding_mode not in _PADDING:
        raise ValueError(f"padding_mode: expected one of {_PADDING}, got {padding_mode!r}")
    check_bool(align_corners, "align_corners")  # (the module's message: "got bool np.True_", not "got bool")
    check_finite(image, "image")
    check_finite(flow, "flow")

    out_dtype = torch.promote_types(image.dtype, flow.dtype)
    work = result_dtype(image, flow)
    H, W = image.shape[-2:]
    # Geometry in at least float32: a bfloat16 pixel coordinate is off by up to 4 px at u = 1000.
    with autocast_off(image):
        img = image.to(work)
        f = flow.to(work)
        u = torch.arange(W, dtype=work, device=image.device).expand(H, W)
        v = torch.arange(H, dtype=work, device=image.device).unsqueeze(1).expand(H, W)
        x = u + f[:, 0]
        y = v + f[:, 1]
        in_bounds = ((x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)).unsqueeze(1)

        if mode == "nearest":
            warped = _sample_nearest(img, torch.round(x).detach(), torch.round(y).detach(),
                                     align_corners=_SAMPLE_ALIGN_CORNERS, padding_mode=padding_mode)
        elif torch.is_grad_enabled() and (image.requires_grad or flow.requires_grad):
            warped = _bilinear(img, x, y, padding_mode)
        else:
            # Without autograd, in bands of rows: the corners' grid and taps, some 100 bytes a
            # pixel of an RGB image, then exist for one band at a time (each pixel's value is
            # computed alone, so the bands give the same values bit for bit)
            rows = band_rows(x.shape[0], H, W, _BAND_POINTS)
            if rows >= H:
                warped = _bilinear(img, x, y, padding_mode)
            else:
                warped = img.new_empty(img.shape)
                for top in range(0, H, rows):
                    band = slice(top, top + rows)
                    warped[:, :, band] = _bilinear(img, x[:, band], y[:, band], padding_mode)
    return warped.to(out_dtype), in_bounds


def band_rows(B: int, H: int, W: int, points: int) -> int:
    """Rows per band of an elementwise computation over (B, ., H, W) maps done a band of rows at a
    time, about ``points`` pixels a band (``H`` or more: one band). A multiple of
    64 / gcd(W, 64) rows, so that a band holds whole 64-element blocks of every sample's plane:
    torch's CPU kernels compute a run's last elements that fill no SIMD vector with scalar code
    (whose transcendental functions may round otherwise), and the bands then leave the same
    elements to it as the whole maps do (in one thread)."""
    step = 64 // math.gcd(max(W, 1), 64)
    return max(step, points // max(B * W, 1) // step * step)


def _bilinear(img: Tensor, x: Tensor, y: Tensor, padding_mode: str) -> Tensor:
    """``img`` (B, C, H, W) bilinearly sampled at the pixel coordinates x, y (B, h, w) of some of
    its pixels (all, or a band of rows) -> (B, C, h, w)."""
    H, W = img.shape[-2:]
    x0, fx = _corner_and_weight(x, W)
    y0, fy = _corner_and_weight(y, H)
    fx, fy = fx.unsqueeze(1), fy.unsqueeze(1)
    # The four corners stacked along rows: one sampler call instead of four.
    taps = _sample_corners(img, x0, y0, align_corners=_SAMPLE_ALIGN_CORNERS, padding_mode=padding_mode)
    t00, t10, t01, t11 = taps.split(x.shape[-2], dim=2)
    # lerp returns its start exactly at weight 0 and its end at weight 1.
    top = torch.lerp(t00, t10, fx)
    bottom = torch.lerp(t01, t11, fx)
    return torch.lerp(top, bottom, fy)


class WarpBackward(nn.Module):
    """``nn.Module`` twin of :func:`warp_backward`: ``forward(image, flow) -> (warped, in_bounds)``."""

    def __init__(self, *, align_corners: bool = True, mode: str = "bilinear",
                 padding_mode: str = "zeros") -> None:
        super().__init__()
        check_bool(align_corners, "align_corners")  # (here, not at the first forward)
        if mode not in _MODES:
            raise ValueError(f"mode: expected one of {_MODES}, got {mode!r}")
        if padding_mode not in _PADDING:
            raise ValueError(f"padding_mode: expected one of {_PADDING}, got {padding_mode!r}")
        self.align_corners = align_corners
        self.mode = mode
        self.padding_mode = padding_mode

    def forward(self, image: Tensor, flow: Tensor) -> tuple[Tensor, Tensor]:
        """``image`` (B, C, H, W) sampled at p + ``flow`` (B, 2, H, W) px: ``(warped, in_bounds)``, :func:`warp_backward`."""
        return warp_backward(image, flow, align_corners=self.align_corners, mode=self.mode,
                             padding_mode=self.padding_mode)

    def extra_repr(self) -> str:
        return f"align_corners={self.align_corners}, mode={self.mode!r}, padding_mode={self.padding_mode!r}"
