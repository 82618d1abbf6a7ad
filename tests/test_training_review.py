"""Tests of the training modules' edge cases: the test net's correlation lookup at coarse levels
and its seed range, the options of the loss terms given as numpy or 0-d tensor numbers, the
smoothness of images with one direction only, losses without any term, the names of
CompositeLoss's terms, empty inputs to the stand-ins and which inputs of batch 1 broadcast."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fsof_torch.training.losses import (
    CompositeLoss,
    FreespaceFlowLoss,
    UnsupervisedFlowLoss,
    freespace_flow_loss,
    photometric_loss,
    sequence_weights,
    smoothness_loss,
    unsupervised_flow_loss,
)
from fsof_torch.training.standins import PtlflowRAFTStandIn, TorchvisionRAFTStandIn
from fsof_torch.training.testnet import TinyRAFT, _correlation_pyramid, _lookup


# -- the test net's correlation lookup -----------------------------------------------------------

def _bilinear_zero_outside(volume: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of ``volume`` (N, hl, wl) at (x, y) (N, k), reading 0 outside it."""
    N, hl, wl = volume.shape
    x0, y0 = x.floor(), y.floor()
    out = torch.zeros_like(x)
    for dx in (0, 1):
        for dy in (0, 1):
            xi, yi = x0 + dx, y0 + dy
            weight = (1 - (x - xi).abs()) * (1 - (y - yi).abs())
            inside = (xi >= 0) & (xi <= wl - 1) & (yi >= 0) & (yi <= hl - 1)
            idx = (yi.clamp(0, hl - 1) * wl + xi.clamp(0, wl - 1)).long()
            out = out + torch.where(inside, weight * volume.flatten(1).gather(1, idx), 0.0)
    return out


@pytest.mark.parametrize("h, w", [(5, 7), (8, 5), (6, 12)])
def test_lookup_window_is_centred_on_coords_over_two_to_the_level(h, w):
    """RAFT's CorrBlock samples level k around coords / 2**k. The lookup scaled x and y by wl / w:
    for a feature width not divisible by 2**k the window was off-centre, and y moved with the x
    ratio; a level of one row or column read its one value over the whole window (not zeros)."""
    g = torch.Generator().manual_seed(0)
    f1 = torch.randn(1, 8, h, w, generator=g, dtype=torch.float64)
    f2 = torch.randn(1, 8, h, w, generator=g, dtype=torch.float64)
    pyramid = _correlation_pyramid(f1, f2, 3)
    coords = torch.stack(torch.meshgrid(torch.arange(w, dtype=torch.float64), torch.arange(h, dtype=torch.float64),
                                        indexing="xy"))[None]
    coords = coords + torch.rand(1, 2, h, w, generator=g, dtype=torch.float64) * 4 - 2
    radius = 2
    out = _lookup(pyramid, coords, radius)
    d = torch.arange(-radius, radius + 1, dtype=torch.float64)
    dy, dx = torch.meshgrid(d, d, indexing="ij")  # window cells, x fastest
    cx, cy = coords[0, 0].reshape(-1, 1), coords[0, 1].reshape(-1, 1)
    cells = (2 * radius + 1) ** 2
    for level, corr in enumerate(pyramid):
        ref = _bilinear_zero_outside(corr[:, 0], cx / 2**level + dx.reshape(1, -1), cy / 2**level + dy.reshape(1, -1))
        got = out[0, level * cells:(level + 1) * cells].permute(1, 2, 0).reshape(h * w, cells)
        torch.testing.assert_close(got, ref, rtol=1e-9, atol=1e-9, msg=f"level {level}")


@pytest.mark.parametrize("seed", [-1, 2**64, -(2**63)])
def test_testnet_seed_out_of_range_is_named(seed):
    """2**64 raised an unnamed overflow from torch.manual_seed; -1 gave the net of 2**64 - 1."""
    with pytest.raises(ValueError, match=rf"^seed: expected an int with 0 <= seed < 2\*\*64, got {seed}$"):
        TinyRAFT(seed=seed)


def test_testnet_largest_seed_is_accepted():
    a, b = TinyRAFT(seed=2**64 - 1), TinyRAFT(seed=0)
    assert not torch.equal(a.fnet.out.weight, b.fnet.out.weight)


# -- loss options given as numpy or 0-d tensor numbers -------------------------------------------

