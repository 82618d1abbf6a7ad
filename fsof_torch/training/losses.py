"""Training losses for flow networks: an unsupervised (photometric) loss and the freespace term.

Every term exists as a plain function and as an ``nn.Module`` twin, and accepts either one flow
(B, 2, H, W) or a RAFT-style list of flows, coarse to refined, weighted γ^(N-1-i) as RAFT does
(the last estimate has weight 1; the weights are not normalised). :class:`CompositeLoss` adds
terms with weights and reports each term's value separately (:mod:`.composite`, imported here).

- :func:`unsupervised_flow_loss` (ARFlow / UFlow style): photometric error of the second image
  warped back by the flow (L1 + SSIM, optionally census) over pixels that are in bounds and pass
  the forward-backward consistency check (its mask carries no gradient), plus edge-aware
  smoothness of the flow (first or second order).
- :func:`freespace_flow_loss`: a robust penalty (Charbonnier or Cauchy) between the predicted
  flow and the road flow of the freespace model (paper eq. 13) inside the road mask, from given
  odometry or from the displacement model fitted to the (detached) prediction.

Every mean is over a count clamped to at least 1: an empty mask or a warp that leaves the image
everywhere gives a loss of 0 with finite (zero) gradients, never NaN.

Precision: the arithmetic of every term runs in at least float32, also under ``torch.autocast``
(bfloat16 keeps three significant digits: enough to make the freespace term of the exact model
flow 3.3 instead of 0, and to flatten SSIM's variances and the census comparisons). A loss comes
back in the prediction's dtype lifted to at least float32, as autocast's own losses do.

Non-finite values. Images must be finite everywhere and within [-0.01, 1.01] × ``data_range``
(0..``data_range`` with 1% either side for rounding; ValueError naming the image otherwise);
flows given to the unsupervised loss must be finite (ValueError naming ``flows[i]``), and a loss
that overflows the working dtype (flows near its largest value) is a ValueError naming the flows
in either term, never inf. In the freespace term, a NaN or inf predicted pixel outside the road
mask does not count and gets a zero gradient; one inside the mask is left out as well, with a
``RuntimeWarning`` that counts them (a network's prediction may diverge at a few pixels; the term
must not turn every gradient of the batch into NaN). Large finite values give large finite
penalties, never squaring the residual.

Convention: images (B, 3, H, W) RGB or (B, 1, H, W) grey (another channel count, such as an RGBA
frame's, is a ValueError naming the image) on 0..``data_range`` (255 by default), compared on 0..1; flow
(B, 2, H, W) in pixels, channel 0 = u, forward from ``image1`` to ``image2``; backward flow from
``image2`` to ``image1``; masks (B, 1, H, W) bool.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .._check import (
    autocast_off,
    batch_choices,
    check_bool,
    check_data_range,
    check_finite,
    check_float_tensor,
    check_image_range,
    check_int,
    check_mask,
    check_number,
    check_same_device,
    check_shape,
    result_dtype,
    skip_values,
)
from ..geometry.camera import Camera
from ..geometry.road_flow import road_flow
from ..geometry.road_models import road_motion_batch
from ..evaluation.photometric import census_transform
from ..evaluation.warp import warp_backward
from ..estimation.robust import check_fixed
from .composite import CompositeLoss  # (defined there; a name of this module's contract)
from .fitted_target import check_fit_options, fitted_target
from ..warn import warn_user

__all__ = ["sequence_weights", "forward_backward_mask", "photometric_loss", "smoothness_loss", "unsupervised_flow_loss",
           "freespace_flow_loss", "UnsupervisedFlowLoss", "FreespaceFlowLoss", "CompositeLoss"]

_REDUCTIONS = ("mean", "sum", "none")
_PENALTIES = ("charbonnier", "cauchy", "l1")


# -- helpers ----------------------------------------------------------------------------------

def _check_reduction(reduction: str) -> None:
    if reduction not in _REDUCTIONS:
        raise ValueError(f"reduction: expected one of {_REDUCTIONS}, got {reduction!r}")


def _reduce(per_sample: Tensor, reduction: str) -> Tensor:
    if reduction == "mean":
        return per_sample.mean()
    if reduction == "sum":
        return per_sample.sum()
    return per_sample


def _as_flow_list(flows: Tensor | Sequence[Tensor], name: str = "flows") -> list[Tensor]:
    if isinstance(flows, Tensor):
        return [flows]
    if not isinstance(flows, (list, tuple)) or len(flows) == 0:
        raise TypeError(f"{name}: expected a tensor (B, 2, H, W) or a non-empty list of them, got "
                        f"{type(flows).__name__}" + (" of length 0" if isinstance(flows, (list, tuple)) else ""))
    return list(flows)


def _check_flow(flow: Tensor, name: str, dims: dict[str, int]) -> None:
    check_float_tensor(flow, name)
    if flow.dim() == 5 and flow.shape[2] == 2:  # (its own message: not a list of estimates)
        raise ValueError(f"{name}: expected shape (B, 2, H, W), got {tuple(flow.shape)}, a stack (B, N, 2, H, W) as "
                         f"ptlflow's outputs['flows']: give flows[:, -1], or a list of the N estimates")
    check_shape(flow, name, ("B", 2, "H", "W"), dims, nonempty=("B", "H", "W"))


def _check_mask(mask: Tensor | None, name: str, dims: dict[str, int]) -> None:
    if mask is not None:
        check_shape(check_mask(mask, name), name, ("B", 1, "H", "W"), dims)


def _check_images(images: dict[str, Tensor], dims: dict[str, int], data_range: float) -> None:
    """Float (B, C, H, W) images, C = 1 (grey) or 3 (RGB), with one shape, finite and within
    [-0.01, 1.01] × data_range."""
    for name, img in images.items():
        check_float_tensor(img, name)
        check_shape(img, name, ("B", "C", "H", "W"), dims)
        if img.shape[1] not in (1, 3):  # (as the refiner's: an RGBA frame's alpha would count as colour)
            raise ValueError(f"{name}: expected 1 (grey) or 3 (RGB) channels, got shape {tuple(img.shape)}")
    for name, img in images.items():
        check_image_range(img, name, data_range)


def _check_weights(**weights: float) -> None:
    for name, value in weights.items():
        check_number(value, name, nonnegative=True)


def _masked_mean(value: Tensor, weight: Tensor) -> Tensor:
    """Per-sample mean of ``value`` (B, C, H, W) under ``weight`` (B, 1, H, W) in 0..1 -> (B,).

    Channels are averaged; the pixel count is clamped to 1, so an empty mask gives 0.
    """
    total = (value.mean(dim=1, keepdim=True) * weight).flatten(1).sum(dim=1)
    return total / weight.flatten(1).sum(dim=1).clamp_min(1.0)


def _check_gamma(gamma: object) -> float:
    """RAFT's decay γ: a real number (a numpy or 0-d tensor one too) with 0 < γ <= 1 -> float."""
    check_fixed(gamma, "gamma")
    value = check_number(gamma, "gamma", finite=False)
    if not 0.0 < value <= 1.0:  # (false for NaN)
        raise ValueError(f"gamma: expected 0 < gamma <= 1, got {gamma!r}")
    return value


