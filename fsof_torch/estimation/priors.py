"""The fits' priors and bounds from the calibration and the physics of a car (DESIGN.md §10):
:func:`calibration_prior` (Gaussian priors on the camera's attitude over the road and the body's
motion between frames), :func:`physical_bounds` (beyond which an estimate has failed whatever the
images say), :func:`within_bounds` (the flow fits' test of them) and :func:`prior_arrays` (priors
as the solver takes them)."""

from __future__ import annotations

import math
from typing import Any, Mapping

import torch
from torch import Tensor

from .._check import batch_choices, check_has_values, check_number
from ..geometry.camera import Camera
from ..geometry.road_models import RoadModel, get_road_model

__all__ = ["calibration_prior", "physical_bounds", "within_bounds", "clear_of_bounds", "prior_arrays", "DEG"]

DEG = math.pi / 180.0


def calibration_prior(model: str | RoadModel, camera: Camera, *, mounting_deg: float = 1.0,
                      body_rotation_deg: float = 0.3, vertical_m: float = 0.02) -> dict[str, tuple[Tensor, float]]:
    """Gaussian priors from the calibration and the physics of a car (DESIGN.md §10).

    The camera's roll and pitch relative to the road: the calibrated values ± ``mounting_deg``;
    the body's pitch and roll change between frames: 0 ± ``body_rotation_deg``; its vertical
    motion: 0 ± ``vertical_m``. Returns ``{name: (mean (B,), sigma)}`` for the model's parameters
    that have one (none for the homography model).
    """
    model = get_road_model(model)
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a fsof_torch.Camera, got {type(camera).__name__}")
    mounting_deg, body_rotation_deg, vertical_m = (check_number(v, n, positive=True) for n, v in (
        ("mounting_deg", mounting_deg), ("body_rotation_deg", body_rotation_deg), ("vertical_m", vertical_m)))
    out: dict[str, tuple[Tensor, float]] = {}
    if "roll" in model.params:
        # (copies: a prior edited in place must not change the camera)
        out["roll"] = (camera.roll.clone(), mounting_deg * DEG)
        out["pitch"] = (camera.pitch.clone(), mounting_deg * DEG)
    for name, sigma in (("pitch_change", body_rotation_deg * DEG), ("roll_change", body_rotation_deg * DEG),
                        ("y_d", vertical_m)):
        if name in model.params:
            out[name] = (torch.zeros_like(camera.height), sigma)
    return out


def physical_bounds(model: str | RoadModel, camera: Camera) -> tuple[Tensor, Tensor]:
    """Bounds (B, P) each, beyond which a road-motion estimate has failed whatever the images say:
    the camera's roll and pitch within 10° of the calibration, the body's pitch and roll change
    below 5° per frame, yaw below 30° per frame, the translation below 20 camera heights per frame
    (y_d below 0.3). The homography model has none."""
    model = get_road_model(model)
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a fsof_torch.Camera, got {type(camera).__name__}")
    B = camera.batch_size
    h = camera.height.to(torch.float64)
    lo = torch.full((B, len(model.params)), -math.inf, dtype=torch.float64, device=camera.device)
    hi = -lo
    limits = {"yaw": 30 * DEG, "pitch_change": 5 * DEG, "roll_change": 5 * DEG, "x_d": 20 * h, "z_d": 20 * h,
              "y_d": 0.3 * h}
    for i, name in enumerate(model.params):
        if name in ("roll", "pitch"):
            centre = getattr(camera, name).to(torch.float64)
            lo[:, i], hi[:, i] = centre - 10 * DEG, centre + 10 * DEG
        elif name in limits:
            lo[:, i], hi[:, i] = -limits[name], limits[name]
    return lo, hi


