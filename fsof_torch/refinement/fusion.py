"""Refining a learned flow with the freespace model inside the road mask (DESIGN.md §1, §9).

A flow network (RAFT, ARFlow/PWC-Lite, ptlflow models, a classical method) predicts forward
flow for an image pair. Inside the road (freespace) mask the road moves by the plane-induced
flow of the paper (eq. 13), computed from the camera and the ego-motion; the refiner replaces
the prediction there by that model flow (``mode="replace"``, the paper), or blends the two
with a per-pixel weight from their disagreement under a Cauchy kernel and the images' evidence
(``mode="confidence"``), so that an obstacle wrongly inside the mask keeps its predicted flow.

The road's motion comes from a component (:mod:`fsof_torch.refinement.estimators`): by default,
with the images given, a direct fit of the 6-DOF road motion to the images (the network's flow
one start among several; the caller's planar odometry, when given, held fixed); without images,
a fit to the prediction. A gate (:mod:`fsof_torch.refinement.gate`) then keeps the prediction in
every region of the mask where the model explains the images worse.

Convention: flow (B, 2, H, W) in pixels of its own resolution, channel 0 = u, forward from
frame t to t+1; masks (B, 1, H, W) bool at the finest flow's resolution; the camera's K refers
to the finest flow's resolution (coarser levels use ``camera.scaled``).

Output structures (whatever the network returns: a tensor, RAFT's list, a ``(low, up)`` pair, a
pyramid, ARFlow's or ptlflow's dict with 5-D stacks) are refined level by level at their own
resolution and come back in the same containers; :mod:`fsof_torch.refinement.contracts` defines
them, with ptlflow's and torchvision's input conventions and RAFT-style padding.
"""

from __future__ import annotations

import itertools
import math
from typing import Any, Mapping, NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .._check import (batch_choices, check_float_tensor, check_has_values, check_mapping, check_mask, check_shape,
                      check_size, held_by, is_number, known_finite, scalar, known_images, option_error, result_dtype,
                      skip_values, summary_repr, to_device, tracing)
from ..estimation.combine import select_samples, where_motion
from ..estimation.flow_fit import RoadFit
from ..estimation.robust import check_fixed, check_scale
from ..estimation.sampling import reused_mask_pixels
from ..evaluation.photometric import to_grey
from ..geometry.camera import Camera
from ..geometry.road_flow import road_flow
from ..geometry.road_models import get_road_model, is_planar_odometry, pack_params, road_motion, road_motion_batch
from .auto_refine import UNCHANGED_NAMED, refine_with_auto_road
from .estimators import ImageMotionEstimator, check_estimate, finite_estimate, given_success, unestimated_motion
from .gate import ImageGate
from .options import FITS, MODES, check_refine_options, select_estimator
from .contracts import DEFAULT_FLOW_KEYS, check_levels, collect_flows, finest_flow, map_flows, refiner_images
from ..warn import warn_user

__all__ = ["DEFAULT_FLOW_KEYS", "RefineOutput", "FreespaceRefiner", "cauchy_weight", "fuse_flow", "refine_flow",
           "resize_mask"]

_MODES, _FITS = MODES, FITS


class RefineOutput(NamedTuple):
    """What :class:`FreespaceRefiner` returns (a NamedTuple: ``out.flow`` or ``flow, *_ = out``).

    Attributes:
        flow: the refined flow(s), in the structure that came in (tensor, list, tuple, dict).
        odometry: the road motion used, a dict of its model's parameters (``model`` names the
            model), (B,) tensors: the caller's, or the estimated ones (0 for samples that were
            not refined): the ``"plane"`` model's eight with images, the paper's ``x_d, z_d``
            (metres), ``yaw`` (radians) fitted to the flow without them (with the camera's
            ``roll`` and ``pitch``, which that model also has).
        fit: the :class:`fsof_torch.fit.FitResult` when ego-motion was fitted, else None. It
            covers the samples that were estimated, in batch order: those with at least
            ``min_pixels`` usable mask pixels (with odometry, one mask pixel). ``refined`` does not
            say which: it is also False for an estimated sample whose estimate failed or whose
            model the gate refused.
        weight: (B, 1, H, W) the model's weight in the finest flow's fusion: 1 where the model
            replaced the prediction, 0 where the prediction was kept (always 0 outside the mask);
            with ``mode="confidence"`` the blend's weight in [0, 1].
        mask: (B, 1, H, W) bool, where the model was applied at the finest resolution (road mask
            ∩ model defined, in refined samples, where the gate uses the model or the prediction
            is not finite; for a float16 prediction, only where float16 holds the model flow).
        refined: (B,) bool, False for samples left unchanged (an empty mask, one where the model is
            undefined, a failed fit, a model the images give no evidence for, a gate that keeps the
            prediction everywhere: see ``gate``).
        camera: the camera the model flow was computed with (with fitted roll/pitch if fitted).
        flow_model: (B, 2, H, W) the model flow at the finest resolution (0 where undefined).
        model: the road model's name (``"paper"``, ``"plane"``, ...) of ``odometry``.
        gate: the :class:`~fsof_torch.refinement.gate.GateResult` where the images were judged, else None; a
            sample left unchanged before the gate (a failed estimate, too few pixels) is judged on none (``points`` 0).
        road: the :class:`~fsof_torch.refinement.auto_road.RoadDetection` of ``mask="auto"`` with images.
    """

    flow: Any
    odometry: dict
    fit: Any
    weight: Tensor
    mask: Tensor
    refined: Tensor
    camera: Camera
    flow_model: Tensor
    model: str = "paper"
    gate: Any = None
    road: Any = None
    __repr__ = summary_repr  # (one line, tensors as their shapes)


