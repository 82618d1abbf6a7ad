"""Refining a learned flow with the freespace model inside the road mask (DESIGN.md §1, §9).

A flow network (RAFT, ARFlow/PWC-Lite, ptlflow models, a classical method) predicts forward
flow for an image pair. Inside the road (freespace) mask the road moves by the plane-induced
flow of the paper (eq. 13), computed from the camera and the ego-motion; the refiner replaces
the prediction there by that model flow (``mode="replace"``, the paper), or blends the two
with a per-pixel weight from their disagreement under a Cauchy kernel
(``mode="confidence"``), so that an obstacle wrongly inside the mask keeps its predicted flow.
Ego-motion comes from the caller's odometry, or is fitted to the prediction (or to the images)
inside the mask.

Convention: flow (B, 2, H, W) in pixels of its own resolution, channel 0 = u, forward from
frame t to t+1; masks (B, 1, H, W) bool at the finest flow's resolution; the camera's K refers
to the finest flow's resolution (coarser levels use ``camera.scaled``).

Output structures (whatever the network returns: a tensor, RAFT's list, a ``(low, up)`` pair, a
pyramid, ARFlow's or ptlflow's dict with 5-D stacks) are refined level by level at their own
resolution and come back in the same containers; :mod:`fsof_torch.refinement.contracts` defines
them, with ptlflow's and torchvision's input conventions and RAFT-style padding.
"""

from __future__ import annotations

import math
import warnings
from typing import Any, Mapping, NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .._check import as_batch_param, check_float_tensor, skip_values, tracing
from ..geometry.camera import Camera
from ..geometry.road_flow import road_flow
from ..geometry.road_models import road_motion
from .contracts import (
    DEFAULT_FLOW_KEYS,
    InputPadder,
    collect_flows,
    finest_flow,
    images_from_ptlflow,
    is_ptlflow_inputs,
    map_flows,
)

__all__ = [
    "DEFAULT_FLOW_KEYS",
    "RefineOutput",
    "FreespaceRefiner",
    "FreespaceRefined",
    "cauchy_weight",
    "fuse_flow",
    "refine_flow",
    "resize_mask",
]

_MODES = ("replace", "confidence")
_FITS = ("flow", "photometric")


class RefineOutput(NamedTuple):
    """What :class:`FreespaceRefiner` returns (a NamedTuple: ``out.flow`` or ``flow, *_ = out``).

    Attributes:
        flow: the refined flow(s), in the structure that came in (tensor, list, tuple, dict).
        odometry: the road motion used, a dict of its model's parameters, (B,) tensors: the
            caller's, or the fitted ``x_d, z_d`` (metres), ``yaw`` (radians) of the paper's model
            (0 for samples that were not refined).
        fit: the :class:`fsof_torch.fit.FitResult` when ego-motion was fitted, else None. With
            some masks empty it covers only the other samples (``refined`` says which).
        weight: (B, 1, H, W) the model's weight at the finest resolution: 1 where the model
            replaced the prediction, 0 where the prediction was kept (always 0 outside the mask).
        mask: (B, 1, H, W) bool, where the model was applied at the finest resolution (road mask
            ∩ model defined, for refined samples).
        refined: (B,) bool, False for samples left unchanged (an empty mask, a failed fit).
        camera: the camera the model flow was computed with (with fitted roll/pitch if fitted).
        flow_model: (B, 2, H, W) the model flow at the finest resolution (0 where undefined).
    """

    flow: Any
    odometry: dict
    fit: Any
    weight: Tensor
    mask: Tensor
    refined: Tensor
    camera: Camera
    flow_model: Tensor


# -- plain functions --------------------------------------------------------------------------

def cauchy_weight(residual_sq: Tensor, scale: float) -> Tensor:
    """Cauchy (Lorentzian) weight ``w = 1 / (1 + r² / c²)`` of squared residuals ``r²`` (px²).

    This is ρ'(r) / r for ρ(r) = c²/2 · log(1 + r²/c²): 1 at agreement, 1/2 at r = c, → 0 for
    large disagreement. Written on r² so the gradient is finite at r = 0.
    """
    return 1.0 / (1.0 + residual_sq / (scale * scale))


