"""Warnings that point at the user's line: the first caller outside fsof_torch and torch.

A fixed ``stacklevel`` names the right line on one path only: the refiner warns from inside
``refine_flow``, which is reached directly, through its ``nn.Module`` twin (whose call runs
through two frames of torch's ``Module.__call__``) or through ``mask="auto"``'s detection; a
loss from a function or its module. :func:`warn_user` counts the frames instead.
"""

from __future__ import annotations

import os
import sys
import warnings

import torch

__all__ = ["FreespaceWarning", "warn_user"]

# (the paths as the modules were loaded: code objects carry the same prefix as __file__)
_LIBRARY = (os.path.dirname(__file__) + os.sep, os.path.dirname(torch.__file__) + os.sep)


class FreespaceWarning(RuntimeWarning):
    """The category of fsof_torch's own warnings (a sample left unrefined, non-finite predicted
    pixels left out, metrics over nothing counted). A ``RuntimeWarning``, which filters on that
    category still catch; and one a filter can name alone,
    ``warnings.filterwarnings("ignore", category=fsof_torch.FreespaceWarning)``, without silencing
    NumPy's or torch's. A filter on the module (``module="fsof_torch"``) catches none: each warning is
    attributed to the caller's line."""


def warn_user(message: str, category: type[Warning] = FreespaceWarning) -> None:
    """``warnings.warn(message, category)`` attributed to the first frame outside fsof_torch and
    torch (the filename and line a warning filter and the printed warning show): the caller's
    line, however the library was reached."""
    frame, level = sys._getframe(1), 2  # (level 1 is this function; 2 its caller)
    while frame is not None and frame.f_code.co_filename.startswith(_LIBRARY):
        frame, level = frame.f_back, level + 1
    warnings.warn(message, category, stacklevel=level)
