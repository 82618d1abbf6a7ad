"""Tests of fsof_torch.estimation.solver (the one robust solver) and the robust kernels.

References written here: closed-form weighted least squares, the Gaussian posterior of a linear
model with a Gaussian prior, SciPy's robust least squares.
"""

from __future__ import annotations

import importlib
import math

import numpy as np
import pytest
import torch

from fsof_torch.estimation.robust import ROBUST_KERNELS, far_outlier_cost, robust_cost, robust_weight
from fsof_torch.estimation.sampling import sample_mask
from fsof_torch.estimation.solver import ResidualProblem, solve


def line_problem(B: int = 2, N: int = 200, noise: float = 0.01, outliers: float = 0.0, seed: int = 0):
    """y = a x + b per sample: a linear problem with known truth (and optional gross outliers)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.linspace(-1, 1, N, dtype=torch.float64).expand(B, N)
    truth = torch.tensor([[2.0, -1.0], [0.5, 3.0], [-1.0, 0.2]], dtype=torch.float64)[:B]
    y = truth[:, :1] * x + truth[:, 1:] + noise * torch.randn(B, N, generator=g, dtype=torch.float64)
    n_out = int(outliers * N)
    if n_out:
        y[:, :n_out] += 20.0 + 5.0 * torch.rand(B, n_out, generator=g, dtype=torch.float64)
    J = torch.stack([x, torch.ones_like(x)], dim=1).unsqueeze(2)  # (B, 2, 1, N)
    use = torch.ones(B, N, dtype=torch.bool)

    def residual(p):
        return ((p[:, :1] * x + p[:, 1:]) - y).unsqueeze(1), J, use

    return ResidualProblem(residual, use.sum(1)), truth, x, y


def test_linear_least_squares_exact():
    problem, truth, x, y = line_problem(noise=0.0)
    sol = solve(problem, torch.zeros(2, 2, dtype=torch.float64), kernel="l2", max_iter=10)
    torch.testing.assert_close(sol.params, truth, rtol=0, atol=1e-10)
    assert bool(sol.converged.all())


def test_redescending_kernels_drop_gross_outliers_and_l2_does_not():
    problem, truth, _, _ = line_problem(noise=0.01, outliers=0.3)
    start = torch.zeros(2, 2, dtype=torch.float64)
    l2 = solve(problem, start, kernel="l2", max_iter=10)
    assert (l2.params - truth).abs().max() > 1.0
    for kernel in ("cauchy", "tukey"):
        sol = solve(problem, start, kernel=kernel, scale=0.05, anneal=True, max_iter=60)
        assert (sol.params - truth).abs().max() < 0.05, kernel
        assert bool(sol.converged.all())


def test_gaussian_prior_gives_the_posterior_mean():
    """Linear model, Gaussian noise and prior: the MAP estimate is the posterior mean
    (JᵀJ + Λ)⁻¹ (Jᵀy + Λμ), written out here."""
    problem, truth, x, y = line_problem(B=1, N=20, noise=0.1)
    mu = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    lam = torch.tensor([[5.0, 0.5]], dtype=torch.float64)
    sol = solve(problem, torch.zeros(1, 2, dtype=torch.float64), kernel="l2", prior_mean=mu,
                prior_precision=lam, max_iter=10)
    J = torch.stack([x[0], torch.ones_like(x[0])], dim=1)
    ref = torch.linalg.solve(J.T @ J + torch.diag(lam[0]), J.T @ y[0] + lam[0] * mu[0])
    torch.testing.assert_close(sol.params[0], ref, rtol=0, atol=1e-7)
    # from the data's own least-squares answer the prior's pull raises the data's cost: only a cost
    # that counts the prior accepts that step; and the reported cost is E / n with the prior's term
    ls = torch.linalg.solve(J.T @ J, J.T @ y[0])
    sol = solve(problem, ls.unsqueeze(0), kernel="l2", prior_mean=mu, prior_precision=lam, max_iter=10)
    torch.testing.assert_close(sol.params[0], ref, rtol=0, atol=1e-7)
    energy = (J @ ref - y[0]).square().sum() + (lam[0] * (ref - mu[0]).square()).sum()
    torch.testing.assert_close(sol.cost[0], energy / x.shape[1], rtol=1e-9, atol=0)
    # a precision alone is a prior at 0: (JᵀJ + Λ)⁻¹ Jᵀy
    sol = solve(problem, torch.zeros(1, 2, dtype=torch.float64), kernel="l2", prior_precision=lam, max_iter=10)
    torch.testing.assert_close(sol.params[0], torch.linalg.solve(J.T @ J + torch.diag(lam[0]), J.T @ y[0]), rtol=0,
                               atol=1e-7)


def test_bounds_fixed_parameters_and_per_sample_convergence():
    problem, truth, _, _ = line_problem(B=3, noise=0.0)
    start = torch.zeros(3, 2, dtype=torch.float64)
    upper = torch.tensor([1.0, float("inf")], dtype=torch.float64)
    sol = solve(problem, start, kernel="l2", upper=upper, max_iter=20)
    assert bool((sol.params[:, 0] <= 1.0).all())
    torch.testing.assert_close(sol.params[2], truth[2])  # inside the bounds: unaffected
    free = torch.tensor([True, False])
    sol = solve(problem, start, kernel="l2", free=free, max_iter=20)
    assert torch.equal(sol.params[:, 1], start[:, 1])
    # a sample that starts at its answer converges at once, the others keep their own count
    start = truth.clone()
    start[1] += 1.0
    sol = solve(problem, start, kernel="l2", max_iter=20)
    assert int(sol.iterations[0]) <= 1 < int(sol.iterations[1])


def test_no_host_read_without_checks_and_fixed_budget():
    problem, truth, _, _ = line_problem(noise=0.0)
    sol = solve(problem, torch.zeros(2, 2, dtype=torch.float64), kernel="l2", max_iter=7, check_every=None)
    torch.testing.assert_close(sol.params, truth)
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        solve(problem, torch.zeros(2, 2, dtype=torch.float64), kernel="cauchy", max_iter=7, check_every=None)
    names = [e.key for e in prof.key_averages()]
    assert "aten::_local_scalar_dense" not in names and "aten::nonzero" not in names


def counted_problem():
    """A line problem with outliers whose evaluations are counted (``calls``), its start, and its
    solution with the fixed budget of 40 iterations (no early stop)."""
    base, _, _, _ = line_problem(noise=0.01, outliers=0.1)
    calls = []

    def counted(p):
        calls.append(1)
        return base.fn(p)

    problem = ResidualProblem(counted, base.count)
    start = torch.zeros(2, 2, dtype=torch.float64)
    return problem, start, calls, solve(problem, start, kernel="cauchy", max_iter=40, check_every=None)


@pytest.mark.parametrize("first", [1, 2, 3, 5])
def test_early_stop_checks_after_first_then_gaps_1_1_2_4(first):
    """An int ``check_every`` k checks after k iterations, then after 1, 1, 2, 4, ... more: the loop
    ends at the first check at or after the iteration where every sample converged, and the
    result is the fixed budget's."""
    problem, start, calls, full = counted_problem()
    converged_at = int(full.iterations.max())  # converged samples stop counting iterations
    assert bool(full.converged.all()) and converged_at < 20
    schedule, gap = [first], 1  # the schedule written out: k, k+1, k+2, k+4, k+8, ...
    while schedule[-1] < 40:
        schedule.append(schedule[-1] + gap)
        gap = gap * 2 if len(schedule) > 2 else gap
    stop = next(k for k in schedule if k >= converged_at)
    calls.clear()
    sol = solve(problem, start, kernel="cauchy", max_iter=40, check_every=first)
    assert len(calls) == 1 + stop  # the start, then one candidate per iteration
    assert torch.equal(sol.params, full.params) and torch.equal(sol.iterations, full.iterations)


