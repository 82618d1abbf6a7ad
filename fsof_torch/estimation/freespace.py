"""Freespace detection: the pixels whose flow agrees with the road model fitted to it.

A V-flow curve (:mod:`fsof_torch.estimation.vflow`) seeds a robust fit of the road model
(:func:`fsof_torch.fit_displacement`); the pixels that agree with the fitted model flow and are
connected to the bottom of the image are the freespace.

Convention: flow (B, 2, H, W) in pixels, frame t to t+1; masks (B, 1, H, W) bool.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

from .._check import (batch_choices, check_bool, check_has_values, check_int, check_keywords, check_mapping,
                      check_number, result_dtype, summary_repr)
from ..geometry.camera import Camera
from .combine import where_motion
from .flow_fit import RoadFit, fit_displacement, fit_road
from .forwarded import keyed_errors
from .vflow import VFlowCurve, check_flow_mask, fit_vflow_curve

__all__ = ["FreespaceDetection", "detect_freespace"]

#: What detect_freespace passes the V-flow curve fit and the road fits itself: refused in
#: ``curve_options`` / ``fit_options`` by name (Python would raise "got multiple values" only
#: after the curve fit), as are ``fit_roll`` / ``fit_pitch``, its own arguments. ``fit_options``'
#: ``init`` is taken: it starts the fits on the seed.
CURVE_RESERVED = ("flow", "mask", "model")
FIT_RESERVED = ("flow", "mask", "camera", "model", "fixed")


@dataclass(eq=False, repr=False)
class FreespaceDetection:
    """Everything :func:`detect_freespace` computed on the way (``return_details=True``).

    Compared by identity, as a :class:`Camera` is.

    Attributes:
        freespace: (B, 1, H, W) bool, the result.
        agreement: (B, 1, H, W) bool, pixels whose flow agrees with the fitted model (before the
            connectivity and hole filling).
        seed: (B, 1, H, W) bool, the pixels on the V-flow curve that seeded the model fit.
        curve: the :class:`VFlowCurve` of the seed.
        fit: the ``FitResult`` of :func:`fsof_torch.fit.fit_displacement` behind ``agreement``:
            the fit on the seed where ``refits=0``, else the last refit, on the pixels that agreed
            with the fit before it (on the seed where fewer than 3 did); per frame, of the
            hypothesis kept (attitude fitted or the camera's; on the seed or on its rest).
        success: (B,) bool, frames where both fits succeeded and the freespace holds a pixel (the
            others get an empty freespace).
    """

    freespace: Tensor
    agreement: Tensor
    seed: Tensor
    curve: VFlowCurve
    fit: object
    success: Tensor
    __repr__ = summary_repr


def detect_freespace(flow: Tensor, camera: Camera, *, mask: Tensor | None = None,
                     threshold: float = 0.25, relative_threshold: float = 0.03,
                     seed_threshold: float = 1.0, seed_relative_threshold: float = 0.1,
                     fit_roll: bool = True, fit_pitch: bool = False, bottom_rows: int = 1,
                     close_kernel: int = 3, max_hole_fraction: float = 0.002,
                     refits: int = 1, curve_options: dict | None = None,
                     fit_options: dict | None = None, return_details: bool = False,
                     ) -> Tensor | FreespaceDetection:
    """Freespace: the pixels whose displacement flow agrees with the fitted road model.

    Steps, per frame:

    1. V-flow seed: :func:`fit_vflow_curve` (displacement model) on the flow in ``mask``; the seed
       is the pixels whose vertical flow lies within ``max(seed_threshold,
       seed_relative_threshold·|F_v|)`` of the curve.
    2. Full model: :func:`fsof_torch.fit.fit_displacement` on the seed (x_d, z_d, yaw, and roll /
       pitch if asked), which is robust to the seed's remaining outliers.
    3. Agreement: ``‖F - F_model‖ <= max(threshold, relative_threshold·‖F_model‖)`` where the
       model is defined; then ``refits`` times: refit on the agreeing pixels (started from the
       previous fit) and test again. With roll or pitch fitted, steps 2 and 3 run a second time
       with the camera's attitude held: the seed also holds planes parallel to the road
       (pavements), and a plane tilted between road and pavement fits both while agreeing with
       neither whole. Then both run again on the rest of the seed, the seed less the pixels that
       agree with the hypothesis kept so far: where a pavement holds more of the seed than the
       road, the first fits lock onto it and the road is the rest. Each frame keeps the
       hypothesis whose agreement holds the most pixels connected to the bottom (step 4).
    4. Connectivity: keep the 8-connected components of the agreement that touch the lowest
       ``bottom_rows`` rows holding a usable pixel (ground-truth validity often drops the last
       rows, whose flow leaves the image) (OpenCV ``cv2.connectedComponents`` on the CPU: exact and fast,
       where kornia's iterative ``connected_components`` needs as many passes as the longest
       path); then a morphological closing with a ``close_kernel`` square (kornia; 0 or 1: none)
       and filling of enclosed holes smaller than ``max_hole_fraction`` of the image (neither
       claims a pixel outside ``mask``, of non-finite flow, or where the model is undefined).

    Not differentiable (a segmentation). Frames whose fits fail, or whose freespace would be empty
    (no agreeing pixel connected to the bottom), fail (``success`` False) with an empty freespace.
    Limitation: from flow alone a plane parallel to the road (a pavement) is as good a road plane;
    where one holds more of the agreeing pixels connected to the bottom than the road does, the
    fit takes it.

    Args:
        flow: (B, 2, H, W) displacement flow in pixels (frame t to t+1).
        camera: intrinsics and mounting at the flow's resolution (batch 1 or B); its roll and
            pitch are the starting point of the model fit.
        mask: (B, 1, H, W) bool, pixels that may be freespace (default all; non-finite flow never is).
        threshold, relative_threshold: the agreement test of step 3 (pixels, fraction); set them
            to the flow's noise: a parallel surface a few centimetres above the road (a pavement
            behind a 12 cm kerb seen from 1.5 m) differs from the road's flow by ~8 %, so
            ground-truth flow separates them with ``threshold=0.05, relative_threshold=0.02``,
            while an estimated flow needs thresholds of its own error (0.5–1 px). ``threshold``
            is also the robust scale of the model fit unless ``fit_options`` sets ``scale``.
        seed_threshold, seed_relative_threshold: the seed test of step 1.
        fit_roll, fit_pitch: passed to ``fit_displacement``. An attitude not fitted is the
            camera's, held: a camera given level for a scene pitched by 0.5° (KITTI geometry)
            finds no freespace with ``fit_pitch=False`` (docs/vflow.md); the V-flow curve's
            ``v0`` is the horizon row, which tells the pitch.
        bottom_rows: the number of lowest usable rows a component must touch to be kept.
        close_kernel: side of the closing's structuring element in pixels.
        max_hole_fraction: enclosed holes up to this fraction of H·W are filled.
        refits: number of refits on the agreeing pixels (step 3).
        curve_options: extra keyword arguments for :func:`fit_vflow_curve` (not ``model``, which
            is the displacement model's).
        fit_options: extra keyword arguments for ``fit_displacement`` (``fit_road``'s, e.g.
            ``scale``, ``max_points``, ``prior``; not ``model``, ``fixed``, ``fit_roll`` or
            ``fit_pitch``, which are this function's). An ``init`` starts each hypothesis' fit on
            the seed (without its roll and pitch where the camera's attitude is held; the fits of
            the seed's rest start afresh); the refits start from the fit before them.
        return_details: return a :class:`FreespaceDetection` instead of the mask alone.

    Returns:
        (B, 1, H, W) bool freespace, or a :class:`FreespaceDetection`.
    """
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a fsof_torch.Camera, got {type(camera).__name__}")
    dims, use = check_flow_mask(flow, mask)
    B, H, W = dims["B"], dims["H"], dims["W"]
    if B == 0:
        raise ValueError(f"flow: expected a non-empty batch, got shape {tuple(flow.shape)}")
    if camera.batch_size not in (1, B):
        raise ValueError(f"camera: expected batch {batch_choices(B)} (from flow), got {camera.batch_size}")
    threshold, relative_threshold, seed_threshold, seed_relative_threshold, max_hole_fraction = (
        check_number(value, name, nonnegative=True) for name, value in (
            ("threshold", threshold), ("relative_threshold", relative_threshold),
            ("seed_threshold", seed_threshold), ("seed_relative_threshold", seed_relative_threshold),
            ("max_hole_fraction", max_hole_fraction)))
    bottom_rows = check_int(bottom_rows, "bottom_rows", minimum=1)
    close_kernel = check_int(close_kernel, "close_kernel", minimum=0)
    refits = check_int(refits, "refits", minimum=0)
    for name, value in (("fit_roll", fit_roll), ("fit_pitch", fit_pitch), ("return_details", return_details)):
        check_bool(value, name)
    curve_options, fit_options = check_mapping(curve_options, "curve_options"), check_mapping(fit_options, "fit_options")
    check_keywords(curve_options, "curve_options", fit_vflow_curve, reserved=CURVE_RESERVED)
    # (fit_displacement takes fit_road's options through **options: checked against fit_road's)
    check_keywords({k: v for k, v in fit_options.items() if k not in ("fit_roll", "fit_pitch")}, "fit_options",
                   fit_road, reserved=FIT_RESERVED)
    if own := sorted(set(fit_options) & {"fit_roll", "fit_pitch"}):
        raise TypeError(f"fit_options: options {own} are detect_freespace's own arguments; pass {own[0]}= itself")
    check_has_values(flow, "flow", "to detect freespace in (the detection fits the road model)")
    use = use & torch.isfinite(flow).all(dim=1, keepdim=True)
    flow_safe = torch.where(use, flow, torch.zeros_like(flow))

    with keyed_errors(curve_options, "curve_options"):  # (its relative_threshold is not this function's)
        curve = fit_vflow_curve(flow_safe, use, model="displacement", **curve_options)
    fv = flow_safe[:, 1:2].to(curve.fitted.dtype)
    seed_tol = torch.clamp(seed_relative_threshold * curve.fitted.abs(), min=float(seed_threshold))
    seed = use & curve.fitted_valid & ((fv - curve.fitted).abs() <= seed_tol)

    camera = camera.expand(B) if camera.batch_size != B else camera
    # The fit's robust scale is the same statement about the flow's noise as the threshold.
    fit_kw = dict(fit_roll=fit_roll, fit_pitch=fit_pitch, scale=max(threshold, 1e-3))
    fit_kw.update(fit_options)
    init = fit_kw.pop("init", None)  # (the start of the fit on the seed; each refit starts from the fit before)

    def fitted(options: dict, init: object, start: Tensor):
        with keyed_errors(fit_options, "fit_options"):  # (a value the fits refuse, named as given)
            fit = fit_displacement(flow_safe, start, camera, init=init, **options)
        agreement, success = _agreement(flow_safe, use, fit, curve.success, threshold, relative_threshold)
        for _ in range(refits):
            # The seed holds obstacle pixels near their contact rows, where the V-flow curve cannot
            # tell them from road; refitting on the agreeing pixels removes their pull.
            enough = agreement.flatten(1).sum(-1) >= 3
            retry = torch.where(enough.reshape(B, 1, 1, 1), agreement, start)
            with keyed_errors(fit_options, "fit_options"):
                fit = fit_displacement(flow_safe, retry, camera, init=fit, **options)
            agreement, success = _agreement(flow_safe, use, fit, curve.success, threshold, relative_threshold)
        return fit, agreement, success

    # The seed also holds planes parallel to the road beside it (pavements, parking strips), and
    # with the attitude free a plane tilted between road and pavement can fit both while agreeing
    # with neither whole: the camera's own attitude is a second hypothesis. (A caller's prior on
    # the roll or pitch, and its start of them, are for the first hypothesis, which fits them.)
    options = [(fit_kw, init)]
    if fit_roll or fit_pitch:
        held_kw = {**fit_kw, "fit_roll": False, "fit_pitch": False, "prior": _without_attitude(fit_kw.get("prior"))}
        options.append((held_kw, _without_attitude(init.params if isinstance(init, RoadFit) else init)))
    best = None
    for rest in (False, True):
        # Round 2 fits the seed less the plane kept in round 1: where a parallel plane (a pavement
        # beyond the kerb) holds more of the seed than the road, round 1 locks onto it, and the
        # road is what is left. Per frame, the hypothesis kept is the one whose agreement keeps the
        # most pixels connected to the bottom of the image, as the freespace does (a plane that
        # agrees with many pixels none of which reach the vehicle is not the road under it).
        start = seed & ~best[1] if rest else seed
        for kw, first in options:
            fit, agreement, success = fitted(kw, None if rest else first, start)
            kept = _keep_bottom_connected(agreement, use, bottom_rows)
            if best is None:
                best = (fit, agreement, success, kept)
                continue
            take = kept.flatten(1).sum(-1) > best[3].flatten(1).sum(-1)
            per_pixel = take.reshape(B, 1, 1, 1)
            best = (where_motion(take, fit, best[0]), torch.where(per_pixel, agreement, best[1]),
                    torch.where(take, success, best[2]), torch.where(per_pixel, kept, best[3]))
    fit, agreement, success, freespace = best  # (the freespace: the kept agreement's bottom-connected part)

    if close_kernel > 1:
        import kornia

        kernel = torch.ones(close_kernel, close_kernel, device=flow.device)
        closed = kornia.morphology.closing(freespace.float(), kernel) > 0.5
        # Closing must not grow freespace over the invalid (masked-out) pixels.
        freespace = closed & use & fit.valid
    if max_hole_fraction > 0:
        freespace = _fill_small_holes(freespace, int(max_hole_fraction * H * W))
    # Neither closing nor hole filling may claim masked-out or NaN-flow pixels, nor pixels where
    # the model is not defined.
    freespace = freespace & use & fit.valid & success.reshape(B, 1, 1, 1)
    # A model that agrees with no pixel connected to the bottom of the image found no freespace:
    # the frame fails rather than succeeding with an empty result.
    success = success & freespace.flatten(1).any(-1)
    if return_details:
        return FreespaceDetection(freespace=freespace, agreement=agreement, seed=seed,
                                  curve=curve, fit=fit, success=success)
    return freespace


def _without_attitude(values: object) -> object:
    """A prior or start (a dict by parameter name) without roll and pitch (None where nothing is
    left); anything else as it came (the fit names a wrong type)."""
    if not isinstance(values, Mapping):
        return values
    return {k: v for k, v in values.items() if k not in ("roll", "pitch")} or None


def _agreement(flow: Tensor, use: Tensor, fit, curve_success: Tensor, threshold: float,
               relative_threshold: float) -> tuple[Tensor, Tensor]:
    """Pixels whose flow is within max(threshold, relative·‖model‖) of the fitted model flow
    (in the flow's dtype, half precision lifted to float32 as the fit's model flow is)."""
    B = flow.shape[0]
    dtype = result_dtype(flow)
    model_flow = fit.flow.to(dtype)
    err = (flow.to(dtype) - model_flow).norm(dim=1, keepdim=True)
    tol = torch.clamp(relative_threshold * model_flow.norm(dim=1, keepdim=True), min=float(threshold))
    success = curve_success & fit.success.to(curve_success.device)
    return use & fit.valid & (err <= tol) & success.reshape(B, 1, 1, 1), success


def _keep_bottom_connected(mask: Tensor, use: Tensor, bottom_rows: int) -> Tensor:
    """Components (8-connected) of a (B,1,H,W) bool mask touching the bottom rows of the usable
    region ``use`` (OpenCV, CPU). Ground-truth validity often drops the last rows (their flow
    leaves the image), so "bottom" is the lowest rows that hold a usable pixel."""
    import cv2
    import numpy as np

    out = []
    rows_used = use[:, 0].any(dim=-1).cpu().numpy()  # (B, H)
    for m, rows in zip(mask[:, 0].cpu().numpy().astype(np.uint8), rows_used):
        count, labels = cv2.connectedComponents(m, connectivity=8)
        keep = np.zeros(count, dtype=bool)
        last = int(np.flatnonzero(rows)[-1]) + 1 if rows.any() else m.shape[0]
        keep[np.unique(labels[max(0, last - bottom_rows):last])] = True
        keep[0] = False  # label 0 is the background
        out.append(keep[labels])
    return torch.from_numpy(np.stack(out)).unsqueeze(1).to(mask.device)


def _fill_small_holes(mask: Tensor, max_area: int) -> Tensor:
    """Fill the background components of a (B,1,H,W) bool mask that do not touch the image
    border and have at most ``max_area`` pixels (4-connected background)."""
    import cv2
    import numpy as np

    if max_area <= 0:
        return mask
    out = []
    for m in mask[:, 0].cpu().numpy():
        count, labels, stats, _ = cv2.connectedComponentsWithStats((~m).astype(np.uint8), connectivity=4)
        border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
        fill = stats[:, cv2.CC_STAT_AREA] <= max_area
        fill[border] = False
        fill[0] = False  # label 0 is the foreground (freespace) itself
        out.append(m | fill[labels])
    return torch.from_numpy(np.stack(out)).unsqueeze(1).to(mask.device)
