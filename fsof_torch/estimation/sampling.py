"""Points of a mask for the estimators: a deterministic, even subsample, chosen on the device.

A fit needs a few thousand of a mask's pixels per frame, not all of them: their statistical error
stays far below the flow's, and each iteration's cost scales with their number. The kept pixels
are an even stride over the mask in raster order, picked with a binary
search over the mask's pixels, so the number of points is fixed in advance.
"""

from __future__ import annotations

import contextlib
import contextvars
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .._check import host_path

__all__ = ["MaskPoints", "sample_mask", "resample_mask", "reused_mask_pixels", "pixel_coordinates", "gather_pixels",
           "sample_points", "points_grid", "sample_at_grid"]


@dataclass
class MaskPoints:
    """The pixels of a mask and an even subsample of them.

    Attributes:
        pix: (B, N) flat pixel indices (y W + x) of at most N pixels per frame.
        sel: (B, N) bool, flags of real points (frames with fewer mask pixels are padded with
            pixel 0, flagged False).
        count: (B,) the number of mask pixels per frame.
        every: (M,) the flat indices into (B H W) of all M mask pixels of the batch, sorted.
        bounds: (B + 1,) where each frame's pixels start in ``every`` (and where the last ends).
    """

    pix: Tensor
    sel: Tensor
    count: Tensor
    every: Tensor
    bounds: Tensor

    def per_frame(self, x: Tensor) -> Tensor:
        """Per-frame sums (B,) float64 of values (M,) given at ``every``'s pixels (accumulated in
        float64 without a float64 copy of ``x``)."""
        if self.bounds.numel() == 2:  # one frame
            if x.dtype == torch.bool:  # (a count: faster than a sum of converted flags)
                return torch.count_nonzero(x).reshape(1).to(torch.float64)
            return x.sum(0, keepdim=True, dtype=torch.float64)
        c = torch.cat([x.new_zeros(1, dtype=torch.float64), x.cumsum(0, dtype=torch.float64)])
        return c[self.bounds[1:]] - c[self.bounds[:-1]]

    def per_pixel(self, v: Tensor) -> Tensor:
        """Per-frame values (B,) spread to ``every``'s pixels (M,): each pixel its frame's value
        (one frame: a broadcast view, no copy)."""
        if self.bounds.numel() == 2:
            return v.expand(self.every.numel())
        return v.repeat_interleave(self.bounds.diff(), output_size=self.every.numel())


def sample_mask(mask: Tensor, max_points: int | None) -> MaskPoints:
    """The pixels of a mask (B, 1, H, W) bool, and an even subsample of at most ``max_points``
    per frame (None: all of them; N is then the largest count in the batch, one more host read).

    The j-th kept pixel of a frame with n > N mask pixels is its floor(j n / N)-th one in raster
    order. One ``nonzero`` finds the pixels (the one host read: it sizes its result); the rest
    stays on the device.
    """
    B, _, H, W = mask.shape
    every = mask_pixels(mask)
    bounds = torch.searchsorted(every, torch.arange(B + 1, device=mask.device) * (H * W))
    return _subsample(every, bounds, H * W, max_points)


def mask_pixels(mask: Tensor) -> Tensor:
    """The flat indices (M,) int64 of a mask's true pixels, in raster order over the whole batch.

    One flat search (a 2-D ``nonzero`` splits each index into (frame, pixel) by an int64
    division). On the CPU NumPy's ``flatnonzero`` finds them in half the time of torch's
    ``nonzero`` (a KITTI frame's road: ``python benchmarks/bench_image_fit.py``); elsewhere torch's."""
    memo = _MASK_PIXELS.get()
    if memo is not None:
        # (the same memory seen the same way, unchanged since: a view's own version counter is its
        # base's; inference tensors have none, and are not written in place where the memo is open)
        key = (mask.data_ptr(), tuple(mask.shape), mask.stride(), mask.dtype, mask.device,
               None if mask.is_inference() else mask._version)
        if key in memo:
            return memo[key][1]
    flat = mask.reshape(-1)
    if host_path(flat):
        every = torch.from_numpy(np.flatnonzero(flat.numpy())).long()
    else:
        every = flat.nonzero().squeeze(1)
    if memo is not None:
        memo[key] = (mask, every)  # (the mask held: its memory is not reused while the memo is open)
    return every


_MASK_PIXELS: contextvars.ContextVar[dict | None] = contextvars.ContextVar("mask_pixels", default=None)


@contextlib.contextmanager
def reused_mask_pixels(memo: dict | None = None):
    """Within the block, :func:`mask_pixels` (and so :func:`sample_mask`) of a mask it has searched
    already (the same memory, shape and strides, not written since) returns the pixels found then:
    for steps that sample one mask in turn (a planar start and the image fit). ``memo``: a dict
    (empty at first) that keeps the pixels found, and the masks searched, beyond the block: a later
    block given it reuses them (steps apart, such as the refiner's estimate and its gate). Blocks
    nest (the outermost one's memo serves); each thread or task has its own."""
    if _MASK_PIXELS.get() is not None:
        yield
        return
    token = _MASK_PIXELS.set({} if memo is None else memo)
    try:
        yield
    finally:
        _MASK_PIXELS.reset(token)


def resample_mask(points: MaskPoints, size: tuple[int, int], max_points: int | None) -> MaskPoints:
    """:func:`sample_mask` of the same mask (of ``size`` (H, W)) with another ``max_points``,
    from its pixels ``points`` (no second search of the mask)."""
    return _subsample(points.every, points.bounds, size[0] * size[1], max_points)


