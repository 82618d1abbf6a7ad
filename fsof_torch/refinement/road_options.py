"""The values of the road detection's options (:func:`~fsof_torch.refinement.auto_road.detect_road`)
checked where no images are needed: by ``detect_road`` itself, and by the wrapper that passes
``road_options`` on (:class:`~fsof_torch.refinement.wrapped.FreespaceRefined`) when it is made, so
that a bad value is named before a network runs. What needs the images (the sizes the levels and
windows leave) or the camera (``min_height_m`` below it) is checked by the detection."""

from __future__ import annotations

import math
from typing import Any, Mapping

from .._check import check_bool, is_number, option_error, scalar

__all__ = ["SLOW_MAX_HEIGHT_M", "ROAD_VALUE_OPTIONS", "check_road_values"]

#: detect_road's default ``slow_max_height_m`` (metres), named in its error
SLOW_MAX_HEIGHT_M = 1.2
_INT_OPTIONS = ("level", "seed_level", "window", "height_window")
_FLAG_OPTIONS = ("refit", "edges", "follow_path")
#: detect_road's options whose values :func:`check_road_values` checks
ROAD_VALUE_OPTIONS = _INT_OPTIONS + ("seed_width_m", "seed_depth_m", "min_height_m", "max_height_m",
                                     "slow_max_height_m", "z", "min_misfit_px", "min_coverage") + _FLAG_OPTIONS


def check_road_values(options: Mapping[str, Any]) -> dict[str, Any]:
    """The values of ``options`` (every name of :data:`ROAD_VALUE_OPTIONS`, as ``detect_road``
    takes them) checked, with ``detect_road``'s errors: a ``TypeError`` for a value of the wrong
    type, a ``ValueError`` for one out of range, naming the option and quoting the value. A
    ``level`` of None (chosen from the images' size) is not checked. Returns them, in the same
    order, as ints (the levels and windows), floats and bools (the flags: True or False, nothing
    else), a 0-d tensor read as its number and None kept."""
    for name in _FLAG_OPTIONS:  # (before a 0-d tensor is read as its number: no flag, as detect_road takes them)
        check_bool(options[name], name)
    options = {k: scalar(v, k) for k, v in options.items()}  # (a 0-d tensor as its number: int or float)
    for name in ("level", "seed_level"):
        v = options[name]
        if (v is not None or name != "level") and (not is_number(v, integer=True) or v < 0):
            raise option_error(v, f"{name}: expected an int >= 0 (images averaged over 2**{name} pixels), got {v!r}",
                               integer=True)
    for name in ("window", "height_window"):
        v = options[name]
        if not is_number(v, integer=True) or v < 3 or v % 2 == 0:
            raise option_error(v, f"{name}: expected an odd int >= 3 (pixels at the working resolution), got {v!r}",
                               integer=True)
    for name in ("seed_width_m", "seed_depth_m", "min_height_m", "max_height_m", "z", "min_misfit_px"):
        v = options[name]
        if not is_number(v) or not (0 < v < math.inf):
            raise option_error(v, f"{name}: expected a finite number > 0, got {v!r}")
    if options["max_height_m"] < options["min_height_m"]:
        raise ValueError(f"max_height_m: expected >= min_height_m ({options['min_height_m']!r}), "
                         f"got {options['max_height_m']!r}")
    v = options["slow_max_height_m"]
    if v is not None and (not is_number(v) or not (v < math.inf) or not v >= options["max_height_m"]):
        raise option_error(v, f"slow_max_height_m: expected None or a finite number >= max_height_m "
                              f"({options['max_height_m']!r}; a max_height_m above the default {SLOW_MAX_HEIGHT_M} "
                              f"needs slow_max_height_m as large, or None), got {v!r}")
    v = options["min_coverage"]
    if not is_number(v) or not (0 <= v < 1):
        raise option_error(v, f"min_coverage: expected a fraction in [0, 1), got {v!r}")
    return {k: None if v is None else v if k in _FLAG_OPTIONS else int(v) if k in _INT_OPTIONS else float(v)
            for k, v in options.items()}
