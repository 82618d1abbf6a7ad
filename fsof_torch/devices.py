"""Devices checked where they come in: a ``device`` argument (the functions that make tensors
from nothing: a pixel grid, a colour wheel, a metric accumulator's sums), and the devices of the
tensors a function takes. Torch's own errors came from inside, naming no argument (a
RuntimeError for ``"gpu"``, an AssertionError for ``"cuda"`` on a CPU build); these name it.

The validation helpers import these (``fsof_torch._check`` holds them all); this module imports
nothing of the package.
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping

import torch
from torch import Tensor

__all__ = ["check_device", "check_has_values", "check_same_device", "to_device"]

_EXPECTED = "expected None, a torch.device, a device string such as 'cpu' or 'cuda:0' or a device index"


def check_device(device: object, name: str = "device") -> torch.device | None:
    """``device`` as a ``torch.device`` that torch can place tensors on (None stays None: the
    default device): a ``torch.device``, a device string such as ``"cuda:0"`` or a device index.

    A ValueError names ``name`` and quotes what came for an unknown string (``"gpu"``), an index
    where there is no accelerator, or a device torch names but cannot reach (``"cuda"`` on a CPU
    build or without a driver: found by placing an empty tensor there, which allocates nothing;
    not while ``torch.compile`` traces); a TypeError for anything else (a float, or a bool, which
    torch would read as index 1). The meta device is a device (shapes without values): a caller
    that needs values refuses it itself."""
    if device is None:
        return None
    given = device
    if not isinstance(device, torch.device):
        try:
            if isinstance(device, bool):
                raise TypeError("a bool")
            device = torch.device(device)
        except (RuntimeError, TypeError) as exc:
            # (an index, which torch takes as the accelerator's, was called the wrong type where there is none)
            index = not isinstance(given, bool) and isinstance(given, numbers.Integral)
            error = ValueError if isinstance(given, str) or index else TypeError
            raise error(f"{name}: {_EXPECTED}, got {given!r}" + (f" ({exc})" if index else "")) from None
    if device.type not in ("cpu", "meta") and not torch.compiler.is_compiling():
        try:
            torch.empty(0, device=device)
        except (RuntimeError, AssertionError) as exc:
            # (a CUDA device that torch names but cannot reach: a CUDA build without a driver, a CPU build)
            raise ValueError(f"{name}: {_EXPECTED} torch can place tensors on, got {given!r} "
                             f"({str(exc).strip().splitlines()[0]})") from None
    return device


def check_has_values(x: object, name: str, purpose: str = "to write or convert") -> None:
    """Writers, readers and data-dependent estimators need values: a tensor on the meta device
    (shapes only) raises a ValueError that says what needs them (``purpose``)."""
    if isinstance(x, Tensor) and x.device.type == "meta":
        raise ValueError(f"{name}: a tensor on the meta device has shapes but no values {purpose}; "
                         f"move it to a real device first")


def check_same_device(named: Mapping[str, Tensor | None]) -> None:
    """The tensors of ``named`` (None left out) on the first one's device: a ValueError names the
    first that is not (torch's own error would come from inside, naming neither)."""
    items = [(name, t) for name, t in named.items() if t is not None]
    for name, t in items[1:]:
        if t.device != items[0][1].device:
            raise ValueError(f"{name}: expected the device of {items[0][0]} ({items[0][1].device}), got {t.device}")


def to_device(x: Tensor, name: str, device: torch.device | str) -> Tensor:
    """``x`` moved to ``device``, the computation's (where a function takes an argument from
    another device); a ValueError naming it where it has no values to move (the meta device)."""
    if x.device.type == "meta" and torch.device(device).type != "meta":
        raise ValueError(f"{name}: a tensor on the meta device has no values to move to {device} (the "
                         f"computation's device); give it on {device}")
    return x.to(device)
