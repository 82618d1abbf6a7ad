"""Where an image fit starts, and how its starts compete.

:func:`~fsof_torch.estimation.image_fit.fit_image` solves every candidate start at the coarsest
pyramid level, batched, and goes on from the one with the lowest robust image cost. The
candidates: the caller's ``init`` and ``starts`` (a network's flow, the previous frame's motion,
a constant-velocity guess) and starts straight ahead at a few speeds (:func:`starts_ahead`),
so that fast driving is found from zero motion or a poor flow. They are compared by
:func:`two_way_cost`, which also maps image 2's road back into image 1: a motion that pushes most
of image 1's road out of view cannot win on the few points it keeps.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import torch
from torch import Tensor

from .._check import check_number
from ..geometry.camera import Camera
from ..geometry.road_models import RoadModel, get_road_model, homography_values, pack_params
from .flow_fit import start_values
from .robust import robust_terms
from .sampling import gather_pixels, pixel_coordinates, sample_mask, sample_points

__all__ = ["start_list", "check_forward_steps", "starts_ahead", "two_way_cost"]


def start_list(model: RoadModel, camera: Camera, init: Any, starts: Sequence[Any], default: Tensor) -> list[Tensor]:
    """Start values (B, P) float64: ``init`` over zero motion (the base), then each of ``starts``
    over the base (a start gives some parameters; the others are the base's)."""
    base, _ = start_values(model, init, camera, default)
    return [base] + [start_values(model, s, camera, base)[0] for s in starts]


def check_forward_steps(steps: object) -> tuple[float, ...]:
    """``forward_starts``: a list or tuple of finite numbers (camera heights per frame)."""
    if not isinstance(steps, (list, tuple)):
        raise TypeError(f"forward_starts: expected a list or tuple of numbers (camera heights per frame), "
                        f"got {type(steps).__name__} {steps!r}")
    return tuple(check_number(k, "forward_starts") for k in steps)


def starts_ahead(model: RoadModel, camera: Camera, steps: Sequence[float], fixed: tuple[str, ...]) -> list[dict]:
    """Starts straight ahead by ``k`` camera heights per frame for each k of ``steps`` (at the
    camera's roll and pitch): a road's image motion scales with the distance over the height, and
    from zero motion or a poor flow the fit can land on a wrong motion when the car moves a few
    heights a frame (tests/test_fit_starts.py). ``"homography"``: that motion's homography; none
    where the forward motion is held fixed."""
    if not steps or "z_d" in fixed or (model.name == "homography" and fixed):
        return []
    if "z_d" in model.params:
        return [{"z_d": k * camera.height} for k in steps]
    if model.name != "homography":
        return []
    plane = get_road_model("plane")
    out = []
    for k in steps:
        _, values = pack_params(plane, camera, {"z_d": k * camera.height})
        H = plane.matrix(camera, values)
        out.append(dict(zip(model.params, homography_values(H, camera.K, camera.K_inv()).unbind(1))))
    return out


def two_way_cost(params: Tensor, model: RoadModel, camera: Camera, img: Tensor, mask: Tensor, kernel: str,
                  max_points: int | None, reps: int) -> Tensor:
    """The robust image cost (B reps,) by which competing starts ``params`` (B reps, P + 2) are
    compared, on one pyramid level ``img`` (B, 2, h, w): the mean over image 1's road points
    mapped into image 2 and over image 2's points at the same pixels mapped back into image 1,
    with a kernel scale common to the candidates of a frame (that of the best aligned).

    Image 1's points alone cannot judge a motion that moves most of them out of image 2: one that
    drives far ahead keeps only a few points near the horizon, which a blurred coarse level fits
    with any motion; mapped back, image 2's road then lands on image 1's road far ahead, and does
    not match. (The road at t + 1 lies about where it lay at t; the robust kernel absorbs the
    rest.)"""
    P = len(model.params)
    values, gain, offset = params[:, :P], params[:, P:P + 1], params[:, P + 1:]
    rep = (lambda t: t.repeat(reps, *([1] * (t.dim() - 1))))
    cam = camera.repeat(reps)
    M, _, horizon = model.evaluate(cam.K, cam.K_inv(), cam.height, values, False)
    if horizon is None:
        horizon = model.horizon_row(cam, values)
    points = sample_mask(mask, max_points)
    pts, sel = rep(pixel_coordinates(points.pix, img.shape[-1])), rep(points.sel)
    at = rep(gather_pixels(img, points.pix).to(torch.float64))  # (I1, I2) at the points
    errors, uses = [], []
    # forward: image 1's points into image 2; backward: image 2's points into image 1
    for H, forward in ((M, True), (torch.linalg.inv_ex(M)[0], False)):
        p = H @ pts
        ok = sel & (p[:, 2] > 1e-9)
        p = p / torch.where(ok, p[:, 2], 1.0).unsqueeze(1)
        ok = ok & ((horizon @ (pts if forward else p))[:, 0] > 0)  # on the road in front at t
        sampled, inb = sample_points(rep(img[:, 1:] if forward else img[:, :1]), p[:, :2])
        I2, I1 = (sampled[:, 0], at[:, 0]) if forward else (at[:, 1], sampled[:, 0])
        errors.append((gain * I2 + offset - I1).abs())
        uses.append(ok & inb)
    e, use = torch.cat(errors, 1), torch.cat(uses, 1)
    mad = torch.nanmedian(torch.where(use, e, float("nan")), dim=1).values
    scale = (1.4826 * torch.nan_to_num(mad, nan=math.inf)).reshape(reps, -1).amin(0)
    scale = torch.where(torch.isfinite(scale), scale.clamp_min(2.0), 2.0)  # (no point in view: any scale)
    rho, _ = robust_terms(e.square(), scale.repeat(reps), kernel, use.to(torch.float64))
    return rho / use.sum(1).clamp_min(1)