@pytest.mark.parametrize("schedule", [range(3, 40), range(3, 40, 4), range(39, 2, -1), [9, 3, 3, 21], (5,)])
def test_early_stop_checks_after_the_listed_iterations(schedule):
    """A sequence ``check_every`` (a range included, rising or not) checks after the iterations it
    lists: the loop ends at the first of them at or after the iteration where every sample
    converged."""
    problem, start, calls, full = counted_problem()
    converged_at = int(full.iterations.max())
    stop = min((k for k in schedule if k >= converged_at), default=40)
    calls.clear()
    sol = solve(problem, start, kernel="cauchy", max_iter=40, check_every=schedule)
    assert len(calls) == 1 + stop
    assert torch.equal(sol.params, full.params) and torch.equal(sol.iterations, full.iterations)


@pytest.mark.parametrize("shape, ok", [((), True), ((1,), True), ((2,), True), ((1, 1), True), ((1, 2), True),
                                       ((3, 1), True), ((3, 2), True), ((3,), False), ((2, 2), False),
                                       ((1, 3), False), ((1, 1, 2), False)])
def test_per_parameter_arguments_broadcast_to_b_p(shape, ok):
    """``lower``, ``upper``, ``prior_mean``, ``prior_precision``: any shape that broadcasts to
    (B, P) (here (3, 2)), no other."""
    problem, _, _, _ = line_problem(B=3, N=50)
    start = torch.zeros(3, 2, dtype=torch.float64)
    for name in ("lower", "prior_mean"):
        options = {name: torch.full(shape, -1.0, dtype=torch.float64)}
        if name == "prior_mean":
            options["prior_precision"] = 1.0
        if ok:
            assert solve(problem, start, kernel="l2", max_iter=2, **options).params.shape == (3, 2)
        else:
            with pytest.raises(ValueError, match=rf"{name}: expected a number or shape \(2,\) or \(3, 2\)"):
                solve(problem, start, kernel="l2", max_iter=2, **options)


def test_predicted_step_ends_a_stage_without_the_step_that_would_not_matter():
    """``predict``: after an accepted step the next one is predicted from the normal equations
    there (δᵀ A δ, what it would move the weighted squared residuals by); below ``resolution``²
    of their weighted sum the sample has converged."""
    # least squares on a linear problem: the first step lands on the answer (short of it by the
    # initial damping, 1e-4 of the way), and the step after it is predicted not to matter: one
    # iteration instead of two, and the same answer to that damping
    problem, truth, x, y = line_problem(noise=0.05)
    start = torch.zeros(2, 2, dtype=torch.float64)
    plain = solve(problem, start, kernel="l2", max_iter=10, resolution=0.01)
    predicted = solve(problem, start, kernel="l2", max_iter=10, resolution=0.01, predict=True)
    assert plain.iterations.tolist() == [2, 2] and predicted.iterations.tolist() == [1, 1]
    torch.testing.assert_close(predicted.params, plain.params, rtol=2e-4, atol=0)
    # a robust, annealed fit: fewer evaluations, and the line it ends on differs from the
    # unpredicted one by well under the resolution's share of the noise
    problem, truth, x, y = line_problem(noise=0.05, outliers=0.2)
    plain = solve(problem, start, kernel="cauchy", scale=0.1, anneal=True, max_iter=40, resolution=0.05)
    predicted = solve(problem, start, kernel="cauchy", scale=0.1, anneal=True, max_iter=40, resolution=0.05,
                      predict=True)
    assert bool(predicted.converged.all()) and bool((predicted.iterations < plain.iterations).all())
    d = predicted.params - plain.params
    moved = (d[:, :1] * x + d[:, 1:]).square().mean(1).sqrt()
    assert bool((moved < 2 * 0.05 * 0.05).all()), moved
    # a zero-residual problem is unaffected: the step predicted there removes the whole residual
    problem, truth, _, _ = line_problem(noise=0.0)
    sol = solve(problem, start, kernel="cauchy", scale=0.1, anneal=True, max_iter=60, resolution=0.05, predict=True)
    torch.testing.assert_close(sol.params, truth, rtol=0, atol=1e-9)


def arctan_problem(offset: float = 0.5):
    """One residual arctan(p - offset): Gauss–Newton from 2 away overshoots (to about -3.5 away,
    a larger residual); every evaluated start is recorded."""
    seen = []

    def residual(p):
        seen.append(p.clone())
        d = p - offset
        return torch.atan(d).reshape(1, 1, 1), (1.0 / (1.0 + d * d)).reshape(1, 1, 1, 1), torch.ones(1, 1, dtype=torch.bool)

    return ResidualProblem(residual, torch.ones(1)), seen