def sequence_weights(n: int, gamma: float) -> list[float]:
    """RAFT's weights γ^(n-1-i), i = 0..n-1, for a list of n estimates (the last gets 1).

    ``n``: an int >= 1; ``gamma``: a number with 0 < γ <= 1 (Python, numpy or a 0-d tensor).
    """
    n = check_int(n, "n", minimum=1)
    gamma = _check_gamma(gamma)
    return [gamma ** (n - 1 - i) for i in range(n)]


def _image_gradients(x: Tensor) -> tuple[Tensor, Tensor]:
    """Forward differences along x (B, C, H, W-1) and y (B, C, H-1, W)."""
    return x[..., :, 1:] - x[..., :, :-1], x[..., 1:, :] - x[..., :-1, :]


# -- terms --------------------------------------------------------------------------------------

def forward_backward_mask(flow_forward: Tensor, flow_backward: Tensor, *, alpha1: float = 0.01,
                          alpha2: float = 0.5) -> Tensor:
    """Forward-backward consistency (UnFlow / UFlow / ARFlow): True where a pixel is not occluded.

    A pixel p of frame t is kept where |F_f(p) + F_b(p + F_f(p))|² < α1 (|F_f(p)|² +
    |F_b(p + F_f(p))|²) + α2 and its sample point lies inside frame t+1. No gradient flows
    through the mask.

    Args:
        flow_forward: (B, 2, H, W) pixels, frame t -> t+1, finite.
        flow_backward: (B, 2, H, W) pixels, frame t+1 -> t, finite.
        alpha1: relative tolerance (unitless); alpha2: absolute tolerance in px².

    Returns:
        (B, 1, H, W) bool, True = visible in both frames.
    """
    dims: dict[str, int] = {}
    _check_flow(flow_forward, "flow_forward", dims)
    _check_flow(flow_backward, "flow_backward", dims)
    check_same_device({"flow_forward": flow_forward, "flow_backward": flow_backward})
    check_finite(flow_forward, "flow_forward")
    check_finite(flow_backward, "flow_backward")
    _check_weights(alpha1=alpha1, alpha2=alpha2)
    return _fb_mask(flow_forward, flow_backward, alpha1, alpha2)


def _fb_mask(flow_forward: Tensor, flow_backward: Tensor, alpha1: float, alpha2: float) -> Tensor:
    with torch.no_grad(), autocast_off(flow_forward):
        work = result_dtype(flow_forward, flow_backward)
        fw, bw = flow_forward.detach().to(work), flow_backward.detach().to(work)
        bw_warped, in_bounds = warp_backward(bw, fw)
        diff = (fw + bw_warped).square().sum(dim=1, keepdim=True)
        mag = fw.square().sum(dim=1, keepdim=True) + bw_warped.square().sum(dim=1, keepdim=True)
        return (diff < alpha1 * mag + alpha2) & in_bounds


