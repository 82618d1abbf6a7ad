"""Tests of fsof_torch.devices: a ``device`` argument checked where it comes in, and named."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from fsof_torch import FlowMetricAccumulator, pixel_grid
from fsof_torch.devices import check_device
from fsof_torch.evaluation.visualize import make_colorwheel

EXPECTED = r"^device: expected None, a torch.device, a device string such as 'cpu' or 'cuda:0' or a device index"

MAKERS = {
    "pixel_grid": lambda device: pixel_grid((2, 3), torch.float32, device=device),
    "make_colorwheel": lambda device: make_colorwheel(device=device),
    "FlowMetricAccumulator": lambda device: FlowMetricAccumulator(device=device).state,
}


def test_check_device_takes_what_torch_places_tensors_on():
    assert check_device(None) is None
    for device in ("cpu", torch.device("cpu"), "meta", torch.device("meta")):
        assert check_device(device) == torch.device(device)
    with pytest.raises(ValueError, match=r"^flow_device: expected None, .*, got 'gpu'$"):
        check_device("gpu", "flow_device")


@pytest.mark.parametrize("maker", list(MAKERS))
def test_a_device_typo_is_a_value_error_naming_device(maker):
    """``pixel_grid(..., device="gpu")`` and ``make_colorwheel(device="gpu")`` raised torch's
    RuntimeError ('Expected one of cpu, cuda, ... device type at start of device string: gpu'),
    naming no argument, and a float or a bool torch's TypeError from ``arange`` or ``to``; the
    accumulator's check, which named ``device``, serves them all."""
    make = MAKERS[maker]
    with pytest.raises(ValueError, match=EXPECTED + r", got 'gpu'$"):
        make("gpu")
    for wrong in (1.5, True):
        with pytest.raises(TypeError, match=EXPECTED + rf", got {wrong}$"):
            make(wrong)
    with pytest.raises(ValueError, match=EXPECTED + r", got -1 \(.*negative"):
        make(-1)
    assert make("cpu").device == make(None).device == torch.device("cpu")


@pytest.mark.parametrize("maker", list(MAKERS))
def test_a_device_torch_cannot_reach_is_a_value_error_naming_device(maker):
    """``device=torch.device("cuda")`` without CUDA (a CPU build: torch's AssertionError 'Torch
    not compiled with CUDA enabled'; a CUDA build without a driver: its RuntimeError) and an index
    without an accelerator are ValueErrors naming ``device``, with torch's reason."""
    make = MAKERS[maker]
    if torch.cuda.is_available():
        assert make(torch.device("cuda")).device.type == "cuda"
        return
    for device in (torch.device("cuda"), "cuda", "cuda:0"):
        with pytest.raises(ValueError, match=EXPECTED + rf" torch can place tensors on, got {re.escape(repr(device))} "
                                                        r"\(.+\)$"):
            make(device)
    if not torch.accelerator.is_available():
        # (a CPU build refuses the index itself; a CUDA build without a driver takes it as cuda:N,
        # which it names but cannot reach)
        for index in (0, np.int64(1)):
            with pytest.raises(ValueError, match=EXPECTED + r"( torch can place tensors on)?, got (0|np\.int64\(1\)) "
                                                            r"\(.+\)$"):
                make(index)


def test_the_meta_device_gives_shapes():
    """The meta device is a device: a grid or a wheel there has its shape (an accumulator, which
    sums values, refuses it itself)."""
    assert pixel_grid((2, 3), torch.float64, device="meta").shape == (3, 6)
    assert make_colorwheel(device=torch.device("meta")).shape == (55, 3)
    with pytest.raises(ValueError, match=r"^device: an accumulator sums values"):
        FlowMetricAccumulator(device="meta")
