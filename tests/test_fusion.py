"""FreespaceRefiner / FreespaceRefined: structures, invariants, gradients, bad input, wrappers."""

from __future__ import annotations

import warnings

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from fsof_torch.geometry.camera import Camera
from fsof_torch.geometry.egomotion import EgoMotion
from fsof_torch.geometry.road_flow import displacement_flow
from fsof_torch.refinement.gate import GateResult, ImageGate
from fsof_torch.refinement.fusion import (
    FreespaceRefiner,
    RefineOutput,
    cauchy_weight,
    fuse_flow,
    refine_flow,
    resize_mask,
)
from fsof_torch.refinement.wrapped import FreespaceRefined

H, W = 48, 120
ODO = {"x_d": 0.05, "z_d": 1.0, "yaw": 0.01}


def make_camera(dtype=torch.float64, B=1, **kw) -> Camera:
    K = torch.tensor([[90.0, 0, 60.0], [0, 90.0, 14.0], [0, 0, 1]], dtype=dtype)
    return Camera(K.expand(B, 3, 3), 1.65, **kw)


def make_case(B=1, dtype=torch.float32, size=(H, W), noise=1.0, seed=0):
    """Model flow of ODO, a noisy prediction, a road mask (model valid, below row 24)."""
    g = torch.Generator().manual_seed(seed)
    cam = make_camera(B=B)
    gt, valid = displacement_flow(make_camera(), ODO["x_d"], ODO["z_d"], ODO["yaw"], size)
    gt, valid = gt.expand(B, 2, *size), valid.expand(B, 1, *size)
    pred = (gt + noise * torch.randn(gt.shape, generator=g, dtype=gt.dtype)).to(dtype)
    mask = valid.clone()
    mask[..., : size[0] // 2, :] = False
    return pred, mask, cam, gt


def road_epe(flow, gt, mask):
    return (flow.double() - gt.double()).norm(dim=1)[mask[:, 0]].mean().item()


# -- smoke --------------------------------------------------------------------------------------

def test_smoke_replace_with_odometry():
    pred, mask, cam, gt = make_case()
    out = FreespaceRefiner()(pred, mask, cam, ODO)
    assert isinstance(out, RefineOutput)
    assert out.flow.shape == pred.shape and out.flow.dtype == pred.dtype
    assert road_epe(out.flow, gt, mask) < 1e-4 < road_epe(pred, gt, mask)
    assert torch.equal(out.weight, out.mask.to(pred.dtype))
    assert out.fit is None and bool(out.refined.all())
    assert out.flow_model.shape == (1, 2, H, W)


def test_module_repr_and_options():
    r = FreespaceRefiner(mode="confidence", scale=3.0)
    assert "confidence" in repr(r) and "scale=3.0" in repr(r)


def test_ego_motion_odometry_equals_dict():
    pred, mask, cam, _ = make_case()
    ego = EgoMotion(torch.tensor([ODO["x_d"]]), torch.tensor([ODO["z_d"]]), torch.tensor([ODO["yaw"]]))
    a = FreespaceRefiner()(pred, mask, cam, ego).flow
    b = FreespaceRefiner()(pred, mask, cam, ODO).flow
    torch.testing.assert_close(a, b)


# -- invariants ---------------------------------------------------------------------------------

@pytest.mark.parametrize("mode", ["replace", "confidence"])
def test_outside_mask_bit_for_bit(mode):
    pred, mask, cam, _ = make_case(B=2)
    g = torch.Generator().manual_seed(3)
    mask = mask & (torch.rand(mask.shape, generator=g) > 0.3)  # ragged mask
    out = FreespaceRefiner(mode=mode)(pred, mask, cam, ODO)
    outside = ~mask.expand_as(pred)
    assert torch.equal(out.flow[outside], pred[outside])
    assert bool((out.weight[~mask] == 0).all())


@pytest.mark.parametrize("mode", ["replace", "confidence"])
def test_caller_tensors_not_modified(mode):
    pred, mask, cam, _ = make_case()
    low = F.interpolate(pred, scale_factor=0.5, mode="bilinear") * 0.5
    odo = {k: torch.tensor([v], dtype=torch.float64) for k, v in ODO.items()}
    saved = [t.clone() for t in (pred, low, mask, cam.K, cam.height, *odo.values())]
    FreespaceRefiner(mode=mode)([low, pred], mask, cam, odo)
    for before, after in zip(saved, (pred, low, mask, cam.K, cam.height, *odo.values())):
        assert torch.equal(before, after)


def test_samples_are_independent():
    pred, mask, cam, _ = make_case(B=3)
    out3 = FreespaceRefiner()(pred, mask, cam, ODO).flow
    out1 = FreespaceRefiner()(pred[1:2], mask[1:2], make_camera(), ODO)
    torch.testing.assert_close(out3[1:2], out1.flow)


# -- cardinality ----------------------------------------------------------------------------------

@pytest.mark.parametrize("B", [1, 3])
@pytest.mark.parametrize("size", [(40, 100), (64, 48)])
def test_cardinality(B, size, dtype):
    pred, mask, cam, gt = make_case(B=B, dtype=dtype, size=size)
    odo = {k: torch.full((B,), v, dtype=dtype) for k, v in ODO.items()}
    out = FreespaceRefiner()(pred, mask, cam.to(dtype), odo)
    assert out.flow.shape == (B, 2, *size) and out.flow.dtype == dtype
    assert out.mask.shape == (B, 1, *size) and out.refined.shape == (B,)
    assert out.odometry["z_d"].shape == (B,)
    assert road_epe(out.flow, gt, out.mask) < 1e-3


# -- structures -----------------------------------------------------------------------------------

def _pyramid(pred, levels=(1, 2, 4)):
    return [pred if s == 1 else F.interpolate(pred, scale_factor=1 / s, mode="area") / s for s in levels]


def test_list_of_iterations():
    pred, mask, cam, gt = make_case()
    flows = [pred * 0.5, pred * 0.9, pred]
    out = FreespaceRefiner()(flows, mask, cam, ODO)
    assert isinstance(out.flow, list) and len(out.flow) == 3
    for f in out.flow:
        assert road_epe(f, gt, mask) < 1e-4


def test_low_up_pair_each_at_own_resolution():
    pred, mask, cam, gt = make_case()
    low = F.interpolate(pred, scale_factor=0.25, mode="area") * 0.25
    out = FreespaceRefiner()((low, pred), mask, cam, ODO)
    assert isinstance(out.flow, tuple) and out.flow[0].shape == low.shape
    gt_low, _ = displacement_flow(cam.scaled(0.25), ODO["x_d"], ODO["z_d"], ODO["yaw"], low.shape[-2:])
    m_low = resize_mask(mask, low.shape[-2:])
    assert bool(m_low.any())
    assert road_epe(out.flow[0], gt_low, m_low) < 1e-4
    assert torch.equal(out.flow[0][~m_low.expand_as(low)], low[~m_low.expand_as(low)])


def test_low_level_model_matches_resampled_full_resolution_model():
    """Our choice: a coarse level's model comes from the scaled camera; it agrees with the
    full-resolution model flow area-averaged and scaled (to interpolation error)."""
    cam = make_camera(roll=0.02)
    size = (128, 320)
    cam = Camera(cam.K * torch.tensor([[2.0, 1, 2.0], [1, 2.0, 2.0], [1, 1, 1]], dtype=torch.float64), 1.65, roll=0.02)
    full, valid = displacement_flow(cam, 0.1, 1.2, 0.02, size)
    for s in (2, 4, 8):
        low = torch.zeros(1, 2, size[0] // s, size[1] // s, dtype=torch.float64)
        out = refine_flow([full, low], valid, cam, {"x_d": 0.1, "z_d": 1.2, "yaw": 0.02})
        resampled = F.interpolate(full, size=low.shape[-2:], mode="area") / s
        m = resize_mask(valid, low.shape[-2:]) & (out.flow[1] != 0).any(1, keepdim=True)
        diff = (out.flow[1] - resampled).norm(dim=1)[m[:, 0]]
        assert diff.numel() > 0 and diff.max().item() < 0.02 and diff.mean().item() < 0.01


def test_arflow_dict_backward_untouched():
    pred, mask, cam, gt = make_case()
    bw = [-p for p in _pyramid(pred)]
    res = {"flows_fw": _pyramid(pred), "flows_bw": bw, "note": "x"}
    out = FreespaceRefiner()(res, mask, cam, ODO)
    assert set(out.flow) == {"flows_fw", "flows_bw", "note"}
    assert out.flow["flows_bw"] is bw and out.flow["note"] == "x"
    assert [f.shape for f in out.flow["flows_fw"]] == [f.shape for f in res["flows_fw"]]
    assert road_epe(out.flow["flows_fw"][0], gt, mask) < 1e-4
    assert not torch.equal(out.flow["flows_fw"][2], res["flows_fw"][2])  # coarse level refined too


def test_ptlflow_dict():
    pred, mask, cam, gt = make_case(B=2)
    occ = torch.zeros(2, 1, 1, H, W)
    res = {"flows": torch.stack([pred, pred * 2], dim=1), "occs": occ, "flow_preds": [pred, pred]}
    out = FreespaceRefiner()(res, mask, cam, ODO)
    assert out.flow["flows"].shape == (2, 2, 2, H, W) and out.flow["occs"] is occ
    for n in range(2):
        assert road_epe(out.flow["flows"][:, n], gt, mask) < 1e-4
    assert isinstance(out.flow["flow_preds"], list)


def test_dict_without_flow_keys():
    pred, mask, cam, _ = make_case()
    with pytest.raises(ValueError, match="no flow found"):
        FreespaceRefiner()({"other": pred}, mask, cam, ODO)
    out = FreespaceRefiner(flow_keys=("other",))({"other": pred}, mask, cam, ODO)
    assert out.flow["other"].shape == pred.shape


# -- confidence fusion ------------------------------------------------------------------------------

def test_fuse_flow_formula():
    pred = torch.tensor([[[[3.0]], [[4.0]]]])
    model = torch.zeros_like(pred)
    mask = torch.ones(1, 1, 1, 1, dtype=torch.bool)
    out, w = fuse_flow(pred, model, mask, mode="confidence", scale=5.0)
    assert w.item() == pytest.approx(0.5)  # r = 5 = c
    torch.testing.assert_close(out, 0.5 * pred)
    assert cauchy_weight(torch.tensor(0.0), 1.0).item() == 1.0


def test_confidence_keeps_a_car_inside_the_mask():
    pred, mask, cam, gt = make_case(noise=0.3)
    car = torch.zeros_like(mask)
    car[..., 30:40, 40:70] = True
    pred = torch.where(car & mask, pred + torch.tensor([15.0, -2.0]).reshape(1, 2, 1, 1), pred)
    conf = FreespaceRefiner(mode="confidence", scale=2.0)(pred, mask, cam, ODO)
    repl = FreespaceRefiner(mode="replace")(pred, mask, cam, ODO)
    in_car = (car & mask)[:, 0]
    car_keep = (conf.flow - pred).norm(dim=1)[in_car].mean().item()
    assert car_keep < 0.5  # the car keeps (nearly) its flow
    assert (repl.flow - pred).norm(dim=1)[in_car].mean().item() > 14  # replace overwrites it
    road = mask & ~car
    assert road_epe(conf.flow, gt, road) < 0.5 * road_epe(pred, gt, road)


# -- gradients --------------------------------------------------------------------------------------

@pytest.mark.parametrize("mode", ["replace", "confidence"])
def test_gradcheck_prediction_camera_odometry(mode):
    size = (8, 12)
    K = torch.tensor([[10.0, 0, 6.0], [0, 10.0, 2.0], [0, 0, 1]], dtype=torch.float64)
    base = Camera(K, 1.65)
    gt, valid = displacement_flow(base, 0.0, 1.0, 0.0, size)
    g = torch.Generator().manual_seed(0)
    pred = (gt + torch.randn(gt.shape, generator=g, dtype=torch.float64)).requires_grad_()
    h = torch.tensor([1.65], dtype=torch.float64, requires_grad=True)
    z = torch.tensor([1.0], dtype=torch.float64, requires_grad=True)
    yaw = torch.tensor([0.01], dtype=torch.float64, requires_grad=True)
    mask = valid.clone()
    mask[..., 5:, :3] = False

    def f(pred, h, z, yaw):
        out = refine_flow(pred, mask, Camera(K, h), {"x_d": 0.0, "z_d": z, "yaw": yaw}, mode=mode,
                          min_pixels=1)
        return out.flow

    assert torch.autograd.gradcheck(f, (pred, h, z, yaw))


def test_gradients_reach_prediction_outside_and_camera_inside():
    pred, mask, cam, _ = make_case()
    pred = pred.double().requires_grad_()
    K = cam.K.clone().requires_grad_()
    z = torch.tensor([1.0], dtype=torch.float64, requires_grad=True)
    out = FreespaceRefiner()(pred, mask, Camera(K, 1.65), {"x_d": 0.0, "z_d": z, "yaw": 0.0})
    out.flow.sum().backward()
    assert torch.equal(pred.grad, (~mask).expand_as(pred).double())  # replace: outside only
    assert K.grad.abs().sum() > 0 and z.grad.abs().sum() > 0


# -- bad input --------------------------------------------------------------------------------------

def test_mask_of_a_different_size():
    pred, mask, cam, _ = make_case()
    with pytest.raises(ValueError, match=r"mask: expected shape \(1, 1, 48, 120\)"):
        FreespaceRefiner()(pred, mask[..., :-1], cam, ODO)


def test_mask_not_bool():
    pred, mask, cam, _ = make_case()
    with pytest.raises(TypeError, match="mask: expected a bool tensor"):
        FreespaceRefiner()(pred, mask.float(), cam, ODO)


@pytest.mark.parametrize("odometry", [ODO, None])
def test_all_false_mask_returns_prediction_with_warning(odometry):
    pred, mask, cam, _ = make_case()
    with pytest.warns(RuntimeWarning, match="left unchanged"):
        out = FreespaceRefiner()([pred, pred], torch.zeros_like(mask), cam, odometry)
    assert torch.equal(out.flow[0], pred) and torch.equal(out.flow[1], pred)
    assert not bool(out.refined.any()) and not bool(out.mask.any())


def test_a_mask_of_too_few_pixels_to_estimate_from_is_named_in_the_warning():
    """Without odometry a sample with fewer usable mask pixels than min_pixels (50 of 100) is left
    unchanged: the warning gives that reason (it listed an empty mask, an undefined model, a failed
    estimate and the gate, none of which applied). With odometry such a mask is refined."""
    pred, mask, cam, _ = make_case(B=2)
    small = mask.clone()
    small[1] = False
    small[1, :, 40:45, 50:60] = True
    assert int(small[1].sum()) == 50 and bool(mask[1, :, 40:45, 50:60].all())
    with pytest.warns(RuntimeWarning, match=r"samples \[1\] left unchanged \(an empty mask or one where the model is "
                      r"undefined, too few mask pixels \(min_pixels\), a failed estimate"):
        out = FreespaceRefiner(gate=None)(pred, small, cam)
    assert out.refined.tolist() == [True, False] and torch.equal(out.flow[1], pred[1])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert FreespaceRefiner(gate=None)(pred, small, cam, ODO).refined.tolist() == [True, True]


@pytest.mark.parametrize("images", [False, True])
def test_a_mask_where_the_model_is_undefined_leaves_the_sample_unrefined_given_odometry(images):
    """Once refined True with no warning: with odometry and no gate only a mask pixel was asked for."""
    pred, mask, cam, _ = make_case(B=2)
    mask = mask.clone()
    mask[1] = False
    mask[1, :, :10] = True  # wholly above the horizon (row 14): the road model is undefined there
    kw = dict(gate=None, images=(torch.full((2, 1, H, W), 9.0), torch.full((2, 1, H, W), 9.0))) if images else {}
    with pytest.warns(RuntimeWarning, match=r"samples \[1\] left unchanged"):
        out = refine_flow(pred, mask, cam, {"model": "paper", **ODO}, **kw)
    assert out.refined.tolist() == [True, False] and not bool(out.mask[1].any())
    assert torch.equal(out.flow[1], pred[1]) and float(out.odometry["z_d"][1]) == 0.0


def test_nan_prediction_inside_and_outside_mask():
    pred, mask, cam, gt = make_case()
    bad = pred.clone()
    bad[0, :, 40, 10] = float("nan")  # inside the mask (row 40 is road)
    bad[0, 0, 2, 3] = float("nan")  # outside
    assert bool(mask[0, 0, 40, 10]) and not bool(mask[0, 0, 2, 3])
    for mode in ("replace", "confidence"):
        with pytest.warns(RuntimeWarning, match="non-finite"):
            out = FreespaceRefiner(mode=mode)(bad, mask, cam, ODO)
        assert torch.isfinite(out.flow[0, :, 40, 10]).all()
        torch.testing.assert_close(out.flow[0, :, 40, 10], gt[0, :, 40, 10].float())
        assert torch.isnan(out.flow[0, 0, 2, 3])
        assert torch.isfinite(out.flow[~torch.isnan(bad)]).all()


def test_a_prediction_not_finite_anywhere_in_the_mask_is_replaced_given_odometry():
    """With odometry the model flow needs no predicted pixel: a mask whose every prediction is
    NaN is still refined (the model replaces them, as the warning says), not left NaN."""
    pred, mask, cam, gt = make_case()
    bad = pred.clone()
    bad[mask.expand_as(bad)] = float("nan")
    with pytest.warns(RuntimeWarning, match="replaced by the model flow"):
        out = FreespaceRefiner()(bad, mask, cam, ODO)
    assert bool(out.refined.all())
    inside = mask.expand_as(bad)
    assert torch.isfinite(out.flow[inside]).all()
    torch.testing.assert_close(out.flow[inside], gt.float()[inside], rtol=0, atol=1e-4)
    assert torch.equal(out.flow[~inside], pred[~inside])


def test_confidence_scale_of_a_coarse_level_is_in_its_pixels():
    """A coarse level's Cauchy scale is the finest's times the level's linear size ratio (its flow is
    proportionally smaller): at half size c / 2, written out here with the level's model flow
    (displacement_flow with the scaled camera)."""
    pred, mask, cam, _ = make_case(dtype=torch.float64)
    size = (H // 2, W // 2)
    model, valid = displacement_flow(cam.scaled(0.5), ODO["x_d"], ODO["z_d"], ODO["yaw"], size)
    low = model + torch.tensor([0.6, -0.8], dtype=torch.float64).reshape(1, 2, 1, 1)  # r = 1 px everywhere
    out = FreespaceRefiner(mode="confidence", scale=2.0)([low, pred], mask, cam, ODO)
    m = (resize_mask(mask, size) & valid).expand(1, 2, *size)
    assert m.any()
    w = 1.0 / (1.0 + 1.0 / (2.0 * 0.5) ** 2)  # r = c: 1/2
    torch.testing.assert_close(out.flow[0][m], (w * model + (1 - w) * low)[m])


def test_nan_in_another_level_than_the_finest():
    """The finest flow's finiteness decides the fast path only for that level: a NaN in a
    coarser level of a list still gets the model inside the mask in confidence mode."""
    pred, mask, cam, gt = make_case()
    low = F.interpolate(pred, scale_factor=0.5, mode="bilinear", align_corners=False) * 0.5
    low[0, :, 20, 5] = float("nan")  # road at the coarse level (row 40 at full size)
    out = FreespaceRefiner(mode="confidence")([low, pred], mask, cam, ODO)
    coarse_mask = resize_mask(mask, low.shape[-2:])
    assert bool(coarse_mask[0, 0, 20, 5])
    assert torch.isfinite(out.flow[0][0, :, 20, 5]).all()
    assert torch.isfinite(out.flow[1]).all()


class _KeepsRows(ImageGate):
    """A gate that keeps the prediction from row 36 down, and everywhere in the samples ``reject``."""

    def __init__(self, reject=()):
        super().__init__()
        self.reject = reject

    def __call__(self, image1, image2, prediction, model, mask):
        B = prediction.shape[0]
        used = torch.tensor([b not in self.reject for b in range(B)])
        use = mask & used.reshape(B, 1, 1, 1)
        use[..., 36:, :] = False
        zeros = torch.zeros(B)
        return GateResult(use, use.float(), zeros, zeros, zeros.long(), zeros.long(), zeros.long(), used,
                          used, used, zeros)


@pytest.mark.parametrize("mode", ["replace", "confidence"])
def test_nan_where_the_gate_keeps_the_prediction_takes_the_model(mode):
    """In a refined sample a NaN predicted pixel inside the mask gets the model flow also where
    the gate keeps the prediction (in every level); in a sample the gate leaves unchanged it stays,
    and the warning says how many were replaced and how many left."""
    pred, mask, cam, gt = make_case(B=2)
    bad = pred.clone()
    bad[:, :, 40, 10] = float("nan")  # inside the mask, where the gate keeps the prediction
    bad[:, :, 30, 10] = float("nan")  # inside the mask, where the gate uses the model
    low = F.interpolate(pred, scale_factor=0.5, mode="bilinear", align_corners=False) * 0.5
    low[:, :, 22, 5] = float("nan")  # row 44 at full size: kept by the gate
    image = torch.rand(2, 1, H, W, generator=torch.Generator().manual_seed(0)) * 255
    # ODO as a complete motion: nothing to estimate from the images, which only the gate reads
    motion = {"model": "plane", **ODO, "pitch_change": 0.0, "roll_change": 0.0, "y_d": 0.0, "roll": 0.0, "pitch": 0.0}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = FreespaceRefiner(mode=mode, gate=_KeepsRows(reject=(1,)))([low, bad], mask, cam, motion,
                                                                         images=(image, image))
    messages = [str(w.message) for w in caught]
    assert "flow: 4 non-finite predicted pixels inside the mask, left out of the estimation; 2 replaced by the " \
           "model flow; 2 left as they came (in samples left unchanged, or where the model flow is undefined)" \
        in messages
    assert out.refined.tolist() == [True, False]
    torch.testing.assert_close(out.flow[1][0, :, 40, 10], gt[0, :, 40, 10].float(), rtol=0, atol=1e-4)
    torch.testing.assert_close(out.flow[1][0, :, 30, 10], gt[0, :, 30, 10].float(), rtol=0, atol=1e-4)
    assert bool(out.mask[0, 0, 40, 10]) and float(out.weight[0, 0, 40, 10]) == 1.0
    assert torch.isfinite(out.flow[0][0]).all() and torch.isfinite(out.flow[1][0]).all()
    # elsewhere in the kept rows the finite prediction comes back bit for bit
    kept = mask[0, 0].clone()
    kept[:36] = False
    kept[40, 10] = False
    assert torch.equal(out.flow[1][0][:, kept], pred[0][:, kept]) and not bool(out.mask[0, 0, kept].any())
    # the sample the gate leaves unchanged: as it came, NaN included
    torch.testing.assert_close(out.flow[1][1], bad[1], rtol=0, atol=0, equal_nan=True)
    torch.testing.assert_close(out.flow[0][1], low[1], rtol=0, atol=0, equal_nan=True)


class _KeepsAll(ImageGate):
    """A gate that uses the model over the whole mask by the sample's test, yet keeps the
    prediction in every cell (as a gate whose cells and objects all favour the prediction)."""

    def __call__(self, image1, image2, prediction, model, mask):
        B = prediction.shape[0]
        used, zeros = torch.ones(B, dtype=torch.bool), torch.zeros(B)
        return GateResult(torch.zeros_like(mask), torch.zeros(mask.shape), zeros, zeros, zeros.long(),
                          zeros.long(), zeros.long(), used, used, used, zeros)


@pytest.mark.parametrize("mode", ["replace", "confidence"])
def test_a_gate_that_keeps_the_prediction_everywhere_leaves_the_sample_unrefined(mode):
    """model_used True but use_model nowhere: the sample comes back unchanged, refined is False,
    its odometry 0, and the warning names it (once refined said True, silently)."""
    pred, mask, cam, gt = make_case(B=2)
    image = torch.rand(2, 1, H, W, generator=torch.Generator().manual_seed(0)) * 255
    motion = {"model": "plane", **ODO, "pitch_change": 0.0, "roll_change": 0.0, "y_d": 0.0, "roll": 0.0, "pitch": 0.0}
    with pytest.warns(RuntimeWarning, match=r"mask: samples \[0, 1\] left unchanged .*a gate that keeps the "
                                            r"prediction everywhere"):
        out = FreespaceRefiner(mode=mode, gate=_KeepsAll())(pred, mask, cam, motion, images=(image, image))
    assert out.refined.tolist() == [False, False]
    assert torch.equal(out.flow, pred) and not bool(out.mask.any()) and not bool(out.weight.any())
    assert all(bool((v == 0).all()) for v in out.odometry.values())
    # a NaN predicted pixel inside the mask is still replaced by the model (the gate's model_used):
    # that sample changes there, and only there, so it is refined
    bad = pred.clone()
    bad[0, :, 40, 10] = float("nan")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = FreespaceRefiner(mode=mode, gate=_KeepsAll())(bad, mask, cam, motion, images=(image, image))
    messages = [str(w.message) for w in caught]
    assert any(m.startswith("mask: samples [1] left unchanged") for m in messages)
    assert any("1 non-finite predicted pixels inside the mask" in m and "1 replaced" in m for m in messages)
    assert out.refined.tolist() == [True, False]
    changed = (out.flow != pred).any(1)
    assert changed.nonzero().tolist() == [[0, 40, 10]] and bool(out.mask[0, 0, 40, 10])
    torch.testing.assert_close(out.flow[0, :, 40, 10], gt[0, :, 40, 10].float(), rtol=0, atol=1e-4)


def test_a_bfloat16_prediction_is_the_float32_result_rounded():
    """Confidence fusion blends in float32: a bfloat16 prediction comes back as the float32
    prediction's result rounded to bfloat16 (and the weight likewise)."""
    pred, mask, cam, gt = make_case(noise=2.0)
    half = pred.bfloat16()
    for mode in ("replace", "confidence"):
        a = refine_flow(half, mask, cam, ODO, mode=mode)
        b = refine_flow(half.float(), mask, cam, ODO, mode=mode)
        assert a.flow.dtype == torch.bfloat16
        assert torch.equal(a.flow, b.flow.bfloat16()) and torch.equal(a.weight, b.weight.bfloat16())
    fused, weight = fuse_flow(half, gt.float(), mask, mode="confidence")
    plain, plain_weight = fuse_flow(half.float(), gt.float(), mask, mode="confidence")
    assert torch.equal(fused, plain.bfloat16()) and torch.equal(weight, plain_weight.bfloat16())




@pytest.mark.parametrize("camera_dtype", [torch.float32, torch.float64], ids=["cam32", "cam64"])
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64],
                         ids=["f16", "bf16", "f32", "f64"])
def test_the_outputs_dtypes(dtype, camera_dtype):
    """contracts.md's dtypes: each level in its own dtype, the weight in the finest's; the model
    flow, the motion, the camera and the fit in the finest flow's dtype lifted to float32 (the
    camera is cast to it), whatever the camera's."""
    pred, mask, _, _ = make_case()
    pred, camera = pred.to(dtype), make_camera(camera_dtype)
    work = torch.promote_types(dtype, torch.float32)
    for odometry in (ODO, None) if camera_dtype == torch.float64 else (ODO,):  # (None: a fit, the slow part)
        out = refine_flow([pred[..., ::2, ::2].float(), pred], mask, camera, odometry)
        assert [f.dtype for f in out.flow] == [torch.float32, dtype] and out.weight.dtype == dtype
        assert out.flow_model.dtype == work and out.camera.K.dtype == work
        assert {v.dtype for v in out.odometry.values()} == {work}
        assert odometry is not None or out.fit.flow.dtype == work

@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32], ids=["f16", "bf16", "f32"])
def test_a_model_flow_beyond_the_predictions_dtype_keeps_the_prediction(dtype):
    """A float16 prediction came back inf where the model flow exceeds float16's 65 504 px (road
    points the camera nearly reaches within the frame gap: a fast camera, a long gap). There the
    model is undefined for that prediction, which keeps its own flow, out of the mask; elsewhere
    the flow is the float32 result rounded. bfloat16 holds float32's range: nothing is left out.
    Another level is judged in its own dtype likewise."""
    camera, full = make_camera(), torch.ones(1, 1, H, W, dtype=torch.bool)
    odo = {**ODO, "z_d": 4.5}
    model, valid = displacement_flow(make_camera(torch.float32), odo["x_d"], odo["z_d"], odo["yaw"], (H, W))
    far = valid & (model.abs().amax(dim=1, keepdim=True) > torch.finfo(torch.float16).max)
    assert int(far.sum()) == 4  # (the case)
    kept = far if dtype == torch.float16 else torch.zeros_like(far)
    pred = (0.5 * torch.randn(1, 2, H, W, generator=torch.Generator().manual_seed(0))).to(dtype)
    for mode in ("replace", "confidence"):
        out = refine_flow(pred, full, camera, odo, mode=mode)
        ref = refine_flow(pred.float(), full, camera, odo, mode=mode)
        assert out.flow.dtype == dtype and bool(torch.isfinite(out.flow).all()), mode
        assert torch.equal(out.mask, ref.mask & ~kept), mode
        assert torch.equal(out.flow[kept.expand_as(pred)], pred[kept.expand_as(pred)]), mode
        assert torch.equal(out.flow[~kept.expand_as(pred)], ref.flow.to(dtype)[~kept.expand_as(pred)]), mode
    # another level in this dtype beside a float32 finest one (a list's last), whose mask holds them
    out, ref = refine_flow([pred, pred.float()], full, camera, odo), refine_flow(pred.float(), full, camera, odo)
    assert torch.equal(out.mask, ref.mask) and torch.equal(out.flow[1], ref.flow)
    assert torch.equal(out.flow[0][kept.expand_as(pred)], pred[kept.expand_as(pred)])
    assert torch.equal(out.flow[0][~kept.expand_as(pred)], ref.flow.to(dtype)[~kept.expand_as(pred)])