def _ssim3(x: Tensor, y: Tensor) -> Tensor:
    """SSIM map over 3x3 box windows (Monodepth, ARFlow), images on 0..1, reflect-padded.

    The training loss uses this rather than kornia's 7x7 Gaussian SSIM (which
    :mod:`fsof_torch.photometric` reports): it is the window the unsupervised flow literature
    trains with, and on the CPU it is several times cheaper, forward and backward.
    """
    c1, c2 = 0.01**2, 0.03**2
    x, y = F.pad(x, (1, 1, 1, 1), mode="reflect"), F.pad(y, (1, 1, 1, 1), mode="reflect")
    mu_x, mu_y = F.avg_pool2d(x, 3, 1), F.avg_pool2d(y, 3, 1)
    sigma_x = F.avg_pool2d(x * x, 3, 1) - mu_x * mu_x
    sigma_y = F.avg_pool2d(y * y, 3, 1) - mu_y * mu_y
    sigma_xy = F.avg_pool2d(x * y, 3, 1) - mu_x * mu_y
    return ((2 * mu_x * mu_y + c1) * (2 * sigma_xy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sigma_x + sigma_y + c2))


def _check_ssim_size(ssim_weight: float, dims: dict[str, int], name: str, shape: tuple) -> None:
    if ssim_weight and min(dims["H"], dims["W"]) < 2:
        # the 3x3 SSIM window is padded by reflection, which needs two pixels per side
        raise ValueError(f"{name}: the SSIM term needs H and W >= 2, got shape {shape} "
                         f"(pass ssim_weight=0 for images of one row or column)")


def photometric_loss(image1: Tensor, image2: Tensor, flow: Tensor, mask: Tensor | None = None, *,
                     l1_weight: float = 0.15, ssim_weight: float = 0.85, census_weight: float = 0.0,
                     data_range: float = 255.0, reduction: str = "mean") -> Tensor:
    """Photometric error between ``image1`` and ``image2`` warped back by ``flow``, for training.

    Per pixel: ``l1_weight`` · mean_c |I1 - Î1| + ``ssim_weight`` · (1 - SSIM)/2 (3×3 box
    windows, as ARFlow) + ``census_weight`` · soft Hamming distance of census transforms
    (:func:`fsof_torch.photometric.census_transform`, 7×7, summed over offsets, robust
    (|d| + 0.01)^0.4 as UFlow), with images compared on 0..1. Averaged over pixels whose sample point lies
    inside ``image2`` and inside ``mask``.

    Args:
        image1, image2: (B, 3, H, W) on 0..``data_range``, finite (ValueError otherwise; images
            0..255 with ``data_range=1`` are caught by the range check).
        flow: (B, 2, H, W) pixels, image1 -> image2, finite.
        mask: (B, 1, H, W) bool, pixels to count (e.g. the non-occluded ones), or None for all.
        l1_weight, ssim_weight, census_weight: finite weights >= 0; the SSIM term needs
            H, W >= 2.
        data_range: the images' maximum, a finite number > 0 (1.0 or 255.0).
        reduction: ``"mean"`` over the batch, ``"sum"``, or ``"none"`` for (B,).

    Returns:
        A scalar, or (B,) for ``reduction="none"``; 0 where no pixel counts or every weight is 0
        (with zero gradients into ``flow``, as ``0 * loss``). In at least float32.
    """
    _check_reduction(reduction)
    _check_weights(l1_weight=l1_weight, ssim_weight=ssim_weight, census_weight=census_weight)
    data_range = check_data_range(data_range)
    dims: dict[str, int] = {}
    _check_images({"image1": image1, "image2": image2}, dims, data_range)
    _check_flow(flow, "flow", dims)
    _check_mask(mask, "mask", dims)
    check_same_device({"image1": image1, "image2": image2, "flow": flow, "mask": mask})
    check_finite(flow, "flow")
    _check_ssim_size(ssim_weight, dims, "image1", tuple(image1.shape))
    value = _photometric(image1, image2, flow, mask, l1_weight, ssim_weight, census_weight, data_range)
    return _reduce(value, reduction)


def _photometric(image1: Tensor, image2: Tensor, flow: Tensor, mask: Tensor | None, l1_weight: float,
                 ssim_weight: float, census_weight: float, data_range: float) -> Tensor:
    """:func:`photometric_loss` per sample (B,) on checked inputs."""
    dtype = result_dtype(flow)
    with autocast_off(flow):
        flow = flow.to(dtype)
        i1 = image1.to(dtype) / data_range
        i2 = image2.to(dtype) / data_range
        warped, in_bounds = warp_backward(i2, flow)
        # Pixels sampled from outside image2 read image1 itself: they count nothing, and they do not
        # pollute the SSIM / census windows of their valid neighbours with the padding's zeros.
        warped = torch.where(in_bounds, warped, i1.detach())
        weight = in_bounds if mask is None else in_bounds & mask
        weight = weight.to(flow.dtype)
        err = torch.zeros_like(flow[:, :1])
        if l1_weight:
            err = err + l1_weight * (i1 - warped).abs().mean(dim=1, keepdim=True)
        if ssim_weight:
            s = _ssim3(i1, warped).mean(dim=1, keepdim=True)
            err = err + ssim_weight * ((1.0 - s) / 2).clamp(0.0, 1.0)
        if census_weight:
            t1 = census_transform(i1, radius=3, data_range=1.0)
            t2 = census_transform(warped, radius=3, data_range=1.0)
            dist = (t1 - t2).square()
            ham = (dist / (0.1 + dist)).sum(dim=1, keepdim=True)
            err = err + census_weight * (ham.abs() + 0.01).pow(0.4)
        if not (l1_weight or ssim_weight or census_weight):
            err = err + 0.0 * flow[:, :1]  # no term: a zero that keeps the flow's graph (zero gradients)
        return _masked_mean(err, weight)


