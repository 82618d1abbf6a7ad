"""Tests of fsof_torch.evaluation.metrics: e_A, e_E, e_U, e_V (paper eq. 25-28) and KITTI Fl."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import fsof_torch.evaluation.metrics as metrics_module
from fsof_torch.evaluation.metrics import (
    BENCHMARK_NAMES,
    METRIC_NAMES,
    FlowMetricAccumulator,
    angular_error,
    endpoint_error,
    flow_error_maps,
    flow_metrics,
    flow_metrics_per_sample,
    outlier_rate,
    u_error,
    v_error,
)

PER_SAMPLE = {"e_A": angular_error, "e_E": endpoint_error, "e_U": u_error, "e_V": v_error,
              "Fl": outlier_rate}


def _vec(u, v, dtype=torch.float64):
    return torch.tensor([float(u), float(v)], dtype=dtype).view(1, 2, 1, 1)


def _random(B=2, H=6, W=9, seed=0, scale=5.0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(B, 2, H, W, generator=g, dtype=torch.float64) * scale).to(dtype)


def _reference(est, gt):
    """Independent numpy reference, straight from the paper's formulas (arccos, clamped)."""
    e, g = est.double().numpy(), gt.double().numpy()
    arg = (e[:, 0] * g[:, 0] + e[:, 1] * g[:, 1] + 1) / np.sqrt(
        (e[:, 0] ** 2 + e[:, 1] ** 2 + 1) * (g[:, 0] ** 2 + g[:, 1] ** 2 + 1))
    epe = np.hypot(e[:, 0] - g[:, 0], e[:, 1] - g[:, 1])
    mag = np.hypot(g[:, 0], g[:, 1])
    return {"e_A": np.arccos(np.clip(arg, -1, 1)), "e_E": epe, "e_U": np.abs(e[:, 0] - g[:, 0]),
            "e_V": np.abs(e[:, 1] - g[:, 1]), "Fl": ((epe > 3) & (epe > 0.05 * mag)).astype(float)}


# --- smoke -------------------------------------------------------------------------------------

def test_smoke(dtype):
    est, gt = _random(dtype=dtype), _random(seed=1, dtype=dtype)
    for name, fn in PER_SAMPLE.items():
        out = fn(est, gt)
        assert out.shape == (2,) and out.dtype == dtype and torch.isfinite(out).all(), name
    m = flow_metrics(est, gt)
    assert set(m) == set(METRIC_NAMES) | set(BENCHMARK_NAMES) | {"n_pixels"} and m["n_pixels"] == 2 * 6 * 9
    assert all(isinstance(m[k], float) for k in METRIC_NAMES)


def test_public_names():
    for name in ["angular_error", "endpoint_error", "u_error", "v_error", "outlier_rate",
                 "flow_metrics", "flow_metrics_per_sample", "flow_error_maps"]:
        assert name in metrics_module.__all__


# --- exceptions --------------------------------------------------------------------------------

def test_bad_shapes_and_types():
    est = _random()
    with pytest.raises(ValueError, match=r"flow_gt: expected shape \(B, 2, H, W\) with W=9"):
        endpoint_error(est, _random(W=8))
    with pytest.raises(ValueError, match=r"flow_est: expected shape \(B, 2, H, W\)"):
        endpoint_error(est[:, :1], est[:, :1])
    with pytest.raises(ValueError, match="valid: expected shape"):
        endpoint_error(est, est, valid=torch.ones(2, 1, 6, 8, dtype=torch.bool))
    with pytest.raises(TypeError, match="mask: expected a bool tensor"):
        endpoint_error(est, est, mask=torch.ones(2, 1, 6, 9))
    with pytest.raises(TypeError, match="flow_gt: expected a floating-point tensor"):
        endpoint_error(est, torch.zeros(2, 2, 6, 9, dtype=torch.int64))


# --- cardinality -------------------------------------------------------------------------------

@pytest.mark.parametrize("B", [1, 3])
def test_cardinality(B):
    est, gt = _random(B=B, H=5, W=11), _random(B=B, H=5, W=11, seed=3)
    per = flow_metrics_per_sample(est, gt)
    assert per["n_pixels"].tolist() == [55] * B
    for name, fn in PER_SAMPLE.items():
        assert per[name].shape == (B,)
        torch.testing.assert_close(fn(est, gt), per[name])
        for b in range(B):
            torch.testing.assert_close(fn(est[b:b + 1], gt[b:b + 1]), per[name][b:b + 1])


# --- feature: hand-computed values -------------------------------------------------------------