def test_fuse_flow_keeps_a_float16_prediction_where_it_cannot_hold_the_model_flow():
    """fuse_flow of a float16 prediction returned inf where the model flow inside the mask exceeds
    65 504 px ("replace" mode): the prediction keeps its own flow there (weight 0), in either mode;
    every other pixel is the float32 fusion rounded. bfloat16 holds float32's range."""
    pred, mask, _, gt = make_case()
    big = gt.float().clone()
    big[..., -1, :] = 1e5
    beyond = torch.zeros_like(mask)
    beyond[..., -1, :] = True
    beyond &= mask
    assert int(beyond.sum()) > 0
    for mode in ("replace", "confidence"):
        for dtype in (torch.float16, torch.bfloat16):
            half = pred.to(dtype)
            fused, weight = fuse_flow(half, big, mask, mode=mode)
            plain, plain_weight = fuse_flow(half.float(), big, mask, mode=mode)
            kept = beyond if dtype == torch.float16 else torch.zeros_like(beyond)
            both = kept.expand_as(half)
            assert bool(torch.isfinite(fused).all()), (mode, dtype)
            assert torch.equal(fused[both], half[both]) and not bool(weight[kept].any()), (mode, dtype)
            assert torch.equal(fused[~both], plain.to(dtype)[~both]), (mode, dtype)
            assert torch.equal(weight[~kept], plain_weight.to(dtype)[~kept]), (mode, dtype)


