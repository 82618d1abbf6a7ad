"""The image fit's options, checked without images.

:func:`~fsof_torch.estimation.image_fit.fit_image` checks its options with :func:`checked_options`
before any work; the estimators and clip fits that forward options to it
(:class:`~fsof_torch.refinement.estimators.ImageMotionEstimator`,
:func:`~fsof_torch.estimation.sequence.fit_sequence`) check them the same way where they are
given (:func:`~fsof_torch.estimation.image_fit.check_image_fit_options`), so that a bad value is
an error at once, not at the first fit of a clip.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, NamedTuple

import torch

from .._check import (batch_choices, check_bool, check_data_range, check_float_tensor, check_has_values, check_int,
                      check_mapping, check_names, check_number)
from ..geometry.road_models import RoadModel, get_road_model
from .flow_fit import RoadFit, fixed_parameters
from .priors import prior_arrays
from .robust import check_fit_options, check_kernel
from .starts import check_steps

__all__ = ["ImageOptions", "checked_options", "check_bounds", "held_parameters", "check_prior_values"]


class ImageOptions(NamedTuple):
    """What :func:`checked_options` returns that the fit uses: the road model, the starts straight
    ahead, the turns and the steps backwards (checked sequences), the fixed names and the prior."""

    model: RoadModel
    steps: tuple
    turns: tuple
    reverse: tuple
    fixed: Any
    prior: Any


def checked_options(*, model: Any, fixed: Any, init: Any, starts: Any, prior: Any, levels: Any,
                    min_size: Any, max_iter: Any, tol: Any, resolution: Any, smooth_sigma: Any, highpass: Any,
                    band_levels: Any, masked_band: Any, robust: Any, scale: Any, max_points: Any,
                    gradient_fraction: Any, fine_points: Any, affine: Any, inlier_threshold: Any, min_points: Any,
                    min_inlier_fraction: Any, min_correlation: Any, data_range: Any, check_every: Any,
                    forward_starts: Any, turn_starts: Any, reverse_starts: Any, retry_starts: Any,
                    retry_without_prior: Any) -> ImageOptions:
    """fit_image's options (all of them but the images, mask, camera and bounds, which
    :func:`check_bounds` checks against the batch) checked: a TypeError or ValueError naming the
    first bad one."""
    model = get_road_model(model)
    if model.velocity:
        raise ValueError("model: the image fit estimates a motion between two frames; the 'velocity' model "
                         "is a rate (fit its flow with fit_velocity instead)")
    check_kernel(robust)
    if inlier_threshold is None:  # (fit_road's None, 3 × the kernel's scale, has no meaning here: div_'s TypeError)
        raise TypeError("inlier_threshold: expected a finite number > 0 (grey levels), got None")
    check_fit_options(robust, 1.0 if scale is None else scale, max_iter, tol, max_points, inlier_threshold,
                      min_points, min_inlier_fraction)
    if not -1.0 <= check_number(min_correlation, "min_correlation") <= 1.0:
        raise ValueError(f"min_correlation: expected a number in [-1, 1], got {min_correlation!r}")
    check_int(retry_starts, "retry_starts", minimum=0)
    check_bool(retry_without_prior, "retry_without_prior")
    check_int(levels, "levels", minimum=1, optional=True)
    check_int(fine_points, "fine_points", minimum=1, optional=True)
    check_int(min_size, "min_size", minimum=2)
    check_int(band_levels, "band_levels", minimum=0)
    check_int(check_every, "check_every", minimum=1, optional=True)
    check_number(resolution, "resolution", nonnegative=True)
    check_number(smooth_sigma, "smooth_sigma", nonnegative=True)
    if highpass is not None:
        check_number(highpass, "highpass", nonnegative=True)
    if not 0.0 < check_number(gradient_fraction, "gradient_fraction") <= 1.0:
        raise ValueError(f"gradient_fraction: expected a number in (0, 1], got {gradient_fraction!r}")
    check_bool(affine, "affine")
    check_bool(masked_band, "masked_band")
    check_data_range(data_range)
    steps = check_steps(forward_starts, "forward_starts", "camera heights per frame")
    turns = check_steps(turn_starts, "turn_starts", "degrees of yaw per frame")
    reverse = check_steps(reverse_starts, "reverse_starts", "camera heights per frame")
    fixed = check_names(fixed, "fixed")
    if isinstance(prior, str) and prior != "calibration":
        raise ValueError(f"prior: expected 'calibration', None or {{name: (mean, sigma)}}, got {prior!r}")
    if not isinstance(prior, str):
        prior = check_mapping(prior, "prior")
    if init is not None and not isinstance(init, (Mapping, RoadFit)):
        raise TypeError(f"init: expected a RoadFit or a dict of {model.params}, got {type(init).__name__} {init!r}")
    if not isinstance(starts, (list, tuple)):
        raise TypeError(f"starts: expected a list of starts (dicts of parameters or fits), got {type(starts).__name__}")
    for x in starts:
        if not isinstance(x, (Mapping, RoadFit)):
            raise TypeError(f"starts: expected dicts of parameters or fits, got an element {type(x).__name__} {x!r}")
    return ImageOptions(model, steps, turns, reverse, fixed, prior)


def check_bounds(bounds: object, model: RoadModel, B: int | None = None) -> None:
    """``"physical"``, None, or ``(lower, upper)`` float tensors (B, P) in the model's order, batch
    1 broadcasting as a prior's one value does (any B where ``B`` is None)."""
    if bounds is None or (isinstance(bounds, str) and bounds == "physical"):
        return
    P = len(model.params)
    rows = "B" if B is None else batch_choices(B)
    if not isinstance(bounds, (tuple, list)) or len(bounds) != 2:
        raise TypeError(f"bounds: expected 'physical', None or (lower, upper) tensors of shape ({rows}, {P}), "
                        f"got {bounds!r}")
    for name, t in zip(("lower", "upper"), bounds):
        check_float_tensor(t, f"bounds ({name})")
        check_has_values(t, f"bounds ({name})", "to bound a fit")  # (torch's "item() cannot be called on meta tensors")
        if t.dim() != 2 or t.shape[1] != P or (B is not None and t.shape[0] not in (1, B)):
            raise ValueError(f"bounds ({name}): expected shape ({rows}, {P}) (batch, the {model.name!r} model's "
                             f"parameters {model.params}), got {tuple(t.shape)}")
    if bounds[0].shape != bounds[1].shape:
        raise ValueError(f"bounds: expected lower and upper of one shape, got {tuple(bounds[0].shape)} and "
                         f"{tuple(bounds[1].shape)}")
    # (each is moved to the images' device by the fit: lower and upper may lie on different ones)
    if not bool((bounds[0] <= bounds[1].to(bounds[0].device)).all()):
        raise ValueError("bounds: expected lower <= upper everywhere (NaN is not a bound; use ±inf for none)")
    # (a lower bound of +inf, or an upper one of -inf, holds a parameter nowhere: the solver's
    # error named its own "lower" and "upper", and quoted the gain's and offset's columns)
    for name, t, wrong in (("lower", bounds[0], math.inf), ("upper", bounds[1], -math.inf)):
        if bool((t == wrong).any()):
            at = [model.params[i] for i in sorted(set((t == wrong).nonzero()[:, 1].tolist()))]
            raise ValueError(f"bounds ({name}): expected values {'below +inf' if wrong > 0 else 'above -inf'} "
                             f"({-wrong}: no {name} bound), got {wrong} for {at}")


def held_parameters(model: RoadModel, fixed: Any, prior: Any) -> tuple[str, ...]:
    """The names ``fixed`` holds (None: the model's default; a name the model lacks is a ValueError),
    checked against a ``prior`` dict: a prior on a held parameter would be ignored (a ValueError)."""
    names = fixed_parameters(model, fixed)
    if held := [n for n in names if isinstance(prior, Mapping) and n in prior]:
        raise ValueError(f"prior: {held[0]!r} is held at its start (fixed={names!r}), so its prior would "
                         f"be ignored; free it (fixed= without it) or drop its prior")
    return names


def check_prior_values(model: RoadModel, prior: Any) -> None:
    """A ``prior`` dict's names (the model's) and its entries of one value each (numbers: a finite
    mean, a sigma > 0), checked as the fit checks them; entries of several values (one per frame)
    are left to the fit, which knows the batch."""
    if not isinstance(prior, Mapping):
        return
    single = {}
    for name, value in prior.items():
        try:
            one = all(torch.as_tensor(v).numel() == 1 for v in value)
        except Exception:  # (not a pair of numbers: prior_arrays names it)
            one = True
        if one or name not in model.params:
            single[name] = value
    prior_arrays(model, single, 1, torch.device("cpu"))
