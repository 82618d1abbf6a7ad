"""V-flow map, eq. 24 curve fit and freespace detection."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from fsof_torch.geometry.camera import Camera
from fsof_torch.geometry.road_flow import displacement_flow, velocity_flow, vflow_curve
from fsof_torch.estimation.freespace import FreespaceDetection, detect_freespace
from fsof_torch.estimation.vflow import (
    VFlowCurve,
    fit_vflow_curve,
    row_dominant_flow,
    vflow_curve_model,
    vflow_map,
)

SIZE = (64, 160)


def _camera(dtype=torch.float64, B=1, **kw) -> Camera:
    K = torch.tensor([[200.0, 0, 80.0], [0, 200.0, 18.0], [0, 0, 1]], dtype=dtype)
    return Camera(K, 1.5, **kw).expand(B) if B > 1 else Camera(K, 1.5, **kw)


def _straight(dtype=torch.float64, z_d=1.0, B=1, size=SIZE):
    cam = _camera(dtype)
    z = torch.as_tensor(z_d, dtype=dtype).reshape(-1).expand(B) if B > 1 else z_d
    return cam, *displacement_flow(cam.expand(B) if B > 1 else cam, 0.0, z, 0.0, size)


# -- vflow_map ------------------------------------------------------------------------------------

class TestVFlowMap:
    def test_smoke(self, dtype):
        _, flow, valid = _straight(dtype)
        hist, edges = vflow_map(flow, valid, bins=32)
        assert hist.shape == (1, SIZE[0], 32) and hist.dtype == dtype
        assert edges.shape == (33,) and edges.dtype == dtype
        assert float(hist.sum()) == float(valid.sum())

    def test_against_numpy_histogram(self):
        g = torch.Generator().manual_seed(0)
        flow = torch.randn(2, 2, 12, 17, generator=g, dtype=torch.float64) * 3
        mask = torch.rand(2, 1, 12, 17, generator=g) > 0.3
        hist, edges = vflow_map(flow, mask, bins=10, min_flow=-5.0, max_flow=5.0)
        for b in range(2):
            for r in range(12):
                vals = flow[b, 1, r][mask[b, 0, r]].numpy()
                ref, _ = np.histogram(vals, bins=10, range=(-5.0, 5.0))
                np.testing.assert_array_equal(hist[b, r].numpy(), ref)
        np.testing.assert_allclose(edges.numpy(), np.linspace(-5, 5, 11))

    def test_default_range_covers_the_mask(self):
        _, flow, valid = _straight()
        hist, edges = vflow_map(flow, valid, bins=16)
        assert float(edges[0]) == 0.0
        assert float(edges[-1]) == pytest.approx(float(flow[:, 1][valid[:, 0]].max()))
        assert float(hist.sum()) == float(valid.sum())

    def test_nan_flow_is_skipped(self):
        _, flow, valid = _straight()
        flow = flow.clone()
        flow[0, 1, 40, :10] = float("nan")
        hist, _ = vflow_map(flow, valid)
        assert torch.isfinite(hist).all()
        assert float(hist[0, 40].sum()) == float(valid[0, 0, 40].sum()) - 10

    @settings(max_examples=25, deadline=None)
    @given(seed=st.integers(0, 10_000), bins=st.integers(2, 40), lo=st.floats(-5, 0), width=st.floats(0.1, 10))
    def test_counts_every_in_range_pixel_once(self, seed, bins, lo, width):
        g = torch.Generator().manual_seed(seed)
        flow = torch.randn(2, 2, 7, 9, generator=g, dtype=torch.float64) * 4
        mask = torch.rand(2, 1, 7, 9, generator=g) > 0.5
        hist, edges = vflow_map(flow, mask, bins=bins, min_flow=lo, max_flow=lo + width)
        fv = flow[:, 1:2]
        inside = mask & (fv >= edges[0]) & (fv <= edges[-1])
        torch.testing.assert_close(hist.sum(-1), inside[:, 0].sum(-1).double())
        assert bool((hist >= 0).all())

    @pytest.mark.parametrize("B", [1, 3])
    def test_cardinality(self, B):
        flow = torch.randn(B, 2, 20, 31, generator=torch.Generator().manual_seed(0))
        hist, edges = vflow_map(flow, bins=8)
        assert hist.shape == (B, 20, 8)
        assert torch.all(hist.sum(-1) == 31)

    def test_numpy_numbers_are_options_like_python_numbers(self):
        """A NumPy integer ``bins`` and float bounds were refused ("expected an integer >= 2, got 8")."""
        flow = torch.randn(2, 2, 20, 31, generator=torch.Generator().manual_seed(0))
        plain = vflow_map(flow, bins=8, min_flow=-1.0, max_flow=2.5)
        numpy = vflow_map(flow, bins=np.int64(8), min_flow=np.float32(-1.0), max_flow=np.float64(2.5))
        assert torch.equal(plain.histogram, numpy.histogram) and torch.equal(plain.edges, numpy.edges)

    def test_errors(self):
        flow = torch.zeros(1, 2, 8, 9)
        with pytest.raises(ValueError, match=r"flow: expected shape \(B, 2, H, W\)"):
            vflow_map(torch.zeros(1, 3, 8, 9))
        with pytest.raises(TypeError, match="flow: expected a floating-point tensor"):
            vflow_map(torch.zeros(1, 2, 8, 9, dtype=torch.int64))
        with pytest.raises(TypeError, match="mask: expected dtype torch.bool"):
            vflow_map(flow, torch.ones(1, 1, 8, 9))
        with pytest.raises(ValueError, match="mask: expected shape"):
            vflow_map(flow, torch.ones(1, 1, 8, 8, dtype=torch.bool))
        with pytest.raises(ValueError, match="bins: expected an integer >= 2"):
            vflow_map(flow, bins=1)
        with pytest.raises(ValueError, match="max_flow: expected > min_flow"):
            vflow_map(flow, min_flow=2.0, max_flow=1.0)

    @pytest.mark.parametrize("lo, hi, bins", [(-1.3, 7.9, 7), (0.0, 37.99993986673388, 128), (-2.7, 41.3, 255)])
    def test_values_on_an_edge_are_in_the_bin_above(self, lo, hi, bins):
        """Bin k holds edges[k] <= F_v < edges[k+1], the last bin its upper edge too, as
        numpy.histogram bins with these edges (the affine index put about one edge in seven into
        the bin below, by rounding)."""
        edges = vflow_map(torch.zeros(1, 2, 1, 1, dtype=torch.float64), bins=bins, min_flow=lo, max_flow=hi).edges
        assert float(edges[0]) == lo and float(edges[-1]) == hi
        flow = torch.zeros(1, 2, 1, bins + 1, dtype=torch.float64)
        flow[0, 1, 0] = edges
        hist, _ = vflow_map(flow, bins=bins, min_flow=lo, max_flow=hi)
        ref, _ = np.histogram(edges.numpy(), bins=edges.numpy())
        np.testing.assert_array_equal(hist[0, 0].numpy(), ref)
        assert hist[0, 0].tolist() == [1.0] * (bins - 1) + [2.0]

    def test_a_given_bound_is_kept(self):
        """A max_flow at or below the data's default lower bound (or a min_flow above its upper
        one) keeps its bound: the range lies beyond it, and no flow outside the requested range is
        counted (the range was [0, 1], counting flows above max_flow=-2)."""
        flow = torch.zeros(1, 2, 4, 5)
        flow[:, 1] = torch.arange(4.0).reshape(4, 1) + 1.0  # F_v in 1 ... 4
        hist, edges = vflow_map(flow, bins=4, max_flow=-2.0)
        assert edges.tolist() == [-3.0, -2.75, -2.5, -2.25, -2.0] and float(hist.sum()) == 0.0
        hist, edges = vflow_map(flow, bins=4, max_flow=1.0)  # the flows equal to max_flow count
        assert edges.tolist() == [0.0, 0.25, 0.5, 0.75, 1.0] and float(hist.sum()) == 5.0
        hist, edges = vflow_map(flow, bins=4, min_flow=10.0)
        assert edges.tolist() == [10.0, 10.25, 10.5, 10.75, 11.0] and float(hist.sum()) == 0.0
        hist, edges = vflow_map(flow, bins=4, min_flow=4.0)
        assert edges.tolist() == [4.0, 4.25, 4.5, 4.75, 5.0] and float(hist.sum()) == 5.0
        hist, edges = vflow_map(flow, bins=4, max_flow=2.5)  # a bound within the data, as before
        assert float(edges[0]) == 0.0 and float(edges[-1]) == 2.5 and float(hist.sum()) == 10.0

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_a_range_wider_than_the_dtype_has_finite_edges(self, dtype):
        # hi - lo overflows; the edges must still be finite, increasing and span [lo, hi]
        big = float(torch.tensor(torch.finfo(dtype).max * 0.9, dtype=dtype))
        flow = torch.zeros(1, 2, 2, 3, dtype=dtype)
        flow[0, 1, 0] = torch.tensor([-big, 0.0, big], dtype=dtype)
        hist, edges = vflow_map(flow, bins=4)
        assert torch.isfinite(edges).all() and bool((edges.diff() > 0).all())
        assert float(edges[0]) == -big and float(edges[-1]) == big
        assert hist[0].tolist() == [[1, 0, 1, 1], [0, 0, 3, 0]]

    @pytest.mark.parametrize("half", [torch.float16, torch.bfloat16])
    def test_half_precision_is_counted_in_float32(self, half):
        _, flow, valid = _straight(torch.float32)
        hist, edges = vflow_map(flow.to(half), valid, bins=32)
        assert hist.dtype == torch.float32 and edges.dtype == torch.float32
        ref, ref_edges = vflow_map(flow.to(half).float(), valid, bins=32)
        assert torch.equal(hist, ref) and torch.equal(edges, ref_edges)


# -- per-row statistic --------------------------------------------------------------------------

class TestRowDominant:
    def test_peak_is_not_quantised(self):
        _, flow, valid = _straight()
        value, support = row_dominant_flow(flow, valid, bins=8)
        rows = support[0] > 0
        torch.testing.assert_close(value[0][rows], flow[0, 1, :, 80][rows], atol=1e-12, rtol=0)

    def test_peak_ignores_a_minority_obstacle(self):
        _, flow, valid = _straight()
        flow = flow.clone()
        flow[0, 1, 30:50, 10:60] = 0.3  # an obstacle over a third of these rows
        value, _ = row_dominant_flow(flow, valid, bins=64)
        _, clean, _ = _straight()
        torch.testing.assert_close(value[0, 30:50], clean[0, 1, 30:50, 80], atol=1e-12, rtol=0)

    def test_median(self):
        flow = torch.zeros(1, 2, 3, 5, dtype=torch.float64)
        flow[0, 1] = torch.tensor([[1.0, 2, 3, 4, 100], [5, 5, 5, 5, 5], [0, 0, 0, 0, 0]])
        mask = torch.ones(1, 1, 3, 5, dtype=torch.bool)
        mask[0, 0, 2] = False
        value, support = row_dominant_flow(flow, mask, statistic="median")
        assert value[0].tolist() == [3.0, 5.0, 0.0]
        assert support[0].tolist() == [5.0, 5.0, 0.0]
        # an even count: the mean of the middle two, as numpy.median (was: the lower, 2)
        mask[0, 0, 0, 4] = False
        value, support = row_dominant_flow(flow, mask, statistic="median")
        assert float(value[0, 0]) == float(np.median([1.0, 2, 3, 4])) == 2.5 and float(support[0, 0]) == 4.0

    def test_peak_neighbours_include_the_upper_edge(self):
        """A flow on the last edge lies in the last bin, a neighbour of the one below it (the
        affine index put it one bin further, out of the peak's neighbours)."""
        flow = torch.zeros(1, 2, 1, 4, dtype=torch.float64)
        flow[0, 1, 0] = torch.tensor([2.5, 2.5, 2.6, 4.0], dtype=torch.float64)
        value, support = row_dominant_flow(flow, bins=4, min_flow=0.0, max_flow=4.0)
        assert support.tolist() == [[4.0]] and float(value) == pytest.approx(2.9, abs=1e-12)

    def test_bad_statistic(self):
        with pytest.raises(ValueError, match="statistic: expected 'peak' or 'median'"):
            row_dominant_flow(torch.zeros(1, 2, 4, 4), statistic="mean")


    @pytest.mark.parametrize("options, error, message", [
        (dict(bins=0), ValueError, "bins: expected an integer >= 2, got 0"),
        (dict(bins=2.5), TypeError, "bins: expected an integer >= 2, got 2.5"),
        (dict(max_flow=float("nan")), ValueError, "max_flow: expected a finite number or None, got nan"),
        (dict(min_flow="1"), TypeError, "min_flow: expected a finite number or None, got '1'"),
        (dict(min_flow=2.0, max_flow=1.0), ValueError, "max_flow: expected > min_flow"),
    ])
    def test_histogram_options_are_checked_with_the_median_too(self, options, error, message):
        # the median reads no histogram, but a bad option is an error there too (not ignored)
        flow = torch.zeros(1, 2, 4, 4)
        with pytest.raises(error, match=message):
            row_dominant_flow(flow, statistic="median", **options)
        if "min_flow" not in options:
            with pytest.raises(error, match=message):
                fit_vflow_curve(flow, statistic="median", **options)


# -- curve fit -------------------------------------------------------------------------------------

class TestFitVFlowCurve:
    def test_curve_model_matches_flow_model(self):
        v = torch.arange(64, dtype=torch.float64)
        z_d, h, fy, cy = 1.3, 1.5, 200.0, 18.0
        ref = vflow_curve(v, z_d, h, fy, cy)
        ours = vflow_curve_model(v, torch.tensor(z_d / (h * fy), dtype=torch.float64), torch.tensor(cy, dtype=torch.float64))
        torch.testing.assert_close(ours, ref, atol=1e-12, rtol=0)

    def test_curve_model_checks_its_arguments_as_vflow_curve(self):
        """A NaN or inf a or v0 read as "no road flow" (0 on every row) or gave inf; numbers,
        mismatched shapes and half precision went to torch's errors or overflowed in float16."""
        v = torch.arange(6, dtype=torch.float64)
        for name, bad in (("a", dict(a=float("nan"))), ("v0", dict(v0=float("inf"))), ("v", dict(v=[1.0, float("nan")]))):
            args = dict(v=v, a=torch.tensor(0.01, dtype=torch.float64), v0=1.0) | bad
            for model in ("displacement", "velocity"):
                with pytest.raises(ValueError, match=f"^{name}: expected finite values"):
                    vflow_curve_model(**args, model=model)
        with pytest.raises(ValueError, match=r"v, a, v0: expected shapes that broadcast together, got v \(3,\), a \(4,\)"):
            vflow_curve_model(torch.zeros(3), torch.zeros(4), 0.0)
        with pytest.raises(TypeError, match="a: expected a tensor or a number, got bool True"):
            vflow_curve_model(v, True, 1.0)
        assert float(vflow_curve_model(3.0, 0.01, 1.0)) == pytest.approx(0.04 / 0.98)
        half = vflow_curve_model(torch.arange(300.0, dtype=torch.float16), torch.tensor(2.0, dtype=torch.float16), 0.0,
                                 model="velocity")
        assert half.dtype == torch.float32 and float(half[-1]) == 2.0 * 299**2

    @pytest.mark.parametrize("statistic", ["peak", "median"])
    def test_the_fit_is_detached(self, statistic):
        """A fit is not differentiable (docs/fitting.md): given a flow that requires grad, its
        results are plain detached tensors. They once carried a graph through the robust fit that
        failed on backward (a tensor of it changed in place)."""
        _, flow, valid = _straight()
        flow = (flow + 0.01 * torch.randn(flow.shape, generator=torch.Generator().manual_seed(0),
                                          dtype=flow.dtype)).requires_grad_()
        curve = fit_vflow_curve(flow, valid, statistic=statistic)
        assert bool(curve.success.all())
        tensors = [v for v in vars(curve).values() if isinstance(v, torch.Tensor)]
        assert tensors and not any(t.requires_grad or t.is_inference() for t in tensors)
        assert not flow.grad_fn and flow.grad is None

    @pytest.mark.parametrize("model", ["displacement", "velocity"])
    def test_curve_gradcheck(self, model):
        v = torch.linspace(20.0, 60.0, 9, dtype=torch.float64)
        a = torch.tensor(0.004, dtype=torch.float64, requires_grad=True)
        v0 = torch.tensor(18.5, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(lambda a_, v0_: vflow_curve_model(v, a_, v0_, model), (a, v0))

    @pytest.mark.parametrize("model", ["displacement", "velocity"])
    def test_analytic_jacobian_of_the_fit(self, model):
        """The Gauss–Newton Jacobian (private) against autograd."""
        from fsof_torch.estimation.vflow import _curve

        v = torch.linspace(20.0, 60.0, 9, dtype=torch.float64)
        a = torch.tensor(0.004, dtype=torch.float64, requires_grad=True)
        v0 = torch.tensor(18.5, dtype=torch.float64, requires_grad=True)
        f, da, dv0, _ = _curve(v, a, v0, model)
        for i in range(v.numel()):
            ga, gv0 = torch.autograd.grad(f[i], (a, v0), retain_graph=True)
            torch.testing.assert_close(da[i], ga, rtol=1e-12, atol=1e-15)
            torch.testing.assert_close(dv0[i], gv0, rtol=1e-12, atol=1e-15)

    @pytest.mark.parametrize("z_d", [0.4, 1.0, 2.5, -0.8])
    def test_recovers_displacement_parameters(self, z_d):
        cam, flow, valid = _straight(z_d=z_d)
        curve = fit_vflow_curve(flow, valid)
        assert isinstance(curve, VFlowCurve) and bool(curve.success)
        torch.testing.assert_close(curve.scale(cam), torch.tensor([z_d], dtype=torch.float64), atol=0, rtol=1e-6)
        torch.testing.assert_close(curve.v0, cam.cy, atol=0, rtol=1e-6)
        # The fitted F_v map is the eq. 24 curve on every road row.
        torch.testing.assert_close(curve.fitted[valid[:, :1]], flow[:, 1:2][valid], atol=1e-8, rtol=0)

    def test_recovers_velocity_parameters(self):
        cam = _camera()
        flow, valid = velocity_flow(cam, 12.0, 0.0, 2.7, SIZE)
        curve = fit_vflow_curve(flow, valid, model="velocity")
        torch.testing.assert_close(curve.scale(cam), torch.tensor([12.0], dtype=torch.float64), atol=0, rtol=1e-6)
        torch.testing.assert_close(curve.v0, cam.cy, atol=0, rtol=1e-6)

    @pytest.mark.parametrize("pitch_deg", [-8.0, 5.0])
    def test_scale_of_a_pitched_camera(self, pitch_deg):
        # a pitched camera's road still draws the curve exactly, around its horizon row, with
        # a = z_d cos²β / (h f_y): scale() gives z_d (v_r), not z_d cos²β
        cam = _camera(pitch=float(np.radians(pitch_deg)))
        flow, valid = displacement_flow(cam, 0.0, 1.2, 0.0, SIZE)
        curve = fit_vflow_curve(flow, valid)
        assert bool(curve.success) and float(curve.residual) < 1e-9
        torch.testing.assert_close(curve.scale(cam), torch.tensor([1.2], dtype=torch.float64), atol=0, rtol=1e-9)
        torch.testing.assert_close(curve.v0, cam.horizon_row(), atol=1e-9, rtol=0)
        flow, valid = velocity_flow(cam, 12.0, 0.0, 2.7, SIZE)
        curve = fit_vflow_curve(flow, valid, model="velocity")
        torch.testing.assert_close(curve.scale(cam), torch.tensor([12.0], dtype=torch.float64), atol=0, rtol=1e-9)

    def test_scale_names_a_camera_of_another_batch(self):
        cam, flow, valid = _straight(B=2)
        curve = fit_vflow_curve(flow, valid)
        assert curve.scale(cam).shape == (2,) and curve.scale(cam.expand(2)).shape == (2,)
        with pytest.raises(ValueError, match=r"camera: expected batch 1 or 2 \(from the curve\), got 3"):
            curve.scale(cam.expand(3))

    def test_numpy_numbers_are_options_like_python_numbers(self):
        import numpy as np

        cam, flow, valid = _straight(z_d=1.0)
        plain = fit_vflow_curve(flow, valid, hypotheses=50, iterations=10, inlier_threshold=0.5, max_false_alarms=1.0)
        numpy = fit_vflow_curve(flow, valid, hypotheses=np.int64(50), iterations=np.int32(10),
                                inlier_threshold=np.float32(0.5), max_false_alarms=np.float64(1.0))
        assert torch.equal(plain.a, numpy.a) and torch.equal(plain.v0, numpy.v0)
        with pytest.raises(TypeError, match="inlier_threshold: expected a finite number >= 0, got True"):
            fit_vflow_curve(flow, valid, inlier_threshold=True)

    def test_float32(self):
        cam, flow, valid = _straight(torch.float32)
        curve = fit_vflow_curve(flow, valid)
        assert curve.a.dtype == torch.float32 and curve.fitted.dtype == torch.float32
        torch.testing.assert_close(curve.scale(cam), torch.tensor([1.0]), atol=0, rtol=1e-4)

    def test_robust_to_obstacle_rows(self):
        """Obstacles fill whole rows (a wall ahead, cars side by side): those rows are outliers."""
        cam, flow, valid = _straight(z_d=1.2)
        flow = flow.clone()
        # A fronto-parallel wall at the depth of row 30: flow radial with a constant scale.
        dv = torch.arange(SIZE[0], dtype=torch.float64) - 18.0
        scale = 1.2 / (1.5 * 200.0 / 12.0 - 1.2)
        flow[0, 1, 20:30, :] = scale * dv[20:30].reshape(-1, 1)
        g = torch.Generator().manual_seed(1)
        flow[0, 1, 45:52, :] += 3.0 + torch.rand(7, 1, generator=g, dtype=torch.float64)  # other motions
        # Noise-free flow: a tight threshold, else wall rows near the contact row pass as road.
        curve = fit_vflow_curve(flow, valid, inlier_threshold=0.01)
        torch.testing.assert_close(curve.scale(cam), torch.tensor([1.2], dtype=torch.float64), atol=0, rtol=1e-6)
        assert not curve.row_inliers[0, 45:52].any() and not curve.row_inliers[0, 20:28].any()
        # The default threshold (0.5 px) still keeps the outliers' effect small.
        curve = fit_vflow_curve(flow, valid)
        assert abs(float(curve.scale(cam)) - 1.2) < 0.03

    def test_noise(self):
        cam, flow, valid = _straight(z_d=1.5)
        g = torch.Generator().manual_seed(0)
        noisy = flow + 0.2 * torch.randn(flow.shape, generator=g, dtype=torch.float64)
        curve = fit_vflow_curve(noisy, valid, statistic="median")
        assert abs(float(curve.scale(cam)) - 1.5) < 0.03
        assert abs(float(curve.v0) - 18.0) < 0.5

    @pytest.mark.parametrize("B", [1, 3])
    def test_cardinality(self, B):
        z = torch.tensor([0.5, 1.0, 2.0][:B], dtype=torch.float64)
        cam = _camera(B=B)
        zero = torch.zeros_like(z)
        flow, valid = displacement_flow(cam, zero, z, zero, (48, 71))
        curve = fit_vflow_curve(flow, valid)
        assert curve.a.shape == (B,) and curve.fitted.shape == (B, 1, 48, 71)
        assert curve.row_value.shape == (B, 48) and curve.success.all()
        torch.testing.assert_close(curve.scale(cam), z, atol=0, rtol=1e-6)

    def test_deterministic(self):
        _, flow, valid = _straight()
        flow = flow + 0.3 * torch.randn(flow.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
        a = fit_vflow_curve(flow, valid, seed=5)
        b = fit_vflow_curve(flow, valid, seed=5)
        assert torch.equal(a.a, b.a) and torch.equal(a.v0, b.v0)

    def test_empty_mask_fails_cleanly(self):
        _, flow, valid = _straight()
        curve = fit_vflow_curve(flow, torch.zeros_like(valid))
        assert not bool(curve.success)
        assert torch.isfinite(curve.a).all() and torch.isfinite(curve.fitted).all()
        assert not curve.fitted_valid.any()

    def test_nan_flow_in_mask(self):
        cam, flow, valid = _straight()
        flow = flow.clone()
        flow[0, :, 50, 3:9] = float("nan")
        curve = fit_vflow_curve(flow, valid)
        torch.testing.assert_close(curve.scale(cam), torch.tensor([1.0], dtype=torch.float64), atol=0, rtol=1e-6)

    def test_random_flow_is_no_curve(self):
        """Noise draws no road: the curve RANSAC finds through a few of its rows is no more than
        chance gives (fit_vflow_curve succeeded on 13 of these 15 frames while its only bar was 5
        inlier rows), and only the chance bar rejects them."""
        g = torch.Generator().manual_seed(0)
        amplitude = torch.tensor([1.0, 2.0, 5.0, 10.0, 20.0]).repeat(3).reshape(15, 1, 1, 1)
        flow = (2 * torch.rand(15, 2, 96, 320, generator=g) - 1) * amplitude
        curve = fit_vflow_curve(flow)
        assert not curve.success.any()
        assert (curve.nfa > 1e4).all()  # far beyond the bar of 1, not just beyond it
        lenient = fit_vflow_curve(flow, max_false_alarms=1e30)
        assert lenient.success.sum() >= 10 and torch.equal(lenient.row_inliers, curve.row_inliers)
        assert not detect_freespace(flow, _camera(torch.float32)).any()

    @pytest.mark.parametrize("road_noise", [0.0, 0.15])
    def test_false_alarms_against_the_binomial_tail(self, road_noise):
        """``nfa`` = min over the precisions α = 1, 1/2, ..., 1/1024 of the band of
        11 C(n, 3) P(Binomial(n - 3, p(α)) >= k(α) - 3), written out with math.comb: k(α) the rows
        within α of their band, p(α) the mean share of the usable rows' values inside a row's band
        narrowed to α. Half the road's rows spoiled; its other rows exact or noisy."""
        import math

        cam, flow, valid = _straight(z_d=2.0, size=(48, 16))
        g = torch.Generator().manual_seed(2)
        flow = flow + road_noise * torch.randn(48, 1, generator=g, dtype=torch.float64).expand(48, 16)
        noise_rows = torch.arange(18, 48, 2)        # every second road row replaced by a random value
        flow[0, 1, noise_rows] = (30 * torch.rand(len(noise_rows), 1, generator=g, dtype=torch.float64)).expand(-1, 16)
        curve = fit_vflow_curve(flow, valid)
        assert bool(curve.success)
        y, usable = curve.row_value[0].tolist(), (curve.row_support[0] >= 3).tolist()
        f = vflow_curve_model(torch.arange(48, dtype=torch.float64), curve.a, curve.v0).tolist()
        thr = [max(0.5, 0.05 * abs(value)) for value in y]
        rows = [v for v in range(48) if usable[v]]
        n = len(rows)
        best = math.inf
        for alpha in (2.0 ** -i for i in range(11)):
            k = sum(abs(y[v] - f[v]) <= alpha * thr[v] for v in rows)
            p = sum(sum(abs(y[j] - f[v]) <= alpha * thr[j] for j in rows) for v in rows) / n**2
            tail = sum(math.comb(n - 3, i) * p**i * (1 - p) ** (n - 3 - i) for i in range(max(k - 3, 0), n - 2))
            best = min(best, 11 * math.comb(n, 3) * tail)
        assert best < 1
        assert float(curve.nfa) == pytest.approx(best, rel=1e-9)

    def test_a_clean_curve_of_little_flow_is_no_chance_curve(self):
        """A road whose flow spans 1.5 px, every row on the curve: at the 0.5 px band most rows'
        values would agree by chance (NFA 7 to 22 there), at the precision its rows reach none."""
        import fsof_torch.data.scene as scene

        pair = scene.render_pair("carla-turning", 0, seed=0, size=(48, 160), dtype=torch.float64)
        flow = pair["flow"].unsqueeze(0)
        assert float(flow[:, 1][pair["road"].unsqueeze(0)[:, 0]].max()) < 2.0
        for mask in (pair["road"], pair["valid"]):
            curve = fit_vflow_curve(flow, mask.unsqueeze(0))
            assert bool(curve.success) and float(curve.nfa) < 1e-6

    def test_errors(self):
        flow = torch.zeros(1, 2, 8, 9)
        with pytest.raises(ValueError, match="model: expected one of"):
            fit_vflow_curve(flow, model="affine")
        with pytest.raises(ValueError, match="hypotheses: expected an integer >= 1"):
            fit_vflow_curve(flow, hypotheses=0)
        with pytest.raises(ValueError, match="inlier_threshold: expected a finite number"):
            fit_vflow_curve(flow, inlier_threshold=float("nan"))
        for bad, error in ((0, ValueError), (-1.0, ValueError), (float("inf"), ValueError), (True, TypeError),
                           ("1", TypeError)):
            with pytest.raises(error, match=rf"^max_false_alarms: expected a finite number > 0, got {bad!r}$"):
                fit_vflow_curve(flow, max_false_alarms=bad)
        with pytest.raises(TypeError, match="camera: expected a fsof_torch.Camera"):
            fit_vflow_curve(flow).scale("camera")

    def test_seed_and_empty_batch_named(self):
        """The seed is a Generator's (0 <= seed < 2**64; it raised int()'s or an overflow error,
        and took 1.5 and -1); an empty batch is named (it was torch.cat's error)."""
        _, flow, valid = _straight()
        for seed, error, shown in (("x", TypeError, "str 'x'"), (1.5, TypeError, "float 1.5"),
                                   (True, TypeError, "bool True")):
            with pytest.raises(error, match=rf"^seed: expected an int, got {shown}$"):
                fit_vflow_curve(flow, valid, seed=seed)
        for seed in (-1, 2**64, 2**70):
            with pytest.raises(ValueError, match=rf"^seed: expected an int with 0 <= seed < 2\*\*64, got {seed}$"):
                fit_vflow_curve(flow, valid, seed=seed)
        assert bool(fit_vflow_curve(flow, valid, seed=2**64 - 1).success)
        empty = torch.zeros(0, 2, 8, 8, dtype=torch.float64)
        with pytest.raises(ValueError, match=r"^flow: expected a non-empty batch, got shape \(0, 2, 8, 8\)$"):
            fit_vflow_curve(empty)
        with pytest.raises(ValueError, match=r"^flow: expected a non-empty batch, got shape \(0, 2, 8, 8\)$"):
            detect_freespace(empty, _camera())


# -- freespace detection --------------------------------------------------------------------------

def _iou(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a & b).sum()) / max(1.0, float((a | b).sum()))


@pytest.mark.slow
def test_a_rolled_camera_spreads_the_rows():
    """docs/vflow.md's figures for a camera rolled 1° (KITTI geometry, exact flow): the rows'
    flow spreads, the peak's curve drifts, the median's stays near, the freespace fits the roll."""
    K = torch.tensor([[721.5, 0, 609.6], [0, 721.5, 172.9], [0, 0, 1]], dtype=torch.float64)
    cam = Camera(K, 1.65, roll=float(np.radians(1.0)))
    flow, valid = displacement_flow(cam, 0.0, 1.2, 0.0, (375, 1242))
    bottom = flow[0, 1, -1][valid[0, 0, -1]]
    assert float(bottom.max() - bottom.min()) == pytest.approx(6.9, abs=0.05)
    peak = fit_vflow_curve(flow, valid)
    assert float(peak.scale(cam)) == pytest.approx(1.169, abs=5e-4) and float(peak.v0) == pytest.approx(175.85, abs=0.005)
    median = fit_vflow_curve(flow, valid, statistic="median")
    assert float(median.scale(cam)) == pytest.approx(1.1999, abs=5e-5)
    assert float(median.v0) == pytest.approx(172.8, abs=0.05)
    found = detect_freespace(flow, cam, mask=valid, return_details=True)
    assert bool(found.success) and bool((found.freespace == valid).all())
    torch.testing.assert_close(found.fit.params["z_d"], torch.tensor([1.2], dtype=torch.float64), atol=1e-4, rtol=0)


@pytest.mark.slow
def test_a_pitch_held_wrong_loses_the_freespace():
    """docs/vflow.md's figures: a camera given level for a scene pitched by -0.5° or -1° (KITTI
    geometry, exact flow) holds the wrong pitch by default; fit_pitch=True finds the road; the
    curve's v0 is the true horizon row."""
    K = torch.tensor([[721.5, 0, 609.6], [0, 721.5, 172.9], [0, 0, 1]], dtype=torch.float64)
    level = Camera(K, 1.65)
    for pitch_deg in (-0.5, -1.0):
        cam = Camera(K, 1.65, pitch=float(np.radians(pitch_deg)))
        flow, valid = displacement_flow(cam, 0.0, 1.2, 0.0, (375, 1242))
        held = detect_freespace(flow, level, mask=valid, return_details=True)
        assert not bool(held.success) and not bool(held.freespace.any())
        torch.testing.assert_close(held.curve.v0, cam.horizon_row(), atol=1e-6, rtol=0)
        coarse = detect_freespace(flow, level, mask=valid, threshold=1.0, return_details=True)
        share = float((coarse.freespace & valid).sum() / valid.sum())
        assert share == (pytest.approx(0.684, abs=0.005) if pitch_deg == -0.5 else 0.0)
        for threshold in (0.25, 1.0):
            assert bool((detect_freespace(flow, level, mask=valid, threshold=threshold, fit_pitch=True) == valid).all())


def test_a_wall_passes_the_curve_not_the_freespace():
    """docs/vflow.md: the a-contrario test is against chance, not other structure: a wall facing
    the camera 30 m ahead, approached by 1 m (flow (p - p_0) / 29, measured to 0.01 px), passes as a
    curve; the freespace detection finds none. Its exact flow, F_v linear in the row, is no curve:
    three collinear rows solve to a ≈ 0 (a rounding's worth) with the horizon ~1e15 px away; a
    curve defined on no row of the image is refused (before, one such, below the image, won by
    scoring the rows of small flow as inliers of its zero, and the fit failed or passed by the
    machine's rounding)."""
    cam = Camera(torch.tensor([[300.0, 0, 80], [0, 300, 20], [0, 0, 1]], dtype=torch.float64), 1.5)
    v, u = torch.meshgrid(torch.arange(64.0, dtype=torch.float64), torch.arange(160.0, dtype=torch.float64),
                          indexing="ij")
    wall = torch.stack([u - 80, v - 20])[None] / 29.0
    assert float(wall[:, 1].abs().max()) < 1.5
    exact = fit_vflow_curve(wall)
    assert not bool(exact.success) and int(exact.row_inliers.sum()) < 29
    for seed in range(3):
        measured = wall + 0.01 * torch.randn(wall.shape, generator=torch.Generator().manual_seed(seed),
                                             dtype=torch.float64)
        curve = fit_vflow_curve(measured)
        assert bool(curve.success) and float(curve.nfa) < 1e-10 and int(curve.row_inliers.sum()) > 50
        assert float(curve.scale(cam)) == pytest.approx(0.21, abs=0.005)
        found = detect_freespace(measured, cam, return_details=True)
        assert not bool(found.success) and not bool(found.freespace.any())


class TestDetectFreespace:
    def test_a_pavement_nearly_as_wide_as_the_road(self):
        """docs/vflow.md's limitation: a pavement 12 cm higher (8 % more flow) enters the default
        seed band; where it holds more of the seed than the road the first fit locks onto it, and
        the fit of the rest of the seed finds the road, kept as long as the road holds more of the
        pixels connected to the bottom (the pavements' 140 px a side drew the fit before)."""
        K = torch.tensor([[721.5377, 0.0, 609.5593], [0.0, 721.5377, 172.854], [0.0, 0.0, 1.0]], dtype=torch.float64)
        cam = Camera(K, 1.65).scaled(0.5)
        size = (188, 621)
        road, valid = displacement_flow(cam, 0.0, 1.2, 0.0, size)
        pavement, _ = displacement_flow(cam.replace(height=1.65 - 0.12), 0.0, 1.2, 0.0, size)

        def iou(width, **options):
            side = torch.zeros(1, 1, *size, dtype=torch.bool)
            side[..., :width] = True
            side[..., -width:] = True
            free = detect_freespace(torch.where(side, pavement, road), cam, threshold=0.05, relative_threshold=0.02,
                                    **options)
            truth = valid & ~side
            return float((free & truth).sum() / (free | truth).sum())

        assert iou(130) > 0.98
        assert iou(150) > 0.98   # 48 % of every row
        assert iou(160) < 0.1    # 52 %: from flow alone the pavement is as good a plane

    def test_cvc_simple_road_beside_wider_pavements(self):
        """The cvc-simple preset (no buildings): the pavements, 12 cm above the road, cover more
        of the upper rows than the road and drew the fit (z_d 0.543 for 0.5, and no pixel of its
        agreement reached the bottom: an empty freespace with success=True)."""
        import fsof_torch.data.scene as scene

        pair = scene.render_pair("cvc-simple", 0, seed=0, size=(128, 416), dtype=torch.float64)
        valid = pair["valid"].unsqueeze(0)
        det = detect_freespace(pair["flow"].unsqueeze(0), pair["camera"], mask=valid, threshold=0.05,
                               relative_threshold=0.02, return_details=True)
        assert bool(det.success.all())
        assert float(det.fit.params["z_d"][0]) == pytest.approx(0.5, abs=1e-3)
        # (the pavements near the horizon, whose flow differs from the road's by less than
        # 0.05 px, agree with the road model: the IoU is below the cvc-complex preset's)
        assert _iou(det.freespace[0], pair["road"] & pair["valid"]) > 0.75

    def test_no_freespace_is_a_failure(self):
        """A road model that agrees with no pixel connected to the bottom (here the lowest rows
        hold a foreign flow) gives an empty freespace, flagged as a failure (it was a success)."""
        cam = _camera()
        flow, valid = displacement_flow(cam, 0.0, 1.0, 0.0, SIZE)
        flow = flow.clone()
        flow[:, :, -12:] = torch.tensor([3.0, -4.0], dtype=flow.dtype).reshape(1, 2, 1, 1)
        det = detect_freespace(flow, cam, mask=valid, return_details=True)
        assert det.agreement.any()   # the road above the foreign rows agrees with the fit
        assert not det.freespace.any() and not bool(det.success.any())

    def _scene(self, B=1):
        """Road flow of a turning motion with an obstacle standing on the road and a detached
        island of road-like flow above the obstacle."""
        cam = _camera(B=B, roll=0.01)
        full = lambda x: torch.full((B,), x, dtype=torch.float64)  # noqa: E731
        flow, valid = displacement_flow(cam, full(0.05), full(1.0), full(0.01), SIZE)
        flow = flow.clone()
        road = valid.clone()
        # Obstacle: a fronto-parallel surface standing on row 40, columns 60..100.
        v = torch.arange(SIZE[0], dtype=torch.float64).reshape(-1, 1)
        u = torch.arange(SIZE[1], dtype=torch.float64).reshape(1, -1)
        scale = 1.0 / (1.5 * 200.0 / (40 - 18.0) - 1.0)
        flow[:, 0, 20:41, 60:100] = (scale * (u - 80.0)).expand(SIZE)[20:41, 60:100]
        flow[:, 1, 20:41, 60:100] = (scale * (v - 18.0)).expand(SIZE)[20:41, 60:100]
        road[:, :, 20:41, 60:100] = False
        return cam, flow, valid, road

    def test_separates_obstacle(self):
        cam, flow, valid, road = self._scene()
        free = detect_freespace(flow, cam)
        assert free.shape == (1, 1, *SIZE) and free.dtype == torch.bool
        # Where the obstacle touches the road the two flows agree: judge the upper part only.
        assert not free[:, :, 20:36, 60:100].any()
        assert _iou(free, road) > 0.95

    def test_keeps_only_bottom_connected(self):
        cam, flow, valid, road = self._scene()
        flow = flow.clone()
        # Surround a patch of road by a ring of foreign flow: the patch is cut off from the bottom.
        flow[:, :, 44:60, 5:8] += 5.0
        flow[:, :, 44:60, 30:33] += 5.0
        flow[:, :, 44:47, 5:33] += 5.0
        flow[:, :, 57:60, 5:33] += 5.0
        free = detect_freespace(flow, cam, max_hole_fraction=0.0, close_kernel=0)
        assert not free[:, :, 47:57, 8:30].any()
        assert free[:, :, 62:, 40:].all()

    def test_details_and_mask(self):
        cam, flow, valid, road = self._scene()
        mask = torch.ones_like(valid)
        mask[..., :, :20] = False
        det = detect_freespace(flow, cam, mask=mask, return_details=True)
        assert isinstance(det, FreespaceDetection)
        assert not det.freespace[..., :20].any()
        assert det.seed.any() and bool(det.success.all())
        assert (det.freespace & ~valid).sum() == 0

    @pytest.mark.parametrize("B", [1, 3])
    def test_cardinality(self, B):
        cam, flow, valid, road = self._scene(B=B)
        free = detect_freespace(flow, cam)
        assert free.shape == (B, 1, *SIZE)
        for b in range(B):
            assert _iou(free[b], road[b]) > 0.95

    def test_errors(self):
        cam, flow, valid, road = self._scene()
        with pytest.raises(TypeError, match="camera: expected a fsof_torch.Camera"):
            detect_freespace(flow, None)
        with pytest.raises(ValueError, match="threshold: expected a number >= 0, got -1.0"):
            detect_freespace(flow, cam, threshold=-1.0)
        with pytest.raises(ValueError, match="threshold: expected a finite number, got inf"):
            detect_freespace(flow, cam, threshold=float("inf"))
        with pytest.raises(ValueError, match="bottom_rows: expected an int >= 1, got 0"):
            detect_freespace(flow, cam, bottom_rows=0)
        with pytest.raises(ValueError, match="camera: expected batch 1 "):
            detect_freespace(flow, _camera(B=2))
        with pytest.raises(TypeError, match="fit_roll: expected True or False, got str 'yes'"):
            detect_freespace(flow, cam, fit_roll="yes")
        with pytest.raises(TypeError, match="fit_options: expected None or a dict with string keys, got int 5"):
            detect_freespace(flow, cam, fit_options=5)

    @pytest.mark.parametrize("half", [torch.float16, torch.bfloat16])
    def test_agreement_of_half_precision_flow_in_float32(self, half):
        """The agreement test of a half precision flow runs in float32, as the fit's model flow (it
        rounded the model flow, the error and the tolerance to the flow's dtype: 16 and 4 of
        about 5700 pixels differed here)."""
        import fsof_torch.data.scene as scene

        pair = scene.render_pair("default", 0, seed=0, size=(96, 320))
        cam, flow, valid = pair["camera"], pair["flow"][None].to(half), pair["valid"][None]
        det = detect_freespace(flow, cam, mask=valid, refits=0, return_details=True)
        model = det.fit.flow
        assert model.dtype == torch.float32
        err = (flow.float() - model).norm(dim=1, keepdim=True)
        tol = torch.clamp(0.03 * model.norm(dim=1, keepdim=True), min=0.25)
        assert torch.equal(det.agreement, valid & det.fit.valid & (err <= tol))

    def test_meta_device_needs_values(self):
        """The detection and the V-flow curve are fits: a named error on the meta device, where
        the V-flow map itself infers shapes."""
        cam, flow, valid, road = self._scene(B=2)
        meta = flow.to("meta")
        with pytest.raises(ValueError, match="flow: a tensor on the meta device has shapes but no values to detect"):
            detect_freespace(meta, cam)
        with pytest.raises(ValueError, match="flow: a tensor on the meta device has shapes but no values to fit the V-flow"):
            fit_vflow_curve(meta, valid.to("meta"))
        hist, edges = vflow_map(meta, valid.to("meta"), bins=16)
        assert hist.device.type == "meta" and hist.shape == (2, SIZE[0], 16) and edges.shape == (17,)

    @pytest.mark.parametrize("fill", [0.0, float("nan")])
    def test_undeterminable_flow_gives_empty_failed_result(self, fill):
        """A standing car (zero flow) or a flow with no finite value: flagged, empty, no NaN."""
        cam = _camera()
        flow = torch.full((1, 2, *SIZE), fill, dtype=torch.float64)
        det = detect_freespace(flow, cam, return_details=True)
        assert not bool(det.success.any()) and not det.freespace.any()
        assert torch.isfinite(det.curve.a).all()

    def test_cvc_complex_iou(self):
        """Freespace of the cvc-complex preset from its ground-truth flow: IoU >= 0.9."""
        import fsof_torch.data.scene as scene
        ious = []
        for index in range(1):
            pair = scene.render_pair("cvc-complex", index, seed=0, size=(128, 416), dtype=torch.float64)
            flow = pair["flow"].unsqueeze(0)
            # Noise-free flow: thresholds that separate the road from the pavement 12 cm above it.
            free = detect_freespace(flow, pair["camera"], threshold=0.05, relative_threshold=0.02)
            ious.append(_iou(free[0], pair["road"]))
            # Restricted to the valid ground truth (the last rows' flow leaves the image).
            valid = pair["valid"].unsqueeze(0)
            free = detect_freespace(flow, pair["camera"], mask=valid, threshold=0.05, relative_threshold=0.02)
            ious.append(_iou(free[0], pair["road"] & pair["valid"]))
        assert min(ious) >= 0.9, ious


    @pytest.mark.parametrize("preset, index", [("carla-straight", 0), ("cvc-complex", 10)])
    def test_no_plane_tilted_between_road_and_pavement(self, preset, index):
        """The seed holds the road and the raised pavements beside it; with roll free, the fit
        settled on a plane tilted between them (roll 0.6°) that agrees with neither whole (IoU
        0.42 and 0.38). The camera's own roll, a second hypothesis, gathers more agreeing pixels
        and is kept."""
        import fsof_torch.data.scene as scene

        pair = scene.render_pair(preset, index, seed=0, size=(128, 416), dtype=torch.float64)
        flow, valid = pair["flow"].unsqueeze(0), pair["valid"].unsqueeze(0)
        det = detect_freespace(flow, pair["camera"], mask=valid, threshold=0.05, relative_threshold=0.02,
                               return_details=True)
        assert _iou(det.freespace[0], pair["road"] & pair["valid"]) >= 0.95
        assert abs(float(det.fit.roll)) < 1e-4 and float(det.fit.z_d) == pytest.approx(pair["odometry"]["z_d"], rel=1e-3)

    def test_roll_fitted_where_the_camera_gives_it_wrong(self):
        """The hypothesis of the camera's attitude does not pin a wrong one: the camera given level
        on a scene whose mounting rolls 1°, the fitted roll wins."""
        import fsof_torch.data.scene as scene

        pair = scene.render_pair("default", 0, seed=0, size=(128, 416), dtype=torch.float64)
        flow, valid, cam = pair["flow"].unsqueeze(0), pair["valid"].unsqueeze(0), pair["camera"]
        level = cam.replace(roll=torch.zeros_like(cam.roll))
        det = detect_freespace(flow, level, mask=valid, threshold=0.05, relative_threshold=0.02, return_details=True)
        assert float(det.fit.roll) == pytest.approx(float(cam.roll), abs=1e-4) and float(cam.roll) > 0.017
        assert _iou(det.freespace[0], pair["road"] & pair["valid"]) >= 0.95

    def test_numpy_numbers_are_taken_and_a_bool_is_not_a_number(self):
        """NumPy integers and floats are numbers (isinstance(x, (int, float)) refused np.int64 and
        np.float32); True is no threshold (it passed as 1.0)."""
        cam, flow, valid, road = self._scene()
        plain = detect_freespace(flow, cam, threshold=0.25, bottom_rows=1, close_kernel=3, refits=1)
        numpy = detect_freespace(flow, cam, threshold=np.float32(0.25), bottom_rows=np.int64(1),
                                 close_kernel=np.int64(3), refits=np.int64(1))
        assert torch.equal(numpy, plain) and _iou(plain, road) > 0.95
        with pytest.raises(TypeError, match="threshold: expected a number, got bool True"):
            detect_freespace(flow, cam, threshold=True)
        with pytest.raises(TypeError, match="refits: expected an int, got float 1.0"):
            detect_freespace(flow, cam, refits=1.0)

    def test_options_for_the_fits_are_checked_before_any_fit(self, monkeypatch):
        """curve_options and fit_options are checked against the receiving function's keywords at
        entry: an unknown name, or one detect_freespace sets itself, is a named TypeError (it was
        Python's "got multiple values" or "unexpected keyword", after the curve fit)."""
        import fsof_torch.estimation.freespace as freespace

        cam, flow, valid, road = self._scene()

        @functools.wraps(fit_vflow_curve)  # (its keywords, which the check reads)
        def no_fit(*args, **kwargs):
            raise AssertionError("fitted before the options were checked")

        monkeypatch.setattr(freespace, "fit_vflow_curve", no_fit)
        for options, match in [
            (dict(curve_options={"model": "velocity"}),
             r"curve_options: options \['model'\] of \w+ are set by the function that forwards"),
            (dict(curve_options={"bogus": 1}), r"curve_options: unknown options \['bogus'\] of fit_vflow_curve"),
            (dict(fit_options={"bogus": 1}), r"fit_options: unknown options \['bogus'\] of fit_road"),
            (dict(fit_options={"model": "plane"}), r"fit_options: options \['model'\] of \w+ are set by the function that forwards"),
            (dict(fit_options={"fixed": ()}), r"fit_options: options \['fixed'\] of \w+ are set by the function that forwards"),
            (dict(fit_options={"fit_roll": False}),
             r"fit_options: options \['fit_roll'\] are detect_freespace's own arguments; pass fit_roll="),
        ]:
            with pytest.raises(TypeError, match=match):
                freespace.detect_freespace(flow, cam, **options)

    def test_a_bad_value_in_the_fits_options_is_named_as_their_key(self):
        """``curve_options={"relative_threshold": -1.0}`` raised "relative_threshold: expected a finite
        number >= 0, got -1.0", which names detect_freespace's own (valid) relative_threshold; a bad
        fit_options value was named as fit_road takes it. Both now name the mapping and the key."""
        cam, flow, valid, road = self._scene()
        with pytest.raises(ValueError, match=r"^curve_options\['relative_threshold'\]: expected a finite number >= 0, "
                                             r"got -1.0$"):
            detect_freespace(flow, cam, relative_threshold=0.03, curve_options={"relative_threshold": -1.0})
        with pytest.raises(ValueError, match=r"^curve_options\['bins'\]: expected an integer >= 2, got 1$"):
            detect_freespace(flow, cam, curve_options={"bins": 1})
        with pytest.raises(ValueError, match=r"^fit_options\['scale'\]: expected a finite number > 0, got -1.0$"):
            detect_freespace(flow, cam, fit_options={"scale": -1.0})
        with pytest.raises(ValueError, match=r"^fit_options\['prior'\]: unknown parameter 'bogus' of model 'paper'$"):
            detect_freespace(flow, cam, fit_options={"prior": {"bogus": (0.0, 1.0)}})
        # the function's own argument keeps its name
        with pytest.raises(ValueError, match=r"^relative_threshold: "):
            detect_freespace(flow, cam, relative_threshold=-1.0, curve_options={"relative_threshold": 0.05})

    def test_fit_options_init_starts_the_fits_on_the_seed(self, monkeypatch):
        """A caller's init starts each hypothesis' fit on the seed (without its roll where the
        camera's attitude is held), not the fits of the rest of the seed; each refit starts from the fit before it (with refits=1, the
        default, init= crashed: "got multiple values for keyword argument 'init'")."""
        import fsof_torch.estimation.freespace as freespace

        cam, flow, valid, road = self._scene()
        starts = []
        fit_displacement = freespace.fit_displacement

        def spy(*args, init=None, **kwargs):
            starts.append((init, kwargs["fit_roll"]))
            return fit_displacement(*args, init=init, **kwargs)

        monkeypatch.setattr(freespace, "fit_displacement", spy)
        init = {"x_d": 0.05, "z_d": 1.0, "yaw": 0.01, "roll": 0.01}
        free = freespace.detect_freespace(flow, cam, fit_options={"init": init})
        assert _iou(free, road) > 0.95
        # (roll fitted: fit, refit; then the camera's attitude held: fit, refit; then both again on
        # the rest of the seed, started afresh: the caller's start is that of the seed's plane)
        assert [roll for _, roll in starts] == [True, True, False, False] * 2
        assert starts[0][0] is init and starts[2][0] == {"x_d": 0.05, "z_d": 1.0, "yaw": 0.01}
        assert starts[4][0] is None and starts[6][0] is None
        assert all(isinstance(start, freespace.RoadFit) for start, _ in (starts[1], starts[3], starts[5], starts[7]))

def test_row_dominant_flow_and_curve_of_a_frame_as_alone():
    """A frame's histogram range is its own: beside a faster frame (larger flows) it gets the
    peaks and the curve it gets alone."""
    cam = _camera()
    g = torch.Generator().manual_seed(0)
    slow, valid = displacement_flow(cam, 0.0, 1.0, 0.0, SIZE)
    fast, _ = displacement_flow(cam, 0.0, 3.0, 0.0, SIZE)
    slow = slow + 0.05 * torch.randn(slow.shape, generator=g, dtype=slow.dtype)
    fast = fast + 0.05 * torch.randn(fast.shape, generator=g, dtype=fast.dtype)
    both, masks = torch.cat([slow, fast]), torch.cat([valid, valid])
    for statistic in ("peak", "median"):
        alone, n_alone = row_dominant_flow(slow, valid, statistic=statistic)
        batch, n_batch = row_dominant_flow(both, masks, statistic=statistic)
        assert torch.equal(batch[:1], alone) and torch.equal(n_batch[:1], n_alone), statistic
    curve, curve_alone = fit_vflow_curve(both, masks), fit_vflow_curve(slow, valid)
    assert float(curve.a[0]) == pytest.approx(float(curve_alone.a[0]), abs=1e-12)