def within_bounds(model: str | RoadModel, camera: Camera, params: Tensor, covariance: Tensor,
                  free: Tensor) -> Tensor:
    """(B,) bool: every free parameter of ``params`` (B, P) lies within :func:`physical_bounds` and
    is determined by the data to better than half their width (its standard deviation from
    ``covariance`` (B, P, P)): a fit outside them, or one that cannot place a parameter inside
    them (the camera's attitude of a vehicle at rest: the flow is about 0 whatever it is), has
    failed. ``free`` (P,) bool; parameters without bounds pass. The bounds are inclusive up to
    rounding (1e-9 of their width): an exact fit of a camera rolled by the 10° of the paper's own
    experiments lands on either side of the bound."""
    lo, hi = (b.to(params.device, torch.float64) for b in physical_bounds(model, camera))
    p = params.to(torch.float64)
    sd = covariance.to(torch.float64).diagonal(dim1=-2, dim2=-1).clamp_min(0).sqrt()
    slack = 1e-9 * (hi - lo)
    ok = (p >= lo - slack) & (p <= hi + slack) & (sd <= 0.5 * (hi - lo))
    return (ok | ~free.to(params.device)).all(-1)


def clear_of_bounds(params: Tensor, covariance: Tensor, lower: Tensor | None, upper: Tensor | None) -> Tensor:
    """(B,) bool: every parameter of ``params`` (B, P) lies more than its standard deviation (from
    ``covariance`` (B, P, P)) inside its bounds ``lower`` and ``upper`` ((B, P) or more columns,
    the first P read; ±inf: none; None: no bounds). The image fit's test of its bounds: its solver
    clamps the parameters into them, so a fit that the images (and the prior) would take beyond
    one ends on it, or as near it as its last step leaves it; the bound, not the images, placed
    such a parameter."""
    P = params.shape[-1]
    p = params.to(torch.float64)
    sd = covariance.to(torch.float64).diagonal(dim1=-2, dim2=-1).clamp_min(0).sqrt()
    ok = torch.ones(params.shape[:-1], dtype=torch.bool, device=params.device)
    for bound, side in ((lower, 1.0), (upper, -1.0)):
        if bound is not None:
            bound = bound[..., :P].to(p)
            ok = ok & (torch.isinf(bound) | (side * (p - bound) > sd)).all(-1)
    return ok


def prior_arrays(model: RoadModel, spec: Mapping[str, tuple[Any, Any]] | None, B: int,
                 device: torch.device) -> tuple[Tensor | None, Tensor | None]:
    """(mean, 1 / σ²) (B, P + 2) of Gaussian priors ``{name: (mean, sigma)}`` (zero where none)."""
    if not spec:
        return None, None
    P = len(model.params)
    mean = torch.zeros(B, P + 2, dtype=torch.float64, device=device)
    inverse_variance = torch.zeros_like(mean)
    good = []  # (each entry's values judged at the end, in one host read)
    for name, value in spec.items():
        if name not in model.params:
            raise ValueError(f"prior: unknown parameter {name!r} of model {model.name!r}; expected some of {model.params}")
        try:
            mu, sigma = value
        except (TypeError, ValueError):
            raise ValueError(f"prior[{name!r}]: expected (mean, sigma), got {value!r}") from None
        for v in (mu, sigma):  # (was: "expected numbers or tensors (mean, sigma)")
            check_has_values(v, f"prior[{name!r}]", "for a prior")
        try:
            mu = torch.as_tensor(mu, dtype=torch.float64, device=device).reshape(-1)
            sigma = torch.as_tensor(sigma, dtype=torch.float64, device=device).reshape(-1)
        except (TypeError, ValueError, RuntimeError):
            raise TypeError(f"prior[{name!r}]: expected numbers or tensors (mean, sigma), got {value!r}") from None
        if mu.numel() not in (1, B) or sigma.numel() not in (1, B):
            raise ValueError(f"prior[{name!r}]: expected a mean and a sigma of batch {batch_choices(B)}, got "
                             f"{mu.numel()} and {sigma.numel()} values")
        good.append(torch.isfinite(mu).all() & (sigma > 0).all())
        i = model.params.index(name)
        mean[:, i] = mu
        inverse_variance[:, i] = sigma.square().reciprocal()
    for (name, value), ok in zip(spec.items(), torch.stack(good).tolist()):
        if not ok:
            raise ValueError(f"prior[{name!r}]: expected a finite mean and sigma > 0, got {value!r}")
    return mean, inverse_variance
