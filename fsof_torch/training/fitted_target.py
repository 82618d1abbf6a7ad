"""The freespace term's target fitted to the prediction (``odometry="fit"``).

:func:`check_fit_options` checks the fit's options, names and values, where they are given (the
loss term when made, the function at every call, also with a given odometry);
:func:`fitted_target` fits the road model to the detached last estimate inside the road and
returns its flow, detached, with the pixels where it counts.
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping

import torch
from torch import Tensor

from .._check import check_bool, check_keywords, check_mapping
from ..estimation.forwarded import keyed_errors
from ..geometry.camera import Camera
from ..geometry.road_models import get_road_model

__all__ = ["check_fit_options", "fitted_target"]


def check_fit_options(fit_options: Mapping[str, object] | None) -> dict[str, object]:
    """``fit_options`` for ``odometry="fit"``: ``fit_road``'s keyword arguments (with a
    ``"model"``), or ``fit_displacement``'s (``fit_road``'s with ``fit_roll`` / ``fit_pitch`` in
    place of ``model`` / ``fixed``) -> a dict of them.

    Unknown names raise now, named, not at the fit, and so does the ``"velocity"`` model (its flow
    is in px/s: no target for a flow in pixels per frame); so do the values ``fit_road`` checks
    without a flow (a robust kernel, a scale, the fixed names, a prior, ...), as
    :class:`~fsof_torch.FlowMotionEstimator` checks them when made: a TypeError or ValueError
    naming ``fit_options`` and the option.
    """
    from ..estimation.flow_fit import check_road_fit_options, fit_road

    options = dict(check_mapping(fit_options, "fit_options") or {})
    if "model" in options:
        model = get_road_model(options["model"], "fit_options['model']")
        if model.velocity:
            raise ValueError(f"fit_options['model']: the {options['model']!r} model gives flow in px/s, not the pixels "
                             f"per frame the loss compares; fit a displacement model ('paper', 'plane' or 'homography')")
        check_keywords(options, "fit_options", fit_road, reserved=("flow", "mask", "camera"))
        given = dict(options)
    else:
        check_keywords({k: v for k, v in options.items() if k not in ("fit_roll", "fit_pitch")}, "fit_options",
                       fit_road, reserved=("flow", "mask", "camera", "fixed"))
        # (fit_displacement's defaults: the roll fitted, the pitch held)
        fit_roll, fit_pitch = options.get("fit_roll", True), options.get("fit_pitch", False)
        check_bool(fit_roll, "fit_options['fit_roll']")
        check_bool(fit_pitch, "fit_options['fit_pitch']")
        model = get_road_model("paper")
        given = {k: v for k, v in options.items() if k not in ("fit_roll", "fit_pitch")}
        given["fixed"] = tuple(n for n, on in (("roll", fit_roll), ("pitch", fit_pitch)) if not on)
    defaults = {n: p.default for n, p in inspect.signature(fit_road).parameters.items()
                if p.default is not inspect.Parameter.empty}
    given = {**defaults, **given}
    with keyed_errors(given, "fit_options"):  # (named as fit_road names them: the option, as a key of fit_options)
        check_road_fit_options(model, *(given[n] for n in inspect.signature(check_road_fit_options).parameters
                                         if n != "model"))
    return options


def fitted_target(last: Tensor, mask: Tensor, camera: Camera, options: Mapping[str, object],
                  work: torch.dtype) -> tuple[Tensor, Tensor]:
    """The road model (``options["model"]``, the paper's without one) fitted to ``last`` (B, 2, H, W)
    px, detached, inside ``mask`` (B, 1, H, W) bool (the road where ``last`` is finite), in the
    dtype ``work`` -> its flow (B, 2, H, W), detached, and where it counts (B, 1, H, W) bool: where
    the model is defined in a frame whose fit succeeded. ``options``: checked by
    :func:`check_fit_options`."""
    from ..estimation.flow_fit import fit_displacement, fit_road

    fit = fit_road if "model" in options else fit_displacement  # (the paper's by default)
    with torch.no_grad():
        observed = torch.where(mask, last.detach(), torch.zeros((), dtype=last.dtype, device=last.device))
        fitted = fit(observed.to(work), mask, camera, **options)
    return fitted.flow.detach(), fitted.valid & fitted.success.reshape(-1, 1, 1, 1)