def test_angular_error_hand_values():
    # (1, 0) vs (0, 1): (0 + 1) / sqrt(2 * 2) = 1/2
    assert float(angular_error(_vec(1, 0), _vec(0, 1))) == pytest.approx(math.acos(0.5), abs=1e-12)
    # (0, 0) vs (1, 0): 1 / sqrt(2)  -> 45 degrees
    assert float(angular_error(_vec(0, 0), _vec(1, 0))) == pytest.approx(math.pi / 4, abs=1e-12)
    # identical flows: 0 (no NaN from an arccos argument rounding above 1)
    assert float(angular_error(_vec(3.3, -7.1), _vec(3.3, -7.1))) == pytest.approx(0.0, abs=1e-9)
    # float32 keeps accuracy for small angles: (100, 0) vs (100, 0.01)
    got32 = angular_error(_vec(100, 0, torch.float32), _vec(100, 0.01, torch.float32))
    want = math.acos((100 * 100 + 1) / math.sqrt((100 ** 2 + 1) * (100 ** 2 + 0.01 ** 2 + 1)))
    assert float(got32) == pytest.approx(want, rel=1e-3)


def test_endpoint_and_component_hand_values():
    est, gt = _vec(4, 1), _vec(1, 5)   # difference (3, -4)
    assert float(endpoint_error(est, gt)) == pytest.approx(5.0)
    assert float(u_error(est, gt)) == pytest.approx(3.0)
    assert float(v_error(est, gt)) == pytest.approx(4.0)


def test_outlier_rule():
    # e_E = 3.5 > 3 px; true magnitude 100 -> 5% is 5 px: not an outlier
    assert float(outlier_rate(_vec(103.5, 0), _vec(100, 0))) == 0.0
    # e_E = 3.5, true magnitude 10 -> 0.5 px: outlier
    assert float(outlier_rate(_vec(13.5, 0), _vec(10, 0))) == 1.0
    # e_E = 2.9 < 3 px: never an outlier, however small the true flow
    assert float(outlier_rate(_vec(2.9, 0), _vec(0, 0))) == 0.0
    # zero true flow, e_E = 3.1: outlier (no division by the zero magnitude)
    assert float(outlier_rate(_vec(3.1, 0), _vec(0, 0))) == 1.0
    # the 5% are of the true flow, not of the estimate: e_E = 4.9 against 5% of 100 (5) and of 95.1 (4.755)
    assert float(outlier_rate(_vec(95.1, 0), _vec(100, 0))) == 0.0
    assert float(outlier_rate(_vec(100, 0), _vec(95.1, 0))) == 1.0


def test_against_numpy_reference(dtype):
    est, gt = _random(B=3, dtype=dtype), _random(B=3, seed=5, dtype=dtype)
    valid = _random(B=3, seed=9)[:, :1] > -1.0
    mask = _random(B=3, seed=11)[:, :1] > -3.0
    ref = _reference(est, gt)
    sel = (valid & mask)[:, 0].numpy()
    per = flow_metrics_per_sample(est, gt, mask, valid)
    agg = flow_metrics(est, gt, mask, valid)
    tol = {torch.float32: 1e-5, torch.float64: 1e-10}[dtype]
    for name in METRIC_NAMES:
        want = np.array([ref[name][b][sel[b]].mean() for b in range(3)])
        np.testing.assert_allclose(per[name].double().numpy(), want, rtol=tol, atol=tol, err_msg=name)
        np.testing.assert_allclose(agg[name], ref[name][sel].mean(), rtol=tol, atol=tol, err_msg=name)
    assert per["n_pixels"].tolist() == sel.reshape(3, -1).sum(1).tolist()
    assert agg["n_pixels"] == int(sel.sum())


def test_aggregation_weights_pixels_kitti_style():
    """flow_metrics averages over all pixels of the batch, not over per-frame means."""
    est = torch.zeros(2, 2, 2, 2, dtype=torch.float64)
    gt = torch.zeros_like(est)
    gt[0, 0] = 1.0      # frame 0: e_E = 1 on its 4 pixels
    gt[1, 0] = 2.0      # frame 1: e_E = 2, but only 1 valid pixel
    valid = torch.zeros(2, 1, 2, 2, dtype=torch.bool)
    valid[0] = True
    valid[1, 0, 0, 0] = True
    agg = flow_metrics(est, gt, valid=valid)
    assert agg["e_E"] == pytest.approx((4 * 1 + 2) / 5) and agg["n_pixels"] == 5
    assert endpoint_error(est, gt, valid=valid).tolist() == pytest.approx([1.0, 2.0])