def fuse_flow(flow_pred: Tensor, flow_model: Tensor, mask: Tensor, *, mode: str = "replace",
              scale: float = 2.0) -> tuple[Tensor, Tensor]:
    """Fuse a predicted flow with the model flow inside ``mask``; outside it the prediction is
    returned bit for bit.

    Args:
        flow_pred: (B, 2, H, W) predicted flow, pixels.
        flow_model: (B, 2, H, W) model flow, pixels (same size; its dtype is cast to flow_pred's).
        mask: (B, 1, H, W) bool, where the model applies (road ∩ model defined).
        mode: ``"replace"`` (the paper: inside the mask the flow is the model flow) or
            ``"confidence"`` (``w · model + (1 − w) · pred`` with the Cauchy weight
            ``w = 1 / (1 + |pred − model|² / scale²)``).
        scale: the Cauchy scale c in pixels (``confidence`` only): where prediction and model
            disagree by c the two get equal weight.

    Returns:
        ``(flow, weight)``: the fused flow (B, 2, H, W) in flow_pred's dtype and the model's
        weight (B, 1, H, W) (0 outside the mask). Non-finite predicted pixels inside the mask
        get the model flow (weight 1); outside the mask they stay as they are.

    Raises:
        TypeError: a mask that is not bool (threshold a probability or 0/1 map first), or flows
            that are not float tensors.
        ValueError: shapes that differ (batch 1 of ``flow_model`` or ``mask`` is broadcast), a
            scale that is not a finite number > 0, or a non-finite model flow inside the mask
            (the model flow is the reference there: it must be finite).
    """
    if mode not in _MODES:
        raise ValueError(f"mode: expected one of {_MODES}, got {mode!r}")
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not (0 < scale < math.inf):
        raise (ValueError if isinstance(scale, (int, float)) else TypeError)(
            f"scale: expected a finite Cauchy scale > 0 pixels, got {scale!r}")
    check_float_tensor(flow_pred, "flow_pred")
    check_float_tensor(flow_model, "flow_model")
    if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
        got = f"dtype {mask.dtype}" if isinstance(mask, Tensor) else type(mask).__name__
        raise TypeError(f"mask: expected a bool tensor (B, 1, H, W), got {got}")
    if flow_pred.dim() != 4 or flow_pred.shape[1] != 2 or min(flow_pred.shape[-2:]) < 1:
        raise ValueError(f"flow_pred: expected shape (B, 2, H, W), got {tuple(flow_pred.shape)}")
    B, _, H, W = flow_pred.shape
    for name, t, c in (("flow_model", flow_model, 2), ("mask", mask, 1)):
        if t.dim() != 4 or t.shape[0] not in (1, B) or tuple(t.shape[1:]) != (c, H, W):
            raise ValueError(f"{name}: expected shape ({B}, {c}, {H}, {W}) (flow_pred's size; batch 1 "
                             f"is broadcast), got {tuple(t.shape)}")
        if t.device != flow_pred.device:
            raise ValueError(f"{name}: expected the device of flow_pred ({flow_pred.device}), got {t.device}")
    if not skip_values(flow_model, mask):
        bad = (~torch.isfinite(flow_model).all(dim=1, keepdim=True) & mask).sum()
        if int(bad):
            raise ValueError(f"flow_model: expected finite values inside the mask, got {int(bad)} "
                             f"non-finite pixel(s) (NaN or inf) there")
    return _fuse(flow_pred, flow_model, mask, mode, float(scale), all_finite=False)


def _fuse(flow_pred: Tensor, flow_model: Tensor, mask: Tensor, mode: str, scale: float, *,
          all_finite: bool) -> tuple[Tensor, Tensor]:
    """:func:`fuse_flow`; ``all_finite``: the caller knows flow_pred is finite everywhere."""
    flow_model = flow_model.to(flow_pred.dtype)
    if mode == "replace":
        weight = mask.to(flow_pred.dtype)
        return torch.where(mask, flow_model, flow_pred), weight
    if all_finite:
        diff = flow_pred - flow_model
        w = cauchy_weight((diff * diff).sum(dim=1, keepdim=True), scale)
    else:
        finite = torch.isfinite(flow_pred).all(dim=1, keepdim=True)
        # Keep NaN out of the arithmetic (and of its gradient): the unused branch sees 0.
        safe_pred = torch.where(finite, flow_pred, flow_model)
        diff = safe_pred - flow_model
        w = cauchy_weight((diff * diff).sum(dim=1, keepdim=True), scale)
        w = torch.where(finite, w, torch.ones_like(w))
    blended = flow_model + (1 - w) * diff  # = w · model + (1 − w) · pred
    weight = torch.where(mask, w, torch.zeros_like(w))
    return torch.where(mask, blended, flow_pred), weight