def test_float_odometry_is_taken_at_the_flows_dtype():
    """A float64 prediction with the odometry as Python floats: the model flow is the float64 one
    (once off by up to 2.5e-6 px: the floats were rounded to float32 first)."""
    pred, mask, _, _ = make_case()
    pred, cam = pred.double(), make_camera()
    plane = {"model": "plane", **ODO, "pitch_change": 0.003, "y_d": 0.02}
    for odometry in (ODO, plane):
        tensors = {k: (torch.tensor([v], dtype=torch.float64) if k != "model" else v) for k, v in odometry.items()}
        for mode in ("replace", "confidence"):
            a = refine_flow(pred, mask, cam, odometry, mode=mode, gate=None)
            b = refine_flow(pred, mask, cam, tensors, mode=mode, gate=None)
            assert a.flow.dtype == torch.float64
            assert torch.equal(a.flow, b.flow) and torch.equal(a.flow_model, b.flow_model), (odometry, mode)
    exact, _ = displacement_flow(cam, ODO["x_d"], ODO["z_d"], ODO["yaw"], (H, W))
    assert torch.equal(refine_flow(pred, mask, cam, ODO).flow_model, exact)


def test_images_on_another_device_than_the_flow_are_named():
    """The meta device stands in for another one: the images are named before any use."""
    pred, mask, cam, _ = make_case()
    image = torch.rand(1, 3, H, W, generator=torch.Generator().manual_seed(0)) * 255
    for images in ((image.to("meta"), image), (image, image.to("meta"))):
        which = 0 if images[0].device.type == "meta" else 1
        with pytest.raises(ValueError, match=rf"^images\[{which}\]: expected the device of the flow \(cpu\), got meta"):
            refine_flow(pred, mask, cam, ODO, images=images)