def test_invalid_ground_truth_values_are_ignored():
    est, gt = _random(), _random(seed=2)
    valid = torch.ones(2, 1, 6, 9, dtype=torch.bool)
    valid[:, :, 0, :] = False
    gt_bad = gt.clone()
    gt_bad[:, :, 0, :] = float("nan")
    gt_bad[:, 0, 0, 0] = 1e9
    for name, fn in PER_SAMPLE.items():
        torch.testing.assert_close(fn(est, gt_bad, valid=valid), fn(est, gt, valid=valid))


def test_error_maps():
    est, gt = _random(), _random(seed=2)
    mask = torch.zeros(2, 1, 6, 9, dtype=torch.bool)
    mask[:, :, 2:4] = True
    maps, counted = flow_error_maps(est, gt, mask)
    assert torch.equal(counted, mask)
    ref = _reference(est, gt)
    for name in METRIC_NAMES:
        assert maps[name].shape == (2, 1, 6, 9)
        assert (maps[name][~mask] == 0).all()
        np.testing.assert_allclose(maps[name][:, 0].numpy()[mask[:, 0].numpy()],
                                   ref[name][mask[:, 0].numpy()], rtol=1e-10, atol=1e-10)


# --- empty selections and gradients ------------------------------------------------------------

def test_empty_mask_gives_zero_and_count_zero():
    est, gt = _random(), _random(seed=1)
    mask = torch.ones(2, 1, 6, 9, dtype=torch.bool)
    mask[1] = False
    for name, fn in PER_SAMPLE.items():
        value, count = fn(est, gt, mask, return_count=True)
        assert count.tolist() == [54, 0] and value[1] == 0 and torch.isfinite(value).all(), name
    empty = flow_metrics(est, gt, torch.zeros(2, 1, 6, 9, dtype=torch.bool))
    assert empty["n_pixels"] == 0
    assert all(empty[k] == 0.0 for k in METRIC_NAMES)


def test_gradients_finite_at_equal_flows():
    est = _random().requires_grad_()
    gt = est.detach().clone()
    assert endpoint_error(est, gt).eq(0).all() and angular_error(est, gt).eq(0).all()
    total = sum(fn(est, gt).sum() for name, fn in PER_SAMPLE.items() if name != "Fl")
    total.backward()
    assert torch.isfinite(est.grad).all()


def test_gradcheck():
    est = _random(B=1, H=3, W=4).requires_grad_()
    gt = _random(B=1, H=3, W=4, seed=7)
    for name in ["e_A", "e_E", "e_U", "e_V"]:
        assert torch.autograd.gradcheck(lambda f: PER_SAMPLE[name](f, gt), (est,)), name


# --- non-finite values and overflow ------------------------------------------------------------

@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_nonfinite_estimate_at_a_counted_pixel_raises(bad):
    """An all-NaN estimate against 10 px ground truth once scored e_E = 0, Fl = 0 (perfect)."""
    gt = torch.full((1, 2, 4, 5), 10.0)
    est = torch.full_like(gt, bad)
    fns = [*PER_SAMPLE.values(), flow_metrics, flow_metrics_per_sample, flow_error_maps]
    for fn in fns:
        with pytest.raises(ValueError, match=r"flow_est: 20 non-finite value\(s\) \(NaN or inf\) at counted pixels"):
            fn(est, gt)
    one = torch.zeros_like(gt)
    one[0, 1, 2, 3] = bad
    with pytest.raises(ValueError, match=r"flow_est: 1 non-finite .* sample 0, pixel \(u=3, v=2\)"):
        flow_metrics(one, gt)


def test_nonfinite_estimate_outside_the_selection_is_not_counted():
    est, gt = _random(), _random(seed=1)
    mask = torch.ones(2, 1, 6, 9, dtype=torch.bool)
    mask[:, :, 0] = False
    bad = est.clone()
    bad[:, :, 0] = float("nan")
    bad[0, 0, 0, 0] = float("inf")
    assert flow_metrics(bad, gt, mask) == flow_metrics(est, gt, mask)
    for name, fn in PER_SAMPLE.items():
        torch.testing.assert_close(fn(bad, gt, valid=mask), fn(est, gt, valid=mask))


def test_nonfinite_ground_truth_is_invalid():
    """NaN or inf ground truth marks the pixel invalid (as KITTI's valid channel), without a mask."""
    est, gt = _random(), _random(seed=1)
    gt_bad = gt.clone()
    gt_bad[0, 0, 1, 2] = float("nan")
    gt_bad[1, 1, 3, 4] = float("inf")
    valid = torch.isfinite(gt_bad).all(dim=1, keepdim=True)
    got = flow_metrics(est, gt_bad)
    assert got["n_pixels"] == 2 * 6 * 9 - 2
    assert got == flow_metrics(est, gt, valid=valid)
    per = flow_metrics_per_sample(est, gt_bad)
    assert per["n_pixels"].tolist() == [53, 53]


