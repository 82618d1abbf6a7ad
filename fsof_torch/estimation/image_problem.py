"""One pyramid level's photometric problem for the image fit
(:func:`~fsof_torch.estimation.image_fit.fit_image`): the road pixels it samples (those with the
strongest gradient among candidates spread evenly over the mask), their intensities and
gradients, and the residuals and Jacobians of a road model's motion there, for the library's
solver (:mod:`~fsof_torch.estimation.solver`)."""

from __future__ import annotations

import math
from typing import Callable

import torch
from torch import Tensor

from ..geometry.camera import Camera
from ..geometry.road_models import RoadModel
from .sampling import MaskPoints, pixel_coordinates, resample_mask, sample_mask, sample_points
from .solver import Evaluation

__all__ = ["ImageProblem", "level_problem", "level_scale", "with_gradient", "pixel_gradient"]


def with_gradient(image: Tensor) -> Tensor:
    """``image`` (B, 1, H, W) and its central-difference gradient: (B, 3, H, W) = (I, ∂I/∂x,
    ∂I/∂y), replicated at the border. Sampling this bilinearly gives the same numbers as central
    differences of bilinear samples one pixel apart (both are linear in the pixels, and a shift by
    whole pixels keeps the interpolation weights), for one ``grid_sample`` of three channels
    instead of five points."""
    # (written into one tensor, without a padded copy: half the difference of the two neighbours,
    # the pixel itself standing in for a missing one at the border; 0 across a single pixel)
    B, _, H, W = image.shape
    out = image.new_empty(B, 3, H, W)
    out[:, :1] = image
    gx, gy = out[:, 1:2], out[:, 2:3]
    if W > 1:
        torch.sub(image[..., 2:], image[..., :-2], out=gx[..., 1:-1])
        torch.sub(image[..., 1:2], image[..., :1], out=gx[..., :1])
        torch.sub(image[..., -1:], image[..., -2:-1], out=gx[..., -1:])
    else:
        gx.zero_()
    if H > 1:
        torch.sub(image[..., 2:, :], image[..., :-2, :], out=gy[..., 1:-1, :])
        torch.sub(image[..., 1:2, :], image[..., :1, :], out=gy[..., :1, :])
        torch.sub(image[..., -1:, :], image[..., -2:-1, :], out=gy[..., -1:, :])
    else:
        gy.zero_()
    out[:, 1:].mul_(0.5)
    return out


def pixel_gradient(image: Tensor, pix: Tensor) -> tuple[Tensor, Tensor]:
    """``image`` (B, 1, H, W) at flat pixel indices (B, N): values (B, N) and central-difference
    gradients (B, 2, N) (one-sided at the image border), gathered (no gradient image)."""
    H, W = image.shape[-2:]
    B, N = pix.shape
    v = torch.div(pix, W, rounding_mode="floor")
    u = pix - v * W
    # the neighbours' columns and rows, clamped into the image (one-sided differences at its
    # border); the pixel and its four neighbours read in one gather
    left, right = (u - 1).clamp_min(0), (u + 1).clamp_max(W - 1)
    up, down = (v - 1).clamp_min(0), (v + 1).clamp_max(H - 1)
    row = v * W
    at = image.reshape(B, -1).gather(1, torch.cat([pix, row + right, row + left, down * W + u, up * W + u], dim=1))
    at = at.reshape(B, 5, N)
    du, dv = (right - left).to(image.dtype), (down - up).to(image.dtype)
    g = torch.stack([(at[:, 1] - at[:, 2]) / du.clamp_min(1), (at[:, 3] - at[:, 4]) / dv.clamp_min(1)], dim=1)
    return at[:, 0].to(torch.float64), g.to(torch.float64)


class ImageProblem:
    """The photometric residuals of a road model at fixed sample points of one pyramid level.

    Parameters (B, P + 2): the model's, then the gain a and the offset b. Residual per point:
    e = a I_2(x + f(x; p)) + b − I_1(x), grey levels.

    ``pts`` (B, 3, N) homogeneous pixel coordinates of the points, ``I1`` (B, N) and ``grad1``
    (B, 2, N) image1 there, ``image2`` (B, 3, H, W) image2 with its gradient (I, ∂I/∂x, ∂I/∂y),
    ``sel`` (B, N) the real points.
    """

    def __init__(self, model: RoadModel, camera: Camera, pts: Tensor, I1: Tensor, grad1: Tensor,
                 image2: Tensor, sel: Tensor) -> None:
        self.model, self.pts, self.I1, self.grad1, self.image2, self.sel = model, pts, I1, grad1, image2, sel
        self.K, self.K_inv, self.height = camera.K, camera.K_inv(), camera.height
        self.horizon_camera = camera
        self.count = sel.sum(1)
        self.P = len(model.params)
        # (the iterations' constants, formed once: the points as the rows of the outer products,
        # and the offset's column of the Jacobian)
        self._pts_rows = pts.unsqueeze(1)  # (B, 1, 3, N)
        self._ones = torch.ones_like(I1).unsqueeze(1)  # (B, 1, N)

    def evaluate(self, params: Tensor) -> Evaluation:
        P = self.P
        # (the gain and offset as columns (B, 1): broadcast against the points without reshaping)
        values, gain, offset = params[:, :P], params[:, P:P + 1], params[:, P + 1:P + 2]
        M, dM, horizon = self.model.evaluate(self.K, self.K_inv, self.height, values, True)
        if horizon is None:
            horizon = self.model.horizon_row(self.horizon_camera, values)
        B = M.shape[0]
        q = torch.bmm(torch.cat([M, horizon], dim=1), self.pts)  # (B, 4, N): the mapped point, the horizon test
        qz = q[:, 2]
        ok = self.sel & (q[:, 3] > 0) & (qz > 1e-9)
        inv_z = torch.where(ok, qz, 1.0).reciprocal().unsqueeze(1)  # (B, 1, N)
        proj = q[:, :2] * inv_z
        sample, inb = sample_points(self.image2, proj)  # (B, 3, N): I_2 and its gradient
        I2, grad2 = sample[:, 0], sample[:, 1:]
        use = ok & inb
        e = gain * I2 + offset - self.I1
        # efficient second-order minimisation: the mean of both images' gradients
        grad = 0.5 * (self.grad1 + gain.unsqueeze(-1) * grad2)
        # ∂e/∂p = g · ∂proj/∂p with ∂proj/∂p = (dq_xy − proj dq_z) / z and dq = dM x:
        # = Σ_ij dM_ij c_i x_j, c = (g_x, g_y, −g · proj) / z, one (P x 9) @ (9 x N) product
        c = torch.cat([grad, -(grad * proj).sum(1, keepdim=True)], dim=1) * inv_z
        outer = (c.unsqueeze(2) * self._pts_rows).reshape(B, 9, -1)
        J_image = torch.bmm(dM.reshape(B, P, 9), outer)
        J = torch.cat([J_image, sample[:, :1], self._ones], dim=1)  # (by the gain: I_2; by the offset: 1)
        return Evaluation(e.square(), use, e.unsqueeze(1), J)

    def normal_equations(self, ev: Evaluation, w: Tensor) -> tuple[Tensor, Tensor]:
        J = ev.state  # (B, P + 2, N)
        Jw = J * w.unsqueeze(1)
        return torch.bmm(Jw, J.transpose(1, 2)), torch.bmm(Jw, ev.residual.transpose(1, 2)).squeeze(-1)