@pytest.mark.parametrize("coarse_on_meta", [True, False])
def test_levels_on_another_device_than_the_finest_are_named(coarse_on_meta):
    """A network output whose levels lie on two devices (meta standing in for another one) is
    named before any work, not torch's device error from inside the fusion."""
    pred, mask, cam, _ = make_case()
    coarse = pred[..., ::2, ::2] / 2
    levels = [coarse.to("meta"), pred] if coarse_on_meta else [coarse, pred.to("meta")]
    other, finest = ("meta", "cpu") if coarse_on_meta else ("cpu", "meta")
    with pytest.raises(ValueError, match=rf"^flow\[0\]: expected the device of the finest flow flow\[1\] "
                                         rf"\({finest}\), got {other}$"):
        refine_flow(levels, mask, cam, ODO)


def test_odometry_wrong_batch_size():
    pred, mask, cam, _ = make_case(B=2)
    odo = {"x_d": 0.0, "z_d": torch.ones(3), "yaw": 0.0}
    with pytest.raises(ValueError, match=r"odometry\['z_d'\]: expected .* shape \(1,\) or \(2,\) \(the flow's batch\)"):
        FreespaceRefiner()(pred, mask, cam, odo)


def test_odometry_missing_key_and_bad_type():
    pred, mask, cam, _ = make_case()
    with pytest.raises(ValueError, match="odometry: missing keys"):
        FreespaceRefiner()(pred, mask, cam, {"z_d": 1.0})
    with pytest.raises(TypeError, match="odometry: expected a dict"):
        FreespaceRefiner()(pred, mask, cam, [0.0, 1.0, 0.0])


