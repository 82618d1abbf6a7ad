"""Tests of the training losses: unsupervised (photometric + smoothness + occlusion) and freespace."""

from __future__ import annotations

import contextlib
import functools
import math
import warnings

import numpy as np
import pytest
import torch

from fsof_torch.geometry.camera import Camera
from fsof_torch.geometry.road_flow import displacement_flow, road_flow
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
_PENALTY_NAMES = ("charbonnier", "cauchy", "l1")


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


def test_images_of_another_channel_count_are_named_and_grey_is_its_three_channel_copy():
    """An RGBA (or CARLA's BGRA) frame was taken: its alpha averaged into the L1 and SSIM terms
    (the photometric term a quarter lower), the census grey and the smoothness's edge weights;
    the refiner and FreespaceRefined refuse it. Grey frames are the losses of their RGB copy."""
    image1, image2, flow = _shifted_pair(2)
    flow = flow + 0.4
    alpha = torch.full_like(image1[:, :1], 255.0)
    rgba1, rgba2 = torch.cat([image1, alpha], 1), torch.cat([image2, alpha], 1)
    for name, call in (("image1", lambda: photometric_loss(rgba1, image2, flow)),
                       ("image1", lambda: unsupervised_flow_loss(flow, rgba1, rgba2)),
                       ("image", lambda: smoothness_loss(flow, rgba1)),
                       ("image1", lambda: UnsupervisedFlowLoss(census_weight=1.0)(flow, rgba1[:, :2], rgba2[:, :2]))):
        with pytest.raises(ValueError, match=rf"^{name}: expected 1 \(grey\) or 3 \(RGB\) channels, got shape "
                                             rf"\(2, [24], {H}, {W}\)$"):
            call()
    grey1, grey2 = image1[:, :1], image2[:, :1]
    torch.testing.assert_close(unsupervised_flow_loss(flow, grey1, grey2, census_weight=1.0),
                               unsupervised_flow_loss(flow, grey1.expand(-1, 3, -1, -1), grey2.expand(-1, 3, -1, -1),
                                                      census_weight=1.0))


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


def test_unsupervised_smoothness_follows_the_edges_of_the_frame_each_flow_starts_from():
    """The smoothness term of a forward flow is weighted by image 1's edges, of a backward flow by
    image 2's: with the photometric terms off the loss is smoothness_loss (tested against ARFlow's
    formula) of each flow on its own first frame, the two directions averaged."""
    image1, _, _ = _shifted_pair(2)
    image2 = image1.flip(-1).flip(-2)  # (other edges)
    g = torch.Generator().manual_seed(4)
    fw = torch.randn(2, 2, *image1.shape[-2:], generator=g, dtype=image1.dtype)
    bw = torch.randn(fw.shape, generator=g, dtype=image1.dtype)
    off = dict(l1_weight=0.0, ssim_weight=0.0, smooth_weight=1.0, occlusion=False, reduction="none")
    ref1, ref2 = smoothness_loss(fw, image1, reduction="none"), smoothness_loss(bw, image2, reduction="none")
    assert float((ref1 - smoothness_loss(fw, image2, reduction="none")).abs().min()) > 1e-3
    torch.testing.assert_close(unsupervised_flow_loss([fw], image1, image2, **off), ref1)
    torch.testing.assert_close(unsupervised_flow_loss([fw], image1, image2, flows_backward=[bw], **off),
                               (ref1 + ref2) / 2)


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
    flow = torch.randn(1, 2, H, W, dtype=torch.float64, generator=torch.Generator().manual_seed(0), requires_grad=True)
    with pytest.warns(RuntimeWarning, match="road: the road model is defined at none of the road pixels"):
        value = freespace_flow_loss(flow, road, cam, {"x_d": 0.0, "z_d": 1.0, "yaw": 0.0})
    value.backward()
    assert value.item() == 0.0 and torch.isfinite(flow.grad).all()