def test_rejected_step_is_retried_at_half_its_length():
    """The cost a rejected step raised is least within its first half: the retry is that half (more
    damping alone, ×8 from 1e-4, would take four more rejections to shorten the step enough)."""
    problem, seen = arctan_problem()
    start = torch.tensor([[2.5]], dtype=torch.float64)
    sol = solve(problem, start, kernel="l2", max_iter=20, tol=1e-12)
    first, retry = seen[1] - start, seen[2] - start
    assert float(torch.atan(seen[1] - 0.5).abs()) > float(torch.atan(start - 0.5).abs())  # rejected
    torch.testing.assert_close(retry, 0.5 * first, rtol=1e-12, atol=0)
    assert float(torch.atan(seen[2] - 0.5).abs()) < float(torch.atan(start - 0.5).abs())  # accepted
    torch.testing.assert_close(sol.params, torch.tensor([[0.5]], dtype=torch.float64), rtol=0, atol=1e-9)
    assert bool(sol.converged.all())


@pytest.mark.parametrize("resolution, ends", [(1.5, True), (0.9, False)])
def test_rejected_step_within_twice_the_resolution_ends_the_sample(resolution, ends):
    """A rejected step that moves the residuals by at most twice ``resolution`` of their RMS
    (squared: four times the bar) ends the sample where it is: the best point along it, in its
    first half, moves them by at most the resolution. Here the overshoot moves the one residual
    from atan(2) to about -atan(3.54): 2.4, against its RMS of 1.1."""
    problem, seen = arctan_problem()
    start = torch.tensor([[2.5]], dtype=torch.float64)
    sol = solve(problem, start, kernel="l2", max_iter=20, resolution=resolution)
    assert bool(sol.converged.all())
    if ends:  # after the one (rejected) iteration, where it started
        assert sol.iterations.tolist() == [1] and torch.equal(sol.params, start)
    else:  # the retry at half the step is accepted, and the fit goes on
        assert int(sol.iterations) > 2 and abs(float(sol.params) - 0.5) < 0.1


def test_covariance_of_linear_least_squares():
    problem, truth, x, y = line_problem(B=1, N=400, noise=0.05, seed=3)
    sol = solve(problem, torch.zeros(1, 2, dtype=torch.float64), kernel="l2", max_iter=10)
    J = torch.stack([x[0], torch.ones_like(x[0])], dim=1)
    r = J @ sol.params[0] - y[0]
    sigma2 = (r @ r) / (400 - 2)
    torch.testing.assert_close(sol.covariance()[0], sigma2 * torch.linalg.inv(J.T @ J), rtol=1e-8, atol=1e-15)


def test_covariance_counts_the_free_parameters_only():
    """A fixed parameter takes no degree of freedom: with the offset held, the slope's variance is
    rᵀr / (N - 1) (Jᵀ J)⁻¹ of the one-parameter fit, written out here (it was N - 2)."""
    problem, truth, x, y = line_problem(B=1, N=5, noise=0.3, seed=2)
    start = torch.tensor([[0.0, -1.0]], dtype=torch.float64)  # the offset held at its truth, -1
    sol = solve(problem, start, free=torch.tensor([True, False]), kernel="l2", max_iter=20)
    r = sol.params[0, 0] * x[0] - 1.0 - y[0]
    J = x[0].unsqueeze(1)
    ref = (r @ r) / (5 - 1) * torch.linalg.inv(J.T @ J)
    torch.testing.assert_close(sol.covariance()[0, :1, :1], ref, rtol=1e-10, atol=0)
    # every parameter free: N - 2, as before
    both = solve(problem, start, free=torch.tensor([[True, True]]), kernel="l2", max_iter=20)
    torch.testing.assert_close(both.covariance(), solve(problem, start, kernel="l2", max_iter=20).covariance())


def test_covariance_of_an_exact_fit_is_unknown():
    """As many points as free parameters: the fit is exact and says nothing of the noise, so the
    variances are +inf (was: about 1e-25, 'known exactly'); one point more gives a finite one,
    and a held parameter frees a degree of freedom."""
    for N, free, finite in ((2, None, False), (3, None, True), (2, torch.tensor([True, False]), True)):
        problem, truth, x, y = line_problem(B=1, N=N, noise=0.3, seed=4)
        start = torch.tensor([[0.0, float(truth[0, 1])]], dtype=torch.float64)
        cov = solve(problem, start, free=free, kernel="l2", max_iter=20).covariance()[0]
        assert bool(torch.isfinite(cov).all()) == finite and not bool(cov.isnan().any()), (N, free)
        if not finite:
            assert bool((cov.diagonal() == math.inf).all())


def test_covariance_of_fixed_and_of_singular_problems():
    """A fixed parameter has 0 rows and columns; a sample whose problem is singular (every point
    at one x: the slope unknowable) has +inf variances on its free parameters, never NaN; the
    other sample keeps its covariance."""
    problem, truth, x, y = line_problem(B=2, N=50, noise=0.05, seed=1)
    free = torch.tensor([True, False])  # the slope estimated, the offset held
    sol = solve(problem, truth.clone(), kernel="l2", max_iter=10, free=free)
    cov = sol.covariance()
    assert bool((cov[:, 1, :] == 0).all()) and bool((cov[:, :, 1] == 0).all()) and bool((cov[:, 0, 0] > 0).all())
    x0 = torch.zeros(2, 50, dtype=torch.float64)
    x0[0] = x[0]
    J = torch.stack([x0, torch.ones_like(x0)], dim=1).unsqueeze(2)
    use = torch.ones(2, 50, dtype=torch.bool)

    def residual(p):  # sample 1's x are all 0: its slope is not determined
        return ((p[:, :1] * x0 + p[:, 1:]) - y).unsqueeze(1), J, use

    sol = solve(ResidualProblem(residual, use.sum(1)), torch.zeros(2, 2, dtype=torch.float64), kernel="l2",
                max_iter=10)
    cov = sol.covariance()
    assert bool(torch.isfinite(cov[0]).all())
    assert cov[1].diagonal().tolist() == [float("inf"), float("inf")] and float(cov[1, 0, 1]) == 0.0