# -- plain functions --------------------------------------------------------------------------

def cauchy_weight(residual_sq: Tensor, scale: float) -> Tensor:
    """Cauchy (Lorentzian) weight ``w = 1 / (1 + r² / c²)`` of squared residuals ``r²`` (px²).

    This is ρ'(r) / r for ρ(r) = c²/2 · log(1 + r²/c²): 1 at agreement, 1/2 at r = c, → 0 for
    large disagreement. Written on r² so the gradient is finite at r = 0. Elementwise: a NaN
    residual gives a NaN weight, as ``torch`` functions do. ``scale`` is a finite number > 0 (px),
    or a tensor of them broadcast against the residuals (its values are not read while tracing).
    """
    check_float_tensor(residual_sq, "residual_sq")
    check_scale(scale)  # (a tensor scale is elementwise, like the residuals)
    return 1.0 / (1.0 + residual_sq / (scale * scale))


def fuse_flow(flow_pred: Tensor, flow_model: Tensor, mask: Tensor, *, mode: str = "replace",
              scale: float = 2.0) -> tuple[Tensor, Tensor]:
    """Fuse a predicted flow with the model flow inside ``mask``; outside it the prediction is
    returned bit for bit.

    Args:
        flow_pred: (B, 2, H, W) predicted flow, pixels.
        flow_model: (B, 2, H, W) model flow, pixels (same size; any float dtype).
        mask: (B, 1, H, W) bool, where the model applies (road ∩ model defined).
        mode: ``"replace"`` (the paper: inside the mask the flow is the model flow) or
            ``"confidence"`` (``w · model + (1 − w) · pred`` with the Cauchy weight
            ``w = 1 / (1 + |pred − model|² / scale²)``).
        scale: the Cauchy scale c in pixels (``confidence`` only): where prediction and model
            disagree by c the two get equal weight.

    Returns:
        ``(flow, weight)``: the fused flow (B, 2, H, W) in flow_pred's dtype and the model's weight
        (B, 1, H, W) (0 outside the mask). The fusion runs in flow_pred's dtype, half precision in float32 (the
        result rounded once: a bfloat16 prediction gets the float32 result rounded to bfloat16). Non-finite
        predicted pixels inside the mask get the model flow (weight 1); outside the mask they stay as they are,
        and so does a float16 prediction where float16 cannot hold the model flow (beyond 65 504 px; weight 0).

    Raises:
        TypeError: a mask that is not bool (threshold a probability or 0/1 map first), flows
            that are not float tensors, or a scale that requires grad (read as a number, its
            gradient would be lost).
        ValueError: shapes that differ (batch 1 of ``flow_model`` or ``mask`` is broadcast), a
            scale that is not a finite number > 0, or a non-finite model flow inside the mask
            (the model flow is the reference there: it must be finite).
    """
    if mode not in _MODES:
        raise ValueError(f"mode: expected one of {_MODES}, got {mode!r}")
    check_fixed(scale, "scale")  # (read as a number: a learnable scale's gradient would be lost)
    scale = scalar(scale, "scale")
    if not is_number(scale) or not (0 < float(scale) < math.inf):
        raise option_error(scale, f"scale: expected a finite Cauchy scale > 0 pixels, got {scale!r}")
    scale = float(scale)  # (a NumPy scalar too, as the refiner takes it)
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
          all_finite: bool, evidence: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """:func:`fuse_flow`; ``all_finite``: the caller knows flow_pred is finite everywhere;
    ``evidence`` (B, 1, H, W): the images' evidence for the model in [0, 1] (confidence mode):
    where the two flows disagree, it decides, w = w_flow + (1 − w_flow) · evidence."""
    dtype = flow_pred.dtype
    mask = held_by(mask, flow_model, dtype)  # (a model flow the prediction's dtype cannot hold is undefined for it)
    if mode == "replace":
        # (B, 1, H, W) also where the mask is one for the batch; converted from bytes: torch
        # converts bool to float several times slower
        weight = mask.view(torch.uint8).expand(flow_pred.shape[0], 1, -1, -1).to(dtype)
        return torch.where(mask, flow_model.to(dtype), flow_pred), weight
    # half precision blends in float32 and is rounded once: the float32 result, rounded
    work = result_dtype(flow_pred)
    pred, flow_model = flow_pred.to(work), flow_model.to(work)
    if all_finite:
        diff = pred - flow_model
        w = cauchy_weight((diff * diff).sum(dim=1, keepdim=True), scale)
    else:
        finite = torch.isfinite(pred).all(dim=1, keepdim=True)
        # Keep NaN out of the arithmetic (and of its gradient): the unused branch sees 0 (also
        # fuse_flow's model flow outside the mask, which may be anything there).
        flow_model = torch.where(mask, flow_model, 0.0)
        safe_pred = torch.where(finite, pred, flow_model)
        diff = safe_pred - flow_model
        w = cauchy_weight((diff * diff).sum(dim=1, keepdim=True), scale)
        w = torch.where(finite, w, torch.ones_like(w))
    if evidence is not None:
        w = w + (1 - w) * evidence.to(w.dtype)
    blended = (flow_model + (1 - w) * diff).to(dtype)  # = w · model + (1 − w) · pred
    weight = torch.where(mask, w, torch.zeros_like(w)).to(dtype)
    return torch.where(mask, blended, flow_pred), weight