def resize_mask(mask: Tensor, size: tuple[int, int]) -> Tensor:
    """A bool mask (B, 1, H, W) resampled to ``size = (h, w)``.

    Shrinking keeps a coarse pixel only when its whole footprint is in the mask (area averaging,
    then ``== 1``): a coarse road pixel never straddles a car's edge. Growing uses exact nearest
    neighbour.
    """
    H, W = mask.shape[-2:]
    h, w = size
    if (h, w) == (H, W):
        return mask
    m = mask.to(torch.float32)
    if h <= H and w <= W:
        return F.interpolate(m, size=(h, w), mode="area") > 1.0 - 1e-6
    return F.interpolate(m, size=(h, w), mode="nearest-exact") > 0.5


# -- odometry ---------------------------------------------------------------------------------

def _odometry_tensors(odometry: object, B: int, dtype: torch.dtype,
                      device: torch.device) -> tuple[str, dict[str, Tensor]]:
    """The caller's road motion (any form :func:`~fsof_torch.geometry.road_models.road_motion`
    takes) as its model's name and parameters, tensors of shape (B,) (batch 1 broadcast)."""
    model, values = road_motion(odometry)
    out = {}
    for k, v in values.items():
        t = as_batch_param(v, f"odometry[{k!r}]")
        if t.shape[0] not in (1, B):
            raise ValueError(f"odometry[{k!r}]: expected a float or a tensor of shape ({B},) "
                             f"(the flow's batch) or (1,), got shape {tuple(t.shape)}")
        out[k] = t.to(device=device, dtype=dtype).expand(B)
    return model.name, out


def _camera_subset(camera: Camera, index: Tensor) -> Camera:
    return Camera(camera.K[index], camera.height[index], camera.roll[index], camera.pitch[index])


def _scatter(values: Tensor, index: Tensor, B: int) -> Tensor:
    out = torch.zeros(B, *values.shape[1:], dtype=values.dtype, device=values.device)
    return out.index_copy(0, index, values)


# -- the refinement ---------------------------------------------------------------------------

