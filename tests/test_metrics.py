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