def resize_mask(mask: Tensor, size: tuple[int, int]) -> Tensor:
    """A bool mask (B, 1, H, W) resampled to ``size = (h, w)``.

    Shrinking keeps a coarse pixel only when its whole footprint is in the mask (area averaging,
    then ``== 1``): a coarse road pixel never straddles a car's edge. Growing uses exact nearest
    neighbour.
    """
    check_shape(check_mask(mask, "mask"), "mask", ("B", 1, "H", "W"))
    h, w = check_size(size, "size")
    H, W = mask.shape[-2:]
    if (h, w) == (H, W):
        return mask
    m = mask.to(torch.float32)
    if h <= H and w <= W:
        return F.interpolate(m, size=(h, w), mode="area") > 1.0 - 1e-6
    return F.interpolate(m, size=(h, w), mode="nearest-exact") > 0.5


# -- odometry ---------------------------------------------------------------------------------

def _planar_as(model: str, planar: Mapping[str, Tensor], camera: Camera) -> dict[str, Tensor]:
    """Planar odometry (x_d, z_d, yaw; roll and pitch where given, else the camera's) as the
    parameters of the ``"paper"`` or ``"plane"`` model (no vertical motion, no pitch or roll
    change): the same road motion."""
    _, values = pack_params(model, camera, planar)
    return dict(zip(get_road_model(model).params, values.unbind(1)))


def _scatter(values: Tensor, index: Tensor, B: int) -> Tensor:
    out = torch.zeros(B, *values.shape[1:], dtype=values.dtype, device=values.device)
    return out.index_copy(0, index, values)


# -- the refinement ---------------------------------------------------------------------------

def _grey_once(images: tuple[Tensor, Tensor] | None, estimator: Any, flow: Tensor) -> tuple | None:
    """The frames for an image estimator and the gate, which both compare their grey levels and
    convert them alike where the images share the flow's precision (float32 or float64): grey,
    converted once for both. Otherwise (another estimator, a subclass too, which may read the
    colours; other dtypes; or while compiling: the estimator runs eagerly, and a conversion in
    the graph may round otherwise) as they came. The two greys are the channels of one
    (B, 2, H, W) tensor, which the image fit takes as its pair of frames without a copy."""
    if images is None or tracing() or type(estimator) is not ImageMotionEstimator or not (
            images[0].dtype == images[1].dtype == flow.dtype in (torch.float32, torch.float64)):
        return images
    B, _, H, W = images[0].shape
    pair = torch.empty((B, 2, H, W), dtype=flow.dtype, device=flow.device)
    for i, im in enumerate(images):
        to_grey(im, out=pair[:, i:i + 1])
    return pair[:, :1], pair[:, 1:]