def test_covariance_with_the_priors_noise_is_the_posterior():
    """With ``prior_noise`` ν the prior λ = ν² / σ_p² keeps its own weight: the covariance is
    (JᵀJ / σ² + 1 / σ_p²)⁻¹, written out here, whatever the residuals' variance σ² (without it,
    σ² (JᵀJ + λ)⁻¹: the prior's share scaled by σ² / ν²). A parameter the data barely see (the
    slope of points all near x = 0) is then known to about σ_p, not to σ_p σ / ν."""
    for spread, noise in ((1.0, 0.05), (1e-3, 0.05), (1.0, 0.5)):
        problem, truth, x, y = line_problem(B=1, N=40, noise=noise, seed=5)
        xs = spread * x
        y = y + truth[:, :1] * (xs - x)  # (the line y = 2 xs - 1, plus the noise)
        J = torch.stack([xs, torch.ones_like(xs)], dim=1).unsqueeze(2)
        use = torch.ones(1, 40, dtype=torch.bool)

        def residual(p, xs=xs, J=J, y=y, use=use):
            return ((p[:, :1] * xs + p[:, 1:]) - y).unsqueeze(1), J, use

        nu, sigma_p = 0.3, torch.tensor([[2.0, 5.0]], dtype=torch.float64)
        lam = nu ** 2 / sigma_p.square()
        sol = solve(ResidualProblem(residual, use.sum(1)), torch.zeros(1, 2, dtype=torch.float64), kernel="l2",
                    prior_mean=torch.zeros(1, 2, dtype=torch.float64), prior_precision=lam, max_iter=20)
        Jm = torch.stack([xs[0], torch.ones_like(xs[0])], dim=1)
        r = Jm @ sol.params[0] - y[0]
        sigma2 = (r @ r) / (40 - 2)
        posterior = torch.linalg.inv(Jm.T @ Jm / sigma2 + torch.diag(1 / sigma_p[0].square()))
        torch.testing.assert_close(sol.covariance(nu)[0], posterior, rtol=1e-8, atol=1e-15)
        torch.testing.assert_close(sol.covariance(torch.tensor([nu], dtype=torch.float64))[0], posterior,
                                   rtol=1e-8, atol=1e-15)
        torch.testing.assert_close(sol.covariance()[0], sigma2 * torch.linalg.inv(Jm.T @ Jm + torch.diag(lam[0])),
                                   rtol=1e-8, atol=1e-15)
        if spread < 1:  # (the slope left to the prior: its standard deviation about σ_p = 2)
            assert float(sol.covariance(nu)[0, 0, 0].sqrt()) == pytest.approx(2.0, rel=0.05)
            assert float(sol.covariance()[0, 0, 0].sqrt()) < 0.5  # (σ_p σ / ν = 2 · 0.05 / 0.3)
    # a held parameter keeps 0 rows and columns; no prior: ``prior_noise`` changes nothing
    sol = solve(problem, truth.clone(), kernel="l2", max_iter=10, free=torch.tensor([True, False]),
                prior_mean=torch.zeros(1, 2, dtype=torch.float64), prior_precision=lam)
    cov = sol.covariance(nu)
    assert bool((cov[:, 1, :] == 0).all()) and bool((cov[:, :, 1] == 0).all()) and float(cov[0, 0, 0]) > 0
    plain = solve(problem, truth.clone(), kernel="l2", max_iter=10)
    torch.testing.assert_close(plain.covariance(nu), plain.covariance(), rtol=0, atol=0)


def test_robust_kernels_match_scipy_losses():
    scipy_ls = importlib.import_module("scipy.optimize._lsq.least_squares")  # the module, not the function
    r2 = torch.linspace(0, 9, 50, dtype=torch.float64)
    c = 1.5
    for kind, name in (("soft_l1", "soft_l1"), ("cauchy", "cauchy"), ("huber", "huber")):
        rho = np.empty((3, 50))
        getattr(scipy_ls, name)((r2 / c**2).numpy(), rho, cost_only=False)
        torch.testing.assert_close(robust_cost(r2, c, kind), c**2 * torch.from_numpy(rho[0]))
        torch.testing.assert_close(robust_weight(r2, c, kind), torch.from_numpy(rho[1]))
    with pytest.raises(ValueError, match="kind: expected one of"):  # (the kernels' argument)
        robust_weight(r2, c, "bisquare")
    assert set(ROBUST_KERNELS) == {"cauchy", "huber", "soft_l1", "tukey", "l2"}


@pytest.mark.parametrize("kind", ROBUST_KERNELS)
def test_robust_weight_is_the_derivative_of_the_cost(kind):
    """w = dρ/d(r²), checked by central differences of ``robust_cost`` for every kernel (SciPy has
    no Tukey kernel: its cost is also checked against the module's formula, written here)."""
    c = 1.5
    r2 = torch.tensor([0.3, 1.0, 1.9, 3.1, 5.0, 9.0], dtype=torch.float64)  # (off huber's and tukey's cut, c² = 2.25)
    h = 1e-6
    numeric = (robust_cost(r2 + h, c, kind) - robust_cost(r2 - h, c, kind)) / (2 * h)
    torch.testing.assert_close(robust_weight(r2, c, kind), numeric, rtol=1e-6, atol=1e-9)
    if kind == "tukey":
        ref = torch.where(r2 < c * c, c * c / 3 * (1 - (1 - r2 / c**2) ** 3), torch.full_like(r2, c * c / 3))
        torch.testing.assert_close(robust_cost(r2, c, kind), ref)