def test_float32_values_of_1e20_give_finite_correct_metrics():
    """Squares of 1e20 overflow float32; the metrics scale by powers of two first."""
    g = torch.Generator().manual_seed(4)
    est64 = torch.randn(1, 2, 3, 4, generator=g, dtype=torch.float64) * 1e20
    gt64 = torch.randn(1, 2, 3, 4, generator=g, dtype=torch.float64) * 1e20
    est, gt = est64.float(), gt64.float()
    ref = _reference(est.double(), gt.double())  # the float32 inputs, evaluated in float64
    maps, _ = flow_error_maps(est, gt)
    for name in METRIC_NAMES:
        assert torch.isfinite(maps[name]).all(), name
        np.testing.assert_allclose(maps[name][:, 0].double().numpy(), ref[name], rtol=1e-5, atol=1e-6, err_msg=name)
    # small flows: bit-identical to the unscaled formula (the scale is 1)
    small, small_gt = _random(dtype=torch.float32), _random(seed=5, dtype=torch.float32)
    d = small - small_gt
    assert torch.equal(endpoint_error(small, small_gt), torch.sqrt((d * d).sum(1)).flatten(1).mean(1))


def test_an_error_beyond_the_dtype_range_raises():
    est = torch.full((1, 2, 2, 2), 3e38)
    gt = torch.full((1, 2, 2, 2), -3e38)
    with pytest.raises(ValueError, match=r"flow_est: 4 end-point error\(s\) overflow torch.float32 .* evaluate in float64"):
        flow_metrics(est, gt)
    assert flow_metrics(est.double(), gt.double())["e_E"] == pytest.approx(6e38 * math.sqrt(2), rel=1e-6)


def test_float32_angular_error_of_nearly_equal_flows():
    """e_A of estimates within 1e-3 px of 20 px flows keeps float32 accuracy: the cross product's
    third component is formed from the flows' differences, not as u v̂ - v û of nearly equal
    products (which left a worst relative error of 0.60 against float64)."""
    g = torch.Generator().manual_seed(0)
    gt = torch.randn(1, 2, 50, 50, generator=g) * 20
    est = gt + torch.randn(1, 2, 50, 50, generator=g) * 1e-3
    got = flow_error_maps(est, gt)[0]["e_A"].double().numpy()[:, 0]
    e, t = est.double().numpy(), gt.double().numpy()  # the same float32 inputs, in float64
    cross = np.stack([e[:, 1] - t[:, 1], t[:, 0] - e[:, 0], e[:, 0] * t[:, 1] - e[:, 1] * t[:, 0]])
    ref = np.arctan2(np.sqrt((cross ** 2).sum(0)), e[:, 0] * t[:, 0] + e[:, 1] * t[:, 1] + 1)
    assert ref.min() > 0
    assert np.abs(got / ref - 1).max() < 1e-5
    assert angular_error(est, gt).item() == pytest.approx(ref.mean(), rel=1e-6)


# --- benchmark names: epe, fl / flall, px1, px3, px5 -------------------------------------------

def test_benchmark_names_match_their_definitions():
    """ptlflow: pxN = mean(epe < N) over valid pixels; KITTI Fl-all: epe > 3 px and > 5 % of |gt|."""
    est, gt = _random(B=3, H=7, W=8, scale=4.0), _random(B=3, H=7, W=8, seed=9, scale=4.0)
    valid = torch.rand(3, 1, 7, 8, generator=torch.Generator().manual_seed(2)) > 0.3
    e, gnp, sel = est.numpy(), gt.numpy(), valid[:, 0].numpy()
    epe = np.sqrt(((e - gnp) ** 2).sum(axis=1))
    mag = np.sqrt((gnp ** 2).sum(axis=1))
    want = {"epe": epe, "fl": (epe > 3) & (epe > 0.05 * mag), "px1": epe < 1, "px3": epe < 3, "px5": epe < 5}
    want["flall"] = want["fl"]
    pooled = flow_metrics(est, gt, valid=valid)
    per = flow_metrics_per_sample(est, gt, valid=valid)
    for name, w in want.items():
        assert pooled[name] == pytest.approx(w[sel].mean(), rel=1e-12), name
        for b in range(3):
            assert float(per[name][b]) == pytest.approx(w[b][sel[b]].mean(), rel=1e-12), (name, b)
    assert pooled["epe"] == pooled["e_E"] and pooled["fl"] == pooled["Fl"] == pooled["flall"]
    assert set(BENCHMARK_NAMES) <= set(per)


# --- the accumulator ----------------------------------------------------------------------------

