"""The image fit's own tests of a motion (:func:`~fsof_torch.estimation.image_fit.fit_image`'s
``success``): how the two images compare once image 2 is moved back by the motion's flow, at
every pixel of the road mask that stays in view.

- :func:`photometric_inliers`: the share of those pixels whose plain intensities match within a
  threshold, image 2's matched to image 1's by their own gain and offset (:func:`matched_gain`);
- :func:`detail_correlation`: the correlation of the images' band of detail there. A plain
  road's intensities match under almost any motion; its detail lines up only under the right
  one (``python benchmarks/fit_confidence.py``);
- :func:`backward_correlation`: the same judged from image 2's side, for a road that recedes
  between the frames (image 2 sees it farther away and smaller).

And the flow fits' (:func:`~fsof_torch.estimation.flow_fit.fit_road`'s): :func:`agreement`, the
mask pixels within the inlier threshold of the model flow, their mean end-point error and share.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from .sampling import MaskPoints, pixel_coordinates, points_grid, sample_at_grid, sample_mask

__all__ = ["warped_samples", "photometric_inliers", "detail_correlation", "backward_correlation", "matched_gain",
           "spread_out", "agreement"]


def warped_samples(images1: Sequence[Tensor], images2: Sequence[Tensor], flow: Tensor, valid: Tensor,
                   points: MaskPoints) -> tuple[Tensor, Tensor, Tensor]:
    """At every mask pixel (``points.every``): the values (C, M) of frame 1's images ``images1``
    (a sequence of (B, C_i, H, W), their channels in order), those (C, M) of frame 2's
    ``images2`` at the pixel moved by the flow (bilinear), and whether that lies inside image 2
    where the flow is defined (M,). The images are sampled one by one, not stacked first (which
    would copy whole frames)."""
    B, _, H, W = images1[0].shape
    every = points.every
    within = every if B == 1 else every % (H * W)  # (the pixel within its frame)
    # (the flow added to the coordinates in place, frame 1's values written into one tensor: the
    # fit's tests take every mask pixel's)
    xy = pixel_coordinates(within.unsqueeze(0), W)[0, :2]
    xy += flow.transpose(0, 1).reshape(2, -1).gather(1, every.expand(2, -1))  # (in float64)
    I1 = torch.empty(sum(im.shape[1] for im in images1), every.numel(), dtype=torch.float64, device=every.device)
    channel = 0
    for im in images1:
        C = im.shape[1]
        I1[channel:channel + C] = im.transpose(0, 1).reshape(C, -1).gather(1, every.expand(C, -1))
        channel += C
    I2 = torch.empty(sum(im.shape[1] for im in images2), every.numel(), dtype=torch.float64, device=every.device)
    inb = torch.empty(every.shape, dtype=torch.bool, device=every.device)
    bounds = points.bounds.tolist()  # (one host read, not two per frame)
    for b in range(B):  # (B is small; the points of a frame are one contiguous run of ``every``)
        run = slice(bounds[b], bounds[b + 1])
        # (one grid for all of image 2's images: they share the frame's size)
        at = xy[:, run].unsqueeze(0)
        grid, inb_b = points_grid(at, (H, W), images2[0].dtype)
        inb[run] = inb_b[0]
        channel = 0
        for im in images2:
            C = im.shape[1]
            g = grid if im.dtype == grid.dtype else points_grid(at, (H, W), im.dtype)[0]
            I2[channel:channel + C, run] = sample_at_grid(im[b:b + 1], g)[0]
            channel += C
    return I1, I2, inb & valid.reshape(-1).gather(0, every)


def photometric_inliers(I1: Tensor, I2: Tensor, ok: Tensor, points: MaskPoints, threshold: float,
                        size: tuple[int, int]) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Inliers (B, 1, H, W) at the mask's pixels (|photometric residual| ≤ threshold), their mean
    |residual| (B,), their share of the mask's pixels that the flow keeps inside image 2 (B,) and
    their number (B,), from the intensities at those pixels (:func:`warped_samples`).

    The residual compares the plain intensities, image 2's matched to image 1's by its own gain
    and offset (:func:`matched_gain`): the fit's gain and offset are those of the band-passed
    images, whose amplitude a blur or a change of sharpness between the frames changes while the
    plain intensities keep theirs.
    """
    B = points.bounds.numel() - 1
    gain, offset = matched_gain(I1, I2, ok, points, threshold)
    err = (points.per_pixel(gain) * I2 + points.per_pixel(offset) - I1).abs()
    inl = ok & (err <= threshold)
    inliers = torch.zeros(B * size[0] * size[1], dtype=torch.bool, device=I1.device).scatter_(0, points.every, inl)
    n_in = points.per_frame(inl)  # (counted as flags: exact, as sums of 0 and 1 are)
    residual = points.per_frame(torch.where(inl, err, 0.0)) / n_in.clamp_min(1)
    fraction = n_in / points.per_frame(ok).clamp_min(1)
    return inliers.reshape(B, 1, *size), residual, fraction, n_in


