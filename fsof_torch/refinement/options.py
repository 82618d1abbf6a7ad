"""The options of the refiner (:func:`~fsof_torch.refinement.fusion.refine_flow` and
:class:`~fsof_torch.refinement.fusion.FreespaceRefiner`), checked in one place before any work:
a named ``TypeError`` / ``ValueError`` quoting what came, also for the options it forwards to the
fits (checked against the receiving function's signature)."""

from __future__ import annotations

from typing import Any, Mapping

from .._check import check_bool, check_int, check_keywords, check_mapping, check_number
from ..estimation.flow_fit import fit_road
from ..estimation.forwarded import keyed_errors
from ..estimation.image_fit import fit_image
from ..estimation.robust import check_fixed
from .contracts import check_flow_keys
from .estimators import FlowMotionEstimator, ImageMotionEstimator, check_estimator
from .gate import ImageGate

__all__ = ["MODES", "FITS", "FIT_RESERVED", "PHOTOMETRIC_RESERVED", "PHOTOMETRIC_DEFAULTS", "check_refine_options",
           "select_estimator"]

#: How the model flow and the prediction are fused.
MODES = ("replace", "confidence")
#: The older way to choose the estimator (``fit=``).
FITS = ("flow", "photometric")
#: What the refiner passes ``fit_road`` / ``fit_image`` itself (their positional inputs and the
#: model it chose; the images' range: they are on 0..255): refused in ``fit_options`` /
#: ``photometric_options`` by name, where Python would raise "got multiple values for argument"
#: (or fit_image would refuse the refiner's images) at the first call.
FIT_RESERVED = ("flow", "mask", "camera", "model", "fixed", "init")
PHOTOMETRIC_RESERVED = ("image1", "image2", "mask", "camera", "model", "fixed", "starts", "data_range")
#: ``fit="photometric"``'s options of ``fit_image`` (``photometric_options`` update them).
PHOTOMETRIC_DEFAULTS = {"prior": None, "bounds": None, "max_points": 40000, "gradient_fraction": 1.0, "min_size": 24,
                        "max_iter": 20, "highpass": None}


def check_refine_options(*, estimator: Any, gate: Any, mode: object, scale: object, min_pixels: object,
                         flow_keys: object, warn: object, fit: object, fit_roll: object, fit_pitch: object,
                         fit_options: object, photometric_options: object, starts: object = ()) -> tuple[tuple[str, ...], int]:
    """The options of :func:`refine_flow` and :class:`FreespaceRefiner` (named errors, quoting
    what came), checked before any work. Returns ``flow_keys`` as a tuple (read once: pass this on,
    not the caller's iterable, which may be a generator) and ``min_pixels`` as an int (a 0-d
    integer tensor read)."""
    if mode not in MODES:
        raise ValueError(f"mode: expected one of {MODES}, got {mode!r}")
    check_fixed(scale, "scale")  # (the refiner keeps it as a float)
    check_number(scale, "scale", positive=True)
    min_pixels = check_int(min_pixels, "min_pixels", minimum=1)
    flow_keys = check_flow_keys(flow_keys)
    check_bool(warn, "warn")
    check_bool(fit_roll, "fit_roll")
    check_bool(fit_pitch, "fit_pitch")
    if fit not in (None, *FITS):
        raise ValueError(f"fit: expected one of {FITS} or None, got {fit!r}")
    if estimator is not None and fit is not None:
        raise ValueError("fit: give an estimator or fit=, not both")
    check_estimator(estimator)
    if not isinstance(starts, (list, tuple)):
        raise TypeError(f"starts: expected a list of start candidates (dicts or fits), got {type(starts).__name__}")
    if isinstance(gate, str) and gate != "auto":
        raise ValueError(f"gate: expected an ImageGate, 'auto' or None, got {gate!r}")
    if not (gate is None or isinstance(gate, ImageGate) or isinstance(gate, str)):
        raise TypeError(f"gate: expected an ImageGate, 'auto' or None, got {gate!r}")
    # the options of the older fit= choice go to fit_road / fit_image with these set by the refiner
    check_keywords(check_mapping(fit_options, "fit_options"), "fit_options", fit_road, reserved=FIT_RESERVED)
    check_keywords(check_mapping(photometric_options, "photometric_options"), "photometric_options", fit_image,
                   reserved=PHOTOMETRIC_RESERVED)
    # and their values, as the estimators they build check them when made (a bad value was an error
    # only at the first call that estimated: a refiner given odometry ran on without a word)
    fixed = tuple(n for n, on in (("roll", fit_roll), ("pitch", fit_pitch)) if not on)
    if fit_options:
        with keyed_errors(fit_options, "fit_options"):  # (named as the caller gave them: not the refiner's scale)
            FlowMotionEstimator(model="paper", fixed=fixed, **fit_options)
    if photometric_options:
        with keyed_errors(photometric_options, "photometric_options"):
            ImageMotionEstimator(model="paper", fixed=fixed, **{**PHOTOMETRIC_DEFAULTS, **photometric_options})
    # and against the estimator they would go to, where the call's images do not choose it (one given,
    # or fit= set): a combination that does not fit raises when a refiner is made, not at its first call
    if estimator is not None or fit is not None:
        select_estimator(estimator, fit, None, fit_roll, fit_pitch, fit_options, photometric_options)
    return flow_keys, min_pixels


def select_estimator(estimator: Any, fit: str | None, images: Any, fit_roll: bool, fit_pitch: bool,
                     fit_options: Mapping[str, Any] | None, photometric_options: Mapping[str, Any] | None):
    """The road-motion estimator to use: the caller's; one built from the older ``fit=``
    options; or the default: the image estimator where there are images, else a fit to the
    prediction."""
    if fit not in (None, *FITS):
        raise ValueError(f"fit: expected one of {FITS} or None, got {fit!r}")
    # the older options apply to the estimator they build; set where another one runs, they
    # would be left aside silently
    chosen = "estimator" if estimator is not None else (fit or ("flow" if images is None else "images"))
    uses = {"fit_roll": ("flow", "photometric"), "fit_pitch": ("flow", "photometric"),
            "fit_options": ("flow",), "photometric_options": ("photometric",)}
    given = {"fit_roll": fit_roll, "fit_pitch": fit_pitch, "fit_options": bool(fit_options),
             "photometric_options": bool(photometric_options)}
    for name, applies in uses.items():
        if given[name] and chosen not in applies:
            where = {"estimator": "an estimator is given: set its own options",
                     "images": "the default image estimator runs (images given, fit=None): pass "
                               "estimator=ImageMotionEstimator(...) with its options",
                     "flow": "fit='flow' (or no images) fits the flow",
                     "photometric": "fit='photometric' takes photometric_options"}[chosen]
            raise ValueError(f"{name}: applies with fit={' or '.join(repr(a) for a in applies)}; here {where}")
    if estimator is not None:
        if fit is not None:
            raise ValueError("fit: give an estimator or fit=, not both")
        return check_estimator(estimator)
    fixed = tuple(n for n, on in (("roll", fit_roll), ("pitch", fit_pitch)) if not on)
    if fit == "flow" or (fit is None and images is None):
        return FlowMotionEstimator(model="paper", fixed=fixed, **dict(fit_options or {}))
    if fit == "photometric":  # the paper's model fitted to the images, started from the flow fit
        return ImageMotionEstimator(model="paper", fixed=fixed, **{**PHOTOMETRIC_DEFAULTS, **dict(photometric_options or {})})
    return ImageMotionEstimator()
