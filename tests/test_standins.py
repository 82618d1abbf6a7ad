"""Tests of fsof_torch.training.standins: the stand-ins check their own arguments and ranges, by
their own names, before the TinyRAFT inside sees them (the contracts themselves are tested in
test_contracts.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fsof_torch.training.standins import PtlflowRAFTStandIn, TorchvisionRAFTStandIn


def _rgb(seed: int = 0) -> torch.Tensor:
    """(1, 3, 16, 24) RGB in [-1, 1], torchvision's convention."""
    return torch.rand(1, 3, 16, 24, generator=torch.Generator().manual_seed(seed)) * 2 - 1


@pytest.mark.parametrize("n, error, match", [
    (0, ValueError, r"^num_flow_updates: expected an int >= 1, got 0$"),
    (-1, ValueError, r"^num_flow_updates: expected an int >= 1, got -1$"),
    (2.5, TypeError, r"^num_flow_updates: expected an int, got float 2.5$"),
    (True, TypeError, r"^num_flow_updates: expected an int, got bool True$"),
    ("3", TypeError, r"^num_flow_updates: expected an int, got str '3'$"),
])
def test_torchvision_num_flow_updates_is_checked_by_its_own_name(n, error, match):
    """The error named TinyRAFT's 'iters', an argument the caller never passed."""
    net = TorchvisionRAFTStandIn().eval()
    with pytest.raises(error, match=match), torch.no_grad():
        net(_rgb(0), _rgb(1), num_flow_updates=n)


def test_torchvision_num_flow_updates_gives_that_many_flows():
    net = TorchvisionRAFTStandIn().eval()
    with torch.no_grad():
        flows = net(_rgb(0), _rgb(1), num_flow_updates=1)
    assert len(flows) == 1 and flows[0].shape == (1, 2, 16, 24)


def test_torchvision_default_update_count_differs_from_torchvision_and_says_so():
    """The module said torchvision's contract was reproduced exactly, yet num_flow_updates
    defaults to 4 where torchvision's RAFT.forward defaults to 12: the difference is stated."""
    import inspect

    from fsof_torch.training import standins

    assert inspect.signature(TorchvisionRAFTStandIn.forward).parameters["num_flow_updates"].default == 4
    for doc in (standins.__doc__, TorchvisionRAFTStandIn.__doc__):
        text = " ".join(doc.split())
        assert "num_flow_updates=12" in text and "4" in text
    with torch.no_grad():
        assert len(TorchvisionRAFTStandIn().eval()(_rgb(0), _rgb(1))) == 4


def test_numpy_integers_are_accepted():
    """np.int64 counts were refused: num_flow_updates was passed on unconverted and TinyRAFT
    refused it under the name 'iters'; PtlflowRAFTStandIn(iters=np.int64(2)) likewise."""
    net = TorchvisionRAFTStandIn().eval()
    with torch.no_grad():
        flows = net(_rgb(0), _rgb(1), num_flow_updates=np.int64(2))
        expected = net(_rgb(0), _rgb(1), num_flow_updates=2)
    assert len(flows) == 2 and torch.equal(flows[-1], expected[-1])
    assert PtlflowRAFTStandIn(iters=np.int64(2)).net.iters == 2


@pytest.mark.parametrize("which", ["image1", "image2"])
def test_torchvision_nan_pixels_are_refused_in_either_image(which):
    """Python's min(lo1, nan) is lo1: a NaN in image2 passed the range check (TinyRAFT then raised
    about values on 0..255, a range the caller never used)."""
    net = TorchvisionRAFTStandIn().eval()
    images = {"image1": _rgb(0), "image2": _rgb(1)}
    images[which][0, 1, 2, 3] = float("nan")
    with pytest.raises(ValueError, match=r"^image1, image2: expected RGB values in \[-1, 1\], got \[nan, nan\]$"):
        net(images["image1"], images["image2"])


def test_torchvision_out_of_range_quotes_the_range():
    net = TorchvisionRAFTStandIn().eval()
    bright = _rgb(1) * 0 + 2.5
    with pytest.raises(ValueError, match=r"expected RGB values in \[-1, 1\], got \[-0\.\d+, 2\.5\]$"):
        net(_rgb(0), bright)


@pytest.mark.parametrize("fill, got", [(float("nan"), r"\[nan, nan\]"), (255.0, r"\[0, 255\]"),
                                       (-0.5, r"\[-0\.5, 1\]")])
def test_ptlflow_range_error_quotes_the_range_that_came(fill, got):
    """The message said only 'expected BGR values in [0, 1]', not what came."""
    net = PtlflowRAFTStandIn(iters=2).eval()
    images = torch.zeros(1, 2, 3, 16, 16)
    images[0, 0, 0, 0, 0] = 1.0
    images[0, 1, 2, 5, 5] = fill
    with pytest.raises(ValueError, match=rf"^inputs\['images'\]: expected BGR values in \[0, 1\], got {got}$"):
        net({"images": images})