def level_problem(model: RoadModel, camera: Camera, img: Tensor, mask: Tensor, gradient_fraction: float,
                   max_points: int | None, reps: int, pixels: MaskPoints | None = None) -> ImageProblem:
    """The sample points of one pyramid level (the points that carry the information): the k road
    pixels of each frame with the strongest gradient among its candidates, where

    - with ``max_points``, the candidates are up to n = min(⌈max_points / gradient_fraction⌉,
      h w) road pixels evenly spread, and k = round(gradient_fraction n) (``max_points``, or
      ``gradient_fraction`` of a level smaller than n): a frame whose road has no more than k
      pixels at the level keeps all of them;
    - with None, the candidates are all the frame's road pixels and k is round(gradient_fraction
      × their count), at least 1 (ties in raster order): a frame's points do not depend on its
      batch-mates.

    ``pixels``: the mask's pixels where already known."""
    w_l = img.shape[-1]
    I1, I2 = img[:, :1], img[:, 1:]
    # (no more candidates than the level has pixels: coarse levels do not carry padding)
    n_candidates = None if max_points is None else min(int(math.ceil(max_points / gradient_fraction)),
                                                        img.shape[-2] * w_l)
    points = sample_mask(mask, n_candidates) if pixels is None else resample_mask(pixels, mask.shape[-2:], n_candidates)
    I1p, g1p = pixel_gradient(I1, points.pix)
    pix, sel = points.pix, points.sel
    if gradient_fraction < 1.0:
        # of each frame's candidates, the strongest gradients (padding never wins)
        keep = max(1, int(round(gradient_fraction * pix.shape[1])))
        strength = torch.where(sel, g1p.abs().sum(1), -1.0)
        if max_points is None:
            # the candidates are padded to the largest count in the batch: each frame keeps its
            # own share (a stable order: the same points whatever the padding)
            ranked = strength.sort(dim=1, descending=True, stable=True).indices[:, :keep]
            own = (gradient_fraction * points.count.to(torch.float64)).round().clamp_min(1)
            within = torch.arange(keep, device=pix.device) < own.unsqueeze(1)  # (B, keep), rank order
            sel = sel & torch.zeros_like(sel).scatter_(1, ranked, within)
        else:
            ranked = strength.topk(keep, dim=1, sorted=False).indices  # (the same set: raster order below)
        order = ranked.sort(dim=1).values
        pix, sel, I1p, g1p = pix.gather(1, order), sel.gather(1, order), I1p.gather(1, order), \
            g1p.gather(2, order.unsqueeze(1).expand(-1, 2, -1))
    pts = pixel_coordinates(pix, w_l)
    # (one start uses the level's tensors themselves, several a copy per start)
    rep = (lambda t: t) if reps == 1 else (lambda t: t.repeat(reps, *([1] * (t.dim() - 1))))
    cam = camera if reps == 1 else camera.repeat(reps)
    return ImageProblem(model, cam, rep(pts), rep(I1p), rep(g1p), rep(with_gradient(I2)), rep(sel))


def level_scale(scale: float | None, reps: int) -> float | Callable[[Evaluation], Tensor]:
    """The kernel's scale per sample (grey levels): given, or 1.4826 × the median absolute
    residual at the level's start (of the first start where several compete, so that their costs
    compare), at least 2."""
    if scale is not None:
        return float(scale)

    def from_start(ev: Evaluation) -> Tensor:
        mad = torch.nanmedian(torch.where(ev.use, ev.r2.sqrt(), float("nan")), dim=1).values
        s = (1.4826 * torch.nan_to_num(mad, nan=2.0)).clamp_min(2.0)
        return s.reshape(reps, -1)[0].repeat(reps)

    return from_start
