"""Where an image fit starts, and how its starts compete.

:func:`~fsof_torch.estimation.image_fit.fit_image` solves every candidate start at the coarsest
pyramid level, batched, and goes on from the one with the lowest robust image cost. The
candidates: the caller's ``init`` and ``starts`` (a network's flow, the previous frame's motion,
a constant-velocity guess) and starts straight ahead at a few speeds (:func:`starts_ahead`),
so that fast driving is found from zero motion or a poor flow. They are compared by
:func:`two_way_cost`, which also maps image 2's road back into image 1: a motion that pushes most
of image 1's road out of view cannot win on the few points it keeps. Where the fits from all of
them fail, :func:`screened_start` screens a few turns for one more start, and where that fails
too, a few steps backwards: a sharp turn moves the whole image sideways, and driving backwards
(the backward flow of forward driving) moves the road away from the camera, both beyond the basin
of a start straight ahead.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import torch
from torch import Tensor

from .._check import check_number
from ..evaluation.census import CONTRAST, census_ring_distances
from ..geometry.camera import Camera
from ..geometry.road_models import RoadModel, get_road_model, homography_values, pack_params
from .flow_fit import start_values
from .robust import robust_terms
from .sampling import gather_pixels, pixel_coordinates, sample_mask, sample_points

__all__ = ["start_list", "check_steps", "starts_ahead", "planar_homography", "turn_moves", "reverse_moves", "screened_start", "two_way_cost",
           "better_fit", "TURN_STARTS", "REVERSE_STARTS"]

#: The turns (degrees of yaw per frame) screened for a start where every other start failed
#: (:func:`screened_start`). A car's yaw rate stays below about 70°/s (tyre grip of about 0.8 g at
#: its tightest turn, about 5 m radius: sqrt(a / r) ≈ 1.25 rad/s), 7° a frame at 10 Hz, 12° at
#: 6 Hz; the 3° steps lie within the basin of a start at the coarsest level (python
#: benchmarks/real_road.py --yaw-deg).
TURN_STARTS = (-12.0, -9.0, -6.0, -3.0, 3.0, 6.0, 9.0, 12.0)
#: the distance ahead (camera heights per frame) at which the turns are screened
TURN_SPEED = 1.0
#: The steps straight backwards (camera heights per frame) screened after the turns: the backward
#: flow of forward driving (image 2 to image 1, as a forward-backward check computes it) moves
#: the road away from the camera, where no start straight ahead lies in its basin. 2 and 4
#: mirror the starts straight ahead (``fit_image``'s ``forward_starts``); 1, as from zero motion
#: the fit can land short from about half a camera height a frame backwards.
REVERSE_STARTS = (1.0, 2.0, 4.0)


def start_list(model: RoadModel, camera: Camera, init: Any, starts: Sequence[Any], default: Tensor) -> list[Tensor]:
    """Start values (B, P) float64: ``init`` over zero motion (the base), then each of ``starts``
    over the base (a start gives some parameters; the others are the base's)."""
    base, _ = start_values(model, init, camera, default)
    return [base] + [start_values(model, s, camera, base, f"starts[{i}]")[0] for i, s in enumerate(starts)]


def check_steps(steps: object, name: str, unit: str) -> tuple[float, ...]:
    """``forward_starts``, ``reverse_starts`` or ``turn_starts`` (``name``): a list or tuple of
    finite numbers (in ``unit``)."""
    if not isinstance(steps, (list, tuple)):
        raise TypeError(f"{name}: expected a list or tuple of numbers ({unit}), got {type(steps).__name__} {steps!r}")
    return tuple(check_number(k, name) for k in steps)


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
    return [planar_homography(camera, {"z_d": k * camera.height}) for k in steps]


def planar_homography(camera: Camera, planar: dict[str, Any]) -> dict[str, Tensor]:
    """The ``"homography"`` model's parameters {name: (B,)} of a planar motion ``planar`` (some
    of x_d, z_d, yaw; floats or (B,) tensors) at the camera's roll and pitch: the same start for a
    homography fit, whose parameters share no name with it."""
    plane = get_road_model("plane")
    camera, values = pack_params(plane, camera, planar)
    H = plane.matrix(camera, values)
    return dict(zip(get_road_model("homography").params, homography_values(H, camera.K, camera.K_inv()).unbind(1)))


def turn_moves(turns: Sequence[float], fixed: tuple[str, ...]) -> list[tuple[float, float]]:
    """The screen's turns (:func:`screened_start`): each of ``turns`` degrees of yaw per frame at
    :data:`TURN_SPEED` camera heights ahead; none where the yaw is held fixed."""
    return [] if "yaw" in fixed else [(float(t), TURN_SPEED) for t in turns]


def reverse_moves(steps: Sequence[float], fixed: tuple[str, ...]) -> list[tuple[float, float]]:
    """The screen's steps straight backwards (:func:`screened_start`): each of ``steps`` camera
    heights per frame backwards, no yaw; none where z_d is held fixed."""
    return [] if "z_d" in fixed else [(0.0, -float(k)) for k in steps]


def screened_start(model: RoadModel, camera: Camera, base: Tensor, img: Tensor, mask: Tensor,
                   moves: Sequence[tuple[float, float]], fixed: tuple[str, ...], kernel: str,
                   max_points: int | None, census: bool = True, rank: int = 0) -> Tensor | None:
    """The start (B, P), among ``moves`` (degrees of yaw per frame, camera heights ahead per frame:
    :func:`turn_moves`, :func:`reverse_moves`), whose motion best aligns one pyramid level ``img``
    (B, 2, h, w) (its camera: ``camera``; road ``mask``) by :func:`two_way_cost` with the census: a
    screen, not a fit, so one batched cost evaluation, which an exposure change between the frames
    does not fool (``census=False``: raw intensities instead, gain 1 and offset 0, for comparison:
    benchmarks/turn_screen.py). A turn moves the whole image sideways, by about f tan(yaw) pixels,
    beyond the basin of a start straight ahead (a few pixels of the coarsest level) within a few
    degrees a frame; a network's flow often misses such a shift too. Driving backwards (the
    backward flow of forward driving) moves the road away from the camera, the other way from
    every start straight ahead. For a model with a yaw, a start is ``base`` with the move's yaw
    and z_d (k h), each where it is not held fixed, the rest (roll and pitch among them)
    ``base``'s; for the ``"homography"`` it is built from the camera alone (not from ``base``'s
    values): the homography of the ``"plane"`` model's move at ``camera``'s roll and pitch, every
    other motion zero. ``rank``: the start ranked so (0: the best; at most the last). None where
    there are no moves or a homography parameter is held."""
    if not moves or (model.name == "homography" and fixed):
        return None
    B, T = base.shape[0], len(moves)
    dev = base.device
    yaw = torch.tensor([math.radians(m[0]) for m in moves], dtype=torch.float64, device=dev).repeat_interleave(B)
    ahead = torch.tensor([m[1] for m in moves], dtype=torch.float64, device=dev).repeat_interleave(B)
    z_d = ahead * camera.height.to(torch.float64).repeat(T)
    cam = camera.repeat(T)
    if model.name == "homography":
        plane = get_road_model("plane")
        _, values = pack_params(plane, cam, {"yaw": yaw, "z_d": z_d})
        values = homography_values(plane.matrix(cam, values), cam.K, cam.K_inv())
    else:
        values = base.repeat(T, 1)
        for name, value in (("yaw", yaw), ("z_d", z_d)):
            if name not in fixed:
                values[:, model.params.index(name)] = value
    ones = torch.ones(T * B, 1, dtype=torch.float64, device=base.device)
    cost = two_way_cost(torch.cat([values, ones, torch.zeros_like(ones)], dim=1), model, camera, img, mask,
                        kernel, max_points, T, census=census)
    ranked = cost.reshape(T, B).argsort(dim=0, stable=True)[min(rank, T - 1)]
    return values.reshape(T, B, -1)[ranked, torch.arange(B, device=base.device)]


def two_way_cost(params: Tensor, model: RoadModel, camera: Camera, img: Tensor, mask: Tensor, kernel: str,
                  max_points: int | None, reps: int, match: bool = False, census: bool = False) -> Tensor:
    """The robust image cost (B reps,) by which competing starts ``params`` (B reps, P + 2) are
    compared, on one pyramid level ``img`` (B, 2, h, w): the mean over image 1's road points
    mapped into image 2 and over image 2's points at the same pixels mapped back into image 1,
    with a kernel scale common to the candidates of a frame (that of the best aligned).

    ``match``: each candidate's gain and offset are replaced by those matching the compared
    intensities' means and spreads (as :func:`~fsof_torch.estimation.confidence.matched_gain`, not
    a regression, whose gain shrinks under a wrong motion), for candidates whose own were fitted
    on other images (the band of detail): applied to ``img``, those judge the band's gain, not the
    alignment (tests/test_fit_starts.py).

    ``census``: the mean ternary census distance over the compared points instead
    (:func:`~fsof_torch.evaluation.census.census_ring_distance`, the gate's: the order of each point
    against its ring of neighbours, at the level's resolution), for candidates that were never
    fitted (the screens of turns and of steps backwards). Gains and offsets are not used: the
    order of the grey levels does not change with the exposure, where raw intensities under a
    change of exposure move every residual alike and the robust kernel, its scale grown with
    them, no longer tells the candidates apart; and nothing is estimated per candidate, so nothing can absorb part of a
    wrong candidate's misalignment, as a gain or offset matched per candidate can
    (tests/test_fit_starts.py). A candidate without a compared point costs 1, the largest
    distance.

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
    if not census:
        at = rep(gather_pixels(img, points.pix).to(torch.float64))  # (I1, I2) at the points
    pairs, uses, distances = [], [], []
    # forward: image 1's points into image 2; backward: image 2's points into image 1
    for H, forward in ((M, True), (torch.linalg.inv_ex(M)[0], False)):
        p = H @ pts
        ok = sel & (p[:, 2] > 1e-9)
        p = p / torch.where(ok, p[:, 2], 1.0).unsqueeze(1)
        ok = ok & ((horizon @ (pts if forward else p))[:, 0] > 0)  # on the road in front at t
        if census:
            own, other = (img[:, :1], img[:, 1:]) if forward else (img[:, 1:], img[:, :1])
            (d, n, inside), = census_ring_distances(rep(own), rep(other), pts[:, 0], pts[:, 1],
                                                    (p[:, :2] - pts[:, :2],), CONTRAST)
            distances.append(d.to(torch.float64))
            uses.append(ok & inside & (n > 0))
            continue
        sampled, inb = sample_points(rep(img[:, 1:] if forward else img[:, :1]), p[:, :2])
        pairs.append((sampled[:, 0], at[:, 0]) if forward else (at[:, 1], sampled[:, 0]))
        uses.append(ok & inb)
    use = torch.cat(uses, 1)
    if census:
        count = use.sum(1)
        total = torch.where(use, torch.cat(distances, 1), 0.0).sum(1)
        return torch.where(count > 0, total / count.clamp_min(1), 1.0)
    I2, I1 = (torch.cat(x, 1) for x in zip(*pairs))
    if match:
        w = use.to(torch.float64)
        w = w / w.sum(1, keepdim=True).clamp_min(1)
        m1, m2 = (w * I1).sum(1, keepdim=True), (w * I2).sum(1, keepdim=True)
        s1, s2 = (w * (I1 - m1).abs()).sum(1, keepdim=True), (w * (I2 - m2).abs()).sum(1, keepdim=True)
        gain = torch.where(s2 > 0, s1 / s2.clamp_min(1e-12), 1.0)
        offset = m1 - gain * m2
    e = (gain * I2 + offset - I1).abs()
    mad = torch.nanmedian(torch.where(use, e, float("nan")), dim=1).values
    scale = (1.4826 * torch.nan_to_num(mad, nan=math.inf)).reshape(reps, -1).amin(0)
    scale = torch.where(torch.isfinite(scale), scale.clamp_min(2.0), 2.0)  # (no point in view: any scale)
    rho, _ = robust_terms(e.square(), scale.repeat(reps), kernel, use.to(torch.float64))
    return rho / use.sum(1).clamp_min(1)


def better_fit(fit: dict[str, Tensor], other: dict[str, Tensor], clear: float | None = None) -> dict[str, Tensor]:
    """Two fits of the same frames (dicts of (B, ...) tensors with ``success`` and
    ``correlation``): ``fit`` where it succeeded; elsewhere ``other`` where that succeeds or its
    images correlate better. With ``clear``, a success whose detail correlates below ``clear``
    (a weak one) gives way to a success of ``other`` that correlates better."""
    take = ~fit["success"] & (other["success"] | (other["correlation"] > fit["correlation"]))
    if clear is not None:
        take |= fit["success"] & (fit["correlation"] < clear) & other["success"] & (
            other["correlation"] > fit["correlation"])
    return {k: torch.where(take.reshape(-1, *([1] * (v.dim() - 1))), other[k], v) for k, v in fit.items()}