def smoothness_loss(flow: Tensor, image: Tensor, *, order: int = 2, edge_weight: float = 10.0,
                    data_range: float = 255.0, reduction: str = "mean") -> Tensor:
    """Edge-aware smoothness of ``flow`` (ARFlow): |∇^order F| weighted by exp(-w · mean_c |∇I|).

    Args:
        flow: (B, 2, H, W) pixels, finite.
        image: (B, 3, H, W) RGB or (B, 1, H, W) grey on 0..``data_range`` (finite, range checked),
            the frame the flow starts from.
        order: 1 (first differences) or 2 (second differences; the one of columns i, i+1, i+2
            weighted by the image gradient between i+1 and i+2, as ARFlow's ``smooth_grad_2nd``;
            likewise for rows).
        edge_weight: w >= 0, per unit of image gradient on the 0..1 scale.
        reduction: ``"mean"``, ``"sum"`` or ``"none"`` for (B,).

    Returns:
        Mean weighted |difference| in pixels, the x and y directions averaged; a direction
        without differences of that order (y in an image of ``order`` rows) is left out of the
        average, and an image with none in either direction gives 0. In at least float32. A
        mean that overflows the working dtype (a flow near its largest value) raises ValueError
        naming ``flow``.
    """
    _check_reduction(reduction)
    if check_int(order, "order") not in (1, 2):  # (a TypeError for 1.0 or True)
        raise ValueError(f"order: expected 1 or 2, got {order!r}")
    _check_weights(edge_weight=edge_weight)
    data_range = check_data_range(data_range)
    dims: dict[str, int] = {}
    _check_flow(flow, "flow", dims)
    _check_images({"image": image}, dims, data_range)
    check_same_device({"flow": flow, "image": image})
    check_finite(flow, "flow")
    total = _smoothness(flow, image, order, edge_weight, data_range)
    _check_no_overflow(total, {"flow": [flow]}, "smoothness loss")
    return _reduce(total, reduction)


def _smoothness(flow: Tensor, image: Tensor, order: int, edge_weight: float, data_range: float) -> Tensor:
    """:func:`smoothness_loss` per sample (B,) on checked inputs."""
    with autocast_off(flow):
        flow = flow.to(result_dtype(flow))
        img = image.to(flow.dtype) / data_range
        gx, gy = _image_gradients(img)
        wx = torch.exp(-edge_weight * gx.abs().mean(dim=1, keepdim=True))
        wy = torch.exp(-edge_weight * gy.abs().mean(dim=1, keepdim=True))
        fx, fy = _image_gradients(flow)
        if order == 2:
            fx, _ = _image_gradients(fx)
            _, fy = _image_gradients(fy)
            wx, wy = wx[..., :, 1:], wy[..., 1:, :]  # as ARFlow's smooth_grad_2nd
        # A side shorter than order + 1 has no differences along it: that direction's sum is 0 and
        # it is not averaged in (an image with neither gives 0, still on the flow's graph).
        sx = (wx * fx.abs()).flatten(1).sum(dim=1) / max(fx[0, 0].numel(), 1) / 2
        sy = (wy * fy.abs()).flatten(1).sum(dim=1) / max(fy[0, 0].numel(), 1) / 2
        directions = int(fx[0, 0].numel() > 0) + int(fy[0, 0].numel() > 0)
        return (sx + sy) / max(directions, 1)


