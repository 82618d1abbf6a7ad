"""Direct photometric fit of the displacement model: ego-motion from the two images themselves.

Flow methods fail on the road exactly where its motion is large and its texture weak (the
bottom of the image), and a fit to such a flow inherits the failure. The road's motion is
nevertheless fixed by a handful of parameters, and the images determine them: this module
minimises the robust photometric error of the road between the two frames under the model
flow,

    E(p) = Σ_road ρ( a · I_2(x + f(x; p)) + b − I_1(x) ),   p = (x_d/h, z_d/h, φ[, θ, β]),

with a gain a and an offset b absorbing an exposure change, by Gauss–Newton (Levenberg–Marquardt
damping) coarse to fine over an image pyramid. Images are converted to grey and smoothed; the
gradient is the ESM average of the gradients of I_1 and of the warped I_2, which widens the
basin of convergence. Warping goes through :func:`fsof_torch.warp.warp_backward`.

The result is a :class:`fsof_torch.fit.FitResult`; its ``residual`` and ``inliers`` refer to the
photometric residual (grey levels, 0..255 scale), not to an end-point error.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import Tensor

from .._check import check_float_tensor, check_shape, result_dtype
from ..geometry.camera import Camera, mounting_matrix
from ..geometry.road_flow import displacement_flow

if TYPE_CHECKING:  # fit imports this module at its end
    from .flow_fit import FitResult

__all__ = ["fit_photometric"]


def _grey(image: Tensor) -> Tensor:
    if image.shape[1] == 3:
        w = torch.tensor([0.299, 0.587, 0.114], dtype=image.dtype, device=image.device)
        return (image * w.reshape(1, 3, 1, 1)).sum(1, keepdim=True)
    return image


def _gather(x: Tensor, pix: Tensor) -> Tensor:
    """x (B, C, H, W) at flat pixel indices (B, N) -> (B, C, N)."""
    B, C = x.shape[:2]
    return x.reshape(B, C, -1).gather(2, pix.unsqueeze(1).expand(B, C, pix.shape[1]))


def _sample_points(image: Tensor, xy: Tensor) -> tuple[Tensor, Tensor]:
    """Bilinear samples of ``image`` (B, C, H, W) at pixel positions ``xy`` (B, 2, N) float64.

    The iterations need the warped image only at the road's sample points, so they sample those
    points (grid_sample on a (B, 1, N) grid, the corner-aligned normalisation written here)
    instead of warping the whole frame with :func:`warp_backward`, which the final full-resolution
    evaluation uses. Returns (B, C, N) float64 and in-bounds flags (B, N).
    """
    B, C, H, W = image.shape
    x, y = xy[:, 0], xy[:, 1]
    inb = (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
    gx = x * (2.0 / max(W - 1, 1)) - 1.0
    gy = y * (2.0 / max(H - 1, 1)) - 1.0
    grid = torch.stack([gx, gy], dim=-1).unsqueeze(1).to(image.dtype)  # (B, 1, N, 2)
    out = F.grid_sample(image, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out[:, :, 0].to(torch.float64), inb


@torch.no_grad()
def fit_photometric(image1: Tensor, image2: Tensor, mask: Tensor, camera: Camera, *,
                    init: object = None, fit_roll: bool = True, fit_pitch: bool = False,
                    levels: int | None = None, min_size: int = 24, max_iter: int = 20,
                    tol: float = 1e-6, smooth_sigma: float = 1.0, robust: str = "cauchy",
                    scale: float | None = None, max_points: int | None = 40000,
                    affine: bool = True, inlier_threshold: float = 10.0,
                    min_points: int = 100) -> "FitResult":
    """Fit x_d, z_d, yaw (and roll / pitch) by minimising the road's photometric error.

    Args:
        image1, image2: the frames at t and t+1, (B, 3, H, W) RGB or (B, 1, H, W) grey, 0..255.
        mask: road pixels of image1 (B, 1, H, W) bool (batch 1 broadcasts).
        camera: intrinsics at the images' resolution, known height; roll / pitch used where not
            fitted and as the start.
        init: a start: a :class:`FitResult` (e.g. of :func:`fit_displacement` on a flow) or a dict
            with any of x_d, z_d, yaw, roll, pitch; default zero motion.
        fit_roll, fit_pitch: also fit the mounting roll / pitch (radians).
        levels: pyramid levels (default: halve until the shorter side would drop below
            ``min_size``); each level runs at most ``max_iter`` Gauss–Newton iterations,
            stopping when the step falls below ``tol`` (relative).
        smooth_sigma: Gaussian smoothing of the grey images in pixels before the pyramid.
        robust: the kernel of the IRLS weights (see :data:`fsof_torch.fit.ROBUST_KERNELS`).
        scale: its scale in grey levels (default: from the residuals' median absolute
            deviation at each level's start, at least 2).
        max_points: at most this many road pixels per frame and level (deterministic stride).
        affine: also fit a gain and an offset between the frames' brightness.
        inlier_threshold: |photometric residual| in grey levels below which a road pixel is an
            inlier at the end; min_points: fewer inliers mark the frame as failed.

    Returns:
        :class:`fsof_torch.fit.FitResult`: parameters (B,), the model ``flow`` (B, 2, H, W) px,
        ``valid``, ``inliers`` (photometric), ``residual`` (B,): mean |photometric residual| over
        the inliers in grey levels, ``success``.
    """
    from kornia.filters import gaussian_blur2d, spatial_gradient
    from kornia.geometry.transform import build_pyramid

    from .flow_fit import (FitResult, _check_options, _evaluate, _homography_jac, _init_value, _mask_sample,
                      _pixels, _robust_cost, robust_weight)
    from ..evaluation.warp import warp_backward

    for name, img in (("image1", image1), ("image2", image2)):
        check_float_tensor(img, name)
    dims = check_shape(image1, "image1", ("B", "C", "H", "W"))
    check_shape(image2, "image2", ("B", "C", "H", "W"), dims)
    if dims["C"] not in (1, 3):
        raise ValueError(f"image1: expected 1 or 3 channels, got {dims['C']}")
    B, H, W = dims["B"], dims["H"], dims["W"]
    if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
        raise TypeError(f"mask: expected a bool tensor of shape (B, 1, H, W), got "
                        f"{mask.dtype if isinstance(mask, Tensor) else type(mask).__name__}")
    if mask.dim() == 4 and mask.shape[0] == 1 and B != 1:
        mask = mask.expand(B, -1, -1, -1)
    check_shape(mask, "mask", ("B", 1, "H", "W"), dims)
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a fsof_torch.Camera, got {type(camera).__name__}")
    if camera.batch_size not in (1, B):
        raise ValueError(f"camera: expected batch 1 or {B} (the images' B), got {camera.batch_size}")
    _check_options(robust, 1.0 if scale is None else scale, max_iter, tol, max_points)
    for name, img in (("image1", image1), ("image2", image2)):
        if not bool(torch.isfinite(img).all()):
            raise ValueError(f"{name}: expected finite values, got NaN or inf")
    out_dtype = result_dtype(image1, camera.K)
    camera = camera.expand(B).to(device=image1.device)
    cam64 = camera.to(torch.float64)
    h = cam64.height

    if levels is None:
        levels = max(1, int(math.floor(math.log2(max(min(H, W), 1) / min_size))) + 1)
    work = torch.float32 if image1.dtype != torch.float64 else torch.float64
    grey = torch.cat([_grey(image1.detach().to(work)), _grey(image2.detach().to(work))], dim=1)
    if smooth_sigma > 0:
        k = 2 * int(math.ceil(3 * smooth_sigma)) + 1
        grey = gaussian_blur2d(grey, (k, k), (smooth_sigma, smooth_sigma), border_type="replicate")
    pyramid = build_pyramid(grey, levels)

    zero = torch.zeros(B, dtype=torch.float64, device=image1.device)
    roll0 = _init_value(init, "roll", B, cam64.roll.clone())
    pitch0 = _init_value(init, "pitch", B, cam64.pitch.clone())
    a0 = _init_value(init, "x_d", B, zero) / h
    b0 = _init_value(init, "z_d", B, zero) / h
    yaw0 = _init_value(init, "yaw", B, zero)
    params = torch.stack([a0, b0, yaw0, roll0, pitch0], dim=-1)
    gain = torch.ones(B, dtype=torch.float64, device=image1.device)
    offset = torch.zeros(B, dtype=torch.float64, device=image1.device)
    free = torch.tensor([True, True, True, bool(fit_roll), bool(fit_pitch)] + [affine, affine],
                        device=image1.device)
    P = free.numel()
    eye = torch.eye(P, dtype=torch.float64, device=image1.device)
    iters = torch.zeros(B, dtype=torch.long, device=image1.device)
    converged = torch.zeros(B, dtype=torch.bool, device=image1.device)
    finest_An = None

    for level in reversed(range(levels)):
        img = pyramid[level]
        h_l, w_l = img.shape[-2:]
        cam_l = cam64.scaled(w_l / W, h_l / H)
        K, Kinv = cam_l.K, cam_l.K_inv()
        if level == 0:
            mask_l = mask
        else:
            # a coarse pixel is road only if all the fine pixels under it are
            mask_l = F.interpolate(mask.to(work), size=(h_l, w_l), mode="area") > 0.999
        pix, sel, _ = _mask_sample(mask_l, max_points)
        pts = _pixels(pix, w_l)
        I1, I2 = img[:, :1], img[:, 1:]
        g1 = spatial_gradient(I1, mode="diff", order=1)[:, 0]  # (B, 2, h, w): d/du, d/dv (central)
        g2 = spatial_gradient(I2, mode="diff", order=1)[:, 0]
        stack2 = torch.cat([I2, g2], dim=1)
        I1p = _gather(I1, pix)[:, 0].to(torch.float64)
        g1p = _gather(g1, pix).to(torch.float64)
        lam = torch.full((B,), 1e-3, dtype=torch.float64, device=image1.device)
        s_level = None
        prev_cost = None
        prev_state = None
        done = torch.zeros(B, dtype=torch.bool, device=image1.device)

        def residual(params, gain, offset, want_jac):
            M, dM = _homography_jac(K, Kinv, params)
            ray_row = (mounting_matrix(params[:, 3], params[:, 4]).transpose(-1, -2) @ Kinv)[:, 1:2, :]
            flow_p, valid_m, J = _evaluate(M, ray_row, pts, False, dM if want_jac else None)
            I2p, inb = _sample_points(stack2, pts[:, :2] + flow_p)
            ok = inb & sel & valid_m
            e = gain.unsqueeze(-1) * I2p[:, 0] + offset.unsqueeze(-1) - I1p
            return e, ok, I2p, J

        for it in range(max_iter):
            e, ok, I2p, J = residual(params, gain, offset, True)
            if s_level is None:
                if scale is not None:
                    s_level = torch.full((B,), float(scale), dtype=torch.float64, device=image1.device)
                else:
                    ae = torch.where(ok, e.abs(), torch.full_like(e, float("nan")))
                    mad = torch.nan_to_num(torch.nanmedian(ae, dim=1).values, nan=2.0)
                    s_level = (1.4826 * mad).clamp_min(2.0)
            r2 = torch.where(ok, e * e, torch.zeros_like(e))
            w = robust_weight(r2, s_level.unsqueeze(-1), robust) * ok
            n_ok = ok.sum(1).clamp_min(1)
            cost = (_robust_cost(r2, s_level.unsqueeze(-1), robust) * ok).sum(1) / n_ok
            if prev_cost is not None:
                # reject a step that made things worse: go back and damp more
                worse = ~(cost <= prev_cost) & ~done
                if bool(worse.any()):
                    p_prev, g_prev, o_prev, step_prev = prev_state
                    params = torch.where(worse.unsqueeze(-1), p_prev, params)
                    gain = torch.where(worse, g_prev, gain)
                    offset = torch.where(worse, o_prev, offset)
                    lam = torch.where(worse, lam * 10.0, (lam / 3.0).clamp_min(1e-9))
                    if bool(worse.all()):
                        continue
                    e, ok, I2p, J = residual(params, gain, offset, True)
                    r2 = torch.where(ok, e * e, torch.zeros_like(e))
                    w = robust_weight(r2, s_level.unsqueeze(-1), robust) * ok
                    n_ok = ok.sum(1).clamp_min(1)
                    cost = (_robust_cost(r2, s_level.unsqueeze(-1), robust) * ok).sum(1) / n_ok
                else:
                    lam = (lam / 3.0).clamp_min(1e-9)
            grad = 0.5 * (g1p + gain.reshape(B, 1, 1) * I2p[:, 1:])  # ESM: mean of both gradients
            Jg = gain.reshape(B, 1, 1) * (grad[:, None, 0] * J[:, :, 0] + grad[:, None, 1] * J[:, :, 1])
            Jall = torch.cat([Jg, I2p[:, None, 0], torch.ones_like(I2p[:, None, 0])], dim=1)  # (B, P, N)
            Jw = Jall * w.unsqueeze(1)
            A = Jw @ Jall.transpose(1, 2)
            g = (Jw * e.unsqueeze(1)).sum(-1)
            fixed = ~free
            A = torch.where(fixed.unsqueeze(-1) | fixed.unsqueeze(-2), eye.expand(B, P, P) * fixed.unsqueeze(-1), A)
            g = torch.where(fixed, torch.zeros_like(g), g)
            diag = A.diagonal(dim1=-2, dim2=-1)
            sc = torch.maximum(diag, 1e-12 * diag.amax(-1, keepdim=True)).clamp_min(1e-300).sqrt()
            An = A / (sc.unsqueeze(-1) * sc.unsqueeze(-2))
            L = An + lam.reshape(B, 1, 1) * eye
            delta = -torch.linalg.solve(L, (g / sc).unsqueeze(-1)).squeeze(-1) / sc
            delta = torch.where(fixed | done.unsqueeze(-1), torch.zeros_like(delta), delta)
            delta = torch.nan_to_num(delta, nan=0.0, posinf=0.0, neginf=0.0)
            prev_state = (params, gain, offset, delta)
            prev_cost = cost
            params = params + delta[:, :5]
            gain = gain + delta[:, 5]
            offset = offset + delta[:, 6]
            iters += (~done).long()
            small = (delta[:, :5].abs() <= tol * (1.0 + params.abs())).all(-1)
            done = done | small
            if level == 0:
                finest_An = An
            if bool(done.all()):
                break
        if level == 0:
            converged = done | (lam < 1e3)

    x_d, z_d = params[:, 0] * h, params[:, 1] * h
    yaw, roll, pitch = params[:, 2], params[:, 3], params[:, 4]
    finite = torch.isfinite(params).all(-1)
    cam_fit = camera.replace(roll=roll.to(camera.dtype), pitch=pitch.to(camera.dtype))
    model, model_valid = displacement_flow(cam_fit.to(torch.float64), x_d, z_d, yaw, (H, W))
    model = model.to(out_dtype)
    # photometric inliers at full resolution
    g1, g2 = grey[:, :1], grey[:, 1:]
    warped, inb = warp_backward(g2, model.to(work))
    err = (gain.reshape(B, 1, 1, 1) * warped.to(torch.float64) + offset.reshape(B, 1, 1, 1)
           - g1.to(torch.float64)).abs()
    use = mask & model_valid & inb
    inliers = use & (err <= inlier_threshold)
    n_in = inliers.flatten(1).sum(1)
    residual = (torch.where(inliers, err, torch.zeros_like(err))).flatten(1).sum(1) / n_in.clamp_min(1)
    if finest_An is not None:
        well_posed = torch.linalg.eigvalsh(finest_An)[:, 0] > 1e-9
    else:
        well_posed = torch.zeros(B, dtype=torch.bool, device=image1.device)
    success = finite & converged & well_posed & (n_in >= min_points)
    return FitResult(
        x_d=x_d.to(out_dtype), z_d=z_d.to(out_dtype), yaw=yaw.to(out_dtype),
        roll=roll.to(out_dtype), pitch=pitch.to(out_dtype), flow=model, valid=model_valid,
        inliers=inliers, residual=residual.to(out_dtype), success=success,
        camera=cam_fit.to(out_dtype), iterations=iters)