def test_bad_options_and_flows():
    pred, mask, cam, _ = make_case()
    with pytest.raises(ValueError, match="mode: expected one of"):
        FreespaceRefiner(mode="blend")
    with pytest.raises(ValueError, match="scale: expected"):
        FreespaceRefiner(scale=0.0)
    with pytest.raises(ValueError, match=r"flow: expected a flow of shape"):
        FreespaceRefiner()(pred[:, :1], mask, cam, ODO)
    with pytest.raises(TypeError, match="flow: expected a flow tensor"):
        FreespaceRefiner()("flow", mask, cam, ODO)
    with pytest.raises(ValueError, match="camera: expected batch 1 "):
        FreespaceRefiner()(pred, mask, make_camera(B=2), ODO)


# -- fitted odometry (fsof_torch.estimation.flow_fit) ----------------------------------------------------------------

def test_fitted_odometry_recovers_motion_and_refines():
    pred, mask, cam, gt = make_case(B=2, noise=1.0)
    out = FreespaceRefiner()(pred, mask, cam)
    assert out.fit is not None and bool(out.refined.all())
    torch.testing.assert_close(out.odometry["z_d"], torch.full((2,), ODO["z_d"], dtype=pred.dtype),
                               atol=0.05, rtol=0)
    assert road_epe(out.flow, gt, mask) < 0.3 * road_epe(pred, gt, mask)
    assert not out.odometry["z_d"].requires_grad


def test_fitted_model_flow_is_the_fits_and_matches_the_model():
    """With fitted odometry the refiner reuses the fit's full-size model flow: it is the model
    of the fitted motion (displacement_flow of the returned camera and odometry)."""
    pred, mask, cam, gt = make_case(B=2, noise=1.0)
    out = FreespaceRefiner()(pred, mask, cam)
    assert out.flow_model is out.fit.flow or torch.equal(out.flow_model, out.fit.flow)
    again, valid = displacement_flow(out.camera, out.odometry["x_d"], out.odometry["z_d"],
                                     out.odometry["yaw"], (H, W))
    assert torch.equal(out.mask, mask & valid)
    torch.testing.assert_close(out.flow_model[valid.expand_as(again)], again[valid.expand_as(again)],
                               atol=1e-3, rtol=0)
    inside = out.mask.expand_as(pred)
    assert torch.equal(out.flow[inside], out.flow_model.to(pred.dtype)[inside])


def test_fitted_odometry_gradient_reaches_the_camera():
    """The fit is detached, but the model flow is recomputed on the caller's camera when that
    carries a graph, so the refined road flow is differentiable with respect to K and h."""
    pred, mask, _, _ = make_case(noise=0.5)
    K = make_camera(dtype=torch.float32).K.clone().requires_grad_(True)
    height = torch.tensor(1.65, requires_grad=True)
    out = FreespaceRefiner(warn=False)(pred, mask, Camera(K, height))
    assert bool(out.refined.all())
    (out.flow * mask).sum().backward()
    assert K.grad is not None and torch.isfinite(K.grad).all() and K.grad.abs().sum() > 0
    assert height.grad is not None and torch.isfinite(height.grad) and height.grad != 0