def test_sample_mask_even_stride_and_padding():
    mask = torch.zeros(2, 1, 10, 12, dtype=torch.bool)
    mask[0, 0, 5:] = True          # 60 pixels
    mask[1, 0, 2, 3:6] = True      # 3 pixels
    pts = sample_mask(mask, 16)
    assert pts.pix.shape == (2, 16) and pts.count.tolist() == [60, 3]
    ref = torch.arange(60)[(torch.arange(16) * 60) // 16] + 60  # the floor(j n / N)-th mask pixel
    assert torch.equal(pts.pix[0], ref)
    assert pts.sel[1].tolist() == [True] * 3 + [False] * 13 and pts.pix[1, :3].tolist() == [27, 28, 29]
    assert pts.per_frame(torch.ones(63, dtype=torch.float64)).tolist() == [60.0, 3.0]


def test_mask_points_per_pixel_spreads_each_frames_value():
    mask = torch.zeros(3, 1, 4, 5, dtype=torch.bool)
    mask[0, 0, 1, :2] = True       # 2 pixels
    mask[2, 0, 3] = True           # 5 pixels; frame 1 has none
    pts = sample_mask(mask, 4)
    v = torch.tensor([1.5, -2.0, 7.0], dtype=torch.float64)
    frame = torch.div(pts.every, 20, rounding_mode="floor")
    assert torch.equal(pts.per_pixel(v), v[frame])
    assert pts.per_pixel(v).tolist() == [1.5] * 2 + [7.0] * 5
    one = sample_mask(mask[2:], 4)
    assert torch.equal(one.per_pixel(v[2:]), torch.full((5,), 7.0, dtype=torch.float64))


def test_resample_mask_is_sample_mask_of_the_same_mask():
    from fsof_torch.estimation.sampling import resample_mask

    mask = torch.rand(2, 1, 9, 11, generator=torch.Generator().manual_seed(3)) > 0.4
    pts = sample_mask(mask, 7)
    for n in (1, 5, 30, None):
        a, b = resample_mask(pts, (9, 11), n), sample_mask(mask, n)
        for name in ("pix", "sel", "count", "every", "bounds"):
            assert torch.equal(getattr(a, name), getattr(b, name)), (n, name)



def test_mask_pixels_matches_torch_nonzero():
    """The CPU path (NumPy's flatnonzero) finds the same flat indices, in the same order and dtype,
    as torch's nonzero: batches, an expanded (non-contiguous) mask, an empty and a full one."""
    from fsof_torch.estimation.sampling import mask_pixels

    g = torch.Generator().manual_seed(5)
    masks = [torch.rand(3, 1, 17, 23, generator=g) > 0.6, (torch.rand(1, 1, 8, 9, generator=g) > 0.5).expand(4, 1, 8, 9),
             torch.zeros(2, 1, 5, 6, dtype=torch.bool), torch.ones(1, 1, 4, 4, dtype=torch.bool),
             (torch.rand(1, 1, 9, 12, generator=g) > 0.5)[..., ::2, 1::3]]
    for mask in masks:
        got, want = mask_pixels(mask), mask.reshape(-1).nonzero().squeeze(1)
        assert got.dtype == torch.int64 and torch.equal(got, want), tuple(mask.shape)


# -- bounds: the constrained minimum ----------------------------------------------------------------

def exponential_problem():
    """a exp(-k t) + c0 with a tenth of the points gross outliers (Cauchy's territory); the data's
    c0 (0.3) lies below the bound 0.35 used here, so that bound is active at the answer."""
    g = torch.Generator().manual_seed(1)
    t = torch.linspace(0, 3, 120, dtype=torch.float64)
    y = 2.5 * torch.exp(-1.3 * t) + 0.3 + 0.02 * torch.randn(120, generator=g, dtype=torch.float64)
    y[::10] += 3.0

    def residual(p):
        a, k, c0 = p[:, 0:1], p[:, 1:2], p[:, 2:3]
        e = torch.exp(-k * t)
        J = torch.stack([e, -a * t * e, torch.ones_like(e)], 1).unsqueeze(2)
        return (a * e + c0 - y).unsqueeze(1), J, torch.ones(1, 120, dtype=torch.bool)

    return ResidualProblem(residual, torch.tensor([120])), t, y


@pytest.mark.parametrize("kernel, loss", [("cauchy", "cauchy"), ("soft_l1", "soft_l1"), ("huber", "huber")])
def test_an_active_bound_holds_its_parameter_and_the_others_reach_the_constrained_minimum(kernel, loss):
    """With c0's lower bound active, the step of the other parameters is the constrained one (c0
    held at its bound), not the unconstrained step cut short by the clamp: the fit reaches SciPy's
    bounded robust answer (a trust-region reflective method, independent of this solver), where it
    once stopped 0.1 short of it and called that converged."""
    from scipy.optimize import least_squares

    problem, t, y = exponential_problem()
    lower = torch.tensor([0.0, 0.0, 0.35], dtype=torch.float64)
    upper = torch.tensor([10.0, 10.0, 1.0], dtype=torch.float64)
    sol = solve(problem, torch.tensor([[1.0, 1.0, 0.5]], dtype=torch.float64), kernel=kernel, scale=0.1,
                max_iter=200, tol=1e-12, lower=lower, upper=upper)
    ref = least_squares(lambda p: p[0] * np.exp(-p[1] * t.numpy()) + p[2] - y.numpy(), [1.0, 1.0, 0.5], loss=loss,
                        f_scale=0.1, bounds=(lower.numpy(), upper.numpy()), xtol=1e-14, ftol=1e-14, gtol=1e-14)
    assert abs(ref.x[2] - 0.35) < 1e-12  # (the bound is active at the reference answer)
    assert bool(sol.converged.all())
    torch.testing.assert_close(sol.params[0], torch.from_numpy(ref.x), rtol=0, atol=1e-6)
    assert float(sol.params[0, 2]) == 0.35


# -- precision: at least float32, autocast off ---------------------------------------------------------

@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_16_bit_params_are_solved_in_float32(dtype):
    """Cholesky has no 16-bit kernel (it raised), and 16-bit normal equations would lose the fit:
    the solver works, and answers, in float32."""
    x = (torch.arange(-64, 65) / 64).to(dtype).unsqueeze(0)
    y = 2.0 * x - 1.0  # (exact in 16 bits: on a grid of 1/64)
    use = torch.ones(1, 129, dtype=torch.bool)

    def residual(p):  # (the data in 16 bits, the residuals in the parameters' dtype)
        return (p[:, :1] * x + p[:, 1:] - y).unsqueeze(1), torch.stack([x, torch.ones_like(x)], 1).unsqueeze(2).to(p.dtype), use

    sol = solve(ResidualProblem(residual, use.sum(1)), torch.zeros(1, 2, dtype=dtype), kernel="l2", max_iter=20)
    assert sol.params.dtype == sol.normal.dtype == sol.cost.dtype == torch.float32
    torch.testing.assert_close(sol.params, torch.tensor([[2.0, -1.0]]), rtol=0, atol=1e-5)
    assert bool(torch.isfinite(sol.covariance()).all())


@pytest.mark.parametrize("options", [dict(kernel="l2"), dict(kernel="cauchy", scale=0.05, anneal=True),
                                     dict(kernel="huber", resolution=0.01, predict=True),
                                     dict(kernel="cauchy", missing="mean", upper=torch.tensor([1.5, math.inf])),
                                     dict(kernel="tukey", scale=0.5, free=torch.tensor([True, False]),
                                          prior_mean=torch.tensor([1.0, 0.0]), prior_precision=torch.tensor([2.0, 0.0]))])
def test_float32_params_with_float64_residuals_are_solved_in_float64(options):
    """A problem whose residuals come wider than the parameters (float64 data, a float32 start)
    is solved, and answers, in its dtype, as a float64 start would be (this raised: the points'
    mask was made in the parameters' dtype)."""
    problem, truth, _, _ = line_problem(noise=0.01)
    with_64 = solve(problem, torch.zeros(2, 2, dtype=torch.float64), max_iter=40, **options)
    sol = solve(problem, torch.zeros(2, 2, dtype=torch.float32), max_iter=40, **options)
    assert sol.params.dtype == sol.cost.dtype == sol.normal.dtype == torch.float64
    torch.testing.assert_close(sol.params, with_64.params, rtol=0, atol=1e-6)
    assert torch.equal(sol.converged, with_64.converged)


def test_autocast_does_not_reach_the_normal_equations():
    """Under CPU autocast (bfloat16) the problem's matmuls built the normal equations in bfloat16
    (a normal matrix off by 1e-3 relative, a covariance of inf): autocast is off inside, and the
    answer is the one without it, bit for bit."""
    problem, truth, _, _ = line_problem(B=1, N=2000, noise=0.01, seed=4)

    def fn32(p):  # (the problem in float32)
        r, J, use = problem.fn(p.double())
        return r.float(), J.float(), use

    problem32 = ResidualProblem(fn32, problem.count)
    ref = solve(problem32, torch.zeros(1, 2), kernel="cauchy", max_iter=30, scale=0.05)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        sol = solve(problem32, torch.zeros(1, 2), kernel="cauchy", max_iter=30, scale=0.05)
    assert sol.normal.dtype == torch.float32
    assert torch.equal(sol.params, ref.params) and torch.equal(sol.normal, ref.normal)
    torch.testing.assert_close(sol.covariance(), ref.covariance(), rtol=0, atol=0)


# -- the arguments ----------------------------------------------------------------------------------

NAN, INF = float("nan"), float("inf")


@pytest.mark.parametrize("options, error, message", [
    (dict(free=torch.tensor([1.0, 0.0])), TypeError, r"free: expected a bool tensor of shape \(2,\) or \(2, 2\), got dtype torch.float32"),
    (dict(free=[True, False]), TypeError, "free: expected a bool tensor .* got list"),
    (dict(free=torch.tensor([True, False, True])), ValueError, r"free: expected shape \(2,\) or \(2, 2\) \(B, P of params\), got \(3,\)"),
    (dict(upper=torch.tensor([1.0, 2.0, 3.0])), ValueError, r"upper: expected a number or shape \(2,\) or \(2, 2\) .* got \(3,\)"),
    (dict(lower=torch.tensor([True, False])), TypeError, "lower: expected a number or a real tensor .* got dtype torch.bool"),
    (dict(prior_mean=torch.zeros(3), prior_precision=torch.ones(2)), ValueError, r"prior_mean: expected .* got \(3,\)"),
    (dict(prior_precision=torch.ones(2, 3)), ValueError, r"prior_precision: expected .* got \(2, 3\)"),
    (dict(prior_precision="1"), TypeError, "prior_precision: expected a number or a tensor"),
    # a mean without a precision was dropped unsaid: no prior, the fit as without it
    (dict(prior_mean=torch.tensor([5.0, 5.0])), ValueError,
     r"^prior_mean: given without prior_precision, it would weigh nothing: give the prior's precision too"),
    (dict(damping=-1.0), ValueError, r"damping: expected a positive number \(> 0\), got -1.0"),
    (dict(max_iter=-1), ValueError, "max_iter: expected an int >= 0, got -1"),
    (dict(max_iter=2.0), TypeError, "max_iter: expected an int, got float 2.0"),
    (dict(tol=NAN), ValueError, "tol: expected a finite number, got nan"),
    (dict(resolution=-0.1), ValueError, "resolution: expected a number >= 0, got -0.1"),
    (dict(kernel="gauss"), ValueError, "kernel: expected one of"),
    # values: told by the loop's first host read
    (dict(lower=torch.tensor([5.0, 5.0]), upper=torch.tensor([-5.0, -5.0])), ValueError,
     r"lower, upper: expected lower <= upper, got lower \[5.0, 5.0, 5.0\] above upper \[-5.0, -5.0, -5.0\]"),
    (dict(lower=torch.tensor([NAN, -9.0])), ValueError, r"lower: expected values below \+inf \(not NaN\), got \[nan, nan\]"),
    (dict(upper=torch.tensor([-INF, 9.0])), ValueError, r"upper: expected values above -inf \(not NaN\), got \[-inf, -inf\]"),
    (dict(prior_precision=torch.tensor([-1e6, 0.0])), ValueError, r"prior_precision: expected finite values >= 0, got \[-1000000.0"),
    (dict(lower=torch.tensor([INF, 0.0])), ValueError, r"lower: expected values below \+inf \(not NaN\), got \[inf, inf\]"),
    (dict(upper=torch.tensor([0.0, NAN])), ValueError, r"upper: expected values above -inf \(not NaN\), got \[nan, nan\]"),
    (dict(lower=-INF, upper=-INF), ValueError, r"upper: expected values above -inf \(not NaN\), got \[-inf, -inf, -inf\]"),
    # the first bad argument is named
    (dict(params=torch.tensor([[0.0, NAN], [0.0, 0.0]], dtype=torch.float64), lower=5.0, upper=-5.0,
          prior_mean=torch.tensor([NAN, 0.0]), prior_precision=torch.ones(2)), ValueError,
     r"params: expected finite start values, got \[nan\]"),
    (dict(prior_precision=torch.tensor([NAN, 1.0]), lower=5.0, upper=-5.0), ValueError,
     r"prior_precision: expected finite values >= 0, got \[nan, nan\]"),
    (dict(prior_mean=torch.tensor([NAN, 0.0]), prior_precision=torch.ones(2)), ValueError,
     r"prior_mean: expected finite values, got \[nan, nan\]"),
    (dict(params=torch.tensor([[NAN, 0.0], [0.0, 0.0]], dtype=torch.float64)), ValueError,
     r"params: expected finite start values, got \[nan\]"),
    (dict(params=torch.tensor([[0.0, 0.0], [INF, 0.0]], dtype=torch.float64), max_iter=1), ValueError,
     r"params: expected finite start values, got \[inf\]"),  # (no check in the loop: one after it)
    (dict(params=torch.zeros(0, 2, dtype=torch.float64)), ValueError, r"params: expected shape \(B, P\) with B >= 1, got \(0, 2\)"),
    (dict(params=torch.zeros(2, 0, dtype=torch.float64)), ValueError, r"params: expected shape \(B, P\) with P >= 1, got \(2, 0\)"),
])
def test_solve_names_a_bad_argument(options, error, message):
    problem, _, _, _ = line_problem(B=2, N=50)
    options = {"kernel": "l2", "max_iter": 30, **options}
    with pytest.raises(error, match=message):
        solve(problem, options.pop("params", torch.zeros(2, 2, dtype=torch.float64)), **options)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_bounds_at_the_largest_finite_numbers_are_valid(dtype):
    """lower < +inf, upper > -inf and lower <= upper hold for bounds at the dtype's largest finite
    numbers (decided in one comparison of the bounds clamped to them): no error."""
    problem, _, _, _ = line_problem(B=2, N=50)
    big = torch.finfo(dtype).max
    for lower, upper in (([big, -INF], [INF, -big]), ([-big, -big], [big, big]), ([big, 0.0], [big, 0.0])):
        sol = solve(problem, torch.zeros(2, 2, dtype=dtype), kernel="l2", max_iter=3,
                    lower=torch.tensor(lower, dtype=dtype), upper=torch.tensor(upper, dtype=dtype))
        assert sol.params.shape == (2, 2)


def test_without_checks_the_values_are_the_callers():
    """``check_every=None`` reads nothing, also not to check values (a GPU loop without a
    synchronisation): a NaN start gives a NaN answer, as it is documented to."""
    problem, _, _, _ = line_problem(B=2, N=50)
    start = torch.tensor([[NAN, 0.0], [0.0, 0.0]], dtype=torch.float64)
    sol = solve(problem, start, kernel="l2", max_iter=5, check_every=None)
    assert bool(sol.params[0].isnan().any()) and bool(torch.isfinite(sol.params[1]).all())


def test_no_points_and_annealing():
    """A problem without points (N = 0): every point missing, whatever the kernel's annealing (the
    median of no residuals raised)."""
    def empty(p):
        return torch.zeros(2, 1, 0, dtype=torch.float64), torch.zeros(2, 2, 1, 0, dtype=torch.float64), \
            torch.zeros(2, 0, dtype=torch.bool)

    problem = ResidualProblem(empty, torch.full((2,), 10))
    for anneal in (False, True):
        sol = solve(problem, torch.zeros(2, 2, dtype=torch.float64), kernel="cauchy", anneal=anneal)
        assert torch.equal(sol.params, torch.zeros(2, 2, dtype=torch.float64))
        torch.testing.assert_close(sol.cost, torch.full((2,), far_outlier_cost("cauchy"), dtype=torch.float64))


# -- missing="mean" where no point counts ------------------------------------------------------------

def test_mean_cost_where_no_point_counts_is_the_far_outliers():
    """``missing="mean"``: the mean cost of no points was 0, so a step that moved every point out
    of the model's domain was taken as the best fit. Where none counts, they all cost what far
    outliers would (as with ``missing="outlier"``), and the fit stays where its points are."""
    t = torch.linspace(0, 1, 40, dtype=torch.float64).expand(1, 40)

    def residual(p):  # p - 5 at every point; the model is defined only while p < 3
        return (p[:, :1] - 5.0 + 0.1 * t).unsqueeze(1), torch.ones(1, 1, 1, 40, dtype=torch.float64), \
            (p[:, :1] < 3.0).expand(1, 40)

    problem = ResidualProblem(residual, torch.tensor([40]))
    outside = solve(problem, torch.full((1, 1), 4.0, dtype=torch.float64), kernel="cauchy", scale=2.0,
                    missing="mean", max_iter=0)
    assert float(outside.cost) == pytest.approx(4.0 * far_outlier_cost("cauchy"), rel=1e-12)  # (c² ρ₁(10⁴))
    for missing in ("outlier", "mean"):
        sol = solve(problem, torch.zeros(1, 1, dtype=torch.float64), kernel="cauchy", scale=1.0, missing=missing,
                    max_iter=20)
        assert float(sol.params) < 3.0 and bool(sol.evaluation.use.all()), missing
        assert float(sol.cost) < far_outlier_cost("cauchy"), missing


def test_results_are_not_the_callers_tensors():
    """``solve(max_iter=0).params`` and ``robust_cost(kind="l2")`` returned the caller's own
    tensors: an in-place edit of the result changed the caller's start or residuals."""
    t = torch.linspace(0, 1, 10, dtype=torch.float64).expand(1, 10)
    problem = ResidualProblem(lambda p: ((p[:, :1] - t).unsqueeze(1), torch.ones(1, 1, 1, 10, dtype=torch.float64),
                                         torch.ones(1, 10, dtype=torch.bool)), torch.tensor([10]))
    start = torch.zeros(1, 1, dtype=torch.float64)
    sol = solve(problem, start, max_iter=0)
    assert torch.equal(sol.params, start) and sol.params.data_ptr() != start.data_ptr()
    r2 = torch.rand(5, dtype=torch.float64)
    cost = robust_cost(r2, 1.0, kind="l2")
    assert torch.equal(cost, r2) and cost.data_ptr() != r2.data_ptr()


def test_every_kernel_broadcasts_r2_with_the_scale():
    """``l2`` returned ``r2``'s shape whatever the scale, every other kernel their broadcast."""
    r2, scale = torch.rand(5, dtype=torch.float64), torch.full((3, 1), 1.5, dtype=torch.float64)
    for kind in ROBUST_KERNELS:
        cost, weight = robust_cost(r2, scale, kind), robust_weight(r2, scale, kind)
        assert cost.shape == weight.shape == (3, 5), kind
    torch.testing.assert_close(robust_cost(r2, scale, "l2"), r2.expand(3, 5), rtol=0, atol=0)
    assert bool((robust_weight(r2, scale, "l2") == 1).all())
    assert robust_cost(r2, 2.0, "l2").shape == robust_weight(r2, 2.0, "l2").shape == (5,)


@pytest.mark.parametrize("kind", ROBUST_KERNELS)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_robust_terms_are_the_kernels_weights_and_cost_over_the_mask(kind, dtype):
    """``robust_terms`` (the solver's kernel, both terms at once): its weights are
    ``robust_weight``'s times the mask, bit for bit; its cost the sum of ``robust_cost`` over the
    mask; at one scale (B,) or S at once (B, S), each as if alone."""
    from fsof_torch.estimation.robust import robust_terms

    g = torch.Generator().manual_seed(3)
    r2 = (torch.rand(2, 301, generator=g, dtype=torch.float64) * 9).square().to(dtype)
    mask = (torch.rand(2, 301, generator=g) > 0.3).to(dtype)
    scale = torch.tensor([0.7, 2.5], dtype=dtype)
    cost, w = robust_terms(r2, scale, kind, mask)
    assert w.dtype == cost.dtype == dtype and cost.shape == (2,) and w.shape == (2, 301)
    assert torch.equal(w, robust_weight(r2, scale.unsqueeze(-1), kind) * mask)
    torch.testing.assert_close(cost, (robust_cost(r2, scale.unsqueeze(-1), kind) * mask).sum(1))
    scales = torch.stack([scale, 2 * scale], dim=-1)  # (B, S)
    costs, ws = robust_terms(r2, scales, kind, mask)
    assert costs.shape == (2, 2) and ws.shape == (2, 2, 301) and ws.dtype == dtype
    for k in range(2):
        single_cost, single_w = robust_terms(r2, scales[:, k].contiguous(), kind, mask)
        assert torch.equal(ws[:, k], single_w)
        torch.testing.assert_close(costs[:, k], single_cost)


# -- sample_points: 16-bit images ---------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_16_bit_images_are_sampled_on_a_float32_grid(dtype):
    """The grid was built in the image's dtype (across a KITTI frame a bfloat16 position is off
    by up to 1.2 px, a float16 one by 0.15), and torch's CPU ``grid_sample`` returned 0 or garbage
    in 16 bits: a 16-bit image is sampled as its float32 copy would be."""
    from fsof_torch.estimation.sampling import points_grid, sample_points

    H, W = 375, 1242
    image = (torch.arange(W, dtype=torch.float32) / 4).expand(1, 1, H, W).to(dtype)
    xy = torch.tensor([[[1000.3, 1100.7, 300.25], [200.0, 17.5, 3.0]]], dtype=torch.float64)
    got, inb = sample_points(image, xy)
    want, _ = sample_points(image.to(torch.float32), xy)
    assert torch.equal(got, want) and inb.tolist() == [[True] * 3]
    if dtype == torch.float16:  # (the ramp x / 4 is exact in float16 up to x = 2048)
        torch.testing.assert_close(4 * got[0, 0], xy[0, 0], rtol=0, atol=1e-3)
    grid, _ = points_grid(xy, (H, W), dtype)
    assert grid.dtype == torch.float32
    torch.testing.assert_close((grid[0, 0, :, 0].double() + 1) * (W - 1) / 2, xy[0, 0], rtol=0, atol=1e-3)


def test_posterior_covariance_of_exact_data_and_the_prior_noise_checked():
    """Exact data of a line whose slope the points do not see (all within 1e-12 of x = 0): with the
    prior noise ν the slope's posterior is its prior's σ_p, as with noisy data. With exact data
    the prior's weight λ in the normal matrix, rounded, swamped the data's JᵀJ of the slope, and
    the posterior came back +inf on every parameter; it is σ_p now, the intercept known to about
    1.5e-6 ν at most (σ² is taken at least 1e4 ε ν²). ``prior_noise`` is checked: 0 or NaN gave +inf, a wrong shape or type
    torch's own errors."""
    N = 40
    x = torch.linspace(-1, 1, N, dtype=torch.float64)[None] * 1e-12
    y = 2.0 * x - 1.0  # (exact)
    J = torch.stack([x, torch.ones_like(x)], dim=1).unsqueeze(2)
    use = torch.ones(1, N, dtype=torch.bool)

    def residual(p):
        return ((p[:, :1] * x + p[:, 1:]) - y).unsqueeze(1), J, use

    nu, sigma_p = 0.3, torch.tensor([[2.0, 5.0]], dtype=torch.float64)
    sol = solve(ResidualProblem(residual, use.sum(1)), torch.tensor([[2.0, -1.0]], dtype=torch.float64), kernel="l2",
                prior_mean=torch.tensor([2.0, -1.0], dtype=torch.float64), prior_precision=nu ** 2 / sigma_p.square(),
                max_iter=5)
    cov = sol.covariance(nu)[0]
    assert float(cov[0, 0].sqrt()) == pytest.approx(2.0, rel=1e-3)
    assert 0 < float(cov[1, 1].sqrt()) <= 1.6e-6 * nu / math.sqrt(N)
    # ν as a number or a tensor of shape (), (1,) or (B,): the same; anything else is named
    for same in (torch.tensor(nu, dtype=torch.float64), torch.tensor([nu]), torch.tensor([nu], dtype=torch.float16)):
        torch.testing.assert_close(sol.covariance(same)[0], cov, rtol=1e-3, atol=0)
    for bad, error, message in ((0.0, ValueError, r"^prior_noise: expected a positive number \(> 0\), got 0.0"),
                                (float("nan"), ValueError, r"^prior_noise: expected a finite number, got nan"),
                                (-0.3, ValueError, r"^prior_noise: expected a positive number"),
                                ("0.3", TypeError, r"^prior_noise: expected a number, got str '0.3'"),
                                (torch.tensor([0.3, 0.3]), ValueError,
                                 r"^prior_noise: expected a number or a tensor of shape \(\), \(1,\) or \(1,\), got "
                                 r"shape \(2,\)"),
                                (torch.tensor([True]), TypeError, r"^prior_noise: expected a number or a real tensor")):
        with pytest.raises(error, match=message):
            sol.covariance(bad)