def unsupervised_flow_loss(flows: Tensor | Sequence[Tensor], image1: Tensor, image2: Tensor, *,
                           flows_backward: Tensor | Sequence[Tensor] | None = None, gamma: float = 0.8,
                           l1_weight: float = 0.15, ssim_weight: float = 0.85, census_weight: float = 0.0,
                           smooth_weight: float = 2.0, smooth_order: int = 2, edge_weight: float = 10.0,
                           occlusion: bool = True, alpha1: float = 0.01, alpha2: float = 0.5,
                           data_range: float = 255.0, reduction: str = "mean") -> Tensor:
    """ARFlow/UFlow-style unsupervised loss: masked photometric error + edge-aware smoothness.

    With ``flows_backward`` (the net run on (image2, image1)) the loss is symmetric (both
    directions count, each half) and, if ``occlusion``, pixels failing the forward-backward check
    of the last estimates (:func:`forward_backward_mask`, no gradient) are left out of the
    photometric term. Without it only the forward direction counts and nothing is masked but the
    pixels warped from outside the image.

    Args:
        flows: (B, 2, H, W) or a list of them (RAFT iterations, weighted γ^(N-1-i)); finite.
        image1, image2: (B, 3, H, W) on 0..``data_range``, finite (ValueError naming the image
            otherwise: 0..255 images with ``data_range=1`` are caught here). With
            ``ssim_weight > 0`` H and W must be at least 2.
        flows_backward: the same for image2 -> image1, or None.
        smooth_weight: weight of :func:`smoothness_loss` (order ``smooth_order``) against the
            photometric term (on the 0..1 scale).

    Returns:
        A scalar, or (B,) for ``reduction="none"``, in at least float32 (also under autocast). A
        loss that overflows the working dtype (flows near its largest value: the smoothness sums
        their differences) raises ValueError naming ``flows`` (or ``flows_backward``), as the
        freespace term does.
    """
    _check_reduction(reduction)
    if check_int(smooth_order, "smooth_order") not in (1, 2):
        raise ValueError(f"smooth_order: expected 1 or 2, got {smooth_order!r}")
    _check_weights(l1_weight=l1_weight, ssim_weight=ssim_weight, census_weight=census_weight,
                   smooth_weight=smooth_weight, edge_weight=edge_weight, alpha1=alpha1, alpha2=alpha2)
    check_bool(occlusion, "occlusion")
    data_range = check_data_range(data_range)
    fw = _as_flow_list(flows, "flows")
    bw = None if flows_backward is None else _as_flow_list(flows_backward, "flows_backward")
    if bw is not None and len(bw) != len(fw):
        raise ValueError(f"flows_backward: expected {len(fw)} estimates like flows, got {len(bw)}")
    weights = sequence_weights(len(fw), gamma)
    dims: dict[str, int] = {}
    _check_images({"image1": image1, "image2": image2}, dims, data_range)
    for prefix, group in (("flows", fw), ("flows_backward", bw or [])):
        for i, f in enumerate(group):
            _check_flow(f, f"{prefix}[{i}]", dims)
            check_finite(f, f"{prefix}[{i}]")
    check_same_device({"image1": image1, "image2": image2, **{f"flows[{i}]": f for i, f in enumerate(fw)},
                       **{f"flows_backward[{i}]": f for i, f in enumerate(bw or [])}})
    _check_ssim_size(ssim_weight, dims, "image1", tuple(image1.shape))
    mask_fw = mask_bw = None
    if bw is not None and occlusion:
        mask_fw = _fb_mask(fw[-1], bw[-1], alpha1, alpha2)
        mask_bw = _fb_mask(bw[-1], fw[-1], alpha1, alpha2)
    # All iterations in one batch: one warp and one SSIM call instead of N (same arithmetic).
    n = len(fw)
    dtype = result_dtype(*fw, *(bw or []))
    wts = torch.tensor(weights, dtype=dtype, device=fw[-1].device).reshape(n, 1)

    def direction(flows: list[Tensor], first: Tensor, second: Tensor, mask: Tensor | None) -> Tensor:
        stacked = torch.cat([f.to(dtype) for f in flows])
        rep = lambda x: None if x is None else x.repeat(n, *([1] * (x.dim() - 1)))  # noqa: E731
        value = _photometric(rep(first), rep(second), stacked, rep(mask), l1_weight, ssim_weight,
                             census_weight, data_range)
        value = value + smooth_weight * _smoothness(stacked, rep(first), smooth_order, edge_weight, data_range)
        return (wts * value.reshape(n, -1)).sum(dim=0)

    total = direction(fw, image1, image2, mask_fw)
    if bw is not None:
        total = (total + direction(bw, image2, image1, mask_bw)) / 2
    _check_no_overflow(total, {"flows": fw, **({} if bw is None else {"flows_backward": bw})}, "unsupervised loss")
    return _reduce(total, reduction)


def _check_no_overflow(total: Tensor, flows: Mapping[str, Sequence[Tensor]], what: str) -> None:
    """A ValueError naming the flows where ``total`` (B,), the loss of finite flows, is not finite:
    the smoothness term's sums of flow differences overflow the working dtype for flows near its
    largest value (a prediction that has diverged), which would otherwise come back as inf."""
    if skip_values(total) or bool(torch.isfinite(total).all()):
        return
    largest = {name: max(float(f.detach().abs().amax()) for f in group) for name, group in flows.items()}
    name = max(largest, key=largest.get)
    raise ValueError(f"{name}: the {what} overflows {total.dtype} (largest |flow| {largest[name]:.3g} px); the "
                     f"prediction has diverged, or compute the loss in float64")


# -- the freespace term -------------------------------------------------------------------------

def _charbonnier(r: Tensor) -> Tensor:
    """sqrt(r² + 1) - 1 (kornia's ``charbonnier_loss``) without forming r² (r = 1e20 px in float32:
    a penalty of 1e20, a gradient of ±1). The value is r (r / (hypot(r, 1) + 1)): hypot(r, 1) - 1
    cancels (float32: 0 below r = 3e-4 px, 0.6 % off at 1e-3); the gradient is r / hypot(r, 1)."""
    h = torch.hypot(r, torch.ones_like(r))
    plain = h - 1.0
    return plain + (r * (r / (h + 1.0)) - plain).detach()