def test_fitted_odometry_with_one_empty_sample():
    pred, mask, cam, gt = make_case(B=2)
    mask = mask.clone()
    mask[1] = False
    with pytest.warns(RuntimeWarning, match=r"samples \[1\] left unchanged"):
        out = FreespaceRefiner()(pred, mask, cam)
    assert out.refined.tolist() == [True, False]
    assert torch.equal(out.flow[1], pred[1])
    assert road_epe(out.flow[:1], gt[:1], mask[:1]) < 0.5


# -- the wrapper ---------------------------------------------------------------------------------------

class StandIn(nn.Module):
    """A 'network' returning a noisy model flow in a chosen output structure, with one parameter."""

    def __init__(self, kind: str):
        super().__init__()
        self.kind = kind
        self.gain = nn.Parameter(torch.ones(()))

    def forward(self, image1, image2, iters=3):
        pred, _, _, _ = make_case(B=image1.shape[0])
        pred = pred * self.gain
        low = F.interpolate(pred, scale_factor=0.25, mode="area") * 0.25
        if self.kind == "tensor":
            return pred
        if self.kind == "list":
            return [pred * (i + 1) / iters for i in range(iters)]
        if self.kind == "pair":
            return low, pred
        if self.kind == "arflow":
            return {"flows_fw": _pyramid(pred), "flows_bw": [-f for f in _pyramid(pred)]}
        return {"flows": pred.unsqueeze(1), "flow_small": low}


@pytest.mark.parametrize("kind", ["tensor", "list", "pair", "arflow", "ptlflow"])
def test_wrapper_each_structure(kind):
    net = StandIn(kind)
    model = FreespaceRefined(net, FreespaceRefiner(fit="flow", gate=None))
    images = torch.zeros(2, 3, H, W)
    _, mask, cam, gt = make_case(B=2)
    raw = net(images, images)
    out, info = model(images, images, mask=mask, camera=cam, odometry=ODO, return_info=True)
    assert type(out) is type(raw)
    finest = {"tensor": lambda o: o, "list": lambda o: o[-1], "pair": lambda o: o[1],
              "arflow": lambda o: o["flows_fw"][0], "ptlflow": lambda o: o["flows"][:, 0]}[kind]
    assert road_epe(finest(out), gt, mask) < 1e-4
    outside = ~mask.expand(2, 2, H, W)
    assert torch.equal(finest(out)[outside], finest(raw)[outside])
    finest(out).sum().backward()  # gradients reach the network's parameters
    assert net.gain.grad is not None and net.gain.grad.abs() > 0


def test_wrapper_needs_a_mask():
    model = FreespaceRefined(StandIn("tensor"))
    images = torch.zeros(1, 3, H, W)
    with pytest.raises(ValueError, match="mask: expected a road mask"):
        model(images, images, camera=make_camera(), odometry=ODO)
    with pytest.raises(ValueError, match="road: expected None or 'auto'"):
        FreespaceRefined(StandIn("tensor"), road="yes")


def test_wrapper_with_the_test_net():
    from fsof_torch.training.testnet import TinyRAFT

    net = TinyRAFT(seed=0)
    # odometry used as given (no estimation from these unrelated images), no gate: the model replaces the mask
    model = FreespaceRefined(net, FreespaceRefiner(fit="flow", gate=None))
    g = torch.Generator().manual_seed(0)
    image1 = torch.rand(1, 3, H, W, generator=g) * 255
    image2 = torch.roll(image1, 1, dims=-1)
    _, mask, cam, gt = make_case()
    raw = net(image1, image2)
    out = model(image1, image2, mask=mask, camera=cam, odometry=ODO)
    assert isinstance(out, list) and len(out) == len(raw)
    assert road_epe(out[-1], gt, mask) < 1e-4
    assert torch.equal(out[-1][~mask.expand(1, 2, H, W)], raw[-1][~mask.expand(1, 2, H, W)])


def test_wrapper_road_auto():
    """With road='auto' the road is found in the two images; on textureless images it cannot be,
    and the output is the net's, with the reason in ``info.road``."""
    from fsof_torch.data.scene import render_pair

    p = render_pair("default", 30, size=(188, 621))

    class Noisy(nn.Module):
        def forward(self, image1, image2):
            return [p["flow"][None] + 2.0 * torch.randn(1, 2, 188, 621, generator=torch.Generator().manual_seed(0))]

    model = FreespaceRefined(Noisy(), FreespaceRefiner(gate=None), road="auto")
    out, info = model(p["image1"][None], p["image2"][None], camera=p["camera"], return_info=True)
    assert isinstance(out, list) and info.road.flag == ["ok"]
    assert bool(info.mask.any()) and bool((info.mask <= info.road.mask).all())
    road = info.mask & p["valid"][None]
    err = lambda f: float((f - p["flow"][None]).norm(dim=1, keepdim=True)[road].mean())  # noqa: E731
    assert err(out[-1]) < err(Noisy()(None, None)[-1])

    flat = torch.full((1, 3, 188, 621), 80.0)
    with pytest.warns(RuntimeWarning, match="left unrefined"):
        out, info = model(flat, flat, camera=p["camera"], return_info=True)
    assert info.road.flag[0] != "ok" and not bool(info.mask.any())
    assert torch.equal(out[-1], Noisy()(None, None)[-1])


def test_default_refiner_in_a_sharp_turn():
    """The default refiner (road motion from the images) in a sharp turn: the ``default`` scene
    with steering 0.1 rad, 2.6° of yaw per frame (26°/s at 10 Hz). The yaw is recovered to a few
    percent and the road flow of a badly wrong prediction is mostly corrected."""
    from fsof_torch.data.scene import render_pair

    p = render_pair("default", 0, size=(188, 621), steering=0.1)
    gt, road = p["flow"][None], p["road"][None]
    g = torch.Generator().manual_seed(0)
    rows = torch.arange(188).reshape(1, 1, 188, 1)
    pred = gt * torch.where(rows > 140, 0.6, 1.0) + 0.3 * torch.randn(gt.shape, generator=g)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        out = FreespaceRefiner()(pred, road, p["camera"], images=(p["image1"][None], p["image2"][None]))
    sel = road & p["valid"][None]
    assert bool(out.refined.all())
    assert road_epe(out.flow, gt, sel) < 0.25 * road_epe(pred, gt, sel)
    assert out.odometry["yaw"].item() == pytest.approx(p["odometry"]["yaw"], rel=0.05)


def test_photometric_fit_from_the_images():
    """fit='photometric': ego-motion from the two images (started from the flow fit)."""
    from fsof_torch.data.scene import render_pair

    # noise-free images: the mechanism is under test here; real, noisy images are covered by the
    # KITTI check in test_refine_job.py
    p = render_pair("default", 0, size=(96, 320), noise=0.0)
    gt, road = p["flow"][None], p["road"][None]
    g = torch.Generator().manual_seed(0)
    # a prediction that is badly wrong where road flow is large (as classical flow on weak texture)
    rows = torch.arange(96).reshape(1, 1, 96, 1)
    pred = gt * torch.where(rows > 70, 0.6, 1.0) + 0.3 * torch.randn(gt.shape, generator=g)
    images = (p["image1"][None], p["image2"][None])
    out = FreespaceRefiner(fit="photometric")(pred, road, p["camera"], images=images)
    sel = road & p["valid"][None]
    assert bool(out.refined.all())
    assert road_epe(out.flow, gt, sel) < 0.3 < road_epe(pred, gt, sel)
    assert out.odometry["z_d"].item() == pytest.approx(p["odometry"]["z_d"], rel=0.05)
    with pytest.raises(ValueError, match="images: fit='photometric' needs images"):
        FreespaceRefiner(fit="photometric")(pred, road, p["camera"])