def refine_flow(flow: Any, mask: Tensor, camera: Camera, odometry: object = None, *,
                mode: str = "replace", scale: float = 2.0, fit: str = "flow",
                images: tuple[Tensor, Tensor] | None = None, fit_roll: bool = False,
                fit_pitch: bool = False, fit_options: Mapping[str, Any] | None = None,
                photometric_options: Mapping[str, Any] | None = None, min_pixels: int = 100,
                flow_keys: tuple[str, ...] = DEFAULT_FLOW_KEYS, warn: bool = True) -> RefineOutput:
    """Refine predicted flow(s) with the freespace model inside the road mask.

    Args:
        flow: the prediction: (B, 2, H, W), a list/tuple of flows (RAFT iterations, a
            ``(low, up)`` pair, a pyramid), or a dict (ARFlow, ptlflow; see ``flow_keys``).
            Every flow is refined at its own resolution.
        mask: (B, 1, H, W) or (1, 1, H, W) bool road mask at the finest flow's size.
        camera: :class:`Camera` (batch 1 or B), K at the finest flow's resolution.
        odometry: ego-motion from t to t+1: a dict ``x_d, z_d, yaw`` (floats or (B,) tensors;
            metres, radians), any road model's motion (a dict with a ``"model"`` key and its
            parameters, or a fit result: :func:`~fsof_torch.geometry.road_models.road_motion`),
            an :class:`EgoMotion`, or None to fit it (detached) to the finest
            flow inside the mask (``fit="flow"``, :func:`fsof_torch.fit.fit_displacement`), or
            to the images (``fit="photometric"``: :func:`fsof_torch.fit.fit_photometric` started
            from the flow fit; needs ``images``).
        mode: ``"replace"`` or ``"confidence"`` (see :func:`fuse_flow`); ``scale`` the Cauchy
            scale in pixels of the finest level (coarser levels scale it with their size).
        images: ``(image1, image2)`` (B, 3, H, W) RGB 0..255 at the finest size, or ptlflow's input
            dict ``{"images": (B, 2, 3, H, W)}`` (BGR in [0, 1]), for ``fit="photometric"``.
        fit_roll, fit_pitch: also fit the camera's roll / pitch (else the camera's are kept).
        fit_options: further keyword arguments for ``fit_displacement``.
        photometric_options: further keyword arguments for ``fit_photometric``.
        min_pixels: without odometry, samples with fewer usable mask pixels are not fitted and
            are left unchanged (``refined`` False); with odometry only an empty mask is.
        flow_keys: the dict keys whose values are forward flows to refine.
        warn: warn when samples are left unchanged or non-finite predictions are masked.

    Returns:
        :class:`RefineOutput`. Pixels outside the (resampled) mask, and samples left unchanged,
        are bit for bit the prediction; the caller's tensors are never modified. The result is
        differentiable with respect to the prediction and, when given, to the camera and the
        odometry (the fit itself is detached).

    Non-finite predicted values: they are left out of the fit; inside the mask the model
    replaces them (both modes); outside the mask they are returned as they came.
    """
    if mode not in _MODES:
        raise ValueError(f"mode: expected one of {_MODES}, got {mode!r}")
    if fit not in _FITS:
        raise ValueError(f"fit: expected one of {_FITS}, got {fit!r}")
    if not (scale > 0 and math.isfinite(scale)):
        raise ValueError(f"scale: expected a finite Cauchy scale > 0 pixels, got {scale!r}")
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a fsof_torch.Camera, got {type(camera).__name__}")
    flow_keys = tuple(flow_keys)
    if is_ptlflow_inputs(images):
        images = images_from_ptlflow(images)
    flows = collect_flows(flow, "flow", flow_keys)
    if not flows:
        raise ValueError(f"flow: no flow found in the {type(flow).__name__}; expected a value under "
                         f"one of the keys {flow_keys} (set flow_keys)")
    _, finest = finest_flow(flows)
    B, _, H, W = finest.shape
    for name, f in flows:
        if f.shape[0] != B:
            raise ValueError(f"{name}: expected batch {B} (as the finest flow), got shape {tuple(f.shape)}")
    if not isinstance(mask, Tensor):
        raise TypeError(f"mask: expected a bool tensor (B, 1, H, W), got {type(mask).__name__}")
    if mask.dtype != torch.bool:
        raise TypeError(f"mask: expected a bool tensor (threshold a probability map first), got dtype {mask.dtype}")
    if mask.dim() != 4 or mask.shape[1] != 1 or mask.shape[0] not in (1, B) or tuple(mask.shape[-2:]) != (H, W):
        raise ValueError(f"mask: expected shape ({B}, 1, {H}, {W}) (the finest flow's size), got {tuple(mask.shape)}")
    if camera.batch_size not in (1, B):
        raise ValueError(f"camera: expected batch 1 or {B} (the flow's batch), got {camera.batch_size}")
    device = finest.device
    mask = mask.to(device).expand(B, 1, H, W)
    # The model flow is computed in the prediction's dtype (half lifted to float32): float32
    # evaluates the road homography to about 1e-3 px, far below any network's error, at half
    # the cost of float64; a float64 prediction gets float64 geometry.
    geo_dtype = torch.float32 if finest.dtype in (torch.float16, torch.bfloat16) else finest.dtype
    camera = camera.to(device=device, dtype=geo_dtype).expand(B)

    # One reduction settles the common case (a NaN or inf anywhere makes the sum non-finite;
    # so may an overflow, which then takes the per-pixel path): no full-size test and no copy.
    all_finite = not tracing() and bool(torch.isfinite(finest.detach().sum()))
    if all_finite:
        fit_mask = mask
    else:
        finite = torch.isfinite(finest).all(dim=1, keepdim=True)
        fit_mask = mask & finite
        if warn and not tracing():
            n_bad = int((mask & ~finite).sum())
            if n_bad:
                warnings.warn(f"flow: {n_bad} non-finite predicted pixels inside the mask; they are left "
                              f"out of the fit and replaced by the model flow", RuntimeWarning, stacklevel=3)
    # (a uint8 sum into int32: the sum converts its input first, and a bool sum or
    # count_nonzero converts to int64, a copy twice the size)
    counts = fit_mask.view(torch.uint8).flatten(1).sum(1, dtype=torch.int32)
    # min_pixels guards the fit; with odometry given any mask pixel can be refined.
    refined = counts >= (min_pixels if odometry is None else 1)

    fit_result = None
    motion_model = "paper"
    if odometry is not None:
        motion_model, odo = _odometry_tensors(odometry, B, geo_dtype, device)
        cam_model = camera
    else:
        odo, cam_model, fit_result, refined = _fit(
            finest, fit_mask, camera, refined, fit=fit, images=images, fit_roll=fit_roll,
            fit_pitch=fit_pitch, fit_options=fit_options or {},
            photometric_options=photometric_options or {}, all_finite=all_finite)

    if warn and not tracing() and not bool(refined.all()):
        bad = (~refined).nonzero().flatten().tolist()
        why = ("an empty mask" if odometry is not None
               else f"fewer than {min_pixels} usable mask pixels or a failed fit")
        warnings.warn(f"mask: samples {bad} left unchanged ({why}); see RefineOutput.refined",
                      RuntimeWarning, stacklevel=3)

    # (a broadcast & over the whole mask is slow on CPU: only when some sample is left out)
    all_refined = not tracing() and bool(refined.all())
    sample_ok = refined.reshape(B, 1, 1, 1)

    def usable(m: Tensor) -> Tensor:
        return m if all_refined else m & sample_ok
    cache: dict[tuple[int, int], tuple[Tensor, Tensor]] = {}
    if fit_result is not None and fit_result.flow.shape[0] == B and not _needs_grad(cam_model):
        # The fit evaluated this very model flow at the finest size (same parameters, same
        # dtype): reuse it instead of a second full-size evaluation. Not when the camera carries
        # a graph: then the model flow must be differentiable with respect to it.
        valid = fit_result.valid.to(device)
        cache[(H, W)] = (fit_result.flow.to(device=device, dtype=geo_dtype), usable(mask & valid))

    def level(size: tuple[int, int]) -> tuple[Tensor, Tensor]:
        """Model flow and fusion mask at a level's size (computed once per size)."""
        if size not in cache:
            h, w = size
            cam = cam_model if (h, w) == (H, W) else cam_model.scaled(w / W, h / H)
            f_model, valid = road_flow(cam, odo, (h, w), model=motion_model)
            m = usable(resize_mask(mask, (h, w)) & valid)
            cache[size] = (f_model, m)
        return cache[size]

    weights: dict[tuple[int, int], Tensor] = {}

    def refine_one(f: Tensor) -> Tensor:
        size = (f.shape[-2], f.shape[-1])
        f_model, m = level(size)
        # The Cauchy scale is in pixels of the level: a coarse level's flow is proportionally smaller.
        c = scale * math.sqrt(size[0] * size[1] / (H * W))
        # (the finiteness test above covered the finest prediction itself, not the other levels)
        out, w = _fuse(f, f_model, m, mode, c, all_finite=all_finite and f is finest)
        if size == (H, W):
            weights[size] = w
        return out

    refined_flow = map_flows(flow, refine_one, flow_keys)
    f_model, m = level((H, W))
    weight = weights.get((H, W))
    if weight is None:  # pragma: no cover - the finest level is always visited
        weight = m.to(finest.dtype)
    return RefineOutput(refined_flow, odo, fit_result, weight, m, refined, cam_model, f_model)