def test_freespace_loss_warns_when_road_pixels_count_nothing():
    """Road pixels that the model defines nowhere add 0 to the loss: a step beyond the visible road
    (20 m a frame takes every road point of this camera, 16.5 m ahead at most, behind it) and a
    fit that fails say so, naming the samples; an empty mask and a sample whose road counts stay silent."""
    cam = _camera()
    road = torch.zeros(2, 1, H, W, dtype=torch.bool)
    road[..., H // 2:, :] = True
    flow = torch.zeros(2, 2, H, W, dtype=torch.float64)
    beyond = {"x_d": torch.tensor([0.0, 0.0]), "z_d": torch.tensor([1.0, 20.0]), "yaw": 0.0}
    with pytest.warns(RuntimeWarning, match="not in metres and radians") as caught:
        value = freespace_flow_loss(flow, road, cam, beyond, reduction="none")
    assert len(caught) == 1 and value[0] > 0 and value[1] == 0
    # the sample is named (the warning said "of a sample": in a batch, which one was left to guess)
    assert "road pixels of samples [1], which adds 0" in str(caught[0].message)
    with pytest.warns(RuntimeWarning, match="a fit that failed"):
        assert freespace_flow_loss(torch.full_like(flow, 1e4), road, cam, "fit").item() == 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        freespace_flow_loss(flow, torch.zeros_like(road), cam, beyond)
        freespace_flow_loss(flow, road, cam, {"x_d": 0.0, "z_d": 1.0, "yaw": 0.0})


def test_freespace_loss_refuses_odometry_in_millimetres_by_name():
    """Odometry in millimetres (a kilometre a frame) added 0 with only the generic warning above: a
    step beyond what a road vehicle travels between two frames (100 m) names the odometry and the
    sample, as the refiner and the poses' check do, with or without an empty road mask."""
    cam = _camera()
    road = torch.zeros(2, 1, H, W, dtype=torch.bool)
    road[..., H // 2:, :] = True
    flow = torch.zeros(2, 2, H, W, dtype=torch.float64)
    millimetres = {"x_d": torch.tensor([0.0, 0.0]), "z_d": torch.tensor([1.0, 1000.0]), "yaw": 0.0}
    message = r"^odometry: sample 1 moves 1000 m in a frame \(x_d 0, z_d 1000\), farther than a road vehicle"
    for mask in (road, torch.zeros_like(road)):
        with pytest.raises(ValueError, match=message):
            freespace_flow_loss(flow, mask, cam, millimetres)
        with pytest.raises(ValueError, match=message):
            FreespaceFlowLoss()(flow, mask, cam, millimetres)
    with pytest.raises(ValueError, match=r"^odometry: sample 0 moves 101 m in a frame \(.*y_d 101"):
        freespace_flow_loss(flow, road, cam, {"model": "plane", "y_d": 101.0})
    with pytest.raises(ValueError, match=r"^odometry: sample 0 turns by 5 rad in a frame.*in degrees\?"):
        freespace_flow_loss(flow, road, cam, {"x_d": 0.0, "z_d": 1.0, "yaw": 5.0})  # (degrees for radians)


# -- gradcheck -----------------------------------------------------------------------------------

def test_gradcheck_freespace_and_smoothness():
    # a 12 x 14 crop of the frame's road, below the horizon (row 18): every pixel counts
    cam = _camera().cropped(33, 30)
    road = torch.ones(1, 1, 12, 14, dtype=torch.bool)
    # (seeded: the smoothness term's |gradient| has kinks where neighbours are equal; random
    # flows differ by far more than gradcheck's step)
    flow = torch.randn(1, 2, 12, 14, dtype=torch.float64, generator=torch.Generator().manual_seed(1), requires_grad=True)
    image = _textured(1)[..., :12, :14]
    odo = {"x_d": 0.1, "z_d": 0.5, "yaw": 0.01}
    (grad,) = torch.autograd.grad(freespace_flow_loss(flow, road, cam, odo), flow)
    assert (grad != 0).all()
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



def test_unsupervised_module_registers_a_parameter_weight_and_keeps_no_other_tensor():
    """A weight given as a tensor was kept as given in the options dict: an nn.Parameter (a learned
    weight, which the function's arithmetic trains) was no parameter of the module (absent from
    parameters() and state_dict(), not moved or cast by .to()), and a fixed tensor stayed where
    .to() does not reach it, printed as tensor(...) (a NumPy number as np.float64(...))."""
    import copy

    image1, image2, flow = _shifted_pair(1)
    flows = [flow * 0.5, flow.clone()]
    flows[1][:, 0, :, W // 2:] += 1.0   # (a step: a smoothness term that is not 0)
    weight = torch.nn.Parameter(torch.tensor(3.0, dtype=torch.float64))
    loss = UnsupervisedFlowLoss(smooth_weight=weight, l1_weight=torch.tensor(0.25), alpha1=np.float64(0.02))
    assert list(loss.named_parameters()) == [("smooth_weight", weight)] and list(loss.state_dict()) == ["smooth_weight"]
    assert all(not isinstance(v, torch.Tensor) for v in loss.options.values())
    assert repr(loss) == repr(UnsupervisedFlowLoss(smooth_weight=3.0, l1_weight=0.25, alpha1=0.02)).replace(
        "smooth_weight=3.0", "smooth_weight=Parameter(3)")
    value = loss(flows, image1, image2, flows)
    assert torch.equal(value, unsupervised_flow_loss(flows, image1, image2, flows_backward=flows, smooth_weight=3.0,
                                                     l1_weight=0.25, alpha1=0.02))
    value.backward()
    assert weight.grad is not None and weight.grad.item() > 0
    twin = UnsupervisedFlowLoss(smooth_weight=torch.nn.Parameter(torch.tensor(1.0, dtype=torch.float64)),
                                l1_weight=0.25, alpha1=0.02)
    twin.load_state_dict(copy.deepcopy(loss).state_dict())
    assert torch.equal(twin(flows, image1, image2, flows), value.detach())
    assert loss.float().smooth_weight.dtype == torch.float32 and loss.smooth_weight is weight
    with pytest.raises(TypeError, match=r"^edge_weight: expected a number or an nn.Parameter, got a tensor that "
                                        r"requires grad"):
        UnsupervisedFlowLoss(edge_weight=torch.tensor(10.0, requires_grad=True))

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


@pytest.mark.parametrize("weight, error, match", [
    (float("nan"), ValueError, r"terms\['census'\] weight: expected a finite number, got nan"),
    (float("inf"), ValueError, r"terms\['census'\] weight: expected a finite number, got inf"),
    (-1.0, ValueError, r"terms\['census'\] weight: expected a number >= 0, got -1.0"),
    ("2", TypeError, r"terms\['census'\] weight: expected a number, got str '2'"),
    (True, TypeError, r"terms\['census'\] weight: expected a number, got bool True"),
    (None, TypeError, r"terms\['census'\] weight: expected a number, got NoneType None"),
])
def test_composite_weights_are_finite_numbers_at_least_zero(weight, error, match):
    """A NaN, inf or negative weight made the total NaN, inf or a reward; '2' and True passed
    as 2.0 and 1.0 (float() of them). Each is refused, naming the term."""
    term = lambda flows: flows[-1].abs().mean() + 1.0  # noqa: E731
    with pytest.raises(error, match=match):
        CompositeLoss({"smooth": (1.0, term), "census": (weight, term)})


def test_composite_weights_accept_zero_ints_and_0d_tensors():
    term = lambda flows: flows[-1].abs().mean() + 1.0  # noqa: E731
    loss = CompositeLoss({"a": (0, term), "b": (3, term), "c": (torch.tensor(0.5), term)})
    assert loss.weights == {"a": 0.0, "b": 3.0, "c": 0.5}
    assert all(type(w) is float for w in loss.weights.values())
    total, values = loss([torch.zeros(1, 2, 4, 4)])
    assert total.item() == pytest.approx(3.5) and values["a"].item() == 1.0


def test_composite_refuses_a_learnable_weight():
    """A weight that requires grad (an nn.Parameter, for learned loss weights) was read as a float:
    the total carried no gradient to it, so it never changed, silently."""
    term = lambda flows: flows[-1].abs().mean()  # noqa: E731
    for weight in (torch.nn.Parameter(torch.tensor(0.5)), torch.tensor(2.0, requires_grad=True)):
        with pytest.raises(TypeError, match=r"^terms\['b'\] weight: expected a fixed number, got a tensor that "
                                            r"requires grad"):
            CompositeLoss({"a": (1.0, term), "b": (weight, term)})
    # the same values without gradient are weights
    loss = CompositeLoss({"a": (1.0, term), "b": (torch.nn.Parameter(torch.tensor(0.5)).detach(), term)})
    assert loss.weights == {"a": 1.0, "b": 0.5}


def test_composite_zero_weight_terms_are_reported_not_summed():
    """0 * inf is NaN: a zero-weight diagnostic term returning inf made the total NaN."""
    flow = torch.ones(1, 2, 4, 4, requires_grad=True)
    loss = CompositeLoss({"a": (2.0, lambda flows: flows[-1].sum()),
                          "diag": (0.0, lambda flows: flows[-1].sum() / 0.0)})
    total, values = loss([flow])
    assert total.item() == 64.0 and values["diag"].item() == float("inf")
    total.backward()
    assert torch.equal(flow.grad, torch.full_like(flow, 2.0))
    # every weight 0: a zero total that backward() accepts; no gradient reaches the flow
    flow.grad = None
    total, values = CompositeLoss({"diag": (0.0, lambda flows: flows[-1].sum() / 0.0)})([flow])
    assert total.item() == 0.0 and values["diag"].item() == float("inf")
    total.backward()
    assert flow.grad is None


def test_composite_total_of_zero_weights_needs_no_gradient_where_grad_is_off():
    """Every weight 0 gave a total with requires_grad=True also under no_grad and inference_mode,
    unlike any other total there."""
    flow = torch.ones(1, 2, 4, 4)
    for weight in (0.0, 1.0):
        loss = CompositeLoss({"a": (weight, lambda flows: flows.sum())})
        for off in (torch.no_grad, torch.inference_mode):
            with off():
                total, _ = loss(flow)
            assert not total.requires_grad, (weight, off)
        assert loss(flow.requires_grad_(True))[0].requires_grad
        flow = flow.detach()


def test_composite_terms_may_return_python_numbers():
    """A float result crashed on .detach()."""
    total, values = CompositeLoss({"a": (2.0, lambda flows: 0.5), "b": (1.0, lambda flows: flows.sum())})(
        torch.ones(1, 2, 1, 1))
    assert total.item() == 3.0 and values["a"].item() == 0.5 and isinstance(values["a"], torch.Tensor)
    # only Python numbers weighted: a total that backward() accepts, as with every weight 0 (was:
    # a tensor without a graph, whose backward() raised); no gradient reaches the flow
    flow = torch.ones(1, 2, 1, 1, requires_grad=True)
    total, _ = CompositeLoss({"a": (2.0, lambda flows: 0.25), "b": (0.0, lambda flows: flows[-1].sum())})([flow])
    assert total.item() == 0.5
    total.backward()
    assert flow.grad is None
    with torch.no_grad():  # (no graph asked for: none given)
        assert not CompositeLoss({"a": (2.0, lambda flows: 0.25)})([flow])[0].requires_grad


def test_composite_takes_a_builtin_term_without_a_readable_signature():
    """torch.mean or torch.Tensor.abs as a term (a regulariser, a diagnostic of weight 0): CompositeLoss
    raised inspect's 'no signature found for builtin' when made, naming no term; such a term is fed
    the flows alone."""
    g = torch.Generator().manual_seed(0)
    flow = torch.randn(2, 2, 4, 5, generator=g, dtype=torch.float64).requires_grad_(True)
    batch = {"road": torch.ones(2, 1, 4, 5, dtype=torch.bool), "odometry": _odometry(2)}
    loss = CompositeLoss({"mean": (0.5, torch.mean), "sum": (0.0, torch.sum),
                          "l1": (2.0, functools.partial(torch.nn.functional.l1_loss, target=torch.zeros_like(flow)))})
    total, values = loss(flow, batch)
    assert values["mean"].item() == pytest.approx(flow.mean().item(), rel=1e-12)
    assert values["sum"].item() == pytest.approx(flow.sum().item(), rel=1e-12)
    assert total.item() == pytest.approx(0.5 * flow.mean().item() + 2.0 * flow.abs().mean().item(), rel=1e-12)
    total.backward()
    torch.testing.assert_close(flow.grad, 0.5 / flow.numel() + 2.0 * flow.detach().sign() / flow.numel())
    # a builtin that needs more than the flows fails at its call, named
    with pytest.raises(TypeError, match=r"^terms\['d'\]: "):
        CompositeLoss({"d": (1.0, torch.dist)})(flow, batch)


@pytest.mark.filterwarnings("ignore:`torch.jit.trace:DeprecationWarning")
def test_composite_feeds_a_traced_term_the_inputs_its_schema_names():
    """A torch.jit.trace'd module's forward has no Python signature: CompositeLoss raised 'no
    signature found' when made; it reads the TorchScript schema's argument names instead."""

    class Term(torch.nn.Module):
        def forward(self, flows, image1, road):
            return flows.abs().mean() + 0.01 * (image1 * road).mean()

    image1, _, flow = _shifted_pair(1)
    road = torch.zeros(1, 1, H, W, dtype=torch.float64)
    road[..., H // 2:, :] = 1.0
    traced = torch.jit.trace(Term(), (flow, image1, road))
    g = torch.Generator().manual_seed(1)
    probe = torch.randn(flow.shape, generator=g, dtype=flow.dtype)
    total, values = CompositeLoss({"traced": (2.0, traced)})(probe, {"image1": image1, "road": road, "camera": None})
    expected = probe.abs().mean() + 0.01 * (image1 * road).mean()
    assert values["traced"].item() == pytest.approx(expected.item(), rel=1e-12)
    assert total.item() == pytest.approx(2.0 * expected.item(), rel=1e-12)


def test_composite_bad_inputs_are_named():
    """A list as inputs gave dict()'s 'dictionary update sequence' error, a missing input Python's
    'missing 2 required positional arguments' without the term's name."""
    flows = [torch.zeros(1, 2, 4, 4)]
    loss = CompositeLoss({"a": (1.0, lambda flows: flows[0].sum())})
    with pytest.raises(TypeError, match=r"^inputs: expected None or a mapping .*, got list$"):
        loss(flows, [1, 2])
    loss = CompositeLoss({"fs": (1.0, FreespaceFlowLoss())})
    with pytest.raises(TypeError, match=r"^terms\['fs'\]: .*missing 2 required positional arguments: 'road' and "
                                        r"'camera' \(inputs given: \['depth'\]\)$"):
        loss(flows, {"depth": 1})
    loss = CompositeLoss({"a": (1.0, lambda flows, **kw: flows[0].sum())})
    with pytest.raises(TypeError, match=r"^terms\['a'\]: .*multiple values for argument 'flows'"):
        loss(flows, {"flows": 1})


def test_composite_feeds_a_compiled_term_the_inputs_its_forward_names():
    """torch.compile(term) is a module whose forward takes (*args, **kwargs): it was fed every
    input of the batch and raised "unexpected keyword argument 'image1'", naming the term."""
    image1, image2, flow = _shifted_pair(2)
    flow = flow + 0.5
    batch = {"image1": image1, "image2": image2, "road": torch.ones(2, 1, H, W, dtype=torch.bool),
             "camera": _camera(), "odometry": _odometry(2)}
    eager = CompositeLoss({"u": (1.0, UnsupervisedFlowLoss()), "f": (0.1, FreespaceFlowLoss())})
    compiled = CompositeLoss({"u": (1.0, UnsupervisedFlowLoss()),
                              "f": (0.1, torch.compile(FreespaceFlowLoss(), backend="eager"))})
    total, values = compiled(flow, batch)
    expected_total, expected = eager(flow, batch)
    torch.testing.assert_close(values["f"], freespace_flow_loss(flow, batch["road"], batch["camera"],
                                                                batch["odometry"]))
    torch.testing.assert_close(total, expected_total)
    assert values["f"] > 0


def test_composite_leaves_a_partials_bound_keywords_to_it():
    """partial(freespace_flow_loss, odometry="fit") was fed the batch's odometry, whose keyword
    overrides the bound one: the term silently used the given odometry, not the fit."""
    image1, image2, flow = _shifted_pair(2)
    road = torch.zeros(2, 1, H, W, dtype=torch.bool)
    road[:, :, H // 2:] = True
    cam, odo = _camera(), _odometry(2)
    g = torch.Generator().manual_seed(0)
    # the road flow of another motion than the batch's, plus noise: a fit follows it, the batch's odometry does not
    target, _ = road_flow(cam, {"x_d": 0.05, "z_d": 0.6, "yaw": 0.01}, (H, W))
    flow = target.expand(2, 2, H, W) + 0.3 * torch.randn(2, 2, H, W, generator=g, dtype=torch.float64)
    batch = {"image1": image1, "image2": image2, "road": road, "camera": cam, "odometry": odo}
    fitted = freespace_flow_loss(flow, road, cam, "fit")
    given = freespace_flow_loss(flow, road, cam, odo)
    assert given > 10 * fitted  # (the two targets differ: the test tells them apart)
    _, values = CompositeLoss({"f": (1.0, functools.partial(freespace_flow_loss, odometry="fit"))})(flow, batch)
    torch.testing.assert_close(values["f"], fitted)
    # a bound image too; a term taking **kwargs is not fed its bound keywords either
    _, values = CompositeLoss({"u": (1.0, functools.partial(unsupervised_flow_loss, image2=image1))})(flow, batch)
    torch.testing.assert_close(values["u"], unsupervised_flow_loss(flow, image1, image1))
    # a partial of a module term: fed its forward's inputs but the bound one (was: every input, and
    # "unexpected keyword argument 'image1'")
    other = {"x_d": 0.05, "z_d": 0.6, "yaw": 0.01}
    _, values = CompositeLoss({"f": (1.0, functools.partial(FreespaceFlowLoss(), odometry=other))})(flow, batch)
    torch.testing.assert_close(values["f"], freespace_flow_loss(flow, road, cam, other))
    seen = {}
    term = functools.partial(lambda flows, **kw: seen.update(kw) or 0.0, camera="mine")
    CompositeLoss({"k": (1.0, term)})(flow, batch)
    assert seen["camera"] == "mine" and seen["road"] is road


def test_composite_refuses_a_term_that_is_not_a_scalar():
    """A term of reduction="none" gave a (B,) total silently: the scalar terms broadcast to every
    sample, so a sum of it counted them B times (and backward() raised, naming no term)."""
    image1, image2, flow = _shifted_pair(3)
    road = torch.ones(3, 1, H, W, dtype=torch.bool)
    batch = {"image1": image1, "image2": image2, "road": road, "camera": _camera(), "odometry": _odometry(3)}
    loss = CompositeLoss({"u": (1.0, UnsupervisedFlowLoss()), "f": (0.1, FreespaceFlowLoss(reduction="none"))})
    with pytest.raises(ValueError, match=r"^terms\['f'\]: expected a scalar loss, got shape \(3,\) .*reduction='none'"):
        loss(flow, batch)
    # one value in a tensor of shape (1,) is a scalar loss, as are sums
    loss = CompositeLoss({"u": (1.0, lambda flows: flows.sum().reshape(1)),
                          "f": (0.1, FreespaceFlowLoss(reduction="sum"))})
    total, values = loss(flow, batch)
    assert total.numel() == 1 and values["u"].shape == (1,)


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
    # an empty batch: nothing to average (not a NaN mean)
    with pytest.raises(ValueError, match=r"flows\[0\]: expected shape \(B, 2, H, W\) with B >= 1"):
        freespace_flow_loss(flow[:0], road[:0], cam, odo)
    with pytest.raises(ValueError, match=r"flow: expected shape \(B, 2, H, W\) with B >= 1"):
        photometric_loss(image1[:0], image2[:0], flow[:0])
    with pytest.raises(ValueError, match="penalty: expected one of"):
        freespace_flow_loss(flow, road, cam, odo, penalty="huber")
    with pytest.raises(ValueError, match="odometry: missing keys"):
        freespace_flow_loss(flow, road, cam, {"z_d": 1.0})
    with pytest.raises(ValueError, match="odometry: expected a dict of x_d, z_d, yaw or 'fit'"):
        freespace_flow_loss(flow, road, cam, "given")
    # the fit's options are checked by name where they are given, not at the fit
    with pytest.raises(TypeError, match=r"fit_options: unknown options \['bogus'\] of fit_road"):
        FreespaceFlowLoss(odometry="fit", fit_options={"bogus": 1})
    with pytest.raises(TypeError, match=r"fit_options: unknown options \['fit_roll'\] of fit_road"):
        FreespaceFlowLoss(odometry="fit", fit_options={"model": "plane", "fit_roll": True})
    with pytest.raises(TypeError, match=r"fit_options: unknown options \['bogus'\]"):
        freespace_flow_loss(flow, road, cam, "fit", fit_options={"bogus": 1})
    FreespaceFlowLoss(odometry="fit", fit_options={"fit_roll": True, "max_iter": 5})  # fit_displacement's
    with pytest.raises(TypeError, match="camera: expected a fsof_torch.Camera"):
        freespace_flow_loss(flow, road, None, odo)
    with pytest.raises(ValueError, match="odometry: this FreespaceFlowLoss was built with odometry='given'"):
        FreespaceFlowLoss()(flow, road, cam)
    with pytest.raises(ValueError, match="smooth_order: expected 1 or 2"):
        UnsupervisedFlowLoss(smooth_order=3)
    # a float or bool order is a wrong type (1.0 was taken, True raised a ValueError)
    for bad in (1.0, True, "2"):
        with pytest.raises(TypeError, match=f"^smooth_order: expected an int, got {type(bad).__name__} {bad!r}$"):
            UnsupervisedFlowLoss(smooth_order=bad)
        with pytest.raises(TypeError, match=f"^order: expected an int, got {type(bad).__name__} {bad!r}$"):
            smoothness_loss(flow, torch.zeros(1, 3, *flow.shape[-2:]), order=bad)
    # a truthy string or number is no flag: "False" would switch the occlusion mask on
    with pytest.raises(TypeError, match="occlusion: expected True or False, got str 'False'"):
        UnsupervisedFlowLoss(occlusion="False")
    with pytest.raises(TypeError, match="occlusion: expected True or False, got int 0"):
        unsupervised_flow_loss(flow, image1, image2, flows_backward=flow, occlusion=0)
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
    # the fitted target carries no gradient: the term pulls toward it like a fixed target, the
    # Charbonnier gradient r / sqrt(r^2 + 1) / N on the N counted pixels (written out here)
    g = torch.Generator().manual_seed(0)
    bumped = (model + 0.5 + 0.3 * torch.randn(model.shape, generator=g)).requires_grad_(True)
    value = term(bumped, road, cam)
    value.backward()
    from fsof_torch.estimation.flow_fit import fit_displacement

    fitted = fit_displacement(torch.where(road, bumped.detach(), 0.0), road, cam)
    counted = road & fitted.valid
    r = torch.where(counted, bumped.detach() - fitted.flow, 0.0)
    n = counted.sum()
    assert value.item() == pytest.approx(float(((r.square() + 1).sqrt() - 1).sum() / n), rel=1e-5)
    torch.testing.assert_close(bumped.grad, r / (r.square() + 1).sqrt() / n, rtol=1e-4, atol=1e-9)


def test_photometric_and_smoothness_compute_in_float32_under_bfloat16():
    """A bfloat16 flow is lifted to float32 before warping and differencing: the terms equal those
    of the same values given in float32, bit for bit, also under bfloat16 autocast (a warp in
    bfloat16 would round positions 300 px along to 1 or 2 px)."""
    g = torch.Generator().manual_seed(0)
    image1 = torch.rand(1, 3, 24, 300, generator=g) * 255
    image2 = torch.rand(1, 3, 24, 300, generator=g) * 255
    flow = (0.3 + torch.randn(1, 2, 24, 300, generator=g)).bfloat16()
    as_float = flow.float()
    for ctx in (contextlib.nullcontext(), torch.autocast("cpu", dtype=torch.bfloat16)):
        with ctx:
            low = photometric_loss(image1, image2, flow)
            smooth = smoothness_loss(flow, image1)
        assert low.dtype == smooth.dtype == torch.float32
        assert torch.equal(low, photometric_loss(image1, image2, as_float))
        assert torch.equal(smooth, smoothness_loss(as_float, image1))


# -- mixed precision: the terms compute in at least float32 under autocast -------------------------

def _road_case(dtype=torch.float32):
    cam = _camera(dtype)
    odo = {"x_d": 0.05, "z_d": 1.0, "yaw": 0.01}
    model, valid = displacement_flow(cam, odo["x_d"], odo["z_d"], odo["yaw"], (H, W))
    road = valid.clone()
    road[..., : H // 2 + 2, :] = False
    return cam, odo, model, road


@pytest.mark.parametrize("amp", [torch.bfloat16, torch.float16], ids=["bf16", "f16"])
def test_freespace_loss_of_the_exact_model_flow_is_zero_under_autocast(amp):
    """Once 3.29 instead of 0 under bfloat16: the model flow was computed in bfloat16."""
    cam, odo, model, road = _road_case()
    for penalty in _PENALTY_NAMES:
        with torch.autocast("cpu", dtype=amp):
            # end to end: the term computes its own model flow inside the autocast region
            value = FreespaceFlowLoss(penalty=penalty)(model, road, cam, odo)
        assert value.dtype == torch.float32 and value.item() == 0.0, penalty
    # a float64 camera: the model flow in float64, compared in float32
    cam64 = _camera(torch.float64)
    model64, _ = displacement_flow(cam64, odo["x_d"], odo["z_d"], odo["yaw"], (H, W))
    with torch.autocast("cpu", dtype=amp):
        value = freespace_flow_loss(model64.float(), road, cam64, odo)
    assert value.item() <= 1e-12


@pytest.mark.parametrize("model", ["paper", "plane"])
def test_freespace_loss_takes_float_odometry_at_the_geometry_dtype(model):
    """A float64 model flow with the odometry as Python floats: the loss of the exact model flow is
    exactly 0 (once 4e-15: the floats were rounded to float32 before the float64 geometry)."""
    cam = _camera(torch.float64)
    odo = {"x_d": 0.1, "z_d": 1.2, "yaw": 0.01}
    if model == "plane":
        odo = {"model": "plane", **odo, "pitch_change": 0.003, "y_d": 0.02}
    exact, valid = road_flow(cam, {k: v for k, v in odo.items() if k != "model"}, (H, W), model=model)
    road = valid & (torch.arange(W) > W // 4)
    assert exact.dtype == torch.float64 and road.sum() > 100
    for penalty in _PENALTY_NAMES:
        assert freespace_flow_loss(exact, road, cam, odo, penalty=penalty).item() == 0.0, penalty
    # float32 flows with a float64 camera: the geometry in float64, the odometry with it
    as_tensors = {k: (torch.tensor([v], dtype=torch.float64) if k != "model" else v) for k, v in odo.items()}
    assert freespace_flow_loss(exact.float(), road, cam, odo).item() == freespace_flow_loss(
        exact.float(), road, cam, as_tensors).item()


@pytest.mark.parametrize("amp, low, high", [(torch.bfloat16, 5e-5, 2e-4), (torch.float16, 5e-7, 5e-6)],
                         ids=["bf16", "f16"])
def test_freespace_loss_of_a_half_precision_prediction_is_its_rounding(amp, low, high):
    """docs/training.md: exactly 0 holds for a float32 prediction only; the exact model flow held
    in bfloat16 (float16) gives about 1e-4 (1.6e-6) with the Charbonnier penalty, flows <= 19 px."""
    cam, odo, model, road = _road_case()
    assert model[road.expand_as(model)].abs().max() < 19.0
    with torch.autocast("cpu", dtype=amp):
        exact = freespace_flow_loss(model, road, cam, odo)
        rounded = freespace_flow_loss(model.to(amp), road, cam, odo)
    assert exact.item() == 0.0
    assert rounded.dtype == torch.float32 and low < rounded.item() < high


@pytest.mark.parametrize("amp", [torch.bfloat16, torch.float16], ids=["bf16", "f16"])
def test_losses_under_autocast_equal_float32(amp):
    cam, odo, model, road = _road_case()
    g = torch.Generator().manual_seed(3)
    flow = (model + torch.randn(model.shape, generator=g)).requires_grad_(True)
    image1, image2, shift = _shifted_pair(1, dtype=torch.float32)
    cases = {
        "freespace": lambda f: freespace_flow_loss([f * 0.5, f], road, cam, odo, penalty="cauchy"),
        "freespace_fit": lambda f: FreespaceFlowLoss(odometry="fit")(f, road, cam),
        "unsupervised": lambda f: unsupervised_flow_loss([f], image1, image2, flows_backward=[-f],
                                                         census_weight=1.0),
    }
    for name, fn in cases.items():
        f = flow if name != "unsupervised" else (shift + 0.3).requires_grad_(True)
        exact = fn(f)
        (grad_exact,) = torch.autograd.grad(exact, f)
        with torch.autocast("cpu", dtype=amp):
            low = fn(f)
        (grad_low,) = torch.autograd.grad(low, f)
        assert low.dtype == torch.float32, name
        torch.testing.assert_close(low, exact, rtol=1e-4, atol=0, msg=name)
        torch.testing.assert_close(grad_low, grad_exact, rtol=1e-4, atol=1e-9, msg=name)


def test_census_term_runs_in_float32_under_autocast():
    """The census convolution once ran in bfloat16 under autocast (three significant digits)."""
    from fsof_torch.evaluation.photometric import census_transform

    image = _textured(1, torch.float32) / 255
    exact = census_transform(image, data_range=1.0)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        low = census_transform(image, data_range=1.0)
    assert low.dtype == torch.float32 and torch.equal(low, exact)


# -- non-finite and huge predictions in the freespace term ---------------------------------------

def test_nonfinite_predictions_outside_the_road_do_not_count():
    """One inf or NaN pixel outside the road (or 1e20 in float32) once made the loss and every
    gradient NaN."""
    cam, odo, model, road = _road_case()
    off = model + 0.7
    clean = freespace_flow_loss(off, road, cam, odo)
    bad = off.clone()
    bad[0, 0, 0, 0], bad[0, 1, 1, 1], bad[0, 0, 2, 2] = float("inf"), float("nan"), 1e20
    assert not road[0, 0, :3, :3].any()
    bad.requires_grad_(True)
    for penalty in _PENALTY_NAMES:
        value = freespace_flow_loss([bad, bad], road, cam, odo, penalty=penalty)
        (grad,) = torch.autograd.grad(value, bad)
        assert torch.isfinite(grad).all() and (grad[..., :3, :3] == 0).all(), penalty
        if penalty == "charbonnier":
            torch.testing.assert_close(value, clean * (1 + 0.8), rtol=1e-6, atol=0)


def test_nonfinite_predictions_inside_the_road_are_left_out_with_a_warning():
    cam, odo, model, road = _road_case()
    off = model + 0.7
    bad = off.clone()
    rows, cols = torch.nonzero(road[0, 0])[:3].T
    bad[0, 0, rows[0], cols[0]] = float("nan")
    bad[0, 1, rows[1], cols[1]] = float("inf")
    keep = road.clone()
    keep[0, 0, rows[:2], cols[:2]] = False
    bad.requires_grad_(True)
    with pytest.warns(RuntimeWarning, match=r"flows: non-finite predicted pixels inside the road mask are "
                                            r"left out of the freespace loss \(flows\[0\]: 2\)"):
        value = freespace_flow_loss(bad, road, cam, odo)
    (grad,) = torch.autograd.grad(value, bad)
    assert torch.isfinite(grad).all()
    torch.testing.assert_close(value, freespace_flow_loss(off, keep, cam, odo), rtol=1e-6, atol=0)


def test_fit_mode_warns_of_a_prediction_nan_on_the_whole_road():
    """Once silent: a diverged sample makes its fit fail, and the count went over the fitted road."""
    cam, odo, model, road = _road_case()
    road = road.expand(2, 1, H, W).clone()
    flow = (model + 0.3).expand(2, 2, H, W).clone()
    flow[0] = float("nan")
    n_road = int(road[0].sum())
    with (pytest.warns(RuntimeWarning, match="a fit that failed"),
          pytest.warns(RuntimeWarning, match=rf"left out of the freespace loss \(flows\[0\]: {n_road}\)")):
        value = freespace_flow_loss(flow, road, cam, "fit", reduction="none")
    assert value[0].item() == 0.0 and value[1].item() > 0
    torch.testing.assert_close(value[1:], freespace_flow_loss(flow[1:], road[1:], cam, "fit", reduction="none"))


def test_huge_finite_predictions_give_finite_penalties():
    """r = 1e20 px in float32: r² overflows; the penalties are written without forming it."""
    cam, odo, model, road = _road_case()
    big = model.clone()
    r, c = torch.nonzero(road[0, 0])[0].tolist()
    big[0, 0, r, c] = 1e20
    big.requires_grad_(True)
    n = int(road.sum())
    for penalty, want in (("charbonnier", 1e20 - 1), ("cauchy", 2 * math.log(1e20 / math.sqrt(2))), ("l1", 1e20)):
        value = freespace_flow_loss(big, road, cam, odo, penalty=penalty)
        (grad,) = torch.autograd.grad(value, big)
        assert torch.isfinite(grad).all() and torch.isfinite(value), penalty
        assert value.item() == pytest.approx(want / n, rel=1e-5), penalty
    with pytest.raises(ValueError, match="flows: the charbonnier penalty overflows torch.float32"):
        freespace_flow_loss(torch.full_like(model, 3e38), road, cam, odo, scale=0.01)


def test_charbonnier_value_of_small_residuals_is_precise_in_float32():
    """sqrt(r² + 1) - 1 written as hypot(r, 1) - 1 cancels in float32: residuals of 1e-4 px read
    1.4e-10 instead of 1e-8 (and 0 below 3e-4 px). The value matches the float64 formula at every
    scale; the gradient is r / sqrt(r² + 1)."""
    cam, odo, model, road = _road_case()
    g = torch.Generator().manual_seed(0)
    n = road.sum()
    for size in (1e-1, 1e-3, 1e-4, 1e-6):
        flow = (model.float() + size * torch.randn(model.shape, generator=g, dtype=torch.float64).float())
        flow.requires_grad_(True)
        r = flow.detach().double() - model.double()
        want = ((torch.sqrt(r * r + 1) - 1).sum(dim=1, keepdim=True) * road).sum() / n
        value = freespace_flow_loss(flow, road, cam, odo)
        assert value.dtype == torch.float32
        assert value.item() == pytest.approx(want.item(), rel=1e-5), size
        (grad,) = torch.autograd.grad(value, flow)
        want_grad = torch.where(road, r / torch.sqrt(r * r + 1), 0.0) / n
        torch.testing.assert_close(grad.double(), want_grad, rtol=1e-5, atol=1e-12)


def test_unsupervised_loss_of_flows_near_the_dtype_limit_is_an_error_not_inf():
    """The smoothness sums flow differences: a float32 flow of 3e38 px at one pixel made the loss
    inf (from finite input, silently); it is a ValueError naming the flows, as the freespace term's
    overflow is. Large flows that fit stay finite, with finite gradients, and in float64 the same
    flow is a finite loss."""
    image = _textured(1, torch.float32)
    for magnitude in (1e20, 3e38):
        flow = torch.zeros(1, 2, H, W)
        flow[0, 0, 20, 30] = magnitude
        if magnitude == 1e20:
            f = flow.clone().requires_grad_(True)
            value = unsupervised_flow_loss(f, image, image, flows_backward=torch.zeros_like(flow))
            (grad,) = torch.autograd.grad(value, f)
            assert torch.isfinite(value) and value.item() > 1e15 and torch.isfinite(grad).all()
            continue
        before = flow.clone()
        for call, name in ((lambda: unsupervised_flow_loss(flow, image, image), "flows"),
                           (lambda: UnsupervisedFlowLoss()([torch.zeros_like(flow), flow], image, image), "flows"),
                           (lambda: unsupervised_flow_loss(torch.zeros_like(flow), image, image, flows_backward=flow),
                            "flows_backward"),
                           (lambda: smoothness_loss(flow, image), "flow")):
            with pytest.raises(ValueError, match=rf"^{name}: the \w+ loss overflows torch.float32 \(largest \|flow\| "
                                                 rf"3e\+38 px\)"):
                call()
        assert torch.equal(flow, before)
        assert torch.isfinite(unsupervised_flow_loss(flow.double(), image.double(), image.double()))


def test_cauchy_penalty_is_continuous_at_its_switch():
    from fsof_torch.training.losses import _CAUCHY_SWITCH, _cauchy

    r = torch.tensor([_CAUCHY_SWITCH * (1 - 1e-12), _CAUCHY_SWITCH, 7.0, 1e-4], dtype=torch.float64)
    torch.testing.assert_close(_cauchy(r), torch.log1p(r * r / 2), rtol=1e-12, atol=0)


# -- the failures of bad arguments, each named -------------------------------------------------------

def test_a_stack_of_estimates_is_refused_saying_what_to_give():
    """ptlflow's outputs["flows"] (B, N, 2, H, W) once got "expected shape (B, 2, H, W)" alone; the
    message says it is a stack. docs/training.md: its [:, -1] with the images flipped to RGB on
    0..1 is what TinyRAFT's own call gives the terms."""
    from fsof_torch.training.standins import PtlflowRAFTStandIn

    net = PtlflowRAFTStandIn(seed=0, iters=2).eval()
    image1, image2, _ = _shifted_pair(2, dtype=torch.float32)
    images = torch.stack([image1, image2], dim=1).flip(2) / 255  # ptlflow's input: BGR on 0..1
    with torch.no_grad():
        out = net({"images": images})
        own = net.net(image1, image2)[-1]
    stack = out["flows"]
    assert stack.shape == (2, 1, 2, H, W)
    cam, odo = _camera(torch.float32), _odometry(2)
    road = torch.ones(2, 1, H, W, dtype=torch.bool)
    match = r"flows\[0\]: expected shape \(B, 2, H, W\), got \(2, 1, 2, 48, 80\), a stack .* give flows\[:, -1\]"
    for call in (lambda f: freespace_flow_loss(f, road, cam, odo), lambda f: unsupervised_flow_loss(f, image1, image2),
                 lambda f: UnsupervisedFlowLoss()([f], image1, image2)):
        with pytest.raises(ValueError, match=match):
            call(stack)
    with pytest.raises(ValueError, match=r"^flow: expected shape .* a stack"):
        photometric_loss(image1, image2, stack)
    i1, i2 = images[:, 0].flip(1), images[:, 1].flip(1)
    for census in (0.0, 1.0):
        got = unsupervised_flow_loss(stack[:, -1], i1, i2, census_weight=census, data_range=1.0)
        want = unsupervised_flow_loss(own, image1, image2, census_weight=census)
        torch.testing.assert_close(got, want, rtol=1e-5, atol=0)
    torch.testing.assert_close(freespace_flow_loss(stack[:, -1], road, cam, odo), freespace_flow_loss(own, road, cam, odo))


def test_freespace_mean_gives_each_sample_the_weight_one_over_b():
    """docs/training.md: a sample without road counts 0 in the mean, and the others' terms and
    gradients are those of each sample alone, divided by B."""
    cam, odo, model, road = _road_case()
    g = torch.Generator().manual_seed(3)
    flows = [(model + torch.randn(3, *model.shape[1:], generator=g)).requires_grad_(True) for _ in range(2)]
    masks = road.expand(3, -1, -1, -1).clone()
    masks[1] = False
    masks[2, ..., : W // 2] = False
    mean = freespace_flow_loss(flows, masks, cam, odo)
    grads = torch.autograd.grad(mean, flows)
    for b in range(3):
        alone = freespace_flow_loss([f[b:b + 1] for f in flows], masks[b:b + 1], cam, odo)
        want = torch.autograd.grad(alone, flows, allow_unused=True) if b != 1 else None
        if b == 1:
            assert alone.item() == 0.0 and all(gr[1].abs().max() == 0 for gr in grads)
            continue
        for got, w in zip(grads, want):
            torch.testing.assert_close(got[b], w[b] / 3)
    per_sample = freespace_flow_loss(flows, masks, cam, odo, reduction="none")
    assert per_sample[1].item() == 0.0
    torch.testing.assert_close(mean, per_sample.sum() / 3)
    torch.testing.assert_close(freespace_flow_loss(flows, masks, cam, odo, reduction="sum"), per_sample.sum())


def test_freespace_term_at_ptlflows_flow_small_takes_the_padded_camera_scaled():
    """docs/training.md: flow at 1/8 of the padded grid (the model flow averaged over 8x8 blocks)
    is the road flow of camera.padded(...).scaled(1/8) to averaging's curvature error; the camera
    scaled by the unpadded size ratio misses it by ten times that (0.0056 and 0.059 px here)."""
    from fsof_torch.refinement.contracts import InputPadder

    K = torch.tensor([[180.4, 0.0, 152.4], [0.0, 180.4, 43.2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    cam, (h, w) = Camera(K, 1.65), (94, 310)  # KITTI's camera at a quarter of its size
    pad = InputPadder(8, mode="sintel").padding((h, w))
    hp, wp = pad.padded_size((h, w))
    padded = cam.padded(pad.left, pad.top, pad.right, pad.bottom)
    full, valid = displacement_flow(padded, 0.0, 1.2, 0.01, (hp, wp))
    small = torch.nn.functional.avg_pool2d(full, 8) / 8
    road = valid & (torch.arange(hp)[:, None] > 60)
    road_small = ~torch.nn.functional.max_pool2d((~road).double(), 8).bool()
    odo = {"x_d": 0.0, "z_d": 1.2, "yaw": 0.01}
    right = freespace_flow_loss(small, road_small, padded.scaled(1 / 8), odo, penalty="l1")
    naive = freespace_flow_loss(small, road_small, cam.scaled(wp / 8 / w, hp / 8 / h), odo, penalty="l1")
    assert right.item() < 0.01 and naive.item() > 5 * right.item()


def test_freespace_batch_mismatches_name_the_argument():
    """Once a RuntimeError 'expanded size ...' from inside the model flow."""
    flow = torch.zeros(2, 2, H, W, dtype=torch.float64)
    road = torch.ones(2, 1, H, W, dtype=torch.bool)
    K3 = _camera().K.expand(3, 3, 3)
    with pytest.raises(ValueError, match=r"camera: expected batch 1 or 2 \(the flows' batch\), got 3"):
        freespace_flow_loss(flow, road, Camera(K3, 1.65), {"x_d": 0.0, "z_d": 1.0, "yaw": 0.0})
    with pytest.raises(ValueError, match=r"odometry\['z_d'\]: expected a float or a tensor of shape \(1,\) or "
                                         r"\(2,\) \(the flows' batch\), got shape \(3,\)"):
        FreespaceFlowLoss()(flow, road, _camera(), {"x_d": 0.0, "z_d": torch.ones(3), "yaw": 0.0})


@pytest.mark.parametrize("scale", [float("inf"), float("nan"), 0.0, -1.0])
def test_freespace_scale_must_be_finite_and_positive(scale):
    """scale=inf once made the term 0 whatever the flow."""
    flow, road = torch.zeros(1, 2, H, W), torch.ones(1, 1, H, W, dtype=torch.bool)
    with pytest.raises(ValueError, match="scale: expected a finite residual scale > 0 px"):
        FreespaceFlowLoss(scale=scale)
    with pytest.raises(ValueError, match="scale: expected a finite residual scale > 0 px"):
        freespace_flow_loss(flow, road, _camera(), {"x_d": 0.0, "z_d": 1.0, "yaw": 0.0}, scale=scale)
    with pytest.raises(TypeError, match=r"^scale: expected a number, got str '1'$"):
        FreespaceFlowLoss(scale="1")


def test_unsupervised_loss_rejects_bad_images_and_ranges():
    image1, image2, flow = _shifted_pair(1)
    with pytest.raises(ValueError, match=r"image1: expected values in \[0, data_range=1\], got values in"):
        UnsupervisedFlowLoss(data_range=1.0)(flow, image1, image2)  # 0..255 images
    nan_image = image2.clone()
    nan_image[0, 1, 3, 4] = float("nan")
    with pytest.raises(ValueError, match=r"image2: expected finite pixel values, got \[nan\]"):
        UnsupervisedFlowLoss()(flow, image1, nan_image)
    bad_flow = flow.clone()
    bad_flow[0, 0, 5, 5] = float("inf")
    with pytest.raises(ValueError, match=r"flows\[1\]: expected finite values, got \[inf\]"):
        unsupervised_flow_loss([flow, bad_flow], image1, image2)
    with pytest.raises(ValueError, match=r"flows_backward\[0\]: expected finite values"):
        unsupervised_flow_loss(flow, image1, image2, flows_backward=bad_flow)
    for bad in (float("nan"), 0.0, -1.0, float("inf")):
        with pytest.raises(ValueError, match="data_range: expected a positive finite number"):
            UnsupervisedFlowLoss(data_range=bad)
        with pytest.raises(ValueError, match="data_range: expected a positive finite number"):
            photometric_loss(image1, image2, flow, data_range=bad)
        with pytest.raises(ValueError, match="data_range: expected a positive finite number"):
            smoothness_loss(flow, image1, data_range=bad)
    with pytest.raises(ValueError, match="ssim_weight: expected a number >= 0"):
        UnsupervisedFlowLoss(ssim_weight=-1.0)


def test_one_pixel_images():
    """The unsupervised loss on 1-pixel images once failed inside the SSIM padding."""
    image = torch.full((1, 3, 1, 1), 100.0)
    flow = torch.zeros(1, 2, 1, 1)
    with pytest.raises(ValueError, match=r"image1: the SSIM term needs H and W >= 2, got shape \(1, 3, 1, 1\)"):
        UnsupervisedFlowLoss()(flow, image, image)
    value = UnsupervisedFlowLoss(ssim_weight=0.0, census_weight=1.0)(flow, image, image)
    assert torch.isfinite(value)
    row = torch.rand(1, 3, 1, 9, generator=torch.Generator().manual_seed(0)) * 255
    with pytest.raises(ValueError, match=r"image1: the SSIM term needs H and W >= 2"):
        photometric_loss(row, row, torch.zeros(1, 2, 1, 9))
    with pytest.raises(ValueError, match=r"image1: expected shape \(B, C, H, W\) with H >= 1"):
        UnsupervisedFlowLoss()(torch.zeros(1, 2, 0, 4), image[..., :0, :4], image[..., :0, :4])


# -- the terms against references written out here (numpy) ---------------------------------------

def _np_pair(seed: int = 0, H: int = 9, W: int = 11):
    """Two unrelated textured RGB images on 0..255 (float64 numpy, (3, H, W)): a pair with error."""
    rng = np.random.default_rng(seed)
    image1 = rng.uniform(0, 255, (3, H, W))
    image2 = np.clip(0.7 * image1 + 0.3 * rng.uniform(0, 255, (3, H, W)) + 10, 0, 255)
    return image1, image2


def _t(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a)).unsqueeze(0)


def _box3(a: np.ndarray) -> np.ndarray:
    """Mean over 3x3 windows of (C, H, W), reflect-padded (the edge pixel not repeated)."""
    p = np.pad(a, ((0, 0), (1, 1), (1, 1)), mode="reflect")
    H, W = a.shape[-2:]
    return sum(p[:, dy:dy + H, dx:dx + W] for dy in range(3) for dx in range(3)) / 9


def test_photometric_ssim_term_matches_a_3x3_box_ssim_written_out():
    """ssim_weight alone: (1 - SSIM)/2, SSIM over 3x3 box windows (reflect padding, c1 = 0.01²,
    c2 = 0.03², images on 0..1), mean over channels, clipped to [0, 1], mean over pixels."""
    a, b = _np_pair()
    x, y = a / 255, b / 255
    mx, my = _box3(x), _box3(y)
    vx, vy, cxy = _box3(x * x) - mx ** 2, _box3(y * y) - my ** 2, _box3(x * y) - mx * my
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    ssim = (2 * mx * my + c1) * (2 * cxy + c2) / ((mx ** 2 + my ** 2 + c1) * (vx + vy + c2))
    want = np.clip((1 - ssim.mean(axis=0)) / 2, 0, 1).mean()
    assert want > 0.05  # a pair with error
    got = photometric_loss(_t(a), _t(b), torch.zeros(1, 2, *a.shape[-2:], dtype=torch.float64),
                           l1_weight=0.0, ssim_weight=1.0)
    assert float(got) == pytest.approx(want, rel=1e-9)


def _np_soft_census(rgb: np.ndarray, radius: int = 3) -> np.ndarray:
    """UFlow's soft census of an RGB image on 0..255 ((3, H, W)): per offset q - p of the
    (2r+1)² window (border replicated), δ / sqrt(0.81 + δ²) of the BT.601 grey levels."""
    grey = 0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2]
    H, W = grey.shape
    k = 2 * radius + 1
    p = np.pad(grey, radius, mode="edge")
    out = []
    for dy in range(k):
        for dx in range(k):
            d = p[dy:dy + H, dx:dx + W] - grey
            out.append(d / np.sqrt(0.81 + d * d))
    return np.stack(out)


def test_photometric_census_term_matches_the_uflow_formula_written_out():
    """census_weight alone: (Σ_offsets d²/(0.1 + d²) + 0.01)^0.4 per pixel, d the difference of
    the 7x7 soft census transforms, mean over pixels."""
    a, b = _np_pair(seed=1)
    d2 = (_np_soft_census(a) - _np_soft_census(b)) ** 2
    want = ((d2 / (0.1 + d2)).sum(axis=0) + 0.01) ** 0.4
    want = want.mean()
    assert want > 1.0
    got = photometric_loss(_t(a), _t(b), torch.zeros(1, 2, *a.shape[-2:], dtype=torch.float64),
                           l1_weight=0.0, ssim_weight=0.0, census_weight=1.0)
    assert float(got) == pytest.approx(want, rel=1e-9)
    # on 0..1 images the same value (compared on the 0..255 scale)
    on_1 = photometric_loss(_t(a / 255), _t(b / 255), torch.zeros(1, 2, *a.shape[-2:], dtype=torch.float64),
                            l1_weight=0.0, ssim_weight=0.0, census_weight=1.0, data_range=1.0)
    assert float(on_1) == pytest.approx(want, rel=1e-9)


def _np_smoothness_first_order(flow: np.ndarray, image: np.ndarray, edge_weight: float) -> float:
    """exp(-w · mean_c |∇I|) · |∇F| (I on 0..1, forward differences), mean over the flow's
    channels and the pixels of each direction, the two directions averaged."""
    img = image / 255
    wx = np.exp(-edge_weight * np.abs(np.diff(img, axis=2)).mean(axis=0))
    wy = np.exp(-edge_weight * np.abs(np.diff(img, axis=1)).mean(axis=0))
    sx = (wx * np.abs(np.diff(flow, axis=2))).mean()
    sy = (wy * np.abs(np.diff(flow, axis=1))).mean()
    return (sx + sy) / 2


def test_smoothness_is_edge_aware_as_documented():
    """A flow step on an image edge: the first-order loss equals the edge-aware form written out,
    and the edge makes it cheaper than without edge weights."""
    rng = np.random.default_rng(2)
    H_, W_ = 8, 10
    image = rng.uniform(90, 110, (3, H_, W_))
    image[:, :, 5:] += 120  # a strong vertical edge between columns 4 and 5 ...
    flow = rng.normal(0, 0.05, (2, H_, W_))
    flow[0, :, 5:] += 3.0  # ... where the flow jumps by 3 px
    got = smoothness_loss(_t(flow), _t(image), order=1, edge_weight=10.0)
    want = _np_smoothness_first_order(flow, image, 10.0)
    assert float(got) == pytest.approx(want, rel=1e-9)
    plain = smoothness_loss(_t(flow), _t(image), order=1, edge_weight=0.0)
    assert float(plain) == pytest.approx(_np_smoothness_first_order(flow, image, 0.0), rel=1e-9)
    assert float(got) < 0.5 * float(plain)


def test_occlusion_mask_leaves_out_the_pixels_failing_the_forward_backward_check():
    """image2 is image1 moved 2 px right, darker, with a patch of new content; the backward flow is
    inconsistent (+5 px instead of -2) on that patch. With occlusion, the forward direction counts
    only the pixels whose sample point lies off the patch (and in the image), the backward one only
    the pixels off the patch: the L1 means over those pixels, computed here by hand."""
    rng = np.random.default_rng(3)
    H_, W_, s = 10, 16, 2
    a = rng.uniform(20, 230, (3, H_, W_))
    b = np.roll(a, s, axis=2) * 0.9 + 5.0
    patch = (slice(3, 7), slice(8, 12))
    b[:, patch[0], patch[1]] = rng.uniform(0, 255, (3, 4, 4))  # new content in image2
    on_patch = np.zeros((H_, W_), dtype=bool)
    on_patch[patch] = True
    fw = np.zeros((2, H_, W_)); fw[0] = s
    bw = np.zeros((2, H_, W_)); bw[0] = np.where(on_patch, 5.0, -s)
    cols = np.arange(W_)[None, :].repeat(H_, 0)
    rows = np.arange(H_)[:, None].repeat(W_, 1)
    # forward: p -> p + 2 in image2; counts where inside image2 and not landing on the patch
    fw_in = cols + s <= W_ - 1
    land = np.zeros((H_, W_), dtype=bool)
    land[fw_in] = on_patch[rows[fw_in], cols[fw_in] + s]
    err_fw = np.zeros((H_, W_))
    err_fw[fw_in] = np.abs(a[:, rows[fw_in], cols[fw_in]] - b[:, rows[fw_in], cols[fw_in] + s]).mean(axis=0) / 255
    # backward: q -> q + bw(q) in image1; counts where inside image1 and off the patch
    target = cols + bw[0].astype(int)
    bw_in = (target >= 0) & (target <= W_ - 1)
    err_bw = np.zeros((H_, W_))
    err_bw[bw_in] = np.abs(b[:, rows[bw_in], cols[bw_in]] - a[:, rows[bw_in], target[bw_in]]).mean(axis=0) / 255

    def mean(err, keep):
        return err[keep].mean()

    want_masked = (mean(err_fw, fw_in & ~land) + mean(err_bw, bw_in & ~on_patch)) / 2
    want_unmasked = (mean(err_fw, fw_in) + mean(err_bw, bw_in)) / 2
    options = dict(flows_backward=_t(bw), l1_weight=1.0, ssim_weight=0.0, smooth_weight=0.0)
    masked = unsupervised_flow_loss(_t(fw), _t(a), _t(b), occlusion=True, **options)
    unmasked = unsupervised_flow_loss(_t(fw), _t(a), _t(b), occlusion=False, **options)
    assert float(masked) == pytest.approx(want_masked, rel=1e-9)
    assert float(unmasked) == pytest.approx(want_unmasked, rel=1e-9)
    assert want_unmasked > 1.5 * want_masked  # the patch's error is what the mask leaves out


def test_forward_backward_mask_threshold_grows_with_the_flow():
    """|F_f + F_b(p + F_f)|² < α1 (|F_f|² + |F_b(p + F_f)|²) + α2 at large flows (20 px): a
    mismatch of 2 px (4 px² > α2 = 0.5) passes thanks to the relative term, one of 3 px does not."""
    H_, W_ = 6, 40
    fw = torch.zeros(1, 2, H_, W_, dtype=torch.float64)
    fw[:, 0] = 20.0
    for err, visible in ((2.0, True), (2.7, True), (2.9, False), (3.0, False)):
        bw = torch.zeros_like(fw)
        bw[:, 0] = -20.0 + err
        diff, mag = err ** 2, 20.0 ** 2 + (20.0 - err) ** 2
        assert (diff < 0.01 * mag + 0.5) == visible and diff > 0.5  # the relative term decides
        mask = forward_backward_mask(fw, bw)
        assert bool(mask[..., : W_ - 20].all()) == visible and not mask[..., W_ - 20:].any(), err


def _arflow_gradient(data: torch.Tensor):
    """ARFlow's ``gradient`` (losses/flow_loss.py), as written there."""
    D_dy = data[:, :, 1:] - data[:, :, :-1]
    D_dx = data[:, :, :, 1:] - data[:, :, :, :-1]
    return D_dx, D_dy


def _arflow_smooth_grad_2nd(flo: torch.Tensor, image: torch.Tensor, alpha: float) -> torch.Tensor:
    """ARFlow's ``smooth_grad_2nd`` (losses/flow_loss.py), as written there (image on 0..1)."""
    img_dx, img_dy = _arflow_gradient(image)
    weights_x = torch.exp(-torch.mean(torch.abs(img_dx), 1, keepdim=True) * alpha)
    weights_y = torch.exp(-torch.mean(torch.abs(img_dy), 1, keepdim=True) * alpha)

    dx, dy = _arflow_gradient(flo)
    dx2, dxdy = _arflow_gradient(dx)
    dydx, dy2 = _arflow_gradient(dy)

    loss_x = weights_x[:, :, :, 1:] * dx2.abs()
    loss_y = weights_y[:, :, 1:, :] * dy2.abs()

    return loss_x.mean() / 2. + loss_y.mean() / 2.


def test_smoothness_second_order_matches_arflow_smooth_grad_2nd():
    """The second-order term weights the second difference centred on pixel i+1 (from i, i+1,
    i+2) with the image gradient between i+1 and i+2, as ARFlow does ([..., 1:]), not [..., :-1]."""
    g = torch.Generator().manual_seed(3)
    image = torch.rand(2, 3, 12, 15, generator=g, dtype=torch.float64) * 255
    flow = torch.randn(2, 2, 12, 15, generator=g, dtype=torch.float64) * 2
    for alpha in (10.0, 3.0):
        want = _arflow_smooth_grad_2nd(flow, image / 255, alpha)
        torch.testing.assert_close(smoothness_loss(flow, image, order=2, edge_weight=alpha), want,
                                   rtol=1e-12, atol=0.0)
        per_sample = smoothness_loss(flow, image, order=2, edge_weight=alpha, reduction="none")
        for b in range(2):
            one = _arflow_smooth_grad_2nd(flow[b:b + 1], image[b:b + 1] / 255, alpha)
            torch.testing.assert_close(per_sample[b], one, rtol=1e-12, atol=0.0)


def test_freespace_rejects_a_velocity_motion_as_the_target():
    """The "velocity" model's flow is px/s: a per-frame prediction cannot be compared with it
    (its exact px/s flow would otherwise give a large loss, not 0)."""
    cam = _camera()
    model, valid = displacement_flow(cam, 0.0, 1.2, 0.0, (H, W))
    for odometry in ({"model": "velocity", "speed": 12.0}, {"model": "velocity", "speed": 12.0, "yaw_rate": 0.1}):
        with pytest.raises(ValueError, match=r"odometry: the 'velocity' model gives flow in px/s.*displacement model"):
            freespace_flow_loss(model, valid, cam, odometry)
        with pytest.raises(ValueError, match=r"odometry: the 'velocity' model gives flow in px/s"):
            FreespaceFlowLoss()(model, valid, cam, odometry)
    # a displacement model's motion over the frame interval is still taken, as before
    assert freespace_flow_loss(model, valid, cam, {"model": "paper", "z_d": 1.2}) == pytest.approx(0.0, abs=1e-12)
    assert freespace_flow_loss(model, valid, cam, {"model": "plane", "z_d": 1.2}) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("fit_options, error, match", [
    ({"bogus": 1}, TypeError, r"fit_options: unknown options \['bogus'\]"),
    (42, TypeError, "fit_options: expected None or a dict"),
    # the fit's model names its key; the "velocity" model (px/s) is no per-frame target (was: taken, and
    # the fit mode's target was the linearised flow of a rate fitted to pixels per frame)
    ({"model": "velocity"}, ValueError, r"^fit_options\['model'\]: the 'velocity' model gives flow in px/s, not the "
                                        r"pixels per frame the loss compares; fit a displacement model"),
    ({"model": "bogus"}, ValueError, r"^fit_options\['model'\]: expected one of \('paper', "),
    ({"model": 3}, TypeError, r"^fit_options\['model'\]: expected one of"),
])
def test_freespace_checks_fit_options_with_a_given_odometry_as_its_module_does(fit_options, error, match):
    cam = _camera()
    model, valid = displacement_flow(cam, 0.0, 1.0, 0.0, (H, W))
    with pytest.raises(error, match=match):
        freespace_flow_loss(model, valid, cam, {"x_d": 0.0, "z_d": 1.0, "yaw": 0.0}, fit_options=fit_options)
    with pytest.raises(error, match=match):
        FreespaceFlowLoss(fit_options=fit_options)
    with pytest.raises(error, match=match):
        FreespaceFlowLoss(odometry="fit", fit_options=fit_options)
    with pytest.raises(error, match=match):
        freespace_flow_loss(model, valid, cam, "fit", fit_options=fit_options)
    # valid options that only odometry="fit" uses are accepted (unused) with a given odometry
    assert freespace_flow_loss(model, valid, cam, {"x_d": 0.0, "z_d": 1.0, "yaw": 0.0},
                               fit_options={"fit_roll": True}) == pytest.approx(0.0, abs=1e-12)
    for road_model in ("paper", "plane", "homography"):  # (the displacement models, fitted)
        assert freespace_flow_loss(model, valid, cam, "fit", fit_options={"model": road_model}) < 1e-6


def test_gamma_and_scale_that_require_grad_are_refused():
    """gamma and scale are read as numbers: a tensor that requires grad (a learnable residual
    scale, say) was taken, its gradient lost in silence (scale.grad stayed None after backward),
    so it never changed; the weights of the unsupervised terms, used as given, do get theirs."""
    cam = _camera()
    model, valid = displacement_flow(cam, 0.0, 1.0, 0.0, (H, W))
    flow = (model + 0.5).requires_grad_(True)
    image1, image2, _ = _shifted_pair(2)
    learnable = torch.nn.Parameter(torch.tensor(0.9, dtype=torch.float64))
    match = r"^{}: expected a fixed number, got a tensor that requires grad"
    with pytest.raises(TypeError, match=match.format("scale")):
        freespace_flow_loss(flow, valid, cam, _odometry(1), scale=learnable)
    with pytest.raises(TypeError, match=match.format("scale")):
        FreespaceFlowLoss(scale=learnable)
    with pytest.raises(TypeError, match=match.format("gamma")):
        freespace_flow_loss([flow, flow], valid, cam, _odometry(1), gamma=learnable)
    with pytest.raises(TypeError, match=match.format("gamma")):
        FreespaceFlowLoss(gamma=learnable)
    with pytest.raises(TypeError, match=match.format("gamma")):
        unsupervised_flow_loss(torch.zeros(2, 2, H, W), image1, image2, gamma=learnable)
    with pytest.raises(TypeError, match=match.format("gamma")):
        UnsupervisedFlowLoss(gamma=learnable)
    with pytest.raises(TypeError, match=match.format("gamma")):
        sequence_weights(3, learnable)
    # a fixed 0-d tensor is read as its number, as before
    fixed = learnable.detach()
    assert freespace_flow_loss(flow, valid, cam, _odometry(1), scale=fixed) == freespace_flow_loss(
        flow, valid, cam, _odometry(1), scale=0.9)
    assert sequence_weights(3, fixed) == sequence_weights(3, 0.9)
    # (a weight of the unsupervised loss enters its arithmetic as given: its gradient is kept)
    weight = torch.nn.Parameter(torch.tensor(2.0, dtype=torch.float64))
    flows = torch.zeros(2, 2, H, W, dtype=torch.float64)
    flows[:, 0, :, W // 2:] = 1.0
    unsupervised_flow_loss(flows, image1, image2, smooth_weight=weight).backward()
    expected = smoothness_loss(flows, image1)
    assert weight.grad is not None and weight.grad.item() == pytest.approx(expected.item(), rel=1e-9)