def _batches():
    """Three batches with different valid-pixel counts (one image with none)."""
    out = []
    for k, B in enumerate((2, 1, 3)):
        est, gt = _random(B=B, seed=10 + k), _random(B=B, seed=20 + k)
        valid = torch.rand(B, 1, 6, 9, generator=torch.Generator().manual_seed(30 + k)) > 0.4
        if k == 2:
            valid[1] = False
        out.append((est, gt, valid))
    return out


def test_accumulator_pools_pixels_and_images():
    acc = FlowMetricAccumulator()
    per_image = []
    for est, gt, valid in _batches():
        returned = acc.update(est, gt, valid=valid)
        per = flow_metrics_per_sample(est, gt, valid=valid)
        torch.testing.assert_close(returned["epe"], per["epe"])
        per_image += [{k: float(per[k][b]) for k in BENCHMARK_NAMES + METRIC_NAMES} | {"n": int(per["n_pixels"][b])}
                      for b in range(est.shape[0])]
    est = torch.cat([b[0] for b in _batches()])
    gt = torch.cat([b[1] for b in _batches()])
    valid = torch.cat([b[2] for b in _batches()])
    pooled, by_image = acc.compute("pixels"), acc.compute("images")
    whole = flow_metrics(est, gt, valid=valid)
    for name in METRIC_NAMES + BENCHMARK_NAMES:
        assert pooled[name] == pytest.approx(whole[name], rel=1e-12, abs=1e-15), name
        counted = [p[name] for p in per_image if p["n"] > 0]
        assert by_image[name] == pytest.approx(sum(counted) / len(counted), rel=1e-12, abs=1e-15), name
    assert pooled["n_pixels"] == whole["n_pixels"] == acc.n_pixels
    assert by_image["n_images"] == 5  # six images, one without a counted pixel


def test_accumulator_merge_state_and_errors():
    batches = _batches()
    one, a, b = FlowMetricAccumulator(), FlowMetricAccumulator(), FlowMetricAccumulator()
    for i, (est, gt, valid) in enumerate(batches):
        one.update(est, gt, valid=valid)
        (a if i % 2 else b).update(est, gt, valid=valid)
    assert a.merge(b).compute() == pytest.approx(one.compute())
    restored = FlowMetricAccumulator()
    restored.load_state_dict(one.state_dict())
    assert restored.compute("images") == one.compute("images")
    assert one.all_reduce().compute() == one.compute()  # no process group: a copy
    with pytest.warns(RuntimeWarning, match=r"compute\('pixels'\): nothing was counted"):
        empty = FlowMetricAccumulator().compute()
    assert empty["n_pixels"] == 0 and empty["epe"] == 0.0
    with pytest.raises(ValueError, match="reduction: expected 'pixels' or 'images'"):
        one.compute("frames")
    with pytest.raises(TypeError, match="other: expected a FlowMetricAccumulator"):
        one.merge({"epe": 1.0})
    with pytest.raises(ValueError, match="state: expected"):
        one.load_state_dict({"state": torch.zeros(3)})
    with pytest.raises(ValueError, match="flow_est: 1 non-finite"):
        bad = batches[0][0].clone()
        bad[0, 0, 0, 0] = float("nan")
        one.update(bad, batches[0][1])


def test_accumulator_device_is_checked_and_named():
    """``device="gpu"`` (a typo for "cuda") raised torch's RuntimeError 'Expected one of cpu, cuda,
    ... device type at start of device string: gpu', naming no argument."""
    for device in ("cpu", torch.device("cpu"), None):
        assert FlowMetricAccumulator(device=device).state.device == torch.device("cpu")
    with pytest.raises(ValueError, match=r"device: expected None, a torch.device, a device string .*got 'gpu'"):
        FlowMetricAccumulator(device="gpu")
    with pytest.raises(TypeError, match=r"device: expected .*got 1.5"):
        FlowMetricAccumulator(device=1.5)


def test_accumulator_device_index_is_named_as_one():
    """The docstring takes a device index: where torch has no accelerator for it, the index was a
    TypeError whose message listed the types it takes without an index, as if an int were the wrong
    type; it is a ValueError that says why, on a CPU build of torch (which refuses the index) and
    on a CUDA build without a driver (which names cuda:0, then cannot reach it: torch's
    RuntimeError, or for "cuda" on a CPU build its AssertionError). A bool, which torch reads as
    index 1, is a TypeError."""
    if torch.accelerator.is_available():
        assert FlowMetricAccumulator(device=0).state.device == torch.device(0)
    else:
        for index in (0, np.int64(1), "cuda", torch.device("cuda", 0)):
            with pytest.raises(ValueError, match=r"^device: expected None, a torch.device, a device string such as "
                                                 r"'cpu' or 'cuda:0' or a device index.*, got (0|np\.int64\(1\)|'cuda'|"
                                                 r"device\(type='cuda', index=0\)) \(.+\)$"):
                FlowMetricAccumulator(device=index)
    with pytest.raises(ValueError, match=r"got -1 \(.*negative"):
        FlowMetricAccumulator(device=-1)
    for flag in (True, False):
        with pytest.raises(TypeError, match=rf"^device: expected .* or a device index, got {flag}$"):
            FlowMetricAccumulator(device=flag)