# -- fuse_flow: bad input, each named ----------------------------------------------------------------

def test_fuse_flow_rejects_bad_input():
    pred, mask, _, gt = make_case()
    model = gt.to(pred.dtype)
    with pytest.raises(TypeError, match="mask: expected a bool tensor .* got dtype torch.uint8"):
        fuse_flow(pred, model, mask.to(torch.uint8))  # once only a deprecation warning
    with pytest.raises(ValueError, match=r"flow_model: expected shape \(1, 2, 48, 120\) .* got \(1, 2, 24, 60\)"):
        fuse_flow(pred, model[..., ::2, ::2], mask)  # once a RuntimeError
    with pytest.raises(ValueError, match=r"mask: expected shape \(1, 1, 48, 120\)"):
        fuse_flow(pred, model, mask[..., :10])
    for scale in (0.0, float("nan"), float("inf"), -2.0):
        with pytest.raises(ValueError, match="scale: expected a finite Cauchy scale > 0 pixels"):
            fuse_flow(pred, model, mask, mode="confidence", scale=scale)  # once a NaN output
    with pytest.raises(TypeError, match="scale: expected a finite Cauchy scale"):
        fuse_flow(pred, model, mask, scale="2")
    nan_model = model.clone()
    nan_model[mask.expand_as(nan_model)] = float("nan")
    with pytest.raises(ValueError, match=r"flow_model: expected finite values inside the mask, got \d+ non-finite"):
        fuse_flow(pred, nan_model, mask)
    with pytest.raises(TypeError, match="flow_pred: expected a floating-point tensor"):
        fuse_flow(pred.to(torch.int32), model, mask)


def test_fuse_flow_nonfinite_model_outside_the_mask_is_harmless():
    pred, mask, _, gt = make_case()
    model = gt.to(pred.dtype).clone()
    model[~mask.expand_as(model)] = float("nan")
    for mode in ("replace", "confidence"):
        out, weight = fuse_flow(pred, model, mask, mode=mode)
        assert torch.equal(out[~mask.expand_as(out)], pred[~mask.expand_as(pred)])
        assert torch.isfinite(out).all() and torch.isfinite(weight).all()
        # and in the gradient (confidence mode once gave NaN there: (1 − w) · diff of the NaN model)
        p = pred.clone().requires_grad_(True)
        grad, = torch.autograd.grad(fuse_flow(p, model, mask, mode=mode)[0].sum(), p)
        assert torch.isfinite(grad).all()
        assert torch.equal(grad[~mask.expand_as(grad)], torch.ones_like(grad)[~mask.expand_as(grad)])


def test_the_refiner_fits_a_dicts_final_flow_not_its_warm_start():
    """Once the refiner fitted (and gated against) a flow_init listed after flow_final."""
    pred, mask, cam, gt = make_case()
    alone = FreespaceRefiner()({"flow_final": pred}, mask, cam)
    out = FreespaceRefiner()({"flow_final": pred, "flow_init": torch.zeros_like(pred)}, mask, cam)
    assert torch.equal(out.flow["flow_final"], alone.flow["flow_final"])
    assert road_epe(out.flow["flow_final"], gt, mask) < 0.3 * road_epe(pred, gt, mask)