def detail_correlation(x: Tensor, y: Tensor, ok: Tensor, points: MaskPoints) -> Tensor:
    """(B,) the correlation (zero-mean, normalised) of image 1's values ``x`` and image 2's ``y``
    at the mask's pixels in view (``ok``; :func:`warped_samples`), of the images as the fit
    compared them (the finest level's band); 0 where either has no variance there. Not
    differentiable (the fit judges without autograd)."""
    w = ok.view(torch.uint8).to(torch.float64)  # (from bytes: torch converts bool several times slower)
    n = points.per_frame(w).clamp_min(1.0)
    x = x - points.per_pixel(points.per_frame(w * x) / n)
    y = y - points.per_pixel(points.per_frame(w * y) / n)
    wx, wy = w * x, w * y  # (weighted once: w x y, w x x and w y y multiply them on)
    sxy = points.per_frame(wx * y)
    sxx, syy = points.per_frame(wx.mul_(x)), points.per_frame(wy.mul_(y))
    den = (sxx * syy).sqrt()
    return torch.where(den > 0, sxy / den.clamp_min(1e-300), 0.0)


def backward_correlation(band1: Tensor, band2: Tensor, M: Tensor, horizon: Tensor, mask: Tensor) -> Tensor:
    """(B,) :func:`detail_correlation` judged from image 2's side: at every pixel of image 2 onto
    which the road map ``M`` (B, 3, 3; pixels of image 1 -> image 2) takes a pixel of image 1's
    road ``mask`` (B, 1, H, W) bool (the pre-image, rounded to the nearest pixel, in the mask and
    in front of camera 1 below the horizon row ``horizon`` (B, 1, 3)), image 2's band of detail
    ``band2`` (B, 1, H, W) against image 1's ``band1`` at the pre-image (bilinear).

    Where the road recedes between the frames (the backward flow of forward driving, a car
    reversing) image 1's near, detailed road falls on image 2's far, smaller road, whose band holds
    less of that detail: judged from image 1's side the right motion correlates less than a road
    coming nearer does. Judged from image 2's side the roles swap, as for a road coming nearer.
    A map that is singular judges no pixel (0)."""
    B, _, H, W = band1.shape
    M = M.to(torch.float64)
    grid = pixel_coordinates(torch.arange(H * W, device=M.device).unsqueeze(0), W)  # (1, 3, H W)
    q, singular = torch.linalg.solve_ex(M, grid.expand(B, 3, H * W))  # the pre-images, homogeneous
    ahead = ((singular == 0).unsqueeze(-1) & torch.isfinite(q).all(1) & (q[:, 2] > 1e-9)
             & ((horizon.to(torch.float64) @ q)[:, 0] > 0))
    x1 = torch.where(ahead.unsqueeze(1), q[:, :2] / torch.where(ahead, q[:, 2], 1.0).unsqueeze(1), 0.0)
    u, v = x1.round().unbind(1)
    inside = ahead & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    nearest = (v.clamp(0, H - 1) * W + u.clamp(0, W - 1)).long()
    road2 = inside & mask.reshape(B, -1).gather(1, nearest)
    flow = torch.where(ahead.unsqueeze(1), x1 - grid[:, :2], 0.0).reshape(B, 2, H, W)
    points = sample_mask(road2.reshape(B, 1, H, W), 1)  # (every pixel of it; no subsample used)
    at2, at1, ok = warped_samples((band2,), (band1,), flow, ahead.reshape(B, 1, H, W), points)
    return detail_correlation(at2[0], at1[0], ok, points)