@pytest.mark.parametrize("gamma", [np.float32(0.5), np.float64(0.5), torch.tensor(0.5)])
def test_gamma_accepts_numpy_and_0d_tensor_numbers(gamma):
    """gamma was refused unless a Python int or float ('expected 0 < gamma <= 1, got 0.5')."""
    assert sequence_weights(np.int64(3), gamma) == pytest.approx([0.25, 0.5, 1.0])
    g = torch.Generator().manual_seed(0)
    image1 = torch.rand(1, 3, 8, 10, generator=g, dtype=torch.float64) * 255
    image2 = torch.rand(1, 3, 8, 10, generator=g, dtype=torch.float64) * 255
    flows = [torch.randn(1, 2, 8, 10, generator=g, dtype=torch.float64) for _ in range(2)]
    expected = unsupervised_flow_loss(flows, image1, image2, gamma=0.5)
    torch.testing.assert_close(UnsupervisedFlowLoss(gamma=gamma)(flows, image1, image2), expected)
    road = torch.ones(1, 1, 8, 10, dtype=torch.bool)
    from fsof_torch.geometry.camera import Camera

    camera = Camera(torch.tensor([[10.0, 0, 5], [0, 10.0, 2], [0, 0, 1]], dtype=torch.float64), 1.65)
    odometry = {"x_d": 0.0, "z_d": 1.0, "yaw": 0.0}
    torch.testing.assert_close(FreespaceFlowLoss(gamma=gamma, scale=torch.tensor(2.0))(flows, road, camera, odometry),
                               freespace_flow_loss(flows, road, camera, odometry, gamma=0.5, scale=2.0))
    assert FreespaceFlowLoss(scale=np.float32(2.0)).options["scale"] == 2.0


@pytest.mark.parametrize("gamma, error, match", [
    (0.0, ValueError, r"^gamma: expected 0 < gamma <= 1, got 0\.0$"),
    (np.float32(1.5), ValueError, r"^gamma: expected 0 < gamma <= 1, got np\.float32\(1\.5\)$"),
    (float("nan"), ValueError, r"^gamma: expected 0 < gamma <= 1, got nan$"),
    ("0.8", TypeError, r"^gamma: expected a number, got str '0\.8'$"),
    (True, TypeError, r"^gamma: expected a number, got bool True$"),
])
def test_gamma_out_of_range_or_not_a_number(gamma, error, match):
    with pytest.raises(error, match=match):
        UnsupervisedFlowLoss(gamma=gamma)
    with pytest.raises(error, match=match):
        sequence_weights(2, gamma)


def test_sequence_weights_n_is_an_int_at_least_one():
    with pytest.raises(ValueError, match=r"^n: expected an int >= 1, got 0$"):
        sequence_weights(0, 0.8)
    with pytest.raises(TypeError, match=r"^n: expected an int, got float 2\.0$"):
        sequence_weights(2.0, 0.8)


@pytest.mark.parametrize("scale", [torch.tensor(0.0), np.float64(-1.0), np.float32("inf")])
def test_scale_numpy_and_tensor_values_are_range_checked(scale):
    with pytest.raises(ValueError, match=r"^scale: expected a finite residual scale > 0 px, got "):
        FreespaceFlowLoss(scale=scale)


# -- smoothness of images with differences in one direction only -----------------------------------

@pytest.mark.parametrize("order, size, along", [(1, (1, 10), "x"), (2, (2, 10), "x"), (1, (9, 1), "y"),
                                                (2, (9, 2), "y")])
def test_smoothness_averages_only_the_directions_with_differences(order, size, along):
    """An image of one row (order 1) or two rows (order 2) has no y differences; the missing
    direction was averaged in as 0, halving the term."""
    g = torch.Generator().manual_seed(0)
    flow = torch.randn(1, 2, *size, generator=g, dtype=torch.float64)
    image = torch.zeros(1, 3, *size, dtype=torch.float64)  # flat: every edge weight is 1
    dim = -1 if along == "x" else -2
    diff = torch.diff(flow, n=order, dim=dim)
    torch.testing.assert_close(smoothness_loss(flow, image, order=order), diff.abs().mean())


def test_smoothness_of_an_image_without_differences_is_zero_with_a_gradient():
    flow = torch.randn(1, 2, 1, 1, dtype=torch.float64, requires_grad=True)
    value = smoothness_loss(flow, torch.zeros(1, 3, 1, 1, dtype=torch.float64), order=1)
    assert value.item() == 0.0
    value.backward()
    assert torch.equal(flow.grad, torch.zeros_like(flow))


# -- losses without any term ---------------------------------------------------------------------

def test_photometric_with_all_weights_zero_keeps_the_graph():
    """All weights 0 gave a constant outside the graph: backward() raised."""
    image = torch.rand(2, 3, 8, 8, generator=torch.Generator().manual_seed(0)) * 255
    flow = torch.randn(2, 2, 8, 8, generator=torch.Generator().manual_seed(1), requires_grad=True)
    value = photometric_loss(image, image, flow, l1_weight=0, ssim_weight=0)
    assert value.requires_grad and value.item() == 0.0
    value.backward()
    assert torch.equal(flow.grad, torch.zeros_like(flow))
    per_sample = photometric_loss(image, image, flow, l1_weight=0, ssim_weight=0, reduction="none")
    assert per_sample.shape == (2,) and per_sample.requires_grad and torch.equal(per_sample, torch.zeros(2))


# -- CompositeLoss term names --------------------------------------------------------------------

class _Scaled(torch.nn.Module):
    """A module term with a parameter: its state_dict key shows where it is stored."""

    def __init__(self, factor: float) -> None:
        super().__init__()
        self.factor = torch.nn.Parameter(torch.tensor(factor))

    def forward(self, flows):
        return self.factor * flows.sum()