def test_accumulator_compute_over_nothing_counted_warns():
    """compute() over no counted pixel returned e_E 0.0, a perfect score, without a word: the
    count was the only flag (a data set whose valid masks all came out False)."""
    import warnings

    est, gt = _random(), _random(seed=1)
    acc = FlowMetricAccumulator()
    acc.update(est, gt, valid=torch.zeros(2, 1, 6, 9, dtype=torch.bool))
    for reduction in ("pixels", "images"):
        with pytest.warns(RuntimeWarning, match=rf"^FlowMetricAccumulator.compute\('{reduction}'\): nothing was "
                                                r"counted \(n_pixels 0, n_images 0\); every metric is 0.0") as record:
            out = acc.compute(reduction)
        assert record[0].filename == __file__  # (the caller's line)
        assert out["epe"] == 0.0 and out["n_pixels"] == 0 and out["n_images"] == 0
    acc.update(est, gt)  # something counted: no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert acc.compute()["n_pixels"] == 108 and acc.compute("images")["n_images"] == 2


@pytest.mark.parametrize("return_count", ["no", "False", 1, 0, None])
def test_per_sample_functions_take_return_count_as_true_or_false(return_count):
    """return_count was read by its truth: "no" or "False" gave a (mean, count) tuple, 0 or None the
    mean alone, where the photometric functions refuse anything but True or False."""
    est, gt = _random(), _random(seed=1)
    for fn in PER_SAMPLE.values():
        with pytest.raises(TypeError, match=rf"^return_count: expected True or False, got {type(return_count).__name__} "):
            fn(est, gt, return_count=return_count)
        mean, count = fn(est, gt, return_count=True)
        assert torch.equal(fn(est, gt, return_count=False), mean) and count.tolist() == [54, 54]


def test_accumulator_on_the_meta_device_is_refused():
    """FlowMetricAccumulator(device="meta") was built: update() then added every batch's sums to a
    state without values (lost, silently), and compute() and repr() raised torch's own errors
    ("Cannot copy out of meta tensor; no data!", "Tensor.item() cannot be called on meta
    tensors"). Now the constructor names ``device``, as update() names a meta flow."""
    for device in ("meta", torch.device("meta")):
        with pytest.raises(ValueError, match=r"^device: an accumulator sums values, which the meta device does not "
                                             r"hold; got meta$"):
            FlowMetricAccumulator(device=device)
    with torch.device("meta"):  # (the default device: None's)
        with pytest.raises(ValueError, match=r"^device: an accumulator sums values"):
            FlowMetricAccumulator()


def test_accumulator_returns_what_flow_metrics_per_sample_returns():
    """Per-image values of update() are flow_metrics_per_sample's, dtype included: the working
    dtype, at least float32 (bfloat16 flows gave bfloat16 from update(), float32 from the other)."""
    est, gt = _random(seed=3, dtype=torch.float32), _random(seed=4, dtype=torch.float32)
    for e, t, dtype in ((est.bfloat16(), gt.bfloat16(), torch.float32), (est.half(), gt.half(), torch.float32),
                        (est, gt.double(), torch.float64), (est, gt, torch.float32)):
        got = FlowMetricAccumulator().update(e, t)
        want = flow_metrics_per_sample(e, t)
        assert set(got) == set(want)
        for name in METRIC_NAMES + BENCHMARK_NAMES:
            assert got[name].dtype == want[name].dtype == dtype, (name, e.dtype, t.dtype)
            assert torch.equal(got[name], want[name]), name
        assert torch.equal(got["n_pixels"], want["n_pixels"])


