"""Tests of fsof_torch.training.standins: the stand-ins check their own arguments and ranges, by
their own names, before the TinyRAFT inside sees them (the contracts themselves are tested in
test_contracts.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

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


def test_on_the_meta_device_both_contracts_give_their_shapes_through_the_wrapper():
    """A meta tensor has no values to check the range of: the stand-ins skip that check there, as
    the package's value checks do, so FreespaceRefined infers shapes on meta around them with a
    model's full motion and gate=None (docs/reliability.md); their range check read a meta value."""
    import fsof_torch as fs
    from fsof_torch.refinement.contracts import ptlflow_inputs

    cam = fs.Camera(torch.tensor([[20.0, 0, 11.5], [0, 20.0, 4.0], [0, 0, 1]]), 1.65).to("meta")
    road = torch.ones(1, 1, 13, 21, dtype=torch.bool, device="meta")
    motion = {"model": "plane", "x_d": 0.0, "z_d": 1.0, "yaw": 0.0}
    refiner = fs.FreespaceRefiner(gate=None)
    rgb = torch.rand(1, 3, 13, 21, generator=torch.Generator().manual_seed(0)) * 255
    tv = fs.FreespaceRefined(TorchvisionRAFTStandIn(), refiner, pad=fs.InputPadder(8), image_range=(-1, 1)).to("meta")
    image = (rgb / 127.5 - 1).to("meta")
    with torch.no_grad():
        flows = tv(image, image, camera=cam, mask=road, odometry=motion, num_flow_updates=2)
    assert [(f.device.type, tuple(f.shape)) for f in flows] == [("meta", (1, 2, 13, 21))] * 2
    pl = fs.FreespaceRefined(PtlflowRAFTStandIn(iters=2).eval(), refiner, pad=fs.InputPadder(8)).to("meta")
    inputs = {"images": ptlflow_inputs(rgb, rgb)["images"].to("meta")}
    with torch.no_grad():
        out = pl(inputs, camera=cam, mask=road, odometry=motion)
    assert {k: (v.device.type, tuple(v.shape)) for k, v in out.items()} == {
        "flows": ("meta", (1, 1, 2, 13, 21)), "flow_small": ("meta", (1, 2, 2, 3))}


def test_ptlflow_training_mode_returns_flow_preds_as_ptlflows_raft():
    """ptlflow's RAFT returns {"flows", "flow_preds"} in training mode (every iteration's flow at
    the input size; "flow_small" only in eval mode): the stand-in returned its eval dict in both
    modes, so code tested with it that read "flow_small" in training, or "flow_preds", would
    fail on ptlflow's network."""
    from fsof_torch import TinyRAFT

    g = torch.Generator().manual_seed(3)
    images = torch.rand(1, 2, 3, 13, 21, generator=g)
    net = PtlflowRAFTStandIn(seed=0, iters=3)
    assert net.training
    with torch.no_grad():
        out = net({"images": images})
        # by hand: 13 x 21 padded to 16 x 24 as (left, right, top, bottom) = (1, 2, 1, 2), BGR -> RGB 0..255
        rgb = F.pad(images[0].flip(1) * 255.0, (1, 2, 1, 2), mode="replicate")
        expected = [f[..., 1:14, 1:22] for f in TinyRAFT(seed=0, iters=3).train()(rgb[:1], rgb[1:])]
        evaluated = net.eval()({"images": images})
    assert sorted(out) == ["flow_preds", "flows"]
    assert len(out["flow_preds"]) == 3 and all(f.shape == (1, 2, 13, 21) for f in out["flow_preds"])
    for got, want in zip(out["flow_preds"], expected):
        torch.testing.assert_close(got, want, atol=1e-5, rtol=0)
    assert torch.equal(out["flows"], out["flow_preds"][-1][:, None])
    # eval mode: the same estimate, with flow_small on the padded 1/8 grid (2 x 3) in its pixels
    assert sorted(evaluated) == ["flow_small", "flows"] and evaluated["flow_small"].shape == (1, 2, 2, 3)
    torch.testing.assert_close(evaluated["flows"], out["flows"], atol=1e-5, rtol=0)


def test_torchvision_overshoot_the_wrapper_lets_through_runs():
    """FreespaceRefined(image_range=(-1, 1)) lets values up to 1 % of the range's width beyond it
    through (a resize's overshoot), and torchvision's RAFT runs on them, but the stand-in raised
    "expected RGB values in [-1, 1]": it takes them now (clipped for TinyRAFT), and still refuses
    values beyond that."""
    import fsof_torch as fs
    from fsof_torch.data.scene import render_pair

    p = render_pair("default", 0, size=(16, 24))
    im1, im2 = (p[k][None] / 127.5 - 1 for k in ("image1", "image2"))
    over = im1.clone()
    over[0, 0, 3, 4], over[0, 2, 5, 6] = 1.015, -1.02
    net = TorchvisionRAFTStandIn().eval()
    with torch.no_grad():
        flows = net(over, im2, num_flow_updates=2)
        expected = net(over.clamp(-1, 1), im2, num_flow_updates=2)
        assert torch.equal(flows[-1], expected[-1])
        model = fs.FreespaceRefined(net, fs.FreespaceRefiner(gate=None), image_range=(-1, 1))
        odo = {k: float(p["odometry"][k]) for k in ("x_d", "z_d", "yaw")}
        out = model(over, im2, camera=p["camera"].to(torch.float32), mask=p["road"][None], odometry=odo)
    assert len(out) == 4 and bool(torch.isfinite(out[-1]).all())
    over[0, 1, 7, 8] = 1.03
    with pytest.raises(ValueError, match=r"^image1, image2: expected RGB values in \[-1, 1\], got \[-1\.02, 1\.03\]$"):
        net(over, im2)