def _needs_grad(camera: Camera) -> bool:
    return torch.is_grad_enabled() and any(
        t.requires_grad for t in (camera.K, camera.height, camera.roll, camera.pitch))


def _fit(finest: Tensor, fit_mask: Tensor, camera: Camera, refined: Tensor, *, fit: str,
         images: tuple[Tensor, Tensor] | None, fit_roll: bool, fit_pitch: bool,
         fit_options: Mapping[str, Any], photometric_options: Mapping[str, Any],
         all_finite: bool = False):
    """Fit ego-motion (detached) to the samples with enough mask pixels; scatter back to B.
    ``all_finite``: the prediction is known to be finite everywhere (no masking needed)."""
    B = finest.shape[0]
    dtype, device = camera.dtype, camera.device
    zeros = torch.zeros(B, dtype=dtype, device=device)
    if fit == "photometric":
        if images is None:
            raise ValueError("images: fit='photometric' needs images=(image1, image2), got None")
        if not isinstance(images, (tuple, list)) or len(images) != 2:
            raise TypeError(f"images: expected a pair (image1, image2), got {type(images).__name__}")
        for i, im in enumerate(images):
            check_float_tensor(im, f"images[{i}]")
            if im.dim() != 4 or im.shape[0] != B or tuple(im.shape[-2:]) != tuple(finest.shape[-2:]):
                raise ValueError(f"images[{i}]: expected shape ({B}, C, {finest.shape[-2]}, "
                                 f"{finest.shape[-1]}), got {tuple(im.shape)}")
    if not bool(refined.any()):
        return {"x_d": zeros, "z_d": zeros.clone(), "yaw": zeros.clone()}, camera, None, refined
    from ..estimation.flow_fit import fit_displacement  # the fitting layer (imported when needed)

    index = refined.nonzero().flatten()
    subset = index.numel() < B
    with torch.no_grad():
        f = finest.detach()
        if not all_finite:
            f = torch.where(fit_mask, f, torch.zeros_like(f))  # no NaN reaches the fit
        f = f.to(dtype)
        m = fit_mask
        cam = camera.to(dtype)
        cam_d = Camera._checked(cam.K.detach(), cam.height.detach(), cam.roll.detach(), cam.pitch.detach())
        if subset:
            f, m, cam_d = f[index], m[index], _camera_subset(cam_d, index)
        result = fit_displacement(f, m, cam_d, fit_roll=fit_roll, fit_pitch=fit_pitch, **fit_options)
        if fit == "photometric":
            from ..estimation.image_fit import fit_photometric

            im1, im2 = (im.detach() for im in images)
            if subset:
                im1, im2 = im1[index], im2[index]
            result = fit_photometric(im1, im2, m, cam_d, init=result, fit_roll=fit_roll,
                                     fit_pitch=fit_pitch, **photometric_options)
    ok = result.success.to(device=device, dtype=torch.bool)
    odo = {k: _scatter(getattr(result, k).detach().to(dtype), index, B) for k in ("x_d", "z_d", "yaw")}
    refined = refined.clone()
    refined[index] = refined[index] & ok
    cam_model = camera
    if fit_roll or fit_pitch:
        # The fitted mounting, attached to the caller's camera so K and height keep their graph.
        roll = camera.roll.index_copy(0, index, result.roll.detach().to(dtype)) if fit_roll else camera.roll
        pitch = camera.pitch.index_copy(0, index, result.pitch.detach().to(dtype)) if fit_pitch else camera.pitch
        cam_model = camera.replace(roll=roll, pitch=pitch)
    return odo, cam_model, result, refined


