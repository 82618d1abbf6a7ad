"""The refiner with ``mask="auto"``: the road found in the images (:func:`~fsof_torch.detect_road`),
or on the prediction without them (:func:`~fsof_torch.detect_freespace`), then the refinement
inside it, with the motion the detection settled on."""

from __future__ import annotations

from contextvars import ContextVar
from dataclasses import replace
from typing import Any

import torch

from .._check import check_keywords, skip_values
from ..estimation.flow_fit import RoadFit
from ..estimation.freespace import detect_freespace
from ..geometry.camera import Camera
from ..geometry.road_models import is_planar_odometry, road_motion_batch
from .auto_road import ROAD_RESERVED, check_motion, detect_road
from .contracts import collect_flows, finest_flow
from ..warn import warn_user

__all__ = ["refine_with_auto_road", "motion_complete"]

#: True while :func:`refine_with_auto_road` refines inside the road it found: the refinement leaves
#: the warning that names its samples left unchanged to it, which names them with the reason
UNCHANGED_NAMED: ContextVar[bool] = ContextVar("UNCHANGED_NAMED", default=False)


def motion_complete(odometry: object, fit: object) -> bool:
    """Whether ``odometry`` gives the road's whole motion, so that ``mask="auto"``'s detection
    estimates none: a road model's full motion, or a planar one that the refiner's ``fit``
    completes."""
    return odometry is not None and (not is_planar_odometry(odometry) or fit is not None)


def refine_with_auto_road(refine: Any, flow: Any, mask: str, camera: Camera, odometry: object, *, images: Any,
                          road_estimator: Any, road_options: dict[str, Any] | None, warn: bool, **kw: Any):
    """``refine_flow(flow, "auto", ...)``: find the road, then refine inside it (the refiner's
    function ``refine`` is passed in: it builds on this module).

    With images, :func:`detect_road` runs with the refiner's road-motion ``road_estimator`` (the
    predicted flow one start; the caller's planar odometry held fixed, or priors with
    ``odometry_sigma``), or judges with the caller's complete road motion; the motion it settled
    on is the refinement's (no second estimate; a held planar odometry as the caller's tensors, so
    a gradient reaches them). Flagged samples are left unrefined, with a warning that gives the
    reason (one also names samples whose road was found but that the refinement left unchanged: a
    failed estimate, a gate without evidence or one that keeps the prediction everywhere); the
    detection comes back as ``RefineOutput.road``.
    Without images, the road is detected on the prediction (:func:`fsof_torch.detect_freespace`),
    which never holds a pixel whose predicted flow is not finite: a warning counts such pixels,
    which come back as they were.
    ``warn=False`` silences the detection's warnings too (an estimate's non-finite parameters,
    :func:`~fsof_torch.refinement.estimators.finite_estimate`), as the refinement's own with a mask
    tensor; the estimator's own warnings pass, as they do there, and so do the refinement's (the
    non-finite predicted pixels inside the road, replaced or left), but for its samples left
    unchanged: those are named here, with the reason.
    ``images``: as ``refine_flow`` checked them (a pair, detached, at the flow's batch, on 0..255), or None.
    """
    if mask != "auto":
        raise ValueError(f"mask: expected a bool tensor (B, 1, H, W) or 'auto', got {mask!r}")
    options = dict(road_options or {})
    # (options the detection does not take, or that the refiner sets itself, raise here, named)
    if images is not None:
        check_keywords(options, "road_options", detect_road, reserved=ROAD_RESERVED)
    else:
        check_keywords(options, "road_options", detect_freespace, reserved=("flow", "camera"))
    _, finest = finest_flow(collect_flows(flow, "flow", kw.get("flow_keys", ())))
    if images is None:
        with torch.no_grad():
            road = detect_freespace(finest.detach().to(camera.dtype), camera.to(device=finest.device), **options)
        # the road found on the prediction holds none of its non-finite pixels (no flow to judge them by),
        # so the refinement's own warning, which counts those inside the mask, cannot name them
        if warn and not skip_values(finest) and not bool(torch.isfinite(finest.detach().sum())):
            n_bad = int((~torch.isfinite(finest.detach()).all(1)).sum())
            if n_bad:
                warn_user(f"flow: {n_bad} non-finite predicted pixels left as they came: mask='auto' without "
                          f"images finds the road on the prediction, which has no flow there (with images= the road "
                          f"is found in the images, and inside it the model replaces them; or give a mask)")
        return refine(flow, road, camera, odometry, images=None, warn=warn, **kw)
    image1, image2 = images
    B = finest.shape[0]
    complete = motion_complete(odometry, kw.get("fit"))
    if complete:  # (checked here: detect_road's errors would name its `motion`)
        check_motion(odometry, B, finest.device, "odometry")
    starts = kw.pop("starts", ())
    # an estimate's inputs, where the motion is estimated (a non-finite pixel of the flow is left
    # out by the estimator, in its own sample only)
    estimate = {} if complete else {"flow": finest.detach(), "estimator": road_estimator, "odometry": odometry,
                                    "starts": starts}
    det = detect_road(image1, image2, camera.to(device=finest.device), motion=odometry if complete else None,
                      warn=warn, **estimate, **options)
    if warn and not all(det.ok.tolist()):
        bad = {i: f"{det.flag[i]}: {det.reason[i]}" for i in range(B) if not bool(det.ok[i])}
        warn_user(f"mask: the road was not found in samples {sorted(bad)} (left unrefined): {bad}")
    motion = odometry if complete else det.motion  # (the caller's own: det.motion holds a batch of 1 per sample)
    if odometry is not None and not complete and isinstance(motion, RoadFit):  # (the caller's planar tensors, graph and all)
        _, odo = road_motion_batch(odometry, B, torch.float64, finest.device)
        motion = replace(motion, params={k: torch.where(v == odo[k].to(v).detach(), odo[k].to(v), v) if k in odo else v
                                         for k, v in motion.params.items()})
    token = UNCHANGED_NAMED.set(True)  # (the refinement's other warnings pass: its non-finite pixels replaced)
    try:
        out = refine(flow, det.usable_mask, camera, motion, images=(image1, image2), warn=warn, **kw)
    finally:
        UNCHANGED_NAMED.reset(token)
    if warn and not bool((out.refined | ~det.ok.to(out.refined.device)).all()):
        kept = (det.ok.to(out.refined.device) & ~out.refined).nonzero().flatten().tolist()
        warn_user(f"mask: samples {kept} left unchanged: the road was found, but the estimate failed, the images "
                  f"gave no evidence for the model, or the gate kept the prediction everywhere (the images favour "
                  f"it: see RefineOutput.refined and .gate)")
    cam = out.camera
    if not complete and isinstance(det.motion, RoadFit) and {"roll", "pitch"} <= set(det.motion.params):
        # the attitude the detection estimated (in the samples whose road it found), as the refiner
        # reports an estimate's: the model flow was computed with it
        ok = det.ok.to(cam.device)
        roll, pitch = (torch.where(ok, det.motion.params[n].detach().to(getattr(cam, n)), getattr(cam, n))
                       for n in ("roll", "pitch"))
        cam = Camera._checked(cam.K, cam.height, roll, pitch)
    return out._replace(road=det, fit=det.motion if not complete else out.fit, camera=cam)