def _subsample(every: Tensor, bounds: Tensor, HW: int, max_points: int | None) -> MaskPoints:
    B = bounds.numel() - 1
    count, start = bounds.diff(), bounds[:-1]
    N = max(int(count.max()) if B else 0, 1) if max_points is None else int(max_points)
    j = torch.arange(N, device=every.device).expand(B, N)
    n = count.unsqueeze(1)
    rank = torch.where(n > N, (j * n) // N, j)
    sel = rank < n
    if every.numel():
        frame0 = torch.arange(B, device=every.device).unsqueeze(1) * HW
        pix = every[(start.unsqueeze(1) + rank).clamp_max(every.numel() - 1)] - frame0
        pix = torch.where(sel, pix, 0)
    else:
        pix = torch.zeros(B, N, dtype=torch.long, device=every.device)
    return MaskPoints(pix, sel, count, every, bounds)


def pixel_coordinates(pix: Tensor, width: int, dtype: torch.dtype = torch.float64) -> Tensor:
    """Homogeneous pixel coordinates (B, 3, N) (u, v, 1) of flat indices (B, N)."""
    # (written into one tensor, not stacked: the image fit's tests take every mask pixel's, python
    # benchmarks/bench_image_fit.py --baseline. The row by a float64 division, floored, the column
    # from it: the same whole numbers as an int64 division, which the CPU does not vectorise, in
    # about a seventh of the time on the KITTI pair's 93 312 road pixels; exact, as (i + 0.5) /
    # width lies at least 0.5 / width from a whole number, farther than its rounding moves it for
    # any index below 2^52)
    out = torch.empty((pix.shape[0], 3, pix.shape[1]), dtype=torch.float64, device=pix.device)
    u, v = out[:, 0], out[:, 1]
    u.copy_(pix)
    torch.add(u, 0.5, out=v).div_(width).floor_()
    u.sub_(v, alpha=width)
    out[:, 2] = 1.0
    return out if dtype == torch.float64 else out.to(dtype)


def gather_pixels(x: Tensor, pix: Tensor) -> Tensor:
    """``x`` (B, C, H, W) at flat pixel indices (B, N) -> (B, C, N)."""
    B, C = x.shape[:2]
    return x.reshape(B, C, -1).gather(2, pix.unsqueeze(1).expand(B, C, pix.shape[1]))


BORDER_SLACK = 1e-6
"""Pixels beyond the image's border within which a sample point still counts as inside (rounding)."""


def sample_points(image: Tensor, xy: Tensor) -> tuple[Tensor, Tensor]:
    """Bilinear samples of ``image`` (B, C, H, W) at pixel positions ``xy`` (B, 2, N) float64.

    The iterations need the warped image only at the sample points, so they sample those points
    (``grid_sample`` on a (B, 1, N) grid, with the corner-aligned normalisation written here)
    instead of warping the whole frame. Returns (B, C, N) float64 and in-bounds flags (B, N).
    A 16-bit image is sampled in float32 (see :func:`points_grid`).
    """
    grid, inb = points_grid(xy, image.shape[-2:], image.dtype)
    return sample_at_grid(image, grid), inb


def points_grid(xy: Tensor, size: tuple[int, int], dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """The ``grid_sample`` grid (B, 1, N, 2) of pixel positions ``xy`` (B, 2, N) in images of
    ``size`` (H, W), in ``dtype`` (an image's; half precision lifted to float32: across a KITTI
    frame a float16 grid is off by up to 0.15 px, a bfloat16 one by up to 1.2 px), and their
    in-bounds flags (B, N) (:func:`sample_points` in two parts: images of one size sampled at the
    same points share the grid).

    A point counts as inside up to :data:`BORDER_SLACK` pixels beyond the border (sampled there at
    the border): a motion that maps a border pixel onto the border computes it to within rounding,
    and batched products round each frame of a batch differently, so an exact bound kept a
    frame's border points in one copy of it and dropped them in another (identical frames of one
    batch got fits up to 5 px apart, tests/test_fit_photometric.py)."""
    H, W = size
    x, y = xy[:, 0], xy[:, 1]
    s = BORDER_SLACK
    inb = (x >= -s) & (x <= W - 1 + s) & (y >= -s) & (y <= H - 1 + s)
    # (each coordinate written into the grid in its dtype: no stacked copy in xy's dtype first)
    grid = xy.new_empty((xy.shape[0], 1, xy.shape[2], 2), dtype=_at_least_float32(dtype))
    grid[:, 0, :, 0] = x * (2.0 / max(W - 1, 1)) - 1.0
    grid[:, 0, :, 1] = y * (2.0 / max(H - 1, 1)) - 1.0
    return grid, inb


def sample_at_grid(image: Tensor, grid: Tensor) -> Tensor:
    """Bilinear samples (B, C, N) float64 of ``image`` (B, C, H, W) at a grid of :func:`points_grid`,
    sampled in at least float32 (torch's CPU ``grid_sample`` also misreads 16-bit images)."""
    dt = _at_least_float32(torch.promote_types(image.dtype, grid.dtype))
    out = F.grid_sample(image.to(dt), grid.to(dt), mode="bilinear", padding_mode="border", align_corners=True)
    return out[:, :, 0].to(torch.float64)


def _at_least_float32(dtype: torch.dtype) -> torch.dtype:
    return torch.float32 if dtype in (torch.float16, torch.bfloat16) else dtype