# Below this |r| the Cauchy penalty is log1p(r²/2) (r² fits any float dtype; precise near 0);
# above, 2 log(hypot(r/√2, 1)), which never squares r.
_CAUCHY_SWITCH = 1024.0


def _cauchy(r: Tensor) -> Tensor:
    """log(1 + r²/2) (kornia's ``cauchy_loss``) without overflow for large r."""
    small = r.abs() < _CAUCHY_SWITCH
    r_small = torch.where(small, r, torch.zeros_like(r))
    r_large = torch.where(small, torch.full_like(r, _CAUCHY_SWITCH), r)
    return torch.where(small, torch.log1p(0.5 * r_small * r_small),
                       2.0 * torch.log(torch.hypot(r_large * math.sqrt(0.5), torch.ones_like(r))))


_PENALTY_FNS = {"charbonnier": _charbonnier, "cauchy": _cauchy, "l1": torch.abs}


def _check_scale(scale: object) -> float:
    """The residual scale: a real number (a numpy or 0-d tensor one too), finite and > 0 -> float."""
    check_fixed(scale, "scale")
    value = check_number(scale, "scale", finite=False)
    if not 0 < value < math.inf:  # (false for NaN)
        raise ValueError(f"scale: expected a finite residual scale > 0 px, got {scale!r}")
    return value