def matched_gain(I1: Tensor, I2: Tensor, ok: Tensor, points: MaskPoints, threshold: float,
                  iterations: int = 2) -> tuple[Tensor, Tensor]:
    """Per frame (B,) the gain and offset that match image 2's intensities ``I2`` to image 1's
    ``I1`` (paired samples at ``ok`` points): their means and spreads matched, weighted robustly
    (Cauchy weights at ``threshold`` of the residuals, ``iterations`` times).

    Matching the spreads, not regressing one image on the other: under a wrong flow the samples
    do not correspond, and a regression's gain would shrink toward 0, making any flow over a
    plain road look right; the spreads' ratio stays the images' contrast ratio. Not differentiable
    (the fit judges without autograd).
    """
    w = usable = ok.view(torch.uint8).to(torch.float64)  # (from bytes: torch converts bool several times slower)
    # the per-point terms written into one scratch tensor, and the weights into another: the fit
    # judges every mask pixel, where a new tensor per term (some twenty per pass) cost more than
    # the arithmetic (python benchmarks/bench_image_fit.py --baseline)
    term = torch.empty_like(usable, dtype=torch.promote_types(torch.promote_types(I1.dtype, I2.dtype), usable.dtype))
    weights = torch.empty_like(term)
    gain = offset = None
    for i in range(iterations + 1):
        n = points.per_frame(w).clamp_min(1e-12)
        m1, m2 = points.per_frame(torch.mul(w, I1, out=term)) / n, points.per_frame(torch.mul(w, I2, out=term)) / n
        s1 = points.per_frame(torch.sub(I1, points.per_pixel(m1), out=term).abs_().mul_(w)) / n  # Σ w |I1 - m1|
        s2 = points.per_frame(torch.sub(I2, points.per_pixel(m2), out=term).abs_().mul_(w)) / n
        gain = torch.where(s2 > 0, s1 / s2.clamp_min(1e-12), 1.0)
        offset = m1 - gain * m2
        if i == iterations:  # (the last pass: its weights would weigh nothing more)
            break
        # r = (gain I2 + offset - I1) / threshold, w = usable / (1 + r²)
        r = torch.mul(I2, points.per_pixel(gain), out=term).add_(points.per_pixel(offset)).sub_(I1).div_(threshold)
        w = torch.div(usable, r.square_().add_(1.0), out=weights)
    return gain, offset


def spread_out(inliers: Tensor, least: int = 3) -> Tensor:
    """(B,) bool: the inliers (B, 1, H, W) lie on at least ``least`` rows and ``least`` columns (a
    single row or column pins a road model's motion poorly: the road's texture along it matches
    under many motions)."""
    in8 = inliers.view(torch.uint8)  # (max over uint8: a bool any() along a dimension is slower)
    return (in8.amax(3).flatten(1).sum(1) >= least) & (in8.amax(2).flatten(1).sum(1) >= least)


def agreement(flow: Tensor, model_flow: Tensor, model_valid: Tensor, points: MaskPoints,
              threshold: float) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Inliers (B, 1, H, W) — mask pixels within ``threshold`` px of the model flow where it is
    defined — their mean end-point error (B,), whether they spread over at least 3 rows and
    columns (B,), their share of the mask pixels where the model is defined (B,), and their
    number (B,) float64.

    Works on the mask's pixels only (``points.every``), frame by frame: a road mask is a
    fraction of the image, and full-size differences, norms and sums cost more than gathering
    them from each frame's own contiguous flow. The end-point errors stay in the flow's dtype (in
    place on the fresh gathers); only the sums are float64 (python benchmarks/bench_fit.py: a
    float64 copy of the gathered flows cost more than the rest). A batch reads where each
    frame's pixels start once (bench_fit.py, batch 8: gathering the whole batch through
    channel-first copies of both flows cost more than the rest of the fit)."""
    B, _, H, W = flow.shape
    HW, every = H * W, points.every
    bounds = [0, every.numel()] if B == 1 else points.bounds.tolist()
    inliers = torch.zeros(B, HW, dtype=torch.bool, device=flow.device)
    n_in, n_use, epe_in = [], [], []
    for b in range(B):
        idx = every[bounds[b]:bounds[b + 1]]
        idx = idx - b * HW if b else idx
        at = idx.expand(2, -1)
        diff = model_flow[b].reshape(2, HW).gather(1, at).sub_(flow[b].reshape(2, HW).gather(1, at).to(model_flow.dtype))
        # (|d|² then its root: hypot's overflow guard is not needed for a flow's differences)
        epe = torch.mul(diff[0], diff[0], out=diff[0]).addcmul_(diff[1], diff[1]).sqrt_()
        use = model_valid[b].reshape(HW).gather(0, idx)
        inl = torch.le(epe, threshold).logical_and_(use)
        inliers[b].scatter_(0, idx, inl)
        # (count_nonzero and masked_fill_: a bool sum or product first converts the flags)
        n_in.append(torch.count_nonzero(inl))
        n_use.append(torch.count_nonzero(use))
        epe_in.append(epe.masked_fill_(inl.logical_not(), 0.0).sum(dtype=torch.float64))
    n_in = torch.stack(n_in).to(torch.float64)
    residual = torch.stack(epe_in) / n_in.clamp_min(1)
    fraction = n_in / torch.stack(n_use).clamp_min(1)
    inliers = inliers.reshape(B, 1, H, W)
    return inliers, residual.to(model_flow.dtype), spread_out(inliers), fraction, n_in
