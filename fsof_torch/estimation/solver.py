"""One batched robust solver for every estimator of the library: Levenberg–Marquardt with a robust
kernel, Gaussian priors, bounds and per-sample convergence.

The problem (B independent samples, P parameters each, N residual points per sample) minimises

    E(p) = Σ_i ρ(r_i(p)²) + m · (n - n_used(p)) + Σ_k λ_k (p_k - μ_k)²

with ρ a robust kernel of scale c (:mod:`~fsof_torch.estimation.robust`), ``m`` the cost of a
point where the model is not defined (that of a far outlier, so that a fit cannot shrink the
model's domain to escape its residuals), and an optional Gaussian prior of mean μ and precision λ
(in residual² per parameter²). Each iteration builds the IRLS normal equations Jᵀ W J and Jᵀ W r
(the problem does, knowing its structure), adds the prior, scales them (Marquardt), solves the
damped system by Cholesky (no host read), clamps the candidate to the bounds and
keeps it per sample where E went down (else damps more).

The kernel's scale can be annealed from the spread of the first residuals down to c (halving each
iteration, or dropping to the current residuals' spread), so that a wrong start is not locked in
by its own weights.

The loop runs a fixed budget of ``max_iter`` iterations with the convergence of each sample kept
on the device; converged samples stop moving. After ``check_every`` iterations, then twice as many,
four times...: one host read asks whether all have converged, to stop early
(``check_every=None``: never, for a GPU loop without synchronisation).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Protocol

import torch
from torch import Tensor

from .robust import check_kernel, robust_cost, robust_weight

__all__ = ["Evaluation", "Problem", "ResidualProblem", "Solution", "solve", "spd_solve", "positive_definite"]


@dataclass
class Evaluation:
    """A problem evaluated at some parameters.

    Attributes:
        r2: (B, N) squared residual norms (finite; ignored where not ``use``).
        use: (B, N) bool, points where the model is defined and that count.
        residual: (B, R, N) the residual vectors (R components per point), or None; with them a
            step's movement is measured exactly (``resolution``), else through their norms.
        state: whatever the problem needs to build its normal equations there.
    """

    r2: Tensor
    use: Tensor
    residual: Tensor | None = None
    state: Any = None


class Problem(Protocol):
    """What :func:`solve` needs of a problem.

    ``evaluate(params (B, P)) -> Evaluation``; ``normal_equations(evaluation, weights (B, N)) ->
    (JᵀWJ (B, P, P), JᵀWr (B, P))`` with r the residual whose squared norm is ``r2`` and J its
    derivative by the parameters; ``count``: (B,) the number of points that could count.
    """

    count: Tensor

    def evaluate(self, params: Tensor) -> Evaluation: ...

    def normal_equations(self, evaluation: Evaluation, weights: Tensor) -> tuple[Tensor, Tensor]: ...


class ResidualProblem:
    """A problem given by a function ``params (B, P) -> (r (B, R, N), J (B, P, R, N), use (B, N))``:
    residual vectors of R components per point (finite everywhere; only ``use`` points count)
    and their derivatives."""

    def __init__(self, fn: Callable[[Tensor], tuple[Tensor, Tensor, Tensor]], count: Tensor) -> None:
        self.fn = fn
        self.count = count

    def evaluate(self, params: Tensor) -> Evaluation:
        r, J, use = self.fn(params)
        return Evaluation(r.square().sum(1), use, r, J)

    def normal_equations(self, evaluation: Evaluation, weights: Tensor) -> tuple[Tensor, Tensor]:
        r, J = evaluation.residual, evaluation.state
        B, P = J.shape[:2]
        Jw = (J * weights.unsqueeze(1).unsqueeze(1)).reshape(B, P, -1)
        return Jw @ J.reshape(B, P, -1).transpose(1, 2), (Jw @ r.reshape(B, -1, 1)).squeeze(-1)


@dataclass
class Solution:
    """The result of :func:`solve`.

    Attributes:
        params: (B, P) the estimate.
        cost: (B,) E / n at the estimate, with the kernel at its final scale.
        converged: (B,) bool.
        iterations: (B,) int64, iterations that moved the sample.
        evaluation: the problem's :class:`Evaluation` at the estimate.
        weights: (B, N) the final IRLS weights (0 where not used).
        normal: (B, P, P) JᵀWJ + prior at the estimate (fixed parameters: identity rows).
        scale: (B,) the kernel's final scale.
    """

    params: Tensor
    cost: Tensor
    converged: Tensor
    iterations: Tensor
    evaluation: Evaluation
    weights: Tensor
    normal: Tensor
    scale: Tensor

    def conditioning(self) -> Tensor:
        """The smallest eigenvalue of the normal matrix scaled to a unit diagonal (B,): near 0
        when two parameters are nearly collinear for the data."""
        return torch.linalg.eigvalsh(_unit_diagonal(self.normal))[..., 0]

    def well_conditioned(self, margin: float = 1e-9) -> Tensor:
        """(B,) bool: :meth:`conditioning` exceeds ``margin`` (decided without a host read)."""
        return positive_definite(_unit_diagonal(self.normal), margin)

    def covariance(self) -> Tensor:
        """(B, P, P) parameter covariance: the inverse normal matrix times the weighted residual
        variance per degree of freedom (0 rows and columns for fixed parameters)."""
        w, ev = self.weights, self.evaluation
        R = 1 if ev.residual is None else ev.residual.shape[1]
        # weights as fractional counts: a down-weighted outlier counts for its weight
        dof = (R * w.sum(1) - self.params.shape[1]).clamp_min(1.0)
        sigma2 = (w * ev.r2).sum(1) / dof
        eye = torch.eye(self.normal.shape[-1], dtype=self.normal.dtype, device=self.normal.device)
        return spd_solve(self.normal, eye.expand_as(self.normal)) * sigma2.reshape(-1, 1, 1)


# Small symmetric positive definite systems by Cholesky and two triangular solves: on the CPU,
# torch's LU, Cholesky-solve, inverse and eigenvalue routines read a value back to the host inside
# (a workspace or error query), which the triangular solves and cholesky_ex do not.

def spd_solve(A: Tensor, b: Tensor) -> Tensor:
    """x with A x = b for symmetric positive definite A (B, P, P) and b (B, P, K); NaN or inf
    where A is not positive definite."""
    L, _ = torch.linalg.cholesky_ex(A)
    return torch.linalg.solve_triangular(L.mT, torch.linalg.solve_triangular(L, b, upper=False), upper=True)


def positive_definite(A: Tensor, margin: float | Tensor = 0.0) -> Tensor:
    """(B,) bool: the smallest eigenvalue of symmetric A (B, P, P) exceeds ``margin``."""
    eye = torch.eye(A.shape[-1], dtype=A.dtype, device=A.device)
    _, info = torch.linalg.cholesky_ex(A - margin * eye)
    return info == 0


def _expand(x: Tensor | float | None, B: int, P: int, like: Tensor, fill: float) -> Tensor:
    if x is None:
        return torch.full((B, P), fill, dtype=like.dtype, device=like.device)
    x = torch.as_tensor(x, dtype=like.dtype, device=like.device)
    return x.expand(B, P) if x.dim() else x.expand(B, P)


def solve(problem: Problem, params: Tensor, *, free: Tensor | None = None,
          prior_mean: Tensor | None = None, prior_precision: Tensor | Callable[[Tensor], Tensor] | None = None,
          lower: Tensor | None = None, upper: Tensor | None = None, kernel: str = "cauchy",
          scale: Tensor | float | Callable[[Evaluation], Tensor] = 1.0, anneal: bool = False, max_iter: int = 50, tol: float = 1e-6,
          resolution: float = 0.0, check_every: int | None = 2, damping: float = 1e-4,
          missing: str = "outlier") -> Solution:
    """Robust Levenberg–Marquardt for B independent samples (see the module docstring).

    Args:
        problem: a :class:`Problem`.
        params: (B, P) the start (float64 recommended; the normal equations use its dtype).
        free: (P,) or (B, P) bool, the parameters to estimate (default all); the others stay.
        prior_mean, prior_precision: (P,) or (B, P): a Gaussian prior λ (p - μ)² per parameter
            (precision 0: none); the precision may be a function of the scale (B,) returning it
            (a prior whose weight follows the residuals' noise).
        lower, upper: (P,) or (B, P) bounds (±inf: none); the start is clamped into them.
        kernel: a name of :data:`~fsof_torch.estimation.robust.ROBUST_KERNELS`.
        scale: the kernel's scale c (float or (B,)), in the residual's unit, or a function of the
            start's :class:`Evaluation` returning it (B,) (a scale from the residuals, without
            evaluating the start twice).
        anneal: start the scale at max(c, 3 · median residual norm), then halve it every iteration
            or drop it to 3 × the current median, whichever is smaller, down to c.
        max_iter: the iteration budget.
        tol: converged when a step changes no parameter by more than tol (1 + |p|), or E by less
            than tol E.
        resolution: also converged when a step (accepted or not) moves the residuals by at most
            this fraction of their robust RMS (below what the points can resolve); 0: off.
        check_every: stop early when all samples converged, checked (one host read each) after
            this many iterations, then after twice as many, four times...: a handful of reads for
            any budget; None: always run ``max_iter``.
        damping: the initial Levenberg–Marquardt damping.
        missing: what a point that does not count (not ``use``) costs: ``"outlier"``, as much as a
            far outlier (a flow fit must not shrink the model's domain to escape its residuals);
            ``"mean"``, the mean cost of the points that count (an image fit, whose points may
            rightly move out of the image).

    Returns:
        :class:`Solution`.
    """
    check_kernel(kernel)
    B, P = params.shape
    dt, dev = params.dtype, params.device
    eye = torch.eye(P, dtype=dt, device=dev)
    # optional parts cost nothing when absent (Python flags, not tensor tests)
    has_fixed = free is not None
    if has_fixed:
        fixed = ~free.to(dev).expand(B, P)
        fixed_rc = fixed.unsqueeze(-1) | fixed.unsqueeze(-2)
        eye_fixed = eye * fixed.unsqueeze(-1)
    has_bounds = lower is not None or upper is not None
    if has_bounds:
        lo = _expand(lower, B, P, params, -float("inf"))
        hi = _expand(upper, B, P, params, float("inf"))
        params = torch.minimum(torch.maximum(params, lo), hi)
    n = problem.count.to(dt).clamp_min(1)

    if missing not in ("outlier", "mean"):
        raise ValueError(f"missing: expected 'outlier' or 'mean', got {missing!r}")

    def cost(ev: Evaluation, p: Tensor, s: Tensor, far: Tensor) -> Tensor:
        rho = robust_cost(ev.r2, s.unsqueeze(-1), kernel).mul_(ev.use).sum(1)
        if missing == "outlier":
            total = rho + far * (n - ev.use.sum(1))
        else:
            total = rho * (n / ev.use.sum(1).clamp_min(1))
        if has_prior:
            total = total + (lam_p * (p - mu).square()).sum(1)
        return total / n

    def normal(ev: Evaluation, p: Tensor, s: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        w = robust_weight(ev.r2, s.unsqueeze(-1), kernel).mul_(ev.use)
        A, g = problem.normal_equations(ev, w)
        if has_prior:
            A = A + torch.diag_embed(lam_p)
            g = g + lam_p * (p - mu)
        if has_fixed:
            A, g = torch.where(fixed_rc, eye_fixed, A), torch.where(fixed, 0.0, g)
        return A, g, w

    def far_cost(s: Tensor) -> Tensor:
        """The cost of a point where the model is undefined: that of a far outlier."""
        return robust_cost(1e4 * s * s, s, kernel)

    def kernel_spread(ev: Evaluation) -> Tensor:
        """3 × the median residual norm (B,): the scale that keeps most points in the kernel."""
        med = torch.nanmedian(torch.where(ev.use, ev.r2, float("nan")), dim=1).values
        return 3.0 * torch.nan_to_num(med, nan=0.0).sqrt()

    ev = problem.evaluate(params)
    if callable(scale):
        scale = scale(ev)
    s_min = torch.as_tensor(scale, dtype=dt, device=dev).expand(B).clone()
    has_prior = prior_precision is not None
    if has_prior:
        mu = _expand(prior_mean, B, P, params, 0.0)
        lam_p = _expand(prior_precision(s_min) if callable(prior_precision) else prior_precision, B, P, params, 0.0)
    s = torch.maximum(s_min, kernel_spread(ev)) if anneal else s_min
    far = far_cost(s)
    c = cost(ev, params, s, far)
    A, g, w = normal(ev, params, s)
    lam = torch.full((B,), damping, dtype=dt, device=dev)
    done = torch.zeros(B, dtype=torch.bool, device=dev)
    iters = torch.zeros(B, dtype=torch.long, device=dev)
    next_check = check_every or 0
    for it in range(max_iter):
        d = A.diagonal(dim1=-2, dim2=-1)
        # a relative floor: a direction the data do not see must not be blown up to unit size
        sc = torch.maximum(d, 1e-12 * d.amax(-1, keepdim=True)).clamp_min(1e-300).sqrt()
        An = A / (sc.unsqueeze(-1) * sc.unsqueeze(-2))
        step = spd_solve(An + lam.reshape(B, 1, 1) * eye, (g / sc).unsqueeze(-1))
        delta = step.squeeze(-1).div_(sc).neg_()
        # no step for finished samples, and none from a singular system
        delta = torch.where(done.unsqueeze(-1) | ~torch.isfinite(delta), 0.0, delta)
        cand = params + delta
        if has_bounds:
            cand = torch.minimum(torch.maximum(cand, lo), hi)
            delta = cand - params
        ev_c = problem.evaluate(cand)
        c1 = cost(ev_c, cand, s, far)
        ok = (c1 <= c) & ~done  # (False for a NaN cost)
        small = ok & (c - c1 <= tol * c)
        if resolution > 0:
            # the step moved the residuals (RMS) by at most ``resolution`` of their robust RMS
            if ev.residual is not None:
                moved = (ev_c.residual - ev.residual).square_().sum(1).mul_(ev.use).sum(1)
            else:
                moved = (ev_c.r2.sqrt() - ev.r2.sqrt()).square_().mul_(ev.use).sum(1)
            spread = (w * ev.r2).sum(1) / w.sum(1).clamp_min(1e-300)
            # (also a rejected step: below resolution the cost cannot reliably go down any more)
            small = small | (~done & (moved <= resolution ** 2 * spread * ev.use.sum(1)))
        params = torch.where(ok.unsqueeze(-1), cand, params)
        ev = _select(ok, ev_c, ev)
        iters += (~done).long()
        tiny = (delta.abs() <= tol * (1.0 + params.abs())).all(-1)
        small = small | (tiny & (ok | (lam <= 1e-2)))
        c = torch.where(ok, c1, c)
        lam = torch.where(ok, (lam / 3.0).clamp_min(1e-12), lam * 8.0)
        stuck = ~ok & (lam > 1e8)
        if anneal:
            at_scale = s <= s_min * (1 + 1e-12)
            done = done | (at_scale & (small | stuck))
            # halve, or drop to the spread of the current residuals when that is smaller
            s_next = torch.where(at_scale, s, torch.maximum(s_min, torch.minimum(0.5 * s, kernel_spread(ev))))
            changed = s_next < s
            s = s_next
            far = far_cost(s)
            c = torch.where(changed, cost(ev, params, s, far), c)
        else:
            done = done | small | stuck
        A, g, w = normal(ev, params, s)
        if check_every and it + 1 == next_check and it + 1 < max_iter:
            next_check *= 2
            if bool(done.all()):
                break
    return Solution(params, c, done, iters, ev, w, A, s)


def _unit_diagonal(A: Tensor) -> Tensor:
    d = A.diagonal(dim1=-2, dim2=-1).clamp_min(torch.finfo(A.dtype).tiny).sqrt()
    return A / (d.unsqueeze(-1) * d.unsqueeze(-2))


def _select(ok: Tensor, new: Evaluation, old: Evaluation) -> Evaluation:
    """Per sample: ``new`` where ``ok`` else ``old`` (every tensor of the state, recursively)."""
    def pick(a: Any, b: Any) -> Any:
        if isinstance(a, Tensor):
            return torch.where(ok.reshape(-1, *([1] * (a.dim() - 1))), a, b)
        if isinstance(a, (tuple, list)):
            return type(a)(pick(x, y) for x, y in zip(a, b))
        return a
    return Evaluation(pick(new.r2, old.r2), pick(new.use, old.use), pick(new.residual, old.residual),
                      pick(new.state, old.state))
