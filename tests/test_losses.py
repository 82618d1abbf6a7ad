"""Tests of the training losses: unsupervised (photometric + smoothness + occlusion) and freespace."""

from __future__ import annotations

import math

import pytest
import torch

from fsof_torch.geometry.camera import Camera
from fsof_torch.geometry.road_flow import displacement_flow
from fsof_torch.training.losses import (
    CompositeLoss,
    FreespaceFlowLoss,
    UnsupervisedFlowLoss,
    forward_backward_mask,
    freespace_flow_loss,
    photometric_loss,
    sequence_weights,
    smoothness_loss,
    unsupervised_flow_loss,
)

H, W = 48, 80


def _camera(dtype=torch.float64) -> Camera:
    K = torch.tensor([[60.0, 0.0, 40.0], [0.0, 60.0, 18.0], [0.0, 0.0, 1.0]], dtype=dtype)
    return Camera(K, 1.65)


def _textured(B: int, dtype=torch.float64, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(B, 3, H // 4, W // 4, generator=g, dtype=dtype)
    return torch.nn.functional.interpolate(x, size=(H, W), mode="bilinear", align_corners=True) * 255


def _shifted_pair(B: int, shift: int = 2, dtype=torch.float64):
    """image2 = image1 moved `shift` px to the right, so the true flow is (+shift, 0)."""
    image1 = _textured(B, dtype)
    image2 = torch.roll(image1, shifts=shift, dims=3)
    flow = torch.zeros(B, 2, H, W, dtype=dtype)
    flow[:, 0] = shift
    return image1, image2, flow


def _odometry(B: int):
    return {"x_d": torch.zeros(B, dtype=torch.float64), "z_d": torch.full((B,), 1.0, dtype=torch.float64),
            "yaw": torch.zeros(B, dtype=torch.float64)}


# -- smoke / feature -----------------------------------------------------------------------------

def test_sequence_weights_raft():
    assert sequence_weights(3, 0.8) == pytest.approx([0.64, 0.8, 1.0])
    with pytest.raises(ValueError, match="gamma: expected 0 < gamma <= 1"):
        sequence_weights(3, 0.0)


def test_photometric_true_flow_beats_zero_flow():
    image1, image2, flow = _shifted_pair(2)
    right = photometric_loss(image1, image2, flow, reduction="none")
    wrong = photometric_loss(image1, image2, torch.zeros_like(flow), reduction="none")
    assert right.shape == (2,)
    assert (right < 1e-6).all() and (wrong > 0.01).all()


def test_photometric_l1_matches_hand_computation():
    image1, image2, flow = _shifted_pair(1)
    flow0 = torch.zeros_like(flow)
    got = photometric_loss(image1, image2, flow0, l1_weight=1.0, ssim_weight=0.0)
    want = ((image1 - image2).abs().mean(dim=1) / 255).mean()
    torch.testing.assert_close(got, want)


def test_smoothness_zero_for_affine_flow_second_order():
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64),
                          indexing="ij")
    flow = torch.stack([0.1 * u + 0.2 * v, -0.05 * u]).unsqueeze(0)
    image = _textured(1)
    assert smoothness_loss(flow, image, order=2) == pytest.approx(0.0, abs=1e-12)
    assert smoothness_loss(flow, image, order=1) > 0


def test_smoothness_hand_value_first_order_flat_image():
    flow = torch.zeros(1, 2, 4, 5, dtype=torch.float64)
    flow[0, 0, :, 3:] = 1.0  # one vertical step of 1 px in u
    image = torch.full((1, 3, 4, 5), 100.0, dtype=torch.float64)
    # x: 4 of 4*4 differences are 1 over 2 channels -> 4/16/2; y: 0; mean of the two directions
    assert smoothness_loss(flow, image, order=1).item() == pytest.approx(4 / 16 / 2 / 2)