class FreespaceRefiner(nn.Module):
    """``nn.Module`` twin of :func:`refine_flow`: post-processes a flow network's output.

    Args (keyword-only):
        mode: ``"replace"`` (the paper: inside the road mask the flow becomes the model flow) or
            ``"confidence"`` (Cauchy-weighted blend; an obstacle in the mask keeps its flow).
        scale: Cauchy scale in pixels (finest level) for ``confidence``.
        fit: ``"flow"`` or ``"photometric"``: how ego-motion is estimated when no odometry is given.
        fit_roll, fit_pitch: fit the camera's roll / pitch as well (default: keep the camera's).
        fit_options: extra keyword arguments for ``fit_displacement``.
        photometric_options: extra keyword arguments for ``fit_photometric``.
        min_pixels: without odometry, fewer usable mask pixels leave the sample unchanged.
        flow_keys: dict keys of forward flows to refine (default :data:`DEFAULT_FLOW_KEYS`).

    Forward: ``refiner(flow, mask, camera, odometry=None, *, images=None) -> RefineOutput``.

    Example:
        >>> refiner = FreespaceRefiner(mode="replace")
        >>> flows = raft(image1, image2)                       # list of (B, 2, H, W)
        >>> out = refiner(flows, road, camera, {"x_d": 0.0, "z_d": 1.2, "yaw": 0.0})
        >>> flow = out.flow[-1]                                # same structure as ``flows``
    """

    def __init__(self, *, mode: str = "replace", scale: float = 2.0, fit: str = "flow",
                 fit_roll: bool = False, fit_pitch: bool = False,
                 fit_options: Mapping[str, Any] | None = None,
                 photometric_options: Mapping[str, Any] | None = None, min_pixels: int = 100,
                 flow_keys: tuple[str, ...] = DEFAULT_FLOW_KEYS, warn: bool = True) -> None:
        super().__init__()
        if mode not in _MODES:
            raise ValueError(f"mode: expected one of {_MODES}, got {mode!r}")
        if fit not in _FITS:
            raise ValueError(f"fit: expected one of {_FITS}, got {fit!r}")
        if not (float(scale) > 0 and math.isfinite(float(scale))):
            raise ValueError(f"scale: expected a finite Cauchy scale > 0 pixels, got {scale!r}")
        if int(min_pixels) < 1:
            raise ValueError(f"min_pixels: expected >= 1, got {min_pixels!r}")
        self.mode = mode
        self.scale = float(scale)
        self.fit = fit
        self.fit_roll = bool(fit_roll)
        self.fit_pitch = bool(fit_pitch)
        self.fit_options = dict(fit_options or {})
        self.photometric_options = dict(photometric_options or {})
        self.min_pixels = int(min_pixels)
        self.flow_keys = tuple(flow_keys)
        self.warn = bool(warn)

    def forward(self, flow: Any, mask: Tensor, camera: Camera, odometry: object = None, *,
                images: tuple[Tensor, Tensor] | None = None) -> RefineOutput:
        return refine_flow(flow, mask, camera, odometry, mode=self.mode, scale=self.scale,
                           fit=self.fit, images=images, fit_roll=self.fit_roll,
                           fit_pitch=self.fit_pitch, fit_options=self.fit_options,
                           photometric_options=self.photometric_options,
                           min_pixels=self.min_pixels, flow_keys=self.flow_keys, warn=self.warn)

    def extra_repr(self) -> str:
        extra = f", scale={self.scale}" if self.mode == "confidence" else ""
        return f"mode={self.mode!r}{extra}, fit={self.fit!r}, fit_roll={self.fit_roll}, fit_pitch={self.fit_pitch}"