@pytest.mark.parametrize("index, value, match", [
    (1, float("nan"), r"state\['state'\]\[1\] \(the pixel sum of e_E\): expected a finite number >= 0, got nan"),
    (0, -3.0, r"state\['state'\]\[0\] \(the pixel sum of e_A\): expected a finite number >= 0, got -3.0"),
    (9, float("inf"), r"\[9\] \(the per-image sum of e_A\): expected a finite number >= 0, got inf"),
    (8, -1.0, r"\[8\] \(the count n_pixels\): expected a finite integer >= 0, got -1.0"),
    (8, 2.5, r"\[8\] \(the count n_pixels\): expected a finite integer >= 0, got 2.5"),
    (17, float("nan"), r"\[17\] \(the count n_images\): expected a finite integer >= 0, got nan"),
])
def test_accumulator_load_state_dict_refuses_impossible_sums_and_counts(index, value, match):
    """A state of sums and counts no data set gives (NaN, inf, negative, a fractional count) is
    refused, naming the entry, and the accumulator keeps its own state."""
    acc = FlowMetricAccumulator()
    for est, gt, valid in _batches():
        acc.update(est, gt, valid=valid)
    before = acc.compute("images")
    state = acc.state_dict()
    state["state"][index] = value
    with pytest.raises(ValueError, match=match):
        acc.load_state_dict(state)
    assert acc.compute("images") == before
    state["state"][index] = acc.state[index]  # a state that came from update() loads
    acc.load_state_dict(state)
    assert acc.compute("images") == before


def test_accumulator_built_under_inference_mode_works_outside_it():
    """An accumulator built or updated under torch.inference_mode held an inference tensor:
    update, reset and merge outside it raised "Inplace update to inference tensor outside
    InferenceMode". They work, with the same sums as an accumulator that never saw it."""
    batches = _batches()
    plain = FlowMetricAccumulator()
    for est, gt, valid in batches:
        plain.update(est, gt, valid=valid)
    with torch.inference_mode():
        acc = FlowMetricAccumulator()
        acc.update(*batches[0][:2], valid=batches[0][2])
    for est, gt, valid in batches[1:]:
        acc.update(est, gt, valid=valid)
    assert torch.equal(acc.state, plain.state)
    assert acc.all_reduce().compute() == plain.compute()
    with torch.inference_mode():
        other = FlowMetricAccumulator()
        other.update(*batches[0][:2], valid=batches[0][2])
    merged = FlowMetricAccumulator().merge(other)  # a plain one takes an inference one, and back
    assert other.merge(merged).n_pixels == 2 * merged.n_pixels
    acc.reset()
    assert acc.n_pixels == 0 and not acc.state.any()
    with torch.inference_mode():  # and a plain accumulator updated under it keeps working outside
        plain.update(*batches[0][:2], valid=batches[0][2])
    plain.update(*batches[0][:2], valid=batches[0][2])
    plain.reset()
    assert plain.n_pixels == 0


def _all_reduce_worker(rank: int, world: int, init: str, out: str) -> None:
    import torch.distributed as dist

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=init, rank=rank, world_size=world)
    try:
        with torch.inference_mode():  # built as an evaluation loop would, updated outside too
            acc = FlowMetricAccumulator()
        for i, (est, gt, valid) in enumerate(_batches()):
            if i % world == rank:  # strided shards, each batch on exactly one process
                acc.update(est, gt, valid=valid)
        total = acc.all_reduce()
        if rank == 0:
            torch.save({"pixels": total.compute("pixels"), "images": total.compute("images"),
                        "local": acc.compute()}, out)
    finally:
        dist.destroy_process_group()


def test_accumulator_all_reduce_across_two_processes(tmp_path):
    import torch.multiprocessing as mp

    out = tmp_path / "result.pt"
    mp.spawn(_all_reduce_worker, args=(2, f"file://{tmp_path / 'store'}", str(out)), nprocs=2)
    got = torch.load(out)
    one = FlowMetricAccumulator()
    for est, gt, valid in _batches():
        one.update(est, gt, valid=valid)
    assert got["pixels"] == pytest.approx(one.compute("pixels"), rel=1e-12)
    assert got["images"] == pytest.approx(one.compute("images"), rel=1e-12)
    assert got["local"]["n_pixels"] < got["pixels"]["n_pixels"]


def test_metrics_under_autocast_equal_float32():
    est, gt = _random(dtype=torch.float32), _random(seed=1, dtype=torch.float32)
    exact = flow_metrics(est, gt)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        low = flow_metrics(est, gt)
        per = flow_metrics_per_sample(est, gt)
    assert low == exact and per["epe"].dtype == torch.float32