def freespace_flow_loss(flows: Tensor | Sequence[Tensor], road: Tensor, camera: Camera,
                        odometry: Mapping[str, object] | str, *, penalty: str = "charbonnier",
                        scale: float = 1.0, gamma: float = 0.8, fit_options: Mapping[str, object] | None = None,
                        reduction: str = "mean") -> Tensor:
    """Robust distance between predicted flow and the freespace model flow inside the road mask.

    The target is the road flow (:func:`fsof_torch.road_flow`) of ``camera`` under ``odometry``,
    any displacement model's motion (not the ``"velocity"`` model's, in px/s); pixels count where
    ``road`` is True, the model is defined and the prediction is finite. With ``odometry="fit"``
    a road model (``fit_options["model"]``, default the paper's) is fitted to the last (detached)
    estimate inside ``road`` and its flow, detached, is the target; frames whose fit did not
    succeed count no pixel. The fitted target only makes the road flow consistent with *some*
    plane motion: it suits fine-tuning a net whose flow is roughly right; from scratch it did not
    help in ``python -m eval train``.

    Args:
        flows: (B, 2, H, W) pixels, or a list of them (weighted γ^(N-1-i)).
        road: (B, 1, H, W) bool freespace mask.
        camera: intrinsics (at the flow's resolution) and mounting, batch 1 or B.
        odometry: the road motion from t to t+1: a dict with ``x_d``, ``z_d`` (metres) and
            ``yaw`` (radians), floats or tensors of shape (1,) or (B,); a dict with a ``"model"``
            key and a displacement model's parameters; a fit result; or ``"fit"`` (see
            :func:`~fsof_torch.geometry.road_models.road_motion`). The ``"velocity"`` model (flow
            in px/s, not pixels per frame) raises a ValueError, as does a step beyond 100 m a
            frame (odometry in millimetres) or a yaw of half a turn (degrees).
        penalty: ``"charbonnier"`` (sqrt(r² + 1) - 1, as kornia's), ``"cauchy"`` (log(1 + r²/2),
            as kornia's) or ``"l1"``, on each component of the residual r = (F - F_model) / scale;
            evaluated without forming r² where it could overflow.
        scale: residual scale in pixels, finite and > 0, a fixed number (a tensor that requires
            grad raises TypeError: its gradient would be lost); the penalty is quadratic below
            about ``scale``.
        fit_options: keyword arguments for ``fit_road`` (with a ``"model"``) or
            ``fit_displacement`` (without), used with ``odometry="fit"`` only; checked always,
            names and values (a wrong one raises, naming ``fit_options``, also with a given
            odometry, as in the module twin when it is made).

    Returns:
        Per-pixel penalty summed over u and v, averaged over the counted pixels: a scalar, or (B,)
        for ``reduction="none"``; 0 for an empty mask (road pixels where the model is defined
        nowhere: 0, with a ``RuntimeWarning`` naming ``road``). In the prediction's dtype, at least
        float32; the model flow and the penalty are computed in at least float32 whatever the
        autocast state.

    Non-finite predictions: outside ``road`` they do not count (zero gradient); inside, they are
    left out too, with a ``RuntimeWarning`` giving their number (with ``odometry="fit"`` counted
    over the whole road, also where the fit failed). A penalty that overflows the
    working dtype (a prediction near its largest value) raises ValueError naming ``flows``.
    """
    _check_reduction(reduction)
    if penalty not in _PENALTIES:
        raise ValueError(f"penalty: expected one of {_PENALTIES}, got {penalty!r}")
    scale = _check_scale(scale)
    # (checked with a given odometry too, as FreespaceFlowLoss checks them: unused, but not wrong)
    options = check_fit_options(fit_options)
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a fsof_torch.Camera, got {type(camera).__name__}")
    fw = _as_flow_list(flows, "flows")
    weights = sequence_weights(len(fw), gamma)
    dims: dict[str, int] = {}
    for i, f in enumerate(fw):
        _check_flow(f, f"flows[{i}]", dims)
    if road is None:
        raise TypeError("road: expected a bool tensor (B, 1, H, W) (the freespace mask), got None")
    _check_mask(road, "road", dims)
    check_same_device({**{f"flows[{i}]": f for i, f in enumerate(fw)}, "road": road})
    B, size = dims["B"], (dims["H"], dims["W"])
    if camera.batch_size not in (1, B):
        raise ValueError(f"camera: expected batch {batch_choices(B)} (the flows' batch), got {camera.batch_size}")
    last = fw[-1]
    work = result_dtype(*fw)
    device = last.device
    finite = [torch.isfinite(f).all(dim=1, keepdim=True) for f in fw]
    with autocast_off(last):
        if isinstance(odometry, str):
            if odometry != "fit":
                raise ValueError(f"odometry: expected a dict of x_d, z_d, yaw or 'fit', got {odometry!r}")
            target, model_valid = fitted_target(last, road & finite[-1], camera, options, work)
        else:
            geo = torch.promote_types(work, camera.dtype)
            model, values = road_motion_batch(odometry, B, geo, device, batch_of="the flows' batch",
                                               displacement=True)
            cam = camera.to(device=device, dtype=geo)
            target, model_valid = road_flow(cam, values, size, model=model)
        target = target.to(device=device, dtype=work).expand(B, 2, *size)
        counted_model = road & model_valid.to(device)
        # a diverged prediction makes the fit fail: its non-finite pixels are counted on the road
        warn_region = road if isinstance(odometry, str) else counted_model
        rho = _PENALTY_FNS[penalty]
        total = torch.zeros(B, dtype=work, device=device)
        n_bad = []
        for w, f, ok in zip(weights, fw, finite):
            counted = counted_model & ok
            n_bad.append((warn_region & ~ok).sum())
            # the residual is 0 (and its gradient too) wherever the pixel does not count
            safe = torch.where(counted, f.to(work), target)
            per_pixel = rho((safe - target) / scale).sum(dim=1, keepdim=True)
            total = total + w * _masked_mean(per_pixel, counted.to(work))
    if not skip_values(total, last):
        # samples with road pixels of which the model defines none
        undefined = road.flatten(1).any(1) & ~counted_model.flatten(1).any(1)  # (B,) (one host read for all)
        read = torch.cat([torch.stack([*n_bad, torch.isfinite(total).all()]), undefined]).tolist()
        bad, finite_total, undefined = read[:len(n_bad)], read[len(n_bad)], read[len(n_bad) + 1:]
        if any(undefined):
            warn_user(f"road: the road model is defined at none of the road pixels of samples "
                      f"{[b for b, u in enumerate(undefined) if u]}, which adds 0 to the freespace loss (odometry not "
                      f"in metres and radians, a camera that puts the road above the horizon, or with odometry='fit' "
                      f"a fit that failed)")
        if any(bad):
            listing = ", ".join(f"flows[{i}]: {n}" for i, n in enumerate(bad) if n)
            warn_user(f"flows: non-finite predicted pixels inside the road mask are left out of the "
                      f"freespace loss ({listing})")
        if not finite_total:
            largest = max(float(torch.where(ok, f.detach(), 0).abs().amax()) for f, ok in zip(fw, finite))
            raise ValueError(f"flows: the {penalty} penalty overflows {work} (largest |flow| {largest:.3g} px at "
                             f"scale {scale:g}); the prediction has diverged, or compute the loss in float64")
    return _reduce(total, reduction)


# -- modules ------------------------------------------------------------------------------------