def refine_flow(flow: Any, mask: Tensor | str, camera: Camera, odometry: object = None, *,
                estimator: Any = None, gate: Any = "auto", mode: str = "replace", scale: float = 2.0,
                images: tuple[Tensor, Tensor] | None = None, starts: tuple = (), min_pixels: int = 100,
                flow_keys: tuple[str, ...] = DEFAULT_FLOW_KEYS, warn: bool = True, fit: str | None = None,
                fit_roll: bool = False, fit_pitch: bool = False, fit_options: Mapping[str, Any] | None = None,
                photometric_options: Mapping[str, Any] | None = None, road_options: Mapping | None = None) -> RefineOutput:
    """Refine predicted flow(s) with the road model inside the road mask.

    Args:
        flow: the prediction: (B, 2, H, W), a list/tuple of flows (RAFT iterations, a
            ``(low, up)`` pair, a pyramid), or a dict (ARFlow, ptlflow; see ``flow_keys``).
            Every flow is refined at its own resolution.
        mask: (B, 1, H, W) or (1, 1, H, W) bool road mask at the finest flow's size, or ``"auto"`` (auto_road.py).
        camera: :class:`Camera` (batch 1 or B), K at the finest flow's resolution.
        odometry: the motion from t to t+1, or None to estimate it. A road motion in any form
            :func:`~fsof_torch.geometry.road_models.road_motion` takes: a dict ``x_d, z_d, yaw``
            (metres, radians; floats or (B,) tensors), an :class:`EgoMotion`, a dict with a
            ``"model"`` key and that model's parameters, or a fit result, of a displacement model
            (the ``"velocity"`` model's flow is in px/s, not pixels per frame: a ValueError; so is a
            step beyond 100 m or a yaw of half a turn a frame, mm or degrees). A complete model's motion
            (with ``"model"``, a roll or pitch, or a fit: its samples of ``success`` False left unchanged)
            is used as it is; the planar odometry of the paper's model, with images, fixes the planar
            motion while the images estimate the body's pitch and roll changes, its vertical motion
            and the camera's attitude (the plain planar model where that estimate fails). Nothing is estimated,
            and the estimator and its options (``fit_roll``, ``fit_pitch``, ``fit_options``,
            ``photometric_options``) go unused, with a complete motion, with planar odometry
            and no images, and with planar odometry and ``fit=`` set; they are still checked,
            as without odometry, so a refiner configured with an estimator may be given
            odometry on some calls.
        estimator: the road-motion estimator (:mod:`fsof_torch.refinement.estimators`); default:
            :class:`ImageMotionEstimator` with images, :class:`FlowMotionEstimator` without.
            Called only where the motion is estimated (see ``odometry``). An
            :class:`ImageMotionEstimator` (not a subclass) gets the frames in grey where they
            share the flow's dtype (float32 or float64), converted once for it and the gate,
            which both compare grey levels.
        gate: an :class:`~fsof_torch.refinement.gate.ImageGate`, ``"auto"`` (the default gate where
            there are images), or None (no gate: the model replaces the whole mask).
        mode: ``"replace"`` or ``"confidence"`` (see :func:`fuse_flow`; with the gate, the images'
            evidence per region decides where the flows disagree); ``scale`` the Cauchy scale in
            pixels of the finest level (coarser levels scale it with their size), a fixed number.
        images: ``(image1, image2)`` (B, C, H, W) on 0..255 at the finest size, on the flow's
            device (batch 1 serves every sample: B predictions of one pair), or ptlflow's input
            dict ``{"images": (B, 2, 3, H, W)}`` (BGR in [0, 1]).
        starts: further start candidates for an image estimator (e.g. the previous frame's motion).
        min_pixels: without odometry, samples with fewer usable mask pixels are not refined.
        flow_keys: the dict keys whose values are forward flows to refine: one key or a sequence
            of keys (read once; None is a TypeError, the default is :data:`DEFAULT_FLOW_KEYS`).
        warn: warn when samples are left unchanged or non-finite predictions are masked.
        fit, fit_roll, fit_pitch, fit_options, photometric_options: the older way to choose the
            estimator (``fit="flow"``: the paper's model fitted to the prediction with
            ``fit_displacement``'s options; ``fit="photometric"``: fitted to the images, started
            from that flow fit). ``fit_roll`` and ``fit_pitch`` apply to both, ``fit_options`` to
            ``"flow"`` (also the default without images), ``photometric_options`` to
            ``"photometric"``; set where another estimator would run (one given, or the default
            image estimator) they raise a ValueError instead of being left aside, also where
            ``odometry`` makes estimation unnecessary. Names the fits receive from the refiner
            (``flow``, ``mask``, ``camera``, ``image1``, ``image2``, ``model``, ...) raise a
            TypeError.
        road_options: keyword arguments of the road detection of ``mask="auto"``
            (:func:`~fsof_torch.refinement.auto_road.detect_road` with images,
            :func:`~fsof_torch.detect_freespace` without); a mapping with string keys, or None.
            Given with a mask tensor (no detection runs) they raise a ValueError.

    Returns:
        :class:`RefineOutput`. Pixels outside the (resampled) mask, where the gate keeps a finite
        prediction, and samples left unchanged, are bit for bit the prediction; the caller's
        tensors are never modified. The result is differentiable with respect to the prediction
        and, when given, to the camera and the odometry (estimation itself is detached).

    Non-finite predicted values: they are left out of the estimation; inside the mask of a
    refined sample the model replaces them wherever it is defined (both modes, every level, also
    where the gate keeps the prediction); in a sample left unchanged, where the model flow is
    undefined, and outside the mask they are returned as they came. The warning counts the
    pixels inside the mask replaced and left.
    """
    flow_keys, min_pixels = check_refine_options(estimator=estimator, gate=gate, mode=mode, scale=scale, min_pixels=min_pixels,
                                     flow_keys=flow_keys, warn=warn, fit=fit, fit_roll=fit_roll, fit_pitch=fit_pitch,
                                     fit_options=fit_options, photometric_options=photometric_options, starts=starts)
    road_options = check_mapping(road_options, "road_options")
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a fsof_torch.Camera, got {type(camera).__name__}")
    flows = collect_flows(flow, "flow", flow_keys)
    if not flows:
        raise ValueError(f"flow: no flow found in the {type(flow).__name__}; expected a value under "
                         f"one of the keys {flow_keys} (set flow_keys)")
    finest_name, finest = finest_flow(flows)
    B, _, H, W = finest.shape
    check_levels(flows, finest_name, finest)
    if odometry is not None and isinstance(mask, str):
        # (a motion no refinement takes, or absurd values, raise before mask="auto"'s detection)
        road_motion_batch(odometry, B, result_dtype(finest), finest.device, displacement=True)
    elif odometry is not None:  # (its kind first, by name; its values where the batch is made below)
        road_motion(odometry, displacement=True)
    if isinstance(mask, str):  # "auto": the road found in the images (the detection's motion reused)
        images = refiner_images(images, finest)
        if mask == "auto":  # (the detection reads the flow and the images: no shape inference on meta)
            check_has_values(finest, "flow", "to find the road in (mask='auto'; give a mask tensor instead)")
        # (the options are checked before the detection, also where it estimates nothing itself)
        chosen = select_estimator(estimator, fit, images, fit_roll, fit_pitch, fit_options, photometric_options)
        return refine_with_auto_road(
            refine_flow, flow, mask, camera, odometry, images=images, road_options=road_options, warn=warn,
            road_estimator=None if images is None else chosen,
            estimator=estimator, gate=gate, mode=mode, scale=scale, starts=starts, min_pixels=min_pixels, flow_keys=flow_keys,
            fit=fit, fit_roll=fit_roll, fit_pitch=fit_pitch, fit_options=fit_options, photometric_options=photometric_options)
    if not isinstance(mask, Tensor):
        raise TypeError(f"mask: expected a bool tensor (B, 1, H, W), got {type(mask).__name__}")
    if mask.dtype != torch.bool:
        raise TypeError(f"mask: expected a bool tensor (threshold a probability map first), got dtype {mask.dtype}")
    if mask.dim() != 4 or mask.shape[1] != 1 or mask.shape[0] not in (1, B) or tuple(mask.shape[-2:]) != (H, W):
        raise ValueError(f"mask: expected shape ({B}, 1, {H}, {W}) (the finest flow's size), got {tuple(mask.shape)}")
    if road_options:
        raise ValueError(f"road_options: apply to the road detection of mask='auto'; with a mask tensor nothing is "
                         f"detected, got road_options={road_options!r}")
    if camera.batch_size not in (1, B):
        raise ValueError(f"camera: expected batch {batch_choices(B)} (the flow's batch), got {camera.batch_size}")
    images = refiner_images(images, finest)
    if fit == "photometric" and images is None:
        raise ValueError("images: fit='photometric' needs images=(image1, image2), got None")
    # Built (and so checked) also where odometry leaves nothing to estimate: an option that does
    # not fit the estimator raises whether or not this call's odometry makes it unused.
    chosen = select_estimator(estimator, fit, images, fit_roll, fit_pitch, fit_options, photometric_options)
    images = _grey_once(images, chosen, finest)
    device = finest.device
    mask = to_device(mask, "mask", device).expand(B, 1, H, W)
    # The model flow is computed in the prediction's dtype (half lifted to float32): float32
    # evaluates the road homography to about 1e-3 px, far below any network's error, at half
    # the cost of float64; a float64 prediction gets float64 geometry.
    geo_dtype = torch.float32 if finest.dtype in (torch.float16, torch.bfloat16) else finest.dtype
    camera = camera.to(device=device, dtype=geo_dtype).expand(B)

    # One reduction settles the common case (a NaN or inf anywhere makes the sum non-finite;
    # so may an overflow, which then takes the per-pixel path): no full-size test and no copy.
    # (no host reads while tracing or on meta tensors, which have no values: nothing to warn about)
    no_values = skip_values(finest)
    all_finite = not no_values and bool(torch.isfinite(finest.detach().sum()))
    warn = warn and not no_values
    if all_finite:
        fit_mask = mask
    else:
        finite = torch.isfinite(finest).all(dim=1, keepdim=True)
        fit_mask = mask & finite
    # planar odometry (the paper's x_d, z_d, yaw alone) leaves the rest of the road's motion to the
    # images; a complete motion ("model" key, roll or pitch, a fit result), also the paper's, is used as it is
    estimating = odometry is None or (images is not None and is_planar_odometry(odometry) and fit is None)
    # min_pixels guards estimation, which uses the finite predicted pixels; with odometry given
    # any mask pixel can be refined, also one whose prediction is not finite (the model flow
    # needs no prediction). (A uint8 sum into int32: the sum converts its input first, and a
    # bool sum or count_nonzero converts to int64, a copy twice the size.)
    counted = fit_mask if odometry is None else mask
    refined = counted.view(torch.uint8).flatten(1).sum(1, dtype=torch.int32) >= (min_pixels if odometry is None else 1)

    fit_result = None
    pixels: dict = {}  # (the masks' pixels the estimate found: see the gate)
    cam_model = camera
    motion_model, odo = "paper", None
    fit_index, fit_used = None, None  # (the samples the fit's rows hold; (B,) those whose model it is)
    if odometry is not None:
        given, odo = road_motion_batch(odometry, B, geo_dtype, device, displacement=True)
        motion_model, refined = given.name, refined & given_success(odometry, B, device)  # (a failed fit given)
    if estimating:
        # frames of one row or one column hold nothing the image fit can use (its pyramid and image
        # gradients need 2 x 2 pixels): its estimate fails there, as on an empty mask
        flat = images is not None and min(H, W) < 2 and isinstance(chosen, ImageMotionEstimator)
        est = None if flat else _estimate(chosen, finest, fit_mask, camera, refined, images=images, odometry=odometry,
                                          starts=starts, all_finite=all_finite, warn=warn, pixels=pixels)
        if est is not None:
            fit_result, ok, values, est_model, est_camera, fit_index = est
            if odometry is None:
                motion_model, odo, cam_model = est_model, values, est_camera
                refined = refined & ok
            else:
                # the planar motion the estimate held is the caller's: its tensors, with their graph
                values = {k: torch.where(v == odo[k].detach(), odo[k], v) if k in ("x_d", "z_d", "yaw") else v
                          for k, v in values.items()}
                if bool(ok.all()):
                    motion_model, odo, cam_model = est_model, values, est_camera
                elif bool(ok.any()) and est_model in ("paper", "plane"):
                    # where the images say nothing, the odometry alone, sample by sample
                    motion_model, odo = est_model, where_motion(ok, values, _planar_as(est_model, odo, camera))
                    cam_model = Camera._checked(camera.K, camera.height, torch.where(ok, est_camera.roll, camera.roll),
                                                torch.where(ok, est_camera.pitch, camera.pitch))
                    fit_used = ok
                else:  # the odometry alone
                    fit_result = None
        elif odometry is None:
            refined = torch.zeros_like(refined)  # (the model and keys of a sample not estimated beside others)
            motion_model, odo = unestimated_motion(chosen, B, geo_dtype, device)

    def usable(m: Tensor, ok: Tensor) -> Tensor:  # (a broadcast & over the whole mask is slow on CPU: only where needed)
        return m if not no_values and bool(ok.all()) else m & ok.reshape(B, 1, 1, 1)
    cache: dict[tuple[int, int], tuple[Tensor, Tensor]] = {}
    # (a RoadFit's flow is its model flow; another result's "flow" may be anything: the input's)
    fit_flow, fit_valid = (fit_result.flow, fit_result.valid) if isinstance(fit_result, RoadFit) else (None, None)
    n_fit = -1 if fit_index is None else fit_index.numel()
    if (isinstance(fit_flow, Tensor) and tuple(fit_flow.shape) == (n_fit, 2, H, W)
            and isinstance(fit_valid, Tensor) and tuple(fit_valid.shape) == (n_fit, 1, H, W)
            and not _needs_grad(cam_model) and not (torch.is_grad_enabled() and any(v.requires_grad for v in odo.values()))):
        # The estimate evaluated this very model flow at the finest size: reuse it (not where the camera or
        # odometry carries a graph, which the model flow must then keep). Samples it lacks, or given the odometry
        # alone, are evaluated: a sample's model flow is the same whatever the others' (a custom result's: computed).
        f_fit, v_fit = fit_flow.to(device=device, dtype=geo_dtype), fit_valid.to(device)
        if n_fit < B or fit_used is not None:
            use = (torch.zeros_like(refined).index_fill(0, fit_index, True) if fit_used is None else fit_used)
            f_fit, v_fit = (torch.where(use.reshape(B, 1, 1, 1), a.index_copy(0, fit_index, b), a) for a, b in
                            zip(road_flow(cam_model, odo, (H, W), model=motion_model), (f_fit, v_fit)))
        cache[(H, W)] = (f_fit, v_fit)

    def model_flow(size: tuple[int, int]) -> tuple[Tensor, Tensor]:
        if size not in cache:
            h, w = size
            cam = cam_model if (h, w) == (H, W) else cam_model.scaled(w / W, h / H)
            cache[size] = road_flow(cam, odo, (h, w), model=motion_model)
        return cache[size]

    f_model_finest, valid_finest = model_flow((H, W))
    fuse_mask = usable(held_by(mask & valid_finest, f_model_finest, finest.dtype), refined)
    region = fuse_mask  # where the model flow applies in the samples it refines
    gate_result = None
    the_gate = ImageGate() if gate == "auto" and images is not None else (None if gate in ("auto", None) else gate)
    if the_gate is not None:
        if images is None:
            raise ValueError("images: a gate judges the flows by the images; pass images=(image1, image2)")
        # (where the estimate's mask holds the very pixels the gate judges, the gate gets that mask,
        # whose pixels the estimate found: one pass to compare them instead of a second search)
        judged = fuse_mask
        memo = None if tracing() else pixels  # (traced, a guard on its keys, masks' addresses, recompiled each call)
        if memo and fit_mask.is_contiguous() and not bool((fuse_mask ^ fit_mask).view(torch.uint8).amax()):
            judged = fit_mask
        with reused_mask_pixels(memo):
            gate_result = the_gate(images[0], images[1], finest, f_model_finest, judged)
        region = usable(fuse_mask, gate_result.model_used)
        fuse_mask = gate_result.use_model
        refined = refined & gate_result.model_used
    gated = fuse_mask  # the gate's decision (coarser levels resample it)
    if not all_finite:
        # a non-finite prediction explains nothing: in a refined sample the model replaces it
        # wherever the model is defined, also where the gate keeps the prediction
        fuse_mask = fuse_mask | (region & ~finite)
        if warn and not tracing():
            n_bad, n_replaced = torch.stack([(mask & ~finite).sum(), (fuse_mask & ~finite).sum()]).tolist()
            if n_bad:
                left = "" if n_replaced == n_bad else (f"; {n_bad - n_replaced} left as they came (in samples left "
                                                       f"unchanged, or where the model flow is undefined)")
                warn_user(f"flow: {n_bad} non-finite predicted pixels inside the mask, left out of the "
                          f"estimation; {n_replaced} replaced by the model flow{left}")
    # a sample where the model applies nowhere (no mask pixel where it is defined, a gate that keeps
    # the prediction everywhere; no NaN replaced) comes back unchanged, as odometry given or not
    refined = refined & (fuse_mask.view(torch.uint8).flatten(1).amax(1) > 0)  # (bytes: a bool any() is slower)
    if gate_result is not None:
        region = usable(region, refined)
    if warn and not tracing() and not bool(refined.all()) and not UNCHANGED_NAMED.get():
        bad, few = (~refined).nonzero().flatten().tolist(), "" if odometry is not None else ", too few mask pixels (min_pixels)"
        warn_user(f"mask: samples {bad} left unchanged (an empty mask or one where the model is undefined{few}, a "
                  f"failed estimate, images without evidence for the model, or a gate that keeps the prediction "
                  f"everywhere: see RefineOutput.refined and .gate)")

    masks: dict[tuple[int, int], Tensor] = {(H, W): gated}
    regions: dict[tuple[int, int], Tensor] = {(H, W): region}
    weights: dict[tuple[int, int], Tensor] = {}
    evidence = gate_result.evidence if gate_result is not None and mode == "confidence" else None

    # the finest flow's place among the flows map_flows visits (collect_flows' order, a stack's
    # predictions one by one; a stack's last is a new view, not the object finest_flow gave): its
    # fusion is the one the gate decided and the one whose weight is reported
    ends = list(itertools.accumulate(f.shape[1] if f.dim() == 5 else 1 for _, f in flows))
    finest_visit = ends[[name for name, _ in flows].index(finest_name)] - 1
    visits = itertools.count()

    def refine_one(f: Tensor) -> Tensor:
        is_finest = next(visits) == finest_visit
        size = (f.shape[-2], f.shape[-1])
        f_model, valid = model_flow(size)
        if size not in masks:
            masks[size] = resize_mask(gated, size) & valid
        m = masks[size]
        if is_finest:
            m = fuse_mask
        elif gate_result is not None and (skip_values(f) or not bool(torch.isfinite(f.detach().sum()))):
            # this level's own non-finite pixels, where the gate keeps the prediction (see above)
            if size not in regions:
                regions[size] = resize_mask(region, size) & valid
            m = m | (regions[size] & ~torch.isfinite(f).all(dim=1, keepdim=True))
        # The Cauchy scale is in pixels of the level: a coarse level's flow is proportionally smaller.
        c = scale * math.sqrt(size[0] * size[1] / (H * W))
        ev = None if evidence is None else (evidence if size == (H, W) else F.interpolate(evidence, size=size, mode="area"))
        # (the finiteness test above covered the finest prediction itself, not the other levels)
        out, w = _fuse(f, f_model, m, mode, c, all_finite=all_finite and is_finest, evidence=ev)
        if is_finest:
            weights[size] = w
        return out

    refined_flow = map_flows(flow, refine_one, flow_keys)
    weight = weights[(H, W)]  # (the finest is always visited)
    odo = {k: torch.where(refined, v, torch.zeros_like(v)) for k, v in odo.items()}  # (0 where not refined)
    return RefineOutput(refined_flow, odo, fit_result, weight, fuse_mask, refined, cam_model, f_model_finest,
                        motion_model, gate_result)