@pytest.mark.parametrize("name", ["values", "items", "keys", "update", "photo.l1", "", "training", 3])
def test_composite_module_terms_take_any_name(name):
    """A module term named like a ModuleDict attribute, with a '.', or empty raised a raw KeyError
    from nn.ModuleDict (a function term of the same name worked)."""
    loss = CompositeLoss({name: (2.0, _Scaled(3.0)), "plain": (1.0, _Scaled(5.0))})
    total, values = loss(torch.ones(1, 2, 2, 2))
    assert list(values) == [name, "plain"]
    assert values[name].item() == 24.0 and values["plain"].item() == 40.0 and total.item() == 88.0
    assert list(loss.state_dict()) == ["terms._term0.factor", "terms.plain.factor"]


def test_composite_valid_names_keep_their_state_dict_keys():
    loss = CompositeLoss({"a": (1.0, _Scaled(1.0)), "_term2": (1.0, _Scaled(2.0)), "b.c": (1.0, _Scaled(3.0)),
                          "f": (1.0, lambda flows: flows.sum())})
    assert list(loss.state_dict()) == ["terms.a.factor", "terms._term2.factor", "terms.__term2.factor"]
    total, values = loss(torch.ones(1, 2, 1, 1))
    assert {k: v.item() for k, v in values.items()} == {"a": 2.0, "_term2": 4.0, "b.c": 6.0, "f": 2.0}


# -- stand-ins: empty inputs ---------------------------------------------------------------------

@pytest.mark.parametrize("shape, letter", [((0, 2, 3, 16, 16), "B"), ((1, 2, 3, 0, 16), "H"), ((1, 2, 3, 16, 0), "W")])
def test_ptlflow_standin_empty_images_are_named(shape, letter):
    """An empty batch or side raised amin()'s raw 'Expected reduction dim' RuntimeError."""
    net = PtlflowRAFTStandIn(iters=1).eval()
    with pytest.raises(ValueError, match=rf"^inputs\['images'\]: expected shape \(B, 2, 3, H, W\) with {letter} >= 1, "
                                         rf"got \({', '.join(map(str, shape))}\)$"):
        net({"images": torch.zeros(shape)})


@pytest.mark.parametrize("shape, letter", [((0, 3, 16, 16), "B"), ((1, 3, 0, 16), "H"), ((1, 3, 16, 0), "W")])
def test_torchvision_standin_empty_images_are_named(shape, letter):
    net = TorchvisionRAFTStandIn().eval()
    with pytest.raises(ValueError, match=rf"^image1: expected shape \(B, 3, H, W\) with {letter} >= 1"):
        net(torch.zeros(shape), torch.zeros(shape))


# -- which batch-1 inputs broadcast (docs/conventions.md) -------------------------------------------

def test_conventions_state_which_batch_1_inputs_broadcast():
    """docs/conventions.md said "a batch of 1 broadcasts against B" for every core function, but
    image, flow and mask tensors must share B: what it says now is what the functions do."""
    from pathlib import Path

    from fsof_torch import Camera, fit_road, refine_flow, road_flow

    text = " ".join((Path(__file__).resolve().parents[1] / "docs" / "conventions.md").read_text().split())
    assert "a batch of 1 broadcasts against B." not in text
    assert "Per-frame scalars and cameras of batch 1 broadcast against B; image, flow and mask tensors must share B" in text
    assert ("the road mask of the road fits (`fit_road`, `fit_image` and their wrappers; `fit_road`'s `valid` too), "
            "of the refiner and of `fuse_flow` (its `mask` and `flow_model`)") in text

    cam = Camera(torch.tensor([[60.0, 0.0, 40.0], [0.0, 60.0, 18.0], [0.0, 0.0, 1.0]], dtype=torch.float64), 1.65)
    flow1, road1 = road_flow(cam, {"z_d": 1.0}, (24, 80))  # a camera and a mask of batch 1
    flows = flow1.expand(2, 2, 24, 80)
    image = torch.rand(2, 3, 24, 80, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 255
    # the camera and per-frame scalars of batch 1 broadcast ...
    odometry = {"x_d": 0.0, "z_d": torch.ones(1, dtype=torch.float64), "yaw": torch.zeros(2, dtype=torch.float64)}
    assert freespace_flow_loss(flows, road1.expand(2, 1, 24, 80), cam, odometry).item() == pytest.approx(0.0, abs=1e-12)
    # ... a mask of batch 1 against B = 2 does not, in the losses
    with pytest.raises(ValueError, match=r"road: expected shape \(B, 1, H, W\) with B=2"):
        freespace_flow_loss(flows, road1, cam, odometry)
    with pytest.raises(ValueError, match=r"mask: expected shape \(B, 1, H, W\) with B=2"):
        photometric_loss(image, image, flows, road1)
    # the road fits and the refiner take one mask for every frame
    assert fit_road(flows, road1, cam).flow.shape == (2, 2, 24, 80)
    assert refine_flow(flows, road1, cam, {"x_d": 0.0, "z_d": 1.0, "yaw": 0.0}, gate=None).flow.shape == (2, 2, 24, 80)