class FreespaceRefined(nn.Module):
    """A flow network with freespace refinement attached: a drop-in replacement for ``net``.

    Args:
        net: a flow network, called as it expects to be called (see
            :mod:`fsof_torch.refinement.contracts`): ``net(image1, image2, **kw)`` (RAFT,
            torchvision's RAFT, TinyRAFT, ARFlow) or ``net(inputs, **kw)`` with ptlflow's input
            dict. It may return any structure :func:`refine_flow` accepts.
        refiner: a :class:`FreespaceRefiner` (default: ``FreespaceRefiner()``).
        road: None (the caller passes ``mask``) or ``"auto"``: when no mask is given, detect the
            freespace on the prediction with :func:`fsof_torch.detect_freespace`.
        road_options: keyword arguments for ``detect_freespace``.
        pad: an :class:`~fsof_torch.refinement.contracts.InputPadder` for networks that need
            sizes divisible by a stride (torchvision's RAFT: ``InputPadder(8)``; ptlflow's RAFT,
            so that its ``flow_small`` is refined on its true grid). The images are padded before
            the net, the mask (with False) and the camera (:meth:`Camera.padded`) the same way;
            the output is refined on the padded grid, so a coarse level such as ``flow_small``
            (1/8 of the padded size) gets the padded camera scaled to it; then every output tensor
            of the padded full size is cropped back to the input size. Coarser levels stay on
            their padded grid, as the network returned them.
        image_range: ``(low, high)`` of the images passed as two tensors (the net's convention:
            (0, 255) for RAFT and TinyRAFT, (-1, 1) for torchvision's weights' transforms); the
            refiner's photometric fit reads them as 0..255. ptlflow dicts are BGR in [0, 1].

    Forward: ``model(image1, image2, *, camera, mask=None, odometry=None, return_info=False, **kw)``
    or ``model(inputs, *, camera, ...)`` with a ptlflow dict. Returns the net's output with its
    forward flows refined (same structure), or ``(output, RefineOutput)`` with
    ``return_info=True``. The mask (B, 1, H, W) bool and the camera refer to the input images'
    size. With ``pad`` the RefineOutput's maps are cropped to the input size and its camera
    is the input's (the padding undone).
    """

    def __init__(self, net: nn.Module, refiner: FreespaceRefiner | None = None, *,
                 road: str | None = None, road_options: Mapping[str, Any] | None = None,
                 pad: InputPadder | None = None, image_range: tuple[float, float] = (0.0, 255.0)) -> None:
        super().__init__()
        if not callable(net):
            raise TypeError(f"net: expected a callable flow network, got {type(net).__name__}")
        if refiner is not None and not isinstance(refiner, FreespaceRefiner):
            raise TypeError(f"refiner: expected a FreespaceRefiner, got {type(refiner).__name__}")
        if road not in (None, "auto"):
            raise ValueError(f"road: expected None or 'auto', got {road!r}")
        if pad is not None and not isinstance(pad, InputPadder):
            raise TypeError(f"pad: expected an InputPadder or None, got {type(pad).__name__}")
        lo, hi = (float(v) for v in image_range)
        if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
            raise ValueError(f"image_range: expected finite (low, high) with high > low, got {image_range!r}")
        self.net = net
        self.refiner = refiner if refiner is not None else FreespaceRefiner()
        self.road = road
        self.road_options = dict(road_options or {})
        self.pad = pad
        self.image_range = (lo, hi)

    def forward(self, *inputs: Any, camera: Camera, mask: Tensor | None = None, odometry: object = None,
                return_info: bool = False, **kw: Any):
        if len(inputs) == 1 and is_ptlflow_inputs(inputs[0]):
            net_inputs = dict(inputs[0])
            image1, image2 = images_from_ptlflow(net_inputs)  # (validates the dict)
            size = tuple(image1.shape[-2:])
            padding = self.pad.padding(size) if self.pad is not None else None
            if padding is not None:
                net_inputs["images"] = padding.pad(net_inputs["images"], mode=self.pad.pad_mode)
            output = self.net(net_inputs, **kw)
        elif len(inputs) == 2:
            image1, image2 = inputs
            for name, im in (("image1", image1), ("image2", image2)):
                check_float_tensor(im, name)
                if im.dim() != 4:
                    raise ValueError(f"{name}: expected shape (B, C, H, W), got {tuple(im.shape)}")
            size = tuple(image1.shape[-2:])
            padding = self.pad.padding(size) if self.pad is not None else None
            if padding is not None:
                output = self.net(padding.pad(image1, mode=self.pad.pad_mode),
                                  padding.pad(image2, mode=self.pad.pad_mode), **kw)
            else:
                output = self.net(image1, image2, **kw)
            lo, hi = self.image_range
            if (lo, hi) != (0.0, 255.0):
                image1, image2 = ((im - lo) * (255.0 / (hi - lo)) for im in (image1, image2))
        else:
            raise TypeError(f"inputs: expected (image1, image2) or one ptlflow dict {{'images': ...}}, "
                            f"got {len(inputs)} positional argument(s)")
        if padding is not None and padding.is_zero:
            padding = None
        if padding is not None:
            camera = padding.camera(camera)
            image1, image2 = (padding.pad(im, mode=self.pad.pad_mode) for im in (image1, image2))
            if mask is not None:
                if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
                    raise TypeError(f"mask: expected a bool tensor (B, 1, H, W), got {getattr(mask, 'dtype', type(mask).__name__)}")
                if tuple(mask.shape[-2:]) != size:
                    raise ValueError(f"mask: expected the images' size {size}, got shape {tuple(mask.shape)}")
                mask = padding.pad(mask)
        if mask is None:
            if self.road != "auto":
                raise ValueError("mask: expected a road mask (B, 1, H, W) bool, got None "
                                 "(pass mask=..., or build FreespaceRefined(..., road='auto'))")
            _, finest = finest_flow(collect_flows(output, "output", self.refiner.flow_keys))
            from ..estimation.freespace import detect_freespace  # freespace detection (imported when needed)

            with torch.no_grad():
                cam = camera.to(device=finest.device)
                mask = detect_freespace(finest.detach(), cam, **self.road_options)
            if padding is not None:  # the replicated border is not road
                mask = padding.pad(padding.unpad(mask))
        images = (image1, image2) if self.refiner.fit == "photometric" else None
        info = self.refiner(output, mask, camera, odometry, images=images)
        if padding is None:
            return (info.flow, info) if return_info else info.flow
        padded_size = padding.padded_size(size)
        flow = padding.unpad_output(info.flow, padded_size)
        if not return_info:
            return flow
        info = info._replace(flow=flow, weight=padding.unpad(info.weight), mask=padding.unpad(info.mask),
                             flow_model=padding.unpad(info.flow_model),
                             camera=info.camera.cropped(padding.left, padding.top, padding.right, padding.bottom))
        return flow, info