@pytest.mark.parametrize("magnitude", [1e20, 1e25, 1e30, 3e38])
def test_float32_angular_error_of_huge_flows(magnitude):
    """e_A of a zero estimate against (m, 0) is atan2(m, 1) ≈ pi/2 and of (m, 0) against (0, m)
    is pi/2 too: the cross product's components, about 1/m, are scaled before squaring (their
    squares underflow float32, which gave 0 from about 1e22 px). e_E stays finite up to the
    dtype's largest value."""
    gt = torch.tensor([magnitude, 0.0]).view(1, 2, 1, 1)
    zero = torch.zeros(1, 2, 1, 1)
    assert angular_error(zero, gt).item() == pytest.approx(math.atan2(magnitude, 1.0), rel=1e-6)
    half = gt / 2  # (the end-point errors below stay within float32)
    across = torch.tensor([0.0, magnitude / 2]).view(1, 2, 1, 1)
    assert angular_error(across, half).item() == pytest.approx(math.pi / 2, rel=1e-6)
    assert angular_error(-half, half).item() == pytest.approx(math.pi, rel=1e-6)
    assert endpoint_error(zero, gt).item() == pytest.approx(magnitude, rel=1e-6)


def test_float32_angular_error_of_huge_flows_matches_float64():
    g = torch.Generator().manual_seed(6)
    est = (torch.randn(1, 2, 8, 8, generator=g, dtype=torch.float64) * 1e25).float()
    gt = (torch.randn(1, 2, 8, 8, generator=g, dtype=torch.float64) * 1e25).float()
    est[..., :2] = 0.0  # where one vector is (0, 0, 1), only the components of about 1/m remain
    got = flow_error_maps(est, gt)[0]["e_A"]
    ref = flow_error_maps(est.double(), gt.double())[0]["e_A"]
    assert ref.min() > 0.01
    torch.testing.assert_close(got.double(), ref, rtol=1e-5, atol=0)


@pytest.mark.parametrize("B, H, W, dtype", [(1, 700, 1000, torch.float32), (3, 375, 1242, torch.float64),
                                            (2, 555, 777, torch.float32)])
def test_large_maps_without_autograd_are_computed_in_bands(monkeypatch, B, H, W, dtype):
    """Without autograd, error maps of more than ``_BAND_PIXELS`` pixels are computed a band of
    rows at a time (the formulas' temporaries of the whole frame, some 100 bytes a pixel, were
    held at once: about 1.1 GB more peak for one 2160x3840 update of an accumulator), with the
    one-pass values bit for bit in one thread (torch's atan2 rounds a run's last elements in
    scalar code: the bands hold whole 64-element blocks of every plane), and so the same sums."""
    from fsof_torch.evaluation.warp import band_rows

    assert band_rows(1, 375, 1242, metrics_module._BAND_PIXELS) >= 375  # a KITTI frame: one band
    assert band_rows(1, 2160, 3840, 1 << 19) == 136 and band_rows(3, 555, 777, 1000) == 64
    g = torch.Generator().manual_seed(0)
    gt = (torch.randn(B, 2, H, W, generator=g, dtype=torch.float64) * 20).to(dtype)
    est = gt + (torch.randn(B, 2, H, W, generator=g, dtype=torch.float64) * 3).to(dtype)
    gt[:, :, :3] = float("nan")  # invalid ground truth; a flow of 1e30 px and NaN estimates where not counted
    est[:, 0, 10, :5], est[:, :, 20:22], gt[:, :, 20:22] = 1e30, float("nan"), float("inf")
    valid = torch.rand(B, 1, H, W, generator=g) > 0.2
    bands = []
    maps_of = metrics_module._maps

    def spy(est, gt):
        bands.append(est.shape[-2])
        return maps_of(est, gt)

    monkeypatch.setattr(metrics_module, "_maps", spy)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with torch.no_grad():
            banded, counted = flow_error_maps(est, gt, valid=valid)
            acc = FlowMetricAccumulator()
            acc.update(est, gt, valid=valid)
        assert len(bands) == 2 * math.ceil(H / band_rows(B, H, W, metrics_module._BAND_PIXELS)) > 2
        bands.clear()
        whole, whole_counted = flow_error_maps(est.clone().requires_grad_(), gt, valid=valid)
        assert bands == [H]
        one = FlowMetricAccumulator()
        one.update(est.clone().requires_grad_(), gt, valid=valid)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(counted, whole_counted)
    for name in whole:
        assert torch.equal(banded[name], whole[name].detach()), name
    assert torch.equal(acc.state, one.state)
    # and the values are the metrics' own: e_E and the angle from their formulas, in float64
    e, t = est.double(), gt.double()
    keep = counted[:, 0] & (e.abs() < 1e20).all(1)
    torch.testing.assert_close(banded["e_E"][:, 0][keep].double(), (e - t).norm(dim=1)[keep], rtol=1e-5, atol=1e-4)
    cos = ((e * t).sum(1) + 1) / ((e.square().sum(1) + 1) * (t.square().sum(1) + 1)).sqrt()
    torch.testing.assert_close(banded["e_A"][:, 0][keep].double(), cos.clamp(-1, 1).acos()[keep], rtol=1e-3, atol=1e-3)
