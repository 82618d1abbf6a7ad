"""What the fits report about themselves: success, covariance, cost and their independence from
batch-mates (fit_road, the solver, fit_vflow_curve, detect_freespace).

Each test pins one promise of a docstring that a review found broken: the values come from the
review's reproductions (the default scene at 93 × 310, noisy flow, masks that leave a fit
undetermined).
"""

from __future__ import annotations

import math
import re

import pytest
import torch

import fsof_torch.estimation.flow_fit as flow_fit
from fsof_torch.data.scene import render_pair
from fsof_torch.estimation.flow_fit import fit_displacement, fit_road
from fsof_torch.estimation.freespace import detect_freespace
from fsof_torch.estimation.solver import Evaluation, ResidualProblem, Solution, solve
from fsof_torch.estimation.vflow import fit_vflow_curve
from fsof_torch.geometry.camera import Camera
from fsof_torch.geometry.road_flow import displacement_flow
from torch import Tensor


@pytest.fixture(scope="module")
def scene():
    d = render_pair("default", 0, size=(93, 310), dtype=torch.float64)
    noise = 0.5 * torch.randn(d["flow"].shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    return {"flow": d["flow"][None], "noisy": (d["flow"] + noise)[None], "valid": d["valid"][None],
            "road": (d["road"] & d["valid"])[None], "camera": d["camera"], "z_d": d["odometry"]["z_d"]}


def _stages(monkeypatch):
    """The solver's stages of the fits that follow, as they return."""
    log, original = [], flow_fit.solve

    def spy(*args, **kw):
        log.append(original(*args, **kw))
        return log[-1]

    monkeypatch.setattr(flow_fit, "solve", spy)
    return log


# -- fit_road: the returned point and what is reported with it ------------------------------------

def test_unconverged_polish_returns_the_robust_stage_with_its_cost_and_covariance_and_no_success(scene, monkeypatch):
    """Ten iterations do not let the polish converge on noisy flow: the robust stage's answer (a
    third off in z_d) is returned, so its cost and covariance are, and success is False."""
    log = _stages(monkeypatch)
    fit = fit_displacement(scene["noisy"], scene["valid"], scene["camera"], max_iter=10)
    robust, polish = log
    assert bool(robust.converged) and not bool(polish.converged)
    assert float(fit.z_d) == float(robust.params[0, 1]) and abs(float(fit.z_d) / scene["z_d"] - 1) > 0.3
    assert float(fit.cost) == float(robust.cost) != float(polish.cost)
    assert torch.equal(fit.covariance, robust.covariance())
    assert fit.success.tolist() == [False]
    # with the budget to converge, the polish's answer and its own figures
    log.clear()
    fit = fit_displacement(scene["noisy"], scene["valid"], scene["camera"])
    assert bool(log[1].converged) and fit.success.tolist() == [True]
    assert float(fit.cost) == float(log[1].cost) and torch.equal(fit.covariance, log[1].covariance())
    assert abs(float(fit.z_d) / scene["z_d"] - 1) < 0.02


def test_min_points_counts_inliers_not_mask_pixels(scene):
    """100 mask pixels of which 75 carry random flow: 25 inliers fall short of min_points=30."""
    flow, road = scene["flow"].clone(), scene["road"]
    g = torch.Generator().manual_seed(0)
    idx = road[0, 0].nonzero()
    pick = idx[torch.randperm(len(idx), generator=g)[:100]]
    mask = torch.zeros_like(road)
    mask[0, 0, pick[:, 0], pick[:, 1]] = True
    bad = pick[25:]
    flow[0, :, bad[:, 0], bad[:, 1]] += 20 * torch.randn(2, len(bad), generator=g, dtype=torch.float64)
    fit = fit_displacement(flow, mask, scene["camera"], min_points=30, min_inlier_fraction=0.2)
    assert int(fit.inliers.sum()) == 25 and fit.success.tolist() == [False]
    assert abs(float(fit.z_d) / scene["z_d"] - 1) < 1e-6  # (the fit itself is right: too few inliers)
    fit = fit_displacement(flow, mask, scene["camera"], min_points=25, min_inlier_fraction=0.2)
    assert fit.success.tolist() == [True]


def test_all_points_fit_of_a_frame_does_not_depend_on_its_batch_mates(scene):
    """max_points=None: the robust stage's stride comes from each frame's own mask, so a frame
    next to a full-image mask gets what it gets alone (to rounding)."""
    alone = fit_displacement(scene["noisy"], scene["road"], scene["camera"], max_points=None)
    batch = fit_displacement(scene["noisy"].expand(2, -1, -1, -1),
                             torch.cat([scene["road"], torch.ones_like(scene["road"])]), scene["camera"],
                             max_points=None)
    for name in ("x_d", "z_d", "yaw", "roll"):
        torch.testing.assert_close(batch.params[name][:1], alone.params[name], rtol=1e-9, atol=1e-15)
    assert batch.iterations[0] == alone.iterations[0]


def test_singular_fits_report_an_infinite_covariance(scene):
    """One pixel (the Cholesky fails and leaves finite values) and one row for the plane (the
    Cholesky passes on rounding): the free parameters' variances are +inf, the rest 0."""
    one = torch.zeros_like(scene["road"])
    one[0, 0, 80, 150] = True
    fit = fit_displacement(scene["flow"], one, scene["camera"])
    unknown = torch.diag(torch.tensor([math.inf] * 4 + [0.0], dtype=torch.float64))  # (the pitch is fixed)
    assert torch.equal(fit.covariance[0], unknown) and fit.success.tolist() == [False]
    row = torch.zeros_like(scene["road"])
    row[0, 0, 80] = True
    fit = fit_road(scene["flow"], row & scene["road"], scene["camera"], model="plane")
    assert fit.covariance[0].diagonal().tolist() == [math.inf] * 8 and fit.success.tolist() == [False]
    fit = fit_road(scene["flow"], scene["road"], scene["camera"], model="plane")
    assert bool(torch.isfinite(fit.covariance).all()) and bool((fit.covariance[0].diagonal() > 0).all())


def test_fit_camera_is_detached_from_the_callers(scene):
    cam = scene["camera"]
    K = cam.K.clone().requires_grad_(True)
    height = torch.tensor([1.65], dtype=torch.float64, requires_grad=True)
    fit = fit_displacement(scene["flow"], scene["road"], Camera(K, height, cam.roll, cam.pitch))
    assert not fit.camera.K.requires_grad and fit.camera.K.grad_fn is None and fit.camera.K._base is not K
    assert not fit.camera.height.requires_grad
    torch.testing.assert_close(fit.camera.K, K.detach())


# -- the solver -----------------------------------------------------------------------------------

def _solution(normal: Tensor) -> Solution:
    """A Solution at 0 with the given normal matrices (B, 2, 2): 10 points of r² = 0.01, weight 1
    (σ² = 0.1 / 8)."""
    B = normal.shape[0]
    f64 = dict(dtype=torch.float64)
    ev = Evaluation(torch.full((B, 10), 0.01, **f64), torch.ones(B, 10, dtype=torch.bool))
    return Solution(torch.zeros(B, 2, **f64), torch.zeros(B, **f64), torch.ones(B, dtype=torch.bool),
                    torch.zeros(B, dtype=torch.long), ev, torch.ones(B, 10, **f64), normal, torch.ones(B, **f64))


def test_covariance_infinite_where_the_normal_matrix_is_not_positive_definite():
    """An indefinite matrix (Cholesky fails, finite leftovers) and a singular one that rounding
    makes pass: +inf variances, not the 0.018 and 1.1e13 of the solve."""
    N = torch.tensor([[[4.0, 0.0], [0.0, 1.0]], [[1.0, 2.0], [2.0, 1.0]], [[1.0, 1.0], [1.0, 1.0 + 1e-15]]],
                     dtype=torch.float64)
    cov = _solution(N).covariance()
    torch.testing.assert_close(cov[0], torch.diag(torch.tensor([0.0125 / 4, 0.0125], dtype=torch.float64)))
    for b in (1, 2):
        assert cov[b].tolist() == [[math.inf, 0.0], [0.0, math.inf]]


def _line(B: int = 2) -> ResidualProblem:
    """y = 2 x + 1 at 20 points per sample, parameters (slope, offset)."""
    x = torch.linspace(-1, 1, 20, dtype=torch.float64).expand(B, 20)
    J = torch.stack([x, torch.ones_like(x)], dim=1).unsqueeze(2)
    use = torch.ones(B, 20, dtype=torch.bool)
    return ResidualProblem(lambda p: ((p[:, :1] * x + p[:, 1:] - (2 * x + 1)).unsqueeze(1), J, use), use.sum(1))


@pytest.mark.parametrize("scale", [0.0, -1.0, math.nan, math.inf])
def test_solve_rejects_a_float_scale_that_is_not_finite_and_positive(scale):
    with pytest.raises(ValueError, match=rf"scale: expected a finite number > 0, got {scale!r}"):
        solve(_line(), torch.zeros(2, 2, dtype=torch.float64), scale=scale)


def test_solve_checks_a_tensor_scale_and_a_computed_ones_shape():
    """A given tensor scale is checked for its values; a scale function's result only for its
    shape (it is called once, and its values are not read back to the host)."""
    start = torch.zeros(2, 2, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"scale: expected finite values > 0, got \[0.0\]"):
        solve(_line(), start, scale=torch.tensor([1.0, 0.0]))
    with pytest.raises(ValueError, match=r"scale: expected a float or a \(2,\) tensor \(B of params\), got shape \(3,"):
        solve(_line(), start, scale=torch.ones(3))
    calls = []

    def spread(ev):
        calls.append(ev)
        return torch.ones(3, dtype=torch.float64)

    with pytest.raises(ValueError, match=r"scale: expected the function to return a float or a \(2,\) tensor"):
        solve(_line(), start, scale=spread)
    assert len(calls) == 1
    sol = solve(_line(), start, scale=torch.tensor([1.0, 2.0]), kernel="l2")
    torch.testing.assert_close(sol.params, torch.tensor([[2.0, 1.0]] * 2, dtype=torch.float64))


@pytest.mark.parametrize("params, got", [(torch.zeros(2, dtype=torch.float64), "(2,)"),
                                          (torch.zeros(1, 2, 2, dtype=torch.float64), "(1, 2, 2)")])
def test_solve_requires_params_of_shape_b_p(params, got):
    with pytest.raises(ValueError, match=rf"params: expected shape \(B, P\), got {re.escape(got)}"):
        solve(_line(), params)
    with pytest.raises(TypeError, match=r"params: expected a floating-point tensor, got dtype torch.int64"):
        solve(_line(), torch.zeros(2, 2, dtype=torch.long))


def test_iterations_count_rejected_steps_too():
    """One residual atan(p - 0.5) from p = 2.5: Gauss–Newton overshoots, the step is rejected and,
    moving the residual by less than twice the resolution, ends the sample where it started. That
    iteration counts, though the sample never moved (the docstring says so)."""
    def residual(p):
        d = p - 0.5
        return torch.atan(d).reshape(1, 1, 1), (1 / (1 + d * d)).reshape(1, 1, 1, 1), torch.ones(1, 1, dtype=torch.bool)

    start = torch.tensor([[2.5]], dtype=torch.float64)
    sol = solve(ResidualProblem(residual, torch.ones(1)), start, kernel="l2", max_iter=20, resolution=1.5)
    assert torch.equal(sol.params, start) and sol.iterations.tolist() == [1] and bool(sol.converged)
    doc = " ".join(Solution.__doc__.split())
    assert "iterations run while the sample was active (not yet converged): accepted steps and rejected" in doc


# -- fit_vflow_curve ------------------------------------------------------------------------------

_VCAM = Camera(torch.tensor([[300., 0, 80], [0, 300, 20], [0, 0, 1]], dtype=torch.float64), 1.5)


def _noisy_curve_frame(z_d: float, seed: int):
    flow, valid = displacement_flow(_VCAM, 0.0, z_d, 0.0, (64, 160))
    flow = flow + 0.3 * torch.randn(flow.shape, generator=torch.Generator().manual_seed(seed), dtype=flow.dtype)
    flow[:, 1, 40:50, :100] = 0.8  # an obstacle over ten rows
    return flow, valid


def test_vflow_curve_of_a_frame_does_not_depend_on_its_batch_mates():
    """Each frame draws its RANSAC samples from the seed alone: in a batch, in either order, it
    gets bit for bit what it gets alone, which is what a batch of one gave before (pinned)."""
    (fa, va), (fb, vb) = _noisy_curve_frame(1.0, 1), _noisy_curve_frame(1.3, 2)
    alone = [fit_vflow_curve(f, v, hypotheses=16) for f, v in ((fa, va), (fb, vb))]
    pinned = [(float.fromhex("0x1.510b33ed1fb40p-9"), float.fromhex("0x1.7046560ada585p+4")),
              (float.fromhex("0x1.9502c407dedb0p-9"), float.fromhex("0x1.56110c8ea4d90p+4"))]
    for c, (a, v0) in zip(alone, pinned):
        torch.testing.assert_close(c.a, torch.tensor([a], dtype=torch.float64), rtol=1e-12, atol=0)
        torch.testing.assert_close(c.v0, torch.tensor([v0], dtype=torch.float64), rtol=1e-12, atol=0)
    ab = fit_vflow_curve(torch.cat([fa, fb]), torch.cat([va, vb]), hypotheses=16)
    ba = fit_vflow_curve(torch.cat([fb, fa]), torch.cat([vb, va]), hypotheses=16)
    for order, batch in (((0, 1), ab), ((1, 0), ba)):
        for i, k in enumerate(order):
            assert torch.equal(batch.a[i:i + 1], alone[k].a) and torch.equal(batch.v0[i:i + 1], alone[k].v0)
            assert torch.equal(batch.fitted[i:i + 1], alone[k].fitted)


def test_vflow_curve_without_curvature_is_no_success():
    """Zero flow fits a = 0 (every row an inlier of the flat curve) and leaves v0 arbitrary;
    flow within the row threshold of 0 likewise. A moving frame still succeeds."""
    flow, valid = displacement_flow(_VCAM, 0.0, 1.0, 0.0, (64, 160))
    zero = fit_vflow_curve(torch.zeros_like(flow), valid)
    assert zero.success.tolist() == [False] and zero.a.tolist() == [0.0] and zero.v0.tolist() == [0.0]
    assert not bool(zero.fitted_valid.any())
    tiny = fit_vflow_curve(0.1 * torch.randn(flow.shape, generator=torch.Generator().manual_seed(0),
                                             dtype=flow.dtype), valid)
    assert tiny.success.tolist() == [False]
    moving = fit_vflow_curve(flow, valid)
    assert moving.success.tolist() == [True]
    torch.testing.assert_close(moving.scale(_VCAM), torch.tensor([1.0], dtype=torch.float64))


# -- detect_freespace -----------------------------------------------------------------------------

def test_freespace_never_fills_masked_out_or_nan_pixels(scene):
    """A hole in the mask and a patch of NaN flow inside the road: hole filling used to claim
    them; the pixels around them stay freespace."""
    flow, valid = scene["flow"], scene["valid"]
    mask = valid.clone()
    mask[:, :, 75:80, 140:150] = False
    free = detect_freespace(flow, scene["camera"], mask=mask, threshold=0.05, relative_threshold=0.02)
    assert int((free & ~mask).sum()) == 0
    assert bool(free[0, 0, 74, 140:150].all()) and bool(free[0, 0, 80, 140:150].all())
    nan = flow.clone()
    nan[:, :, 70:72, 100:120] = math.nan
    free = detect_freespace(nan, scene["camera"], mask=valid, threshold=0.05, relative_threshold=0.02)
    assert int((free & torch.isnan(nan[:, :1])).sum()) == 0
    assert bool(free[0, 0, 69, 100:120].all()) and bool(free[0, 0, 72, 100:120].all())


def test_the_covariance_keeps_the_priors_own_weight():
    """A parameter the data leave to its prior is reported as known to the prior's σ. A vehicle at
    rest shows nothing of the camera's attitude in its flow: its pitch's standard deviation is the
    prior's 1° (it was about 1° × σ / scale, the prior's share scaled with the residuals' variance:
    0.02° here); at 1 mm a frame the flow already halves it, at 1 m a frame it fixes it far
    better than the prior."""
    cam = Camera(torch.tensor([[700.0, 0, 320], [0, 700, 90], [0, 0, 1]], dtype=torch.float64), 1.65)
    from fsof_torch.geometry.road_flow import road_flow
    deg = math.pi / 180
    prior = {"roll": (0.0, deg), "pitch": (0.0, deg)}
    sd = {}
    for z_d in (0.0, 0.001, 1.0):
        flow, valid = road_flow(cam, {"z_d": z_d}, (192, 640), model="plane")
        noise = 0.05 * torch.randn(flow.shape, generator=torch.Generator().manual_seed(0), dtype=flow.dtype)
        fit = fit_road(flow + noise, valid, cam, model="plane", fixed=(), prior=prior)
        i = list(fit.params).index("pitch")
        sd[z_d] = float(fit.covariance[0, i, i].sqrt()) / deg
    assert 0.99 < sd[0.0] <= 1.0 and 0.3 < sd[0.001] < 0.7 and sd[1.0] < 0.01, sd