class UnsupervisedFlowLoss(nn.Module):
    """``nn.Module`` twin of :func:`unsupervised_flow_loss` (options fixed at construction).

    ``forward(flows, image1, image2, flows_backward=None)`` -> scalar (or (B,)).

    A weight (``l1_weight`` ... ``alpha2``) given as a 0-d ``nn.Parameter`` is a parameter of the
    module under its own name: learned through the loss, moved, cast and saved with the module; another
    tensor is read as its number, as ``gamma`` (one that requires grad, whose gradient would be lost, is a TypeError).

    Example:
        >>> loss = UnsupervisedFlowLoss(smooth_weight=2.0)
        >>> value = loss(net(i1, i2), i1, i2, flows_backward=net(i2, i1))  # doctest: +SKIP
    """

    def __init__(self, *, gamma: float = 0.8, l1_weight: float = 0.15, ssim_weight: float = 0.85,
                 census_weight: float = 0.0, smooth_weight: float = 2.0, smooth_order: int = 2,
                 edge_weight: float = 10.0, occlusion: bool = True, alpha1: float = 0.01,
                 alpha2: float = 0.5, data_range: float = 255.0, reduction: str = "mean") -> None:
        super().__init__()
        _check_reduction(reduction)
        gamma = _check_gamma(gamma)
        if check_int(smooth_order, "smooth_order") not in (1, 2):
            raise ValueError(f"smooth_order: expected 1 or 2, got {smooth_order!r}")
        weights = dict(l1_weight=l1_weight, ssim_weight=ssim_weight, census_weight=census_weight,
                       smooth_weight=smooth_weight, edge_weight=edge_weight, alpha1=alpha1, alpha2=alpha2)
        _check_weights(**weights)
        check_bool(occlusion, "occlusion")
        data_range = check_data_range(data_range)
        for name, value in weights.items():
            if isinstance(value, nn.Parameter):  # (registered: parameters(), .to(), state_dict(), deepcopy)
                self.register_parameter(name, value)
            elif isinstance(value, Tensor) and value.requires_grad:  # (read as a number, its gradient would be lost)
                raise TypeError(f"{name}: expected a number or an nn.Parameter, got a tensor that requires grad "
                                f"(to learn {name}, give an nn.Parameter, which the module registers)")
            else:  # (a float: a tensor is not kept where .to() does not reach it)
                weights[name] = check_number(value, name)
        options = dict(gamma=gamma, smooth_order=int(smooth_order), occlusion=occlusion, data_range=data_range,
                       reduction=reduction, **weights)
        self.options = {k: options[k] for k in _UNSUPERVISED_OPTIONS if k not in self._parameters}

    def forward(self, flows: Tensor | Sequence[Tensor], image1: Tensor, image2: Tensor,
                flows_backward: Tensor | Sequence[Tensor] | None = None) -> Tensor:
        """The loss of ``flows`` ((B, 2, H, W) px, or a list) on ``image1, image2`` (B, C, H, W): :func:`unsupervised_flow_loss`."""
        return unsupervised_flow_loss(flows, image1, image2, flows_backward=flows_backward, **self.options,
                                      **dict(self.named_parameters(recurse=False)))

    def extra_repr(self) -> str:
        return ", ".join(f"{k}=Parameter({self._parameters[k].item():g})" if k in self._parameters
                         else f"{k}={self.options[k]!r}" for k in _UNSUPERVISED_OPTIONS)


_UNSUPERVISED_OPTIONS = ("gamma", "l1_weight", "ssim_weight", "census_weight", "smooth_weight", "smooth_order",
                         "edge_weight", "occlusion", "alpha1", "alpha2", "data_range", "reduction")


class FreespaceFlowLoss(nn.Module):
    """``nn.Module`` twin of :func:`freespace_flow_loss`.

    Args:
        odometry: ``"given"`` (pass the odometry to ``forward``) or ``"fit"`` (fit the road
            model, ``fit_options["model"]`` or the paper's, to the detached prediction at every
            call).
        penalty, scale, gamma, fit_options, reduction: as in :func:`freespace_flow_loss`.

    ``forward(flows, road, camera, odometry=None)`` -> scalar (or (B,)). With ``odometry="fit"``
    an odometry passed to ``forward`` is not used: the target is the fit, so one batch dict that
    holds an odometry feeds either mode (as ``python -m eval train --odometry fit`` does).

    Example:
        >>> term = FreespaceFlowLoss(penalty="charbonnier", scale=1.0)
        >>> value = term(flows, batch["road"], batch["camera"], batch["odometry"])  # doctest: +SKIP
    """

    def __init__(self, *, odometry: str = "given", penalty: str = "charbonnier", scale: float = 1.0,
                 gamma: float = 0.8, fit_options: Mapping[str, object] | None = None,
                 reduction: str = "mean") -> None:
        super().__init__()
        if odometry not in ("given", "fit"):
            raise ValueError(f"odometry: expected 'given' or 'fit', got {odometry!r}")
        if penalty not in _PENALTIES:
            raise ValueError(f"penalty: expected one of {_PENALTIES}, got {penalty!r}")
        scale = _check_scale(scale)
        _check_reduction(reduction)
        gamma = _check_gamma(gamma)
        check_fit_options(fit_options)
        self.mode = odometry
        self.options = dict(penalty=penalty, scale=scale, gamma=gamma,
                            fit_options=dict(fit_options or {}), reduction=reduction)

    def forward(self, flows: Tensor | Sequence[Tensor], road: Tensor, camera: Camera,
                odometry: Mapping[str, object] | None = None) -> Tensor:
        """The loss of ``flows`` ((B, 2, H, W) px, or a list) against the road model in ``road`` (B, 1, H, W) bool."""
        if self.mode == "fit":
            odometry = "fit"
        elif odometry is None:
            raise ValueError("odometry: this FreespaceFlowLoss was built with odometry='given'; pass a dict "
                             "with x_d, z_d, yaw, or build it with odometry='fit'")
        return freespace_flow_loss(flows, road, camera, odometry, **self.options)

    def extra_repr(self) -> str:
        return f"odometry={self.mode!r}, " + ", ".join(f"{k}={v!r}" for k, v in self.options.items())