def test_forward_backward_mask_consistent_and_occluded():
    _, _, flow = _shifted_pair(1)
    visible = forward_backward_mask(flow, -flow)
    assert visible.dtype == torch.bool and visible.shape == (1, 1, H, W)
    assert visible[..., : W - 2].all() and not visible[..., W - 2:].any()  # right border leaves the image
    assert not forward_backward_mask(flow, flow)[..., : W - 2].any()  # |2 f|² = 16 > 0.01*8 + 0.5


def test_unsupervised_sequence_weighting():
    image1, image2, flow = _shifted_pair(1)
    f0, f1 = torch.zeros_like(flow), flow + 0.3
    one = [unsupervised_flow_loss(f, image1, image2) for f in (f0, f1)]
    both = unsupervised_flow_loss([f0, f1], image1, image2, gamma=0.5)
    torch.testing.assert_close(both, 0.5 * one[0] + one[1])


def test_unsupervised_symmetric_with_backward():
    image1, image2, flow = _shifted_pair(2)
    value = unsupervised_flow_loss([flow], image1, image2, flows_backward=[-flow], reduction="none")
    assert value.shape == (2,) and (value < 1e-6).all()


def test_freespace_zero_at_model_flow_positive_elsewhere():
    cam = _camera()
    model, valid = displacement_flow(cam, 0.0, 1.0, 0.0, (H, W))
    road = valid.clone()
    road[..., : H // 2, :] = False
    odo = {"x_d": 0.0, "z_d": 1.0, "yaw": 0.0}
    assert freespace_flow_loss(model, road, cam, odo) == pytest.approx(0.0, abs=1e-12)
    off = model + torch.tensor([3.0, 0.0], dtype=torch.float64).reshape(1, 2, 1, 1)
    for penalty, want in (("charbonnier", 10**0.5 - 1), ("cauchy", math.log1p(4.5)),
                          ("l1", 3.0)):
        got = freespace_flow_loss(off, road, cam, odo, penalty=penalty)
        assert got.item() == pytest.approx(want, rel=1e-9)
    # scale: Charbonnier of r / s
    got = freespace_flow_loss(off, road, cam, odo, scale=3.0)
    assert got.item() == pytest.approx(2**0.5 - 1, rel=1e-9)


def test_freespace_only_road_pixels_count():
    cam = _camera()
    model, valid = displacement_flow(cam, 0.0, 1.0, 0.0, (H, W))
    road = torch.zeros(1, 1, H, W, dtype=torch.bool)
    road[..., -5:, :] = True
    flow = model.clone()
    flow[..., : H - 5, :] += 50.0  # wrong everywhere outside the road mask
    assert freespace_flow_loss(flow, road, cam, {"x_d": 0.0, "z_d": 1.0, "yaw": 0.0}).item() == pytest.approx(0.0)


# -- cardinality ---------------------------------------------------------------------------------

@pytest.mark.parametrize("B", [1, 3])
def test_per_sample_shapes(B):
    image1, image2, flow = _shifted_pair(B)
    cam = _camera()
    road = torch.ones(B, 1, H, W, dtype=torch.bool)
    assert photometric_loss(image1, image2, flow, reduction="none").shape == (B,)
    assert smoothness_loss(flow, image1, reduction="none").shape == (B,)
    assert unsupervised_flow_loss(flow, image1, image2, reduction="none").shape == (B,)
    assert freespace_flow_loss(flow, road, cam, _odometry(B), reduction="none").shape == (B,)
    assert freespace_flow_loss(flow, road, cam, _odometry(B)).dim() == 0


# -- empty masks and invalid warps: finite gradients, no division by zero --------------------------

def test_empty_masks_give_zero_and_finite_gradients():
    image1, image2, flow = _shifted_pair(2)
    flow = flow.clone().requires_grad_(True)
    empty = torch.zeros(2, 1, H, W, dtype=torch.bool)
    photo = photometric_loss(image1, image2, flow, empty)
    free = freespace_flow_loss([flow, flow], empty, _camera(), _odometry(2))
    assert photo.item() == 0.0 and free.item() == 0.0
    (photo + free).backward()
    assert torch.isfinite(flow.grad).all()


def test_all_invalid_warp_gives_finite_gradients():
    image1, image2, _ = _shifted_pair(2)
    flow = torch.full((2, 2, H, W), 1000.0, dtype=torch.float64, requires_grad=True)
    photo = photometric_loss(image1, image2, flow)
    assert photo.item() == 0.0
    total = unsupervised_flow_loss([flow], image1, image2, flows_backward=[-flow])
    assert torch.isfinite(total)
    total.backward()
    assert torch.isfinite(flow.grad).all()


def test_freespace_model_undefined_everywhere_is_zero():
    """A mask above the horizon: the model is defined nowhere in it, the term is 0, not NaN."""
    cam = _camera()
    road = torch.zeros(1, 1, H, W, dtype=torch.bool)
    road[..., :5, :] = True
    flow = torch.randn(1, 2, H, W, dtype=torch.float64, requires_grad=True)
    value = freespace_flow_loss(flow, road, cam, {"x_d": 0.0, "z_d": 1.0, "yaw": 0.0})
    value.backward()
    assert value.item() == 0.0 and torch.isfinite(flow.grad).all()


# -- gradcheck -----------------------------------------------------------------------------------

def test_gradcheck_freespace_and_smoothness():
    cam = _camera()
    road = torch.ones(1, 1, 12, 14, dtype=torch.bool)
    flow = torch.randn(1, 2, 12, 14, dtype=torch.float64, requires_grad=True)
    image = _textured(1)[..., :12, :14]
    odo = {"x_d": 0.1, "z_d": 0.5, "yaw": 0.01}
    assert torch.autograd.gradcheck(lambda f: freespace_flow_loss(f, road, cam, odo), (flow,))
    assert torch.autograd.gradcheck(lambda f: freespace_flow_loss(f, road, cam, odo, penalty="cauchy"), (flow,))
    assert torch.autograd.gradcheck(lambda f: smoothness_loss(f, image), (flow,))


def test_gradcheck_photometric():
    image1, image2, _ = _shifted_pair(1)
    image1, image2 = image1[..., :6, :9].contiguous(), image2[..., :6, :9].contiguous()
    # fractional flow away from integer sample points, where bilinear sampling is differentiable
    flow = (torch.full((1, 2, 6, 9), 0.37, dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda f: photometric_loss(image1, image2, f, census_weight=0.5), (flow,),
                                    fast_mode=True)


# -- modules and composition ---------------------------------------------------------------------

def test_modules_match_functions():
    image1, image2, flow = _shifted_pair(1)
    flows = [flow * 0.5, flow]
    torch.testing.assert_close(UnsupervisedFlowLoss(smooth_weight=3.0)(flows, image1, image2, flows),
                               unsupervised_flow_loss(flows, image1, image2, flows_backward=flows,
                                                      smooth_weight=3.0))
    cam, road, odo = _camera(), torch.ones(1, 1, H, W, dtype=torch.bool), _odometry(1)
    torch.testing.assert_close(FreespaceFlowLoss(penalty="cauchy")(flows, road, cam, odo),
                               freespace_flow_loss(flows, road, cam, odo, penalty="cauchy"))


def test_composite_reports_each_term_and_weighted_total():
    image1, image2, flow = _shifted_pair(2)
    flow = (flow + 0.5).requires_grad_(True)
    cam, road, odo = _camera(), torch.ones(2, 1, H, W, dtype=torch.bool), _odometry(2)
    loss = CompositeLoss({"unsup": (1.0, UnsupervisedFlowLoss()), "free": (0.25, FreespaceFlowLoss()),
                          "mag": (2.0, lambda flows: flows[-1].abs().mean())})
    batch = {"image1": image1, "image2": image2, "road": road, "camera": cam, "odometry": odo,
             "depth": torch.zeros(1)}  # an unused key is ignored
    total, values = loss([flow], batch)
    assert set(values) == {"unsup", "free", "mag"}
    assert all(not v.requires_grad for v in values.values())
    torch.testing.assert_close(total.detach(), values["unsup"] + 0.25 * values["free"] + 2.0 * values["mag"])
    total.backward()
    assert torch.isfinite(flow.grad).all()


# -- exceptions ----------------------------------------------------------------------------------

def test_errors_name_the_argument():
    image1, image2, flow = _shifted_pair(1)
    cam, road = _camera(), torch.ones(1, 1, H, W, dtype=torch.bool)
    odo = {"x_d": 0.0, "z_d": 1.0, "yaw": 0.0}
    with pytest.raises(ValueError, match="reduction: expected one of"):
        photometric_loss(image1, image2, flow, reduction="avg")
    with pytest.raises(ValueError, match=r"flow: expected shape \(B, 2, H, W\)"):
        photometric_loss(image1, image2, flow[:, :1])
    with pytest.raises(TypeError, match="mask: expected a bool tensor"):
        photometric_loss(image1, image2, flow, road.float())
    with pytest.raises(ValueError, match=r"road: expected shape .*H=48"):
        freespace_flow_loss(flow, road[..., :10, :], cam, odo)
    with pytest.raises(ValueError, match="penalty: expected one of"):
        freespace_flow_loss(flow, road, cam, odo, penalty="huber")
    with pytest.raises(ValueError, match="odometry: missing keys"):
        freespace_flow_loss(flow, road, cam, {"z_d": 1.0})
    with pytest.raises(ValueError, match="odometry: expected a dict of x_d, z_d, yaw or 'fit'"):
        freespace_flow_loss(flow, road, cam, "given")
    with pytest.raises(TypeError, match="camera: expected a fsof_torch.Camera"):
        freespace_flow_loss(flow, road, None, odo)
    with pytest.raises(ValueError, match="odometry: this FreespaceFlowLoss was built with odometry='given'"):
        FreespaceFlowLoss()(flow, road, cam)
    with pytest.raises(ValueError, match="smooth_order: expected 1 or 2"):
        UnsupervisedFlowLoss(smooth_order=3)
    with pytest.raises(TypeError, match="flows: expected a tensor"):
        unsupervised_flow_loss([], image1, image2)
    with pytest.raises(ValueError, match="flows_backward: expected 2 estimates"):
        unsupervised_flow_loss([flow, flow], image1, image2, flows_backward=[flow])
    with pytest.raises(TypeError, match=r"terms\['a'\]: expected \(weight, callable term\)"):
        CompositeLoss({"a": 1.0})


# -- odometry fitted to the prediction -----------------------------------------------------------

def test_freespace_fit_mode_recovers_model_and_detaches():
    cam = _camera()
    model, valid = displacement_flow(cam, 0.05, 1.0, 0.01, (H, W))
    road = valid.clone()
    road[..., : H // 2 + 4, :] = False
    flow = model.clone().requires_grad_(True)
    term = FreespaceFlowLoss(odometry="fit")
    assert term([flow], road, cam).item() == pytest.approx(0.0, abs=1e-6)
    # the fitted target carries no gradient: the term pulls toward it like a fixed target
    bumped = (model + 0.5).requires_grad_(True)
    value = term(bumped, road, cam)
    value.backward()
    assert value.item() > 0 and torch.isfinite(bumped.grad).all()


def test_photometric_and_smoothness_compute_in_float32_under_bfloat16():
    g = torch.Generator().manual_seed(0)
    image1 = torch.rand(1, 3, 24, 32, generator=g) * 255
    image2 = torch.roll(image1, 1, dims=-1)
    flow = torch.zeros(1, 2, 24, 32)
    flow[:, 0] = 1.0
    exact = photometric_loss(image1, image2, flow)
    low = photometric_loss(image1, image2, flow.bfloat16())
    assert low.dtype == torch.float32
    assert torch.allclose(low, exact, atol=1e-2)
    assert smoothness_loss(flow.bfloat16(), image1).dtype == torch.float32