def _needs_grad(camera: Camera) -> bool:
    return torch.is_grad_enabled() and any(
        t.requires_grad for t in (camera.K, camera.height, camera.roll, camera.pitch))


def _estimate(*args: Any, **kwargs: Any):
    """Estimation is iterative, data dependent and detached: under torch.compile it runs eagerly,
    and the geometry and fusion around it compile (tests/test_fusion_backends.py,
    docs/reliability.md). ``torch.compiler.disable`` is applied only while compiling: as a
    decorator it would import torch._dynamo, the compiler (a slow import), with the library."""
    if tracing():
        return torch.compiler.disable(_estimate_eager)(*args, **kwargs)
    return _estimate_eager(*args, **kwargs)


def _estimate_eager(estimator: Any, finest: Tensor, fit_mask: Tensor, camera: Camera, refined: Tensor, *,
                    images: tuple[Tensor, Tensor] | None, odometry: object, starts: tuple, all_finite: bool,
                    warn: bool = True, pixels: dict | None = None):
    """Estimate the road's motion (detached) for the samples with enough mask pixels.

    Returns None when no sample can be estimated, else ``(fit, success (B,), params {name: (B,)},
    model name, camera with the estimated roll and pitch, index (n,): the fit's samples)``; those
    not estimated get zero motion and success False, as do those with non-finite parameters.
    ``pixels``: a dict that keeps the pixels of the masks the estimator searched
    (:func:`~fsof_torch.estimation.sampling.reused_mask_pixels`).
    """
    check_has_values(finest, "flow", "to estimate the road's motion from (for shape inference on the meta "
                     "device pass odometry=: planar odometry without images, or a model's full motion)")
    B = finest.shape[0]
    dtype, device = camera.dtype, camera.device
    if not bool(refined.any()):
        return None
    index = refined.nonzero().flatten()
    subset = index.numel() < B
    with torch.no_grad():
        f = finest.detach()
        if not all_finite:
            f = torch.where(fit_mask, f, torch.zeros_like(f))  # no NaN reaches the estimate
        f = f.to(dtype)
        m = fit_mask
        cam_d = Camera._checked(camera.K.detach(), camera.height.detach(), camera.roll.detach(), camera.pitch.detach())
        ims = images
        odo = odometry
        if subset:
            f, m, cam_d = f[index], m[index], select_samples(cam_d, index, B)
            ims = None if images is None else tuple(im[index] for im in images)
            if odometry is not None:
                given, values = road_motion_batch(odometry, B, dtype, device)
                odo = {"model": given.name, **select_samples(values, index, B)}
            starts = tuple(select_samples(s, index, B) for s in starts)
        # (f is finite, and the images were checked on 0..255 (refiner_images; their grey levels
        # too): the estimator's own tests of them need not read them again, nor guess a dim frame's
        # grey for a 0..1 image; the masks' pixels it finds are kept in ``pixels``)
        with known_finite(f), known_images(*(ims or ())), reused_mask_pixels(pixels):
            estimate = estimator(f, m, cam_d, images=ims, odometry=odo, starts=starts)
        result = finite_estimate(check_estimate(estimate, index.numel()), cam_d, samples=index.tolist(), warn=warn)
    ok = result.success.to(device=device, dtype=torch.bool)
    params = {k: _scatter(v.detach().to(device=device, dtype=dtype), index, B) for k, v in result.params.items()}
    success = torch.zeros(B, dtype=torch.bool, device=device).index_copy(0, index, ok)
    roll = camera.roll.index_copy(0, index, result.camera.roll.detach().to(device=device, dtype=dtype))
    pitch = camera.pitch.index_copy(0, index, result.camera.pitch.detach().to(device=device, dtype=dtype))
    # the estimated attitude (a failed sample's as fitted) on the caller's K and height (their graph kept)
    cam_model = camera if torch.equal(roll, camera.roll) and torch.equal(pitch, camera.pitch) else \
        Camera._checked(camera.K, camera.height, roll, pitch)
    return result, success, params, result.model, cam_model, index