@pytest.mark.parametrize("structure", ["final_init", "stack_nan"])
def test_the_reported_weight_is_the_finest_flows_fusion(structure):
    """RefineOutput.weight is the weight of the finest flow's fusion: once it was the weight of
    the last full-size flow visited (a flow_init listed after flow_final). A ptlflow stack's finest
    is a new view of the stack, found by its place (its NaN pixels replaced as a tensor's)."""
    pred, mask, cam, _ = make_case()
    if structure == "final_init":
        flow, final = {"flow_final": pred, "flow_init": torch.zeros_like(pred)}, (lambda o: o["flow_final"])
    else:
        pred = pred.clone()
        pred[..., 30:34, 50:60] = float("nan")  # inside the mask
        flow, final = {"flows": torch.stack([torch.zeros_like(pred), pred], 1)}, (lambda o: o["flows"][:, -1])
    for mode in ("replace", "confidence"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            alone = refine_flow(pred, mask, cam, ODO, mode=mode)
            out = refine_flow(flow, mask, cam, ODO, mode=mode)
        assert torch.equal(final(out.flow).nan_to_num(-99.0), alone.flow.nan_to_num(-99.0))
        assert torch.equal(out.weight, alone.weight), mode
        assert torch.equal(out.mask, alone.mask)


# -- options and helpers: named errors quoting what came ----------------------------------------------

@pytest.mark.parametrize("options, error, message", [
    (dict(scale="2"), TypeError, "scale: expected a number, got str '2'"),
    (dict(min_pixels=2.5), TypeError, "min_pixels: expected an int, got float 2.5"),  # once accepted
    (dict(min_pixels=0), ValueError, "min_pixels: expected an int >= 1, got 0"),
    (dict(warn="x"), TypeError, "warn: expected True or False, got str 'x'"),
    (dict(flow_keys=5), TypeError, r"flow_keys: expected a key or a sequence of keys \(str\) .*, got int 5"),
    (dict(fit_roll="x"), TypeError, "fit_roll: expected True or False, got str 'x'"),
    (dict(fit_options=5), TypeError, "fit_options: expected None or a dict with string keys, got int 5"),
    (dict(fit_options={"bogus": 1}), TypeError, r"fit_options: unknown options \['bogus'\] of fit_road"),
    (dict(photometric_options={"model": "plane"}), TypeError,
     r"photometric_options: options \['model'\] of \w+ are set by the function that forwards"),
    (dict(gate=5), TypeError, "gate: expected an ImageGate, 'auto' or None, got 5"),
    (dict(gate="AUTO"), ValueError, "gate: expected an ImageGate, 'auto' or None, got 'AUTO'"),
])
def test_refiner_options_named_and_quoted(options, error, message):
    pred, mask, cam, _ = make_case()
    with pytest.raises(error, match=message):
        FreespaceRefiner(**options)
    with pytest.raises(error, match=message):
        refine_flow(pred, mask, cam, ODO, **options)


def test_refiner_flow_keys_as_one_name_and_starts():
    pred, mask, cam, _ = make_case()
    # a single key once became its letters ('f', 'l', 'o', 'w'): the dict's flow was not found
    out = refine_flow({"flow": pred}, mask, cam, ODO, flow_keys="flow")
    assert torch.equal(out.flow["flow"], FreespaceRefiner()(pred, mask, cam, ODO).flow)
    with pytest.raises(TypeError, match="starts: expected a list of start candidates"):
        refine_flow(pred, mask, cam, starts=5)


def test_estimator_options_checked_when_built():
    from fsof_torch.refinement.estimators import FlowMotionEstimator, ImageMotionEstimator

    with pytest.raises(TypeError, match="fixed: expected None, a name or a sequence of names, got int 5"):
        FlowMotionEstimator(fixed=5)
    with pytest.raises(TypeError, match=r"options: unknown options \['bogus'\] of fit_road"):
        FlowMotionEstimator(bogus=1)
    with pytest.raises(TypeError, match="flow_start: expected True or False, got str 'x'"):
        ImageMotionEstimator(flow_start="x")
    with pytest.raises(TypeError, match=r"options: options \['starts'\] of \w+ are set by the function that forwards"):
        ImageMotionEstimator(starts=[])


def test_image_estimator_inputs_are_checked_images_first():
    from fsof_torch.refinement.estimators import ImageMotionEstimator

    pred, mask, cam, _ = make_case()
    image = torch.rand(1, 3, H, W, generator=torch.Generator().manual_seed(0)) * 255
    estimator = ImageMotionEstimator()
    with pytest.raises(ValueError, match=rf"flow: expected shape \(B, 2, H, W\) with H={H}"):
        estimator(pred[..., :-4, :], mask, cam, images=(image, image))
    with pytest.raises(ValueError, match=r"image1: expected shape \(B, C, H, W\) with B >= 1"):
        estimator(pred[:0], mask[:0], cam, images=(image[:0], image[:0]))
    with pytest.raises(ValueError, match=r"camera: expected batch 1 \(the images' B\), got 3"):
        estimator(pred, mask, cam.expand(3), images=(image, image))
    with pytest.raises(ValueError, match=r"images\[0\]: values in .* look like 0..1 images, expected 0..255"):
        FreespaceRefiner()(pred, mask, cam, images=(image / 255, image / 255))


def test_estimator_options_that_would_be_left_aside_are_refused():
    """fit_roll, fit_pitch, fit_options and photometric_options apply to the estimator that
    fit= builds; where another one runs they are an error, not silently ignored."""
    from fsof_torch.refinement.estimators import ImageMotionEstimator

    pred, mask, cam, _ = make_case()
    image = torch.rand(1, 3, H, W, generator=torch.Generator().manual_seed(0)) * 255
    images = (image, image)
    with pytest.raises(ValueError, match="fit_roll: applies with fit='flow' or 'photometric'; here the default image "
                                         "estimator runs"):
        refine_flow(pred, mask, cam, images=images, fit_roll=True)
    with pytest.raises(ValueError, match="fit_options: applies with fit='flow'; here an estimator is given"):
        refine_flow(pred, mask, cam, images=images, estimator=ImageMotionEstimator(), fit_options={"max_iter": 5})
    with pytest.raises(ValueError, match="photometric_options: applies with fit='photometric'; here fit='flow'"):
        refine_flow(pred, mask, cam, fit="flow", photometric_options={"max_iter": 5})
    with pytest.raises(ValueError, match="fit_options: applies with fit='flow'; here fit='photometric'"):
        refine_flow(pred, mask, cam, images=images, fit="photometric", fit_options={"max_iter": 5})
    # where they apply they are taken: the roll is fitted (held at the camera's without the flag)
    rolled = refine_flow(pred, mask, cam, fit_roll=True, fit_options={"max_iter": 30})
    held = refine_flow(pred, mask, cam)
    assert float(held.fit.params["roll"][0]) == float(cam.roll[0]) != float(rolled.fit.params["roll"][0])


def test_gate_arguments_named():
    from fsof_torch.refinement.gate import ImageGate

    pred, mask, _, gt = make_case()
    image = torch.rand(1, 3, H, W, generator=torch.Generator().manual_seed(0)) * 255
    gate = ImageGate()
    with pytest.raises(TypeError, match="image1: expected a torch.Tensor, got int"):
        gate(5, image, pred, gt.float(), mask)  # once an AttributeError
    with pytest.raises(ValueError, match=r"model: expected shape \(B, 2, H, W\) with W=119"):
        gate(image[..., :-1], image[..., :-1], pred[..., :-1], gt.float(), mask)  # once an IndexError
    with pytest.raises(TypeError, match="mask: expected a bool tensor .* got dtype torch.uint8"):
        gate(image, image, pred, gt.float(), mask.to(torch.uint8))  # once accepted
    with pytest.raises(ValueError, match="image1: expected 1 .grey. or 3 .RGB. channels"):
        gate(image[:, :2], image[:, :2], pred, gt.float(), mask)
    with pytest.raises(ValueError, match="prediction: a tensor on the meta device has shapes but no values to judge"):
        gate(image.to("meta"), image.to("meta"), pred.to("meta"), gt.float().to("meta"), mask.to("meta"))


def test_cauchy_weight_and_resize_mask_check_their_arguments():
    """Once a list or None reached the arithmetic (TypeError or AttributeError without a name)."""
    r2 = torch.tensor([0.0, 4.0])
    torch.testing.assert_close(cauchy_weight(r2, 2.0), torch.tensor([1.0, 0.5]))
    for bad, error, message in [([1.0], TypeError, "residual_sq: expected a torch.Tensor, got list"),
                                (None, TypeError, "residual_sq: expected a torch.Tensor, got NoneType")]:
        with pytest.raises(error, match=message):
            cauchy_weight(bad, 2.0)
    for scale, error in [(0.0, ValueError), (float("nan"), ValueError), ("2", TypeError), (None, TypeError)]:
        with pytest.raises(error, match="scale: expected"):
            cauchy_weight(r2, scale)
    # a tensor scale (elementwise): its values too (once 0 gave a NaN weight, -2 weights from a
    # negative scale)
    torch.testing.assert_close(cauchy_weight(r2, torch.tensor([1.0, 2.0])), torch.tensor([1.0, 0.5]))
    for scale in (torch.tensor(0.0), torch.tensor(-2.0), torch.tensor(float("nan")), torch.tensor([1.0, float("inf")])):
        with pytest.raises(ValueError, match=r"^scale: expected finite values > 0, got \["):
            cauchy_weight(r2, scale)
    mask = torch.ones(1, 1, 4, 6, dtype=torch.bool)
    assert resize_mask(mask, (2, 3)).shape == (1, 1, 2, 3)
    with pytest.raises(TypeError, match="mask: expected a bool tensor .* got list"):
        resize_mask([[True]], (2, 3))
    with pytest.raises(TypeError, match="mask: expected a bool tensor .* got dtype torch.float32"):
        resize_mask(mask.float(), (2, 3))
    with pytest.raises(ValueError, match=r"size: expected positive sides \(H, W\), got \(0, 3\)"):
        resize_mask(mask, (0, 3))
    with pytest.raises(TypeError, match="size: expected"):
        resize_mask(mask, None)


def test_a_confidence_scale_that_requires_grad_is_refused_not_detached():
    """The Cauchy scale is read as a number: a tensor that requires grad (an ``nn.Parameter``, to
    learn the scale) was taken and its gradient lost in silence (``scale.grad`` stayed None after
    backward, as torch.autograd.gradcheck shows), so it never changed. A TypeError names it, as the
    losses' ``scale`` and ``gamma`` do; a plain 0-d tensor is still read as its number."""
    pred, road, cam, model = make_case(B=2, dtype=torch.float64)
    learnable = nn.Parameter(torch.tensor(2.0, dtype=torch.float64))
    match = r"^scale: expected a fixed number, got a tensor that requires grad"
    with pytest.raises(TypeError, match=match):
        fuse_flow(pred, model, road, mode="confidence", scale=learnable)
    with pytest.raises(TypeError, match=match):
        refine_flow(pred, road, cam, ODO, mode="confidence", scale=learnable, gate=None)
    with pytest.raises(TypeError, match=match):
        FreespaceRefiner(mode="confidence", scale=learnable)
    fused, weight = fuse_flow(pred, model, road, mode="confidence", scale=torch.tensor(2.0))
    expected = 1.0 / (1.0 + ((pred - model) ** 2).sum(1, keepdim=True) / 4.0)
    torch.testing.assert_close(weight, torch.where(road, expected, torch.zeros_like(expected)))
    torch.testing.assert_close(fused, torch.where(road, expected * model + (1 - expected) * pred, pred))