class FreespaceRefiner(nn.Module):
    """``nn.Module`` twin of :func:`refine_flow`: post-processes a flow network's output.

    Args (keyword-only):
        estimator: the road-motion estimator (default: from the images where given, else from the
            prediction; see :mod:`fsof_torch.refinement.estimators`).
        gate: an :class:`~fsof_torch.refinement.gate.ImageGate`, ``"auto"`` (the default gate
            where there are images) or None.
        mode: ``"replace"`` (the paper: inside the road mask the flow becomes the model flow) or
            ``"confidence"`` (a blend by the flows' disagreement and the images' evidence).
        scale: Cauchy scale in pixels (finest level) for ``confidence``, a fixed number.
        min_pixels: without odometry, fewer usable mask pixels leave the sample unchanged.
        flow_keys: dict keys of forward flows to refine (default :data:`DEFAULT_FLOW_KEYS`; one key
            or a sequence of keys, not None).
        fit, fit_roll, fit_pitch, fit_options, photometric_options: the older way to choose the
            estimator (see :func:`refine_flow`). Checked against the estimator here (one given, or fit=)
            and at every call, also one whose odometry leaves nothing to estimate (the estimator unused).

    Forward: ``refiner(flow, mask, camera, odometry=None, *, images=None, starts=()) -> RefineOutput``.

    Example:
        >>> import fsof_torch as fs; p = fs.render_pair("default", 0, size=(64, 224))
        >>> image1, image2, road, camera = p["image1"][None], p["image2"][None], p["road"][None], p["camera"]
        >>> flows = fs.TinyRAFT(iters=2)(image1, image2)      # a RAFT-style list of (B, 2, H, W)
        >>> refiner = FreespaceRefiner()
        >>> out = refiner(flows, road, camera, images=(image1, image2))
        >>> [tuple(f.shape) for f in out.flow], out.refined   # the same structure as ``flows``
        ([(1, 2, 64, 224), (1, 2, 64, 224)], tensor([True]))
    """

    def __init__(self, *, estimator: Any = None, gate: Any = "auto", mode: str = "replace", scale: float = 2.0,
                 min_pixels: int = 100, flow_keys: tuple[str, ...] = DEFAULT_FLOW_KEYS, warn: bool = True,
                 fit: str | None = None, fit_roll: bool = False, fit_pitch: bool = False,
                 fit_options: Mapping[str, Any] | None = None,
                 photometric_options: Mapping[str, Any] | None = None) -> None:
        super().__init__()
        flow_keys, min_pixels = check_refine_options(estimator=estimator, gate=gate, mode=mode, scale=scale,
                                         min_pixels=min_pixels, flow_keys=flow_keys, warn=warn, fit=fit,
                                         fit_roll=fit_roll, fit_pitch=fit_pitch, fit_options=fit_options,
                                         photometric_options=photometric_options)
        self.estimator = estimator
        self.gate = gate
        self.mode = mode
        self.scale = float(scale)
        self.fit = fit
        self.fit_roll = bool(fit_roll)
        self.fit_pitch = bool(fit_pitch)
        self.fit_options = dict(fit_options or {})
        self.photometric_options = dict(photometric_options or {})
        self.min_pixels = int(min_pixels)
        self.flow_keys = flow_keys
        self.warn = warn

    def forward(self, flow: Any, mask: Tensor | str, camera: Camera, odometry: object = None, *,
                images: tuple[Tensor, Tensor] | None = None, starts: tuple = ()) -> RefineOutput:
        """Refine ``flow`` ((B, 2, H, W) px, or a network's output) inside ``mask`` (B, 1, H, W) bool: :func:`refine_flow`."""
        return refine_flow(flow, mask, camera, odometry, images=images, starts=starts, **self.refine_options())

    def refine_options(self) -> dict[str, Any]:
        """The keyword arguments of :func:`refine_flow` this refiner calls it with (beside the
        call's own inputs): its options."""
        return dict(estimator=self.estimator, gate=self.gate, mode=self.mode, scale=self.scale,
                    min_pixels=self.min_pixels, flow_keys=self.flow_keys, warn=self.warn, fit=self.fit,
                    fit_roll=self.fit_roll, fit_pitch=self.fit_pitch, fit_options=self.fit_options,
                    photometric_options=self.photometric_options)

    def extra_repr(self) -> str:  # mode (scale), the estimator (or fit) and the gate; the rest where not the default
        o, default, how = self.refine_options(), FreespaceRefiner.__init__.__kwdefaults__, "fit" if self.fit else "estimator"
        keys = ["mode", *(["scale"] if self.mode == "confidence" else []), how, "gate"]
        return ", ".join(f"{k}={o[k]!r}" for k in keys + [k for k in o if k not in keys and o[k] not in (default[k], {})])
